"""Hostile inputs not tried before (issue 17, round 2): each one line ``markcal: error: FILE: …``, exit 1, nothing
written, under 5 CPU s and 1 GiB, run in a forked, limited child (tests/hostile_run.py).

Groups: clouds and plate specs (scan), images and AFM files (indents), marking jobs (path), drive logs and
configs (servo), measured grids (grid), pmcal / drift / selfcal sessions, controller tables (export, inspect),
batch folders and output paths. Every case writes its files into ``tmp_path`` and builds the command line."""
from __future__ import annotations

import json
import os
import pathlib
import struct

import numpy as np
import pytest

import hostile_run
from hostile_run import assert_refused, listing, run, scan_outputs

PLATE = "[grid]\nrows = 7\ncols = 7\npitch_mm = 10.0\n"
ARRAY = "[array]\nrows = 3\ncols = 3\npitch_um = 20.0\nnominal_diameter_um = 5.0\n"


def _refused(argv, tmp_path, *needles):
    """Run; assert one error line holding every needle, exit 1, limits kept, and nothing written or changed."""
    before = listing(tmp_path)
    o = run(argv, tmp_path)
    assert_refused(o, *needles)
    assert listing(tmp_path) == before, sorted(set(listing(tmp_path)) ^ set(before))
    return o


def _w(tmp_path, name, data) -> str:
    p = os.path.join(os.fspath(tmp_path), name)
    os.makedirs(os.path.dirname(p), exist_ok=True)
    with open(p, "wb") as fh:
        fh.write(data.encode("utf-8") if isinstance(data, str) else data)
    return p


def _out(tmp_path):
    return os.path.join(os.fspath(tmp_path), "o")


# ============================================================================ scan: clouds and plate specs

def _ply_ascii_head(n, props=("x", "y", "z", "intensity")):
    return ("ply\nformat ascii 1.0\nelement vertex %d\n" % n + "".join(f"property float {p}\n" for p in props)
            + "end_header\n")


def _pts(n=300, seed=1):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), rng.normal(0, 0.01, n),
                            rng.uniform(0, 1, n)])


SCAN_CLOUDS = {
    "ply_zero_vertices": ("c.ply", _ply_ascii_head(0)),
    "ply_big_endian_short": ("c.ply", ("ply\nformat binary_big_endian 1.0\nelement vertex 5000\nproperty float x\n"
                                       "property float y\nproperty float z\nproperty float intensity\nend_header\n")
                             .encode() + np.zeros(400, ">f4").tobytes()),
    "ply_no_end_header": ("c.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"),
    "ply_unknown_format": ("c.ply", "ply\nformat binary_middle_endian 1.0\nelement vertex 1\nproperty float x\n"
                                    "property float y\nproperty float z\nend_header\n" + "\0" * 12),
    "ply_negative_count": ("c.ply", _ply_ascii_head(-5)),
    "ply_no_z": ("c.ply", _ply_ascii_head(300, ("x", "y")) + "".join(f"{a:.3f} {b:.3f}\n" for a, b, *_ in _pts())),
    "ply_vertex_count_not_a_number": ("c.ply", _ply_ascii_head(3).replace("vertex 3", "vertex 3e9")),
    "ply_double_property_uint64_huge": ("c.ply", "ply\nformat binary_little_endian 1.0\nelement vertex "
                                                 "18446744073709551615\nproperty double x\nproperty double y\n"
                                                 "property double z\nend_header\n" + "\0" * 48),
    "ply_text_rows_short": ("c.ply", _ply_ascii_head(300) + "".join("1 2\n" for _ in range(300))),
    "pcd_width_height_mismatch": ("c.pcd", "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
                                           "TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 10\nHEIGHT 10\nVIEWPOINT 0 0 0 1 0 0 0\n"
                                           "POINTS 7\nDATA ascii\n" + "1 2 3 4\n" * 7),
    "pcd_compressed_bogus": ("c.pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                                      b"WIDTH 1000\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1000\n"
                                      b"DATA binary_compressed\n" + struct.pack("<II", 10, 2 ** 31) + b"\0" * 10),
    "pcd_all_nan": ("c.pcd", "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\n"
                             "COUNT 1 1 1 1\nWIDTH 300\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 300\nDATA ascii\n"
                    + "nan nan nan nan\n" * 300),
    "csv_header_only": ("c.csv", "x,y,z,intensity\n"),
    "csv_duplicate_columns": ("c.csv", "x,x,z,intensity\n" + "".join(f"{a:.3f},{b:.3f},{c:.4f},{d:.2f}\n"
                                                                      for a, b, c, d in _pts())),
    "xyz_only_one_row": ("c.xyz", "1 2 3 4\n"),
    "npy_zero_rows": ("c.npy", None),
    "npy_three_dims": ("c.npy", None),
    "npy_bool": ("c.npy", None),
    "npy_object_pickle": ("c.npy", None),
    "unknown_extension": ("c.stl", "solid x\nendsolid x\n"),
}


