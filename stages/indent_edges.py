"""Edges of a single imprint between its corners, and the chips spalled beside them.

Brittle materials (glass, ceramics) spall beside a Vickers imprint's edges (lateral cracks): a
flat-bottomed chip tens to hundreds of nm deep that the contact boundary at the surface level runs
round. An operator draws the imprint's edge past it. :func:`edges_past_chips` does the same: each
edge between two corners is a smooth curve through them (bowed in by sink-in or out by pile-up),
fitted to the boundary where it follows the edge; where the boundary leaves the curve outwards by
more than a chip's least width over a flat shelf (a facet's own wiggle slopes as the facet does), the run is
taken back onto the curve and its area counted as chipped.

Frame: (x, y) µm, the contour a closed polyline, the corners in order around the imprint.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .indent_geometry import inside_polygon

__all__ = ["EdgesPastChips", "edge_frame", "edges_past_chips", "shoelace"]

FIT_ITER = 8               # rounds of the edge fit, the outward tolerance shrinking each round
START_TOL_HALF_D = 0.10    # first round: points within this of the chord (of d/2; bows reach 0.08)
TOL_PX = 1.0               # final tolerance: the boundary's roughness and the curve's misfit (px) ...
TOL_HALF_D = 0.015         # ... or this of d/2, the larger
CHIP_MIN_PX = 3.0          # a chip stands out of the edge by this (px) ...
CHIP_MIN_HALF_D = 0.06     # ... and this of d/2 at least (the feedback renderer's chips: 0.1-0.3 of d/2)
REFIT_TOL_CHIP = 0.5       # an edge fitted again from its neighbours' bow starts at this much of a chip's least width
CORNER_KEEP_T = 0.04       # the boundary this close to a corner (fraction of the edge) is the corner's own
SHELF_SLOPES = 0.5         # a chip's floor is a shelf: a tenth of the region or more sloping under half a facet's
SHELF_SHARE = 0.1          # slope (its walls, smeared by the z loop, take the rest: 25-75 % on the feedback
                           # renderer's chips; 0 % on a facet's S-bend at a shear step, feedback seed 9)


@dataclass(frozen=True)
class EdgesPastChips:
    """The contact boundary with chips taken back onto the edges, and what was taken.

    ``contour_um`` (n, 2) the boundary, chips replaced by the fitted edges; ``chipped_area_um2`` the
    area between the two (0 without chips); ``chipped_edges`` the edges (k: corner k to k + 1) that had one;
    ``chips_um`` each chip's outline (m, 2): the boundary round it, back along the edge.
    """

    contour_um: np.ndarray
    chipped_area_um2: float
    chipped_edges: tuple
    chips_um: tuple = ()


def edge_frame(p0, p1, centre):
    """Unit vector along the edge from corner ``p0`` to ``p1``, its outward normal (away from ``centre``) and
    the chord's length."""
    chord = p1 - p0
    ln = float(np.hypot(*chord))
    e = chord / ln
    nrm = np.array([e[1], -e[0]])
    if nrm @ ((p0 + p1) / 2 - centre) < 0:
        nrm = -nrm
    return e, nrm, ln


def _curve(t, coef):
    """Offset (outward) of the edge at fraction t of its chord: t (1 - t) (a + b t), zero at both corners."""
    return t * (1 - t) * (coef[0] + coef[1] * t)


def _fit_edge(t, off, half_d, tol, start_mid=0.0, start_tol=None):
    """Edge curve fitted to the boundary points that lie on it.

    Started from the chord; each round keeps the points within a tolerance of the last curve, shrinking from a
    tenth of d/2 (beyond any bow, within most chips' width) to ``tol``: the majority of the edge, neither a chip
    outwards nor a notch inwards. A symmetric bow first (a chip at one end would otherwise bend the curve's
    asymmetric term out to it), then both terms on the points left. Fitted again from the neighbours' bow: a
    symmetric curve ``start_mid`` out at the edge's middle, the tolerance shrinking from ``start_tol``.
    """
    coef = np.array([4.0 * start_mid, 0.0])
    a = np.column_stack([t * (1 - t), t * t * (1 - t)])
    first = START_TOL_HALF_D * half_d if start_tol is None else start_tol
    for i in range(FIT_ITER + 2):
        lim = first + (tol - first) * min(i / (FIT_ITER - 1), 1.0)
        keep = np.abs(off - _curve(t, coef)) < lim
        if keep.sum() < 6:
            break
        if i < FIT_ITER:
            coef = np.array([np.linalg.lstsq(a[keep, :1], off[keep], rcond=None)[0][0], 0.0])
        else:
            coef = np.linalg.lstsq(a[keep], off[keep], rcond=None)[0]
    return coef


