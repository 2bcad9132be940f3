"""Issue 19: tables laid out as the controllers' own files (structure, not just round trips).

Real EZCAD tables: meerk40t/lmc_corfile_viewer @ 5b25849 : testdata/ (GPL-3.0), read from
``../shared/realdata/galvo_tables/`` and never copied here.
"""
import os
from pathlib import Path

import numpy as np
import pytest

from markcal.fixtures.gls import TrueGalvo
from markcal.pipeline.cli import main
from markcal.pipeline.flows.export import export_table, inspect_bytes, inspect_table
from markcal.stages import table_formats as fmt
from markcal.stages.ctable import centred_nodes, table_structure
from markcal.stages.deviation import GridCorrection

LENS_MM = 70.0          # the small 7 x 7 plate spans +-31.7 mm


def _realdata() -> Path:
    env = os.environ.get("MARKCAL_REALDATA")
    if env:
        return Path(env)
    beside = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
    return beside if beside.is_dir() else Path("/work/shared/realdata")


def _real_cor(name):
    p = _realdata() / "galvo_tables" / name
    if not p.is_file():
        pytest.skip(f"real EZCAD table {p} absent")
    return p


@pytest.fixture(scope="module")
def scan_dir(small_result, tmp_path_factory):
    from markcal.reports.scan_outputs import write_scan_outputs
    out = str(tmp_path_factory.mktemp("scanres"))
    write_scan_outputs(small_result, out, report=False)
    return out


def _lens_table(n=65, half_mm=30.0):
    """A lens correction from a physical machine (x gain error dominant), independent of the exporter."""
    m = TrueGalvo(gain_x=1.012, gain_y=1.003, zero_x_rad=0.0, zero_y_rad=0.0, coupling_yx=0.0)
    nodes = np.linspace(-half_mm, half_mm, n)
    gx, gy = np.meshgrid(nodes, nodes)
    land = m.land(np.column_stack([gx.ravel(), gy.ravel()]))
    off = -(land - np.column_stack([gx.ravel(), gy.ravel()]))        # first order: command offset = -error
    return GridCorrection(nodes, nodes.copy(), off[:, 0].reshape(n, n), off[:, 1].reshape(n, n))


# ----------------------------------------------------------------------------- real EZCAD files

@pytest.mark.parametrize("name", ["50mm.cor", "250mm.cor"])
def test_real_cor_structure(name):
    data = _real_cor(name).read_bytes()
    raw = fmt.cor_file_order(data)
    st = table_structure(raw[..., 0], raw[..., 1])
    # measured: first value odd along inner 0.894 / 0.758 (its two halves have different slopes: -1579 and +930
    # units at the ends of the 250 mm file's middle row), even along outer -0.995 / -0.996; second value odd
    # along outer 0.989 / 0.980, even along inner -0.994 / -0.999; evidence 1.96 / 1.93 of 2
    assert st.first_along == "inner" and st.evidence > 1.7
    assert st.first.odd_inner > 0.7 and st.first.odd_outer < -0.95
    assert st.second.odd_outer > 0.95 and st.second.odd_inner < -0.95
    assert tuple(raw[32, 32]) == (0, 0)
    assert st.first.middle_inner_max == 0 and st.second.middle_outer_max == 0     # exact zero middle lines
    # read with the default layout, the x correction changes sign along x and is zero on the line x = 0
    t, _ = fmt.decode_cor(data)
    assert np.all(t.dx_mm[:, 32] == 0) and np.all(t.dy_mm[32, :] == 0)
    assert np.sign(t.dx_mm[20, 0]) == -np.sign(t.dx_mm[20, 64]) != 0
    assert np.sign(t.dy_mm[0, 20]) == -np.sign(t.dy_mm[64, 20]) != 0
    assert inspect_table(_real_cor(name)).warnings == ()


def test_real_cor_read_transposed_is_flagged(tmp_path, capsys):
    p = _real_cor("50mm.cor")
    t = inspect_table(p, cor=fmt.CorOptions(outer="x"))
    assert len(t.warnings) == 1 and "contradicts the chosen layout" in t.warnings[0] and "--outer y" in t.warnings[0]
    assert main(["inspect", str(p), "--outer", "x", "--out", str(tmp_path / "i")]) == 0
    err = capsys.readouterr().err
    assert err.count("markcal: warning:") == 1 and "contradicts" in err
    assert "contradicts the chosen layout" in (tmp_path / "i" / "report.html").read_text()


