"""Controller tables (issue 7): write -> read round trips, fidelity to the flow's correction, refusals."""
import os
import struct

import numpy as np
import pytest

from markcal.pipeline.cli import main
from markcal.pipeline.flows.export import export_table, inspect_table, load_scan_source
from markcal.stages import table_formats as fmt
from markcal.stages.ctable import check_interpolation, sample_onto_nodes
from markcal.stages.deviation import GridCorrection
from markcal.stages.errors import MarkcalError

LENS_MM = 70.0          # the small 7 x 7 plate spans +-31.7 mm


@pytest.fixture(scope="module")
def scan_dir(small_result, tmp_path_factory):
    from markcal.reports.scan_outputs import write_scan_outputs
    out = str(tmp_path_factory.mktemp("scanres"))
    write_scan_outputs(small_result, out, report=False)
    return out


@pytest.fixture(scope="module")
def selfcal_dir(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("sc"))
    assert main(["render", "selfcal", "--seed", "31", "--out", f"{d}/s", "--quiet"]) == 0
    assert main(["selfcal", f"{d}/s", "--out", f"{d}/o", "--quiet", "--no-report"]) == 0
    return f"{d}/o"


def test_cor_layout_and_round_trip(scan_dir):
    data, facts = export_table("cor", scan_dir, lens_mm=LENS_MM)
    assert len(data) == 33840 and data[:22] == b"JCZ_COR_2_1".ljust(22, b"\0") and data[22:28] == b"\0" * 6
    upm = struct.unpack_from("<d", data, 28)[0]
    assert upm == pytest.approx(65536 / LENS_MM) and data[-4:] == b"\0" * 4
    table, upm2 = fmt.decode_cor(data)
    # re-encoding what was read gives the same bytes: the table survives to the format's resolution
    assert fmt.encode_cor(table, upm2) == data
    src = load_scan_source(scan_dir)
    nodes_in = (np.abs(table.x_mm) <= src.region_mm[1])
    gx, gy = np.meshgrid(table.x_mm[nodes_in], table.y_mm[nodes_in])
    want = src.offset_mm(np.column_stack([gx.ravel(), gy.ravel()]))
    got = np.column_stack([table.dx_mm[np.ix_(nodes_in, nodes_in)].ravel(), table.dy_mm[np.ix_(nodes_in, nodes_in)].ravel()])
    assert np.abs(got - want).max() * upm <= 0.5 + 1e-9          # rounding to whole galvo units only


def test_cor_applied_by_bilinear_reproduces_the_scan_correction(scan_dir):
    # issue 7: within one galvo unit over the field the scan measured
    data, _ = export_table("cor", scan_dir, lens_mm=LENS_MM)
    table, upm = fmt.decode_cor(data)
    src = load_scan_source(scan_dir)
    rng = np.random.default_rng(3)
    x0, x1, y0, y1 = src.region_mm
    xy = np.column_stack([rng.uniform(x0, x1, 5000), rng.uniform(y0, y1, 5000)])
    err_units = np.abs(table.offset(xy) - src.offset_mm(xy)).max() * upm
    assert err_units <= 1.0
    assert np.abs(src.offset_mm(xy)).max() * upm > 20              # a correction far above one unit was carried


def test_cor_options_change_the_bytes_not_the_field(scan_dir):
    ref, _ = export_table("cor", scan_dir, lens_mm=LENS_MM)
    t_ref, _ = fmt.decode_cor(ref)
    for opts in (fmt.CorOptions(outer="x"), fmt.CorOptions(sign="add"), fmt.CorOptions(node_spacing_units=1023.0)):
        data, _ = export_table("cor", scan_dir, lens_mm=LENS_MM, cor=opts)
        assert data != ref
        t, _ = fmt.decode_cor(data, opts)
        if opts.node_spacing_units == 1024.0:
            assert np.array_equal(t.dx_mm, t_ref.dx_mm) and np.array_equal(t.dy_mm, t_ref.dy_mm)
    t_wrong, _ = fmt.decode_cor(ref, fmt.CorOptions(outer="x"))       # read with the wrong index order
    assert np.array_equal(t_wrong.dx_mm, t_ref.dx_mm.T)


