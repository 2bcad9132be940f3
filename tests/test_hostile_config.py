"""Config files with sizes that would exhaust memory or values out of physical range: one line, exit 1 (issue 17)."""
from __future__ import annotations

import pytest

from markcal.pipeline.cli import main


def _err(capsys):
    return capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("text,needle", [
    ("[step]\ndwell_s = 1e7\n", "dwell_s must be at most 600"),
    ("[sine]\nperiods = 1e9\n", "periods must be at most 1000"),
    ("[sine]\nfrequencies_hz = [1e-9]\n", "frequencies_hz must be at least 0.001"),
    ("[step]\nstrokes_mm = [1e300]\n", "strokes_mm must be at most 10000"),
    ("[sine]\nperiods = 900\nfrequencies_hz = [0.001]\n", "samples"),        # in range, but 9e9 samples
    ("[plant]\nts_s = nan\n", "must be finite"),
])
def test_servo_config_bounds(tmp_path, capsys, text, needle):
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    assert main(["servo", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and needle in err[0] and str(cfg) in err[0], err
    assert not (tmp_path / "o" / "summary.json").exists()


@pytest.mark.parametrize("text,needle", [("n = 100001\npitch_mm = 10.0\n", "n must be at most 401"),
                                         ("n = 11\npitch_mm = inf\n", "must be finite"),
                                         ("n = 11\npitch_mm = 10.0\nviews = [0, 7]\n", "views must be at most 3")])
def test_selfcal_setup_bounds(tmp_path, capsys, text, needle):
    from markcal.fixtures.selfcal_stage import SelfcalOptions, render_selfcal, save_selfcal_session
    d = tmp_path / "s"
    save_selfcal_session(d, render_selfcal(0, SelfcalOptions(n=5, k=8)))
    (d / "setup.toml").write_text(text)
    assert main(["selfcal", str(d), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and needle in err[0], err


def test_batch_nan_tolerance_refused(tmp_path, capsys):
    d = tmp_path / "in"
    d.mkdir()
    (d / "x.csv").write_text("t_s,ref_mm,pos_mm\n")
    cfg = tmp_path / "b.toml"
    cfg.write_text("[servo.tolerance]\nmax_mae_um = nan\n")
    assert main(["batch", str(d), "--out", str(tmp_path / "o"), "--config", str(cfg), "--quiet"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and "finite number" in err[0], err


def test_huge_declared_tiff_refused_before_decoding(tmp_path, capsys):
    import numpy as np
    import tifffile
    p = tmp_path / "huge.tif"
    # 16000 x 16000 float32 of zeros, deflate: a few hundred kB on disk, 1 GB decoded; the budget is lowered
    # for the test by monkeypatching the limit instead of writing a 60000² file
    tifffile.imwrite(p, np.zeros((2000, 2000), np.float32), compression="zlib")
    from markcal.stages import image_io
    old = image_io.MAX_IMAGE_PIXELS
    image_io.MAX_IMAGE_PIXELS = 1_000_000
    try:
        assert main(["indents", str(p), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    finally:
        image_io.MAX_IMAGE_PIXELS = old
    err = _err(capsys)
    assert len(err) == 1 and "2000 x 2000" in err[0] and "at most" in err[0], err


def test_batch_nan_option_refused(tmp_path, capsys):
    d = tmp_path / "in"
    d.mkdir()
    cfg = tmp_path / "b.toml"
    cfg.write_text("[path]\njump_speed_mm_s = nan\n")
    assert main(["batch", str(d), "--out", str(tmp_path / "o"), "--config", str(cfg), "--quiet"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and "finite number" in err[0] and str(cfg) in err[0], err


def test_every_flow_with_options_checks_them():
    """Each flow with options beyond no_report declares its validate_options (batch.toml is checked up front)."""
    from markcal.pipeline.registry import all_flows
    for name, f in all_flows().items():
        d = f.descriptor
        assert (d.validate_options is not None) == bool(set(d.options) - {"no_report"}), name
        d.check_options({})                                  # the defaults pass their own checks


def test_negative_seed_refused_for_every_flow_with_a_seed():
    from markcal.pipeline.registry import all_flows
    from markcal.stages.errors import MarkcalError
    seeded = [f.descriptor for f in all_flows().values() if "seed" in f.descriptor.options]
    assert {d.name for d in seeded} >= {"scan", "grid", "path", "pmcal"}
    for d in seeded:
        with pytest.raises(MarkcalError, match="seed must be a whole number"):
            d.check_options({"seed": -1})


def test_plate_spec_is_read_once(tmp_path, monkeypatch):
    """read_plate_spec opens its file once for the emptiness and truncation checks and the TOML."""
    import builtins

    from markcal.fixtures.scan_plate import plate_spec_toml
    from markcal.pipeline.config import read_plate_spec
    from markcal.stages.errors import MarkcalError
    from markcal.stages.plate import PlateSpec
    p = tmp_path / "plate.toml"
    p.write_text(plate_spec_toml(PlateSpec(rows=7, cols=7)))
    opened, real_open = [], builtins.open
    monkeypatch.setattr(builtins, "open", lambda f, *a, **k: opened.append(f) or real_open(f, *a, **k))
    assert read_plate_spec(p).rows == 7
    assert [f for f in opened if str(f) == str(p)] == [str(p)]
    p.write_text(" \n")
    with pytest.raises(MarkcalError, match="empty plate spec"):
        read_plate_spec(p)
    p.write_text(plate_spec_toml(PlateSpec(rows=7, cols=7)).rstrip("\n"))
    with pytest.raises(MarkcalError, match="no line end"):
        read_plate_spec(p)
