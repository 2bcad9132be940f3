"""Robust plane fit of a scanned plate and the in-plane frame."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .errors import MarkcalError
from .limits import check_values
from .quantile import percentiles


@dataclass(frozen=True)
class Plane:
    """A plane in the scanner frame and a right-handed in-plane basis.

    ``origin_mm`` is a point on the plane (the inliers' centroid); ``normal``
    the unit normal; ``e_u``, ``e_v`` the in-plane axes, chosen so that
    (e_u, e_v) follow the scanner's (x, y) without a reflection.
    """

    origin_mm: np.ndarray
    normal: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    rms_mm: float
    inlier_fraction: float
    threshold_mm: float

    @property
    def rotation(self) -> np.ndarray:
        """Rows e_u, e_v, n: rotates scanner-frame vectors into the plate frame."""
        return np.vstack([self.e_u, self.e_v, self.normal])

    @property
    def tilt_deg(self) -> float:
        """Angle between the plate normal and the scanner's z axis."""
        return float(np.degrees(np.arccos(min(1.0, abs(self.normal[2])))))


def _basis(normal: np.ndarray) -> tuple:
    """In-plane axes: scanner x projected onto the plane, and n x e_u.

    The normal is taken on the side where (e_u, e_v) keep the orientation of
    the scanner's (x, y): n_z > 0 (a plate seen by a z-range scanner has its
    normal along -z; flipping it keeps the image unmirrored).
    """
    n = normal / np.linalg.norm(normal)
    if n[2] < 0:
        n = -n
    ex = np.array([1.0, 0.0, 0.0])
    e_u = ex - n * (ex @ n)
    e_u /= np.linalg.norm(e_u)
    e_v = np.cross(n, e_u)
    return n, e_u, e_v


def _ransac(xyz: np.ndarray, threshold_mm: float, rng: np.random.Generator, n_trials: int = 256):
    """Best plane (n, d) with n.p = d by vectorised RANSAC on ``xyz``."""
    m = len(xyz)
    idx = rng.integers(0, m, size=(n_trials, 3))
    p0, p1, p2 = xyz[idx[:, 0]], xyz[idx[:, 1]], xyz[idx[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-9
    normals = normals[ok] / norm[ok, None]
    d = np.einsum("ij,ij->i", normals, p0[ok])
    counts = _inlier_counts(np.ascontiguousarray(xyz, float), normals, d, float(threshold_mm))
    if len(counts) == 0:
        return None, None, 0
    best = int(np.argmax(counts))
    return normals[best], d[best], counts[best]


def fit_plane(xyz_mm: np.ndarray, threshold_mm: float = 0.1, seed: int = 0,
              sample_size: int = 40000, min_inlier_fraction: float = 0.3) -> Plane:
    """Fit the plate plane robustly: RANSAC, then iterated least squares.

    RANSAC runs on a random sample from the central part of the cloud (the
    clamping frame sits around the edges); the refit uses every point within
    a threshold that shrinks to 4 sigma of the inliers, so the frame,
    spurious reflections and scratches do not pull the plane.

    Parameters
    ----------
    xyz_mm : ndarray, shape (n, 3)
        Points in the scanner frame, mm.
    threshold_mm : float
        RANSAC inlier distance.
    seed : int
        Seed of the random sampling.

    Raises
    ------
    MarkcalError
        If no plane holds at least ``min_inlier_fraction`` of the points.
    """
    if len(xyz_mm) < 100:
        raise MarkcalError(f"only {len(xyz_mm)} points: too few to fit a plane")
    check_values(xyz_mm, "xyz_mm", limit=np.inf)  # RANSAC and the refits assume finite points
    rng = np.random.default_rng(seed)
    (lo_x, hi_x), (lo_y, hi_y) = percentiles(xyz_mm[:, 0], [5, 95]), percentiles(xyz_mm[:, 1], [5, 95])
    lo, hi = np.array([lo_x, lo_y]), np.array([hi_x, hi_y])
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    pool = _central(xyz_mm, mid, 0.6 * half)
    if len(pool) <= 1000:
        pool = np.arange(len(xyz_mm))
    sample = xyz_mm[pool[rng.choice(len(pool), size=min(sample_size, len(pool)), replace=False)]].astype(float)
    n, d, count = _ransac(sample, threshold_mm, rng)
    if n is None or count < min_inlier_fraction * len(sample):
        raise MarkcalError("no plane found: the cloud is not a scan of a flat plate")
    thr = threshold_mm
    sub = xyz_mm[rng.choice(len(xyz_mm), size=min(len(xyz_mm), 400_000), replace=False)].astype(float)
    for _ in range(3):
        res = sub @ n - d
        inl = np.abs(res) < thr
        pts = sub[inl]
        c = pts.mean(axis=0)
        q = pts - c
        _, _, vt = np.linalg.svd(q.T @ q)
        n = vt[-1]
        d = float(n @ c)
        sigma = float(np.sqrt(np.mean((q @ n) ** 2)))
        thr = max(4.0 * sigma, 0.02)
    frac = float(inl.mean())
    if frac < min_inlier_fraction:
        raise MarkcalError(f"no plane found: best plane holds only {100 * frac:.0f} % of the points")
    n_out, e_u, e_v = _basis(n)
    return Plane(origin_mm=c, normal=n_out, e_u=e_u, e_v=e_v, rms_mm=sigma,
                 inlier_fraction=frac, threshold_mm=thr)


@njit(cache=True, nogil=True)
def _inlier_counts(xyz, normals, d, threshold):  # pragma: no cover - compiled
    """Points within ``threshold`` of each plane n.p = d."""
    counts = np.zeros(len(normals), np.int64)
    for t in range(len(normals)):
        nx, ny, nz, dt = normals[t, 0], normals[t, 1], normals[t, 2], d[t]
        c = 0
        for i in range(len(xyz)):
            if abs(xyz[i, 0] * nx + xyz[i, 1] * ny + xyz[i, 2] * nz - dt) < threshold:
                c += 1
        counts[t] = c
    return counts


@njit(cache=True, nogil=True)
def _central(xyz, mid, half):  # pragma: no cover - compiled
    """Indices of the points with |x - mid_x| < half_x and |y - mid_y| < half_y."""
    out = np.empty(len(xyz), np.int64)
    m = 0
    for i in range(len(xyz)):
        if abs(xyz[i, 0] - mid[0]) < half[0] and abs(xyz[i, 1] - mid[1]) < half[1]:
            out[m] = i
            m += 1
    return out[:m].copy()


def to_plane(xyz_mm: np.ndarray, plane: Plane) -> np.ndarray:
    """Scanner-frame points to plate-frame (u, v, h) in mm (h: height above the plane)."""
    # einsum, not ``@``: a (n, 3) x (3, 3) product through BLAS is ~6x slower on millions of points
    return np.einsum("ij,kj->ik", xyz_mm - plane.origin_mm, plane.rotation)


def from_plane(uv_mm: np.ndarray, plane: Plane) -> np.ndarray:
    """In-plane (u, v) in mm back to 3D scanner-frame points on the plane (2D -> 3D)."""
    uv = np.asarray(uv_mm, float)
    return plane.origin_mm + uv[:, :1] * plane.e_u + uv[:, 1:2] * plane.e_v
