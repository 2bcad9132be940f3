"""Discrete-time closed-loop simulation of the macro stage and the servo metrics.

The loop runs once per sample (numba); everything that does not depend on the
loop (reference, differentiation, tracking differentiator, metrics) is computed
on whole arrays. Positions mm, time s, controller output V.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from markcal.stages.errors import MarkcalError
from markcal.stages.servo_control import PIDGains, RepetitiveParams, tracking_differentiator
from markcal.stages.servo_plant import DiscretePlant
from markcal.stages.servo_profile import Profile

__all__ = ["Controller", "SimResult", "simulate", "StepMetrics", "step_metrics", "tracking_metrics",
           "BASELINE", "CCA_STEP", "CCA_TRACK"]


@dataclass(frozen=True)
class Controller:
    """Which parts of the composite controller are switched on.

    Attributes
    ----------
    name : str
        ``baseline`` or ``cca`` (the label in metrics.csv).
    tracking_differentiator : bool
        Reference and feed-forward velocity from the TD (eq. 14); otherwise the
        reference itself and its backward difference ("direct differentiation").
    gain_schedule : bool
        ``Kpgs = delta`` inside ``|e| <= phi`` (eq. 17); otherwise ``Kpgs = 1``.
    repetitive : bool
        Plug-in repetitive controller (eq. 18), period = the reference period.
    """

    name: str
    tracking_differentiator: bool = False
    gain_schedule: bool = False
    repetitive: bool = False


#: feed-forward + PID (the paper's "without CCA")
BASELINE = Controller("baseline")
#: paper Fig. 4: TD + velocity feed-forward + gain-scheduled PID (point-to-point)
CCA_STEP = Controller("cca", tracking_differentiator=True, gain_schedule=True)
#: paper Fig. 7: feed-forward (direct differentiation) + gain-scheduled PID + plug-in RC (tracking)
CCA_TRACK = Controller("cca", gain_schedule=True, repetitive=True)


@dataclass(frozen=True)
class SimResult:
    """One simulated run: sample times, desired and error reference, position, command."""

    t_s: np.ndarray
    ref_mm: np.ndarray        # desired trajectory xd
    pos_mm: np.ndarray        # stage position x1 (encoder)
    u_v: np.ndarray           # controller output
    err_mm: np.ndarray        # xd - x1


@njit(cache=True)
def _loop(A, B, r, vff, kf, kp, ki_inv, kd, phi, delta, ts, rc_D, rc_m, tau, kr, u_max, friction_v, d_alpha):
    n = r.shape[0]
    y = np.empty(n)
    u_out = np.empty(n)
    f = np.zeros(n)                       # repetitive-controller filter state Cf[w + e]
    x0 = r[0]
    x1 = 0.0
    e_prev = r[0] - x0
    integ = 0.0
    de_f = 0.0
    for k in range(n):
        y[k] = x0
        e = r[k] - x0
        s = delta if abs(e) <= phi else 1.0
        if rc_D > 0:
            # plug-in RC (paper Fig. 7, eq. 20): its output is added to the error ahead of Ggs.
            # w(k) = f(k - D); f(k) = (1 - tau) f(k-1) + tau (w(k) + e(k)); u_rc(k) = kr f(k - D + m)
            w = f[k - rc_D] if k >= rc_D else 0.0
            fp = f[k - 1] if k >= 1 else 0.0
            f[k] = (1.0 - tau) * fp + tau * (w + e)
            j = k - rc_D + rc_m
            if j >= 0:
                e += kr * f[j]
        de = (e - e_prev) / ts
        e_prev = e
        de_f = d_alpha * de_f + (1.0 - d_alpha) * de      # first-order derivative filter (d_alpha 0: none)
        integ += e * ts
        u = kf * vff[k] + s * (kp * e + kd * de_f) + ki_inv * integ
        if u > u_max:
            u = u_max
        elif u < -u_max:
            u = -u_max
        u_out[k] = u
        ua = u
        if friction_v > 0.0 and x1 != 0.0:
            ua -= friction_v * np.sign(x1)
        n0 = A[0, 0] * x0 + A[0, 1] * x1 + B[0] * ua
        n1 = A[1, 0] * x0 + A[1, 1] * x1 + B[1] * ua
        x0 = n0
        x1 = n1
    return y, u_out


def simulate(dp: DiscretePlant, gains: PIDGains, profile: Profile, controller: Controller,
             rc: RepetitiveParams | None = None, period_s: float | None = None,
             u_max_v: float = np.inf, friction_v: float = 0.0, d_filter_hz: float = np.inf,
             ff_order: int = 1) -> SimResult:
    """Simulate the closed loop on ``profile``.

    Parameters
    ----------
    dp : DiscretePlant
        The discretised stage; its ``ts_s`` must be the profile's sample step.
    gains : PIDGains
        Feed-forward, PID, TD and scheduling parameters.
    profile : Profile
        Desired trajectory (mm).
    controller : Controller
        Which CCA parts are on.
    rc, period_s : RepetitiveParams, float
        Needed when ``controller.repetitive``: the RC and the reference period (s).
    u_max_v : float
        Symmetric output saturation, V (default none).
    friction_v : float
        Coulomb friction expressed as an equivalent input voltage, V (default 0).
    d_filter_hz : float
        Corner of a first-order low-pass on the derivative term, Hz (default none).
    ff_order : int
        What ``Kf`` multiplies: 1 the reference velocity (paper), 2 its acceleration
        (a reading of the feed-forward), 0 nothing (no feed-forward).

    Returns
    -------
    SimResult
    """
    ts = dp.params.ts_s
    if len(profile.t_s) > 1 and not np.isclose(profile.t_s[1] - profile.t_s[0], ts, rtol=1e-9, atol=0):
        raise MarkcalError("profile sample step differs from the plant's Ts")
    xd = np.ascontiguousarray(profile.x_mm, dtype=float)
    if controller.tracking_differentiator:
        r, vff = tracking_differentiator(xd, gains.r0, ts)
    else:
        r = xd
        vff = np.empty_like(xd)
        vff[1:] = np.diff(xd) / ts
        vff[0] = 0.0
    for _ in range(int(ff_order) - 1):             # higher derivatives of the reference: backward differences
        vff = np.concatenate(([0.0], np.diff(vff) / ts))
    if ff_order == 0:
        vff = np.zeros_like(xd)
    rc_D = rc_m = 0
    tau = kr = 0.0
    if controller.repetitive:
        if rc is None or period_s is None:
            raise MarkcalError("the repetitive controller needs its parameters and the reference period")
        rc_D = int(round(period_s / ts))
        rc_m = int(rc.m)
        if rc_D <= rc_m:
            raise MarkcalError(f"repetitive delay D = {rc_D} samples must exceed the lead m = {rc_m}")
        tau, kr = float(rc.tau), float(rc.kr)
    ki_inv = gains.ki_inv
    phi = gains.phi_mm if controller.gain_schedule else -1.0
    d_alpha = 0.0 if np.isinf(d_filter_hz) else float(np.exp(-2 * np.pi * d_filter_hz * ts))
    y, u = _loop(dp.A, dp.B, r, vff, gains.kf, gains.kp, ki_inv, gains.kd, phi, gains.delta, ts,
                 rc_D, rc_m, tau, kr, float(u_max_v), float(friction_v), d_alpha)
    return SimResult(t_s=profile.t_s, ref_mm=xd, pos_mm=y, u_v=u, err_mm=xd - y)


@dataclass(frozen=True)
class StepMetrics:
    """Point-to-point metrics (paper Table 1) and error statistics over the record."""

    settling_time_s: float   # from the end of the reference until |x - target| stays <= band; NaN if never
    overshoot_um: float      # largest excursion past the target in the move direction, whole record (>= 0)
    mae_um: float
    std_um: float


def step_metrics(t_s: np.ndarray, ref_mm: np.ndarray, pos_mm: np.ndarray, t_end_s: float,
                 band_um: float = 1.0) -> StepMetrics:
    """Settling time, overshoot, MAE and STD of a point-to-point move.

    Parameters
    ----------
    t_s, ref_mm, pos_mm : (n,) arrays
        Time (s), reference and measured position (mm).
    t_end_s : float
        When the reference reached its final value (s).
    band_um : float
        Half width of the settling band, µm.
    """
    target = ref_mm[-1]
    stroke = target - ref_mm[0]
    sgn = 1.0 if stroke >= 0 else -1.0
    after = t_s >= t_end_s - 1e-12
    dev_um = (pos_mm - target) * 1e3
    over = float(max(0.0, np.max(sgn * dev_um)))     # peak past the target, anywhere in the record
    outside = np.flatnonzero(after & (np.abs(dev_um) > band_um))
    if outside.size == 0:
        settle = 0.0
    elif outside[-1] == len(t_s) - 1:
        settle = float("nan")                     # still outside the band at the end of the record
    else:
        settle = float(t_s[outside[-1] + 1] - t_end_s)
    e_um = (ref_mm - pos_mm) * 1e3
    return StepMetrics(settle, over, float(np.mean(np.abs(e_um))), float(np.std(e_um)))


def tracking_metrics(err_mm: np.ndarray) -> tuple[float, float]:
    """MAE and STD (population) of a tracking error, µm."""
    e_um = np.asarray(err_mm, dtype=float) * 1e3
    return float(np.mean(np.abs(e_um))), float(np.std(e_um))
