"""Servo flow (paper 003): plant, controllers, eq. 24, metrics, flow goals, traces and bad input."""
import json

import numpy as np
import pytest

from markcal.fixtures.servo_trace import TraceOptions, render_servo_trace
from markcal.pipeline.cli import main
from markcal.pipeline.flows.servo import ServoConfig, run_servo
from markcal.stages.servo_cases import PAPER_TABLE2, find_run
from markcal.stages.servo_reading import NAMED_READINGS
from markcal.reports.files import read_csv, write_csv
from markcal.stages.servo_control import (PIDGains, RepetitiveParams, check_rc_stability,
                                          tracking_differentiator)
from markcal.stages.servo_plant import PlantParams, discretise
from markcal.stages.servo_profile import s_curve, sinusoid
from markcal.stages.servo_sim import CCA_TRACK, simulate, step_metrics

COLUMNS = "case,controller,amplitude_mm,frequency_hz,settling_time_s,overshoot_um,mae_um,std_um"


def test_plant_discretisation_matches_python_control():
    control = pytest.importorskip("control")
    p = PlantParams()
    dp = discretise(p)
    sysd = control.c2d(control.tf([p.b0], [1, p.a1, p.a0]), p.ts_s, method="zoh")
    w = np.array([1.0, 30.0, 300.0, 3000.0])
    z = np.exp(1j * w * p.ts_s)
    from markcal.stages.servo_plant import plant_frequency_response
    ours = plant_frequency_response(dp, z)
    ref = np.array([complex(sysd(zz)) for zz in z])
    np.testing.assert_allclose(ours, ref, rtol=1e-6)
    assert abs(plant_frequency_response(dp, np.array([1.0 + 0j]))[0] - p.b0 / p.a0) < 1e-6 * p.b0 / p.a0


def test_tracking_differentiator_tracks_and_bounds_acceleration():
    ts, r0 = 1e-4, 1e4
    xd = np.where(np.arange(20000) * ts > 0.1, 5.0, 0.0)           # 5 mm step at 0.1 s
    x3, x4 = tracking_differentiator(xd, r0, ts)
    assert abs(x3[-1] - 5.0) < 1e-6 and abs(x4[-1]) < 1e-6
    acc = np.diff(x4) / ts
    assert np.max(np.abs(acc)) <= r0 * (1 + 1e-9)
    # time-optimal: reaches 5 mm in about 2 sqrt(5 / r0) = 44.7 ms, without overshoot
    k = np.flatnonzero(np.abs(x3 - 5.0) < 1e-3)[0]
    assert abs((k * ts - 0.1) - 2 * np.sqrt(5.0 / r0)) < 3e-3
    assert x3.max() < 5.0 + 1e-4
    # on a ramp it returns the slope
    ramp = 100.0 * np.arange(5000) * ts
    _, v = tracking_differentiator(ramp, 1e6, ts)
    assert abs(v[-1] - 100.0) < 1e-6


