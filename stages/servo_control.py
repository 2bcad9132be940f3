"""Controllers of the composite control algorithm (CCA) of paper 003 sec. 4.

* tracking differentiator with Han's ``fst2`` (eqs. 14-15),
* gain-scheduled PID (eqs. 16-17) and velocity feed-forward,
* plug-in repetitive controller ``Gprc(z) = kr z^m Cf(z) z^-D / (1 - Cf(z) z^-D)``
  with ``Cf(z) = tau / (1 - (1 - tau) z^-1)`` (eqs. 18-19),
* the small-gain stability condition of eq. 24, evaluated on a frequency grid.

Units: errors and positions mm, velocities mm/s, controller output V, time s.
The garbled equations are read as follows (stated so a reader can check them):

* eq. 16: ``u = Kpgs (Kp e + Kd de/dt) + (1/Ki) integral(e dt)`` -- the paper writes
  the integral coefficient as ``1/Ki``; markcal keeps that (``ki`` is the divisor).
* eq. 17: ``Kpgs = delta`` for ``|e| <= phi``, ``1`` for ``|e| > phi``.
* eq. 15 is Han's ``fst2`` with the usual minus signs (it drives ``x3 - xd`` to zero).
* eq. 19: ``Cf(z) = tau / (1 - z^-1 (1 - tau))``, unit DC gain, 0 < tau < 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from markcal.stages.errors import MarkcalError
from markcal.stages.servo_plant import DiscretePlant, plant_frequency_response

__all__ = ["PIDGains", "RepetitiveParams", "StabilityCheck", "fst2", "tracking_differentiator",
           "pid_frequency_response", "closed_loop_poles", "check_rc_stability"]


@dataclass(frozen=True)
class PIDGains:
    """Velocity feed-forward + gain-scheduled PID (paper eqs. 16-17, sec. 5.1 values).

    Attributes
    ----------
    kf : float
        Velocity feed-forward, V per mm/s (paper 0.000055).
    kp : float
        Proportional gain, V/mm (paper 85.572).
    ki : float
        Integral *divisor*: the integral term is ``(1/ki) * integral(e dt)``, mm s (paper 0.422).
    kd : float
        Derivative gain, V s/mm (paper 0.193).
    r0 : float
        Tracking-differentiator speed factor, mm/s^2 (paper 1,000,000).
    phi_mm : float
        Half width of the gain-scheduling zone, mm (paper 0.1).
    delta : float
        Scheduling coefficient inside the zone, 0 < delta <= 5 (paper 1.5).
    """

    kf: float = 0.000055
    kp: float = 85.572
    ki: float = 0.422
    kd: float = 0.193
    r0: float = 1_000_000.0
    phi_mm: float = 0.1
    delta: float = 1.5

    def check(self) -> None:
        """Refuse negative or non-finite gains, with the reason."""
        for name in ("kf", "kp", "kd"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise MarkcalError(f"gain {name} = {v} refused: gains must be finite and non-negative "
                                   "(a negative gain turns negative feedback into positive feedback)")
        if not (self.ki > 0):
            raise MarkcalError(f"gain ki = {self.ki} refused: ki divides the integral term (1/ki), "
                               "it must be positive (use inf for no integral action)")
        if not (np.isfinite(self.r0) and self.r0 > 0):
            raise MarkcalError(f"r0 = {self.r0} refused: the tracking-differentiator speed factor must be positive")
        if not (np.isfinite(self.phi_mm) and self.phi_mm >= 0):
            raise MarkcalError(f"phi_mm = {self.phi_mm} refused: the scheduling zone must be non-negative")
        if not (np.isfinite(self.delta) and 0 < self.delta <= 5):
            raise MarkcalError(f"delta = {self.delta} refused: the scheduling coefficient must be in (0, 5] "
                               "(paper eq. 17)")

    @property
    def ki_inv(self) -> float:
        """Integral gain ``1/ki`` (V per mm s)."""
        return 0.0 if np.isinf(self.ki) else 1.0 / self.ki


@dataclass(frozen=True)
class RepetitiveParams:
    """Plug-in repetitive controller (paper eqs. 18-19, sec. 5.2 values).

    Attributes
    ----------
    tau : float
        Filter coefficient of ``Cf(z)``, 0 < tau < 1 (paper 0.085).
    kr : float
        Repetitive gain (paper 0.95).
    m : int
        Lead of the compensator ``Qb(z) = z^m``, samples (paper 100).
    """

    tau: float = 0.085
    kr: float = 0.95
    m: int = 100

    def check(self) -> None:
        if not (np.isfinite(self.tau) and 0 < self.tau < 1):
            raise MarkcalError(f"repetitive tau = {self.tau} refused: Cf(z) needs 0 < tau < 1 (paper eq. 19)")
        if not (np.isfinite(self.kr) and self.kr > 0):
            raise MarkcalError(f"repetitive gain kr = {self.kr} refused: it must be positive")
        if int(self.m) != self.m or self.m < 0:
            raise MarkcalError(f"repetitive lead m = {self.m} refused: it must be a whole number >= 0")


@njit(cache=True)
def fst2(x: float, v: float, r0: float, ts: float) -> float:
    """Han's optimal synthesis function (paper eq. 15).

    Parameters
    ----------
    x : float
        Position error of the differentiator, ``x3 - xd`` (mm).
    v : float
        Its velocity ``x4`` (mm/s).
    r0 : float
        Speed factor (mm/s^2).
    ts : float
        Step (s).

    Returns
    -------
    float
        Acceleration command (mm/s^2), bounded by ``r0``.
    """
    d = ts * r0
    d0 = ts * d
    y = x + ts * v
    a0 = np.sqrt(d * d + 8.0 * r0 * abs(y))
    if abs(y) > d0:
        a = v + 0.5 * (a0 - d) * np.sign(y)
    else:
        a = v + y / ts
    if abs(a) > d:
        return -r0 * np.sign(a)
    return -r0 * a / d


@njit(cache=True)
def _td_loop(xd, r0, ts):
    n = xd.shape[0]
    x3 = np.empty(n)
    x4 = np.empty(n)
    p = xd[0]
    v = 0.0
    for k in range(n):
        x3[k] = p
        x4[k] = v
        pn = p + ts * v
        v = v + ts * fst2(p - xd[k], v, r0, ts)
        p = pn
    return x3, x4


def tracking_differentiator(xd_mm: np.ndarray, r0: float, ts_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete tracking differentiator (paper eq. 14).

    Parameters
    ----------
    xd_mm : (n,) array
        Desired trajectory, mm, sampled every ``ts_s``.
    r0 : float
        Speed factor, mm/s^2.
    ts_s : float
        Sampling period, s.

    Returns
    -------
    x3_mm, x4_mm_s : (n,) arrays
        Smoothed trajectory (mm) and its derivative (mm/s); starts at rest at ``xd[0]``.
    """
    xd = np.ascontiguousarray(xd_mm, dtype=float)
    return _td_loop(xd, float(r0), float(ts_s))


