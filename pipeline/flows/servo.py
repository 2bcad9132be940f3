"""The servo flow: macro-stage positioning and tracking with the composite controller.

Paper 003 (Zhou, Gao & Zhang, Actuators 2024): reduced second-order stage model
(sec. 2-3), tracking differentiator + velocity feed-forward + gain-scheduled PID
for point-to-point moves (Fig. 4), feed-forward + gain-scheduled PID + plug-in
repetitive control for sinusoidal tracking (Fig. 7), simulated against the
baseline (feed-forward + PID) with the paper's simulation parameters (sec. 5).
Also measures drive logs (CSV/TSV/whitespace; time, reference, position columns): cut into moves at
the reference's steps with per-move metrics and statistics, or sinusoidal tracking with the phase lag.
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass

import numpy as np

from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor, file_ext
from markcal.stages.errors import MarkcalError
from markcal.stages.servo_cases import (PAPER_RC_M, Run, ServoConfig, band_um, choose_rc, find_run, sim_model,
                                        validate_config)
from markcal.stages.servo_control import tracking_differentiator
from markcal.stages.servo_reading import (NAMED_READINGS, baseline_rows, reference_end_s, score_rows,
                                          sim_options, sine_phase_deg)
from markcal.stages.servo_control import RepetitiveParams, StabilityCheck
from markcal.stages.servo_plant import discretise
from markcal.stages.servo_profile import s_curve, sinusoid
from markcal.stages.servo_log import (DriveLog, Moves, SineMetrics, check_log, check_log_units, find_moves, move_metrics,
                                     guess_columns, move_statistics, read_log, sine_metrics, sniff_layout)
from markcal.stages.servo_sim import (BASELINE, CCA_STEP, CCA_TRACK, SimResult, simulate, step_metrics,
                                      tracking_metrics)
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
    trace: "TraceAnalysis | None" = None   # trace mode: the log and its moves / tracking metrics


def _step_run(cfg, dp, gains, stroke, ctrl):
    ts = dp.params.ts_s
    p = s_curve(stroke, cfg.velocity_mm_s, cfg.acceleration_mm_s2, cfg.jerk_mm_s3, ts, cfg.dwell_s)
    r = simulate(dp, gains, p, ctrl, friction_v=cfg.friction_v, **sim_options(cfg.reading, cfg.u_max_v))
    t_end = p.t_end_s
    if ctrl.tracking_differentiator and cfg.reading.cca_origin == "own":
        # settling counted from the end of the reference the loop follows: the TD's output
        t_end = max(t_end, reference_end_s(p.t_s, tracking_differentiator(p.x_mm, gains.r0, ts)[0]))
    m = step_metrics(p.t_s, r.ref_mm, r.pos_mm, t_end, band_um(cfg, stroke))
    return Run("step", ctrl.name, float(abs(stroke)), float("nan"), m.settling_time_s, m.overshoot_um,
               m.mae_um, m.std_um, r, slice(None), t_end)


def _sine_run(cfg, dp, gains, amp, freq, ctrl, rc):
    ts = dp.params.ts_s
    n_cca = cfg.reading.cca_sine_periods
    # both controllers run over the same record: the baseline's periods, or as many as the CCA learns for
    p = sinusoid(amp, freq, max(cfg.periods, n_cca), ts, sine_phase_deg(cfg.reading))
    r = simulate(dp, gains, p, ctrl, rc=rc, period_s=1.0 / freq, friction_v=cfg.friction_v,
                 **sim_options(cfg.reading, cfg.u_max_v))
    n1 = int(round(1.0 / freq / ts))
    if ctrl.repetitive and n_cca:
        n = int(round(n_cca / freq / ts)) + 1          # the CCA after learning: period n_cca from rest
        win = slice(n - n1, n)
    else:
        # the reading's window: the whole record of cfg.periods from rest, or its last whole period
        n = int(round(cfg.periods / freq / ts)) + 1
        win = slice(0, n) if cfg.reading.sine_window == "whole" else slice(n - n1, n)
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
    summary["reading"] = next((n for n, rd in NAMED_READINGS.items() if rd == cfg.reading), "custom")
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
        # the baseline over the CCA's own window (differs from the row when the CCA is measured after learning)
        bw = tracking_metrics(b.sim.err_mm[c.window])[1]
        s[f"std_baseline_cca_window_{tag}hz_um"] = bw
        s[f"std_reduction_same_window_{tag}hz_pct"] = reduction_pct(bw, c.std_um)
    return s


# ---------------------------------------------------------------- measured traces / drive logs

#: options of ``markcal servo --trace`` (and of ``[servo]`` in batch.toml)
TRACE_OPTIONS = {"settle_band_um": 1.0, "settle_band_pct": 0.0, "time_col": "t_s", "ref_col": "ref_mm",
                 "pos_col": "pos_mm", "time_unit": "s", "pos_unit": "mm", "counts_per_mm": 0.0, "no_report": False}


@dataclass(frozen=True)
class TraceAnalysis:
    """A drive log and what was measured on it (moves or sinusoidal tracking)."""

    log: DriveLog
    kind: str                          # moves | tracking
    moves: Moves | None
    move_cols: dict | None             # per-move metrics, ``MOVE_COLUMNS``
    sine: SineMetrics | None


_ROLE_OPTION = {"time": "time_col", "reference": "ref_col", "position": "pos_col"}


def resolve_columns(header, options: dict) -> dict:
    """Fill in columns (and the units their names carry) a log names differently from the defaults.

    ``header`` is the log's header row (empty when it has none). A column option
    left at its default (``t_s``, ``ref_mm``, ``pos_mm``) that the header lacks is
    replaced by the column :func:`guess_columns` finds for that role ("time_ms",
    "demand", "actual", ...); the time unit (and a position unit of µm) follows the
    guessed column's name when its option is at its default. Anything given
    explicitly is kept.
    """
    o = dict(options)
    low = {h.lower() for h in header}
    guess = guess_columns(header) if header else {}
    for role, key in _ROLE_OPTION.items():
        if o[key] != TRACE_OPTIONS[key] or str(o[key]).lower() in low or role not in guess:
            continue
        name, unit = guess[role]
        o[key] = name
        if role == "time" and unit in ("ms", "us") and o["time_unit"] == TRACE_OPTIONS["time_unit"]:
            o["time_unit"] = unit
        if role == "position" and unit == "um" and o["pos_unit"] == TRACE_OPTIONS["pos_unit"]:
            o["pos_unit"] = unit
    return o


def read_trace(path, options: dict | None = None) -> tuple:
    """Read and check a drive log with the trace options (columns, units); see :func:`read_log`.

    Columns named otherwise than the defaults are found by :func:`resolve_columns`
    (the header is read once). Refused: a missing or non-numeric column, fewer
    than 20 rows, time out of order or repeated, gaps over 10 samples, a
    reference that never moves.

    Returns
    -------
    log, options
        The :class:`DriveLog` and the options with the columns and units it was read with.
    """
    o = {**TRACE_OPTIONS, **(options or {})}
    try:
        layout = sniff_layout(path)
    except MarkcalError:
        layout = None                              # read_log reports the problem, after the units' check
    o = resolve_columns(layout.header if layout else (), o)
    log = read_log(path, o["time_col"], o["ref_col"], o["pos_col"], o["time_unit"], o["pos_unit"],
                   float(o["counts_per_mm"]), layout=layout)
    check_log(log, os.fspath(path))
    return log, o


def _band(options) -> tuple:
    um, pct = float(options["settle_band_um"]), float(options["settle_band_pct"])
    if pct:
        if not (0 < pct < 100):
            raise MarkcalError(f"settle_band_pct must be in (0, 100) (got {pct:g})")
        return None, pct
    if not um > 0:
        raise MarkcalError(f"settle_band_um must be positive (got {um:g})")
    return um, None


def check_trace_options(options: dict) -> None:
    """Refuse bad drive-log options (settle band, units, counts per mm, empty column names)."""
    _band(options)
    check_log_units(options["time_unit"], options["pos_unit"], float(options["counts_per_mm"]))
    for k in ("time_col", "ref_col", "pos_col"):
        if not str(options[k]).strip():
            raise MarkcalError(f"{k} must name a column (got an empty name)")


def run_servo_trace(path, options: dict | None = None, progress=None) -> ServoResult:
    """Metrics of a measured drive log: per move (and statistics over them), or sinusoidal tracking."""
    say = progress or (lambda msg: None)
    o = {**TRACE_OPTIONS, **(options or {})}
    abs_um, band_pct = _band(o)
    t0 = time.perf_counter()
    path = os.fspath(path)
    log, o = read_trace(path, o)
    t, ref, pos = log.t_s, log.ref_mm, log.pos_mm
    say(f"read {len(t):,} samples ({', '.join(log.columns)})")
    mv = find_moves(ref)
    n = len(t)
    summary = {"kind": "servo", "mode": "trace", "n_samples": int(n), "ts_s": float(np.median(np.diff(t))),
               "duration_s": float(t[-1] - t[0]), "time_col": log.columns[0], "ref_col": log.columns[1],
               "pos_col": log.columns[2], "time_unit": o["time_unit"], "pos_unit": o["pos_unit"]}
    err = ref - pos
    if len(mv.lo) and mv.hold_fraction >= 0.2:
        cols = move_metrics(t, ref, pos, mv, abs_um, band_pct)
        say(f"{len(mv.lo)} moves cut at the reference's steps")
        runs = [Run("trace", "measured", float(abs(cols["stroke_mm"][k])), float("nan"),
                    float(cols["settling_time_s"][k]), float(cols["overshoot_um"][k]), float(cols["mae_um"][k]),
                    float(cols["std_um"][k]),
                    SimResult(t, ref, pos, np.empty(0), err), slice(mv.lo[k], mv.hi[k] + 1), float(cols["t_end_s"][k]))
                for k in range(len(mv.lo))]
        st = move_statistics(cols)
        settle = np.asarray(cols["settling_time_s"])
        summary.update({
            "trace_kind": "move", "n_moves": len(mv.lo), "n_settled": int(np.sum(np.isfinite(settle))),
            "log_ends_moving": mv.dropped_tail,
            "amplitude_mm": float(np.median(np.abs(cols["stroke_mm"]))), "frequency_hz": float("nan"),
            # worst move (what a tolerance judges): NaN settling when a move never settles
            "settling_time_s": float(np.max(settle)) if np.all(np.isfinite(settle)) else float("nan"),
            "overshoot_um": float(np.max(cols["overshoot_um"])),
            "overshoot_pct": float(np.max(cols["overshoot_pct"])),
            "rise_time_s": float(np.nanmax(cols["rise_time_s"])) if np.any(np.isfinite(cols["rise_time_s"]))
            else float("nan"),
            "steady_state_error_um": float(cols["steady_state_error_um"][np.argmax(np.abs(cols["steady_state_error_um"]))]),
            **st, "phase_lag_deg": float("nan"), "phase_lag_s": float("nan"), "gain": float("nan")})
        sw = slice(int(mv.lo[0]), int(mv.hi[-1]) + 1)
        mae, std = tracking_metrics(err[sw])
        analysis = TraceAnalysis(log, "moves", mv, cols, None)
    else:
        sm = sine_metrics(t, ref, pos)
        say(f"tracking log: {sm.frequency_hz:.4g} Hz, phase lag {sm.phase_lag_deg:.3f} deg")
        mae, std = sm.mae_um, sm.std_um
        runs = [Run("trace", "measured", sm.amplitude_mm, sm.frequency_hz, float("nan"), float("nan"), mae, std,
                    SimResult(t, ref, pos, np.empty(0), err), sm.window)]
        summary.update({"trace_kind": "tracking", "n_moves": 0, "amplitude_mm": sm.amplitude_mm,
                        "frequency_hz": sm.frequency_hz, "settling_time_s": float("nan"),
                        "overshoot_um": float("nan"), "phase_lag_deg": sm.phase_lag_deg,
                        "phase_lag_s": sm.phase_lag_s, "gain": sm.gain})
        analysis = TraceAnalysis(log, "tracking", None, None, sm)
    summary.update({"mae_um": mae, "std_um": std,
                    "settle_band_um": abs_um if band_pct is None else float("nan"),
                    "settle_band_pct": band_pct if band_pct is not None else float("nan"),
                    "runtime_s": time.perf_counter() - t0, "source": path})
    return ServoResult(path, "trace", None, runs, None, None, None, summary, trace=analysis)


def _claims(path) -> bool:
    if file_ext(path) not in (".csv", ".tsv", ".txt", ".log", ".dat"):
        return False
    try:
        lay = sniff_layout(path)
    except MarkcalError:
        return False
    if {"t_s", "ref_mm", "pos_mm"} <= {h.lower() for h in lay.header}:
        return True
    return len(guess_columns(lay.header)) == 3        # e.g. time_ms, demand, actual


def _run_trace(path, spec, options, progress=None) -> ServoResult:
    return run_servo_trace(path, options, progress=progress)


FLOW = FlowDescriptor(
    name="servo", help="macro-stage servo: composite controller vs baseline, or a measured drive log",
    claims=_claims, run=_run_trace,
    options=dict(TRACE_OPTIONS), validate_options=check_trace_options,
    key_figures=(Figure("trace_kind", "trace kind"), Figure("mae_um", "servo mean absolute tracking error", "µm"),
                 Figure("std_um", "tracking error STD", "µm"), Figure("settling_time_s", "settling time (worst move)", "s"),
                 Figure("overshoot_um", "overshoot (worst move)", "µm"), Figure("n_moves", "moves"),
                 Figure("phase_lag_deg", "phase lag", "°")),
    tolerances={"max_overshoot_um": 6.0},
    trends=("mae_um",), cost=0.5)