def _npy(case) -> bytes:
    import io
    buf = io.BytesIO()
    if case == "npy_zero_rows":
        np.save(buf, np.zeros((0, 4)))
    elif case == "npy_three_dims":
        np.save(buf, np.zeros((100, 4, 2)))
    elif case == "npy_bool":
        np.save(buf, np.ones((500, 4), bool))
    else:
        np.save(buf, np.array([{"a": 1}] * 4, dtype=object), allow_pickle=True)
    return buf.getvalue()


@pytest.mark.parametrize("case", sorted(SCAN_CLOUDS))
def test_scan_cloud(tmp_path, case):
    name, data = SCAN_CLOUDS[case]
    p = _w(tmp_path, name, _npy(case) if data is None else data)
    spec = _w(tmp_path, "plate.toml", PLATE)
    _refused(["scan", p, "--plate", spec, "--out", _out(tmp_path), "--quiet"], tmp_path, name)


PLATES = {
    "rows_1_cols_1": "[grid]\nrows = 1\ncols = 1\npitch_mm = 10.0\n",
    "rows_cols_huge_field": "[grid]\nrows = 1000\ncols = 1000\npitch_mm = 1000.0\n",
    "pitch_smaller_than_ring": "[grid]\nrows = 7\ncols = 7\npitch_mm = 0.5\n",
    "bom": "\ufeff" + PLATE,
    "duplicate_key": PLATE + "rows = 9\n",
    "mark_negative": PLATE + "[fiducial]\norientation_mark = [-1, 0]\n",
    "mark_three_numbers": PLATE + "[fiducial]\norientation_mark = [0, 1, 2]\n",
    "ring_radii_empty": PLATE + "[fiducial]\nring_radii_mm = []\n",
    "galvo_d_string": PLATE + "[galvo]\nd_mm = \"300\"\n",
    "rows_bool": "[grid]\nrows = true\ncols = 7\npitch_mm = 10.0\n",
    "grid_is_array": "grid = [1, 2]\n",
    "utf16": None,
}


@pytest.fixture(scope="module")
def small_cloud(tmp_path_factory):
    """A rendered 5 x 5 plate's cloud (one render for every plate-spec case)."""
    from markcal.pipeline.cli import main
    d = tmp_path_factory.mktemp("plate")
    assert main(["render", "scan", "--rows", "5", "--cols", "5", "--seed", "1", "--out", str(d), "--quiet"]) == 0
    return str(d / "cloud.npy")


@pytest.mark.parametrize("case", sorted(PLATES))
def test_scan_plate_spec(tmp_path, small_cloud, case):
    text = PLATES[case]
    spec = _w(tmp_path, "bad.toml", PLATE.encode("utf-16") if text is None else text)
    _refused(["scan", small_cloud, "--plate", spec, "--out", _out(tmp_path), "--quiet"], tmp_path, "bad.toml")


def test_scan_input_is_a_directory_named_like_a_cloud(tmp_path):
    (tmp_path / "c.ply").mkdir()
    spec = _w(tmp_path, "plate.toml", PLATE)
    _refused(["scan", str(tmp_path / "c.ply"), "--plate", spec, "--out", _out(tmp_path), "--quiet"], tmp_path, "c.ply")


def test_scan_negative_pixel_size(tmp_path):
    from markcal.pipeline.cli import main
    assert main(["render", "scan-image", "--rows", "5", "--cols", "5", "--dpi", "150", "--out", str(tmp_path / "i"),
                 "--quiet"]) == 0
    _refused(["scan", str(tmp_path / "i" / "plate.tif"), "--plate", str(tmp_path / "i" / "plate.toml"),
              "--pixel-size-mm", "-0.1", "--out", _out(tmp_path), "--quiet"], tmp_path, "pixel")


# ============================================================================ indents: images and AFM files

def _tiff_header(entries, extra=b"") -> bytes:
    """A little-endian TIFF with one IFD of (tag, type, count, value) entries at offset 8."""
    ifd = struct.pack("<H", len(entries)) + b"".join(struct.pack("<HHII", *e) for e in entries) + b"\0\0\0\0"
    return b"II*\0" + struct.pack("<I", 8) + ifd + extra