def test_real_cor_permuted_fits_no_layout():
    data = bytearray(_real_cor("250mm.cor").read_bytes())
    raw = fmt.cor_file_order(bytes(data)).reshape(-1, 2)
    perm = np.random.default_rng(19).permutation(len(raw))
    data[36:36 + raw.nbytes] = np.ascontiguousarray(raw[perm]).astype("<i4").tobytes()
    t = inspect_bytes(bytes(data), "permuted.cor")
    assert t.structure.first_along == "none" and "fits no known layout" in t.warnings[0]


# ----------------------------------------------------------------------------- bad tables: read, reported, not interpreted

def test_all_zero_and_permuted_tables_fit_no_layout(tmp_path, capsys):
    zero = fmt.COR_LABEL.ljust(22, b"\0") + b"\0" * 6 + np.float64(500.0).tobytes() + b"\0" * (65 * 65 * 8 + 4)
    t = inspect_bytes(zero, "zero.cor")
    assert t.structure.first_along == "none" and "every entry is zero" in t.warnings[0]
    p = tmp_path / "zero.cor"
    p.write_bytes(zero)
    assert main(["inspect", str(p), "--out", str(tmp_path / "z")]) == 0
    assert "fits no known layout" in capsys.readouterr().err
    assert "fits no known layout" in (tmp_path / "z" / "report.html").read_text()
    lens = _lens_table()
    good = fmt.encode_cor(lens, 1000.0)
    assert inspect_bytes(good, "lens.cor").warnings == ()
    raw = fmt.cor_file_order(good).reshape(-1, 2)
    perm = np.random.default_rng(7).permutation(len(raw))
    bad = good[:36] + np.ascontiguousarray(raw[perm]).astype("<i4").tobytes() + good[-4:]
    t = inspect_bytes(bad, "perm.cor")
    assert t.structure.first_along == "none" and abs(t.structure.evidence) < 0.5
    ctb = fmt.encode_ctb(lens, 1000.0, fmt.CtbOptions(content="offset"))
    tables = fmt.ctb_file_order(ctb)
    shuffled = (tables.reshape(2, -1)[:, perm] + 32767.5).astype("<u2").tobytes()
    t = inspect_bytes(shuffled, "perm.ctb", lens_mm=65.536)
    assert t.structure.first_along == "none" and "fits no known layout" in t.warnings[0]


# ----------------------------------------------------------------------------- exported tables have the vendors' structure

def test_premise_x_scale_error_dominates(small_render):
    m = small_render.truth["machine"]
    assert abs(m["gain_x"] - 1) >= 0.01 and abs(m["gain_x"] - 1) > 2 * abs(m["gain_y"] - 1)


def test_exported_cor_has_the_real_files_structure(scan_dir):
    data, _ = export_table("cor", scan_dir, lens_mm=LENS_MM)
    raw = fmt.cor_file_order(data)
    st = table_structure(raw[..., 0], raw[..., 1])
    assert st.first_along == "inner" and st.evidence > 1.0
    assert st.first.odd_inner > 0.8 and st.first.rms > 2 * st.second.rms        # x error dominant, in the first value
    # the first value changes sign along the inner index in every row, like EZCAD's files
    assert np.all(np.sign(raw[:, 2, 0] - raw[32, 32, 0]) == -np.sign(raw[:, 62, 0] - raw[32, 32, 0]))
    assert inspect_bytes(data, "x.cor").warnings == ()
    old, _ = export_table("cor", scan_dir, lens_mm=LENS_MM, cor=fmt.CorOptions(outer="x"))   # the former default
    raw_old = fmt.cor_file_order(old)
    assert table_structure(raw_old[..., 0], raw_old[..., 1]).first_along == "outer"
    assert "contradicts" in inspect_bytes(old, "old.cor").warnings[0]


def test_exported_ctb_has_scanlab_structure(scan_dir):
    # offset content from the scan (with absolute content this machine's outward correction at the field edge
    # does not fit 0..65535 and is refused: README)
    data, _ = export_table("ctb", scan_dir, lens_mm=LENS_MM, ctb=fmt.CtbOptions(content="offset"))
    tables = fmt.ctb_file_order(data)
    st = table_structure(tables[0], tables[1])
    assert st.first_along == "inner" and st.first.odd_inner > 0.8 and st.first.rms > 2 * st.second.rms
    assert inspect_bytes(data, "t.ctb", lens_mm=LENS_MM, ctb=fmt.CtbOptions(content="offset")).warnings == ()
    # absolute content (a machine whose field is too large, so the correction points inwards): the X table
    # ramps from 0 to 65535 along the inner index, the Y table along the outer one
    nodes = centred_nodes(65, 65535 / 64, 1000.0)
    lens = _lens_table(half_mm=float(nodes[-1]))
    abs_data = fmt.encode_ctb(lens, 1000.0)
    tables = fmt.ctb_file_order(abs_data) + 32767.5
    assert tables[0][32, 0] < 1000 and tables[0][32, -1] > 64500 and np.ptp(tables[0][:, 32]) < 100
    assert tables[1][0, 32] < 1000 and tables[1][-1, 32] > 64500 and np.ptp(tables[1][32, :]) < 100
    st = table_structure(*fmt.ctb_file_order(abs_data))
    assert st.first_along == "inner" and st.evidence > 1.9


