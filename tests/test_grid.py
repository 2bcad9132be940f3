"""The grid flow: hand-measured galvo grids against the true machines of fixtures/measured_grid.

Truth is the fixture's forward simulation (``GridMachine.land``: fixtures/gls.py's
TrueGalvo plus plate tilt and a fifth-order lens term the fitted model lacks).
Tolerances come from issue 14's goals (9 x 9 over a 110 mm lens, 0.02 mm noise):
corrected landing RMS <= 0.03 mm over the measured area, <= 0.08 mm over the lens
field; 5-fold CV error <= 1.3 x the noise (Euclidean, so 1.3 x sqrt(2) x sigma).
"""
import json
import os

import numpy as np
import pytest

from markcal.fixtures.gls import correction_residual
from markcal.fixtures.measured_grid import GridRenderOptions, render_grid
from markcal.pipeline.cli import main
from markcal.stages.errors import MarkcalError
from markcal.stages.grid_input import parse_grid
from markcal.stages.grid_smooth import fit_thin_plate


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1))))


def _render_cli(tmp_path, *extra):
    out = tmp_path / "render"
    assert main(["render", "grid", "--out", str(out), "--quiet", *extra]) == 0
    truth = json.loads((out / "truth.json").read_text())
    return out, truth


def _machine(truth):
    from markcal.fixtures.gls import TrueGalvo
    from markcal.fixtures.measured_grid import GridMachine
    m = dict(truth["machine"])
    return GridMachine(galvo=TrueGalvo(**m.pop("galvo")), **m)


# ----------------------------------------------------------------------------- building blocks

def test_thin_plate_matches_scipy_and_brute_force_loo():
    """The spline equals scipy's RBFInterpolator (same smoothing) and its closed-form LOO a refit loop."""
    from scipy.interpolate import RBFInterpolator
    rng = np.random.default_rng(5)
    x = rng.uniform(-40, 40, (40, 2))
    y = np.column_stack([np.sin(x[:, 0] / 15), 1e-3 * x[:, 1] ** 2]) + rng.normal(0, 0.02, (40, 2))
    t, loo = fit_thin_plate(x, y)
    u = (x - t.centre_mm) / t.scale_mm
    ref = RBFInterpolator(u, y, kernel="thin_plate_spline", smoothing=t.lam)
    xe = rng.uniform(-50, 50, (100, 2))
    assert np.abs(ref((xe - t.centre_mm) / t.scale_mm) - t(xe)).max() < 1e-9
    e = []
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        e.append(RBFInterpolator(u[keep], y[keep], kernel="thin_plate_spline", smoothing=t.lam)(u[i:i + 1])[0] - y[i])
    assert loo == pytest.approx(_rms(e), rel=1e-6)


@pytest.mark.parametrize("seed", [3, 11, 12])
def test_physical_model_holds_the_true_galvo(seed):
    """Design claim: the physical model (eqs. 1-5 + lens + tilt) contains the renderer's machine without its
    fifth-order lens term, so noise-free marks over 80 % of the field fix it over the whole lens field.

    Truth: fixtures/gls.py's TrueGalvo and the plate tilt of fixtures/measured_grid.py (their own code, not
    galvo_fit). Measured on these seeds: fit RMS 6-29 nm, worst field error 37-129 nm (from 0.27-0.51 mm
    uncorrected); limits at 2x.
    """
    from dataclasses import replace
    from markcal.fixtures.measured_grid import sample_grid_machine
    from markcal.stages.galvo_fit import fit_physical
    machine = replace(sample_grid_machine(np.random.default_rng(seed), 110.0), k5_per_mm4=0.0)
    xs = np.linspace(-44, 44, 9)
    cmd = np.array([(x, y) for y in xs for x in xs])
    land = machine.land(cmd)
    fit = fit_physical(cmd, land, machine.galvo.nominal_d_mm, machine.galvo.nominal_e_mm)
    assert _rms(fit.land(cmd) - land) <= 6e-5 < 0.2 <= _rms(land - cmd)
    f = np.linspace(-55, 55, 23)
    field = np.array([(x, y) for y in f for x in f])
    assert np.abs(fit.land(field) - machine.land(field)).max() <= 2.6e-4


