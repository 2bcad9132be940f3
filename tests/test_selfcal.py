"""Selfcal flow (paper 001) against the renderer's truth, and its bad input."""
import csv
import json
import os

import numpy as np
import pytest

from markcal.fixtures.selfcal_stage import SelfcalOptions, render_selfcal
from markcal.pipeline.cli import main
from markcal.stages.errors import MarkcalError
from markcal.stages.selfcal import GridViews, solve_selfcal


def _errors(r, sol):
    N = r.setup.n
    ex = np.asarray(r.truth["gx_um"]).reshape(N, N) - sol.gx_um
    ey = np.asarray(r.truth["gy_um"]).reshape(N, N) - sol.gy_um
    et = np.asarray(r.truth["gtheta_deg"]) - sol.gtheta_deg if sol.gtheta_deg.size else None
    return ex, ey, et


def test_noise_free_map_is_exact():
    r = render_selfcal(41, SelfcalOptions(noise_xy_um=0.0, noise_theta_deg=0.0))
    sol = solve_selfcal(r.setup, r.grid, r.angle)
    ex, ey, et = _errors(r, sol)
    assert np.abs(np.r_[ex.ravel(), ey.ravel()]).max() < 1e-9          # µm: rounding only
    assert np.abs(et).max() < 1e-10                                    # deg
    assert sol.nonorthogonality_urad == pytest.approx(r.truth["nonorthogonality_urad"], abs=1e-8)
    assert sol.scale_difference_ppm == pytest.approx(r.truth["scale_difference_ppm"], abs=1e-8)
    for v in range(4):
        assert sol.misalignment[f"view{v}_rotation_deg"] == pytest.approx(
            r.truth["misalignment_rotation_deg"][v], abs=1e-10)


@pytest.mark.parametrize("noise_xy_um,noise_theta_deg", [(0.02, 0.001), (0.002, 0.0001)])
def test_accuracy_at_paper_noise_levels(noise_xy_um, noise_theta_deg):
    # issue 5: std of E_Gx, E_Gy <= the xy noise and of E_Gtheta <= the angle noise (paper 11 x 11, 15 deg).
    # The std of 121 errors scatters ~6 % around the LSQ bound (~0.9 x noise), so one seed may touch the
    # goal: each seed is held to goal + 10 % and the mean over seeds to the goal itself.
    sds, sdt = [], []
    for seed in (11, 12, 13):
        r = render_selfcal(seed, SelfcalOptions(noise_xy_um=noise_xy_um, noise_theta_deg=noise_theta_deg))
        sol = solve_selfcal(r.setup, r.grid, r.angle)
        ex, ey, et = _errors(r, sol)
        sds += [ex.std(ddof=1), ey.std(ddof=1)]
        sdt.append(et.std(ddof=1))
        # the estimate is as good as the covariance bound says (not worse than 1.3 x)
        bound = np.sqrt(np.mean(np.r_[sol.predicted_sd_gx_um.ravel(), sol.predicted_sd_gy_um.ravel()] ** 2))
        assert 0.85 < np.sqrt(np.mean([ex.var(), ey.var()])) / bound < 1.3     # measured 1.055-1.129
        assert sol.sigma_xy_um == pytest.approx(noise_xy_um, rel=0.2)
        # limits at ~1.5x the worst measured on seeds 11-13 (both noise levels, in units of the noise):
        # max |E_G| 3.27 x noise_xy, max |E_Gθ| 2.69 x noise_θ, |ΔO| 1.71 µrad per µm of noise
        # (0.034 µrad at 0.02 µm), |ΔR| 1.03 ppm per µm (0.0207 ppm): O, R limits in µrad, ppm per µm
        assert max(np.abs(ex).max(), np.abs(ey).max()) <= 5.0 * noise_xy_um
        assert np.abs(et).max() <= 4.0 * noise_theta_deg
        assert abs(sol.nonorthogonality_urad - r.truth["nonorthogonality_urad"]) <= 2.6 * noise_xy_um
        assert abs(sol.scale_difference_ppm - r.truth["scale_difference_ppm"]) <= 1.6 * noise_xy_um
    assert max(sds) <= 1.1 * noise_xy_um and np.mean(sds) <= noise_xy_um
    assert max(sdt) <= 1.1 * noise_theta_deg and np.mean(sdt) <= noise_theta_deg