def test_exported_correxion_structure_and_order(scan_dir, small_result):
    data, _ = export_table("correxion", scan_dir, lens_mm=LENS_MM, fill_missing=True)
    lines = [l.split() for l in data.decode().splitlines()]
    pts = np.array([[float(v) for v in f] for f in lines if len(f) == 4 and f[0].lstrip("-").isdigit()])
    # as correXion input is written by third-party tools: Xn fastest, top row (Yn = +3) first
    assert pts.shape == (49, 4) and tuple(pts[0, :2]) == (-3, 3) and tuple(pts[1, :2]) == (-2, 3)
    assert tuple(pts[-1, :2]) == (3, -3)
    d = fmt.decode_correxion(data.decode())
    gx, gy = np.meshgrid(d["x_mm"], d["y_mm"])
    dev = d["measured_xy_mm"] - np.stack([gx, gy], axis=-1)
    st = table_structure(dev[..., 0], dev[..., 1])          # [iy, ix]: the file's x-fastest order
    assert st.first_along == "inner" and st.first.odd_inner > 0.8 and st.first.rms > 2 * st.second.rms
    assert inspect_bytes(data, "in.dat").warnings == ()
    text = fmt.encode_correxion(np.linspace(-2, 2, 5), np.linspace(-1, 1, 3), np.zeros((3, 5, 2)), 1000.0)
    assert "[GRIDNUMBERS]=1 2" in text             # half counts (y, x), as the tools that drive correXion write them


def test_a3200_axis_order():
    x = np.linspace(-20.0, 20.0, 5)                # axis 1, 10 mm steps
    y = np.linspace(-5.0, 5.0, 3)                  # axis 2, 5 mm steps
    gx, gy = np.meshgrid(x, y)
    err_x_um, err_y_um = 0.5 * gx + 0.01 * gy ** 2, 0.1 * gy           # x scale error dominates, µm
    text = fmt.encode_a3200(x, y, err_x_um, err_y_um, ax1=1, ax2=2)
    lines = text.splitlines()
    # :START2D RowAxis ColumnAxis OutputAxis(1st of pair) OutputAxis(2nd) RowSampleDist ColSampleDist NumCols
    assert lines[0] == ":START2D 2 1 1 2 5.000000 10.000000 5"
    rows = np.array([[float(v) for v in l.split()] for l in lines[2:-1]])
    assert rows.shape == (3, 10)                   # one row per axis-2 position, pairs along axis 1
    st = table_structure(rows[:, 0::2], rows[:, 1::2])
    assert st.first_along == "inner" and st.first.odd_inner > 0.99
    assert rows[0, 0] == pytest.approx(-err_x_um[0, 0]) and rows[0, 1] == pytest.approx(-err_y_um[0, 0])
    t = inspect_bytes(text.encode(), "s.cal")
    assert t.warnings == () and np.allclose(t.u, -err_x_um)
    sq = np.linspace(-20.0, 20.0, 5)            # a map whose x error varies along y: the axes look swapped
    gx, gy = np.meshgrid(sq, sq)
    swapped = fmt.encode_a3200(sq, sq, 0.5 * gy, 0.3 * gx)
    assert "look swapped relative to its x/y labels" in inspect_bytes(swapped.encode(), "w.cal").warnings[0]


def test_export_note(scan_dir, tmp_path, capsys):
    out = tmp_path / "lens.cor"
    assert main(["export", "cor", scan_dir, "--lens-mm", str(LENS_MM), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr()
    assert "warning" not in printed.err and str(out) + ".html" in printed.out
    html = (tmp_path / "lens.cor.html").read_text()
    for needle in ("inner index along x (EZCAD", "lens field", "70 mm", "nominal − entry", "range: first values",
                   "data:image/png;base64,", "odd along inner / outer"):
        assert needle in html, needle
    assert main(["export", "cor", scan_dir, "--lens-mm", str(LENS_MM), "--outer", "x", "--out",
                 str(tmp_path / "t.cor"), "--quiet", "--no-report"]) == 0
    assert not (tmp_path / "t.cor.html").exists()
    assert main(["export", "cor", scan_dir, "--out", str(tmp_path / "x.cor"), "--quiet"]) == 1
    assert not (tmp_path / "x.cor").exists() and not (tmp_path / "x.cor.html").exists()
