"""Online drift compensation from a periodically measured reference array (paper 000 eqs. 10-11).

Every estimator here is causal: the compensation ``C_k`` is computed from the
samples up to ``t_k`` and stays in force until ``t_{k+1}``; the corrected error
is ``drift − C``. Times in minutes, lengths in µm, arrays (K, 3) for x, y, z.

Eq. 10 of the source text reads ``ΔC(t) = ΔC_GA + α·ΔE_dyn(t) + (1 − α)·ΔC(t − 1)``
(the minus sign is lost in the text). If ΔE_dyn were the increment since the
previous sample the filter would smooth increments and could never follow a
drift level; the paper calls it "a first-order exponential smoothing filter
applied to the dynamic-error signal", so ``paper_filter`` smooths the measured
drift level m_k (relative to the initial calibrated state). The printed formula
puts α on the new sample, C_k = α·m_k + (1 − α)·C_{k−1}; the text says twice
the opposite ("a larger α retains a longer history", "smaller values caused the
compensation to overreact to short-term fluctuations"), i.e. C_k = (1 − α)·m_k +
α·C_{k−1}. Only the text's reading reproduces the paper's Table 2 (η ≈ 76-78 %
on a slow monotonic drift; the printed one gives ≈ 94 %, hardly different from
holding the last sample), so method ``paper`` is the text's reading and
``paper-literal`` the printed one. C_GA (the static GA correction) is 0 here: the
drift record is relative to the calibrated state.
"""
from __future__ import annotations

import numpy as np

__all__ = ["METHODS", "paper_filter", "hold_last", "kalman_cv", "kalman_bank", "compensate",
           "in_force", "reduction_rate", "sample_reduction_rate"]

#: compensation methods: name -> one-line description
METHODS = {
    "kalman": "Bayesian model average of local-level and damped-trend (thermal approach) Kalman filters weighted by their "
              "past predictive likelihood, predicting the mean level over the next interval",
    "paper": "the paper's eq. 10 as its text describes it: exponential smoothing with memory α = 0.8",
    "paper-literal": "eq. 10 as printed: α = 0.8 on the new sample",
    "hold": "hold the last measurement",
    "trend": "one constant-velocity Kalman filter (fixed process noise) predicting to mid-interval",
}

#: local-level (random-walk) members of the model average: level process-noise densities, µm²/min
LEVEL_Q = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3)
#: damped-trend members (a thermal approach): level noise densities, µm²/min
TREND_QL = (1e-6, 1e-5, 1e-4)
#: damped-trend members: velocity noise density, µm²/min³, velocity damping time, min, and prior velocity σ, µm/min
TREND_QV, TREND_TAU_MIN, TREND_V0_UM_MIN = 1e-8, 50.0, 0.01
#: log prior odds (nats) of each damped-trend member against a level member (Occam penalty for the extra state)
TREND_PENALTY = 3.0


def paper_filter(meas_um: np.ndarray, alpha: float = 0.8, c_ga_um=0.0, memory: bool = False) -> np.ndarray:
    """Eq. 10 (reconstructed, see the module docstring): exponential smoothing of the measured drift."""
    m = np.asarray(meas_um, float)
    c = np.zeros_like(m)
    prev = np.zeros(m.shape[1:])
    for k in range(len(m)):
        prev = ((1 - alpha) * m[k] + alpha * prev) if memory else (alpha * m[k] + (1 - alpha) * prev)
        c[k] = prev
    return c + c_ga_um


def hold_last(meas_um: np.ndarray) -> np.ndarray:
    """C_k = m_k."""
    return np.asarray(meas_um, float).copy()