@pytest.mark.parametrize("seed,noise_xy_um,noise_theta_deg", [(21, 0.02, 0.0001), (22, 0.05, 0.00005)])
def test_second_weighted_pass_when_noise_levels_differ(seed, noise_xy_um, noise_theta_deg):
    """Design claim: the second pass, weighted by the estimated noise of each group, is what makes the
    reported bound right when the xy and θ noise levels differ (here 0.02 µm vs 0.0017 mrad, 12x).

    Measured (seeds 21, 22): RMS predicted sd of Gθ 0.97-1.42 x noise_θ with the weighted pass,
    10-55 x with unit weights only; the estimate itself changes by under 3 % (the φ and the eq. 9 rows
    are all the groups share), so the claim is tested on the bound and the noise estimate."""
    r = render_selfcal(seed, SelfcalOptions(noise_xy_um=noise_xy_um, noise_theta_deg=noise_theta_deg))
    sol = solve_selfcal(r.setup, r.grid, r.angle)
    _, _, et = _errors(r, sol)
    pred = np.sqrt(np.mean(sol.predicted_sd_gtheta_deg ** 2))
    assert 0.6 * noise_theta_deg < pred < 2.5 * noise_theta_deg
    assert np.sqrt(np.mean(et ** 2)) < 2.0 * pred                    # the bound covers the realised error
    assert sol.sigma_theta_deg == pytest.approx(noise_theta_deg, rel=0.2)
    assert sol.sigma_xy_um == pytest.approx(noise_xy_um, rel=0.2)


def test_missing_marks_are_skipped_and_reported():
    r = render_selfcal(14, SelfcalOptions(missing_marks=6))
    sol = solve_selfcal(r.setup, r.grid, r.angle)
    ex, ey, _ = _errors(r, sol)
    assert sum("not measured" in n for n in sol.notes) >= 1
    assert max(ex.std(ddof=1), ey.std(ddof=1)) <= 0.025      # 6 of 352 readings fewer; measured 0.0180


def test_xy_only_session():
    r = render_selfcal(15, SelfcalOptions())
    sol = solve_selfcal(r.setup, r.grid, None)
    ex, ey, _ = _errors(r, sol)
    assert max(ex.std(ddof=1), ey.std(ddof=1)) <= 0.022      # measured 0.0182 (the goal is the noise, 0.02)
    assert sol.gtheta_deg.size == 0


def test_a_site_seen_in_no_view_is_refused():
    r = render_selfcal(16, SelfcalOptions())
    g = r.grid
    # site (m=5, n=0) holds mark (5, 0) in view 0, mark (0, -5) in view 1 and mark (4, 0) in view 3
    drop = (((g.view == 0) & (g.m == 5) & (g.n == 0)) | ((g.view == 1) & (g.m == 0) & (g.n == -5))
            | ((g.view == 3) & (g.m == 4) & (g.n == 0)))
    g2 = GridViews(*(np.asarray(a)[~drop] for a in (g.view, g.m, g.n, g.vx_um, g.vy_um)))
    with pytest.raises(MarkcalError, match=r"site \(m=5, n=0\) is not measured"):
        solve_selfcal(r.setup, g2, r.angle)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("selfcal") / "session")
    assert main(["render", "selfcal", "--seed", "17", "--out", out, "--quiet"]) == 0
    return out