def test_refusals(scan_dir):
    nodes = np.linspace(-30, 30, 65)
    big = GridCorrection(nodes, nodes.copy(), np.full((65, 65), 0.6), np.zeros((65, 65)))
    with pytest.raises(MarkcalError, match="outside the format's range"):
        fmt.encode_cor(big, 65536.0)                  # 0.6 mm at 65,536 units/mm: 39,322 > 32,767
    with pytest.raises(MarkcalError, match="would be extrapolated"):
        export_table("cor", scan_dir, lens_mm=400.0)                  # table field 6x the plate
    with pytest.raises(MarkcalError, match="--lens-mm"):
        export_table("ctb", scan_dir)
    with pytest.raises(MarkcalError, match="unknown format"):
        export_table("ct5", scan_dir)
    with pytest.raises(MarkcalError, match="not a selfcal flow result"):
        export_table("a3200", scan_dir)


def test_too_coarse_table_is_refused():
    def wavy(xy):                      # 3 mm period: nodes 10 mm apart cannot carry it
        xy = np.atleast_2d(xy)
        return np.column_stack([0.01 * np.sin(2 * np.pi * xy[:, 0] / 3.0), np.zeros(len(xy))])
    nodes = np.linspace(-50, 50, 11)
    s = sample_onto_nodes(wavy, nodes, nodes, (-50, 50, -50, 50))
    with pytest.raises(MarkcalError, match="too coarse"):
        check_interpolation(wavy, s.table, (-50, 50, -50, 50), 0.001)


def test_ctb_round_trip_absolute_and_offset(scan_dir):
    nodes = (np.arange(65) - 32) * (65535 / 64) / 1000.0       # 1000 bits/mm
    gx, gy = np.meshgrid(nodes, nodes)
    inward = GridCorrection(nodes, nodes.copy(), -0.004 * gx + 0.001 * gy, -0.003 * gy)   # pincushion-like, mm
    for content in ("absolute", "offset"):
        opts = fmt.CtbOptions(content=content)
        data = fmt.encode_ctb(inward, 1000.0, opts)
        assert len(data) == 16900
        back = fmt.decode_ctb(data, 1000.0, opts)
        assert np.abs(back.dx_mm - inward.dx_mm).max() <= 0.5e-3 + 1e-12     # half a bit
        assert np.abs(back.dy_mm - inward.dy_mm).max() <= 0.5e-3 + 1e-12
    ident = fmt.encode_ctb(GridCorrection(nodes, nodes.copy(), 0 * gx, 0 * gy), 1000.0)
    v = np.frombuffer(ident, "<u2").reshape(2, 65, 65)
    assert v[0, 0, 0] == 0 and v[0, 0, -1] == 65535 and v[1, -1, 0] == 65535   # 1:1 table spans 0..65535
    data, _ = export_table("ctb", scan_dir, lens_mm=LENS_MM, ctb=fmt.CtbOptions(content="offset"))
    assert len(data) == 16900
    with pytest.raises(MarkcalError, match="outside the format's range"):
        fmt.encode_ctb(GridCorrection(nodes, nodes.copy(), 0.01 + 0 * gx, 0 * gy), 1000.0)  # pushes past the edge