def _kf_run(t, m, q, r):
    """Constant-velocity Kalman filter on one axis; returns (position, velocity) estimates at each t_k."""
    x = np.array([m[0], 0.0])
    p = np.diag([r, 1e-4])
    pos, vel = np.empty(len(m)), np.empty(len(m))
    pos[0], vel[0] = x
    for k in range(1, len(m)):
        dt = t[k] - t[k - 1]
        f = np.array([[1.0, dt], [0.0, 1.0]])
        qk = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
        x = f @ x
        p = f @ p @ f.T + qk
        s = p[0, 0] + r
        g = p[:, 0] / s
        x = x + g * (m[k] - x[0])
        p = p - np.outer(g, p[0])
        pos[k], vel[k] = x
    return pos, vel


def kalman_cv(t_min: np.ndarray, meas_um: np.ndarray, q: float = 1e-6, noise_um: float = 0.005) -> np.ndarray:
    """One constant-velocity Kalman filter per axis, compensation predicted to the middle of the next interval."""
    t = np.asarray(t_min, float)
    m = np.asarray(meas_um, float)
    half = 0.5 * np.append(np.diff(t), np.diff(t)[-1:] if len(t) > 1 else [0.0])
    c = np.zeros_like(m)
    for ax in range(m.shape[1]):
        pos, vel = _kf_run(t, m[:, ax], q, noise_um ** 2)
        c[:, ax] = pos + vel * half
    return c


def _bank_run(t, m, lam, ql, qv, pv0, r):
    """Run N two-state (level, velocity) Kalman filters on one axis at once.

    Velocity decays with rate ``lam`` (1/min; 0 = constant velocity), the level takes random-walk
    noise ``ql`` (µm²/min), the velocity ``qv`` (µm²/min³); ``pv0`` is the prior velocity variance
    (0 keeps a member a pure local level). Returns (mid (N, K): the mean level predicted over
    [t_k, t_k + Δt_k], loglik (N, K): Gaussian log density of each sample's innovation, 0 at k = 0).
    """
    n, kk = len(lam), len(m)
    dts = np.append(np.diff(t), np.diff(t)[-1:] if kk > 1 else [0.0])

    def coefs(dt):
        e = np.exp(-lam * dt)
        safe = np.where(lam > 0, lam, 1.0)
        g = np.where(lam > 0, (1 - e) / safe, dt)              # level gain of the velocity over dt
        h = np.where(lam > 0, (dt - g) / (safe * max(dt, 1e-12)), dt / 2)  # mean of g(s) over [0, dt]
        return e, g, h

    x0, x1 = np.full(n, m[0]), np.zeros(n)
    p00, p01, p11 = np.full(n, r), np.zeros(n), pv0.astype(float)
    mid, ll = np.empty((n, kk)), np.zeros((n, kk))
    for k in range(kk):
        if k > 0:
            dt = t[k] - t[k - 1]
            e, g, _ = coefs(dt)
            x0, x1 = x0 + g * x1, e * x1
            p00, p01, p11 = (p00 + 2 * g * p01 + g * g * p11 + ql * dt + qv * dt ** 3 / 3,
                             e * (p01 + g * p11) + qv * dt ** 2 / 2, e * e * p11 + qv * dt)
            p11 = np.where(pv0 > 0, p11, 0.0)
            p01 = np.where(pv0 > 0, p01, 0.0)
            s = p00 + r
            nu = m[k] - x0
            ll[:, k] = -0.5 * (np.log(2 * np.pi * s) + nu * nu / s)
            g0, g1 = p00 / s, p01 / s
            x0, x1 = x0 + g0 * nu, x1 + g1 * nu
            p00, p01, p11 = p00 - g0 * p00, p01 - g0 * p01, p11 - g1 * p01
        _, _, h = coefs(dts[k])
        mid[:, k] = x0 + h * x1
    return mid, ll


