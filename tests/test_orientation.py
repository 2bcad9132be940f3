"""The plate's orientation at any angle: orientation mark, rotation hint, the galvo model's margin, refusals.

Truth comes from the scan renderer (its true galvo and pose); a fiducial is
indexed right when its measured scanner position is its true one.
"""
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import save_render
from markcal.fixtures.scan_plate import ScanOptions, render_scan
from markcal.pipeline.flows.scan import ScanOptions as FlowOptions
from markcal.pipeline.flows.scan import run_scan
from markcal.stages.errors import MarkcalError
from markcal.stages.plate import PlateSpec

MARKED = PlateSpec(rows=7, cols=7, orientation_mark=(0, 1))
PLAIN = PlateSpec(rows=7, cols=7)
# a wrong orientation puts marks a pitch (10.6 mm) or more from their true place; right ones are within 0.06 mm
RIGHT_MM = 0.06


def _index_error_mm(res, render):
    t = render.truth["fiducials"]
    ids = res.fiducials["id"]
    true = np.column_stack([t["x_scanner_mm"], t["y_scanner_mm"]])[ids]
    got = np.column_stack([res.fiducials["x_scanner_mm"], res.fiducials["y_scanner_mm"]])
    return np.linalg.norm(got - true, axis=1)


def _scan(tmp_path, spec, seed, rot, flip=False, **opts):
    r = render_scan(seed, spec, ScanOptions(rotation_deg=rot, mirror=flip))
    cloud, _ = save_render(r, str(tmp_path))
    return r, run_scan(cloud, spec, FlowOptions(**opts))


@pytest.mark.parametrize("seed,rot,mirror", [(31, 90.0, False), (32, 135.0, True), (33, -170.0, False)])
def test_orientation_mark_fixes_any_angle_and_mirror(tmp_path, seed, rot, mirror):
    r, res = _scan(tmp_path, MARKED, seed, rot, mirror, mirror="auto")
    err = _index_error_mm(res, r)
    assert err.max() <= RIGHT_MM
    s = res.summary
    assert s["orientation_method"].startswith("orientation mark") and s["mirrored"] == mirror
    assert s["n_expected"] == 48 and s["n_detected"] == 48 and 1 not in res.fiducials["id"]
    assert 1 not in res.targets["id"]
    if not mirror:
        assert s["in_plane_rotation_deg"] == pytest.approx(rot, abs=0.2)


def test_rotation_hint_picks_the_quarter_turn(tmp_path):
    r, res = _scan(tmp_path, PLAIN, 34, 180.0, rotation_hint_deg=160.0)
    assert _index_error_mm(res, r).max() <= RIGHT_MM
    assert res.summary["orientation_method"] == "rotation hint"
    assert abs(res.summary["in_plane_rotation_deg"]) == pytest.approx(180.0, abs=0.2)


@pytest.mark.parametrize("rot,hint", [(40.0, 0.0), (-130.0, -90.0), (175.0, -165.0)])    # the last wraps at 180
def test_hint_takes_the_plate_within_44_deg_of_it(tmp_path, rot, hint):
    r, res = _scan(tmp_path, PLAIN, 39, rot, rotation_hint_deg=hint)
    assert _index_error_mm(res, r).max() <= RIGHT_MM
    assert res.summary["in_plane_rotation_deg"] == pytest.approx(rot, abs=0.2)


def test_upright_option_is_a_hint_of_0_and_refuses_at_45_deg(tmp_path):
    r, res = _scan(tmp_path, PLAIN, 40, -30.0, orientation="upright")
    assert _index_error_mm(res, r).max() <= RIGHT_MM and res.summary["orientation_method"] == "rotation hint"
    r = render_scan(41, PLAIN, ScanOptions(rotation_deg=45.0))
    cloud, _ = save_render(r, str(tmp_path / "45"))
    with pytest.raises(MarkcalError, match=r"no orientation within 44 deg of --rotation-hint-deg 0"):
        run_scan(cloud, PLAIN, FlowOptions(orientation="upright"))


def test_near_45_deg_without_evidence_is_refused(tmp_path):
    r = render_scan(35, PLAIN, ScanOptions(rotation_deg=45.0))
    cloud, _ = save_render(r, str(tmp_path))
    with pytest.raises(MarkcalError, match="ambiguous.*--rotation-hint-deg"):
        run_scan(cloud, PLAIN)


def test_galvo_model_alone_refuses_and_reports_its_margin(tmp_path):
    # the galvo model is closed under 180 deg turns: it can never tell 0 from 180 deg by a wide margin
    r = render_scan(36, PLAIN, ScanOptions(rotation_deg=20.0))
    cloud, _ = save_render(r, str(tmp_path))
    with pytest.raises(MarkcalError, match=r"ambiguous.*margin 1\.0"):
        run_scan(cloud, PLAIN, FlowOptions(orientation="auto"))


