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
    "kalman": "bank of constant-velocity and local-level Kalman filters and hold-last, the member with the smallest past one-step "
              "prediction error chosen at each sample, predicting to the middle of the next interval",
    "paper": "the paper's eq. 10 as its text describes it: exponential smoothing with memory α = 0.8",
    "paper-literal": "eq. 10 as printed: α = 0.8 on the new sample",
    "hold": "hold the last measurement",
    "trend": "one constant-velocity Kalman filter (fixed process noise) predicting to mid-interval",
}

#: process-noise densities (µm²/min³) of the Kalman bank; 0 is a pure straight-line trend
Q_BANK = (0.0, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
#: a bank member replaces hold-last only when its score is at most this fraction of hold-last's
MARGIN = 0.5
#: process-noise densities (µm²/min) of the bank's local-level (random-walk) members
LEVEL_Q_BANK = (1e-6, 1e-5, 1e-4, 1e-3)


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


def _kf_level(t, m, q, r):
    """Local-level (random-walk) Kalman filter on one axis; returns the level estimate at each t_k."""
    x, p = m[0], r
    out = np.empty(len(m))
    out[0] = x
    for k in range(1, len(m)):
        p = p + q * (t[k] - t[k - 1])
        g = p / (p + r)
        x = x + g * (m[k] - x)
        p = (1 - g) * p
        out[k] = x
    return out


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


def kalman_bank(t_min: np.ndarray, meas_um: np.ndarray, noise_um: float = 0.005, q_bank=Q_BANK,
                margin: float = MARGIN) -> np.ndarray:
    """Per axis, choose causally among hold-last, local-level and constant-velocity Kalman filters.

    At ``t_k`` each member's score is the sum of squared errors of its past predictions of the
    next sample (made at t_j for t_{j+1}, j + 1 ≤ k); the member with the lowest score supplies
    ``C_k`` (its prediction to the middle of the next interval). Until two predictions have been
    scored, the q = 1e-6 member is used.
    """
    t = np.asarray(t_min, float)
    m = np.asarray(meas_um, float)
    dt = np.append(np.diff(t), np.diff(t)[-1:] if len(t) > 1 else [0.0])
    c = np.zeros_like(m)
    for ax in range(m.shape[1]):
        mids, nexts = [], []
        for q in q_bank:
            pos, vel = _kf_run(t, m[:, ax], q, noise_um ** 2)
            mids.append(pos + vel * dt / 2)
            nexts.append(pos + vel * dt)
        for q in LEVEL_Q_BANK:
            lev = _kf_level(t, m[:, ax], q, noise_um ** 2)
            mids.append(lev)
            nexts.append(lev)
        mids.append(m[:, ax])
        nexts.append(m[:, ax])
        mids, nexts = np.array(mids), np.array(nexts)
        err = np.zeros((len(mids), len(t)))
        err[:, 1:] = (nexts[:, :-1] - m[None, 1:, ax]) ** 2
        score = np.cumsum(err, axis=1)  # score[:, k] uses predictions checked at samples <= k
        default = list(q_bank).index(1e-6) if 1e-6 in q_bank else 0
        best = np.argmin(score, axis=0)
        hold = len(mids) - 1
        # do no harm: leave hold-last only for a member clearly better on the record so far
        best = np.where(score[best, np.arange(len(t))] <= margin * score[hold], best, hold)
        pick = np.where(np.arange(len(t)) >= 2, best, default)
        c[:, ax] = mids[pick, np.arange(len(t))]
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
