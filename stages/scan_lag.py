"""The z loop's lag along the fast scan axis, from a channel scanned both ways (trace and retrace).

An AFM's z feedback follows the surface with a lag: the trace, scanned left to right, shows every slope a
little to the right of where it is, the retrace (right to left) as far to the left. Corners, centre and
boundary of an imprint then lie 0.5-2 px right of the surface in the trace (feedback-loop renderer:
1.3 px on average, every corner). The two directions' offset is twice the lag, whatever the loop's gains;
half of it, taken off, puts the slopes back where they are (``docs/indents.md``, "Trace and retrace").

Frame: (rows, cols) maps, the fast axis along the columns, both channels stored in the same orientation
(as every AFM file does: the retrace's columns run left to right too). A lag is positive where the
channel lies to the right (+x, growing column) of the surface.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .indent_geometry import Imprint, diagonals

__all__ = ["ScanLag", "both_directions", "pair_directions", "scan_lag", "unlag"]

LAG_MAX_PX = 8.0            # a larger lag is not a z loop's (a scan this slow to follow is not measured)
MIN_CORRELATION = 0.5       # the two directions' slopes must agree this well at their offset
FINE_STEP_PX = 0.01         # the offset's resolution (px)


@dataclass(frozen=True)
class ScanLag:
    """How far one channel lies along the fast axis from the surface, by the other scan direction.

    Attributes
    ----------
    lag_px : float
        The channel's shift from the surface (px, +x: to the right), half the two directions' offset.
    correlation : float
        Normalised correlation of the two directions' x slopes at that offset (1: the same map moved).
    """

    lag_px: float
    correlation: float

    @property
    def usable(self) -> bool:
        """Whether the two directions agree well enough (``MIN_CORRELATION``) and the lag is a z loop's
        (``LAG_MAX_PX``) for the lag to be taken out."""
        return bool(self.correlation >= MIN_CORRELATION and abs(self.lag_px) <= LAG_MAX_PX)


def _slopes(z):
    """x slopes (nm per px) with the map's tilt taken off, non-finite ones 0, outliers clipped."""
    g = np.diff(z, axis=1)
    g = np.where(np.isfinite(g), g, np.nan)
    g -= np.nanmedian(g)
    g = np.nan_to_num(g, nan=0.0)
    lim = np.percentile(np.abs(g), 99.9)
    return np.clip(g, -lim, lim) if lim > 0 else g


