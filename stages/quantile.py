"""Percentiles of millions of values without sorting them all.

``np.percentile`` partitions the whole array (about 0.1-0.3 s for 5.4 M
points). A percentile only needs the two order statistics around its index: a
strided sample brackets them, one compiled pass counts the values below the
bracket and keeps those inside, and only those are sorted. The result is
``np.percentile``'s linear interpolation of the same order statistics.
"""
from __future__ import annotations

import numpy as np
from numba import njit

#: below this many values np.percentile itself is used
SMALL = 200_000
#: values in the strided sample that brackets each percentile
SAMPLE = 20_000
#: half width of the bracket, in percent (about 7 standard errors of a 20 000-value sample's quantile)
MARGIN_PCT = 1.0


@njit(cache=True, nogil=True)
def _bracket(a, lo, hi):  # pragma: no cover - compiled
    """Count of values below ``lo`` and the values in [lo, hi]."""
    below = 0
    m = 0
    out = np.empty(len(a), a.dtype)
    for i in range(len(a)):
        x = a[i]
        if x < lo:
            below += 1
        elif x <= hi:
            out[m] = x
            m += 1
    return below, out[:m]


def percentiles(a: np.ndarray, q) -> np.ndarray:
    """``np.percentile(a, q)`` (linear method) of a 1-D array of finite values.

    Parameters
    ----------
    a : ndarray, shape (n,)
        Finite values (any strides).
    q : sequence of float
        Percentiles, 0-100.
    """
    a = np.asarray(a)
    q = np.atleast_1d(np.asarray(q, float))
    n = len(a)
    if n < SMALL:
        return np.percentile(np.asarray(a, float), q)
    sample = np.sort(a[::max(1, n // SAMPLE)])
    out = np.empty(len(q))
    for j, p in enumerate(q):
        pos = p / 100 * (n - 1)
        i0 = int(np.floor(pos))
        i1 = min(i0 + 1, n - 1)
        lo = np.percentile(sample, p - MARGIN_PCT) if p - MARGIN_PCT > 0 else -np.inf
        hi = np.percentile(sample, p + MARGIN_PCT) if p + MARGIN_PCT < 100 else np.inf
        below, inside = _bracket(a, lo, hi)
        if below > i0 or below + len(inside) <= i1:          # the sample missed: sort everything
            out[j] = np.percentile(np.asarray(a, float), p)
            continue
        v = np.partition(inside, [i0 - below, i1 - below]) if len(inside) > 1 else inside
        x0, x1 = float(v[i0 - below]), float(v[i1 - below])      # float32 values: interpolate in float64
        t = pos - i0
        out[j] = x1 - (x1 - x0) * (1 - t) if t >= 0.5 else x0 + (x1 - x0) * t
    return out


def median_filter(a: np.ndarray, size: int) -> np.ndarray:
    """``scipy.ndimage.median_filter(a, size, mode="nearest")`` of a 2-D array of finite values, odd ``size``.

    The same values (the median of an odd count is one of them), from the values' ranks: a Fenwick
    tree over the ranks slides along each row of windows (``size`` ranks out, ``size`` in, one
    descent for the median), O(size log n) per window instead of a selection among size² values.
    15 x 15 windows over 250 x 250 cells: 0.03 s instead of 0.16 s.
    """
    if size % 2 != 1 or size < 1:
        raise ValueError(f"median_filter: size must be odd and positive, not {size}")
    padded = np.pad(np.asarray(a, np.float64), size // 2, mode="edge")
    values = np.unique(padded)
    ranks = np.searchsorted(values, padded)
    return values[_window_median_ranks(ranks, size, len(values))]


@njit(cache=True, nogil=True)
def _window_median_ranks(ranks, size, n_values):  # pragma: no cover - compiled
    """Rank of the median of every size x size window of ``ranks`` (a Fenwick tree of counts per rank)."""
    ny, nx = ranks.shape[0] - size + 1, ranks.shape[1] - size + 1
    out = np.empty((ny, nx), np.int64)
    tree = np.zeros(n_values + 1, np.int64)
    top = 1
    while top * 2 <= n_values:
        top *= 2
    want = size * size // 2 + 1                  # the median is the want-th smallest (1-based)
    for r in range(ny):
        for i in range(size):
            for j in range(size):
                _fenwick_add(tree, ranks[r + i, j] + 1, 1)
        for c in range(nx):
            if c > 0:
                for i in range(size):
                    _fenwick_add(tree, ranks[r + i, c - 1] + 1, -1)
                    _fenwick_add(tree, ranks[r + i, c + size - 1] + 1, 1)
            pos, rem, step = 0, want, top
            while step > 0:
                if pos + step <= n_values and tree[pos + step] < rem:
                    pos += step
                    rem -= tree[pos]
                step //= 2
            out[r, c] = pos                       # 0-based rank of the median
        for i in range(size):                     # empty the tree for the next row
            for j in range(nx - 1, nx - 1 + size):
                _fenwick_add(tree, ranks[r + i, j] + 1, -1)
    return out


@njit(cache=True, nogil=True, inline="always")
def _fenwick_add(tree, i, delta):  # pragma: no cover - compiled
    n = len(tree) - 1
    while i <= n:
        tree[i] += delta
        i += i & -i
