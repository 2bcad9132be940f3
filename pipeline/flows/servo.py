"""The servo flow: macro-stage positioning and tracking with the composite controller.

Paper 003 (Zhou, Gao & Zhang, Actuators 2024): reduced second-order stage model
(sec. 2-3), tracking differentiator + velocity feed-forward + gain-scheduled PID
for point-to-point moves (Fig. 4), feed-forward + gain-scheduled PID + plug-in
repetitive control for sinusoidal tracking (Fig. 7), simulated against the
baseline (feed-forward + PID) with the paper's simulation parameters (sec. 5).
Also computes the same metrics for a measured encoder trace (t_s, ref_mm, pos_mm).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, fields, replace

import numpy as np

from markcal.pipeline.config import check_sections, load_toml
from markcal.stages.errors import MarkcalError
from markcal.stages.servo_control import PIDGains, RepetitiveParams, StabilityCheck, check_rc_stability
from markcal.stages.servo_plant import PlantParams, discretise
from markcal.stages.servo_profile import s_curve, sinusoid
from markcal.stages.servo_sim import (BASELINE, CCA_STEP, CCA_TRACK, SimResult, step_metrics,
                                      simulate, tracking_metrics)

#: the paper's reported reductions (%), simulation, Tables 1-2 (10 mm move; 10 mm sine)
PAPER_TABLE1 = {  # stroke_mm: (overshoot w/o, with, red %, settling w/o ms, with ms, red %)
    10.0: (232.01, 22.47, 90.31, 85.13, 30.29, 64.41),
    20.0: (232.33, 22.98, 90.11, 85.18, 30.63, 64.04),
    30.0: (232.33, 22.99, 90.10, 85.23, 30.66, 64.02),
}
PAPER_TABLE2 = {  # frequency_hz: (MAE w/o, STD w/o, MAE with, STD with, STD red %), 10 mm amplitude
    0.1: (2.4, 2.8, 0.08, 0.42, 85.0),
    0.2: (4.9, 5.6, 0.26, 0.87, 84.45),
    0.5: (13.1, 14.9, 1.5, 2.6, 82.55),
    1.0: (31.1, 35.2, 6.3, 8.3, 76.42),
    2.0: (91.3, 103.4, 31.5, 40.8, 60.54),
}
#: the paper's lead of the repetitive compensator Qb(z) = z^m (sec. 5.2)
PAPER_RC_M = 100
#: candidate leads tried when ``m = "auto"``
AUTO_M_RANGE = range(0, 201)

METRIC_COLUMNS = ("case", "controller", "amplitude_mm", "frequency_hz", "settling_time_s",
                  "overshoot_um", "mae_um", "std_um")


@dataclass(frozen=True)
class ServoConfig:
    """Everything the simulation needs; defaults are the paper's sec. 5 setup.

    ``rc_m = None`` means "auto": the lead with the largest eq. 24 margin.
    Lengths mm, speeds mm/s, time s.
    """

    plant: PlantParams = PlantParams()
    gains: PIDGains = PIDGains()
    rc_tau: float = 0.085
    rc_kr: float = 0.95
    rc_m: int | None = None
    strokes_mm: tuple = (10.0, 20.0, 30.0)
    velocity_mm_s: float = 100.0
    acceleration_mm_s2: float = 10_000.0
    jerk_mm_s3: float = 1_000_000.0
    dwell_s: float = 0.3
    amplitudes_mm: tuple = (5.0, 10.0)
    frequencies_hz: tuple = (0.1, 0.2, 0.5, 1.0, 2.0)
    periods: float = 3.0
    settle_band_um: float = 1.0
    u_max_v: float = math.inf
    friction_v: float = 0.0


_SECTIONS = {
    "plant": {"b0": "b0", "a1": "a1", "a0": "a0", "ts_s": "ts_s"},
    "controller": {"kf": "kf", "kp": "kp", "ki": "ki", "kd": "kd", "r0": "r0", "phi_mm": "phi_mm",
                   "delta": "delta", "u_max_v": "u_max_v", "friction_v": "friction_v"},
    "repetitive": {"tau": "rc_tau", "kr": "rc_kr", "m": "rc_m"},
    "step": {"strokes_mm": "strokes_mm", "velocity_mm_s": "velocity_mm_s",
             "acceleration_mm_s2": "acceleration_mm_s2", "jerk_mm_s3": "jerk_mm_s3", "dwell_s": "dwell_s"},
    "sine": {"amplitudes_mm": "amplitudes_mm", "frequencies_hz": "frequencies_hz", "periods": "periods"},
    "metrics": {"settle_band_um": "settle_band_um"},
}


def _num(v, sec, key, path):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise MarkcalError(f"[{sec}] {key} must be a number (got {v!r})", path)
    return float(v)


def read_servo_config(path) -> ServoConfig:
    """Read a servo CONFIG.toml (strict: unknown sections or keys are refused).

    Sections and keys: ``[plant] b0 a1 a0 ts_s``; ``[controller] kf kp ki kd r0
    phi_mm delta u_max_v friction_v``; ``[repetitive] tau kr m`` (m an integer or
    "auto"); ``[step] strokes_mm velocity_mm_s acceleration_mm_s2 jerk_mm_s3
    dwell_s``; ``[sine] amplitudes_mm frequencies_hz periods``; ``[metrics]
    settle_band_um``. Missing keys take the paper's values.
    """
    path = os.fspath(path)
    d = load_toml(path, "config file")
    check_sections(d, _SECTIONS, path)
    plant_kw, gain_kw, top_kw = {}, {}, {}
    for sec, keys in d.items():
        for key, v in keys.items():
            if sec == "plant":
                plant_kw[key] = _num(v, sec, key, path)
            elif sec == "controller" and key in {f.name for f in fields(PIDGains)}:
                gain_kw[key] = _num(v, sec, key, path)
            elif key == "m":
                if v == "auto":
                    top_kw["rc_m"] = None
                elif isinstance(v, int) and not isinstance(v, bool):
                    top_kw["rc_m"] = v
                else:
                    raise MarkcalError(f"[repetitive] m must be a whole number of samples or \"auto\" (got {v!r})",
                                       path)
            elif key in ("strokes_mm", "amplitudes_mm", "frequencies_hz"):
                if not isinstance(v, list) or not v:
                    raise MarkcalError(f"[{sec}] {key} must be a non-empty list of numbers", path)
                top_kw[_SECTIONS[sec][key]] = tuple(_num(x, sec, key, path) for x in v)
            else:
                top_kw[_SECTIONS[sec][key]] = _num(v, sec, key, path)
    cfg = ServoConfig(plant=replace(PlantParams(), **plant_kw), gains=replace(PIDGains(), **gain_kw), **top_kw)
    try:
        validate_config(cfg)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    return cfg


def validate_config(cfg: ServoConfig) -> None:
    """Refuse non-physical or unstable settings (with the reason)."""
    cfg.plant.check()
    cfg.gains.check()
    RepetitiveParams(cfg.rc_tau, cfg.rc_kr, 0 if cfg.rc_m is None else cfg.rc_m).check()
    if not (cfg.settle_band_um > 0):
        raise MarkcalError(f"settle_band_um must be positive (got {cfg.settle_band_um})")
    if not (cfg.u_max_v > 0):
        raise MarkcalError(f"u_max_v must be positive (got {cfg.u_max_v})")
    if not (cfg.friction_v >= 0 and math.isfinite(cfg.friction_v)):
        raise MarkcalError(f"friction_v must be finite and non-negative (got {cfg.friction_v})")
    if any(not (f > 0) for f in cfg.frequencies_hz):
        raise MarkcalError("sine frequencies must be positive")


def choose_rc(cfg: ServoConfig) -> tuple[RepetitiveParams, StabilityCheck, StabilityCheck]:
    """The repetitive controller to use, its eq. 24 check, and the check of the paper's m = 100.

    Raises :class:`MarkcalError` when the PID loop is unstable or when an
    explicitly configured ``m`` violates eq. 24.
    """
    dp = discretise(cfg.plant)
    paper = check_rc_stability(dp, cfg.gains, RepetitiveParams(cfg.rc_tau, cfg.rc_kr, PAPER_RC_M))
    if cfg.rc_m is None:
        if paper.pid_pole_radius >= 1:
            raise MarkcalError(f"unstable parameter set: {paper.reason}")
        best = None
        for m in AUTO_M_RANGE:
            c = check_rc_stability(dp, cfg.gains, RepetitiveParams(cfg.rc_tau, cfg.rc_kr, m), n_freq=1500)
            if best is None or c.margin > best[1].margin:
                best = (m, c)
        rc = RepetitiveParams(cfg.rc_tau, cfg.rc_kr, best[0])
    else:
        rc = RepetitiveParams(cfg.rc_tau, cfg.rc_kr, int(cfg.rc_m))
    check = check_rc_stability(dp, cfg.gains, rc)
    if not check.ok:
        raise MarkcalError(f"unstable parameter set: {check.reason}")
    return rc, check, paper


@dataclass(frozen=True)
class Run:
    """One simulated (or measured) case and its metrics."""

    case: str                 # step | sine | trace
    controller: str           # baseline | cca | measured
    amplitude_mm: float       # stroke (step) or amplitude (sine)
    frequency_hz: float       # NaN for moves
    settling_time_s: float
    overshoot_um: float
    mae_um: float
    std_um: float
    sim: SimResult = field(repr=False)
    window: slice = field(default_factory=lambda: slice(None))  # samples the MAE/STD were computed over
    t_end_s: float = float("nan")


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


def _step_run(cfg, dp, stroke, ctrl):
    p = s_curve(stroke, cfg.velocity_mm_s, cfg.acceleration_mm_s2, cfg.jerk_mm_s3, cfg.plant.ts_s, cfg.dwell_s)
    r = simulate(dp, cfg.gains, p, ctrl, u_max_v=cfg.u_max_v, friction_v=cfg.friction_v)
    m = step_metrics(p.t_s, r.ref_mm, r.pos_mm, p.t_end_s, cfg.settle_band_um)
    return Run("step", ctrl.name, float(abs(stroke)), float("nan"), m.settling_time_s, m.overshoot_um,
               m.mae_um, m.std_um, r, slice(None), p.t_end_s)


def _sine_run(cfg, dp, amp, freq, ctrl, rc):
    p = sinusoid(amp, freq, cfg.periods, cfg.plant.ts_s)
    r = simulate(dp, cfg.gains, p, ctrl, rc=rc, period_s=1.0 / freq, u_max_v=cfg.u_max_v,
                 friction_v=cfg.friction_v)
    n1 = int(round(1.0 / freq / cfg.plant.ts_s))
    win = slice(len(p.t_s) - n1, len(p.t_s))          # the last whole period
    mae, std = tracking_metrics(r.err_mm[win])
    return Run("sine", ctrl.name, float(amp), float(freq), float("nan"), float("nan"), mae, std, r, win)


def reduction_pct(before, after):
    """Reduction (%) from ``before`` to ``after``; NaN when either is missing or before <= 0."""
    if not (np.isfinite(before) and np.isfinite(after)) or before <= 0:
        return float("nan")
    return 100.0 * (1.0 - after / before)


def run_servo(cfg: ServoConfig | None = None, source: str = "paper defaults", progress=None) -> ServoResult:
    """Simulate every move and sinusoid with the baseline and the composite controller."""
    say = progress or (lambda msg: None)
    cfg = cfg or ServoConfig()
    validate_config(cfg)
    t0 = time.perf_counter()
    rc, check, paper = choose_rc(cfg)
    say(f"eq. 24: {check.reason}; repetitive lead m = {rc.m}")
    dp = discretise(cfg.plant)
    runs = []
    for stroke in cfg.strokes_mm:
        for ctrl in (BASELINE, CCA_STEP):
            runs.append(_step_run(cfg, dp, stroke, ctrl))
    say(f"{len(cfg.strokes_mm)} moves simulated")
    for amp in cfg.amplitudes_mm:
        for freq in cfg.frequencies_hz:
            for ctrl in (BASELINE, CCA_TRACK):
                runs.append(_sine_run(cfg, dp, amp, freq, ctrl, rc))
    say(f"{len(cfg.amplitudes_mm) * len(cfg.frequencies_hz)} sinusoids simulated")
    summary = _sim_summary(cfg, runs, rc, check, paper)
    summary["runtime_s"] = time.perf_counter() - t0
    summary["source"] = source
    return ServoResult(source, "simulation", cfg, runs, rc, check, paper, summary)


def find(runs, case, controller, amplitude_mm, frequency_hz=None):
    """The run with these labels, or None."""
    for r in runs:
        if r.case == case and r.controller == controller and np.isclose(r.amplitude_mm, amplitude_mm) and (
                frequency_hz is None or np.isclose(r.frequency_hz, frequency_hz)):
            return r
    return None


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
         "settle_band_um": cfg.settle_band_um, "n_runs": len(runs)}
    ref_stroke = 10.0 if any(np.isclose(x, 10.0) for x in cfg.strokes_mm) else cfg.strokes_mm[0]
    b, c = find(runs, "step", "baseline", ref_stroke), find(runs, "step", "cca", ref_stroke)
    s["step_stroke_mm"] = ref_stroke
    for k in ("overshoot_um", "settling_time_s"):
        s[f"step_baseline_{k}"] = getattr(b, k)
        s[f"step_cca_{k}"] = getattr(c, k)
    s["overshoot_reduction_pct"] = reduction_pct(b.overshoot_um, c.overshoot_um)
    s["settling_reduction_pct"] = reduction_pct(b.settling_time_s, c.settling_time_s)
    amp = 10.0 if any(np.isclose(a, 10.0) for a in cfg.amplitudes_mm) else max(cfg.amplitudes_mm)
    s["sine_amplitude_mm"] = amp
    for f in cfg.frequencies_hz:
        b, c = find(runs, "sine", "baseline", amp, f), find(runs, "sine", "cca", amp, f)
        tag = f"{f:g}".replace(".", "p")
        s[f"std_baseline_{tag}hz_um"] = b.std_um
        s[f"std_cca_{tag}hz_um"] = c.std_um
        s[f"std_reduction_{tag}hz_pct"] = reduction_pct(b.std_um, c.std_um)
    return s


# ---------------------------------------------------------------- measured traces

def read_trace(path) -> dict:
    """Read a measured encoder trace CSV ``t_s,ref_mm,pos_mm`` (header required).

    Refused: missing columns, fewer than 20 rows, non-finite values, time not
    strictly increasing, or gaps (a step longer than 1.5 x the median step).
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            header = fh.readline().strip().split(",")
            data = np.atleast_2d(np.genfromtxt(fh, delimiter=",", dtype=float))
    except FileNotFoundError:
        raise MarkcalError("no such trace file", path) from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise MarkcalError(f"cannot read trace ({exc})", path) from None
    header = [h.strip() for h in header]
    need = ("t_s", "ref_mm", "pos_mm")
    missing = [c for c in need if c not in header]
    if missing:
        raise MarkcalError(f"trace needs the columns t_s,ref_mm,pos_mm (missing: {', '.join(missing)})", path)
    if data.shape[0] < 20 or data.shape[1] != len(header):
        raise MarkcalError(f"trace has {data.shape[0]} rows of {data.shape[1]} columns; need >= 20 rows of "
                           f"{len(header)}", path)
    cols = {c: data[:, header.index(c)] for c in need}
    bad = ~np.isfinite(np.column_stack(list(cols.values())))
    if np.any(bad):
        i = int(np.flatnonzero(bad.any(axis=1))[0])
        raise MarkcalError(f"trace has non-finite values (NaN, inf, blank or text) at row {i + 2}", path)
    dt = np.diff(cols["t_s"])
    if np.any(dt <= 0):
        i = int(np.flatnonzero(dt <= 0)[0])
        raise MarkcalError(f"time is not strictly increasing at row {i + 2} (t_s {cols['t_s'][i]!r} -> "
                           f"{cols['t_s'][i + 1]!r})", path)
    med = float(np.median(dt))
    if np.any(dt > 1.5 * med):
        i = int(np.flatnonzero(dt > 1.5 * med)[0])
        raise MarkcalError(f"gap in the trace at row {i + 2}: step {dt[i]:.6g} s against the median "
                           f"{med:.6g} s (samples missing)", path)
    return cols


