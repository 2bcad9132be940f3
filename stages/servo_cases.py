"""The servo flow's cases: configuration, the repetitive lead, per-case metrics, measured traces.

Positions mm, errors µm, time s, controller output V. The paper's own figures
(paper 003, Tables 1-2) are here too, so the flow and its report compare with them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from markcal.stages.errors import MarkcalError
from markcal.stages.servo_control import PIDGains, RepetitiveParams, StabilityCheck, check_rc_stability
from markcal.stages.servo_plant import PlantParams, discretise
from markcal.stages.servo_reading import DEFAULT_READING, Reading, reading_params, settle_band_um
from markcal.stages.servo_sim import SimResult


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


@dataclass(frozen=True)
class ServoConfig:
    """Everything the simulation needs; defaults are the paper's sec. 5 setup.

    ``rc_m = None`` means "auto": the lead with the largest eq. 24 margin.
    ``plant`` and ``gains`` hold the paper's numbers as printed; ``reading``
    says how they are read (units, forms; :mod:`markcal.stages.servo_reading`)
    and :func:`sim_model` gives them in markcal's units. ``settle_band_um =
    None`` takes the reading's band. Lengths mm, speeds mm/s, time s.
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
    periods: float = DEFAULT_READING.sine_periods
    settle_band_um: float | None = None
    u_max_v: float = math.inf
    friction_v: float = 0.0
    reading: Reading = DEFAULT_READING


def sim_model(cfg: ServoConfig) -> tuple[PlantParams, PIDGains]:
    """Plant and gains of ``cfg`` in markcal's units (mm, mm/s, V) under its reading."""
    return reading_params(cfg.reading, cfg.gains, cfg.plant)


def band_um(cfg: ServoConfig, stroke_mm: float) -> float:
    """The settling band half width for a move of ``stroke_mm``, µm."""
    return cfg.settle_band_um if cfg.settle_band_um is not None else settle_band_um(cfg.reading.band, stroke_mm)


def validate_config(cfg: ServoConfig) -> None:
    """Refuse non-physical or unstable settings (with the reason)."""
    cfg.plant.check()
    cfg.gains.check()
    cfg.reading.check()
    RepetitiveParams(cfg.rc_tau, cfg.rc_kr, 0 if cfg.rc_m is None else cfg.rc_m).check()
    if cfg.settle_band_um is not None and not (cfg.settle_band_um > 0):
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
    plant, gains = sim_model(cfg)
    dp = discretise(plant)
    paper = check_rc_stability(dp, gains, RepetitiveParams(cfg.rc_tau, cfg.rc_kr, PAPER_RC_M))
    if cfg.rc_m is None:
        if paper.pid_pole_radius >= 1:
            raise MarkcalError(f"unstable parameter set: {paper.reason}")
        best = None
        for m in AUTO_M_RANGE:
            c = check_rc_stability(dp, gains, RepetitiveParams(cfg.rc_tau, cfg.rc_kr, m), n_freq=1500)
            if best is None or c.margin > best[1].margin:
                best = (m, c)
        rc = RepetitiveParams(cfg.rc_tau, cfg.rc_kr, best[0])
    else:
        rc = RepetitiveParams(cfg.rc_tau, cfg.rc_kr, int(cfg.rc_m))
    check = check_rc_stability(dp, gains, rc)
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


def find_run(runs, case, controller, amplitude_mm, frequency_hz=None):
    """The run with these labels, or None."""
    for r in runs:
        if r.case == case and r.controller == controller and np.isclose(r.amplitude_mm, amplitude_mm) and (
                frequency_hz is None or np.isclose(r.frequency_hz, frequency_hz)):
            return r
    return None


def dominant_frequency_hz(t_s: np.ndarray, x: np.ndarray) -> float:
    """Frequency (Hz) of the strongest line of ``x(t)``: Hann-windowed FFT peak, parabolic refinement.

    ``t_s`` is uniformly sampled (s); the mean of ``x`` is removed first.
    """
    n = len(t_s)
    x = np.asarray(x, float) - np.mean(x)
    spec = np.abs(np.fft.rfft(x * np.hanning(n)))
    fr = np.fft.rfftfreq(n, d=float(np.median(np.diff(t_s))))
    k = int(np.argmax(spec[1:])) + 1
    # parabolic refinement of the peak
    if 1 <= k < len(spec) - 1:
        a, b, c = np.log(spec[k - 1] + 1e-300), np.log(spec[k] + 1e-300), np.log(spec[k + 1] + 1e-300)
        den = a - 2 * b + c
        k = k + (0.5 * (a - c) / den if den != 0 else 0.0)
    return float(k * (fr[1] - fr[0]))