TIFFS = {
    "zero_strips": _tiff_header([(256, 4, 1, 64), (257, 4, 1, 64), (258, 3, 1, 8), (259, 3, 1, 1),
                                 (262, 3, 1, 1), (273, 4, 0, 0), (277, 3, 1, 1), (278, 4, 1, 64), (279, 4, 0, 0)]),
    "strip_offset_past_end": _tiff_header([(256, 4, 1, 64), (257, 4, 1, 64), (258, 3, 1, 8), (259, 3, 1, 1),
                                           (262, 3, 1, 1), (273, 4, 1, 0xFFFFFFF0), (277, 3, 1, 1), (278, 4, 1, 64),
                                           (279, 4, 1, 4096)]),
    "ifd_offset_past_end": b"II*\0" + struct.pack("<I", 0x7FFFFFF0) + b"\0" * 16,
    "ifd_loop": b"II*\0" + struct.pack("<I", 8) + struct.pack("<H", 0) + struct.pack("<I", 8),
    "width_zero": _tiff_header([(256, 4, 1, 0), (257, 4, 1, 64), (258, 3, 1, 8), (259, 3, 1, 1), (262, 3, 1, 1),
                                (273, 4, 1, 200), (277, 3, 1, 1), (278, 4, 1, 64), (279, 4, 1, 0)], b"\0" * 200),
    "declared_2e9_pixels": _tiff_header([(256, 4, 1, 50000), (257, 4, 1, 50000), (258, 3, 1, 32), (259, 3, 1, 1),
                                         (262, 3, 1, 1), (273, 4, 1, 200), (277, 3, 1, 1), (278, 4, 1, 50000),
                                         (279, 4, 1, 10 ** 9), (339, 3, 1, 3)], b"\0" * 200),
    "unknown_compression": _tiff_header([(256, 4, 1, 64), (257, 4, 1, 64), (258, 3, 1, 8), (259, 3, 1, 54321),
                                         (262, 3, 1, 1), (273, 4, 1, 200), (277, 3, 1, 1), (278, 4, 1, 64),
                                         (279, 4, 1, 100)], b"\0" * 300),
    "not_a_tiff": b"GIF89a" + b"\0" * 100,
}