def trace_run(t_s, ref_mm, pos_mm, band_um: float = 1.0) -> Run:
    """Metrics of a measured trace.

    A trace whose reference holds still over its last 10 % is a move: settling
    time from the last change of the reference, overshoot past the final
    reference. Otherwise it is tracking: amplitude = half the reference range,
    frequency = the strongest FFT line. MAE and STD are over the whole trace.
    """
    n = len(t_s)
    tail = ref_mm[int(0.9 * n):]
    moving = np.abs(np.diff(ref_mm)) > 1e-9
    err = ref_mm - pos_mm
    mae, std = tracking_metrics(err)
    sim = SimResult(t_s=t_s, ref_mm=ref_mm, pos_mm=pos_mm, u_v=np.full(n, np.nan), err_mm=err)
    if np.ptp(tail) <= 1e-9 and np.any(moving):
        k_end = int(np.flatnonzero(moving)[-1]) + 1
        t_end = float(t_s[k_end])
        m = step_metrics(t_s, ref_mm, pos_mm, t_end, band_um)
        return Run("trace", "measured", float(abs(ref_mm[-1] - ref_mm[0])), float("nan"), m.settling_time_s,
                   m.overshoot_um, mae, std, sim, slice(None), t_end)
    x = ref_mm - ref_mm.mean()
    spec = np.abs(np.fft.rfft(x * np.hanning(n)))
    fr = np.fft.rfftfreq(n, d=float(np.median(np.diff(t_s))))
    k = int(np.argmax(spec[1:])) + 1
    # parabolic refinement of the peak
    if 1 <= k < len(spec) - 1:
        a, b, c = np.log(spec[k - 1] + 1e-300), np.log(spec[k] + 1e-300), np.log(spec[k + 1] + 1e-300)
        den = a - 2 * b + c
        k = k + (0.5 * (a - c) / den if den != 0 else 0.0)
    freq = float(k * (fr[1] - fr[0]))
    return Run("trace", "measured", float(0.5 * np.ptp(ref_mm)), freq, float("nan"), float("nan"), mae, std, sim)


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