@pytest.mark.parametrize("rot", [44.0, 3.0])
def test_cli_ambiguous_orientation_is_one_line_exit_1_nothing_written(tmp_path, rot):
    # no orientation mark and no hint: refused by default, even for a plate laid upright
    r = render_scan(37, PLAIN, ScanOptions(rotation_deg=rot))
    cloud, plate = save_render(r, str(tmp_path))
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "markcal.pipeline.cli", "scan", cloud, "--plate", plate,
                        "--out", str(out), "--quiet"], capture_output=True, text=True)
    assert p.returncode == 1
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"markcal: error: {cloud}: the plate's orientation is ambiguous")
    assert "margin 1.0" in lines[0] and "--rotation-hint-deg" in lines[0] and "orientation_mark" in lines[0]
    assert not (out / "summary.json").exists()


def test_plate_spec_orientation_mark_round_trip(tmp_path):
    from markcal.fixtures.scan_plate import plate_spec_toml
    from markcal.pipeline.config import read_plate_spec
    p = tmp_path / "plate.toml"
    p.write_text(plate_spec_toml(MARKED))
    assert read_plate_spec(p).orientation_mark == (0, 1)
    p.write_text(plate_spec_toml(MARKED).replace("[0, 1]", "[0, 9]"))
    with pytest.raises(MarkcalError, match="orientation_mark"):
        read_plate_spec(p)


def test_galvo_model_option_closes_the_loop_and_exports(tmp_path):
    """--model physical+rbf: the correction sampled on the grid corrects the true machine."""
    from markcal.fixtures.gls import correction_residual
    from markcal.fixtures.scan_plate import machine_from_truth
    from markcal.pipeline.flows.export import load_scan_source
    from markcal.pipeline.registry import run_and_write
    from markcal.stages.deviation import GridCorrection
    r = render_scan(38, PLAIN, ScanOptions(rotation_deg=8.0))
    cloud, plate = save_render(r, str(tmp_path))
    res, paths = run_and_write("scan", cloud, tmp_path / "out", spec_path=plate,
                               options={"seed": 0, "validation": False, "no_report": False, "model": "physical+rbf",
                                        "rotation_hint_deg": float("nan"), "orientation": "upright",
                                        "mirror": "no"})
    assert res.summary["model"] == "physical+rbf" and set(res.summary["cv_rmse_by_model_mm"]) >= {"rbf", "poly3"}
    grid = GridCorrection.from_nodes(res.grid_xy_mm, res.grid_dxy_mm)
    hx, hy = PLAIN.half_extent_mm
    _, resid = correction_residual(machine_from_truth(r.truth), grid.command, hx, hy, 1.0)
    mag = np.hypot(*resid.T)
    # the scan flow's loop goal (issue 2): RMS <= 0.03 mm, max <= 0.10 mm
    assert np.sqrt(np.mean(mag ** 2)) <= 0.03 and mag.max() <= 0.10
    src = load_scan_source(tmp_path / "out")          # export reads the galvo model back
    w = np.array([[10.0, -20.0]])
    assert np.allclose(src.model(w), res.grid_model.model(w), atol=1e-9)
    assert os.path.exists(paths["report.html"])


@pytest.mark.parametrize("rot,off", [(30.0, 25.0), (-120.0, -35.0)])
def test_hint_resolves_a_mirrored_plate(tmp_path, rot, off):
    # the hint is the direction of the plate's x axis in the scan frame; the renderer's mirror negates the
    # scanner x, so a plate rendered at rot has its x axis at 180 - rot
    r, res = _scan(tmp_path, PLAIN, 42, rot, True, mirror="yes", rotation_hint_deg=180.0 - rot + off)
    assert _index_error_mm(res, r).max() <= RIGHT_MM
    s = res.summary
    assert s["mirrored"] is True and s["orientation_method"] == "rotation hint"
    assert (s["in_plane_rotation_deg"] - (180.0 - rot) + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.2)


def test_hint_on_a_mirrored_plate_needs_the_mirror_stated(tmp_path):
    r = render_scan(43, PLAIN, ScanOptions(rotation_deg=30.0, mirror=True))
    cloud, _ = save_render(r, str(tmp_path))
    with pytest.raises(MarkcalError, match=r"mirrored and not.*give --mirror yes or no"):
        run_scan(cloud, PLAIN, FlowOptions(mirror="auto", rotation_hint_deg=150.0))


def test_face_down_flatbed_image_with_a_hint(tmp_path):
    from markcal.fixtures.plate_image import ImageOptions, render_plate_image, save_plate_image
    spec = PlateSpec(rows=5, cols=5)
    r = render_plate_image(44, spec, ImageOptions(dpi=600, rotation_deg=100.0, mirror=True))
    paths = save_plate_image(str(tmp_path), r)
    res = run_scan(paths["image"], spec, FlowOptions(mirror="yes", rotation_hint_deg=180.0 - 100.0 - 20.0))
    f, t = res.fiducials, r.truth["fiducials"]
    e = np.hypot(f["x_scanner_mm"] / r.pixel_mm - 0.5 - np.array(t["col_px"])[f["id"]],
                 f["y_scanner_mm"] / r.pixel_mm - 0.5 - np.array(t["row_px"])[f["id"]])
    assert res.summary["n_detected"] == 25 and res.summary["mirrored"] is True
    assert np.sqrt(np.mean(e ** 2)) <= 0.1                      # pixels: the right ids, not a mirror's
