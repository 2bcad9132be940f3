"""Geometry shared by the indentation stages: circle fit, diagonals, robust plane, the Imprint record.

Positions are in the image frame: x = column index x pixel size, y = row index
x pixel size (pixel centres, µm, y down the rows). Angles are measured from +x
towards +y.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["circle_fit", "Imprint", "IMPRINT_FIELDS", "diagonals", "robust_plane", "wrap45"]

#: per-imprint fields (``Imprint`` attributes that go into indents.csv)
IMPRINT_FIELDS = ("x_um", "y_um", "diameter_um", "diag1_um", "diag2_um", "d_um", "area_um2", "depth_nm",
                  "apex_depth_nm", "hd_ratio", "orientation_deg", "pileup_nm", "pileup_volume_um3", "edge_bow",
                  "cut_by_border")


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

    @property
    def d_um(self) -> float:
        """Mean diagonal (the ISO 6507 d)."""
        return 0.5 * (self.diag1_um + self.diag2_um)


# ----------------------------------------------------------------------------- helpers

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


def robust_plane(x, y, z, n_iter=4):
    a = np.column_stack([x, y, np.ones_like(x)])
    keep = np.ones(len(z), bool)
    coef = np.zeros(3)
    for _ in range(n_iter):
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak + 1e-12 * np.eye(3), ak.T @ z[keep])
        if n_iter == 1:
            break
        r = z - a @ coef
        s = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep]))) + 1e-9
        new = np.abs(r) < 3.5 * s
        if new.sum() < 10 or np.array_equal(new, keep):
            break
        keep = new
    return coef
