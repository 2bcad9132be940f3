"""Grid identification and rigid registration of detected fiducials."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .errors import MarkcalError


@dataclass(frozen=True)
class GridIndex:
    """Row and column of each detected centre (-1: not on the grid)."""

    row: np.ndarray
    col: np.ndarray
    rotation_deg: float
    pitch_mm: float


@dataclass(frozen=True)
class Lattice:
    """Integer lattice coordinates of detected centres in the grid's own frame.

    ``k`` (n, 2) are steps along the two lattice directions (the first within
    +-45 deg of +u); ``good`` marks centres within 0.35 pitch of a lattice site.
    """

    k: np.ndarray
    good: np.ndarray
    theta_rad: float
    pitch_mm: float


def neighbour_pitch(xy: np.ndarray, pitch: float) -> tuple:
    """The spacing of points on a square lattice, from their neighbours at about ``pitch`` (within 25 %).

    A few stray points between the lattice's (dust, pits) have nearer neighbours and must not decide it;
    when fewer near-pitch distances than points are found, the median nearest-neighbour distance is used.

    Returns
    -------
    spacing : float
        Same units as ``xy`` and ``pitch``.
    dist, nb : ndarray (n, k)
        Distances to and indices of each point's k = min(n, 5) nearest (itself first).
    """
    dist, nb = cKDTree(xy).query(xy, k=min(len(xy), 5))
    step = dist[:, 1:][np.abs(dist[:, 1:] / pitch - 1) < 0.25]
    return float(np.median(step) if len(step) >= len(xy) else np.median(dist[:, 1])), dist, nb


def lattice_coords(uv_mm: np.ndarray, pitch_mm: float, pitch_tolerance: float = 0.04) -> Lattice:
    """Lattice directions, offset and integer coordinates of detected centres (plate frame, mm).

    Raises
    ------
    MarkcalError
        If fewer than 4 centres, or their spacing does not match ``pitch_mm``.
    """
    uv = np.asarray(uv_mm, float)
    n = len(uv)
    if n < 4:
        raise MarkcalError(f"only {n} fiducials detected: cannot identify the grid")
    nn, dist, nb = neighbour_pitch(uv, pitch_mm)
    if abs(nn / pitch_mm - 1) > pitch_tolerance:
        raise MarkcalError(f"fiducial pitch in the scan is {nn:.3f} mm but the plate spec says "
                           f"{pitch_mm:.3f} mm")
    ok = np.abs(dist[:, 1:] / pitch_mm - 1) < 0.25
    vec = uv[nb[:, 1:]] - uv[:, None, :]
    ang = np.arctan2(vec[..., 1], vec[..., 0])[ok]
    theta = np.angle(np.sum(np.exp(4j * ang))) / 4
    c, s = np.cos(-theta), np.sin(-theta)
    local = uv @ np.array([[c, s], [-s, c]]) / pitch_mm
    # lattice offset per axis (circular mean of fractional parts), then integer indices
    off = np.angle(np.exp(2j * np.pi * local).sum(axis=0)) / (2 * np.pi)
    k = np.rint(local - off).astype(int)
    good = np.abs(local - off - k).max(axis=1) < 0.35
    return Lattice(k=k, good=good, theta_rad=float(theta), pitch_mm=float(nn))


def place_block(k_axis: np.ndarray, good: np.ndarray, size: int) -> np.ndarray:
    """Index 0..size-1 along one axis from integer lattice steps (-1: off the grid).

    Spurious far detections: the densest window of ``size`` is kept; whole
    edge rows missing: the detected block is centred.
    """
    kk = k_axis[good]
    lo, hi = (int(kk.min()), int(kk.max())) if len(kk) else (0, 0)
    span = hi - lo + 1
    if span > size:
        counts = [np.sum((kk >= a) & (kk < a + size)) for a in range(lo, hi - size + 2)]
        lo = lo + int(np.argmax(counts))
    elif span < size:
        lo = lo - (size - span) // 2
    out = np.where(good, k_axis - lo, -1)
    return np.where((out >= 0) & (out < size), out, -1)


def index_grid(uv_mm: np.ndarray, rows: int, cols: int, pitch_mm: float,
               max_rotation_deg: float = 45.0, pitch_tolerance: float = 0.04) -> GridIndex:
    """Assign each detected centre its row and column.

    The grid may be turned by any angle within +-45 deg (the plate spec allows
    +-15 deg), shifted, and have missing fiducials. Row index grows with v,
    column index with u. Other orientations: ``stages.orientation``.

    Raises
    ------
    MarkcalError
        If the spacing of the detected centres does not match ``pitch_mm``.
    """
    lat = lattice_coords(uv_mm, pitch_mm, pitch_tolerance)
    if abs(np.degrees(lat.theta_rad)) > max_rotation_deg:
        raise MarkcalError(f"grid is turned by {np.degrees(lat.theta_rad):.1f} deg, more than allowed")
    col = place_block(lat.k[:, 0], lat.good, cols)
    row = place_block(lat.k[:, 1], lat.good, rows)
    off = (col < 0) | (row < 0)
    col[off] = -1
    row[off] = -1
    return GridIndex(row=row, col=col, rotation_deg=float(np.degrees(lat.theta_rad)), pitch_mm=lat.pitch_mm)


@dataclass(frozen=True)
class Rigid2D:
    """x_target = R @ x + t (mm). ``reflection`` is True if R has det -1."""

    rotation: np.ndarray
    translation_mm: np.ndarray

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.rotation[1, 0], self.rotation[0, 0])))

    @property
    def reflection(self) -> bool:
        return bool(np.linalg.det(self.rotation) < 0)

    def apply(self, xy_mm: np.ndarray) -> np.ndarray:
        return np.asarray(xy_mm, float) @ self.rotation.T + self.translation_mm


def rigid_fit(src_mm: np.ndarray, dst_mm: np.ndarray, weights=None,
              allow_reflection: bool = False) -> Rigid2D:
    """Least-squares rigid transform src -> dst (Kabsch), optionally weighted."""
    p = np.asarray(src_mm, float)
    q = np.asarray(dst_mm, float)
    w = np.ones(len(p)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    pc, qc = w @ p, w @ q
    h = (p - pc).T @ ((q - qc) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    dmat = np.eye(2)
    if not allow_reflection and np.linalg.det(vt.T @ u.T) < 0:
        dmat[1, 1] = -1
    rot = vt.T @ dmat @ u.T
    return Rigid2D(rotation=rot, translation_mm=qc - rot @ pc)


def robust_rigid_fit(src_mm: np.ndarray, dst_mm: np.ndarray, outlier_mm: float = 3.0,
                     n_iter: int = 3) -> tuple:
    """Least-squares rigid fit over all pairs, leaving out gross mismatches.

    The residuals of a galvo grid are its distortion (systematic, up to a few
    mm), so all pairs count equally; only pairs farther than ``outlier_mm``
    from the fit (a wrong index) are dropped and the fit repeated.

    Returns
    -------
    Rigid2D, ndarray of bool
        The transform and which pairs were used.
    """
    used = np.ones(len(src_mm), bool)
    tf = rigid_fit(src_mm, dst_mm)
    for _ in range(n_iter):
        r = np.linalg.norm(tf.apply(src_mm) - dst_mm, axis=1)
        new = r < outlier_mm
        if new.sum() < 3 or np.array_equal(new, used):
            break
        used = new
        tf = rigid_fit(src_mm[used], dst_mm[used])
    return tf, used


def rigid_or_mirrored_fit(src_mm: np.ndarray, dst_mm: np.ndarray) -> tuple:
    """Best rigid transform src -> dst, with a reflection when that fits much better.

    A measurement taken from the back of a plate (scanned face down) is the
    mirror image of the marked grid; it registers only through a reflection.

    Returns
    -------
    Rigid2D, float, float
        The chosen transform and the RMS residuals (mm) of the proper and the
        mirrored fit; the mirrored one is chosen when its RMS is below half the
        proper one's.
    """
    src = np.asarray(src_mm, float)
    dst = np.asarray(dst_mm, float)
    proper = rigid_fit(src, dst)
    flip = np.diag([1.0, -1.0])
    m = rigid_fit(src @ flip, dst)
    mirrored = Rigid2D(rotation=m.rotation @ flip, translation_mm=m.translation_mm)
    rms = [float(np.sqrt(np.mean(np.sum((t.apply(src) - dst) ** 2, axis=1)))) for t in (proper, mirrored)]
    return (mirrored if rms[1] < 0.5 * rms[0] else proper), rms[0], rms[1]