def test_cross_validation_predicts_each_fold_without_it():
    """A cubic field plus one 0.1 mm outlier: poly3 fitted without the outlier's fold predicts it exactly, so its
    k-fold error there is the outlier itself (hand-known); every fold holds 2 of the 20 points."""
    from markcal.stages.galvo_fit import cross_validate, fold_labels
    rng = np.random.default_rng(1)
    cmd = rng.uniform(-40, 40, (20, 2))
    u, v = cmd.T / 40
    land = cmd + 0.05 * np.column_stack([u ** 3 - u * v, v * v * u + 0.3 * v])
    land[7] += [0.1, -0.05]
    folds = fold_labels(20, 10, seed=0)
    assert np.bincount(folds).tolist() == [2] * 10
    err = cross_validate("poly3", cmd, land, 160.0, 14.0, folds)
    assert err[7] == pytest.approx([-0.1, 0.05], abs=1e-9)
    clean = folds != folds[7]
    assert np.abs(err[clean]).max() > 1e-4            # the outlier, in their training set, leaks into them


def test_hull_distance_by_hand():
    from markcal.stages.galvo_fit import hull_distance_mm
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, 5]], float)
    d = hull_distance_mm(np.array([[5, 5], [10, 3], [13, 5], [5, -2], [-1, 4]], float), square)
    assert d == pytest.approx([0, 0, 3, 2, 1], abs=1e-12)


def test_bjjcz_line_and_layout_detection():
    upm = 400.0
    lines = [f"{-63.25 + 11 * i:.2f} {-67.30 + 11 * j:.2f} {i - 1} {j - 1} {0x2000 + 0x1000 * i:04X} {0x2000 + 0x1000 * j:04X}"
             for j in range(3) for i in range(3)]
    g = parse_grid("\n".join(lines) + "\n", units_per_mm=upm)
    assert g.layout == "bjjcz"
    assert g.cmd_mm[0] == pytest.approx([(0x2000 - 0x8000) / upm] * 2)
    assert g.meas_mm[0] == pytest.approx([-63.25, -67.30])
    # i (third field) counts along x: the column; j (fourth) along y: the row
    assert g.col.tolist() == [i for j in range(3) for i in range(3)]
    assert g.row.tolist() == [j for j in range(3) for i in range(3)]
    with pytest.raises(MarkcalError, match="units-per-mm"):
        parse_grid("\n".join(lines))


def test_three_layouts_read_the_same_commands(tmp_path):
    """CSV in mm, CSV in (hex) controller units and the BJJCZ file give the commands to one unit."""
    truth_cmd = None
    for fmt, name in (("csv", "measured.csv"), ("units", "measured_units.csv"), ("bjjcz", "measured.txt")):
        out, truth = _render_cli(tmp_path / fmt, "--format", fmt, "--seed", "4")
        from markcal.stages.grid_input import read_grid
        g = read_grid(out / name, units_per_mm=None if fmt == "csv" else truth["units_per_mm"])
        if truth_cmd is None:
            truth_cmd = g.cmd_mm
        assert np.abs(g.cmd_mm - truth_cmd).max() <= 0.5 / truth["units_per_mm"] + 1e-12
        assert len(g.cmd_mm) == 81 - 2


# ----------------------------------------------------------------------------- accuracy against truth