def test_correxion_round_trip(scan_dir, small_result):
    missing = len(small_result.missing_ids)
    if missing:
        with pytest.raises(MarkcalError, match="not detected"):
            export_table("correxion", scan_dir, lens_mm=LENS_MM)
    data, facts = export_table("correxion", scan_dir, lens_mm=LENS_MM, fill_missing=True)
    assert facts["filled_points"] == missing
    assert facts["unmarked_sites"] == 49 - len(small_result.spec.marked_ids)    # the orientation mark's site
    d = fmt.decode_correxion(data.decode())
    assert d["bits_per_mm"] == pytest.approx(2 ** 20 / LENS_MM) and not d["rtc4"]
    src = load_scan_source(scan_dir)
    f = src.fiducials
    ix = np.searchsorted(d["x_mm"], f["x_nom_mm"] - 1e-6)
    iy = np.searchsorted(d["y_mm"], f["y_nom_mm"] - 1e-6)
    assert np.allclose(d["measured_xy_mm"][iy, ix, 0], f["x_meas_mm"], atol=1e-6)
    assert np.allclose(d["measured_xy_mm"][iy, ix, 1], f["y_meas_mm"], atol=1e-6)
    text = data.decode()
    assert "[GRIDNUMBERS]=3 3" in text and text.count("[GRIDVALUES_X]") == 7


def test_a3200_round_trip_and_sign(selfcal_dir):
    data, _ = export_table("a3200", selfcal_dir)
    text = data.decode()
    lines = text.splitlines()
    assert lines[0] == ":START2D 2 1 1 2 10.000000 10.000000 11"
    assert lines[1].startswith(":START2D POSUNIT=METRIC CORUNIT=METRIC/1000") and lines[-1] == ":END"
    assert len(lines) == 2 + 11 + 1 and len(lines[2].split("\t")) == 22
    from markcal.pipeline.tables import read_table
    t = read_table(os.path.join(selfcal_dir, "stage_error.csv"), ("m", "n", "gx_um", "gy_um"), int_columns=("m", "n"))
    g00 = t["gx_um"][(t["m"] == -5) & (t["n"] == -5)][0]
    assert float(lines[2].split("\t")[0]) == pytest.approx(-g00, abs=1e-6)        # correction = -sign x error
    d = fmt.decode_a3200(text)
    gx = np.zeros((11, 11))
    gx[t["n"] + 5, t["m"] + 5] = t["gx_um"]
    assert np.abs(d["error_x_um"] - gx).max() <= 1e-6
    neg, _ = export_table("a3200", selfcal_dir, sign=-1.0)
    assert float(neg.decode().splitlines()[2].split("\t")[0]) == pytest.approx(g00, abs=1e-6)


def test_cli_export_list_inspect(scan_dir, selfcal_dir, tmp_path, capsys):
    assert main(["export", "--list"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ("cor", "ctb", "correxion", "a3200"))
    cor = str(tmp_path / "lens.cor")
    assert main(["export", "cor", scan_dir, "--lens-mm", str(LENS_MM), "--out", cor, "--quiet"]) == 0
    assert main(["inspect", cor, "--out", str(tmp_path / "i")]) == 0
    html = open(tmp_path / "i" / "report.html").read()
    assert "data:image/png;base64," in html and "65 x 65" in html
    t = inspect_table(cor)
    assert t.format == "cor" and t.u.shape == (65, 65)
    cal = str(tmp_path / "stage.cal")
    assert main(["export", "a3200", selfcal_dir, "--out", cal, "--quiet"]) == 0
    assert main(["inspect", cal, "--out", str(tmp_path / "j")]) == 0
    ctb = str(tmp_path / "t.ctb")
    assert main(["export", "ctb", scan_dir, "--lens-mm", str(LENS_MM), "--ctb-content", "offset", "--out", ctb,
                 "--quiet"]) == 0
    capsys.readouterr()
    assert main(["inspect", ctb, "--out", str(tmp_path / "k")]) == 1
    assert "give --lens-mm" in capsys.readouterr().err
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"hello")
    assert main(["inspect", str(junk), "--out", str(tmp_path / "l")]) == 1
    assert "not a correction table" in capsys.readouterr().err
    assert main(["export", "cor", scan_dir, "--out", str(tmp_path / "x.cor"), "--quiet"]) == 1
    assert "--lens-mm" in capsys.readouterr().err and not os.path.exists(tmp_path / "x.cor")