def test_eq24_matches_python_control_and_predicts_divergence():
    control = pytest.importorskip("control")
    p, g = PlantParams(), PIDGains()
    dp = discretise(p)
    rc = RepetitiveParams(m=7)
    chk = check_rc_stability(dp, g, rc, n_freq=3000)
    # independent evaluation with python-control transfer functions (both schedule sides)
    ts = p.ts_s
    G = control.c2d(control.tf([p.b0], [1, p.a1, p.a0]), ts, method="zoh")
    zt = control.tf([1, 0], [1], ts)
    worst = 0.0
    w = np.linspace(0, np.pi / ts, 3000, endpoint=False)[1:]
    for s in (1.0, g.delta):
        C = s * (g.kp + g.kd * (zt - 1) / (ts * zt)) + (1 / g.ki) * ts * zt / (zt - 1)
        T = control.feedback(C * G, 1)
        Cf = control.tf([rc.tau, 0], [1, -(1 - rc.tau)], ts)
        zm = control.tf([1] + [0] * rc.m, [1], ts) if rc.m else 1
        mag = np.abs((Cf * (1 - T * rc.kr * zm))(np.exp(1j * w * ts)))
        worst = max(worst, float(np.max(mag)))
    assert abs(worst - chk.max_gain) < 2e-3
    assert chk.ok
    bad = check_rc_stability(dp, g, RepetitiveParams(m=100))
    assert not bad.ok and "eq. 24 violated" in bad.reason
    # the check predicts the simulation: stable m converges, m = 100 diverges
    prof = sinusoid(10.0, 1.0, 6)
    n1 = 10000
    good = simulate(dp, g, prof, CCA_TRACK, RepetitiveParams(m=7), 1.0)
    div = simulate(dp, g, prof, CCA_TRACK, RepetitiveParams(m=100), 1.0)
    per = lambda r: [np.std(r.err_mm[i * n1:(i + 1) * n1]) for i in range(6)]
    assert per(good)[-1] < 0.1 * per(good)[1]
    assert per(div)[-1] > 5 * per(div)[1]


def test_step_metrics_on_known_signal():
    t = np.arange(0, 0.2, 1e-4)
    ref = np.where(t < 0.05, t / 0.05 * 10.0, 10.0)
    # after t_end: decaying oscillation, overshoot 8 um, enters +-1 um for good at a known time
    tt = np.clip(t - 0.05, 0, None)
    dev_um = 8.0 * np.exp(-tt / 0.01) * np.cos(2 * np.pi * 50 * tt)
    pos = np.where(t < 0.05, ref - 0.002, 10.0 + dev_um * 1e-3)
    m = step_metrics(t, ref, pos, 0.05, band_um=1.0)
    assert abs(m.overshoot_um - 8.0) < 1e-6
    outside = np.flatnonzero((t >= 0.05) & (np.abs(dev_um) > 1.0))
    assert abs(m.settling_time_s - (t[outside[-1] + 1] - 0.05)) < 1e-12
    assert 0.015 < m.settling_time_s < 0.021          # 8 e^(-t/0.01) = 1 at 20.8 ms


def test_s_curve_limits():
    p = s_curve(10.0)
    assert abs(p.x_mm[-1] - 10.0) < 1e-12
    assert np.max(p.v_mm_s) <= 100.0 + 1e-9
    acc = np.diff(p.v_mm_s) / 1e-4
    assert np.max(np.abs(acc)) <= 10_000.0 * 1.01


@pytest.fixture(scope="module")
def paper_run():
    cfg = ServoConfig(strokes_mm=(10.0,), amplitudes_mm=(5.0, 10.0), frequencies_hz=(0.1, 1.0, 2.0))
    return run_servo(cfg)


def test_paper_defaults_goals(paper_run):
    s = paper_run.summary
    # eq. 24 holds for the lead used; the paper's m = 100 is reported as violating it
    assert s["eq24_ok"] and s["eq24_margin"] > 0 and not s["eq24_paper_m_ok"]
    # Table 1 baseline (10 mm) within 20 % under the default reading
    assert abs(s["step_baseline_overshoot_um"] / 232.01 - 1) < 0.2
    assert abs(s["step_baseline_settling_time_s"] / 0.08513 - 1) < 0.2
    # the composite controller's reductions within a third of the paper's (Table 1: 90.31 %, 64.41 %)
    assert abs(s["overshoot_reduction_pct"] - 90.31) < 90.31 / 3
    assert abs(s["settling_reduction_pct"] - 64.41) < 64.41 / 3
    # tracking (Table 2, 10 mm): the composite controller measured over period 8, after the repetitive
    # controller has learnt; STD reductions within a third of the paper's, against the baseline row and
    # against the baseline in the same period (measured 90.8 / 75.7 / 71.8 % and 90.5 / 70.0 / 62.2 %)
    for tag, paper in (("0p1", 85.0), ("1", 76.42), ("2", 60.54)):
        assert abs(s[f"std_reduction_{tag}hz_pct"] - paper) < paper / 3, tag
        assert abs(s[f"std_reduction_same_window_{tag}hz_pct"] - paper) < paper / 3, tag


