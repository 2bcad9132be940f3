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

from .indent_edges import shoelace
from .indent_geometry import Imprint, diagonals

__all__ = ["ScanLag", "both_directions", "crossing_offsets", "exit_weighted_outline", "floor_separations_px",
           "imprints_shift_px", "pair_directions", "scan_lag", "unlag"]

LAG_MAX_PX = 8.0            # a larger lag is not a z loop's (a scan this slow to follow is not measured)
MIN_CORRELATION = 0.5       # the two directions' slopes must agree this well at their offset
FINE_STEP_PX = 0.01         # the correlation's offset: resolution (px)
CROSSING_LEVELS = 5         # levels per side of the far level at which the two channels' crossings are paired
SLOPE_AGREE = 0.10          # two crossings pair where their slopes differ by at most this share of the larger
MIN_CROSSINGS = 10          # fewer pairs: the offset is the slopes' correlation maximum's
MODE_BANDWIDTH_PX = 0.1     # the crossings' offsets: kernel of their mode (px)


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


def _crossings(z, g, level):
    """Where each row of ``z`` crosses ``level`` between two samples: rows, sub-pixel columns, direction (+1
    rising, -1 falling, along +x) and slope magnitude (nm per px: ``g``, the central differences along x,
    interpolated to the crossing)."""
    a, b = z[:, :-1], z[:, 1:]
    with np.errstate(invalid="ignore"):
        hit = ((a < level) != (b < level)) & np.isfinite(a) & np.isfinite(b)
    r, c = np.nonzero(hit)
    za, zb = z[r, c], z[r, c + 1]
    x = c + (za - level) / (za - zb)
    t = x - c
    slope = np.abs((1 - t) * g[r, c] + t * g[r, c + 1])
    return r, x, np.where(zb > za, 1, -1), slope


def crossing_offsets(z_nm, other_nm, n_levels: int = CROSSING_LEVELS,
                     slope_agree: float = SLOPE_AGREE) -> np.ndarray:
    """Offsets (px) along x of ``z_nm``'s level crossings from ``other_nm``'s, where the two channels cross a level
    the same way with the same slope (within ``slope_agree`` of the larger).

    Each row is matched crossing by crossing (same row, same direction, the nearest within twice
    :data:`LAG_MAX_PX`) at ``n_levels`` levels spread between the maps' far level (their median) and their deep
    tail (0.1th percentile: the imprints' slopes), on the maps as recorded: the two directions of one line share its
    offset and the tilt (an offset between them would move a crossing by offset / slope). On a slope both
    directions follow, the channels show the same slope, twice the lag apart. Where the z loop could not follow a
    descent (the tip parachutes after a rim: the height falls at the loop's slew rate, not the surface's), the
    channel going down shows a shallower slope, further along: such pairs are left out.
    """
    a, b = np.asarray(z_nm, float), np.asarray(other_nm, float)
    both = np.concatenate([a[np.isfinite(a)], b[np.isfinite(b)]])
    if both.size == 0:
        return np.zeros(0)
    mid, deep = np.percentile(both, [50.0, 0.1])
    fr = (np.arange(n_levels) + 1.0) / (n_levels + 1.0)
    span = a.shape[1] + 4 * LAG_MAX_PX + 8.0               # keys: a row and a direction per span
    ga, gb = np.gradient(a, axis=1), np.gradient(b, axis=1)
    out = []
    for level in mid + fr * (deep - mid):
        ra, xa, da, sa = _crossings(a, ga, level)
        rb, xb, db, sb = _crossings(b, gb, level)
        if not len(ra) or not len(rb):
            continue
        # one sorted key per crossing of the other channel: row and direction first, then x
        key_b = (2 * rb + (db > 0)) * span + xb
        order = np.argsort(key_b)
        key_b, xb, sb = key_b[order], xb[order], sb[order]
        key_a = (2 * ra + (da > 0)) * span + xa
        j = np.clip(np.searchsorted(key_b, key_a), 1, len(key_b) - 1)
        near = np.where(np.abs(key_b[j - 1] - key_a) <= np.abs(key_b[j] - key_a), j - 1, j)
        off = key_a - key_b[near]
        ok = (np.abs(off) <= 2 * LAG_MAX_PX) & (np.abs(sa - sb[near]) <= slope_agree * np.maximum(sa, sb[near]))
        out.append(off[ok])
    return np.concatenate(out) if out else np.zeros(0)


def _mode(values, bandwidth):
    """The densest value of ``values`` (Gaussian kernel of ``bandwidth``, on a grid a fifth of it), refined to the
    mean of the values within one bandwidth of it."""
    step = bandwidth / 5.0
    edges = np.arange(values.min() - 3 * bandwidth, values.max() + 3 * bandwidth + step, step)
    hist, _ = np.histogram(values, edges)
    dens = ndimage.gaussian_filter1d(hist.astype(float), 5.0, mode="constant")
    peak = edges[int(np.argmax(dens))] + step / 2
    near = values[np.abs(values - peak) <= bandwidth]
    return float(near.mean()) if near.size else float(peak)