def scan_lag(z_nm: np.ndarray, other_nm: np.ndarray) -> ScanLag:
    """The lag of ``z_nm`` along the fast axis, from ``other_nm``, the same channel scanned the other way.

    The x slopes of both maps are cross-correlated along the rows (summed over rows, zero-padded: no wrap
    round); the offset is the correlation's maximum, refined to ``FINE_STEP_PX`` on its band-limited
    interpolation. Row offsets and tilt do not enter (slopes, their median taken off); scars and spikes
    are clipped at the slopes' 99.9th percentile.

    Parameters
    ----------
    z_nm, other_nm : ndarray (rows, cols)
        Heights (nm) of the channel and of its other scan direction, same orientation; NaN where not measured.

    Returns
    -------
    ScanLag
        ``lag_px`` is half the offset: ``z_nm`` shifted by ``-lag_px`` along x (:func:`unlag`) lies on the surface.
    """
    a, b = _slopes(np.asarray(z_nm, float)), _slopes(np.asarray(other_nm, float))
    n = a.shape[1]
    m = 2 * n
    cross = (np.fft.rfft(a, m, axis=1) * np.conj(np.fft.rfft(b, m, axis=1))).sum(axis=0)
    norm = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    if norm <= 0:
        return ScanLag(lag_px=0.0, correlation=0.0)
    corr = np.fft.irfft(cross, m)             # corr[k] = sum_x a(x) b(x - k): a is b moved by k
    reach = int(min(2 * LAG_MAX_PX + 2, n - 1))
    ks = np.arange(-reach, reach + 1)
    k0 = int(ks[np.argmax(corr[ks % m])])
    # the correlation between the samples: sum_f cross(f) e^{2 pi i f s / m}, on a fine grid round k0
    s = k0 + np.arange(-1.0, 1.0 + FINE_STEP_PX / 2, FINE_STEP_PX)
    f = np.arange(cross.size)
    w = np.where((f == 0) | (f == m // 2), 1.0, 2.0)        # rfft's one-sided spectrum
    fine = (w * cross)[None, :] * np.exp(2j * np.pi * np.outer(s, f) / m)
    vals = fine.real.sum(axis=1) / m
    best = int(np.argmax(vals))
    return ScanLag(lag_px=float(s[best]) / 2.0, correlation=float(vals[best] / norm))


def unlag(z_nm: np.ndarray, lag_px: float) -> np.ndarray:
    """``z_nm`` moved by ``-lag_px`` along x (cubic spline; the border columns extended): the surface's place.

    Pixels not measured (NaN) stay not measured, moved with the map.
    """
    z = np.asarray(z_nm, float)
    bad = ~np.isfinite(z)
    filled = np.where(bad, np.nanmedian(z), z) if bad.any() else z
    out = ndimage.shift(filled, (0.0, -lag_px), order=3, mode="nearest")
    if bad.any():
        out[ndimage.shift(bad.astype(float), (0.0, -lag_px), order=1, mode="nearest") > 0.01] = np.nan
    return out


def _paired_corners(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``b`` (n, 2) reordered to pair with ``a`` corner by corner (the same turn round the imprint, the rotation
    with the smallest largest distance)."""
    n = len(a)
    best = min(range(n), key=lambda k: float(np.max(np.hypot(*(a - np.roll(b, -k, axis=0)).T))))
    return np.roll(b, -best, axis=0)


def both_directions(trace: Imprint, retrace: Imprint, lag_um: float) -> Imprint:
    """One imprint from its measurements on the trace and on the retrace (the same channel scanned both ways).

    The z loop lays every slope a little along the scan direction: the trace shows a corner one way, the
    retrace as far the other way, by how much depends on the loop and on the slope (a ramp's lag near the
    imprint's border is not the whole map's). The mean of the two positions, corner by corner, cancels it
    whatever its size (feedback renderer, seeds 1-120: corners within 1.5 px on 93 % of seeds, 82 % with the
    whole map moved back by one lag). So the centre and the corners are the means, and the diagonals those of
    the mean corners. Everything else is the trace's, its boundary, floor and chips moved back by ``lag_um``
    (the report draws them on the trace moved back by it): the area is the boundary's, and the two directions'
    areas differ little (correlation 0.77 over those seeds; their mean missed the 1 % goal more often, 67 against
    70 %); depth stays the trace's, as a border-plane reading of the channel takes it.
    """
    base = trace.moved(-lag_um)
    corners = 0.5 * (np.asarray(trace.corners_um, float) + _paired_corners(np.asarray(trace.corners_um, float),
                                                                          np.asarray(retrace.corners_um, float)))
    d1, d2, orient = diagonals(corners)
    diameter = 0.5 * (trace.diameter_um + retrace.diameter_um)
    return replace(base, x_um=0.5 * (trace.x_um + retrace.x_um), y_um=0.5 * (trace.y_um + retrace.y_um),
                   corners_um=corners, diag1_um=float(d1), diag2_um=float(d2), orientation_deg=float(orient),
                   diameter_um=float(diameter), hd_ratio=trace.depth_nm / (1000.0 * diameter))


#: the most a corner's trace-retrace offset may lie off the four corners' median offset for the two measurements to be
#: one imprint's (px): on the feedback renderer, seeds 1-180, median 0.41 px, 99th percentile 2.9 px
PAIR_CORNER_TOL_PX = 3.0


def _agree(trace: Imprint, retrace: Imprint, pixel_um: float) -> bool:
    """Whether the two directions measured the same imprint: both cut by the border or neither (a retrace whose lines
    run out through the imprint), and the corners' offsets between them one shift give or take
    :data:`PAIR_CORNER_TOL_PX`."""
    if bool(trace.cut_by_border) != bool(retrace.cut_by_border):
        return False
    a = np.asarray(trace.corners_um, float)
    off = a - _paired_corners(a, np.asarray(retrace.corners_um, float))
    return bool(np.max(np.hypot(*(off - np.median(off, axis=0)).T)) <= PAIR_CORNER_TOL_PX * pixel_um)


def pair_directions(trace: list, retrace: list, lag_um: float, pixel_um: float) -> tuple:
    """Each imprint of the trace (None: not measured) with the retrace's imprint at its place
    (:func:`both_directions`), or moved back by ``lag_um`` alone where the retrace has none there or one that
    does not agree with it (:func:`_agree`).

    The retrace's imprint lies ``2 lag_um`` left of the trace's; it is the one nearest that place, within a
    quarter of the trace imprint's mean diagonal.

    Returns
    -------
    list, int
        The imprints (the trace's order) and how many were paired.
    """
    found = [m for m in retrace if m is not None]
    xy = np.array([[m.x_um, m.y_um] for m in found]).reshape(-1, 2)
    out, n_paired = [], 0
    for m in trace:
        if m is None:
            out.append(None)
            continue
        dist = np.hypot(xy[:, 0] - (m.x_um - 2 * lag_um), xy[:, 1] - m.y_um)
        j = int(np.argmin(dist)) if len(dist) else -1
        paired = j >= 0 and dist[j] <= 0.25 * m.d_um and _agree(m, found[j], pixel_um)
        out.append(both_directions(m, found[j], lag_um) if paired else m.moved(-lag_um))
        n_paired += paired
    return out, n_paired
