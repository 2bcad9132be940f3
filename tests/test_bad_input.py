"""Bad input: one line on stderr naming the file and the problem, exit 1, nothing that looks complete."""
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import SMALL, save_render
from markcal.fixtures.scan_plate import ScanOptions, render_scan
from markcal.fixtures.scan_plate import plate_spec_toml
from markcal.stages.plate import PlateSpec


def _scan(cloud, plate, out):
    p = subprocess.run([sys.executable, "-m", "markcal.pipeline.cli", "scan", str(cloud), "--plate", str(plate),
                        "--out", str(out), "--quiet"], capture_output=True, text=True)
    return p


def _assert_clean_failure(p, out, path, words):
    assert p.returncode == 1
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    assert "Traceback" not in p.stderr
    assert str(path) in lines[0]
    assert any(w in lines[0].lower() for w in words), lines[0]
    assert not os.path.exists(os.path.join(out, "summary.json"))
    assert not os.path.exists(os.path.join(out, "report.html"))


@pytest.fixture
def plate(tmp_path):
    p = tmp_path / "plate.toml"
    p.write_text(plate_spec_toml(SMALL))
    return p


def test_empty_file(tmp_path, plate):
    c = tmp_path / "empty.ply"
    c.write_bytes(b"")
    _assert_clean_failure(_scan(c, plate, tmp_path / "o"), tmp_path / "o", c, ["empty"])


def test_truncated_ply(tmp_path, plate, small_render):
    from markcal.reports.files import write_ply
    c = tmp_path / "cut.ply"
    write_ply(c, small_render.xyz_mm[:1000], small_render.intensity[:1000])
    data = c.read_bytes()
    c.write_bytes(data[: len(data) - 4000])
    _assert_clean_failure(_scan(c, plate, tmp_path / "o"), tmp_path / "o", c, ["ply", "truncat", "read"])


def test_ply_without_intensity(tmp_path, plate):
    from plyfile import PlyData, PlyElement
    v = np.zeros(100, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    c = tmp_path / "noint.ply"
    PlyData([PlyElement.describe(v, "vertex")]).write(str(c))
    _assert_clean_failure(_scan(c, plate, tmp_path / "o"), tmp_path / "o", c, ["intensity"])


def test_nan_coordinates(tmp_path, plate, small_render):
    a = np.column_stack([small_render.xyz_mm[:5000], small_render.intensity[:5000]])
    a[10, 1] = np.nan
    c = tmp_path / "nan.npy"
    np.save(c, a)
    _assert_clean_failure(_scan(c, plate, tmp_path / "o"), tmp_path / "o", c, ["nan"])


def test_cloud_with_no_plane(tmp_path, plate):
    rng = np.random.default_rng(0)
    c = tmp_path / "blob.csv"
    np.savetxt(c, np.column_stack([rng.uniform(-50, 50, (20000, 3)), rng.random(20000)]), delimiter=",",
               header="x,y,z,intensity", comments="")
    _assert_clean_failure(_scan(c, plate, tmp_path / "o"), tmp_path / "o", c, ["no plane"])


def test_wrong_pitch(tmp_path, small_files):
    p = tmp_path / "wrong.toml"
    p.write_text(plate_spec_toml(PlateSpec(rows=7, cols=7, pitch_mm=12.0)))
    _assert_clean_failure(_scan(small_files[0], p, tmp_path / "o"), tmp_path / "o", small_files[0], ["pitch"])


def test_wrong_ring_radii(tmp_path, small_files):
    p = tmp_path / "wrong.toml"
    p.write_text(plate_spec_toml(PlateSpec(rows=7, cols=7, ring_radii_mm=(3.6, 3.9))))
    _assert_clean_failure(_scan(small_files[0], p, tmp_path / "o"), tmp_path / "o", small_files[0],
                          ["radi"])


def test_fewer_than_half_found(tmp_path, plate):
    r = render_scan(9, SMALL, ScanOptions(n_contaminated=30))
    cloud, _ = save_render(r, str(tmp_path / "d"))
    _assert_clean_failure(_scan(cloud, plate, tmp_path / "o"), tmp_path / "o", cloud, ["fewer than half"])


def test_bad_plate_spec(tmp_path, small_files):
    p = tmp_path / "typo.toml"
    p.write_text("[grid]\nrows = 7\ncols = 7\npich_mm = 10.5\n")
    out = tmp_path / "o"
    _assert_clean_failure(_scan(small_files[0], p, out), out, p, ["unknown key"])


def test_unknown_extension_and_missing_file(tmp_path, plate):
    c = tmp_path / "scan.las"
    c.write_bytes(b"xx")
    _assert_clean_failure(_scan(c, plate, tmp_path / "o"), tmp_path / "o", c, ["extension"])
    m = tmp_path / "nope.ply"
    _assert_clean_failure(_scan(m, plate, tmp_path / "o"), tmp_path / "o", m, ["no such file"])


def test_few_missing_fiducials_are_not_an_error(tmp_path, plate):
    r = render_scan(12, SMALL, ScanOptions(n_contaminated=3))
    cloud, _ = save_render(r, str(tmp_path / "d"))
    out = tmp_path / "o"
    p = _scan(cloud, plate, out)
    import json
    s = json.loads((out / "summary.json").read_text())
    # 4, not 1: it ran and wrote its results; a calibration plate with marks missing is out of tolerance
    assert p.returncode == 4 and s["failed_checks"] == "n_missing 3 > 0", p.stderr
    assert s["n_detected"] == 45 and s["missing_ids"] == r.truth["hidden_ids"]      # 49 - the mark - 3 hidden


def test_readers_agree(tmp_path, small_render):
    """PLY, PCD, CSV and NPY of the same cloud read to the same numbers."""
    from markcal.reports.files import write_ply
    from markcal.stages.io import read_cloud
    xyz, inten = small_render.xyz_mm[:3000], small_render.intensity[:3000]
    write_ply(tmp_path / "a.ply", xyz, inten)
    np.save(tmp_path / "a.npy", np.column_stack([xyz, inten]))
    np.savetxt(tmp_path / "a.csv", np.column_stack([xyz, inten]), delimiter=",", header="x,y,z,intensity",
               comments="", fmt="%.9g")
    with open(tmp_path / "a.pcd", "w") as fh:
        fh.write("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                 f"WIDTH {len(xyz)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\nDATA ascii\n")
        np.savetxt(fh, np.column_stack([xyz, inten]), fmt="%.9g")
    ref = read_cloud(tmp_path / "a.npy")
    for ext in ("ply", "csv", "pcd"):
        got = read_cloud(tmp_path / f"a.{ext}")
        assert np.allclose(got.xyz_mm, ref.xyz_mm, atol=1e-4), ext
        assert np.allclose(got.intensity, ref.intensity, atol=1e-6), ext
