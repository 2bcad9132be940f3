"""Hostile instrument files, plate specs and options of scan, indents and export (issue 17): one line naming
the file, exit 1, nothing written, under 5 CPU s and 1 GiB, each run in a limited child (tests/hostile_run.py)."""
from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest

import hostile_run
from hostile_run import assert_refused, listing, run

PLATE = "[grid]\nrows = 7\ncols = 7\npitch_mm = 10.0\n"


def _refused(argv, tmp_path, *needles):
    before = listing(tmp_path)
    o = run(argv, tmp_path)
    assert_refused(o, *needles)
    assert listing(tmp_path) == before
    assert not (tmp_path / "o").exists() or os.listdir(tmp_path / "o") == []
    return o


def _cloud(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.normal(0, 0.01, n)])
    return np.column_stack([xyz, rng.uniform(0, 1, n)])


# ----------------------------------------------------------------------------- scan: clouds

def test_ply_declaring_1e9_faces_with_a_list_property(tmp_path):
    p = tmp_path / "c.ply"
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nproperty float intensity\nelement face 1000000000\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    p.write_bytes(head + np.zeros(12, "<f4").tobytes() + b"\x03" + np.zeros(3, "<i4").tobytes() * 2000)
    (tmp_path / "plate.toml").write_text(PLATE)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "c.ply", "face")


def test_ply_declaring_1e12_vertices(tmp_path):
    p = tmp_path / "c.ply"
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty double x\n"
            "property double y\nproperty double z\nproperty double intensity\nend_header\n").encode()
    p.write_bytes(head + np.zeros(400, "<f8").tobytes())
    (tmp_path / "plate.toml").write_text(PLATE)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "c.ply", "vertex")


def test_pcd_declaring_huge_point_count(tmp_path):
    p = tmp_path / "c.pcd"
    p.write_bytes(b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\n"
                  b"COUNT 1 1 1 1\nWIDTH 4000000000\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4000000000\n"
                  b"DATA binary\n" + np.zeros(64, "<f4").tobytes())
    (tmp_path / "plate.toml").write_text(PLATE)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "c.pcd")


@pytest.mark.parametrize("case,needle", [
    ("z_1e300", "10 m"),
    ("n_by_5", "N x 4"),
    ("complex", "real"),
    ("string", "numbers"),
    ("object", "c.npy"),
    ("truncated", "c.npy"),
    ("empty", "empty"),
])
def test_npy_clouds(tmp_path, case, needle):
    a = _cloud()
    p = tmp_path / "c.npy"
    if case == "z_1e300":
        a[5:50, 2] = 1e300
        np.save(p, a)
    elif case == "n_by_5":
        np.save(p, np.column_stack([a, a[:, :1]]))
    elif case == "complex":
        np.save(p, a.astype(complex))
    elif case == "string":
        np.save(p, a.astype(str))
    elif case == "object":
        np.save(p, a.astype(object), allow_pickle=True)
    elif case == "truncated":
        np.save(p, a)
        p.write_bytes(p.read_bytes()[:5000])
    else:
        p.write_bytes(b"")
    (tmp_path / "plate.toml").write_text(PLATE)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "c.npy", needle)


@pytest.mark.parametrize("case,needle", [("cut", "truncated"), ("extra", "columns changed"), ("huge", "10 m")])
def test_text_clouds(tmp_path, case, needle):
    a = _cloud(200)
    text = "x,y,z,intensity\n" + "".join(f"{r[0]:.5f},{r[1]:.5f},{r[2]:.5f},{r[3]:.4f}\n" for r in a)
    lines = text.splitlines()
    if case == "cut":
        text = text[:-3]
    elif case == "extra":
        lines[3] += ",9"
        text = "\n".join(lines) + "\n"
    else:
        lines[2] = "1e300,0,0,1"
        text = "\n".join(lines) + "\n"
    p = tmp_path / "c.csv"
    p.write_text(text)
    (tmp_path / "plate.toml").write_text(PLATE)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "c.csv", needle)


# ----------------------------------------------------------------------------- scan: plate specs

