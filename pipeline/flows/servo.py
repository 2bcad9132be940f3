"""The servo flow: macro-stage positioning and tracking with the composite controller.

Paper 003 (Zhou, Gao & Zhang, Actuators 2024): reduced second-order stage model
(sec. 2-3), tracking differentiator + velocity feed-forward + gain-scheduled PID
for point-to-point moves (Fig. 4), feed-forward + gain-scheduled PID + plug-in
repetitive control for sinusoidal tracking (Fig. 7), simulated against the
baseline (feed-forward + PID) with the paper's simulation parameters (sec. 5).
Also computes the same metrics for a measured encoder trace (t_s, ref_mm, pos_mm).
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass

import numpy as np

from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor, csv_header, file_ext
from markcal.pipeline.tables import check_increasing, read_table
from markcal.stages.errors import MarkcalError
from markcal.stages.servo_cases import (PAPER_RC_M, Run, ServoConfig, band_um, choose_rc, find_run, sim_model,
                                        trace_run, validate_config)
from markcal.stages.servo_control import tracking_differentiator
from markcal.stages.servo_reading import NAMED_READINGS, baseline_rows, reference_end_s, score_rows
from markcal.stages.servo_control import RepetitiveParams, StabilityCheck
from markcal.stages.servo_plant import discretise
from markcal.stages.servo_profile import s_curve, sinusoid
from markcal.stages.servo_sim import BASELINE, CCA_STEP, CCA_TRACK, simulate, step_metrics, tracking_metrics
from markcal.stages.stats import reduction_pct

METRIC_COLUMNS = ("case", "controller", "amplitude_mm", "frequency_hz", "settling_time_s",
                  "overshoot_um", "mae_um", "std_um")


@dataclass(frozen=True)
class ServoResult:
    """Everything the servo flow computed; ``reports`` turns it into files."""

    source: str
    mode: str                     # simulation | trace
    config: ServoConfig | None
    runs: list
    rc: RepetitiveParams | None
    stability: StabilityCheck | None
    stability_paper_m: StabilityCheck | None
    summary: dict
    readings: tuple = ()          # (name, Reading, baseline rows, score) of the named readings


def _step_run(cfg, dp, gains, stroke, ctrl):
    ts = dp.params.ts_s
    p = s_curve(stroke, cfg.velocity_mm_s, cfg.acceleration_mm_s2, cfg.jerk_mm_s3, ts, cfg.dwell_s)
    r = simulate(dp, gains, p, ctrl, u_max_v=cfg.u_max_v, friction_v=cfg.friction_v)
    t_end = p.t_end_s
    if ctrl.tracking_differentiator and cfg.reading.cca_origin == "own":
        # settling counted from the end of the reference the loop follows: the TD's output
        t_end = max(t_end, reference_end_s(p.t_s, tracking_differentiator(p.x_mm, gains.r0, ts)[0]))
    m = step_metrics(p.t_s, r.ref_mm, r.pos_mm, t_end, band_um(cfg, stroke))
    return Run("step", ctrl.name, float(abs(stroke)), float("nan"), m.settling_time_s, m.overshoot_um,
               m.mae_um, m.std_um, r, slice(None), t_end)


def _sine_run(cfg, dp, gains, amp, freq, ctrl, rc):
    ts = dp.params.ts_s
    p = sinusoid(amp, freq, cfg.periods, ts)
    r = simulate(dp, gains, p, ctrl, rc=rc, period_s=1.0 / freq, u_max_v=cfg.u_max_v,
                 friction_v=cfg.friction_v)
    n1 = int(round(1.0 / freq / ts))
    # the reading's window: the whole record from rest, or the last whole period
    win = slice(None) if cfg.reading.sine_window == "whole" else slice(len(p.t_s) - n1, len(p.t_s))
    mae, std = tracking_metrics(r.err_mm[win])
    return Run("sine", ctrl.name, float(amp), float(freq), float("nan"), float("nan"), mae, std, r, win)


def run_servo(cfg: ServoConfig | None = None, source: str = "paper defaults", progress=None,
              compare_readings: bool = True) -> ServoResult:
    """Simulate every move and sinusoid with the baseline and the composite controller.

    With ``compare_readings`` the named readings' baseline rows are simulated
    too and scored against Tables 1-2 (for the report's side-by-side table).
    """
    say = progress or (lambda msg: None)
    cfg = cfg or ServoConfig()
    validate_config(cfg)
    t0 = time.perf_counter()
    rc, check, paper = choose_rc(cfg)
    say(f"eq. 24: {check.reason}; repetitive lead m = {rc.m}")
    plant, gains = sim_model(cfg)
    dp = discretise(plant)
    runs = []
    for stroke in cfg.strokes_mm:
        for ctrl in (BASELINE, CCA_STEP):
            runs.append(_step_run(cfg, dp, gains, stroke, ctrl))
    say(f"{len(cfg.strokes_mm)} moves simulated")
    for amp in cfg.amplitudes_mm:
        for freq in cfg.frequencies_hz:
            for ctrl in (BASELINE, CCA_TRACK):
                runs.append(_sine_run(cfg, dp, gains, amp, freq, ctrl, rc))
    say(f"{len(cfg.amplitudes_mm) * len(cfg.frequencies_hz)} sinusoids simulated")
    summary = _sim_summary(cfg, runs, rc, check, paper)
    readings = []
    if compare_readings:
        for name, rd in NAMED_READINGS.items():
            rows = baseline_rows(rd, gains=cfg.gains, plant=cfg.plant)
            readings.append((name, rd, rows, score_rows(rows)))
        say(f"{len(readings)} readings scored against Tables 1-2")
        own = next((r for r in readings if r[1] == cfg.reading), None)
        if own:
            summary.update({"reading_score": own[3]["score"], "reading_t1_within": own[3]["t1_within"],
                            "reading_t2_within": own[3]["t2_within"]})
    summary["runtime_s"] = time.perf_counter() - t0
    summary["source"] = source
    return ServoResult(source, "simulation", cfg, runs, rc, check, paper, summary, tuple(readings))


def _sim_summary(cfg, runs, rc, check, paper) -> dict:
    s = {"kind": "servo", "mode": "simulation",
         "plant_b0": cfg.plant.b0, "plant_a1": cfg.plant.a1, "plant_a0": cfg.plant.a0, "ts_s": cfg.plant.ts_s,
         "kf": cfg.gains.kf, "kp": cfg.gains.kp, "ki": cfg.gains.ki, "kd": cfg.gains.kd, "r0": cfg.gains.r0,
         "phi_mm": cfg.gains.phi_mm, "delta": cfg.gains.delta,
         "rc_tau": rc.tau, "rc_kr": rc.kr, "rc_m": rc.m, "rc_m_auto": cfg.rc_m is None,
         "eq24_ok": check.ok, "eq24_margin": check.margin, "eq24_max_gain": check.max_gain,
         "eq24_worst_freq_hz": check.worst_freq_hz, "pid_pole_radius": check.pid_pole_radius,
         "eq24_paper_m": PAPER_RC_M, "eq24_paper_m_ok": paper.ok, "eq24_paper_m_max_gain": paper.max_gain,
         "eq24_paper_m_worst_freq_hz": paper.worst_freq_hz,
         "settle_band_um": band_um(cfg, 10.0), "n_runs": len(runs),
         **{f"reading_{k}": v for k, v in asdict(cfg.reading).items()}}
    ref_stroke = 10.0 if any(np.isclose(x, 10.0) for x in cfg.strokes_mm) else cfg.strokes_mm[0]
    b, c = find_run(runs, "step", "baseline", ref_stroke), find_run(runs, "step", "cca", ref_stroke)
    s["step_stroke_mm"] = ref_stroke
    for k in ("overshoot_um", "settling_time_s"):
        s[f"step_baseline_{k}"] = getattr(b, k)
        s[f"step_cca_{k}"] = getattr(c, k)
    s["overshoot_reduction_pct"] = reduction_pct(b.overshoot_um, c.overshoot_um)
    s["settling_reduction_pct"] = reduction_pct(b.settling_time_s, c.settling_time_s)
    amp = 10.0 if any(np.isclose(a, 10.0) for a in cfg.amplitudes_mm) else max(cfg.amplitudes_mm)
    s["sine_amplitude_mm"] = amp
    for f in cfg.frequencies_hz:
        b, c = find_run(runs, "sine", "baseline", amp, f), find_run(runs, "sine", "cca", amp, f)
        tag = f"{f:g}".replace(".", "p")
        s[f"std_baseline_{tag}hz_um"] = b.std_um
        s[f"std_cca_{tag}hz_um"] = c.std_um
        s[f"std_reduction_{tag}hz_pct"] = reduction_pct(b.std_um, c.std_um)
    return s


# ---------------------------------------------------------------- measured traces

def read_trace(path) -> dict:
    """Read a measured encoder trace CSV ``t_s,ref_mm,pos_mm`` (header required).

    Refused: missing columns, fewer than 20 rows, non-numbers, time not
    strictly increasing, or gaps (a step longer than 1.5 x the median step).
    """
    path = os.fspath(path)
    cols = read_table(path, ("t_s", "ref_mm", "pos_mm"))
    if len(cols["t_s"]) < 20:
        raise MarkcalError(f"trace has {len(cols['t_s'])} rows; need at least 20", path)
    check_increasing(cols["t_s"], "t_s", path)
    dt = np.diff(cols["t_s"])
    med = float(np.median(dt))
    if np.any(dt > 1.5 * med):
        i = int(np.flatnonzero(dt > 1.5 * med)[0])
        raise MarkcalError(f"gap in the trace at line {i + 3}: step {dt[i]:.6g} s against the median "
                           f"{med:.6g} s (samples missing)", path)
    return cols


def run_servo_trace(path, band_um: float = 1.0, progress=None) -> ServoResult:
    """Compute the servo metrics of a measured encoder trace file."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    cols = read_trace(path)
    say(f"read {len(cols['t_s']):,} samples")
    r = trace_run(cols["t_s"], cols["ref_mm"], cols["pos_mm"], band_um)
    summary = {"kind": "servo", "mode": "trace", "n_samples": int(len(cols["t_s"])),
               "ts_s": float(np.median(np.diff(cols["t_s"]))), "duration_s": float(cols["t_s"][-1] - cols["t_s"][0]),
               "trace_kind": "move" if np.isfinite(r.t_end_s) else "tracking",
               "amplitude_mm": r.amplitude_mm, "frequency_hz": r.frequency_hz,
               "settling_time_s": r.settling_time_s, "overshoot_um": r.overshoot_um,
               "mae_um": r.mae_um, "std_um": r.std_um, "settle_band_um": band_um,
               "runtime_s": time.perf_counter() - t0, "source": os.fspath(path)}
    return ServoResult(os.fspath(path), "trace", None, [r], None, None, None, summary)


def _claims(path) -> bool:
    return file_ext(path) == ".csv" and {"t_s", "ref_mm", "pos_mm"} <= set(csv_header(path))


def _run_trace(path, spec, options, progress=None) -> ServoResult:
    band = float(options["settle_band_um"])
    if not band > 0:
        raise MarkcalError(f"settle_band_um must be positive (got {band})")
    return run_servo_trace(path, band_um=band, progress=progress)


FLOW = FlowDescriptor(
    name="servo", help="macro-stage servo: composite controller vs baseline, or a measured trace",
    claims=_claims, run=_run_trace,
    options={"settle_band_um": 1.0, "no_report": False},
    key_figures=(Figure("trace_kind", "trace kind"), Figure("mae_um", "servo mean absolute tracking error", "µm"),
                 Figure("std_um", "tracking error STD", "µm"), Figure("settling_time_s", "settling time", "s"),
                 Figure("overshoot_um", "overshoot", "µm")),
    tolerances={"max_overshoot_um": 6.0},
    trends=("mae_um",), cost=0.5)
