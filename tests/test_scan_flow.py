"""The scan flow end to end on small renders, and the calibrate -> correct -> re-mark loop."""
import dataclasses
import json
import os
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from conftest import SMALL, save_render
from markcal.fixtures.gls import correction_residual, sample_true_galvo
from markcal.fixtures.scan_plate import ScanOptions, render_scan
from markcal.pipeline.flows.scan import run_scan
from markcal.reports.files import read_csv
from markcal.stages.deviation import GridCorrection

# issue 2 goals: centres RMS <= 0.015 / max <= 0.06 mm; loop residual RMS <= 0.03 / max <= 0.10 mm
CENTRE_RMS_MM, CENTRE_MAX_MM = 0.015, 0.06
LOOP_RMS_MM, LOOP_MAX_MM = 0.03, 0.10


def _centre_errors(result, render):
    t = render.truth["fiducials"]
    ids = result.fiducials["id"]
    true = np.column_stack([t["x_scanner_mm"], t["y_scanner_mm"], t["z_scanner_mm"]])[ids]
    got = np.column_stack([result.fiducials[k] for k in ("x_scanner_mm", "y_scanner_mm", "z_scanner_mm")])
    return np.linalg.norm(got - true, axis=1)


def _machine(render):
    from markcal.fixtures.scan_plate import machine_from_truth
    return machine_from_truth(render.truth)


def test_flow_finds_indexes_and_measures(small_render, small_result):
    res, r = small_result, small_render
    assert res.summary["n_detected"] == 47 and res.missing_ids == r.truth["hidden_ids"]
    # indexing: each detected fiducial is the true one with that id (checked through its true centre)
    err = _centre_errors(res, r)
    assert np.sqrt(np.mean(err ** 2)) <= CENTRE_RMS_MM and err.max() <= CENTRE_MAX_MM
    # deviations: the measured field equals the true field up to a rigid motion
    t = r.truth["fiducials"]
    ids = res.fiducials["id"]
    true_p = np.column_stack([t["x_true_mm"], t["y_true_mm"]])[ids]
    meas_p = np.column_stack([res.fiducials["x_meas_mm"], res.fiducials["y_meas_mm"]])
    _, resid = _rigid_residual(true_p, meas_p)
    assert np.sqrt(np.mean(np.sum(resid ** 2, 1))) <= CENTRE_RMS_MM
    assert res.summary["plate_tilt_deg"] == pytest.approx(r.truth["plate_tilt_deg"], abs=0.01)
    assert res.summary["in_plane_rotation_deg"] == pytest.approx(r.truth["in_plane_rotation_deg"], abs=0.1)


def _rigid_residual(src, dst):
    from markcal.stages.register import rigid_fit
    tf = rigid_fit(src, dst)
    return tf, tf.apply(src) - dst


def test_correction_grid_closes_the_loop(small_render, small_result):
    res = small_result
    grid = GridCorrection.from_nodes(res.grid_xy_mm, res.grid_dxy_mm)
    hx, hy = res.spec.half_extent_mm
    _, resid = correction_residual(_machine(small_render), grid.command, hx, hy, 1.0)
    mag = np.hypot(*resid.T)
    assert np.sqrt(np.mean(mag ** 2)) <= LOOP_RMS_MM and mag.max() <= LOOP_MAX_MM
    _, raw = correction_residual(_machine(small_render), lambda q: q, hx, hy, 1.0)
    assert np.sqrt(np.mean(np.sum(raw ** 2, 1))) > 5 * np.sqrt(np.mean(mag ** 2))


@pytest.mark.parametrize("conv", ["range"])
def test_z_convention_does_not_change_the_answer(conv, small_render, small_result, tmp_path):
    r2 = render_scan(101, SMALL, ScanOptions(n_contaminated=1, z_convention=conv))
    cloud, _ = save_render(r2, str(tmp_path))
    res2 = run_scan(cloud, SMALL)
    a, b = small_result.fiducials, res2.fiducials
    assert np.array_equal(a["id"], b["id"])
    assert np.abs(a["dx_mm"] - b["dx_mm"]).max() < 0.02
    assert np.abs(a["dy_mm"] - b["dy_mm"]).max() < 0.02