def pid_frequency_response(g: PIDGains, z: np.ndarray, ts_s: float, schedule: float = 1.0) -> np.ndarray:
    """Discrete PID (backward differences) ``Ggs(z)`` at ``z``, V/mm, with ``Kpgs = schedule``."""
    zi = 1.0 / z
    return schedule * (g.kp + g.kd * (1 - zi) / ts_s) + g.ki_inv * ts_s / (1 - zi)


def closed_loop_poles(dp: DiscretePlant, g: PIDGains, schedule: float = 1.0) -> np.ndarray:
    """Poles of the PID loop without repetitive control, ``1 + Ggs Gn = 0`` (z-plane)."""
    A, B, ts = dp.A, dp.B, dp.params.ts_s
    ng = np.array([B[0], A[0, 1] * B[1] - A[1, 1] * B[0]])          # Gn numerator in z
    dg = np.array([1.0, -(A[0, 0] + A[1, 1]), A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]])
    # C(z) = [s Kp z(z-1) + s Kd/ts (z-1)^2 + ki_inv ts z^2] / (z (z - 1))
    nc = (schedule * g.kp * np.array([1.0, -1.0, 0.0]) + schedule * g.kd / ts * np.array([1.0, -2.0, 1.0])
          + g.ki_inv * ts * np.array([1.0, 0.0, 0.0]))
    dc = np.array([1.0, -1.0, 0.0]) if g.ki_inv > 0 else np.array([0.0, 1.0, 0.0])
    char = np.polyadd(np.polymul(dc, dg), np.polymul(nc, ng))
    char = np.trim_zeros(char, "f")
    return np.roots(char)


@dataclass(frozen=True)
class StabilityCheck:
    """Result of the eq. 24 check (and of the loop without RC it presumes).

    ``margin = 1 - max_w |Cf (1 - (1 - S^) kr Qb)|``; stable when ``ok``.
    """

    ok: bool
    margin: float
    max_gain: float
    worst_freq_hz: float
    pid_pole_radius: float
    reason: str


def check_rc_stability(dp: DiscretePlant, g: PIDGains, rc: RepetitiveParams | None,
                       n_freq: int = 4000) -> StabilityCheck:
    """Check the loop without RC (all poles inside the unit circle) and eq. 24.

    Both sides of the gain schedule (``Kpgs = 1`` and ``delta``) are checked,
    since the loop switches between them. ``rc=None`` checks the PID loop only.
    """
    ts = dp.params.ts_s
    schedules = sorted({1.0, float(g.delta)})
    radius = max(float(np.max(np.abs(closed_loop_poles(dp, g, s)))) for s in schedules)
    if radius >= 1.0:
        return StabilityCheck(False, float(1.0 - radius), float("nan"), float("nan"), radius,
                              f"the PID loop without repetitive control is unstable (largest pole radius "
                              f"{radius:.4f} >= 1), so eq. 24 does not apply")
    if rc is None:
        return StabilityCheck(True, float(1.0 - radius), float("nan"), float("nan"), radius,
                              f"PID loop stable (largest pole radius {radius:.4f})")
    w = np.linspace(0.0, np.pi / ts, n_freq, endpoint=False)[1:]
    z = np.exp(1j * w * ts)
    gn = plant_frequency_response(dp, z)
    cf = rc.tau / (1.0 - (1.0 - rc.tau) / z)
    worst, worst_w = -1.0, 0.0
    for s in schedules:
        L = pid_frequency_response(g, z, ts, s) * gn
        T = L / (1.0 + L)
        val = np.abs(cf * (1.0 - T * rc.kr * z ** int(rc.m)))
        i = int(np.argmax(val))
        if val[i] > worst:
            worst, worst_w = float(val[i]), float(w[i])
    f_hz = worst_w / (2 * np.pi)
    ok = worst < 1.0
    if ok:
        reason = (f"eq. 24 holds: max |Cf (1 - T kr z^m)| = {worst:.4f} < 1 (at {f_hz:.1f} Hz), "
                  f"margin {1 - worst:.4f}")
    else:
        reason = (f"eq. 24 violated: |Cf (1 - T kr z^m)| reaches {worst:.4f} >= 1 at {f_hz:.1f} Hz "
                  f"(tau={rc.tau}, kr={rc.kr}, m={rc.m}); the repetitive controller would diverge")
    return StabilityCheck(ok, float(1.0 - worst), worst, f_hz, radius, reason)