@pytest.mark.parametrize("seed,mirror", [(1, False), (2, True)])
def test_grid_to_cor_on_the_true_machine(tmp_path, seed, mirror):
    """9 x 9 over a 110 mm lens, 0.02 mm noise: the exported .cor corrects the true machine to the goals."""
    from markcal.stages.table_formats import decode_cor
    extra = ["--seed", str(seed)] + (["--mirror"] if mirror else [])
    src, truth = _render_cli(tmp_path, *extra)
    out = tmp_path / "out"
    one_step = tmp_path / "one_step.cor"
    assert main(["grid", str(src / "measured.csv"), "--out", str(out), "--lens-mm", "110", "--quiet",
                 "--cor", str(one_step)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["mirrored"] is mirror
    assert s["cv_rmse_mm"] <= 1.3 * np.sqrt(2) * 0.02
    assert s["cv_rmse_physical_rbf_mm"] < s["cv_rmse_rbf_mm"]
    cor = tmp_path / "t.cor"
    assert main(["export", "cor", str(out), "--lens-mm", "110", "--out", str(cor), "--quiet"]) == 0
    assert cor.read_bytes() == one_step.read_bytes()         # grid --cor writes what export cor writes
    table, upm = decode_cor(cor.read_bytes())
    assert upm == pytest.approx(65536 / 110)
    machine = _machine(truth)
    _, before_in = correction_residual(machine, lambda w: w, 44, 44, 2.0)
    _, inside = correction_residual(machine, table.command, 44, 44, 2.0)
    _, field = correction_residual(machine, table.command, 55, 55, 2.0)
    # measured on seeds 1, 2: 0.0079 / 0.0067 mm inside, 0.0129 / 0.0141 mm over the field (goals 0.03 / 0.08)
    assert _rms(inside) <= 0.015 < 0.1 < _rms(before_in)
    assert _rms(field) <= 0.028
    if not mirror:
        return
    # the other formats read the same folder
    from markcal.pipeline.flows.export import inspect_table
    for fmt, extra in (("ctb", ["--ctb-content", "offset"]), ("correxion", ["--fill-missing"]), ("a3200", [])):
        assert main(["export", fmt, str(out), "--lens-mm", "110", "--out", str(tmp_path / f"t.{fmt}"), "--quiet",
                     *extra]) == 0
    a3 = inspect_table(tmp_path / "t.a3200")
    assert np.nanmax(np.hypot(a3.u, a3.v)) == pytest.approx(1e3 * s["max_correction_mm"], abs=1e-3)


@pytest.mark.parametrize("seed,mirror", [(101, True), (102, False)])
def test_physical_rbf_predicts_the_true_landing_better_than_a_spline(tmp_path, seed, mirror):
    """Issue 14's claim: k-fold CV prediction error against the true (noise-free) landing of the held-out marks,
    physical+rbf at least 10 % below the thin-plate spline alone on the same folds (9 x 9, 110 mm, 0.02 mm).

    Truth: the renderer's noise-free landings, put through the measuring frame and the flow's registration.
    Measured: ratio 0.37 (seed 101), 0.42 (seed 102); limit 0.75 (2x the worst, and inside the goal's 0.9).
    """
    from markcal.pipeline.flows.grid import GridOptions, run_grid
    from markcal.reports.files import write_csv
    r = render_grid(seed, GridRenderOptions(mirror=mirror))
    path = tmp_path / "m.csv"
    write_csv(path, {"x_cmd_mm": r.cmd_mm[:, 0], "y_cmd_mm": r.cmd_mm[:, 1],
                     "x_meas_mm": r.meas_mm[:, 0], "y_meas_mm": r.meas_mm[:, 1]})
    res = run_grid(path, GridOptions(lens_mm=110.0))
    a = np.radians(r.truth["frame_angle_deg"])
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.diag([1.0, -1.0 if mirror else 1.0])
    clean = res.registration.apply(r.land_mm @ rot.T + np.array(r.truth["frame_shift_mm"]))
    land = np.column_stack([res.fiducials["x_meas_mm"], res.fiducials["y_meas_mm"]])
    assert _rms(land - clean) == pytest.approx(np.sqrt(2) * 0.02, rel=0.25)      # the frame is undone: noise left
    err = {k: _rms(e + land - clean) for k, e in res.choice.cv_errors_mm.items()}
    assert err["physical+rbf"] <= 0.75 * err["rbf"]


def test_missing_marks_and_units_input(tmp_path):
    """A 7 x 7 grid on a 50 mm lens in controller units, six marks missing, 0.01 mm noise."""
    src, truth = _render_cli(tmp_path, "--rows", "7", "--cols", "7", "--lens-mm", "50", "--noise-mm", "0.01",
                             "--missing", "6", "--format", "units", "--seed", "7")
    out = tmp_path / "out"
    assert main(["grid", str(src / "measured_units.csv"), "--out", str(out), "--units-per-mm",
                 str(truth["units_per_mm"]), "--quiet", "--no-report"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["n_marks"] == 43 and s["lens_mm"] == pytest.approx(50.0)
    from markcal.pipeline.flows.export import load_scan_source
    src_model = load_scan_source(out)
    machine = _machine(truth)
    _, field = correction_residual(machine, lambda w: w + src_model.offset_mm(w), 25, 25, 1.0)
    assert _rms(field) <= 0.04       # 0.08 mm at 0.02 mm noise on 110 mm, scaled to this smaller, quieter case


def test_auto_reports_all_models(tmp_path):
    src, _ = _render_cli(tmp_path, "--seed", "3")
    out = tmp_path / "out"
    assert main(["grid", str(src / "measured.csv"), "--out", str(out), "--model", "auto", "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    cv = {k: s[f"cv_rmse_{k}_mm"] for k in ("physical_rbf", "rbf", "poly3")}
    assert s["cv_rmse_mm"] == min(cv.values())
    html = (out / "report.html").read_text()
    for label in ("physical galvo + thin-plate spline", "thin-plate spline alone", "cubic polynomial",
                  "Extrapolated nodes"):
        assert label in html
    grid = np.genfromtxt(out / "correction_grid.csv", delimiter=",", names=True)
    assert s["n_extrapolated"] == int(grid["extrapolated"].sum()) > 0
    assert np.all(grid["outside_hull_mm"][grid["extrapolated"] == 1] > s["pitch_mm"])


# ----------------------------------------------------------------------------- the job and the sheet

def test_grid_job_files(tmp_path):
    import ezdxf
    from markcal.pipeline.flows.path import read_job
    assert main(["render", "grid-job", "--rows", "9", "--cols", "9", "--field-mm", "110", "--mark", "cross",
                 "--format", "dxf", "--out", str(tmp_path / "d")]) == 0
    doc = ezdxf.readfile(tmp_path / "d" / "grid_job.dxf")
    lines = list(doc.modelspace().query("LWPOLYLINE"))
    assert len(lines) == 162
    pts = np.array([p[:2] for e in lines for p in e.get_points()])
    assert pts.min() == pytest.approx(-56.0) and pts.max() == pytest.approx(56.0)
    assert main(["render", "grid-job", "--mark", "circle", "--format", "json", "--out", str(tmp_path / "j")]) == 0
    job = read_job(str(tmp_path / "j" / "grid_job.json"))
    assert job.job.n == 81
    assert main(["render", "grid-job", "--format", "gcode", "--out", str(tmp_path / "g")]) == 0
    assert (tmp_path / "g" / "grid_job.gcode").read_text().count("M3") == 162
    sheet = (tmp_path / "d" / "measure.csv").read_text().splitlines()
    assert sheet[0] == "id,row,col,x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm"
    assert sheet[1].endswith(",,") and len(sheet) == 82


# ----------------------------------------------------------------------------- bad input

def _fails(capsys, path, out, words, *extra):
    capsys.readouterr()
    assert main(["grid", str(path), "--out", str(out), "--quiet", *extra]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "Traceback" not in err[0], err
    assert any(w in err[0].lower() for w in words), err[0]
    assert not os.path.exists(os.path.join(out, "summary.json"))


def _csv(path, rows):
    path.write_text("x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return path


def _good_rows():
    r = render_grid(0, GridRenderOptions(n_missing=0))
    return [list(c) + list(m) for c, m in zip(r.cmd_mm, r.meas_mm)]


def test_bad_inputs(tmp_path, capsys):
    out = tmp_path / "out"
    rows = _good_rows()
    _fails(capsys, _csv(tmp_path / "few.csv", rows[:8]), out, ["at least 9"])
    line = [[x, 0.0, x + 0.01, 0.02] for x in range(-40, 50, 10)]
    _fails(capsys, _csv(tmp_path / "line.csv", line), out, ["one line"])
    dup = [r[:] for r in rows]
    dup[5][:2] = dup[4][:2]
    _fails(capsys, _csv(tmp_path / "dup.csv", dup), out, ["duplicate"])
    nan = [r[:] for r in rows]
    nan[10][2] = "nan"
    _fails(capsys, _csv(tmp_path / "nan.csv", nan), out, ["line 12", "nan"])
    swapped = [r[:] for r in rows]
    swapped[20][2:], swapped[30][2:] = swapped[30][2:], swapped[20][2:]
    _fails(capsys, _csv(tmp_path / "swap.csv", swapped), out, ["numbering"])
    units = tmp_path / "units.csv"
    units.write_text("x_cmd_units,y_cmd_units,x_meas_mm,y_meas_mm\n"
                     + "".join(f"0x{0x8000 + 4000 * i:04X},{0x8000 + 4000 * j},{i},{j}\n"
                               for i in range(-1, 2) for j in range(-1, 2)))
    _fails(capsys, units, out, ["--units-per-mm"])
    _fails(capsys, tmp_path / "absent.csv", out, ["no such file"])
    capsys.readouterr()
    assert main(["grid", str(_csv(tmp_path / "good.csv", rows)), "--out", str(out), "--cor", str(tmp_path),
                 "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cor names a folder" in err[0], err
    assert not os.path.exists(out / "summary.json")
    sheet = tmp_path / "sheet"
    main(["render", "grid-job", "--out", str(sheet)])
    _fails(capsys, sheet / "measure.csv", out, ["only 0 measured"])


def test_unwritable_cor_is_refused_before_the_fit(tmp_path, capsys, monkeypatch):
    """--cor goes through the same check as --out: a folder it cannot write in fails before any work."""
    from markcal.pipeline.flows import grid as grid_flow
    fits, run_grid = [], grid_flow.run_grid
    monkeypatch.setattr(grid_flow, "run_grid", lambda *a, **k: fits.append(1) or run_grid(*a, **k))
    out = tmp_path / "out"
    bad = "/proc/markcal-no-such/t.cor"                # /proc takes no new folders, even as root
    assert main(["grid", str(_csv(tmp_path / "good.csv", _good_rows())), "--out", str(out), "--cor", bad,
                 "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"markcal: error: {bad}: cannot write here"), err
    assert fits == [] and not out.exists()


def test_nine_marks_are_enough(tmp_path):
    """The smallest grid the issue allows (3 x 3) runs, with fewer folds, and still corrects the true machine."""
    src, truth = _render_cli(tmp_path, "--rows", "3", "--cols", "3", "--missing", "0", "--seed", "2")
    out = tmp_path / "out"
    assert main(["grid", str(src / "measured.csv"), "--out", str(out), "--quiet", "--no-report"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["n_marks"] == 9 and s["folds"] == 4
    from markcal.pipeline.flows.export import load_scan_source
    model = load_scan_source(out)
    half = 0.4 * truth["lens_mm"]
    _, before = correction_residual(_machine(truth), lambda w: w, half, half, 2.0)
    _, after = correction_residual(_machine(truth), lambda w: w + model.offset_mm(w), half, half, 2.0)
    assert _rms(after) < 0.5 * _rms(before)