def test_cca_sine_window_is_the_learned_period(paper_run):
    """The CCA's sine error is taken over period 8 from rest; the baseline's over its 2 periods from rest."""
    ts = 1e-4
    for f in (0.1, 1.0, 2.0):
        n1 = int(round(1 / f / ts))
        b = find_run(paper_run.runs, "sine", "baseline", 10.0, f)
        c = find_run(paper_run.runs, "sine", "cca", 10.0, f)
        assert (c.window.start, c.window.stop) == (7 * n1 + 1, 8 * n1 + 1)
        assert (b.window.start, b.window.stop) == (0, 2 * n1 + 1)
        assert len(c.sim.t_s) == len(b.sim.t_s) == 8 * n1 + 1
        assert np.isclose(c.std_um, np.std(c.sim.err_mm[7 * n1 + 1:]) * 1e3, rtol=1e-12)


def test_previous_window_misses_the_2hz_reduction():
    """Measured over the same 2 periods from rest (reading rc_2periods), the 2 Hz STD is not reduced at all."""
    cfg = ServoConfig(strokes_mm=(10.0,), amplitudes_mm=(10.0,), frequencies_hz=(2.0,),
                      reading=NAMED_READINGS["rc_2periods"])
    s = run_servo(cfg, compare_readings=False).summary
    # measured -14.1 %: the repetitive controller replays the start-up transient in the second period
    assert s["std_reduction_2hz_pct"] < 0.0


def test_cli_simulation_outputs(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[step]\nstrokes_mm = [10.0]\ndwell_s = 0.3\n[sine]\namplitudes_mm = [10.0]\n"
                   "frequencies_hz = [2.0]\nperiods = 2\n[plant]\na0 = 0.0\n")
    out = tmp_path / "o"
    assert main(["servo", str(cfg), "--out", str(out), "--quiet"]) == 0
    with open(out / "metrics.csv") as fh:
        assert fh.readline().strip() == COLUMNS
    t = read_csv(out / "metrics.csv")
    assert list(t["case"]) == ["step", "step", "sine", "sine"]
    assert list(t["controller"]) == ["baseline", "cca", "baseline", "cca"]
    assert np.all(np.isfinite(t["settling_time_s"][:2]))          # both settle within the record
    s = json.loads((out / "summary.json").read_text())
    assert s["plant_a0"] == 0.0 and s["rc_m_auto"] is True
    html = (out / "report.html").read_text()
    assert "Table 1" in html and "Table 2" in html and "Fig. 10" in html
    assert "src=\"http" not in html


@pytest.mark.parametrize("kind,controller", [("step", "cca"), ("sine", "baseline"), ("sine", "cca")])
def test_trace_metrics_against_truth(tmp_path, kind, controller):
    opts = TraceOptions(kind=kind, controller=controller, frequency_hz=2.0, periods=2, dwell_s=0.15,
                        plant_error=0.0 if kind == "step" else 0.05)
    r = render_servo_trace(11, opts)
    r2 = render_servo_trace(11, opts)
    assert np.array_equal(r.pos_mm, r2.pos_mm)                    # deterministic
    p = tmp_path / "trace.csv"
    write_csv(p, {"t_s": np.round(r.t_s, 9), "ref_mm": r.ref_mm, "pos_mm": np.round(r.pos_mm, 7)})
    out = tmp_path / "o"
    assert main(["servo", "--trace", str(p), "--out", str(out), "--quiet", "--no-report"]) == 0
    m = read_csv(out / "metrics.csv")
    truth = r.truth["metrics_noise_free"]
    assert m["case"][0] == "trace" and m["controller"][0] == "measured"
    # encoder noise 5 nm, resolution 1 nm: MAE/STD within 0.05 um, overshoot within 0.03 um
    assert abs(m["mae_um"][0] - truth["mae_um"]) < 0.05
    assert abs(m["std_um"][0] - truth["std_um"]) < 0.05
    if kind == "step":
        assert abs(m["overshoot_um"][0] - truth["overshoot_um"]) < 0.03
        assert abs(m["amplitude_mm"][0] - 10.0) < 1e-9
    else:
        assert abs(m["frequency_hz"][0] - 2.0) < 0.02
        assert abs(m["amplitude_mm"][0] - 5.0) < 1e-3


