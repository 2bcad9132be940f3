"""Smooth 2-D vector fields for sparse grids: a smoothing thin-plate spline and a cubic polynomial.

The thin-plate spline (Duchon; Wahba's smoothing spline) is
``f(u) = sum_j w_j phi(|u - c_j|) + a0 + a1 u + a2 v`` with ``phi(r) = r^2 log r``
on positions normalised to ``u = (x - centre) / scale``; the smoothing
``lam`` is added to the kernel's diagonal. Its leave-one-out residuals come in
closed form (Rippa 1999: ``e_i = w_i / (A^-1)_ii``), so the smoothing is chosen by
leave-one-out cross-validation at the cost of one inverse per candidate.
Lengths in mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: smoothing values tried (normalised kernel units)
LAMBDAS = tuple(10.0 ** np.arange(-7.0, 4.01, 0.5))


def _kernel2(r2):
    """phi(r) = r^2 log r from squared distances: r2 log(r2) / 2, 0 at r = 0."""
    r2 = np.maximum(r2, 1e-300)             # phi -> 0 as r -> 0; no log(0)
    return 0.5 * r2 * np.log(r2)


def _dist2(a, b):
    """Squared distances (n, m) between points a (n, 2) and b (m, 2)."""
    return (a[:, :1] - b[:, 0]) ** 2 + (a[:, 1:] - b[:, 1]) ** 2


def frame_of(xy_mm: np.ndarray) -> tuple:
    """Centre (2,) and scale (half the larger extent, mm) that normalise positions to about [-1, 1]."""
    xy = np.asarray(xy_mm, float)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return 0.5 * (lo + hi), float(max(0.5 * np.max(hi - lo), 1e-9))


@dataclass(frozen=True)
class ThinPlate:
    """A fitted smoothing thin-plate spline R^2 -> R^k.

    ``centres_mm`` (m, 2); ``weights_mm`` (m, k); ``affine_mm`` (3, k) for
    [1, u, v]; ``centre_mm``, ``scale_mm`` normalise positions; ``lam`` the smoothing.
    """

    centres_mm: np.ndarray
    weights_mm: np.ndarray
    affine_mm: np.ndarray
    centre_mm: np.ndarray
    scale_mm: float
    lam: float

    def __call__(self, xy_mm: np.ndarray) -> np.ndarray:
        """Values (n, k) mm at positions (n, 2) mm."""
        u = (np.atleast_2d(np.asarray(xy_mm, float)) - self.centre_mm) / self.scale_mm
        c = (self.centres_mm - self.centre_mm) / self.scale_mm
        return _kernel2(_dist2(u, c)) @ self.weights_mm + np.column_stack([np.ones(len(u)), u]) @ self.affine_mm

    def to_dict(self) -> dict:
        return {"kind": "thin-plate spline: f = sum_j w_j r_j^2 ln r_j + a0 + a1 u + a2 v, "
                        "u = (x - centre_mm) / scale_mm, r_j = |u - (c_j - centre_mm) / scale_mm|",
                "centres_mm": self.centres_mm.tolist(), "weights_mm": self.weights_mm.tolist(),
                "affine_mm": self.affine_mm.tolist(), "centre_mm": self.centre_mm.tolist(),
                "scale_mm": self.scale_mm, "lam": self.lam}

    @classmethod
    def from_dict(cls, d: dict) -> "ThinPlate":
        c = np.asarray(d["centres_mm"], float).reshape(-1, 2)
        return cls(c, np.asarray(d["weights_mm"], float).reshape(len(c), -1),
                   np.asarray(d["affine_mm"], float).reshape(3, -1), np.asarray(d["centre_mm"], float).reshape(2),
                   float(d["scale_mm"]), float(d["lam"]))


def fit_thin_plate(xy_mm: np.ndarray, values_mm: np.ndarray, lams=LAMBDAS) -> tuple:
    """Smoothing thin-plate spline with the smoothing chosen by leave-one-out CV.

    With ``P = [1, u, v]`` and ``Z`` an orthonormal basis of its complement, the
    kernel weights are ``w = Z (Z' K Z + lam I)^-1 Z' y`` (the upper-left block
    ``B`` of the bordered system's inverse); one eigendecomposition of ``Z' K Z``
    serves every ``lam``, and the leave-one-out error is ``w_i / B_ii``.

    Parameters
    ----------
    xy_mm : ndarray, shape (n, 2)
        Positions (mm), n >= 4 and not collinear.
    values_mm : ndarray, shape (n, k)
        Values to smooth (mm).
    lams : sequence of float
        Smoothing values tried.

    Returns
    -------
    ThinPlate, float
        The spline and its leave-one-out RMS of the Euclidean error (mm).
    """
    xy = np.asarray(xy_mm, float)
    y = np.asarray(values_mm, float).reshape(len(xy), -1)
    centre, scale = frame_of(xy)
    u = (xy - centre) / scale
    n = len(u)
    k = _kernel2(_dist2(u, u))
    p = np.column_stack([np.ones(n), u])
    q, _ = np.linalg.qr(p, mode="complete")
    z = q[:, 3:]
    s, v = np.linalg.eigh(z.T @ k @ z)
    zv = z @ v                                   # (n, n-3)
    zy = zv.T @ y                                # (n-3, k)
    zv2 = zv * zv
    best = None
    for lam in lams:
        g = 1.0 / (s + lam)
        w = zv @ (g[:, None] * zy)
        e = w / (zv2 @ g)[:, None]
        loo = float(np.sqrt(np.mean((e * e).sum(axis=1))))
        if best is None or loo < best[0]:
            best = (loo, lam, w)
    loo, lam, w = best
    affine, *_ = np.linalg.lstsq(p, y - k @ w - lam * w, rcond=None)
    return ThinPlate(xy.copy(), w, affine, centre, scale, float(lam)), loo


@dataclass(frozen=True)
class Poly3:
    """Full cubic polynomial R^2 -> R^k on normalised positions; ``coef_mm`` (10, k)."""

    coef_mm: np.ndarray
    centre_mm: np.ndarray
    scale_mm: float

    def __call__(self, xy_mm: np.ndarray) -> np.ndarray:
        return _poly_terms(np.atleast_2d(np.asarray(xy_mm, float)), self.centre_mm, self.scale_mm) @ self.coef_mm

    def to_dict(self) -> dict:
        return {"kind": "cubic: f = sum_k c_k u^i v^j over i + j <= 3 (order 1, u, v, u2, uv, v2, u3, u2v, uv2, v3), "
                        "u = (x - centre_mm) / scale_mm",
                "coef_mm": self.coef_mm.tolist(), "centre_mm": self.centre_mm.tolist(), "scale_mm": self.scale_mm}

    @classmethod
    def from_dict(cls, d: dict) -> "Poly3":
        return cls(np.asarray(d["coef_mm"], float).reshape(10, -1), np.asarray(d["centre_mm"], float).reshape(2),
                   float(d["scale_mm"]))


def _poly_terms(xy, centre, scale):
    u, v = ((xy - centre) / scale).T
    return np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v, u ** 3, u * u * v, u * v * v, v ** 3])


def fit_poly3(xy_mm: np.ndarray, values_mm: np.ndarray) -> Poly3:
    """Least-squares cubic (10 terms per output) through positions (n, 2) mm."""
    xy = np.asarray(xy_mm, float)
    y = np.asarray(values_mm, float).reshape(len(xy), -1)
    centre, scale = frame_of(xy)
    coef, *_ = np.linalg.lstsq(_poly_terms(xy, centre, scale), y, rcond=None)
    return Poly3(coef, centre, scale)
