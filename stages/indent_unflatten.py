"""Scans flattened line by line before export, imprint and all: recognised, and each line's fit put back.

A line flatten (NanoScope's *Flatten*, Gwyddion's *Align rows*) takes off every scan line's own fit to the
whole line: its mean, median, or a polynomial of order 1-3. Through an imprint that fills much of the field
the fit follows the imprint, so the far field of those lines stands hundreds of nm off, and its slope too
for order 1. Such a map carries a signature no scan has by itself: the fits of all its lines are equal (to
the file's rounding), up to a plane levelled afterwards (:func:`detect_line_flatten`). Where it is seen,
:func:`unflatten_lines` fits each line's polynomial again, to that line's far field only, and takes it off:
the map as it was before the flatten, up to a plane.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .level import noise_nm

__all__ = ["LineFlatten", "Unflattened", "detect_line_flatten", "unflatten_lines"]

#: lines whose fits must agree: a few odd lines (blank, NaN) may differ
AGREE_FRACTION = 0.95
#: fits agree within this fraction of the pixel noise (a scan's own lines differ by noise / sqrt(width))
AGREE_NOISE = 0.02
#: a line whose fit rests on less than this fraction of its pixels has too little far field to be sure of:
#: counted (``Unflattened.n_short_lines``). Independent ruled seeds 1-12: every flattened seed that misses a
#: goal has 42-116 such lines of 256; every one that meets them 0, except one with 30
SHORT_FAR_FIELD = 0.15


@dataclass(frozen=True)
class LineFlatten:
    """A flatten found in a map.

    Attributes
    ----------
    axis : int
        0: each row was flattened (the fast scan axis along x); 1: each column.
    order : int
        Order of the polynomial taken off each line (0: an offset).
    how : str
        ``"poly"`` (least squares; order 0 is the mean) or ``"median"``.
    """

    axis: int
    order: int
    how: str

    def describe(self) -> str:
        line = "row" if self.axis == 0 else "column"
        what = {0: "mean", 1: "line", 2: "quadratic", 3: "cubic"}[self.order] if self.how == "poly" else "median"
        return f"each {line}'s {what} taken off"


def _basis(n, order):
    t = np.linspace(-1.0, 1.0, n)
    return t[:, None] ** np.arange(order + 1)                 # (n, order + 1)


def _line_fits(z, order, how):
    """Each row's fit of ``z``: (rows, order + 1) coefficients; NaN for rows with missing pixels."""
    full = np.isfinite(z).all(axis=1)
    rows = z if full.all() else z[full]
    out = np.full((z.shape[0], order + 1), np.nan)
    if how == "median":
        out[full, 0] = np.median(rows, axis=1)
    elif order == 0:
        out[full, 0] = rows.mean(axis=1)                  # the least-squares constant
    else:
        out[full] = np.linalg.lstsq(_basis(z.shape[1], order), rows.T, rcond=None)[0].T
    return out


def _agree(coef, tol):
    """Whether the rows' fits are equal within ``tol`` (a number, or one per row) up to a trend along the
    lines' index (a plane)."""
    ok = np.isfinite(coef[:, 0])
    if ok.sum() < max(8, 0.5 * len(coef)):
        return False
    i = np.flatnonzero(ok).astype(float)
    c = coef[ok]
    trend = np.column_stack([np.polyval(np.polyfit(i, c[:, k], 1), i) for k in range(c.shape[1])])
    dev = np.max(np.abs(c - trend), axis=1) / np.broadcast_to(tol, ok.shape)[ok]
    return bool(np.quantile(dev, AGREE_FRACTION) <= 1.0)


def significant_digits(v):
    """How many significant digits (2-6) the values ``v`` (finite, nonzero) were written with, or None.

    Text exports often keep 3 or 4 digits (``-1.65E+00``).
    """
    def written_with(x, n):
        m = x / 10.0 ** (np.floor(np.log10(np.abs(x))) - n + 1)       # n digits before the point
        return bool(np.all(np.abs(m - np.round(m)) <= 1e-6 * np.abs(m)))

    for n in range(2, 7):
        if written_with(v[:64], n) and written_with(v, n):          # most maps fail on the first values
            return n
    return None