@pytest.mark.parametrize("text,needle", [
    ("", "empty"),
    ("[grid]\nrows = 7\ncols = 7\npitch_mm = 1", "truncated"),
    ("[grid]\nrows = 7\ncols = 7\n", "pitch_mm"),
    ('[grid]\nrows = "5"\ncols = 7\npitch_mm = 10.0\n', "rows must be an integer"),
    ("[grid]\nrows = 5.5\ncols = 7\npitch_mm = 10.0\n", "rows must be an integer"),
    ("[grid]\nrows = 7\ncols = 7\npitch_mm = nan\n", "finite"),
    ("[grid]\nrows = 7\ncols = 7\npitch_mm = inf\n", "finite"),
    ("[grid]\nrows = 7\ncols = 7\npitch_mm = 10.0\n[correction]\ngrid_step_mm = 1e-6\n", "grid_step_mm"),
    ("[grid]\nrows = 100000\ncols = 100000\npitch_mm = 10.0\n", "rows"),
    ("[grid]\nrows = 7\ncols = 7\npitch_mm = 1e300\n", "pitch_mm"),
])
def test_plate_specs(tmp_path, text, needle):
    p = tmp_path / "c.npy"
    np.save(p, _cloud())
    (tmp_path / "plate.toml").write_text(text)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "plate.toml", needle)


def test_argparse_range_error_is_one_line(tmp_path):
    p = tmp_path / "c.npy"
    np.save(p, _cloud())
    (tmp_path / "plate.toml").write_text(PLATE)
    o = run(["indents", str(p), "--pixel-size-um", "0", "--out", str(tmp_path / "o")], tmp_path)
    assert_refused(o, "--pixel-size-um")
    o = run(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"),
             "--pixel-size-mm", "abc"], tmp_path)
    assert o.code in (1, 2) and len(o.err) == 1 and "--pixel-size-mm" in o.err[0], o.err


# ----------------------------------------------------------------------------- indents: images

def _tiff(tmp_path):
    import tifffile
    p = tmp_path / "im.tif"
    rng = np.random.default_rng(3)
    tifffile.imwrite(p, rng.normal(0, 1, (64, 64)).astype(np.float32))
    return p


@pytest.mark.parametrize("kind", ["tif", "gwy", "ibw", "gsf"])
@pytest.mark.parametrize("size", [0, 4, 8, 100])
def test_truncated_images(tmp_path, kind, size):
    from markcal.stages.image_io import gsf_bytes
    if kind == "tif":
        full = _tiff(tmp_path).read_bytes()
    elif kind == "gsf":
        full = gsf_bytes(np.zeros((32, 32)), 1e-5, 1e-5)
    elif kind == "gwy":
        full = b"GWYPGwyContainer\x00" + b"\x00" * 200
    else:
        full = b"\x05\x00" + b"\x00" * 400
    p = tmp_path / f"im.{kind}"
    p.write_bytes(full[:size])
    _refused(["indents", str(p), "--pixel-size-um", "0.1", "--out", str(tmp_path / "o"), "--quiet"], tmp_path,
             f"im.{kind}")