def test_validation_plate_shows_the_post_calibration_state(small_render, small_result, tmp_path):
    grid = GridCorrection.from_nodes(small_result.grid_xy_mm, small_result.grid_dxy_mm)
    val = render_scan(202, SMALL, ScanOptions(z_convention="height"), machine=_machine(small_render),
                      correction=grid.command)
    cloud, _ = save_render(val, str(tmp_path))
    res = run_scan(cloud, SMALL)
    assert res.summary["n_detected"] == len(SMALL.marked_ids)
    assert res.summary["rms_mm"] <= LOOP_RMS_MM and res.summary["max_mm"] <= LOOP_MAX_MM
    assert small_result.summary["rms_mm"] > 5 * res.summary["rms_mm"]


def test_purpose_decides_the_default_verdict(small_render, small_result, tmp_path):
    """An uncorrected plate is judged on what the correction achieves as a calibration plate, on its deviation
    as a validation plate (exit 4); a plate re-marked through the correction passes, its purpose from the spec."""
    from markcal.fixtures.scan_plate import save_scan
    from markcal.pipeline.cli import build_parser, main
    save_scan(tmp_path / "cal", small_render, formats=("npy",), truth=False)
    cal = ["scan", str(tmp_path / "cal" / "cloud.npy"), "--plate", str(tmp_path / "cal" / "plate.toml"), "--quiet",
           "--no-report"]
    # one of 48 marks lies under dirt: a calibration plate must have every mark (exit 4) unless told otherwise
    assert main([*cal, "--out", str(tmp_path / "c")]) == 4
    c = json.loads((tmp_path / "c" / "summary.json").read_text())
    assert c["kind"] == "calibration" and c["failed_checks"] == "n_missing 1 > 0" and c["rms_mm"] > 0.2
    assert main([*cal[:-1], "--out", str(tmp_path / "c1"), "--tol", "n_missing<=1"]) == 0
    c1 = json.loads((tmp_path / "c1" / "summary.json").read_text())
    assert c1["verdict"] == "pass" and "predicted_residual_rms_mm <= 0.071" in c1["checks"]
    html = (tmp_path / "c1" / "report.html").read_text()
    assert ">PASS<" in html[:html.index("<h2")] and "predicted residual RMS after correction" in html
    assert main([*cal, "--out", str(tmp_path / "v"), "--purpose", "validation"]) == 4
    v = json.loads((tmp_path / "v" / "summary.json").read_text())
    assert v["verdict"] == "fail" and v["failed_checks"].startswith("rms_mm ") and "; max_mm " in v["failed_checks"]
    assert build_parser().parse_args([*cal, "--out", "x", "--validation"]).purpose == "validation"   # old spelling
    grid = GridCorrection.from_nodes(small_result.grid_xy_mm, small_result.grid_dxy_mm)
    val = render_scan(202, dataclasses.replace(SMALL, purpose="validation"), ScanOptions(z_convention="height"),
                      machine=_machine(small_render), correction=grid.command)
    save_scan(tmp_path / "val", val, formats=("npy",), truth=False)
    assert 'purpose = "validation"' in (tmp_path / "val" / "plate.toml").read_text()
    assert main(["scan", str(tmp_path / "val" / "cloud.npy"), "--plate", str(tmp_path / "val" / "plate.toml"),
                 "--out", str(tmp_path / "vv"), "--quiet", "--no-report"]) == 0
    vv = json.loads((tmp_path / "vv" / "summary.json").read_text())
    assert vv["kind"] == "validation" and vv["verdict"] == "pass" and vv["checks"] == "rms_mm <= 0.071; max_mm <= 0.252"


def test_deterministic(small_files, small_result):
    again = run_scan(small_files[0], SMALL)
    assert np.array_equal(again.grid_dxy_mm, small_result.grid_dxy_mm)
    assert np.array_equal(again.fiducials["x_meas_mm"], small_result.fiducials["x_meas_mm"])