@pytest.mark.parametrize("case", sorted(TIFFS))
def test_indents_tiff_structure(tmp_path, case):
    p = _w(tmp_path, "img.tif", TIFFS[case])
    _refused(["indents", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "img.tif")


@pytest.mark.parametrize("case", ["one_pixel", "all_nan", "constant", "complex", "huge_values", "rgb_stack_of_200"])
def test_indents_tiff_content(tmp_path, case):
    import tifffile
    p = os.path.join(tmp_path, "img.tif")
    if case == "one_pixel":
        tifffile.imwrite(p, np.zeros((1, 1), np.float32))
    elif case == "all_nan":
        tifffile.imwrite(p, np.full((64, 64), np.nan, np.float32))
    elif case == "constant":
        tifffile.imwrite(p, np.full((64, 64), 7, np.uint8))
    elif case == "complex":
        tifffile.imwrite(p, np.zeros((64, 64), np.complex64))
    elif case == "huge_values":
        tifffile.imwrite(p, np.full((64, 64), 3e38, np.float32))
    else:
        tifffile.imwrite(p, np.zeros((200, 8, 8, 3), np.uint8))
    _refused(["indents", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "img.tif")


def _ibw(npnts, dims=(0, 0, 0, 0), data=b"") -> bytes:
    """An Igor binary wave v5 header declaring ``npnts`` float32 points of ``dims``."""
    bin_header = struct.pack("<hhiiiiiii", 5, 0, 320, 0, 0, 0, 0, 0, 0) + b"\0" * 32
    wave = bytearray(320)
    struct.pack_into("<i", wave, 12, npnts)                  # npnts
    struct.pack_into("<h", wave, 16, 2)                      # type: float32
    struct.pack_into("<4i", wave, 68, *dims)                 # nDim
    return bin_header + bytes(wave) + data


@pytest.mark.parametrize("case", ["absurd_dims", "negative_dims", "npnts_beyond_file", "zero_points"])
def test_indents_ibw_header(tmp_path, case):
    data = {"absurd_dims": _ibw(2 ** 31 - 1, (2 ** 20, 2 ** 20, 2 ** 10, 0), b"\0" * 64),
            "negative_dims": _ibw(16, (-4, -4, 0, 0), b"\0" * 64),
            "npnts_beyond_file": _ibw(10 ** 8, (10 ** 4, 10 ** 4, 0, 0), b"\0" * 64),
            "zero_points": _ibw(0, (0, 0, 0, 0))}[case]
    p = _w(tmp_path, "h.ibw", data)
    _refused(["indents", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "h.ibw")


@pytest.mark.parametrize("case", ["gsf_negative_xres", "gsf_huge_dims", "gwy_garbage", "gsf_nan_real"])
def test_indents_afm_text_headers(tmp_path, case):
    if case == "gsf_negative_xres":
        data = "Gwyddion Simple Field 1.0\nXRes = -8\nYRes = 8\n".encode() + b"\0" * 4 + np.zeros(64, "<f4").tobytes()
        name = "h.gsf"
    elif case == "gsf_huge_dims":
        data = "Gwyddion Simple Field 1.0\nXRes = 100000\nYRes = 100000\n".encode() + b"\0" * 4 + b"\0" * 4096
        name = "h.gsf"
    elif case == "gsf_nan_real":
        data = ("Gwyddion Simple Field 1.0\nXRes = 8\nYRes = 8\nXReal = nan\nYReal = 1e-6\n".encode() + b"\0" * 1
                + np.zeros(64, "<f4").tobytes())
        name = "h.gsf"
    else:
        data = b"GWYP" + os.urandom(200)
        name = "h.gwy"
    p = _w(tmp_path, name, data)
    _refused(["indents", p, "--out", _out(tmp_path), "--quiet"], tmp_path, name)


@pytest.mark.parametrize("case", ["diameter_over_pitch", "rows_cols_huge", "kind_unknown", "pitch_inf"])
def test_indents_array_spec(tmp_path, case):
    import tifffile
    img = os.path.join(tmp_path, "img.tif")
    tifffile.imwrite(img, np.random.default_rng(0).random((64, 64)).astype(np.float32))
    text = {"diameter_over_pitch": ARRAY.replace("nominal_diameter_um = 5.0", "nominal_diameter_um = 50.0"),
            "rows_cols_huge": ARRAY.replace("rows = 3", "rows = 100000").replace("cols = 3", "cols = 100000"),
            "kind_unknown": ARRAY + "[indenter]\nkind = \"spoon\"\n",
            "pitch_inf": ARRAY.replace("pitch_um = 20.0", "pitch_um = inf")}[case]
    spec = _w(tmp_path, "array.toml", text)
    needle = "100000 x 100000" if case == "rows_cols_huge" else "array.toml"     # too big for the image: names it
    _refused(["indents", img, "--array", spec, "--pixel-size-um", "0.1", "--out", _out(tmp_path), "--quiet"],
             tmp_path, needle)


def test_indents_negative_pixel_size_option(tmp_path):
    import tifffile
    img = os.path.join(tmp_path, "img.tif")
    tifffile.imwrite(img, np.zeros((64, 64), np.float32))
    _refused(["indents", img, "--pixel-size-um", "-2", "--out", _out(tmp_path), "--quiet"], tmp_path, "pixel")


# ============================================================================ path: marking jobs

def _dxf(entities: str, blocks: str = "") -> str:
    head = "0\nSECTION\n2\nHEADER\n9\n$ACADVER\n1\nAC1015\n0\nENDSEC\n"
    bl = f"0\nSECTION\n2\nBLOCKS\n{blocks}0\nENDSEC\n" if blocks else ""
    return head + bl + f"0\nSECTION\n2\nENTITIES\n{entities}0\nENDSEC\n0\nEOF\n"


_CIRC_BLOCKS = ("0\nBLOCK\n8\n0\n2\nA\n70\n0\n10\n0\n20\n0\n30\n0\n0\nINSERT\n8\n0\n2\nB\n10\n1\n20\n1\n30\n0\n"
                "0\nENDBLK\n8\n0\n0\nBLOCK\n8\n0\n2\nB\n70\n0\n10\n0\n20\n0\n30\n0\n0\nINSERT\n8\n0\n2\nA\n10\n1\n20\n1\n"
                "30\n0\n0\nLINE\n8\n0\n10\n0\n20\n0\n30\n0\n11\n1\n21\n1\n31\n0\n0\nENDBLK\n8\n0\n")
_HATCH = ("0\nHATCH\n8\n0\n10\n0\n20\n0\n30\n0\n210\n0\n220\n0\n230\n1\n2\nSOLID\n70\n1\n71\n0\n91\n1\n92\n2\n72\n0\n"
          "73\n1\n93\n100000000\n" + "".join(f"10\n{k}\n20\n{k % 7}\n" for k in range(50)) + "97\n0\n75\n0\n76\n1\n98\n0\n")
_SVG = '<svg xmlns="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink" width="100mm" ' \
       'height="100mm" viewBox="0 0 100 100">{}</svg>'
_LAUGHS = ('<?xml version="1.0"?>\n<!DOCTYPE svg [\n<!ENTITY a "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa">\n'
           + "".join(f'<!ENTITY {chr(98 + k)} "{("&" + chr(97 + k) + ";") * 10}">\n' for k in range(8))
           + ']>\n' + _SVG.format('<text x="1" y="1">&i;</text><path d="M0 0 L10 10"/>'))

JOBS = {
    "dxf_no_entities": ("j.dxf", _dxf("")),
    "dxf_circular_blocks": ("j.dxf", _dxf("0\nINSERT\n8\n0\n2\nA\n10\n0\n20\n0\n30\n0\n", _CIRC_BLOCKS)),
    "dxf_huge_hatch": ("j.dxf", _dxf(_HATCH)),
    "dxf_garbage": ("j.dxf", "this is not\na dxf file at all\n" * 5),
    "dxf_line_1e300": ("j.dxf", _dxf("0\nLINE\n8\n0\n10\n0\n20\n0\n30\n0\n11\n1e300\n21\n0\n31\n0\n"
                                     "0\nLINE\n8\n0\n10\n5\n20\n5\n30\n0\n11\n6\n21\n6\n31\n0\n")),
    "svg_use_recursion": ("j.svg", _SVG.format('<g id="g"><path d="M0 0 L1 1"/><use xlink:href="#g" x="1"/></g>')),
    "svg_use_mutual": ("j.svg", _SVG.format('<g id="a"><use href="#b"/></g><g id="b"><use href="#a"/>'
                                            '<path d="M0 0 L1 1"/></g>')),
    "svg_billion_laughs": ("j.svg", _LAUGHS),
    "svg_use_bomb": ("j.svg", _SVG.format('<defs><path id="l0" d="M0 0 L1 1"/>' + "".join(
        f'<g id="l{k}">' + f'<use href="#l{k - 1}" x="1"/>' * 10 + "</g>" for k in range(1, 9))
        + '</defs><use href="#l8"/>')),
    "svg_viewbox_zero": ("j.svg", _SVG.replace('viewBox="0 0 100 100"', 'viewBox="0 0 0 0"')
                         .format('<path d="M0 0 L10 10"/>')),
    "svg_empty": ("j.svg", ""),
    "svg_coordinates_1e300": ("j.svg", _SVG.format('<path d="M0 0 L1e300 10"/><path d="M5 5 L6 6"/>')),
    "svg_no_geometry": ("j.svg", _SVG.format("<desc>nothing</desc>")),
    "hpgl_no_pd": ("j.plt", "IN;SP1;PU0,0;PU100,100;PU200,0;"),
    "hpgl_odd_params": ("j.plt", "IN;SP1;PU0,0;PD100,100,200;PU;"),
    "hpgl_huge": ("j.plt", "IN;SP1;PU0,0;PD1e300,0;PD5,5;PU;"),
    "gcode_1e9_arcs": ("j.gcode", "G21\nG90\nM3\nG1 X0 Y0\nG2 X0 Y0 I100 J0 P1000000000\nM5\n"),
    "gcode_arc_huge_radius": ("j.gcode", "G21\nG90\nM3\nG1 X0 Y0\nG2 X1 Y0 I1e12 J0\nM5\n"),
    "gcode_zero_radius_arc": ("j.gcode", "G21\nG90\nM3\nG1 X0 Y0\nG2 X5 Y5 I0 J0\nM5\n"),
    "gcode_comments_only": ("j.gcode", "; nothing\n(nothing either)\n"),
    "json_no_strokes": ("j.json", json.dumps({"strokes": []})),
    "json_strokes_dict": ("j.json", json.dumps({"strokes": {"kind": "point"}})),
    "json_point_xyz": ("j.json", json.dumps({"strokes": [{"kind": "point", "xy_mm": [1, 2, 3]}] * 5})),
    "json_kind_unknown": ("j.json", json.dumps({"strokes": [{"kind": "blob", "xy_mm": [1, 2]}] * 5})),
    "json_top_level_list": ("j.json", json.dumps([[1, 2], [3, 4]])),
    "csv_header_only": ("j.csv", "x_mm,y_mm\n"),
    "csv_duplicate_columns": ("j.csv", "x_mm,x_mm\n" + "".join(f"{k},{k}\n" for k in range(20))),
}


@pytest.mark.parametrize("case", sorted(JOBS))
def test_path_job(tmp_path, case):
    name, data = JOBS[case]
    p = _w(tmp_path, name, data)
    _refused(["path", p, "--out", _out(tmp_path), "--quiet"], tmp_path, name)


def test_path_out_under_proc(tmp_path):
    p = _w(tmp_path, "j.csv", "x_mm,y_mm\n" + "".join(f"{k},{k % 3}\n" for k in range(10)))
    _refused(["path", p, "--out", "/proc/self/markcal_out", "--quiet"], tmp_path, "/proc/self/markcal_out")


# ============================================================================ servo: drive logs and configs

def _log(rows) -> str:
    return "t_s,ref_mm,pos_mm\n" + "".join(f"{a},{b},{c}\n" for a, b, c in rows)


_STEP = [(k * 1e-3, 0.0 if k < 50 else 1.0, 0.0 if k < 52 else 1.0) for k in range(200)]
LOGS = {
    "two_rows": ("t.csv", _log(_STEP[:2])),
    "all_equal_times": ("t.csv", _log([(0.5, b, c) for _, b, c in _STEP])),
    "header_only": ("t.csv", "t_s,ref_mm,pos_mm\n"),
    "time_decreasing": ("t.csv", _log([(-a, b, c) for a, b, c in _STEP])),
    "duplicate_columns": ("t.csv", "t_s,ref_mm,ref_mm\n" + "".join(f"{a},{b},{c}\n" for a, b, c in _STEP)),
    "reference_never_moves": ("t.csv", _log([(a, 0.0, c) for a, _, c in _STEP])),
    "time_step_1e-300": ("t.csv", _log([(k * 1e-300, b, c) for k, (_, b, c) in enumerate(_STEP)])),
    "tab_and_comma_mixed": ("t.csv", "t_s\tref_mm,pos_mm\n" + "".join(f"{a}\t{b},{c}\n" for a, b, c in _STEP)),
}


@pytest.mark.parametrize("case", sorted(LOGS))
def test_servo_drive_log(tmp_path, case):
    name, data = LOGS[case]
    p = _w(tmp_path, name, data)
    _refused(["servo", "--trace", p, "--out", _out(tmp_path), "--quiet"], tmp_path, name)


SERVO_CONFIGS = {
    "ts_tiny": "[plant]\nts_s = 1e-12\n",
    "strokes_empty": "[step]\nstrokes_mm = []\n",
    "reading_unknown": "[model]\nreading = \"psychic\"\n",
    "m_negative": "[repetitive]\nm = -3\n",
    "section_is_value": "plant = 3\n",
    "frequency_list_of_strings": "[sine]\nfrequencies_hz = [\"10\"]\n",
}


@pytest.mark.parametrize("case", sorted(SERVO_CONFIGS))
def test_servo_config(tmp_path, case):
    p = _w(tmp_path, "c.toml", SERVO_CONFIGS[case])
    _refused(["servo", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "c.toml")


def test_servo_settle_band_pct_100(tmp_path):
    p = _w(tmp_path, "t.csv", _log(_STEP))
    _refused(["servo", "--trace", p, "--settle-band-pct", "100", "--out", _out(tmp_path), "--quiet"], tmp_path,
             "settle_band_pct")


# ============================================================================ grid: measured grids

_G = [(x, y, x + 0.001, y - 0.002) for x in (-20.0, 0.0, 20.0) for y in (-20.0, 0.0, 20.0)]
GRIDS = {
    "two_rows": "x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm\n0,0,0,0\n1,1,1,1\n",
    "all_same_point": "x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm\n" + "0,0,0,0\n" * 9,
    "duplicate_columns": "x_cmd_mm,x_cmd_mm,x_meas_mm,y_meas_mm\n" + "".join(f"{a},{b},{c},{d}\n" for a, b, c, d in _G),
    "header_only": "x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm\n",
    "collinear": "x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm\n" + "".join(f"{k},0,{k},0\n" for k in range(12)),
}


@pytest.mark.parametrize("case", sorted(GRIDS))
def test_grid_measured(tmp_path, case):
    p = _w(tmp_path, "m.csv", GRIDS[case])
    _refused(["grid", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "m.csv")


@pytest.mark.parametrize("opt", [["--grid-step-mm", "1e-9"], ["--folds", "1"], ["--lens-mm", "-5"],
                                 ["--units-per-mm", "0"], ["--model", "zz"]])
def test_grid_options(tmp_path, opt):
    p = _w(tmp_path, "m.csv", "x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm\n"
           + "".join(f"{x},{y},{x + 0.01 * np.sin(x + y):.5f},{y:.5f}\n" for x in range(-20, 21, 10)
                     for y in range(-20, 21, 10)))
    _refused(["grid", p, *opt, "--out", _out(tmp_path), "--quiet"], tmp_path, opt[0][2:].split("-")[0])


def test_grid_bjjcz_garbage(tmp_path):
    p = _w(tmp_path, "m.txt", "@@@ ### \x00\x01\x02\n" * 10)
    _refused(["grid", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "m.txt")


# ============================================================================ pmcal, drift, selfcal sessions

def test_pmcal_empty_session_folder(tmp_path):
    (tmp_path / "s").mkdir()
    _refused(["pmcal", str(tmp_path / "s"), "--out", _out(tmp_path), "--quiet"], tmp_path, "s")


@pytest.mark.parametrize("case", ["zero_byte", "other_version", "not_an_object", "missing_keys"])
def test_pmcal_command_model_json(tmp_path, case):
    model = {"zero_byte": "", "other_version": json.dumps({"markcal_version": "99.0", "format": "pm-model-v9"}),
             "not_an_object": "[1, 2, 3]", "missing_keys": json.dumps({"theta": [0.0] * 3})}[case]
    m = _w(tmp_path, "model.json", model)
    t = _w(tmp_path, "targets.csv", "x_mm,y_mm\n0,0\n1,1\n")
    _refused(["pmcal", "command", m, t, "--depth-um", "1", "--out", os.path.join(tmp_path, "cmd.csv"), "--quiet"],
             tmp_path, "model.json")


@pytest.mark.parametrize("case", ["two_rows", "all_equal_times", "header_only"])
def test_drift_short_or_flat(tmp_path, case):
    head = "t_min,dx_um,dy_um,dz_um\n"
    body = {"two_rows": "0,0,0,0\n1,1,1,1\n", "all_equal_times": "5,0,0,0\n" * 20, "header_only": ""}[case]
    p = _w(tmp_path, "d.csv", head + body)
    _refused(["drift", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "d.csv")


@pytest.mark.parametrize("case", ["empty_folder", "setup_only", "views_empty", "grid_views_header_only"])
def test_selfcal_session(tmp_path, case):
    s = tmp_path / "s"
    s.mkdir()
    if case != "empty_folder":
        (s / "setup.toml").write_text("n = 5\npitch_mm = 10.0\n" + ("views = []\n" if case == "views_empty" else ""))
    if case in ("views_empty", "grid_views_header_only"):
        (s / "grid_views.csv").write_text("view,i,j,x_um,y_um\n")
    _refused(["selfcal", str(s), "--out", _out(tmp_path), "--quiet"], tmp_path, "s")


# ============================================================================ export and inspect

@pytest.fixture(scope="module")
def grid_result(tmp_path_factory):
    return pathlib.Path(hostile_run.grid_result(tmp_path_factory.mktemp("gridres"), seed=2))


@pytest.mark.parametrize("case", ["model_zero_byte", "model_other_version", "summary_other_version",
                                  "summary_zero_byte"])
def test_export_from_a_damaged_result(tmp_path, grid_result, case):
    import shutil
    cal = tmp_path / "cal"
    shutil.copytree(grid_result, cal)
    if case == "model_zero_byte":
        (cal / "model.json").write_text("")
        needle = "model.json"
    elif case == "model_other_version":
        m = json.loads((cal / "model.json").read_text())
        m["model"]["format"] = "markcal-grid-model-9"
        (cal / "model.json").write_text(json.dumps(m))
        needle = "model.json"
    elif case == "summary_zero_byte":
        (cal / "summary.json").write_text("")
        needle = "summary.json"
    else:
        s = json.loads((cal / "summary.json").read_text())
        s["markcal_version"] = "99.0"
        s["kind"] = "something-else"
        (cal / "summary.json").write_text(json.dumps(s))
        needle = "cal"
    _refused(["export", "cor", str(cal), "--lens-mm", "110", "--out", str(tmp_path / "t.cor"), "--quiet"], tmp_path,
             needle)


@pytest.mark.parametrize("case", ["wrong_size", "zero_byte", "directory_named_cor", "header_only", "ctb_garbage"])
def test_inspect_damaged_tables(tmp_path, case):
    name = "t.ctb" if case == "ctb_garbage" else "t.cor"
    if case == "directory_named_cor":
        (tmp_path / name).mkdir()
    else:
        data = {"wrong_size": b"\0" * 36 + b"\1" * 1001, "zero_byte": b"", "header_only": b"\0" * 36,
                "ctb_garbage": os.urandom(999)}[case]
        _w(tmp_path, name, data)
    _refused(["inspect", str(tmp_path / name), "--out", _out(tmp_path), "--quiet"], tmp_path, name)


def test_export_out_under_proc(tmp_path, grid_result):
    _refused(["export", "cor", str(grid_result), "--lens-mm", "110", "--out", "/proc/self/t.cor", "--quiet"],
             tmp_path, "/proc/self/t.cor")


# ============================================================================ batch folders, names, output paths

def test_batch_empty_folder(tmp_path):
    (tmp_path / "in").mkdir()
    _refused(["batch", str(tmp_path / "in"), "--out", _out(tmp_path), "--quiet"], tmp_path, "in")


def test_batch_symlink_loop(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    os.symlink(d, d / "loop")
    os.symlink(d / "x", d / "x")                         # a link to itself
    _refused(["batch", str(d), "--out", _out(tmp_path), "--quiet"], tmp_path, "in")


def test_batch_input_is_a_file(tmp_path):
    p = _w(tmp_path, "in", "x")
    _refused(["batch", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "in")


def test_batch_out_under_proc(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    _w(tmp_path, "in/t.csv", _log(_STEP))
    _refused(["batch", str(d), "--out", "/proc/self/markcal_batch", "--quiet"], tmp_path, "/proc/self/markcal_batch")


@pytest.mark.parametrize("name", ["bad\nname.csv", "\u202etxt.csv", "  .csv", "tr\u00e8s d\u00e9j\u00e0 vu.csv"])
def test_bad_log_with_hostile_file_name(tmp_path, name):
    p = _w(tmp_path, name, "t_s,ref_mm,pos_mm\n0,0,0\n")
    o = _refused(["servo", "--trace", p, "--out", _out(tmp_path), "--quiet"], tmp_path, "rows")
    assert "\u202e" not in o.err[0]                       # an RTL override would turn the line around on a terminal


# ============================================================================ batch.toml: every flow's section checked before any work

BATCH_OPTIONS = {
    "scan": ("pixel_size_mm = -1.0", "pixel_size_mm"),
    "grid": ("folds = 1", "folds"),
    "indents": ("kind = \"spoon\"", "kind"),
    "path": ("population = 0", "population"),
    "pmcal": ("method = \"magic\"", "magic"),
    "servo": ("settle_band_pct = 150.0", "settle_band_pct"),
}


@pytest.mark.parametrize("flow", sorted(BATCH_OPTIONS))
def test_batch_toml_bad_option_of_a_flow_with_no_inputs(tmp_path, flow):
    text, needle = BATCH_OPTIONS[flow]
    d = tmp_path / "in"
    d.mkdir()
    _w(tmp_path, "in/job.csv" if flow != "path" else "in/t.csv",
       "x_mm,y_mm\n" + "".join(f"{k},{k % 3}\n" for k in range(10)) if flow != "path" else _log(_STEP))
    cfg = _w(tmp_path, "b.toml", f"[{flow}]\n{text}\n")
    _refused(["batch", str(d), "--out", _out(tmp_path), "--config", cfg, "--quiet"], tmp_path, "b.toml",
             f"[{flow}]", needle)


def test_batch_toml_bad_servo_option_stops_the_batch_with_servo_inputs(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    _w(tmp_path, "in/t.csv", _log(_STEP))
    cfg = _w(tmp_path, "b.toml", "[servo]\ntime_unit = \"fortnight\"\n")
    _refused(["batch", str(d), "--out", _out(tmp_path), "--config", cfg, "--quiet"], tmp_path, "b.toml", "[servo]")


# ============================================================================ awkward but documented: read right, outputs clean
# (the exit-0 cases of this suite: every output is scanned for NaN/inf, numbers beyond ±1e15 and empty cells or
# nulls the docs do not allow, hostile_run.scan_outputs)

def _summary(out) -> dict:
    with open(os.path.join(out, "summary.json"), encoding="utf-8") as fh:
        return json.load(fh)


def _clean_run(argv, tmp_path, out) -> dict:
    o = run(argv, tmp_path)
    assert o.code in (0, 4), o.err[-10:]
    assert scan_outputs(out) == []
    return _summary(out)


def test_servo_log_bom_crlf_decimal_commas_reads_as_the_plain_log(tmp_path):
    """docs/servo.md 'Layout': semicolon-separated with decimal commas, CRLF and a BOM are accepted."""
    plain = _w(tmp_path, "plain.csv", _log(_STEP))
    odd = _w(tmp_path, "odd.csv", "\ufefft_s;ref_mm;pos_mm\r\n" + "".join(
        f"{a:.4f};{b:.1f};{c:.1f}\r\n".replace(".", ",") for a, b, c in _STEP))
    s0 = _clean_run(["servo", "--trace", plain, "--out", str(tmp_path / "a"), "--quiet"], tmp_path, tmp_path / "a")
    s1 = _clean_run(["servo", "--trace", odd, "--out", str(tmp_path / "b"), "--quiet"], tmp_path, tmp_path / "b")
    assert s1["n_samples"] == s0["n_samples"] == len(_STEP)
    assert s1["mae_um"] == pytest.approx(s0["mae_um"], rel=1e-9, abs=1e-12)


def test_path_json_with_bom_reads_every_stroke(tmp_path):
    """load_json reads UTF-8 with or without a BOM (pipeline/tables.py)."""
    p = _w(tmp_path, "j.json", "\ufeff" + json.dumps({"strokes": [{"kind": "point", "xy_mm": [k, k % 2]}
                                                                   for k in range(6)]}))
    s = _clean_run(["path", p, "--out", _out(tmp_path), "--quiet", "--no-report"], tmp_path, _out(tmp_path))
    assert s["n_strokes"] == 6


@pytest.mark.parametrize("case", ["path_csv", "cloud_csv"])
def test_bom_crlf_decimal_comma_tables_refused_or_read_right(tmp_path, case):
    """Either one line naming the file, or every row read with its decimal commas (never a silent misread)."""
    if case == "path_csv":
        p = _w(tmp_path, "j.csv", "\ufeffx_mm;y_mm\r\n" + "".join(f"{k},5;{k % 3},25\r\n" for k in range(20)))
        argv = ["path", p, "--out", _out(tmp_path), "--quiet", "--no-report"]
    else:
        p = _w(tmp_path, "c.csv", "\ufeffx;y;z;intensity\r\n" + "".join(
            f"{a:.3f};{b:.3f};{c:.4f};{d:.2f}\r\n".replace(".", ",") for a, b, c, d in _pts(3000)))
        argv = ["scan", p, "--plate", _w(tmp_path, "plate.toml", PLATE), "--out", _out(tmp_path), "--quiet"]
    before = listing(tmp_path)
    o = run(argv, tmp_path)
    if o.code == 1:
        assert_refused(o, os.path.basename(p))
        assert listing(tmp_path) == before
        return
    assert o.code in (0, 4), o.err[-10:]
    assert scan_outputs(_out(tmp_path)) == []
    if case == "path_csv":
        assert _summary(_out(tmp_path))["n_strokes"] == 20


@pytest.mark.parametrize("name", ["spaced name .csv", "new\nline.csv", "\u202eRTL\u05e9\u05dc\u05d5\u05dd.csv",
                                  "caf\u00e9 \u6e2c\u5b9a.csv"])
def test_good_log_under_a_hostile_name_runs_and_writes_clean_outputs(tmp_path, name):
    p = _w(tmp_path, name, _log(_STEP))
    s = _clean_run(["servo", "--trace", p, "--out", _out(tmp_path), "--quiet", "--no-report"], tmp_path,
                   _out(tmp_path))
    assert s["n_samples"] == len(_STEP) and s["source"] == p


def test_svg_with_legit_use_references_reads_every_copy(tmp_path):
    """The <use> cycle and bomb checks leave ordinary references alone: a path used three times is three strokes."""
    p = _w(tmp_path, "j.svg", _SVG.format('<defs><path id="p" d="M0 0 L10 0"/></defs>'
                                          '<use href="#p" y="5"/><use xlink:href="#p" y="15"/>'
                                          '<g id="g"><use href="#p" y="25"/></g>'))
    s = _clean_run(["path", p, "--out", _out(tmp_path), "--quiet", "--no-report"], tmp_path, _out(tmp_path))
    assert s["n_strokes"] == 3
