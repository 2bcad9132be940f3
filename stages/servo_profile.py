"""Reference trajectories for the servo flow (paper 003 sec. 5): S-curve moves and sinusoids.

Positions mm, time s, sampled every ``ts_s`` from t = 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from markcal.stages.errors import MarkcalError

__all__ = ["Profile", "s_curve", "sinusoid"]


@dataclass(frozen=True)
class Profile:
    """A sampled reference: ``t_s``, ``x_mm`` and the exact velocity ``v_mm_s``.

    ``t_end_s`` is when the reference reaches its final value (moves) or the
    length of the record (sinusoids).
    """

    t_s: np.ndarray
    x_mm: np.ndarray
    v_mm_s: np.ndarray
    t_end_s: float


def _trapezoid(t, dist, v, a):
    """Position (mm) of a trapezoidal-velocity move of ``dist`` (exact, piecewise quadratic)."""
    if dist < v * v / a:                       # triangle: the peak velocity is not reached
        v = np.sqrt(dist * a)
    ta = v / a
    tc = dist / v - ta                         # cruise duration
    T = 2 * ta + tc
    t = np.clip(t, 0.0, T)
    x = np.where(t < ta, 0.5 * a * t * t,
                 np.where(t < ta + tc, 0.5 * a * ta * ta + v * (t - ta),
                          dist - 0.5 * a * (T - t) ** 2))
    vel = np.where(t < ta, a * t, np.where(t < ta + tc, v, a * (T - t)))
    return x, vel, T


def s_curve(stroke_mm: float, v_mm_s: float = 100.0, a_mm_s2: float = 10_000.0,
            jerk_mm_s3: float = 1_000_000.0, ts_s: float = 1e-4, dwell_s: float = 0.3) -> Profile:
    """Jerk-limited (S-curve) point-to-point move from 0 to ``stroke_mm``.

    A trapezoidal-velocity move (limits ``v_mm_s``, ``a_mm_s2``) is averaged over
    a window ``Tj = a/jerk``, which bounds the jerk by ``jerk_mm_s3`` and keeps
    the velocity and acceleration limits. Defaults: paper 0.1 m/s, 10 m/s^2; the
    paper gives no jerk, markcal takes 1000 m/s^3 (Tj = 10 ms).

    Parameters
    ----------
    stroke_mm : float
        Signed move length, mm.
    dwell_s : float
        Time simulated after the reference has arrived, s.
    """
    for name, val in (("velocity", v_mm_s), ("acceleration", a_mm_s2), ("jerk", jerk_mm_s3)):
        if not ((np.isfinite(val) or name == "jerk") and val > 0):
            raise MarkcalError(f"S-curve {name} must be positive (got {val})")
    if not (np.isfinite(stroke_mm) and stroke_mm != 0):
        raise MarkcalError(f"S-curve stroke must be non-zero (got {stroke_mm})")
    if not (np.isfinite(dwell_s) and dwell_s > 0):
        raise MarkcalError(f"dwell_s must be positive (got {dwell_s})")
    dist = abs(stroke_mm)
    tj = a_mm_s2 / jerk_mm_s3
    nj = max(1, int(round(tj / ts_s)))
    _, _, T = _trapezoid(np.zeros(1), dist, v_mm_s, a_mm_s2)
    t_end = T + nj * ts_s
    n = int(np.ceil((t_end + dwell_s) / ts_s)) + 1
    t = np.arange(n) * ts_s
    # moving average over nj samples of the exact trapezoid position (= box-filtered velocity)
    tt = (np.arange(n + nj - 1) - (nj - 1)) * ts_s
    x0, v0, _ = _trapezoid(tt, dist, v_mm_s, a_mm_s2)
    kern = np.full(nj, 1.0 / nj)
    x = np.convolve(x0, kern, mode="valid")
    v = np.convolve(v0, kern, mode="valid")
    sgn = np.sign(stroke_mm)
    return Profile(t_s=t, x_mm=sgn * x, v_mm_s=sgn * v, t_end_s=float(t_end))


def sinusoid(amplitude_mm: float, frequency_hz: float, periods: float = 3.0, ts_s: float = 1e-4,
             phase_deg: float = 0.0) -> Profile:
    """``x = A sin(2 pi f t + phase)`` over ``periods`` periods (mm, mm/s).

    ``phase_deg = 0`` starts at 0 at full speed (a velocity step for a stage at
    rest); 90 starts at ``A`` with zero velocity.
    """
    if not (np.isfinite(amplitude_mm) and amplitude_mm > 0):
        raise MarkcalError(f"sine amplitude must be positive (got {amplitude_mm})")
    if not (np.isfinite(frequency_hz) and frequency_hz > 0):
        raise MarkcalError(f"sine frequency must be positive (got {frequency_hz})")
    if not (np.isfinite(periods) and periods >= 2):
        raise MarkcalError(f"sine periods must be >= 2 (got {periods}): the repetitive controller learns over one")
    n = int(round(periods / frequency_hz / ts_s)) + 1
    t = np.arange(n) * ts_s
    w = 2 * np.pi * frequency_hz
    ph = np.radians(phase_deg)
    return Profile(t_s=t, x_mm=amplitude_mm * np.sin(w * t + ph), v_mm_s=amplitude_mm * w * np.cos(w * t + ph),
                   t_end_s=float(t[-1]))