@pytest.mark.parametrize("dims", [(0, 0), (0, 32), (-5, 32), (2 ** 31, 2 ** 31)])
def test_gsf_hostile_dimensions(tmp_path, dims):
    from markcal.stages.image_io import gsf_bytes
    raw = gsf_bytes(np.zeros((32, 32)), 1e-5, 1e-5)
    raw = raw.replace(b"XRes = 32", f"XRes = {dims[0]}".encode()).replace(b"YRes = 32", f"YRes = {dims[1]}".encode())
    p = tmp_path / "im.gsf"
    p.write_bytes(raw)
    _refused(["indents", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, "im.gsf")


def test_tiff_decompression_bomb(tmp_path):
    import tifffile
    p = tmp_path / "bomb.tif"
    tifffile.imwrite(p, np.zeros((16000, 16000), np.uint8), compression="zlib", tile=(1024, 1024))
    assert p.stat().st_size < 2_000_000
    _refused(["indents", str(p), "--pixel-size-um", "0.1", "--out", str(tmp_path / "o"), "--quiet"], tmp_path,
             "bomb.tif")


# ----------------------------------------------------------------------------- export

@pytest.fixture(scope="module")
def grid_result(tmp_path_factory):
    return pathlib.Path(hostile_run.grid_result(tmp_path_factory.mktemp("gr"), seed=3))


def test_export_out_is_a_folder(grid_result, tmp_path):
    (tmp_path / "o").mkdir()
    o = run(["export", "cor", str(grid_result), "--lens-mm", "110", "--out", str(tmp_path / "o"), "--quiet"], tmp_path)
    assert_refused(o, str(tmp_path / "o"), "folder")
    assert os.listdir(tmp_path / "o") == []


@pytest.mark.parametrize("spacing", ["nan", "0", "-1", "inf", "1e300"])
def test_export_node_spacing(grid_result, tmp_path, spacing):
    o = run(["export", "cor", str(grid_result), "--lens-mm", "110", "--node-spacing", spacing,
             "--out", str(tmp_path / "t.cor"), "--quiet"], tmp_path)
    assert_refused(o, "--node-spacing")
    assert not (tmp_path / "t.cor").exists()


@pytest.mark.parametrize("lens", ["nan", "0", "inf", "1e300"])
def test_export_lens(grid_result, tmp_path, lens):
    o = run(["export", "cor", str(grid_result), "--lens-mm", lens, "--out", str(tmp_path / "t.cor"), "--quiet"],
            tmp_path)
    assert_refused(o, "--lens-mm")
    assert not (tmp_path / "t.cor").exists()


def test_export_from_a_model_with_nan(grid_result, tmp_path):
    import json
    import shutil
    src = tmp_path / "cal"
    shutil.copytree(grid_result, src)
    text = (src / "model.json").read_text()
    doc = json.loads(text)

    def poison(d):
        if isinstance(d, dict):
            for k, v in d.items():
                if isinstance(v, float):
                    d[k] = float("nan")
                    return True
                if poison(v):
                    return True
        if isinstance(d, list):
            for i, v in enumerate(d):
                if isinstance(v, float):
                    d[i] = float("nan")
                    return True
                if poison(v):
                    return True
        return False
    assert poison(doc["model"])
    (src / "model.json").write_text(json.dumps(doc))
    o = run(["export", "cor", str(src), "--lens-mm", "110", "--out", str(tmp_path / "t.cor"), "--quiet"], tmp_path)
    assert_refused(o, "model.json")
    assert not (tmp_path / "t.cor").exists()


@pytest.mark.parametrize("spread", ["NaN", "1e-300", "-1", "Infinity"])
def test_export_from_a_scan_model_with_a_broken_spread(tmp_path, spread):
    src = tmp_path / "cal"
    src.mkdir()
    (src / "model.json").write_text('{"model": {"centres_mm": [[0, 0], [10, 0], [0, 10]], '
                                    '"weights_mm": [[0.001, 0], [0, 0.001], [0.001, 0.001]], "bias_mm": [0, 0], '
                                    f'"spread_mm": {spread}}}}}')
    rows = [(r, c, 10.0 * c - 10, 10.0 * r - 10) for r in range(3) for c in range(3)]
    (src / "fiducials.csv").write_text("row,col,x_nom_mm,y_nom_mm,x_meas_mm,y_meas_mm\n" +
                                       "".join(f"{r},{c},{x},{y},{x},{y}\n" for r, c, x, y in rows))
    (src / "summary.json").write_text('{"kind": "calibration"}')
    o = run(["export", "cor", str(src), "--lens-mm", "70", "--out", str(tmp_path / "t.cor"), "--quiet",
             "--allow-extrapolation"], tmp_path)
    assert_refused(o, str(src))
    assert "model.json" in o.err[0] or "not finite" in o.err[0], o.err
    assert not (tmp_path / "t.cor").exists()


@pytest.mark.parametrize("data", [b"binary_compressed\n" + b"\x10\x00\x00\x00\x00\x01\x00\x00" + b"\xff" * 64,
                                  b"ascii\n1 2 x 4\n"])
def test_pcd_broken_body_is_one_plain_line(tmp_path, data):
    p = tmp_path / "c.pcd"
    p.write_bytes(b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                  b"WIDTH 1\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA " + data)
    (tmp_path / "plate.toml").write_text(PLATE)
    _refused(["scan", str(p), "--plate", str(tmp_path / "plate.toml"), "--out", str(tmp_path / "o"), "--quiet"],
             tmp_path, "c.pcd")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_inspect_a_fifo(tmp_path):
    os.mkfifo(tmp_path / "t.cor")
    _refused(["inspect", str(tmp_path / "t.cor"), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, "regular file")