def test_cli_render_and_scan_write_documented_outputs(tmp_path):
    exe = [sys.executable, "-m", "markcal.pipeline.cli"]
    d = tmp_path / "plate"
    subprocess.run(exe + ["render", "scan", "--seed", "5", "--rows", "5", "--cols", "5", "--out", str(d),
                          "--quiet"], check=True, capture_output=True)
    assert {"cloud.ply", "cloud.npy", "plate.toml", "truth.json"} <= set(os.listdir(d))
    out = tmp_path / "out"
    p = subprocess.run(exe + ["scan", str(d / "cloud.ply"), "--plate", str(d / "plate.toml"), "--out", str(out)],
                       capture_output=True, text=True)
    s = json.loads((out / "summary.json").read_text())
    # a calibration plate (the default purpose): its uncorrected deviation (0.23 mm RMS) is what it measures;
    # it is judged on what the correction achieves, so it passes (exit 0)
    assert s["kind"] == "calibration" and s["rms_mm"] > 0.1
    assert p.returncode == 0 and s["verdict"] == "pass", p.stderr
    assert s["checks"] == "predicted_residual_rms_mm <= 0.071; cv_rmse_mm <= 0.047; n_missing <= 0"
    assert p.stdout.strip().endswith("report.html") and "fiducials" in p.stderr
    # the renderer leaves site 0,1 unmarked by default, so the plate's orientation is known
    assert "orientation_mark = [0, 1]" in (d / "plate.toml").read_text()
    assert s["orientation_method"].startswith("orientation mark") and s["n_expected"] == 24
    fid = read_csv(out / "fiducials.csv")
    for col in ("id", "row", "col", "x_nom_mm", "y_nom_mm", "x_meas_mm", "y_meas_mm", "dx_mm", "dy_mm"):
        assert col in fid
    assert np.allclose(fid["dx_mm"], fid["x_nom_mm"] - fid["x_meas_mm"], atol=1e-12)
    grid = read_csv(out / "correction_grid.csv")
    assert list(grid) == ["x_mm", "y_mm", "dx_mm", "dy_mm"]
    assert np.allclose(np.unique(np.diff(np.unique(grid["x_mm"]))), 1.0)
    assert grid["x_mm"].max() >= 2 * 10.555555 - 1e-9
    tg = read_csv(out / "corrected_targets.csv")
    assert {"x_cmd_mm", "y_cmd_mm", "alpha_x_deg", "alpha_y_deg", "dfr_mm"} <= set(tg)
    # mirror angles and focus shift by the paper's eqs. 3-5 written out here (mechanical angle = half the
    # optical one; the Y mirror's lever is e plus the X mirror's slant range), not by stages/galvo.py
    plate = tomllib.loads((d / "plate.toml").read_text())
    d_mm, e_mm = float(plate["galvo"]["d_mm"]), float(plate["galvo"]["e_mm"])
    x, y = np.asarray(tg["x_cmd_mm"]), np.asarray(tg["y_cmd_mm"])
    lever = e_mm + np.sqrt(d_mm ** 2 + x ** 2)
    assert np.allclose(tg["alpha_x_deg"], np.degrees(np.arctan(x / d_mm)) / 2, atol=1e-9)
    assert np.allclose(tg["alpha_y_deg"], np.degrees(np.arctan(y / lever)) / 2, atol=1e-9)
    assert np.allclose(tg["dfr_mm"], np.sqrt(lever ** 2 + y ** 2) - (e_mm + d_mm), atol=1e-9)
    assert np.all(tg["dfr_mm"] >= 0) and np.any(tg["dfr_mm"] > 0.01)     # off-axis marks lie further away
    s = json.loads((out / "summary.json").read_text())
    for k in ("n_expected", "n_detected", "rms_mm", "max_mm", "rms_x_mm", "rms_y_mm", "cv_rmse_mm",
              "n_neurons", "plate_tilt_deg", "runtime_s"):
        assert k in s
    assert s["n_expected"] == 24 and s["n_detected"] == 24
    from markcal.pipeline.tables import read_rbf_model as load_model
    m = load_model(out / "model.json")
    g = np.column_stack([grid["x_mm"], grid["y_mm"]])
    assert np.allclose(m(g), np.column_stack([grid["dx_mm"], grid["dy_mm"]]), atol=1e-12)
    html = (out / "report.html").read_text()
    assert "<html" in html.lower() and "data:image/png;base64" in html