def test_cli_outputs(session, tmp_path):
    out = str(tmp_path / "result")
    assert main(["selfcal", session, "--out", out, "--quiet"]) == 0
    for name in ("stage_error.csv", "stage_error_theta.csv", "correction_grid.csv", "summary.json", "report.html"):
        assert os.path.getsize(os.path.join(out, name)) > 0
    with open(os.path.join(out, "stage_error.csv")) as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["m", "n", "x_mm", "y_mm", "gx_um", "gy_um"] and len(rows) == 121
    truth = json.load(open(os.path.join(session, "truth.json")))
    gx = np.array([float(r["gx_um"]) for r in rows])
    assert np.std(gx - np.array(truth["gx_um"])) < 0.022       # rows in the truth's (m, n) order
    with open(os.path.join(out, "correction_grid.csv")) as fh:
        corr = list(csv.DictReader(fh))
    assert list(corr[0]) == ["x_mm", "y_mm", "dx_um", "dy_um"]
    assert [float(c["dx_um"]) for c in corr] == [float(r["gx_um"]) for r in rows]   # command = p + G(p)
    with open(os.path.join(out, "stage_error_theta.csv")) as fh:
        th = list(csv.DictReader(fh))
    assert list(th[0]) == ["k", "theta_deg", "gtheta_deg"] and float(th[1]["theta_deg"]) == 15.0
    s = json.load(open(os.path.join(out, "summary.json")))
    for key in ("nonorthogonality_urad", "scale_difference_ppm", "view0_rotation_deg", "view3_offset_x_um",
                "residual_rms_xy_um", "condition_1norm", "predicted_sd_gxy_um", "error_sd_gx_um"):
        assert key in s
    assert s["nonorthogonality_urad"] == pytest.approx(truth["nonorthogonality_urad"], abs=0.06)   # measured 0.038
    html = open(os.path.join(out, "report.html")).read()
    assert "Tables 1–2" in html and html.count("data:image/png;base64,") == 3


def _copy(session, tmp_path, edit=None, name=None):
    import shutil
    d = str(tmp_path / "bad")
    shutil.copytree(session, d)
    if edit:
        p = os.path.join(d, name)
        with open(p) as fh:
            text = fh.read()
        with open(p, "w") as fh:
            fh.write(edit(text))
    return d


def _drop_view(v):
    return lambda t: "\n".join(l for l in t.splitlines() if not l.startswith(f"{v},")) + "\n"


@pytest.mark.parametrize("name,edit,message", [
    ("grid_views.csv", _drop_view(3), "grid views [3] missing"),
    ("angle_views.csv", _drop_view(2), "angle views [2] missing"),
    ("setup.toml", lambda t: t.replace("n = 11", "n = 10"), "n must be odd"),
    ("setup.toml", lambda t: t.replace("k = 24", "k = 26"), "k must be a multiple of 4"),
    ("setup.toml", lambda t: t + "colour = 'red'\n", "unknown key 'colour'"),
    ("grid_views.csv", lambda t: t + t.splitlines()[5] + "\n", "duplicate rows for view=0"),
    ("grid_views.csv", lambda t: t.replace(t.splitlines()[3].split(",")[3], "nan", 1), "line 4: vx_um is nan"),
    ("grid_views.csv", lambda t: t.replace(",vy_um", ",vy"), "missing column(s) vy_um"),
    ("angle_views.csv", lambda t: t + "0,99,0.001\n", "k = 99 is outside 0..23"),
])
def test_bad_input(session, tmp_path, capsys, name, edit, message):
    d = _copy(session, tmp_path, edit, name)
    assert main(["selfcal", d, "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("markcal: error:") and message in err and len(err.splitlines()) == 1
    assert not os.path.exists(tmp_path / "o" / "summary.json")


def test_missing_session_files(tmp_path, capsys):
    assert main(["selfcal", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "not a session folder" in capsys.readouterr().err
    os.makedirs(tmp_path / "empty")
    assert main(["selfcal", str(tmp_path / "empty"), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "no such setup file" in capsys.readouterr().err