def _one_node_table(ix, iy, dx_mm, dy_mm, spacing_units, units_per_mm):
    nodes = (np.arange(65) - 32) * spacing_units / units_per_mm
    dx, dy = np.zeros((65, 65)), np.zeros((65, 65))
    dx[iy, ix], dy[iy, ix] = dx_mm, dy_mm
    return GridCorrection(nodes, nodes.copy(), dx, dy)


def test_cor_bytes_by_hand():
    """JCZ_COR_2_1 default layout, worked out by hand: entries (dx, dy) int32 from byte 36, the inner
    index along x (entry number iy·65 + ix), each the negated command offset in galvo units
    (sign "subtract"): +0.0102 mm at 1000 units/mm -> -10.2 -> -10; -0.0207 mm -> +20.7 -> +21."""
    t = _one_node_table(10, 3, 0.0102, -0.0207, 1024.0, 1000.0)
    data = fmt.encode_cor(t, 1000.0)
    assert struct.unpack_from("<d", data, 28)[0] == 1000.0
    at = 36 + 8 * (3 * 65 + 10)
    assert struct.unpack_from("<2i", data, at) == (-10, 21)
    assert struct.unpack_from("<2i", data, 36 + 8 * (10 * 65 + 3)) == (0, 0)        # not transposed
    back, scale = fmt.decode_cor(data)
    assert back.dx_mm[3, 10] == pytest.approx(0.010, abs=1e-12) and back.dy_mm[3, 10] == pytest.approx(-0.021, abs=1e-12)
    assert back.x_mm[10] == pytest.approx((10 - 32) * 1.024, abs=1e-12)              # node 10 at -22 x 1024 units


def test_ctb_bytes_by_hand():
    """RTC4 .ctb, content "offset": X table then Y table, uint16 offset binary (32767.5 + offset·bits/mm),
    inner index along x: +0.0102 mm at 1000 bits/mm -> 32777.7 -> 32778 at entry iy·65 + ix of the X table."""
    t = _one_node_table(10, 3, 0.0102, -0.0207, 65535.0 / 64, 1000.0)
    data = fmt.encode_ctb(t, 1000.0, fmt.CtbOptions(content="offset"))
    x_tab = np.frombuffer(data[:65 * 65 * 2], "<u2").reshape(65, 65)
    y_tab = np.frombuffer(data[65 * 65 * 2:], "<u2").reshape(65, 65)
    assert x_tab[3, 10] == 32778 and y_tab[3, 10] == 32747            # 32767.5 - 20.7 = 32746.8 -> 32747
    assert x_tab[10, 3] == 32768 and x_tab[0, 0] == 32768             # 32767.5 rounds to even
    # read back: (32778 - 32767.5) / 1000 = 0.0105 mm, (32747 - 32767.5) / 1000 = -0.0205 mm, 0.0005 elsewhere
    back = fmt.decode_ctb(data, 1000.0, fmt.CtbOptions(content="offset"))
    assert back.dx_mm[3, 10] == pytest.approx(0.0105, abs=1e-12) and back.dy_mm[3, 10] == pytest.approx(-0.0205, abs=1e-12)
    assert back.dx_mm[0, 0] == pytest.approx(0.0005, abs=1e-12)
    # absolute content adds the node position: node (ix = 10) at (10 - 32)·1023.984375 bits
    data = fmt.encode_ctb(t, 1000.0)
    x_abs = np.frombuffer(data[:65 * 65 * 2], "<u2").reshape(65, 65)
    assert x_abs[3, 10] == int(np.rint(32767.5 + (10 - 32) * 65535.0 / 64 + 10.2))
    assert x_abs[10, 3] == int(np.rint(32767.5 + (3 - 32) * 65535.0 / 64))
