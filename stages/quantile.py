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