@dataclass(frozen=True)
class _Edge:
    """One edge's sector of the boundary: its frame, the points' fraction along the chord and outward offset."""

    p0: np.ndarray
    e: np.ndarray
    nrm: np.ndarray
    ln: float
    sec: np.ndarray
    t: np.ndarray
    off: np.ndarray


def edges_past_chips(contour_um: np.ndarray, corners_um: np.ndarray, pixel_um: float, d_um: float,
                     heights_nm: np.ndarray, origin_rc, facet_slope_nm_px: float) -> EdgesPastChips:
    """The contact boundary drawn past chips beside the edges (see the module's text).

    An edge whose curve bows out beyond its neighbours' (the lower median of the four middles) by more than a
    chip's least width is fitted again from their bow: a chip along much of an edge draws the first curve out
    to it (and a small chip beside it may be all the first curve finds). The chips found beside the second
    curve replace the first's; a bow that pile-up made finds none there (the region between is the facet,
    sloping), and the edge keeps its first curve and chips.

    Parameters
    ----------
    contour_um : ndarray (n, 2)
        Closed contact boundary, (x, y) µm.
    corners_um : ndarray (k, 2)
        The imprint's corners in order around it.
    pixel_um, d_um : float
        Pixel size and mean diagonal (µm).
    heights_nm : ndarray
        Smoothed levelled heights of the window around the imprint (nm).
    origin_rc : (int, int)
        The window's first row and column in the map.
    facet_slope_nm_px : float
        The facets' typical slope (nm per pixel).

    Returns
    -------
    EdgesPastChips
    """
    c = np.asarray(contour_um, float)
    k = len(corners_um)
    centre = np.mean(corners_um, axis=0)
    half_d = d_um / 2
    tol = max(TOL_PX * pixel_um, TOL_HALF_D * half_d)
    chip_min = max(CHIP_MIN_PX * pixel_um, CHIP_MIN_HALF_D * half_d)
    ang = np.arctan2(*(c - centre).T[::-1])
    cang = np.arctan2(*(np.asarray(corners_um) - centre).T[::-1])
    edges, coefs = [], []
    for j in range(k):
        p0, p1 = np.asarray(corners_um[j], float), np.asarray(corners_um[(j + 1) % k], float)
        e, nrm, ln = edge_frame(p0, p1, centre)
        # the boundary's points between the two corners' directions (the sector of this edge)
        span = (cang[(j + 1) % k] - cang[j]) % (2 * np.pi)
        rel_ang = (ang - cang[j]) % (2 * np.pi)
        sec = (rel_ang < span) if span < np.pi else (rel_ang > span)
        t = (c - p0) @ e / ln
        off = (c - p0) @ nrm
        sec &= (t > CORNER_KEEP_T) & (t < 1 - CORNER_KEEP_T)
        edges.append(_Edge(p0, e, nrm, ln, sec, t, off) if sec.sum() >= 8 else None)
        coefs.append(_fit_edge(t[sec], off[sec], half_d, tol) if sec.sum() >= 8 else None)
    mids = [_curve(0.5, cf) for cf in coefs if cf is not None]
    ref_mid = float(np.sort(mids)[(len(mids) - 1) // 2]) if len(mids) >= 3 else None      # the lower median
    heights = (heights_nm, np.asarray(origin_rc), facet_slope_nm_px, pixel_um)
    out = c.copy()
    chipped, outlines = [], []
    for j, (edge, coef) in enumerate(zip(edges, coefs)):
        if edge is None:
            continue
        runs = _chips(c, edge, coef, tol, chip_min, heights)
        if ref_mid is not None and _curve(0.5, coef) > ref_mid + chip_min:
            coef2 = _fit_edge(edge.t[edge.sec], edge.off[edge.sec], half_d, tol, start_mid=ref_mid,
                              start_tol=max(tol, REFIT_TOL_CHIP * chip_min))
            if _curve(0.5, coef2) < _curve(0.5, coef) - tol and (runs2 := _chips(c, edge, coef2, tol, chip_min,
                                                                                  heights)):
                runs = runs2
        for run, onto, outline in runs:
            out[run] = onto
            outlines.append(outline)
        if runs:
            chipped.append(j)
    area = shoelace(c) - shoelace(out) if chipped else 0.0
    return EdgesPastChips(contour_um=out, chipped_area_um2=float(max(area, 0.0)), chipped_edges=tuple(chipped),
                          chips_um=tuple(outlines))


def _chips(c, edge: _Edge, coef, tol, chip_min, heights) -> list:
    """The chips beside one edge: runs of the boundary more than ``tol`` outside the edge curve ``coef``, standing
    out by ``chip_min`` somewhere, over a shelf. Each as (indices, the run put onto the curve, its outline)."""
    z, origin_rc, slope, pixel_um = heights
    resid = np.full(len(c), np.nan)
    resid[edge.sec] = edge.off[edge.sec] - _curve(edge.t[edge.sec], coef)
    found = []
    for run in _runs(np.where(edge.sec, resid > tol, False)):
        if np.nanmax(resid[run]) < chip_min:
            continue
        run = _grow(run, edge.sec, resid, tol)
        tt = np.clip(edge.t[run], 0.0, 1.0)
        onto = edge.p0 + np.outer(tt * edge.ln, edge.e) + np.outer(_curve(tt, coef), edge.nrm)
        outline = np.vstack([c[run], onto[::-1]])                       # the region between, µm
        between = outline / pixel_um - origin_rc[::-1]                  # (col, row) of the window
        if _is_shelf(between[:, 1], between[:, 0], z, slope):
            found.append((run, onto, outline))
    return found


def _is_shelf(rows, cols, z, slope):
    """True when SHELF_SHARE of the region inside the polygon (rows, cols) of ``z`` slopes under SHELF_SLOPES facets."""
    ny, nx = z.shape
    r0, c0 = max(int(np.floor(rows.min())) - 1, 0), max(int(np.floor(cols.min())) - 1, 0)
    r1, c1 = min(int(np.ceil(rows.max())) + 2, ny), min(int(np.ceil(cols.max())) + 2, nx)
    if r1 - r0 < 3 or c1 - c0 < 3:
        return False
    inside = inside_polygon(rows - r0, cols - c0, (r1 - r0, c1 - c0))
    if inside.sum() < 4:
        return False
    gr, gc = np.gradient(z[r0:r1, c0:c1])
    return bool(np.mean(np.hypot(gr, gc)[inside] < SHELF_SLOPES * slope) >= SHELF_SHARE)


def _runs(flag):
    """Index arrays of the runs of True in a closed sequence (a run across the end is one run)."""
    n = len(flag)
    if not flag.any():
        return []
    if flag.all():
        return [np.arange(n)]
    start = int(np.argmin(flag))                 # a False: no run crosses the start
    idx = (np.arange(n) + start) % n
    f = flag[idx]
    edges = np.flatnonzero(np.diff(np.concatenate([[0], f.astype(int), [0]])))
    return [idx[a:b] for a, b in zip(edges[::2], edges[1::2])]


def _grow(run, sec, resid, tol):
    """A chip's run widened over its neighbours off the curve (the chip's notch into the edge at its ends)."""
    n = len(resid)
    lo, hi = int(run[0]), int(run[-1])
    ext = list(run)
    for step, i0 in ((-1, lo), (1, hi)):
        i = (i0 + step) % n
        while sec[i] and abs(resid[i]) > tol and len(ext) < n:
            ext.insert(0, i) if step < 0 else ext.append(i)
            i = (i + step) % n
    return np.array(ext)


def shoelace(p):
    """Area enclosed by a closed polygon (n, 2)."""
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
