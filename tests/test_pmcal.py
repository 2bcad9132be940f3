"""pmcal flow: model, GA, least squares, command generation against the renderer's truth; bad input.

The truth side (``fixtures.pm_session.landing_errors``, ``tip_om``) is the fixture's own physics,
not ``stages/pm_model.py``. Limits are about 1.5-2x the worst measured on these fixed seeds (written
beside each); the goals (landing RMS 0.05 µm, max 0.10 µm, depth 5 nm) stay in the benchmark.
"""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from markcal.fixtures.pm_session import (landing_errors, render_pm_session, sample_true_machine, session_data,
                                        truth_dict)
from markcal.pipeline.cli import main
from markcal.reports.files import read_csv, write_csv
from markcal.stages.pm_fit import fit_lsq, model_from_theta, theta_from_model
from markcal.stages.pm_ga import GAOptions, run_ga
from markcal.stages.pm_model import (PMModel, command_for_targets, gram_schmidt, model_from_dict, model_to_dict,
                                     nonorthogonality_rad, tip_pm)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("pm") / "s"
    assert main(["render", "pmcal", "--seed", "7", "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def calibrated(session, tmp_path_factory):
    out = tmp_path_factory.mktemp("pm") / "o"
    assert main(["pmcal", str(session), "--out", str(out), "--quiet"]) == 0
    return out


def test_triad_projection_is_right_handed_orthonormal():
    rng = np.random.default_rng(0)
    q = gram_schmidt(np.eye(3).ravel() + rng.normal(0, 0.05, (20, 9)))
    assert np.allclose(np.einsum("pji,pjk->pik", q, q), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(q), 1.0)


def test_theta_round_trip_and_dict_round_trip():
    m = sample_true_machine(np.random.default_rng(3))
    m2 = model_from_theta(theta_from_model(m))
    c = np.random.default_rng(1).uniform(-25000, 25000, (50, 3))
    assert np.max(np.abs(tip_pm(m, c) - tip_pm(m2, c))) < 1e-9
    m3 = model_from_dict(json.loads(json.dumps(model_to_dict(m))))
    assert np.max(np.abs(tip_pm(m, c) - tip_pm(m3, c))) < 1e-9


def test_inverse_is_exact_with_strong_straightness():
    """Newton inverse lands to < 1 pm even with 5 µm straightness bows; a linear inverse would not."""
    m = sample_true_machine(np.random.default_rng(5))
    m = PMModel(m.a_axes, m.scale, np.full(6, 5.0), m.o_um, m.r_pose, m.t_um, m.plane)
    xy = np.random.default_rng(2).uniform(-20000, 20000, (100, 2))
    c = command_for_targets(m, xy, 1.0)
    lat, dep = landing_errors(m, xy, 1.0, c)
    assert lat.max() < 1e-6 and np.abs(dep).max() < 1e-6
    c_lin = np.linalg.solve(m.m, ((command_for_targets.__globals__["surface_target_om"](m, xy, 1.0) - m.t_um)
                                  @ m.r_pose - m.o_um).T).T
    lat_lin, _ = landing_errors(m, xy, 1.0, c_lin)
    assert lat_lin.max() > 0.5  # the straightness would be missed by a first-order inverse


def test_ga_deterministic_monotone_and_accurate():
    s = render_pm_session(8)
    d = session_data(s)
    a = run_ga(d, GAOptions(seed=3))
    b = run_ga(d, GAOptions(seed=3))
    assert np.array_equal(a.theta, b.theta) and np.array_equal(a.best_f, b.best_f)
    assert len(a.best_f) == 100 and a.n_evals == 60 + 99 * 58
    assert np.all(np.diff(a.best_f) <= 0)  # elitism
    assert a.best_f[-1] < 0.2 * a.best_f[0]                               # measured 0.134
    xy = np.random.default_rng(4).uniform(-20000, 20000, (100, 2))
    lat, _ = landing_errors(s.model, xy, 0.5, command_for_targets(model_from_theta(a.theta), xy, 0.5))
    assert np.sqrt(np.mean(lat ** 2)) < 0.009 and lat.max() < 0.020        # measured 0.0048 / 0.0114 µm


def test_lsq_parameters_within_goals():
    s = render_pm_session(9)
    r = fit_lsq(session_data(s))
    est, tru = model_to_dict(r.model), truth_dict(s.model)      # truth from the fixture's own conversion
    # measured (seed 9): non-orthogonality 0.27 / 0.35 / 0.73 µrad, plane tilt 0.12 / 0.05 µrad,
    # scale 0.12 / 0.014 / 0.068 ppm, pose rotation 0.35 µrad
    for k in ("nonorth_xy_urad", "nonorth_xz_urad", "nonorth_yz_urad"):
        assert abs(est[k] - tru[k]) < 1.2, k
    for k in ("plane_tilt_x_urad", "plane_tilt_y_urad"):
        assert abs(est[k] - tru[k]) < 0.25, k
    for k in ("scale_x_ppm", "scale_y_ppm", "scale_z_ppm"):
        assert abs(est[k] - tru[k]) < 0.2, k
    assert np.linalg.norm(np.subtract(est["rotvec_urad"], tru["rotvec_urad"])) < 0.6
    # straightness bows, pair by pair (labels as the truth's): measured worst 0.045 µm (y(z))
    assert est["straightness_pairs"] == tru["straightness_pairs"] == ["y(x)", "z(x)", "x(y)", "z(y)", "x(z)", "y(z)"]
    assert np.abs(np.subtract(est["straightness_um"], tru["straightness_um"])).max() < 0.08
    # the true machine has ~100 µrad non-orthogonality: the fit must have found it, not ideal axes
    assert np.max(np.abs(nonorthogonality_rad(s.model.a_axes))) > 2e-5


def test_lsq_exact_on_noise_free_session_with_turned_axes():
    """Noise-free session of a machine whose stage triad is turned 0.3 rad in the PM frame, with scale
    errors of hundreds of ppm: the model is exact, so the fit must be (measured: < 1e-5 ppm, µrad).
    Scaling the rows of the axes matrix instead of its columns is invisible on near-identity axes and
    off by 53 ppm here."""
    from scipy.spatial.transform import Rotation
    from markcal.fixtures.pm_session import SessionOptions
    base = sample_true_machine(np.random.default_rng([3, 4]))
    q = Rotation.from_rotvec([0.02, -0.03, 0.3]).as_matrix()
    m = PMModel(q @ base.a_axes, np.array([3e-4, -2e-4, 1e-4]), base.k_um, base.o_um, base.r_pose, base.t_um,
                base.plane)
    s = render_pm_session(5, SessionOptions(noise_um=1e-9, probe_noise_um=1e-9, drift_noise_um=1e-9), model=m)
    est, tru = model_to_dict(fit_lsq(session_data(s)).model), truth_dict(m)
    for k in ("scale_x_ppm", "scale_y_ppm", "scale_z_ppm", "nonorth_xy_urad", "nonorth_xz_urad", "nonorth_yz_urad",
              "plane_tilt_x_urad", "plane_tilt_y_urad"):
        assert abs(est[k] - tru[k]) < 0.01, k


def test_flow_outputs_and_truth(calibrated):
    s = json.load(open(calibrated / "summary.json"))
    cal = json.load(open(calibrated / "calibration.json"))
    for k in ("method", "seed", "scale_x_ppm", "nonorth_xy_urad", "R", "R_angles_urad", "T_um", "plane_a",
              "plane_b", "plane_c_um", "normal", "E_ortho", "E_pose", "E_flat", "E_dyn", "F"):
        assert k in cal, k
    assert cal["method"] == "ga+lsq" and s["method"] == "ga+lsq"
    # measured (seed 7): landing RMS 0.0038, max 0.0069, depth 0.0011 µm; errors: non-orthogonality
    # 0.044 / 0.30 / 0.039 µrad, scale 0.14 / 0.057 / 0.34 ppm, tilt 0.003 / 0.078 µrad, pose 0.24 µrad
    assert s["landing_rms_um"] <= 0.007 and s["landing_max_um"] <= 0.012 and s["depth_err_max_um"] <= 0.002
    assert abs(s["err_nonorth_xy_urad"]) < 0.09 and abs(s["err_scale_x_ppm"]) < 0.25 and s["err_pose_rot_urad"] < 0.4
    for k, lim in (("nonorth_xz_urad", 0.5), ("nonorth_yz_urad", 0.08), ("scale_y_ppm", 0.1), ("scale_z_ppm", 0.55),
                   ("plane_tilt_x_urad", 0.01), ("plane_tilt_y_urad", 0.13)):
        assert abs(s["err_" + k]) < lim, k
    m = read_csv(calibrated / "methods.csv")
    assert list(m["method"]) == ["ga", "lsq", "ga+lsq"]
    assert len(read_csv(calibrated / "ga_convergence.csv")["best_F"]) == 100
    html = open(calibrated / "report.html", encoding="utf-8").read()
    assert "<img" in html and "http://" not in html and "https://" not in html


def test_command_cli_lands_on_true_machine(session, calibrated, tmp_path):
    truth = model_from_dict(json.load(open(session / "truth.json")))
    xy = np.random.default_rng(11).uniform(-20000, 20000, (100, 2))
    write_csv(tmp_path / "targets.csv", {"x_um": xy[:, 0], "y_um": xy[:, 1]})
    out = tmp_path / "commands.csv"
    assert main(["pmcal", "command", str(calibrated / "calibration.json"), str(tmp_path / "targets.csv"),
                 "--depth-um", "0.8", "--out", str(out), "--quiet"]) == 0
    c = read_csv(out)
    assert list(c) == ["x_um", "y_um", "x_cmd_um", "y_cmd_um", "z_cmd_um"]
    lat, dep = landing_errors(truth, xy, 0.8, np.column_stack([c["x_cmd_um"], c["y_cmd_um"], c["z_cmd_um"]]))
    assert np.sqrt(np.mean(lat ** 2)) <= 0.007 and lat.max() <= 0.012      # measured 0.0037 / 0.0065 µm
    assert np.abs(dep).max() <= 0.002                                      # measured 0.00095 µm


def _bad(capsys, argv):
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ")
    return err[0]


def _copy(session, tmp_path):
    d = tmp_path / "s"
    shutil.copytree(session, d)
    return d


def test_bad_sessions(session, tmp_path, capsys):
    out = str(tmp_path / "o")
    d = _copy(session, tmp_path)
    os.remove(d / "probe.csv")
    assert "probe.csv" in _bad(capsys, ["pmcal", str(d), "--out", out, "--quiet"])

    d = _copy(session, tmp_path / "b")
    t = read_csv(d / "probe.csv")
    x = np.linspace(-20000, 20000, len(t["x_um"]))
    write_csv(d / "probe.csv", {"x_um": x, "y_um": 2 * x + 5, "z_um": t["z_um"]})
    msg = _bad(capsys, ["pmcal", str(d), "--out", out, "--quiet"])
    assert "probe.csv" in msg and "collinear" in msg

    d = _copy(session, tmp_path / "c")
    t = read_csv(d / "pose.csv")
    t["x_om_um"][3], t["x_om_um"][10] = t["x_om_um"][10], t["x_om_um"][3]
    write_csv(d / "pose.csv", t)
    msg = _bad(capsys, ["pmcal", str(d), "--out", out, "--quiet"])
    assert "pose.csv" in msg and "mismatched" in msg

    d = _copy(session, tmp_path / "d")
    text = open(d / "pose.csv").read().splitlines()
    cells = text[5].split(",")
    cells[4] = "nan"
    text[5] = ",".join(cells)
    open(d / "pose.csv", "w").write("\n".join(text) + "\n")
    msg = _bad(capsys, ["pmcal", str(d), "--out", out, "--quiet"])
    assert "pose.csv" in msg and "line 6" in msg

    d = _copy(session, tmp_path / "e")
    t = read_csv(d / "drift.csv")
    t["t_min"][4] = 100.0
    write_csv(d / "drift.csv", t)
    msg = _bad(capsys, ["pmcal", str(d), "--out", out, "--quiet"])
    assert "drift.csv" in msg and "time order" in msg

    d = _copy(session, tmp_path / "f")
    os.remove(d / "pose.csv")
    os.mkdir(d / "om")
    assert "marks.csv" in _bad(capsys, ["pmcal", str(d), "--out", out, "--quiet"])

    assert "no such" in _bad(capsys, ["pmcal", str(tmp_path / "nowhere"), "--out", out, "--quiet"])
    assert "depth-um" in _bad(capsys, ["pmcal", "command", "a.json", "b.csv", "--out", out, "--quiet"])
    assert "no such file" in _bad(capsys, ["pmcal", "command", str(tmp_path / "a.json"), "b.csv",
                                           "--depth-um", "1", "--out", out, "--quiet"])


def test_command_checks_the_depth_once_before_its_progress_line(tmp_path, capsys, monkeypatch):
    """``pmcal command --depth-um nan``: refused by one check, one line on stderr (no progress line first)."""
    from markcal.pipeline.flows import pmcal as pmcal_flow
    calls, check = [], pmcal_flow.check_depth_um
    monkeypatch.setattr(pmcal_flow, "check_depth_um", lambda d: calls.append(d) or check(d))
    out = tmp_path / "c.csv"
    assert main(["pmcal", "command", "a.json", "b.csv", "--depth-um", "nan", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: --depth-um must be a finite number"), err
    assert len(calls) == 1 and not out.exists()
    calls.clear()                                          # a good depth: checked once, then the missing file
    assert main(["pmcal", "command", str(tmp_path / "a.json"), "b.csv", "--depth-um", "1", "--out", str(out),
                 "--quiet"]) == 1
    assert calls == [1.0] and "no such" in capsys.readouterr().err


def test_small_probe_grid_warns_but_runs(session, tmp_path):
    d = _copy(session, tmp_path)
    t = read_csv(d / "probe.csv")
    keep = np.isin(t["x_um"], np.unique(t["x_um"])[[0, 2, 4]]) & np.isin(t["y_um"], np.unique(t["y_um"])[[0, 2, 4]])
    write_csv(d / "probe.csv", {k: np.asarray(v)[keep] for k, v in t.items()})
    out = tmp_path / "o"
    assert main(["pmcal", str(d), "--out", str(out), "--method", "lsq", "--no-report", "--quiet"]) == 0
    s = json.load(open(out / "summary.json"))
    assert s["n_warnings"] >= 1 and s["n_probe_points"] == 9 and s["method"] == "lsq"
    assert s["landing_rms_um"] <= 0.007                                    # measured 0.0038 µm


# ----------------------------------------------------------------------------- om/ + marks.csv variant

@pytest.fixture(scope="module")
def om_session(tmp_path_factory):
    """Seed 7 with a 4 x 4 pose grid, pose pairs as OM micrographs (om/ + marks.csv)."""
    out = tmp_path_factory.mktemp("pm") / "om"
    assert main(["render", "pmcal", "--seed", "7", "--pose-grid", "4", "--om-images", "--out", str(out),
                 "--quiet"]) == 0
    return out


def test_om_images_measured_to_nanometres():
    """image -> centre: noise-free field positions, so x_om - truth is the OM measurement error alone."""
    from markcal.fixtures.indent_maps import tiff_bytes
    from markcal.fixtures.pm_session import SessionOptions, render_om_marks
    from markcal.pipeline.flows.pmcal import read_om_marks
    from markcal.fixtures.pm_session import tip_om
    import tempfile

    s = render_pm_session(7, SessionOptions(pose_grid=4))
    om = render_om_marks(s, noise_um=0.0)
    with tempfile.TemporaryDirectory() as d:
        os.mkdir(os.path.join(d, "om"))
        for name, img in zip(om.marks["image"], om.images):
            open(os.path.join(d, "om", name), "wb").write(tiff_bytes(img, om.pixel_um))
        write_csv(os.path.join(d, "marks.csv"), om.marks)
        c_pose, x_om, lines, warnings = read_om_marks(d)
    assert len(c_pose) == 16 and list(lines) == list(range(2, 18)) and not any("dropped" in w for w in warnings)
    true = tip_om(s.model, np.column_stack([s.pose["x_pm_um"], s.pose["y_pm_um"], s.pose["z_pm_um"]]))
    err = x_om[:, :2] - true[:, :2]
    # OM centring noise ~3 nm (indents flow goal); the shared-optics fit gives ~1.5 nm here
    assert np.sqrt(np.mean(err ** 2)) < 0.0025 and np.abs(err).max() < 0.005     # measured 0.0014 / 0.0030 µm


def test_om_session_calibrates_like_pose_csv(om_session, tmp_path):
    assert not (om_session / "pose.csv").exists() and len(os.listdir(om_session / "om")) == 16
    assert list(read_csv(om_session / "marks.csv")) == ["x_pm_um", "y_pm_um", "z_pm_um", "image", "x_field_um",
                                                        "y_field_um", "z_om_um"]
    out = tmp_path / "o"
    assert main(["pmcal", str(om_session), "--out", str(out), "--no-report", "--quiet"]) == 0
    s = json.load(open(out / "summary.json"))
    assert s["n_pose_pairs"] == 16 and s["pose_source"] == "marks.csv"
    # measured: pose 0.57 µrad, landing RMS 0.0051, max 0.0087, depth 0.0036 µm, non-orth. 0.36 µrad, scale 0.03 ppm
    assert s["err_pose_rot_urad"] < 1.0
    assert s["landing_rms_um"] <= 0.009 and s["landing_max_um"] <= 0.015 and s["depth_err_max_um"] <= 0.006
    assert abs(s["err_nonorth_xy_urad"]) < 0.6 and abs(s["err_scale_x_ppm"]) < 0.06


def test_om_session_drops_unfound_mark_and_needs_three(om_session, tmp_path, capsys):
    from markcal.fixtures.indent_maps import tiff_bytes

    d = _copy(om_session, tmp_path)
    blank = np.random.default_rng(0).normal(30000, 300, (128, 128)).astype(np.uint16)
    open(d / "om" / "mark_005.tif", "wb").write(tiff_bytes(blank, 0.1))
    out = tmp_path / "o"
    assert main(["pmcal", str(d), "--out", str(out), "--method", "lsq", "--no-report", "--quiet"]) == 0
    s = json.load(open(out / "summary.json"))
    assert s["n_pose_pairs"] == 15 and s["n_warnings"] >= 1 and s["landing_rms_um"] <= 0.009   # measured 0.0048
    capsys.readouterr()
    assert main(["pmcal", str(d), "--out", str(out), "--method", "lsq", "--no-report"]) == 0
    assert "marks.csv line 7 (mark_005.tif): no mark found; pair dropped" in capsys.readouterr().err

    for i in range(2, 16):
        open(d / "om" / f"mark_{i:03d}.tif", "wb").write(tiff_bytes(blank, 0.1))
    msg = _bad(capsys, ["pmcal", str(d), "--out", str(out), "--quiet"])
    assert "only 2 of 16" in msg and "om" in msg

    d = _copy(om_session, tmp_path / "b")
    os.remove(d / "om" / "mark_003.tif")
    msg = _bad(capsys, ["pmcal", str(d), "--out", str(out), "--quiet"])
    assert "mark_003.tif" in msg and "no such file" in msg