def scan_lag(z_nm: np.ndarray, other_nm: np.ndarray) -> ScanLag:
    """The lag of ``z_nm`` along the fast axis, from ``other_nm``, the same channel scanned the other way.

    The offset is the most common one between the two channels' level crossings on slopes both follow
    (:func:`crossing_offsets`, the mode at :data:`MODE_BANDWIDTH_PX`): a ramp's lag, the one that moves an imprint's
    edges. Whether the two are the same map moved is told by their x slopes: cross-correlated along the rows
    (summed over rows, zero-padded, no wrap round; tilt and row offsets do not enter, scars and spikes are clipped
    at the 99.9th percentile), the correlation's maximum is ``correlation``. Where fewer than
    :data:`MIN_CROSSINGS` crossings pair, the offset is that maximum's, refined to ``FINE_STEP_PX``.

    Before (session 27 and earlier) the correlation's maximum was the offset. On the feedback renderer (seeds 1-60)
    it was within 0.3 px of the ramp lag on 40 % of maps, 2.4 px off at worst: a slow loop follows short features
    (rims, particles, the slope's turns) with less lag than a ramp, and a tip that parachutes past a rim lays the
    descent far along; the crossings' mode is within 0.3 px on 59 of 60 (``docs/indents.md``, session 28).

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
    offset = float(s[best])
    pairs = crossing_offsets(z_nm, other_nm)
    if pairs.size >= MIN_CROSSINGS:
        offset = _mode(pairs, MODE_BANDWIDTH_PX)
    return ScanLag(lag_px=offset / 2.0, correlation=float(vals[best] / norm))


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


#: directions round the centre at which the two scan directions' outlines are blended
OUTLINE_DIRECTIONS = 1440


def _outer_radius(outline, centre, phi):
    """Distance from ``centre`` to the outermost crossing of the closed ``outline`` (n, 2) along each direction
    ``phi`` (rad from +x); NaN where a ray meets no side."""
    p = np.asarray(outline, float) - centre
    e = np.roll(p, -1, axis=0) - p
    out = np.full(len(phi), np.nan)
    for i in range(0, len(phi), 180):                       # 180 rays at a time: (rays, sides) arrays stay small
        d = np.stack([np.cos(phi[i:i + 180]), np.sin(phi[i:i + 180])], axis=1)
        den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (p[None, :, 0] * d[:, None, 1] - p[None, :, 1] * d[:, None, 0]) / den     # along the side
            t = (p[None, :, 0] * e[None, :, 1] - p[None, :, 1] * e[None, :, 0]) / den     # along the ray
        hit = (u >= -1e-9) & (u <= 1.0 + 1e-9) & (t > 0) & np.isfinite(t)     # a vertex on the ray: both sides
        t = np.where(hit, t, -np.inf).max(axis=1)
        out[i:i + 180] = np.where(np.isfinite(t), t, np.nan)
    return out


def exit_weighted_outline(trace_um: np.ndarray, retrace_um: np.ndarray, centre_um) -> np.ndarray | None:
    """One outline (n, 2) of a boundary from the trace's and the retrace's (both on the surface, the lag taken
    out), each counted where its scan leaves the imprint; None where a direction from the centre misses either.

    Along each of :data:`OUTLINE_DIRECTIONS` directions ``phi`` (from +x) from ``centre_um``, the radius is
    ``w r_trace + (1 - w) r_retrace`` with ``w = (1 + cos phi) / 2``: the trace counts on the right, where it climbs
    out of the imprint, the retrace on the left, half each above and below. Each radius is the outline's outermost
    crossing (the small loops chips leave inside an outline do not count). A loop follows a climb with its lag,
    but a descent only as fast as it can fall: past a high rim the tip parachutes, and the edge where a scan enters
    the imprint shows a slope shallower and further in than the surface (feedback renderer, seed 168: 14-20 px
    inside over a quarter of the outline, on the trace's left and the retrace's right).
    """
    c = np.asarray(centre_um, float)
    phi = np.linspace(-np.pi, np.pi, OUTLINE_DIRECTIONS, endpoint=False)
    r_trace, r_retrace = _outer_radius(trace_um, c, phi), _outer_radius(retrace_um, c, phi)
    if not (np.isfinite(r_trace).all() and np.isfinite(r_retrace).all()):
        return None
    w = 0.5 * (1.0 + np.cos(phi))
    r = w * r_trace + (1.0 - w) * r_retrace
    return c + r[:, None] * np.column_stack([np.cos(phi), np.sin(phi)])


def both_directions(trace: Imprint, retrace: Imprint, lag_um: float) -> Imprint:
    """One imprint from its measurements on the trace and on the retrace (the same channel scanned both ways).

    The z loop lays every slope a little along the scan direction: the trace shows a corner one way, the
    retrace as far the other way, by how much depends on the loop and on the slope (a ramp's lag near the
    imprint's border is not the whole map's). The mean of the two positions, corner by corner, cancels it
    whatever its size (feedback renderer, seeds 1-120: corners within 1.5 px on 93 % of seeds, 82 % with the
    whole map moved back by one lag). So the centre and the corners are the means, and the diagonals those of
    the mean corners. The boundary and its area count each direction's outline where its scan leaves the imprint
    (:func:`exit_weighted_outline`). Everything else is the trace's, its floor and chips moved back by ``lag_um``;
    depth stays the trace's, as a border-plane reading of the channel takes it.
    """
    base = trace.moved(-lag_um)
    corners = 0.5 * (np.asarray(trace.corners_um, float) + _paired_corners(np.asarray(trace.corners_um, float),
                                                                          np.asarray(retrace.corners_um, float)))
    d1, d2, orient = diagonals(corners)
    diameter = 0.5 * (trace.diameter_um + retrace.diameter_um)
    area, outline = base.area_um2, base.contour_um
    if outline is not None and retrace.contour_um is not None and np.isfinite(area) \
            and np.isfinite(retrace.area_um2):
        both = exit_weighted_outline(outline, retrace.moved(lag_um).contour_um, corners.mean(axis=0))
        if both is not None:
            area, outline = shoelace(both), both
    return replace(base, x_um=0.5 * (trace.x_um + retrace.x_um), y_um=0.5 * (trace.y_um + retrace.y_um),
                   corners_um=corners, diag1_um=float(d1), diag2_um=float(d2), orientation_deg=float(orient),
                   diameter_um=float(diameter), hd_ratio=trace.depth_nm / (1000.0 * diameter), area_um2=area,
                   contour_um=outline)


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
    out, n_paired = [], 0
    for m, r in _matches(trace, retrace, lag_um, pixel_um):
        out.append(None if m is None else m.moved(-lag_um) if r is None else both_directions(m, r, lag_um))
        n_paired += r is not None
    return out, n_paired


def _matches(trace: list, retrace: list, lag_um: float, pixel_um: float) -> list:
    """Each imprint of the trace (None: not measured) with the retrace's imprint at its place, or None: the retrace's
    nearest ``2 lag_um`` left of it, within a quarter of the trace imprint's mean diagonal, that agrees with it
    (:func:`_agree`)."""
    found = [m for m in retrace if m is not None]
    xy = np.array([[m.x_um, m.y_um] for m in found]).reshape(-1, 2)
    out = []
    for m in trace:
        if m is None or not len(found):
            out.append((m, None))
            continue
        dist = np.hypot(xy[:, 0] - (m.x_um - 2 * lag_um), xy[:, 1] - m.y_um)
        j = int(np.argmin(dist))
        out.append((m, found[j] if dist[j] <= 0.25 * m.d_um and _agree(m, found[j], pixel_um) else None))
    return out


#: imprints that must pair for :func:`imprints_shift_px` to tell their shift
SHIFT_MIN_PAIRS = 3


def imprints_shift_px(trace: list, retrace: list, lag_um: float, pixel_um: float) -> float | None:
    """How far the trace's imprints lie along the fast axis (px, +x): half the median x offset of their centres from
    the retrace's imprints at their places (:func:`_matches`); None where under :data:`SHIFT_MIN_PAIRS` pair.

    A loop moves a short imprint by other than a ramp's lag, and on a sparse array the crossings' lag rests on few
    slopes (the bench's arrays through a PI loop: 1 µm imprints 10 px across moved 0.93-1.47 px for ramp lags of
    1.0-1.9 px, and one map's crossings read 0.41 px for 1.91; ``docs/indents.md``, sessions 28-29)."""
    offsets = [(m.x_um - r.x_um) / pixel_um for m, r in _matches(trace, retrace, lag_um, pixel_um) if r is not None]
    return float(np.median(offsets)) / 2 if len(offsets) >= SHIFT_MIN_PAIRS else None


#: the trace's floor lying this far (px) right of the retrace's beyond twice the lag: neither scan reached the floor.
#: Feedback renderer seeds 1-40: 0.27 px at most where the loop falls as fast as the facets (descent >= 1); 2.5-25 px
#: on the 17 seeds whose depth is 3-23 % short because the tip parachutes
FLOOR_MISSED_PX = 2.0


def floor_separations_px(trace: list, retrace: list, lag_um: float, pixel_um: float) -> list:
    """How far (px, +x) each paired imprint's floor lies on the trace right of the retrace's, beyond twice the lag
    (:func:`_matches`; imprints without a retrace's or a floor left out).

    A tip that falls slower than a facet descends on a line of its own and meets the far facet above the floor:
    the trace's deepest point lies right of the floor, the retrace's as far left, and both are short of it. On a
    V profile of half-width ``a`` the depth missed is ``separation / (2 a)`` of the whole; with
    :data:`FLOOR_MISSED_PX` or more the depth is a lower bound."""
    out = []
    for m, r in _matches(trace, retrace, lag_um, pixel_um):
        if r is not None and m.floor_um is not None and r.floor_um is not None:
            out.append((m.floor_um[0] - r.floor_um[0] - 2 * lag_um) / pixel_um)
    return out
