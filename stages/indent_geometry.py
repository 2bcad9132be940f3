"""Geometry shared by the indentation stages: circle fit, diagonals, robust plane, the Imprint record.

Positions are in the image frame: x = column index x pixel size, y = row index
x pixel size (pixel centres, µm, y down the rows). Angles are measured from +x
towards +y.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["circle_fit", "Imprint", "IMPRINT_FIELDS", "diagonals", "inside_polygon", "lm_soft_l1", "plane_moments",
           "planes_from_moments", "robust_plane", "wrap45"]

#: per-imprint fields (``Imprint`` attributes that go into indents.csv)
IMPRINT_FIELDS = ("x_um", "y_um", "diameter_um", "diag1_um", "diag2_um", "d_um", "area_um2", "depth_nm",
                  "apex_depth_nm", "hd_ratio", "orientation_deg", "pileup_nm", "pileup_volume_um3", "edge_bow",
                  "cut_by_border", "chipped_area_um2")


def circle_fit(points: np.ndarray) -> tuple:
    """Geometric least-squares circle through 2-D points.

    Returns
    -------
    cx, cy, r : float
        Centre and radius in the points' units.
    """
    p = np.asarray(points, float)
    a = np.column_stack([2 * p, np.ones(len(p))])
    b = (p ** 2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)       # Kasa start
    c = sol[:2]
    for _ in range(20):                                # Gauss-Newton on the geometric distances
        d = p - c
        r_i = np.hypot(d[:, 0], d[:, 1])
        r = r_i.mean()
        j = -d / r_i[:, None] + (d / r_i[:, None]).mean(axis=0)
        res = r_i - r
        step, *_ = np.linalg.lstsq(j, -res, rcond=None)
        c = c + step
        if np.hypot(*step) < 1e-12 * max(r, 1e-12):
            break
    d = p - c
    return float(c[0]), float(c[1]), float(np.hypot(d[:, 0], d[:, 1]).mean())


@dataclass(frozen=True)
class Imprint:
    """One measured imprint (image frame; lengths µm, heights nm).

    ``corners_um`` (4, 2) in order around the imprint; ``outline`` is what the
    report draws. AFM-only fields are NaN for OM.
    """

    x_um: float
    y_um: float
    diameter_um: float
    diag1_um: float
    diag2_um: float
    depth_nm: float
    hd_ratio: float
    orientation_deg: float
    pileup_nm: float
    corners_um: np.ndarray
    fit_rms: float
    n_pixels: int
    blend_nm: float = float("nan")          # AFM: tip/ridge blend tau of the facet model (nm)
    psf_um: float = float("nan")            # OM: fitted PSF, Gaussian-equivalent sigma (µm)
    contrast: float = float("nan")          # OM: interior darkness
    # single-imprint metrology (stages.indent_single); NaN / None where not measured
    area_um2: float = float("nan")          # projected contact area
    apex_depth_nm: float = float("nan")     # the facet model's apex depth (depth_nm: measured floor)
    pileup_volume_um3: float = float("nan")
    edge_bow: float = float("nan")          # mean mid-edge displacement / (d/2), outward positive
    cut_by_border: bool = False
    contour_um: np.ndarray | None = None    # contact boundary (m, 2)
    floor_um: tuple | None = None           # (x, y) of the floor
    floor_share: float = float("nan")       # share of the pit deeper than 80 % of its depth (AFM)
    half_share: float = float("nan")        # share of the pit deeper than half its depth (AFM)
    chipped_area_um2: float = float("nan")  # AFM: chips beside the edges, left out of area_um2
    chips_um: tuple = ()                    # AFM: their outlines (m, 2) each, for the report

    @property
    def d_um(self) -> float:
        """Mean diagonal (the ISO 6507 d)."""
        return 0.5 * (self.diag1_um + self.diag2_um)

    def moved(self, dx_um: float, dy_um: float = 0.0) -> "Imprint":
        """The same imprint moved by (dx_um, dy_um): centre, corners, boundary, floor and chips; sizes unchanged."""
        step = np.array([dx_um, dy_um])
        return replace(self, x_um=self.x_um + dx_um, y_um=self.y_um + dy_um,
                       corners_um=np.asarray(self.corners_um) + step,
                       contour_um=None if self.contour_um is None else np.asarray(self.contour_um) + step,
                       floor_um=None if self.floor_um is None else (self.floor_um[0] + dx_um, self.floor_um[1] + dy_um),
                       chips_um=tuple(np.asarray(c) + step for c in self.chips_um))


# ----------------------------------------------------------------------------- helpers

def inside_polygon(rows, cols, shape) -> np.ndarray:
    """Pixel centres inside a closed polygon (even-odd rule), as a boolean mask of ``shape``.

    A scanline fill: every edge's crossings with the pixel rows toggle the columns at and right of
    the crossing. O(vertices x rows + pixels), where ``skimage.draw.polygon`` tests every pixel of
    the bounding box against every edge (0.2-0.8 s for a 256 x 256 imprint's boundary).
    """
    r0, c0 = np.asarray(rows, float), np.asarray(cols, float)
    r1, c1 = np.roll(r0, -1), np.roll(c0, -1)
    lo, hi = np.minimum(r0, r1), np.maximum(r0, r1)
    ny, nx = shape
    first = np.clip(np.ceil(lo), 0, ny).astype(int)            # pixel rows i with lo <= i < hi
    last = np.clip(np.ceil(hi), 0, ny).astype(int)
    n = last - first
    edge = np.repeat(np.arange(len(r0)), n)
    row = first[edge] + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    col = c0[edge] + (row - r0[edge]) * (c1[edge] - c0[edge]) / (r1[edge] - r0[edge])
    start = np.clip(np.ceil(col), 0, nx).astype(int)
    toggle = np.zeros((ny, nx + 1), np.int32)
    np.add.at(toggle, (row, start), 1)
    return (np.cumsum(toggle[:, :nx], axis=1) % 2).astype(bool)


def wrap45(a_deg):
    return (a_deg + 45.0) % 90.0 - 45.0


def diagonals(corners):
    """diag1 (the one within +-45 deg of +x), diag2 and the orientation of diag1 (deg)."""
    v_a = corners[0] - corners[2]
    v_b = corners[1] - corners[3]
    out = []
    for v in (v_a, v_b):
        ang = np.degrees(np.arctan2(v[1], v[0]))
        ang = (ang + 90.0) % 180.0 - 90.0
        out.append((np.hypot(*v), ang))
    (la, aa), (lb, ab) = out
    if abs(aa) <= 45.0:
        return la, lb, wrap45(aa)
    return lb, la, wrap45(ab)


def plane_moments(x, y, z) -> np.ndarray:
    """Per-point products (n, 9) whose sums over any subset give that subset's plane fit
    (:func:`planes_from_moments`)."""
    return np.column_stack([x * x, x * y, x, y * y, y, np.ones_like(x), x * z, y * z, z])


def planes_from_moments(sums: np.ndarray) -> np.ndarray:
    """Least-squares planes z = a x + b y + c from summed :func:`plane_moments` (..., 9) -> (..., 3)."""
    sxx, sxy, sx, syy, sy, n, sxz, syz, sz = np.moveaxis(np.asarray(sums, float), -1, 0)
    m = np.stack([np.stack([sxx, sxy, sx], -1), np.stack([sxy, syy, sy], -1), np.stack([sx, sy, n], -1)], -2)
    return np.linalg.solve(m + 1e-12 * np.eye(3), np.stack([sxz, syz, sz], -1)[..., None])[..., 0]


def robust_plane(x, y, z, n_iter=4, scale_samples=2000, tol=0.001):
    """Plane z = a x + b y + c by least squares, refitted up to ``n_iter`` times without points
    beyond 3.5 robust sigma (MAD, from about ``scale_samples`` evenly spaced kept points), until
    no more than ``tol`` of the points change sides.

    Returns
    -------
    ndarray (3,)
        a, b, c.
    """
    x, y, z = (np.asarray(v, float) for v in (x, y, z))
    mom = plane_moments(x, y, z)           # the normal equations of a kept subset: one product
    w = np.ones(len(z))
    coef = np.zeros(3)
    for _ in range(n_iter):
        sums = w @ mom
        coef = planes_from_moments(sums)
        if n_iter == 1:
            break
        r = z - (coef[0] * x + coef[1] * y + coef[2])
        keep = w > 0
        rk = r[keep][::max(1, int(sums[5]) // scale_samples)]
        s = 1.4826 * np.median(np.abs(rk - np.median(rk))) + 1e-9
        new = np.abs(r) < 3.5 * s
        # converged: the kept set (nearly) unchanged; a few points at the threshold move nothing
        if new.sum() < 10 or np.count_nonzero(new != keep) <= tol * len(z):
            break
        w = new.astype(float)
    return coef


def lm_soft_l1(fun, p, n_iter, f_scale=3.0, step=None, jac=None, ftol=1e-6, xtol=None, lo=None, hi=None,
               vp_jac=None):
    """Levenberg-Marquardt with a soft-L1 loss (reweighted residuals), Marquardt scaling.

    A dense normal-equation solve per iteration: cheaper than a general solver's SVD or
    LSMR when there are few parameters. The Jacobian is ``jac(p)`` when given, else forward
    differences of ``step``; or ``vp_jac(p, wr)`` (``wr``: the weighted residuals) gives an
    approximate Jacobian and what it leaves out of the gradient ``jacobian.T @ wr``, subtracted
    to make the gradient exact (Kaufman's variable projection). ``lo``/``hi`` clip the parameters
    after each step. Stops when the cost falls by less than ``ftol`` of itself or no step is
    larger than ``xtol`` (default ``0.1 step``).

    Returns
    -------
    ndarray
        The parameters.
    """
    def cost(r):
        return float(np.sum(np.sqrt(1 + (r / f_scale) ** 2) - 1))

    def clip(q):
        return q if lo is None else np.clip(q, lo, hi)

    xtol = (0.1 * step if step is not None else 0.0) if xtol is None else xtol
    p = clip(np.asarray(p, float))
    r = fun(p)
    c = cost(r)
    lam = 1e-2
    for _ in range(n_iter):
        w = 1.0 / np.sqrt(1 + (r / f_scale) ** 2)
        left_out = 0.0
        if jac is not None:
            jm = jac(p)
        elif vp_jac is not None:
            jm, left_out = vp_jac(p, w * r)
        else:
            jm = np.empty((len(r), len(p)))
            for j in range(len(p)):
                q = p.copy()
                q[j] += step
                jm[:, j] = (fun(q) - r) / step
        jw = jm * w[:, None]
        a, g = jw.T @ jm, jw.T @ r - left_out
        dia = np.diag(np.diag(a)) + 1e-12 * np.eye(len(p))
        for _try in range(6):
            dp = -np.linalg.solve(a + lam * dia, g)
            if lo is not None:
                dp = clip(p + dp) - p
            rn = fun(p + dp)
            cn = cost(rn)
            if cn < c:
                break
            lam *= 4.0
        else:
            break
        p, r, lam = p + dp, rn, max(lam / 3.0, 1e-6)
        done = c - cn < ftol * c or np.max(np.abs(dp)) < xtol
        c = cn
        if done:
            break
    return p
