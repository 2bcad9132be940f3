"""Levelling of AFM height maps as Gwyddion users expect it, with the features masked.

Steps (iterated, each on the pixels outside the feature mask): plane fit,
row alignment by the median of differences between neighbouring rows
(Gwyddion's "Align Rows", median-of-differences), polynomial bow removal,
a per-row median residual (removes the random walk the differences leave),
scar removal (Gwyddion's "Remove Scars": short streaks of 1-2 rows standing
out from both neighbours, replaced by interpolation), then a new mask of the
features (pits, dust) for the next round.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .cv_filters import dilate_square, gaussian, max_line, min_line

__all__ = ["Levelled", "level_afm", "poly_surface", "noise_nm", "feature_mask"]


@dataclass(frozen=True)
class Levelled:
    """A levelled AFM map.

    Attributes
    ----------
    z_nm : ndarray (rows, cols)
        Levelled heights (nm); the original surface is at 0. NaN where the input was.
    mask : ndarray of bool
        Features (pits, particles) left out of the background fits.
    noise_nm : float
        Pixel noise (robust, from differences along the fast axis).
    tilt_deg : float
        Sample tilt removed (from the first plane fit).
    bow_nm : float
        Peak-to-valley of the polynomial background beyond the plane.
    scars : ndarray of bool
        Pixels replaced by scar removal (interpolated: measurements leave them out).
    """

    z_nm: np.ndarray
    mask: np.ndarray
    noise_nm: float
    tilt_deg: float
    bow_nm: float
    scars: np.ndarray

    @property
    def n_scar_px(self) -> int:
        return int(self.scars.sum())


def _powers(n, degree):
    t = 2 * np.arange(n) / max(n - 1, 1) - 1
    return t[:, None] ** np.arange(degree + 1)


def poly_surface(z, keep, degree: int, step: int = 3) -> np.ndarray:
    """Least-squares 2-D polynomial (total degree ``degree``) over ``keep``, evaluated everywhere.

    The fit uses every ``step``-th pixel in each direction (of those in ``keep``).
    """
    ny, nx = z.shape
    py, px = _powers(ny, degree), _powers(nx, degree)
    terms = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]   # x^i y^j
    sub = np.zeros_like(keep)
    sub[::step, ::step] = True
    sel = keep & sub
    if sel.sum() < 50:
        sel = keep
    rr, cc = np.nonzero(sel)
    a = np.column_stack([px[cc, i] * py[rr, j] for i, j in terms])
    coef = np.linalg.solve(a.T @ a + 1e-12 * np.eye(len(terms)), a.T @ z[rr, cc])
    cm = np.zeros((degree + 1, degree + 1))
    for (i, j), c in zip(terms, coef):
        cm[j, i] = c
    return py @ cm @ px.T


def noise_nm(z, keep) -> float:
    """Robust pixel noise (nm) from differences along the rows (immune to line offsets)."""
    d = np.diff(z, axis=1)
    ok = keep[:, 1:] & keep[:, :-1] & np.isfinite(d)
    if ok.sum() < 20:
        return float("nan")
    v = d[ok]
    return float(1.4826 * np.median(np.abs(v - np.median(v))) / np.sqrt(2))


def _row_nanmedian(a, ok):
    """Median of each row over ``ok`` (0 where a row has none)."""
    srt = np.sort(np.where(ok, a, np.inf), axis=1)
    cnt = ok.sum(axis=1)
    lo = np.clip((cnt - 1) // 2, 0, a.shape[1] - 1)
    hi = np.clip(cnt // 2, 0, a.shape[1] - 1)
    i = np.arange(a.shape[0])
    med = 0.5 * (srt[i, lo] + srt[i, hi])
    return np.where(cnt > 0, med, 0.0)


def _align_rows(z, keep):
    """Row offsets by the median of differences to the previous row (Gwyddion 'Align Rows')."""
    step = _row_nanmedian(z[1:] - z[:-1], keep[1:] & keep[:-1])
    off = np.concatenate([[0.0], np.cumsum(step)])
    return off - off.mean()


def _row_medians(z, keep):
    return _row_nanmedian(z, keep)


def _open1d(a, size, axis):
    """Binary opening with a line of ``size`` pixels along ``axis`` (fast 1-D filters)."""
    return max_line(min_line(a, size, axis), size, axis).astype(bool)


def _close1d(a, size, axis):
    """Binary closing with a line of ``size`` pixels along ``axis``."""
    return min_line(max_line(a, size, axis), size, axis, cval=1).astype(bool)


def _remove_scars(z, keep, sigma, k=4.0, min_len=8, max_width=2):
    """Replace streaks 1..max_width rows tall that stand out from the rows above and below.

    A streak is found where the background is free (``keep``) and followed into
    masked features along its rows (a scar does not stop at a pit; inside a
    planar facet the rows above and below still interpolate it).
    """
    ny, nx = z.shape
    thr = max(k * sigma, 1e-9)
    fixed = np.zeros_like(keep)
    out = z.copy()
    row_struct = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 0]], bool)
    for w in range(1, max_width + 1):
        if ny < w + 2:
            break
        above = z[:ny - w - 1]
        below = z[w + 1:]
        hi = np.ones((ny - w - 1, nx), bool)
        lo = np.ones((ny - w - 1, nx), bool)
        free = np.ones((ny - w - 1, nx), bool)
        for j in range(w):
            mid = z[1 + j:ny - w + j]
            da, db = mid - above, mid - below
            hi &= (da > thr) & (db > thr)
            lo &= (da < -thr) & (db < -thr)
            free &= keep[1 + j:ny - w + j]
        free &= keep[:ny - w - 1] & keep[w + 1:]
        for cand in (hi, lo):
            # a streak lies along one row: only rows with min_len free candidates can hold one
            rows = np.flatnonzero(np.count_nonzero(cand & free, axis=1) >= min_len)
            if rows.size == 0:
                continue
            c_r, f_r = cand[rows], free[rows]
            # bridge short gaps inside masked features along the row
            bridged = _close1d(c_r, 7, axis=1) & (c_r | ~f_r)
            lab, n = ndimage.label(bridged, structure=row_struct)
            if n == 0:
                continue
            n_free = np.bincount(lab.ravel(), weights=(c_r & f_r).ravel(), minlength=n + 1)
            good = n_free >= min_len
            good[0] = False
            sel = good[lab]
            rr, cc = np.nonzero(sel)
            rr = rows[rr]
            for j in range(w):
                t = (j + 1) / (w + 1)
                r = rr + 1 + j
                out[r, cc] = (1 - t) * z[rr, cc] + t * z[rr + w + 1, cc]
                fixed[r, cc] = True
    return out, fixed


def feature_mask(z, sigma, min_area_px: int = 6, grow_px: int = 3, k: float = 5.0,
                 min_nm: float = 2.0) -> np.ndarray:
    """Pits and particles: smoothed heights beyond ``k`` sigma, streaks under 7 rows opened away, grown."""
    zs = gaussian(np.nan_to_num(z), 1.0)
    thr = max(k * sigma * 0.5, min_nm)          # smoothing by sigma = 1 px halves white noise
    bad = np.abs(zs) > thr
    # streaks along the rows (scars, left-over line offsets) are a few rows tall: open them away
    bad = _open1d(bad, 7, axis=0)
    bad = _open1d(bad, 3, axis=1)
    lab, n = ndimage.label(bad)
    if n:
        sizes = np.bincount(lab.ravel())
        small = sizes < min_area_px
        small[0] = True
        bad[small[lab]] = False
    g = 2 * grow_px + 1
    return dilate_square(bad, g)                # grown by grow_px: a g x g square


def level_afm(z_nm: np.ndarray, pixel_um: float = 1.0, n_iter: int = 3, bow_degree: int = 3) -> Levelled:
    """Level an AFM height map (nm) with the features masked; iterated.

    Parameters
    ----------
    z_nm : ndarray (rows, cols)
        Raw heights (nm), rows along the slow scan axis. NaN: no data.
    pixel_um : float
        Pixel size (µm), for the tilt angle.
    n_iter : int
        Rounds of fit -> mask.
    bow_degree : int
        Total degree of the background polynomial.
    """
    valid = np.isfinite(z_nm)
    z = np.where(valid, z_nm - np.nanmedian(z_nm), 0.0).astype(np.float64)
    mask = np.zeros(z.shape, bool)
    tilt_deg = 0.0
    bow = 0.0
    sigma = 1.0
    scars = np.zeros(z.shape, bool)
    for it in range(n_iter):
        keep = valid & ~mask
        if keep.sum() < 0.2 * valid.sum():
            keep = valid
        plane = poly_surface(z, keep, 1)
        if it == 0:
            ny, nx = z.shape
            gy = (plane[-1, 0] - plane[0, 0]) / max(ny - 1, 1)
            gx = (plane[0, -1] - plane[0, 0]) / max(nx - 1, 1)
            tilt_deg = float(np.degrees(np.arctan(np.hypot(gx, gy) / (1000.0 * pixel_um))))
        z -= plane
        z -= _align_rows(z, keep)[:, None]
        surf = poly_surface(z, keep, bow_degree)
        if it == 0:
            bow = float(np.ptp(surf - poly_surface(surf, keep, 1)))
        z -= surf
        z -= _row_medians(z, keep)[:, None]
        sigma = noise_nm(z, keep)
        if not np.isfinite(sigma) or sigma <= 0:
            sigma = float(np.std(z[keep])) or 1.0
        mask = feature_mask(z, sigma)
        z, fixed = _remove_scars(z, valid & ~mask, sigma)
        scars |= fixed
    keep = valid & ~mask
    z -= np.median(z[keep]) if keep.any() else 0.0
    z[~valid] = np.nan
    return Levelled(z_nm=z, mask=mask, noise_nm=float(sigma), tilt_deg=tilt_deg, bow_nm=bow,
                    scars=scars)
