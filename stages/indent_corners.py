"""Corners of a single imprint on an AFM height map: where each valley between two facets meets the
original surface, and radial cracks that would carry a corner out along them.

- :func:`fill_cracks`: narrow grooves (cracks, scratches) lifted to their banks before the boundary is found;
- :func:`corner_on_ray`: a coarse corner (the contact boundary's extreme point along a diagonal) refined to
  where a V fitted to the valley's walls crosses the surface level (the surface just beyond the corner, or the
  bottom of a crease there between pile-up lobes: :func:`crease_beyond`);
- :func:`unless_crack`: the corner taken back to the valley's own end (the kink where its rise ends on the
  valley's bottom profile) when the boundary ran out along a crack wider than the fill, or past a chip;
- :func:`tongue_mask`: the pixels of those tongues, lifted out of the contact boundary.

Frame: (row, col) pixel coordinates of the map window; heights levelled (original surface at 0), nm.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .cv_filters import grey_close
from .indent_level import in_cracks

__all__ = ["VALLEY_END_SLOPES", "bilinear", "corner_on_ray", "crease_beyond", "fill_cracks", "level_beyond",
           "region_pts", "surface_beyond", "tongue_mask", "unless_crack"]

CRACK_LIFT_SLOPES = 2.5      # a groove lifted by more than this many facet slopes (nm per px) is a crack
CRACK_TONGUE_PX = 3.0        # a corner carried out by more than this (px) beyond the valley's end: a crack
VALLEY_END_SLOPES = 0.7      # a corner's V rising at this many facet slopes (nm per px) or more ends a valley
BEYOND_MAX_SLOPES = 2.0      # the surface beyond a corner lies within this many facet slopes (nm per px) under 0
BOTTOM_PX = 1.0              # the V refitted to its walls: pixels within this of its bottom weighted down
V_WIDE_PX = 5.0              # the valley V across this distance of the diagonal, 3 px where a crack runs down it


def bilinear(img, r, c, order=1, prefilter=True):
    return ndimage.map_coordinates(img, [np.atleast_1d(r), np.atleast_1d(c)], order=order, mode="nearest",
                                   prefilter=prefilter)


def _valley_crossing(zr, rc0, e, length, slope_floor, noise, level=0.0, reach=2.5, pixels_below_level=False):
    """Distance from ``rc0`` along ``e`` where the valley between two facets meets ``level`` (nm; the surface).

    The pixels of the last 9 px before the coarse corner (``length``), within ``V_WIDE_PX`` of the ray and
    below the surface, get a V across the valley on a line along it: z = a + b s + c |t - t0| + f t (s along,
    t across the ray, t0 the valley's offset, searched). The V's bottom line a + b s crosses ``level`` at the
    corner. Fitted to the pixels themselves: an interpolated profile along the valley rounds its kink and
    reads it high, which put corners 0.2-0.5 px short on facets of 20-25 deg. Within 3 px only, the V of a
    corner whose edges sink in (a cusp) comes out too shallow (corners 0.3-1 px short at bows of -7 %); but
    where pixels lie deep under the V (a crack down the valley) it is fitted again within 3 px, which
    takes in less of the crack. The crossing is then taken from the V fitted again to its walls, with its offset
    held and the pixels near its bottom (which a z loop scanning across the valley and the tip round and lift)
    weighted down (``BOTTOM_PX``); ``reach`` is checked on the first fit.
    With ``pixels_below_level``, the V's pixels are those below ``level`` where it lies under 0 (the surface beyond
    the corner: its own pixels would bend the V), else below 0.
    Returns (crossing, the valley's slope in nm per px), or None when the pixels do not carry such a fit or
    the crossing lies more than ``reach`` px from ``length``.
    """
    ny, nx = zr.shape
    pad = np.ceil(V_WIDE_PX) + 1
    lo = np.floor(np.minimum(rc0 + (length - 10) * e, rc0 + (length + 1) * e) - pad).astype(int)
    hi = np.ceil(np.maximum(rc0 + (length - 10) * e, rc0 + (length + 1) * e) + pad + 1).astype(int)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, [ny, nx])
    if np.any(hi <= lo):
        return None                                        # the valley's end beyond the map
    rr, cc = np.mgrid[lo[0]:hi[0], lo[1]:hi[1]]
    rel = np.column_stack([rr.ravel() - rc0[0], cc.ravel() - rc0[1]])
    s_all = rel @ e
    t_all = rel @ np.array([-e[1], e[0]])
    z_all = zr[rr, cc].ravel()
    below = (s_all > length - 9) & (s_all < length + 0.5) & np.isfinite(z_all) \
        & (z_all < (min(level, 0.0) if pixels_below_level else 0.0) - max(3 * noise, 1.5 * slope_floor))
    # the V over V_WIDE_PX across (a cusp's V, where the edges sink in, is too shallow within 3 px), or over
    # 3 px where a crack runs down the valley (the wider V takes in more of it)
    for half in (V_WIDE_PX, 3.0):
        use = below & (np.abs(t_all) < np.minimum(half, length - s_all + 0.5))
        if use.sum() < 15:
            return None
        s, t, z = s_all[use], t_all[use], z_all[use]
        k = _v_fit(s - length, t, z)
        if k is None:
            return None
        # a crack running down the valley: a narrow groove under the V; its pixels left out, refitted
        res = z - (k[0] + k[1] * (s - length) + k[2] * np.abs(t - k[4]) + k[3] * (t - k[4]))
        deep = res < -max(4.0 * noise, 3.0, 3.0 * 1.4826 * np.median(np.abs(res)))
        if not deep.any():
            break
    if deep.any() and (~deep).sum() >= 15:
        k = _v_fit(s[~deep] - length, t[~deep], z[~deep])
        if k is None:
            return None
    if not (k[1] > 0.2 * slope_floor and k[2] > 0):
        return None
    at = length + (level - k[0]) / k[1]
    if not abs(at - length) <= reach:
        return None
    # the walls without the V's bottom, which a z loop scanning across the valley (and the tip) rounds and lifts:
    # the N and S corners of feedback seeds 1-40 read 0.24 and 0.13 px short on average with it, -0.02 and +0.11 px
    # without (weighted from 0 within BOTTOM_PX / 2 of it to 1 beyond 3 BOTTOM_PX / 2: a pixel's weight does not
    # flip as a noise draw moves the bottom's offset)
    keep = ~deep if deep.any() and (~deep).sum() >= 15 else np.ones(len(s), bool)
    w = np.clip(np.abs(t[keep] - k[4]) / BOTTOM_PX - 0.5, 0.0, 1.0)
    k2 = _v_fit(s[keep] - length, t[keep], z[keep], t0=k[4], w=w) if w.sum() >= 15 else None
    if k2 is not None and k2[1] > 0.2 * slope_floor and k2[2] > 0:
        return length + (level - k2[0]) / k2[1], float(k2[1])
    return at, float(k[1])


def _v_fit(s, t, z, t0=None, w=None):
    """Least-squares V z = a + b s + c |t - t0| + f (t - t0), t0 searched on a 0.05 px grid (or given), each pixel
    weighted by ``w`` (default 1): (a, b, c, f, t0)."""
    # every offset t0 at once: normal equations (t0, 4, 4), the residual from z.z - k.(A'z)
    t0 = np.arange(-0.75, 0.76, 0.05)[:, None] if t0 is None else np.array([[float(t0)]])
    w = np.ones(len(s)) if w is None else w
    a = np.stack([np.broadcast_to(1.0, (len(t0), len(s))), np.broadcast_to(s, (len(t0), len(s))),
                  np.abs(t - t0), t - t0], axis=-1)
    ata = np.einsum("kni,knj,n->kij", a, a, w)
    atz = np.einsum("kni,n->ki", a, w * z)
    try:
        k_all = np.linalg.solve(ata, atz[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    j = int(np.argmin((w * z) @ z - np.einsum("ki,ki->k", k_all, atz)))
    return np.append(k_all[j], t0[j, 0])


def corner_on_ray(zc, rc0, rc1, slope_floor, noise, zr, local_level=True):
    """Refine a corner on the profile from the floor ``rc0`` through the coarse corner ``rc1``.

    ``zc``: cubic spline coefficients of the levelled heights (``ndimage.spline_filter``); ``zr``: the
    levelled heights themselves.

    The ray is aimed along the valley between the two facets; the corner (where the valley meets the
    original level) is where a V fitted to the valley's own pixels crosses the surface (:func:`_valley_crossing`):
    with ``local_level``, the surface just beyond the corner (:func:`level_beyond`; pile-up vanishes at a Vickers
    imprint's corners, and its tails, a bow or drifting lines left in put the map's zero above the surface there:
    d +0.6 to +1.5 % on feedback-renderer seeds, and between lobes on all four edges, +0.9 to +2.6 % on the scanner
    renderer's), else 0. Where that fit fails, a straight line
    through the interpolated profile of the last few pixels before the coarse corner gives it. Returns the
    corner (row, col), the V's slope along the valley (nm per px; None without the V) and the surface's level the
    V was carried to (nm; 0 without the V).
    """
    v = np.asarray(rc1, float) - rc0
    length = float(np.hypot(*v))
    if length < 4:
        return np.asarray(rc1, float), None, 0.0
    e = _aim_at_valley(zc, rc0, v / length, length)
    level = level_beyond(zc, zr, rc0 + length * e, e, slope_floor, noise) if local_level else 0.0
    fit = _valley_crossing(zr, rc0, e, length, slope_floor, noise, level,
                           reach=2.5 + abs(level) / max(slope_floor, 1e-9), pixels_below_level=True)
    if fit is not None:
        return rc0 + fit[0] * e, fit[1], level
    s0 = _profile_crossing(zc, rc0, e, length, slope_floor, noise)
    corner = rc0 + s0 * e if s0 is not None else np.asarray(rc1, float)
    return corner, None, 0.0


def level_beyond(zc, zr, rc, e, slope_floor, noise):
    """The original surface's level (nm) just beyond a corner at ``rc`` on the diagonal ``e``, as
    :func:`corner_on_ray` takes it: the window's median (:func:`surface_beyond`) where it lies below 0, a crack's
    pixels left out; else 0 (a rim round the corners); the bottom of a crease between pile-up lobes
    (:func:`crease_beyond`) where it lies under that median, taken in part near each threshold so that a noise draw
    does not flip the corner; 0 where the level lies more than ``BEYOND_MAX_SLOPES`` facet slopes down (the window
    in a chip, a crack or the valley)."""
    beyond = surface_beyond(zr, rc, e)
    # only a surface below 0 is taken, then with a crack's pixels left out (which only raises it: the grey closing
    # is not needed where the plain median lies above 0)
    level = min(surface_beyond(zr, rc, e, sigma=noise), 0.0) if beyond < 0.0 else 0.0
    crease = crease_beyond(zc, rc, e, slope_floor, noise)
    if crease is not None:
        under = max(3.0 * noise, 0.5 * slope_floor)
        held = crease[1] * np.clip((beyond - crease[0]) / under - 0.5, 0.0, 1.0)
        level += held * (min(crease[0], 0.0) - level)
    return level if level >= -BEYOND_MAX_SLOPES * slope_floor else 0.0


def _valley_kink(zc, zr, rc0, e, start, stop, slope_floor, noise, step_px=0.5, window_px=12.0):
    """Corner on the valley from ``rc0`` along ``e``: the kink where its steep rise ends, found on the valley's
    bottom profile traced out from ``start`` to ``stop`` (px).

    The bottom is tracked outwards in ``step_px`` steps along ``e``, each the lowest point within 1 px across
    ``e`` of the last one, so the track follows the valley, and a crack on from it, where they run off the
    ray (a track free to turn ran off sideways down the facets). On the profile (height against distance
    along ``e``) a continuous pair of lines is fitted to the ``window_px`` either side of each candidate
    kink; the kink is the candidate with the smallest mean residual among those rising at least
    ``VALLEY_END_SLOPES`` facet slopes before it and under a third of that after it (without that
    condition a kink in the middle of the straight rise fits as well). A radial crack runs on from the
    corner at a nearly constant depth below the surface, pile-up rises slowly, the original surface is
    flat: each is the flatter line. A crack cuts the valley's last pixels down, so the kink lies short of
    the corner (0-3 px on the feedback renderer, 4-5 px where a crack 4-7 px wide runs down the valley): the
    corner is where the valley's V (:func:`_valley_crossing`, fitted to the 20 px before the kink) reaches
    the surface level around it, the median of the heights beyond the kink (``window_px`` on, either
    side; the levelled map's far field lies 10-60 nm off 0 at a corner where pile-up tails bend the far
    field's fit, and extrapolated to 0 the corners went 2 px too far). Without a V fit, the two lines'
    rise is carried on to that level. Returns (row, col) and whether a kink was found, or (the start,
    False).
    """
    rc0 = np.asarray(rc0, float)
    e = _aim_at_valley(zc, rc0, e, start)
    p = rc0 + start * e
    track = [p]
    for _ in range(int(max(stop - start, 0.0) / step_px)):
        p, _ = _lowest_across(zc, p + step_px * e, e, half_px=1.0)
        track.append(p)
    pts = np.array(track)
    s = (pts - rc0) @ e
    z = bilinear(zc, pts[:, 0], pts[:, 1], order=3, prefilter=False)
    if len(s) < 12:
        return rc0 + start * e, False
    fit = _kink_fits(s, z, window_px)
    if fit is None:
        return rc0 + start * e, False
    cand, ks, msr = fit
    steep_then_flat = (ks[:, 1] > VALLEY_END_SLOPES * slope_floor) & (ks[:, 2] < ks[:, 1] / 3.0)
    if not steep_then_flat.any():
        return rc0 + start * e, False
    b = int(np.flatnonzero(steep_then_flat)[np.argmin(msr[steep_then_flat])])
    j, k = int(cand[b]), ks[b]
    # the rise carried on to the surface around the corner
    level = surface_beyond(zr, pts[j], e, window_px)
    shift = max((level - k[0]) / k[1], 0.0)
    # where the valley's own V (fitted to its pixels, a crack down it left out) reaches that level
    fit = _valley_crossing(zr, pts[j] - 20.0 * e, e, 20.0, slope_floor, noise, level, reach=shift + 3.0)
    return pts[j] + ((fit[0] - 20.0) if fit is not None else shift) * e, True


def crease_beyond(zc, rc, e, slope_floor, noise, window_px=14.0, step_px=0.25, from_px=4.0):
    """The bottom (nm) of a crease running on beyond a corner at ``rc`` along ``e``, between pile-up lobes on both
    edges, and how far it holds as one (0-1).

    The bottom is the median of the lowest points across the ray (within 2 px of it), ``from_px`` to ``window_px`` px
    on, of those whose sides rise gradually (at 1 px under 0.45 of the rise at 4 px, a V: a crack's narrow groove
    rises most of the way to its banks within 1 px). It holds fully from 12 such points (none under 4), and where
    it lies no more than ``tol = max(3 noise, slope_floor / 4)`` under the highest point of the track before
    ``from_px`` (none from ``2 tol`` under): the valley's bottom rises into a crease and stays there, while where
    it rose to the surface and dropped again, the valley ended and a crack or a chip runs on. Linear in between,
    so that a noise draw does not flip the corner. None beyond the map."""
    ny, nx = zc.shape
    nrm = np.array([-e[1], e[0]])
    s_px = np.arange(int(window_px / step_px) + 1) * step_px
    on = np.asarray(rc, float) + s_px[:, None] * e
    inside = np.cumprod((on[:, 0] >= 4) & (on[:, 0] <= ny - 5) & (on[:, 1] >= 4) & (on[:, 1] <= nx - 5)) > 0
    s_px, on = s_px[inside], on[inside]
    # the lowest point across each step (0.25 px grid, a parabola through its neighbours), all steps at once
    tt = np.arange(-2.0, 2.01, 0.25)
    q = on[:, None, :] + tt[None, :, None] * nrm
    pv = bilinear(zc, q[..., 0].ravel(), q[..., 1].ravel(), order=3, prefilter=False).reshape(q.shape[:2])
    j_low = np.argmin(pv, axis=1)
    j = np.clip(j_low, 1, len(tt) - 2)
    rows = np.arange(len(j))
    z0, zm, zp = pv[rows, j], pv[rows, j - 1], pv[rows, j + 1]
    den = zm - 2 * z0 + zp
    refine = (j == j_low) & (den > 0)                    # an interior lowest point (as :func:`_lowest_across`)
    t_low = tt[j_low] + np.where(refine, 0.5 * 0.25 * (zm - zp) / np.where(refine, den, 1.0), 0.0)
    low = on + t_low[:, None] * nrm
    probe = low[:, None, :] + np.array([0.0, -1.0, 1.0, -4.0, 4.0])[None, :, None] * nrm
    z = bilinear(zc, probe[..., 0].ravel(), probe[..., 1].ravel(), order=3, prefilter=False).reshape(probe.shape[:2])
    before = s_px < from_px
    top = float(z[before, 0].max()) if before.any() else -np.inf
    gradual = 0.5 * (z[:, 1] + z[:, 2]) - z[:, 0] < 0.45 * (0.5 * (z[:, 3] + z[:, 4]) - z[:, 0])
    bottom = z[~before & gradual, 0]
    if bottom.size == 0 or (~before).sum() < 8:
        return None
    level = float(np.median(bottom))
    tol = max(3.0 * noise, 0.25 * slope_floor)
    held = np.clip((bottom.size - 4) / 8.0, 0.0, 1.0) * np.clip((level - top) / tol + 2.0, 0.0, 1.0)
    return level, float(held)


def surface_beyond(zr, rc, e, window_px=12.0, sigma=None):
    """The original surface's level (nm) just beyond a corner at ``rc`` (row, col) on the diagonal ``e``: the median
    of the heights from 2 to ``window_px`` px on along ``e``, ``window_px`` either side of it (a crack's few pixels
    and the imprint's corner left out by the median; with the noise ``sigma``, the pixels of a crack, which can fill
    a quarter of the window, left out first: :func:`.indent_level.in_cracks`); 0 with under 20 such pixels (the
    map's border)."""
    lo = np.maximum(np.floor(rc - 2 * window_px).astype(int), 0)
    hi = np.minimum(np.ceil(rc + 2 * window_px).astype(int) + 1, zr.shape)
    if not np.all(hi > lo):                              # beyond the map's border: no window
        return 0.0
    rr, cc = np.mgrid[lo[0]:hi[0], lo[1]:hi[1]]
    sa = (rr - rc[0]) * e[0] + (cc - rc[1]) * e[1]
    ta = (cc - rc[1]) * e[0] - (rr - rc[0]) * e[1]
    zw = zr[lo[0]:hi[0], lo[1]:hi[1]]
    use = (sa > 2.0) & (sa < window_px) & (np.abs(ta) < window_px) & np.isfinite(zw)
    if sigma is not None and use.sum() >= 20:
        use &= ~in_cracks(zw, sigma)
    return float(np.median(zw[use])) if use.sum() >= 20 else 0.0


def _kink_fits(s, z, window_px):
    """A continuous pair of lines, z = k0 + k1 min(d, 0) + k2 max(d, 0) with d = s - s_j, fitted by least
    squares to the profile within ``window_px`` of each candidate kink s_j (j from 4 to len - 3), all at once.

    Returns
    -------
    tuple or None
        Candidate indices (m,), coefficients (m, 3) and mean squared residuals (m,); None where a window's
        normal equations are singular.
    """
    cand = np.arange(4, len(s) - 2)
    d = s[None, :] - s[cand][:, None]                           # (m, n): every point against every kink
    w = (np.abs(d) <= window_px).astype(float)
    x = np.stack([w, w * np.minimum(d, 0.0), w * np.maximum(d, 0.0)], axis=-1)
    ata = np.einsum("mni,mnk->mik", x, x)
    atz = np.einsum("mni,n->mi", x, z)
    try:
        ks = np.linalg.solve(ata, atz[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    res = (np.einsum("mni,mi->mn", x, ks) - w * z[None, :]) ** 2
    return cand, ks, res.sum(axis=1) / w.sum(axis=1)


def _lowest_across(zc, p, u, half_px=3.0):
    """The lowest point (row, col) of the cubic surface ``zc`` on the segment across ``u`` through ``p``
    (refined by a parabola), and whether it lies inside the segment rather than at one of its ends."""
    nrm = np.array([-u[1], u[0]])
    tt = np.arange(-half_px, half_px + 0.01, 0.25)
    q = p + tt[:, None] * nrm
    pv = bilinear(zc, q[:, 0], q[:, 1], order=3, prefilter=False)
    j = int(np.argmin(pv))
    tj = tt[j]
    interior = 0 < j < len(tt) - 1
    if interior:
        den = pv[j - 1] - 2 * pv[j] + pv[j + 1]
        tj += 0.5 * 0.25 * (pv[j - 1] - pv[j + 1]) / den if den > 0 else 0.0
    return p + tj * nrm, interior


def _turn(rel, phi):
    """Angle (rad, 0-pi) between the directions of ``rel`` (rows of (row, col)) and the direction ``phi``."""
    return np.abs((np.arctan2(rel[:, 0], rel[:, 1]) - phi + np.pi) % (2 * np.pi) - np.pi)


def region_pts(zs, level, rc):
    """(row, col) of the pixels of the region below ``level`` that holds pixel ``rc``, or None."""
    lab, _ = ndimage.label(zs < level)
    k = lab[int(round(rc[0])), int(round(rc[1]))]
    return np.argwhere(lab == k).astype(float) if k else None


def unless_crack(zc, zr, half_pts, apex, phi, n_corners, corner, slope_floor, noise):
    """The corner ``corner`` (row, col), or the valley's own end when ``corner`` lies out along a crack or
    beside the valley's end; and the crack's tongue (apex, e, distance of the valley's end), or None.

    A crack wider than the fill (a scan's lag smears it) carries the boundary, and with it the corner, out
    along a narrow tongue. The valley's end is the kink where its rise ends (:func:`_valley_kink`), traced
    along the diagonal ``phi`` from ``apex`` (the centroid of the floor's pixels within noise of the lowest:
    the apex, also where the floor is a clipped plateau whose lowest pixel lies anywhere), starting where
    the region half as deep as the floor (``half_pts``; no crack goes that deep) ends, and going up to 10 %
    beyond ``corner``. When ``corner`` lies more than ``CRACK_TONGUE_PX`` from the valley's end, that end is
    the corner: beyond it, a crack (its tongue, the quadrant beyond the end, returned to be lifted out of the
    contact area), or beside it a chip spalled beside the corner that carried the boundary's far point
    sideways, or debris and pile-up that cut it short.
    """
    hc = np.asarray(apex, float)
    rel = half_pts - hc
    e = np.array([np.sin(phi), np.cos(phi)])
    sec = _turn(rel, phi) < np.pi / (3 * n_corners)
    if not sec.any():
        return corner, None
    s_out = float((corner - hc) @ e)
    kink, holds = _valley_kink(zc, zr, hc, e, float((rel[sec] @ e).max()), s_out + max(CRACK_TONGUE_PX, 0.1 * s_out),
                               slope_floor, noise)
    if not holds:
        return corner, None
    s_in = float((kink - hc) @ e)
    if s_out - s_in > CRACK_TONGUE_PX:
        return kink, (hc, e, s_in)
    if np.hypot(*(kink - corner)) > CRACK_TONGUE_PX:
        return kink, None
    return corner, None


def tongue_mask(shape, tongues, n_corners):
    """Pixels beyond each crack's valley end (tongues: apex, e, distance: :func:`unless_crack`), within
    the quadrant about ``e``."""
    pts = np.indices(shape).reshape(2, -1).T.astype(float)
    mask = np.zeros(len(pts), bool)
    for hc, e, s_in in tongues:
        rel = pts - hc
        mask |= (rel @ e > s_in + 0.5) & (_turn(rel, np.arctan2(e[0], e[1])) < np.pi / n_corners)
    return mask.reshape(shape)


def _aim_at_valley(zc, rc0, e, length):
    """Direction from ``rc0`` along the valley: aimed twice at the lowest point across the ray 5 px
    before ``length``."""
    for _ in range(2):
        low, interior = _lowest_across(zc, rc0 + (length - 5.0) * e, e)
        if interior:
            e = (low - rc0) / np.hypot(*(low - rc0))
    return e


def _profile_crossing(zc, rc0, e, length, slope_floor, noise):
    """Where a line through the interpolated profile of the last 9 px before ``length`` crosses 0, or None."""
    s = np.arange(length - 9.0, length + 3.0, 0.25)
    pts = rc0 + s[:, None] * e
    ny, nx = zc.shape
    inb = (pts[:, 0] >= 0) & (pts[:, 0] <= ny - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= nx - 1)
    p = bilinear(zc, pts[:, 0], pts[:, 1], order=3, prefilter=False)
    # the straight part of the profile: clear of the noise and of the kink at the surface level
    use = inb & (p < -max(3 * noise, 1.5 * slope_floor)) & (s < length + 0.5) & np.isfinite(p)
    if use.sum() < 6:
        return None
    k = np.polyfit(s[use], p[use], 1)
    if k[0] <= 0.2 * slope_floor:
        return None
    s0 = -k[1] / k[0]
    return s0 if abs(s0 - length) <= 2.5 else None


def fill_cracks(zr, noise, slope_px, depth_nm, radius_px=2.5):
    """Fill narrow grooves (radial cracks, scratches): heights, filled mask.

    A grey closing with a disc of ``radius_px`` lifts a groove to its banks. A groove is where it lifts
    the map by more than max(5 noise levels, 3 nm, a facet slope) with the banks at the original level
    (within max(5 noise levels, 3 nm) of 0; the valleys' last pixels at the corners are lifted by less
    than a slope), or, in the upper half of the imprint (the closed surface above half the depth ``depth_nm``), by
    more than 2.5 facet slopes (``slope_px``, nm per pixel): the closing lifts the valley between two facets
    by at most two of its slopes, so the imprint itself is left as it is (and its floor, which a closing
    rounds, is no crack).
    """
    r = int(np.ceil(radius_px))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = yy ** 2 + xx ** 2 <= radius_px ** 2 + 1e-9
    closed = grey_close(zr, disc, "nearest")
    tol = max(5.0 * noise, 3.0)
    lift = closed - zr
    groove = ((lift > max(tol, slope_px)) & (np.abs(closed) <= tol)) \
        | ((lift > max(tol, CRACK_LIFT_SLOPES * slope_px)) & (closed > -0.5 * depth_nm))
    if not groove.any():
        return zr, groove
    return np.where(groove, closed, zr), groove