def _err(capsys):
    return capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("text,needle", [
    ("[plant]\nb1 = 3\n", "unknown key 'b1' in [plant]"),
    ("[gains]\nkp = 3\n", "unknown section [gains]"),
    ("[controller]\nkp = -85.0\n", "gain kp = -85.0 refused"),
    ("[controller]\nkd = -0.1\n", "gain kd = -0.1 refused"),
    ("[repetitive]\nm = 100\n", "eq. 24 violated"),
    ("[repetitive]\nkr = 3.0\nm = 7\n", "eq. 24 violated"),
    ("[controller]\nkp = 1e6\n", "unstable"),
    # 2 periods at 0.002 Hz are 10 M samples, but the CCA learns over 8 (40 M): refused before simulating
    ("[sine]\nfrequencies_hz = [0.002]\nperiods = 2\n", "the longest case would be 4e+07 samples"),
])
def test_bad_configs_refused(tmp_path, capsys, text, needle):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "o"
    assert main(["servo", str(cfg), "--out", str(out), "--quiet"]) == 1
    lines = _err(capsys)
    assert len(lines) == 1 and lines[0].startswith("markcal: error: ") and needle in lines[0], lines
    assert not (out / "summary.json").exists()


def _write_trace(path, t, ref, pos):
    write_csv(path, {"t_s": t, "ref_mm": ref, "pos_mm": pos})


@pytest.mark.parametrize("defect,needle", [("gap", "gap in the trace"), ("back", "out of time order"),
                                           ("dup", "out of time order"), ("nan", "line 9: pos_mm = '' is not a number"),
                                           ("cols", "missing column(s) pos_mm")])
def test_bad_traces_refused(tmp_path, capsys, defect, needle):
    t = np.arange(200) * 1e-4
    ref = np.sin(2 * np.pi * 5 * t)
    pos = ref + 1e-4
    if defect == "gap":
        t, ref, pos = np.delete(t, range(50, 60)), np.delete(ref, range(50, 60)), np.delete(pos, range(50, 60))
    elif defect == "back":
        t[100] = t[98]
    elif defect == "dup":
        t[100] = t[99]
    elif defect == "nan":
        pos[7] = np.nan
    p = tmp_path / "t.csv"
    if defect == "cols":
        write_csv(p, {"t_s": t, "ref_mm": ref})
    else:
        _write_trace(p, t, ref, pos)
    out = tmp_path / "o"
    assert main(["servo", "--trace", str(p), "--out", str(out), "--quiet"]) == 1
    lines = _err(capsys)
    assert len(lines) == 1 and needle in lines[0] and str(p) in lines[0], lines
    assert not (out / "summary.json").exists()


def test_render_servo_cli(tmp_path):
    out = tmp_path / "r"
    assert main(["render", "servo", "--seed", "2", "--kind", "sine", "--frequency-hz", "2", "--periods", "2",
                 "--out", str(out), "--quiet"]) == 0
    t = read_csv(out / "trace.csv")
    assert set(t) == {"t_s", "ref_mm", "pos_mm"} and len(t["t_s"]) == 10001
    assert json.loads((out / "truth.json").read_text())["options"]["kind"] == "sine"