def value_step(v, digits=None):
    """The step of the grid the values ``v`` lie on (integer counts times their scale), or 0.0 for values of
    any size: the typical smallest gap between distinct values, when 95 % of all gaps are whole multiples of
    it (to the last of ``digits`` significant digits, when the values were written so)."""
    u = np.unique(v[:: max(1, v.size // 4096)])
    if u.size < 8:
        return 0.0
    gap = np.diff(u)
    slack = 0.0
    if digits is not None:
        top = np.maximum(np.abs(u[1:]), np.abs(u[:-1]))
        slack = 10.0 ** (np.floor(np.log10(np.maximum(top, 1e-300))) - digits + 1)
    best, best_whole = 0.0, 0.0
    small, count = np.unique(np.round(gap[gap < 1.5 * np.percentile(gap, 10)], 12), return_counts=True)
    for step in small[np.argsort(-count)][:16]:                 # the commonest small gaps
        if step > 0:
            whole = np.mean(np.abs(gap - step * np.round(gap / step)) <= 0.02 * step + slack)
            best, best_whole = (step, whole) if whole > best_whole else (best, best_whole)
    return float(best) if best_whole >= 0.95 else 0.0


@dataclass(frozen=True)
class Rounding:
    """How a map's heights were rounded when written: ``digits`` significant digits (None: not so) and a
    grid of ``step_nm`` (0: none). Each height is then off by up to half its last digit or step, which
    scatters the lines' fits by more than a flatten's agreement allows on a smooth map."""

    digits: int | None
    step_nm: float

    @classmethod
    def of(cls, z, n_sample=65536):
        v = np.asarray(z, np.float64).ravel()
        v = v[np.isfinite(v) & (v != 0)]
        if v.size < 64:
            return cls(None, 0.0)
        v = v[:: max(1, v.size // n_sample)]
        digits = significant_digits(v)
        return cls(digits, value_step(v, digits))

    def tol(self, zz, order, k_sigma=4.0):
        """Per row of ``zz``: ``k_sigma`` times the largest standard deviation the rounding gives a
        coefficient of the row's polynomial fit of ``order`` (uniform, independent rounding errors)."""
        var_px = np.full(zz.shape[0], self.step_nm ** 2 / 12.0)
        if self.digits is not None:
            last = 10.0 ** (np.floor(np.log10(np.maximum(np.abs(zz), 1e-300))) - self.digits + 1)
            var_px = var_px + np.nanmean(np.where(np.isfinite(zz), last ** 2 / 12.0, np.nan), axis=1)
        b = _basis(zz.shape[1], order)
        gain = float(np.max(np.diag(np.linalg.inv(b.T @ b))))
        return k_sigma * np.sqrt(var_px * gain)


def detect_line_flatten(z_nm: np.ndarray) -> LineFlatten | None:
    """The line flatten a map went through, or None.

    Every line's mean, median or polynomial fit equal (within 2 % of the pixel noise, on 95 % of the lines),
    up to a plane: the signature of a flatten that left only what its fits cannot hold. A scan's own lines
    differ by the noise over the square root of their length at least, and by tens of nm where they cross an
    imprint.
    """
    z = np.asarray(z_nm, np.float64)
    if z.ndim != 2 or min(z.shape) < 16:
        return None
    finite = np.isfinite(z)
    if not finite.any():
        return None
    few = slice(None, None, max(1, z.shape[0] // 64))           # the noise from some 64 lines is enough
    sigma = noise_nm(np.where(finite, z, 0.0)[few], finite[few])
    scale = float(np.nanmax(z) - np.nanmin(z))
    if not (np.isfinite(sigma) and scale > 0):
        return None
    # the file's rounding: float32 keeps 7 digits of the heights' range; a text export may keep fewer
    tol = max(AGREE_NOISE * sigma, 1e-6 * scale)
    rounding = Rounding.of(z)
    for axis in (0, 1):
        zz = z if axis == 0 else z.T

        def tol_of(order):
            if rounding.digits is None and rounding.step_nm == 0.0:
                return tol
            return np.maximum(tol, rounding.tol(zz, order))

        # any least-squares flatten leaves every line's mean alike: the higher orders are tried only then;
        # a median flatten is tried on a few lines first (the whole map's medians cost more)
        if _agree(_line_fits(zz, 0, "poly"), tol_of(0)):
            for order in (3, 2, 1):
                if _agree(_line_fits(zz, order, "poly"), tol_of(order)):
                    return LineFlatten(axis=axis, order=order, how="poly")
            return LineFlatten(axis=axis, order=0, how="poly")
        few = zz[:: max(1, zz.shape[0] // 24)]
        if _agree(_line_fits(few, 0, "median"), tol) and _agree(_line_fits(zz, 0, "median"), tol):
            return LineFlatten(axis=axis, order=0, how="median")
    return None


def _robust_row(z, ok, b, start, scale, n_iter=8):
    """Tukey-biweight fit of one line (``b``: its basis) over ``ok``, from ``start`` (None: least squares):
    the coefficients and the inliers (within ``scale`` of the fit) (:func:`_tukey_fit`)."""
    c0 = np.zeros(b.shape[1]) if start is None else np.asarray(start, np.float64)
    return _tukey_fit(np.asarray(z, np.float64), ok, b, c0, start is None, float(scale), n_iter)


@njit(cache=True)
def _tukey_fit(z, ok, b, c, from_lsq, scale, n_iter):
    """Weighted normal equations of the line's few coefficients, re-weighted ``n_iter`` times (Tukey's
    biweight at ``scale``) from ``c``, or (``from_lsq``) from the plain least-squares fit over ``ok``."""
    n, k = b.shape
    w = np.where(ok, 1.0, 0.0)
    c = _weighted_solve(z, b, w) if from_lsq else c.copy()
    for _ in range(n_iter):
        cnt = 0
        for i in range(n):
            w[i] = 0.0
            if ok[i]:
                r = (z[i] - _dot(b, i, c)) / scale
                if abs(r) < 1.0:
                    w[i] = (1.0 - r * r) ** 2
                    cnt += 1
        if cnt < k + 2:
            break
        c = _weighted_solve(z, b, w)
    inl = np.zeros(n, np.bool_)
    for i in range(n):
        inl[i] = ok[i] and abs(z[i] - _dot(b, i, c)) < scale
    return c, inl


@njit(cache=True)
def _dot(b, i, c):
    s = 0.0
    for j in range(b.shape[1]):
        s += b[i, j] * c[j]
    return s


@njit(cache=True)
def _weighted_solve(z, b, w):
    """Least squares of ``z`` on the columns of ``b`` with weights ``w`` (normal equations, a few columns)."""
    n, k = b.shape
    ata = np.zeros((k, k))
    atz = np.zeros(k)
    for i in range(n):
        if w[i] > 0.0:
            for j in range(k):
                atz[j] += w[i] * b[i, j] * z[i]
                for m in range(k):
                    ata[j, m] += w[i] * b[i, j] * b[i, m]
    return np.linalg.solve(ata + 1e-12 * np.eye(k), atz)


def _common_profile(zz, valid, order, scale):
    """What a flatten of ``order`` leaves in every line alike: the scan's slope (order 0) and bow (orders
    0-1) along the lines, from the lines at the top and bottom of the map (nm per pixel along the lines)."""
    deg = max(2, order)
    ny, nx = zz.shape
    b = _basis(nx, deg)
    m = max(3, ny // 20)
    high = [_robust_row(zz[r], valid[r], b, None, scale)[0][order + 1:]
            for r in list(range(m)) + list(range(ny - m, ny)) if valid[r].sum() > 2 * (deg + 1)]
    if not high:
        return np.zeros(nx)
    return b[:, order + 1:] @ np.median(np.array(high), axis=0)


def _track_lines(y, valid, b, scale, min_px, rows):
    """Each line's fit, line after line in the order ``rows``, each started from the last ones' (so that the
    far field stays the line's level even where the imprint fills most of the line): (lines, order + 1)
    coefficients, NaN where fewer than ``min_px`` pixels (for a slope: two on each half) lie within
    ``scale`` of the fit, and the counts of those pixels."""
    k = b.shape[1]
    coef = np.full((y.shape[0], k), np.nan)
    n_in = np.zeros(y.shape[0], int)
    hist = []
    half = y.shape[1] // 2
    for r in rows:
        ok = valid[r]
        if ok.sum() < min_px:
            continue
        start = None if not hist else (hist[-1] if len(hist) < 2 else 2 * hist[-1] - hist[-2])
        c, inl = _robust_row(y[r], ok, b, start, scale)
        if inl.sum() >= min_px and (k == 1 or min(inl[:half].sum(), inl[half:].sum()) >= 2):
            coef[r], n_in[r] = c, inl.sum()
            hist.append(c)
    return coef, n_in


def _fill_rows(coef):
    """Lines without a fit take their neighbours' (interpolated per coefficient, held at the ends)."""
    ok = np.isfinite(coef[:, 0])
    if not ok.any():
        return np.zeros_like(coef)
    i = np.arange(len(coef))
    return np.column_stack([np.interp(i, i[ok], coef[ok, k]) for k in range(coef.shape[1])])


@dataclass(frozen=True)
class Unflattened:
    """A map with its line flatten undone.

    Attributes
    ----------
    z_nm : ndarray
        The map before the flatten (nm, up to a plane).
    n_short_lines : int
        Lines whose fit rests on less than ``SHORT_FAR_FIELD`` of their pixels (or none: taken from their
        neighbours): where pile-up or the imprint reaches both ends of a line, its level is uncertain.
    n_lines : int
        Lines in the map (along the flatten).
    """

    z_nm: np.ndarray
    n_short_lines: int
    n_lines: int


def unflatten_lines(z_nm: np.ndarray, flat: LineFlatten) -> Unflattened:
    """The map before the line flatten ``flat`` (nm, up to a plane), and how many lines had little far field.

    Each line's polynomial of the flatten's order is fitted again, robustly, to the line's far field and
    taken off. What the flatten left alike in every line (the scan's slope and bow along the lines) is
    taken from the lines at the map's top and bottom first. The far field is followed line by line, from
    the top and from the bottom of the map, each line's fit started from the lines before it; of the two
    passes the fit with more pixels on it is kept, and a line with too little far field (for a slope:
    on both halves of it) takes its neighbours' fit.
    """
    z = np.asarray(z_nm, np.float64)
    zz = z if flat.axis == 0 else z.T
    valid = np.isfinite(zz)
    zz = np.where(valid, zz, 0.0)
    ny, nx = zz.shape
    order = flat.order
    b = _basis(nx, order)
    sigma = noise_nm(zz, valid)
    sigma = sigma if np.isfinite(sigma) and sigma > 0 else 1.0
    scale = max(6.0 * sigma, 15.0)
    min_px = max(3 * (order + 1), 6)
    y = zz - _common_profile(zz, valid, order, scale)[None, :]
    down, n_down = _track_lines(y, valid, b, scale, min_px, range(ny))
    up, n_up = _track_lines(y, valid, b, scale, min_px, range(ny - 1, -1, -1))
    coef = _fill_rows(np.where((n_up > n_down)[:, None], up, down))
    u = np.where(valid, zz - coef @ b.T, np.nan)
    n_short = int(np.sum(np.maximum(n_up, n_down) < SHORT_FAR_FIELD * valid.sum(axis=1)))
    return Unflattened(z_nm=u if flat.axis == 0 else u.T, n_short_lines=n_short, n_lines=ny)