def kalman_bank(t_min: np.ndarray, meas_um: np.ndarray, noise_um: float = 0.005, level_q=LEVEL_Q,
                trend_ql=TREND_QL, trend_penalty: float = TREND_PENALTY) -> np.ndarray:
    """Bayesian model average of local-level and damped-trend Kalman filters, per axis.

    Members: local-level (random-walk) filters with process noise ``level_q`` (µm²/min), and
    level + damped-velocity filters (a thermal approach: velocity decaying with time constant
    ``TREND_TAU_MIN``, level noise ``trend_ql``). At ``t_k`` each member's weight is its prior
    (``-trend_penalty`` nats for a trend member) plus the summed log predictive density of the
    samples up to ``t_k``; ``C_k`` is the weighted mean of the members' level averaged over the
    next interval. A trend therefore moves the compensation only once the record shows it (on a
    wandering drift the level members win and the estimate stays near the last measurement).
    Causal and deterministic; ``meas_um`` (K, 3) µm, ``t_min`` (K,) min, returns (K, 3) µm.
    """
    t = np.asarray(t_min, float)
    m = np.asarray(meas_um, float)
    nl, nt = len(level_q), len(trend_ql)
    lam = np.r_[np.zeros(nl), np.full(nt, 1.0 / TREND_TAU_MIN)]
    ql = np.r_[np.asarray(level_q, float), np.asarray(trend_ql, float)]
    qv = np.r_[np.zeros(nl), np.full(nt, TREND_QV)]
    pv0 = np.r_[np.zeros(nl), np.full(nt, TREND_V0_UM_MIN ** 2)]
    prior = np.r_[np.zeros(nl), np.full(nt, -float(trend_penalty))]
    c = np.zeros_like(m)
    for ax in range(m.shape[1]):
        mid, ll = _bank_run(t, m[:, ax], lam, ql, qv, pv0, noise_um ** 2)
        score = prior[:, None] + np.cumsum(ll, axis=1)
        w = np.exp(score - score.max(axis=0))
        c[:, ax] = (w * mid).sum(axis=0) / w.sum(axis=0)
    return c


def compensate(t_min: np.ndarray, meas_um: np.ndarray, method: str = "kalman", alpha: float = 0.8,
               noise_um: float = 0.005) -> np.ndarray:
    """Compensation C_k (µm, (K, 3)) at each sample by ``method`` (see ``METHODS``)."""
    if method == "paper":
        return paper_filter(meas_um, alpha, memory=True)
    if method == "paper-literal":
        return paper_filter(meas_um, alpha)
    if method == "hold":
        return hold_last(meas_um)
    if method == "trend":
        return kalman_cv(t_min, meas_um, 1e-6, noise_um)
    if method == "kalman":
        return kalman_bank(t_min, meas_um, noise_um)
    raise ValueError(f"unknown drift method {method!r} (choose from {', '.join(METHODS)})")


def in_force(t_sample_min: np.ndarray, comp_um: np.ndarray, t_min: np.ndarray) -> np.ndarray:
    """The compensation in force at times ``t_min``: C_k for t_k ≤ t < t_{k+1}; 0 before t_0."""
    idx = np.searchsorted(np.asarray(t_sample_min, float), np.asarray(t_min, float), side="right") - 1
    out = np.where(idx[:, None] >= 0, comp_um[np.clip(idx, 0, None)], 0.0)
    return out


def reduction_rate(drift_um: np.ndarray, comp_um: np.ndarray) -> tuple:
    """Eq. 11 per axis: η = (|Ē_pre| − |Ē_post|)/|Ē_pre| with Ē the mean absolute error.

    Returns (e_pre_um (3,), e_post_um (3,), eta_pct (3,)).
    """
    pre = np.mean(np.abs(drift_um), axis=0)
    post = np.mean(np.abs(drift_um - comp_um), axis=0)
    return pre, post, 100.0 * (pre - post) / np.where(pre > 0, pre, np.nan)


def sample_reduction_rate(meas_um: np.ndarray, comp_um: np.ndarray) -> tuple:
    """Eq. 11 seen at the samples alone: the error at t_{k+1} is m_{k+1} − C_k (k ≥ 0)."""
    return reduction_rate(meas_um[1:], comp_um[:-1])
