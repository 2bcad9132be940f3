"""Least-squares calibration of the PM machine and the paper's error terms (eq. 9).

The parameter vector θ (27 values) is, in order: the stage triad's rotation
vector q (rad, 3), the non-orthogonality angles γ (rad, 3), the scale errors ε
(3), the straightness bows K (µm, 6), the offset o (µm, 3), the PM -> OM
rotation vector r (rad, 3), the translation T (µm, 3) and the plane a, b, c
(-, -, µm). See ``markcal.stages.pm_model`` for the model.

The four terms of the fitness F = 0.3·E_ortho + 0.3·E_pose + 0.2·E_flat + 0.2·E_dyn
(eq. 9) are each an RMS divided by its tolerance bound (``TOLERANCES_UM``):

* E_ortho: RMS (µm) of the axis trajectories' residuals ``p_ref − (A·S·c + s(c) + o)``.
  The paper's eq. 3 is garbled in the source text (its eq. 2 even sets the dot
  products to 1); its intent is "how far the axes measured along the calibration
  trajectories are from the calibrated triad", which this residual measures
  (with the calibrated non-orthogonal triad, the residual vanishes when the
  model explains the trajectories, as eq. 3's sum of squared dot products does
  for an orthonormal set).
* E_pose: RMS (µm) of ``X_om − (R·p(c) + T)`` over the PM–OM mark pairs (eq. 4).
* E_flat: RMS (µm) of the probed contacts (mapped to the OM frame) about the plane (eqs. 5-6).
* E_dyn: mean |drift| (µm) of the reference array mapped into the calibrated
  command frame, ``(R·A·S)⁻¹·d``; it hardly depends on θ (it is there because
  the paper puts it there; the drift flow does the real work on drift).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from markcal.stages.pm_model import (STRAIGHTNESS_REF_UM, PMModel, K_PAIRS, matrix_to_rotvec,
                                     rotvec_to_matrix, shear_matrix)

__all__ = ["WEIGHTS", "TOLERANCES_UM", "SessionData", "N_PARAMS", "model_from_theta", "theta_from_model",
           "residuals", "residual_parts_m", "terms_from_parts", "error_terms", "coarse_start", "fit_lsq", "LsqResult"]

#: ω1..ω4 of eq. 9
WEIGHTS = {"ortho": 0.3, "pose": 0.3, "flat": 0.2, "dyn": 0.2}
#: tolerance bounds that make the E terms dimensionless (the paper's ±0.1 µm requirement)
TOLERANCES_UM = {"ortho": 0.1, "pose": 0.1, "flat": 0.1, "dyn": 0.1}
N_PARAMS = 27


@dataclass(frozen=True)
class SessionData:
    """Session measurements (µm).

    c_axes, p_axes : (N, 3) commanded positions and reference-measured tip (PM frame) along the axis moves.
    c_pose, x_om : (M, 3) commanded positions of the marks and their OM-frame positions.
    c_probe : (K, 3) commanded x, y and contact z of the probing grid.
    drift_um : (J, 3) reference-array drift samples (may be empty).
    """
    c_axes: np.ndarray
    p_axes: np.ndarray
    c_pose: np.ndarray
    x_om: np.ndarray
    c_probe: np.ndarray
    drift_um: np.ndarray


def model_from_theta(th: np.ndarray) -> PMModel:
    """The PMModel of a 27-value parameter vector."""
    th = np.asarray(th, float)
    a = rotvec_to_matrix(th[0:3]) @ shear_matrix(th[3:6])
    return PMModel(a, th[6:9].copy(), th[9:15].copy(), th[15:18].copy(), rotvec_to_matrix(th[18:21]),
                   th[21:24].copy(), th[24:27].copy())


def theta_from_model(m: PMModel) -> np.ndarray:
    """Inverse of ``model_from_theta`` (the triad is split by a QR-like decomposition)."""
    a = m.a_axes
    x = a[:, 0]
    y = a[:, 1] - (a[:, 1] @ x) * x
    y /= np.linalg.norm(y)
    q = np.column_stack([x, y, np.cross(x, y)])
    n = q.T @ a  # unit-column shear in the triad's frame
    g = np.array([n[0, 1] / n[1, 1], n[0, 2] / n[2, 2], n[1, 2] / n[2, 2]])
    return np.concatenate([matrix_to_rotvec(q), g, m.scale, m.k_um, m.o_um, matrix_to_rotvec(m.r_pose),
                           m.t_um, m.plane])


def _tip_pm_batch(m_mat, k_mat, o, c):
    """Tip positions for P models at once: m_mat, k_mat (P, 3, 3), o (P, 3), c (N, 3) -> (P, N, 3)."""
    u2 = (c / STRAIGHTNESS_REF_UM) ** 2
    return np.matmul(c, m_mat.transpose(0, 2, 1)) + np.matmul(u2, k_mat.transpose(0, 2, 1)) + o[:, None, :]


def _k_matrix_batch(k):
    km = np.zeros(k.shape[:-1] + (3, 3))
    for idx, (i, j) in enumerate(K_PAIRS):
        km[..., i, j] = k[..., idx]
    return km


def residual_parts_m(a, eps, k, o, r, t, plane, d: SessionData):
    """Residuals (µm) for P models given as arrays: a, r (P, 3, 3); eps, o, t, plane (P, 3); k (P, 6).

    Returns axes (P, N, 3), pose (P, M, 3), probe (P, K) residuals, A·S (P, 3, 3) and R.
    """
    m_mat = a * (1.0 + eps[:, None, :])
    k_mat = _k_matrix_batch(k)
    ra = d.p_axes[None] - _tip_pm_batch(m_mat, k_mat, o, d.c_axes)
    xp = np.matmul(_tip_pm_batch(m_mat, k_mat, o, d.c_pose), r.transpose(0, 2, 1)) + t[:, None, :]
    rp = d.x_om[None] - xp
    xq = np.matmul(_tip_pm_batch(m_mat, k_mat, o, d.c_probe), r.transpose(0, 2, 1)) + t[:, None, :]
    rf = xq[..., 2] - (plane[:, None, 0] * xq[..., 0] + plane[:, None, 1] * xq[..., 1] + plane[:, None, 2])
    return ra, rp, rf, m_mat, r


def residual_parts(th: np.ndarray, d: SessionData):
    """``residual_parts_m`` for θ of shape (27,) or (P, 27)."""
    th = np.atleast_2d(th)
    a = rotvec_to_matrix(th[:, 0:3]) @ shear_matrix(th[:, 3:6])
    return residual_parts_m(a, th[:, 6:9], th[:, 9:15], th[:, 15:18], rotvec_to_matrix(th[:, 18:21]),
                            th[:, 21:24], th[:, 24:27], d)


def terms_from_parts(ra, rp, rf, m_mat, r, d: SessionData) -> dict:
    """E terms and F (arrays of length P) from ``residual_parts_m`` output."""
    e = {"ortho": np.sqrt(np.mean(np.sum(ra ** 2, -1), -1)) / TOLERANCES_UM["ortho"],
         "pose": np.sqrt(np.mean(np.sum(rp ** 2, -1), -1)) / TOLERANCES_UM["pose"],
         "flat": np.sqrt(np.mean(rf ** 2, -1)) / TOLERANCES_UM["flat"]}
    if len(d.drift_um):
        rm = np.linalg.inv(r @ m_mat)
        dc = np.matmul(d.drift_um, rm.transpose(0, 2, 1))
        e["dyn"] = np.mean(np.linalg.norm(dc, axis=-1), -1) / TOLERANCES_UM["dyn"]
    else:
        e["dyn"] = np.zeros(len(e["ortho"]))
    e["F"] = sum(WEIGHTS[k] * e[k] for k in WEIGHTS)
    return e


def error_terms(th: np.ndarray, d: SessionData) -> dict:
    """E_ortho, E_pose, E_flat, E_dyn and F for θ of shape (27,) or (P, 27) (arrays of length P)."""
    return terms_from_parts(*residual_parts(th, d), d)


def residuals(th: np.ndarray, d: SessionData) -> np.ndarray:
    """Weighted residual vector whose half squared norm is Σ ω·E² /2 (E_dyn omitted: no lever on θ)."""
    ra, rp, rf, _, _ = residual_parts(th, d)
    parts = []
    for key, res in (("ortho", ra[0].ravel()), ("pose", rp[0].ravel()), ("flat", rf[0].ravel())):
        n = len(res) // (1 if key == "flat" else 3)
        parts.append(res * np.sqrt(WEIGHTS[key] / n) / TOLERANCES_UM[key])
    return np.concatenate(parts)


def coarse_start(d: SessionData) -> np.ndarray:
    """A datum start: ideal axes, rigid Kabsch fit of commanded -> OM positions, mean probe plane."""
    th = np.zeros(N_PARAMS)
    a0, b0 = d.c_pose - d.c_pose.mean(0), d.x_om - d.x_om.mean(0)
    u, _, vt = np.linalg.svd(b0.T @ a0)
    r = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt
    th[18:21] = matrix_to_rotvec(r)
    th[21:24] = d.x_om.mean(0) - r @ d.c_pose.mean(0)
    xq = d.c_probe @ r.T + th[21:24]
    g = np.column_stack([xq[:, 0], xq[:, 1], np.ones(len(xq))])
    th[24:27] = np.linalg.lstsq(g, xq[:, 2], rcond=None)[0]
    return th


@dataclass(frozen=True)
class LsqResult:
    """Least-squares fit: θ, its model, the E terms, iterations (function evaluations) and the cost."""
    theta: np.ndarray
    model: PMModel
    terms: dict
    nfev: int
    cost: float


def fit_lsq(d: SessionData, start: np.ndarray | None = None) -> LsqResult:
    """Fit all 27 parameters by scipy ``least_squares`` (trust-region reflective, ``x_scale='jac'``).

    Parameters
    ----------
    d : SessionData
    start : (27,) initial θ; default ``coarse_start(d)``.
    """
    x0 = coarse_start(d) if start is None else np.asarray(start, float)
    sol = least_squares(residuals, x0, args=(d,), method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12,
                        gtol=1e-12, max_nfev=200)
    th = sol.x
    terms = {k: float(v[0]) for k, v in error_terms(th, d).items()}
    return LsqResult(th, model_from_theta(th), terms, int(sol.nfev), float(sol.cost))
