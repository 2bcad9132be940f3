"""Single Vickers imprints in light (OM) and electron (SEM) micrographs: corners and diagonals.

A Vickers imprint in a micrograph is four facets meeting at the apex, each of its own
brightness (shading, detector side), inside a square-ish outline; the corners are where the
facet edges end. The measurement:

- :func:`info_bar_rows`: an instrument information bar along the bottom (rows whose most
  common value covers much of the row: the bar's flat background with text) is left out;
- coarse detection on a block-averaged copy: deviation from a robust quadratic background,
  closed, thin lines (scratches) opened away, filled, opened with a disk a fifth of the smallest
  imprint across, one component per imprint; orientation from the outline's four-fold
  moment, corners as the outline's extreme points along the diagonals;
- refinement, coarse to fine: a quadrilateral (four corners) with an apex, its four
  triangular facets and the surroundings each given a linear brightness (fitted in closed
  form for every trial geometry: variable projection), edges softened by about a pixel's blur
  (the inside is the product of the four soft half-planes, so a blurred corner keeps a quarter
  of the contrast at its tip); the coordinates by robust (soft-L1) least squares with analytic
  derivatives and the exact gradient of the reweighted cost (:mod:`.indent_micrograph_model`). On the
  finer levels only a band around the edges and ridges is used. Below the coarsest level each edge may
  bow (a parabola through its corners, outward positive), so the corners are the tips of bowed edges;
- a fit whose diagonals differ by more than 5 % tried again from the square on its longer diagonal, and an
  apex adrift from the corners' mean refitted from there (both kept at a cost no higher);
- each corner refitted on the pixels near it (:func:`_corner_tips`).

Frame: x = column x pixel size, y = row x pixel size (pixel centres, µm, y down).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .errors import MarkcalError
from .indent_geometry import Imprint, circle_fit, diagonals
from .indent_micrograph_model import QuadModel, block_mean, lm, noise_level, soft_cost
from .indent_select import dedupe
from .indent_square_search import square_candidates
from .threads import map_on_threads

__all__ = ["info_bar_rows", "find_imprints", "measure_micrograph", "MIN_DIAGONAL_PX"]

#: smallest imprint (mean diagonal, px) measured as a single imprint in a micrograph; smaller dots are
#: arrays (the dot model of :mod:`.indent_om`)
#: a four-facet fit leaving more than this many noise levels (RMS) and more than MAX_FIT_RMS_REL of its
#: contrast is not an imprint (on low-noise images what the model leaves, a few percent of a high
#: contrast, is several noise levels: 4-5 at contrasts of 60-75 on independent OM renders of bowed edges)
MAX_FIT_RMS = 3.0
MAX_FIT_RMS_REL = 0.1
MIN_DIAGONAL_PX = 60.0
#: a corner on a faint edge moves to the end of its ridge when they are farther apart than this (px), and
#: not farther than RIDGE_OVERRIDE_MAX of the mean diagonal (the real SEM image: 6 px, 2 %)
RIDGE_OVERRIDE_PX = 3.0
RIDGE_OVERRIDE_MAX = 0.04
#: farthest the apex lies from the corners' mean (fraction of d): 0.012 for a depth of d/7 seen 5 degrees
#: off normal; on imprints outlined partly by grain boundaries (BSE, strong grain) the fits that went
#: wrong had 0.09 and 0.27, those that went right 0.014 at most
MAX_APEX_OFF_CENTRE = 0.06
#: an apex refitted from the corners' mean is kept when the cost rises by less than this fraction (a flat valley)
APEX_COST_TOL = 1e-4
#: diagonals differing by more than this fraction of their mean: the fit tried again from the square on the longer
#: diagonal (a corner on a faint edge stops short; ISO 6507-1 notes Vickers diagonals differing by more than 5 %)
UNEQUAL_DIAGONALS = 0.05
COARSE_MAX_ANGLE_DEG = 35.0     # a coarsest-level fit further from square than this is not refined
COARSE_MAX_APEX_OFF = 0.2
#: the finest level of the whole-imprint fit has at most this many blocks across the imprint (mean diagonal);
#: the corner refit at most twice as many
FINEST_PX = 160
#: largest edge bow fitted (fraction of d/2 at mid-edge; real imprints bow up to about 8 %): a bow free
#: without bound took in a scratch beside an edge (32 px on a 240 px imprint)
MAX_BOW = 0.12


def info_bar_rows(img: np.ndarray, min_rows: int = 8) -> int:
    """Rows of an instrument information bar along the bottom of a micrograph (0: none).

    A bar row's most common grey value covers at least 40 % of the row (the bar's flat
    background between text) or the row is constant; the bar is the run of such rows from
    the bottom, at least ``min_rows`` long and at most a third of the image. Two rows of
    margin are added (the bar's edge).
    """
    ny, nx = img.shape
    n = 0
    for r in range(ny - 1, ny - ny // 3, -1):
        row = img[r]
        _v, cnt = np.unique(row, return_counts=True)
        if cnt.max() >= 0.4 * nx or np.ptp(row) == 0:
            n += 1
        else:
            break
    return n + 2 if n >= min_rows else 0


def _robust_quadratic(z, step=2, n_iter=4):
    ny, nx = z.shape
    rr, cc = np.mgrid[0:ny:step, 0:nx:step]
    x, y = cc.ravel() / nx - 0.5, rr.ravel() / ny - 0.5
    v = z[::step, ::step].ravel()
    a = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    keep = np.ones(len(v), bool)
    coef = np.zeros(6)
    for _ in range(n_iter):
        coef = np.linalg.lstsq(a[keep], v[keep], rcond=None)[0]
        r = v - a @ coef
        s = 1.4826 * np.median(np.abs(r[keep])) + 1e-12
        keep = np.abs(r) < 2.5 * s
    R, C = np.mgrid[0:ny, 0:nx]
    X, Y = C / nx - 0.5, R / ny - 0.5
    return coef[0] + coef[1] * X + coef[2] * Y + coef[3] * X * X + coef[4] * X * Y + coef[5] * Y * Y


def _coarse(img, min_d_px):
    """Candidate imprints: list of (corners (4, 2) [x, y] px, apex (2,) px, corners of the largest
    square inside the outline (4, 2) px) on the full-res grid."""
    f = max(1, int(np.ceil(max(img.shape) / 320)))
    small = block_mean(img, f)
    s = ndimage.gaussian_filter(small, 1.0)
    dev = s - _robust_quadratic(s)
    sd = 1.4826 * np.median(np.abs(dev - np.median(dev))) + 1e-12
    noise_s = noise_level(small) / 2.0
    thr = max(3.0 * sd, 5 * noise_s)
    grad = ndimage.gaussian_gradient_magnitude(small, 1.0)
    gthr = np.median(grad) + 6 * 1.4826 * np.median(np.abs(grad - np.median(grad)))
    mask = (np.abs(dev) > thr) | (grad > gthr)
    rad = max(1, int(round(0.04 * min_d_px / f)) + 1)
    st = ndimage.generate_binary_structure(2, 1)
    mask = ndimage.binary_closing(mask, st, iterations=rad + 1)
    # thin lines go before the holes are filled: crossing scratches had closed a loop with an imprint
    mask = ndimage.binary_opening(mask, st, iterations=rad)
    mask = ndimage.binary_fill_holes(mask)
    # scratches and grain boundaries narrower than the smallest imprint's inner square are cut off (a
    # scratch joined to an imprint had made one component of both: missed), then the corners' tips
    # are grown back within the mask
    r_cut = max(rad, int(0.2 * min_d_px / f))
    disk = np.hypot(*np.mgrid[-r_cut:r_cut + 1, -r_cut:r_cut + 1]) <= r_cut
    core = ndimage.binary_opening(mask, disk)
    mask = ndimage.binary_dilation(core, st, iterations=2, mask=mask)
    lab, n = ndimage.label(mask)
    out = []
    if n == 0:
        return out
    areas = ndimage.sum(mask, lab, np.arange(1, n + 1))
    min_area = 0.5 * (min_d_px / f) ** 2 * 0.5
    for k in np.flatnonzero(areas >= min_area) + 1:
        comp = lab == k
        edge = comp & ~ndimage.binary_erosion(comp, st)
        er, ec = np.nonzero(edge)
        cr, cc_ = ndimage.center_of_mass(comp)
        rel = np.column_stack([ec - cc_, er - cr])
        ang = np.arctan2(rel[:, 1], rel[:, 0])
        rad_ = np.hypot(rel[:, 0], rel[:, 1])
        theta = np.angle(np.sum(rad_ ** 8 * np.exp(4j * ang))) / 4
        corners = []
        for j in range(4):
            phi = theta + j * np.pi / 2
            e = np.array([np.cos(phi), np.sin(phi)])
            sec = np.abs((ang - phi + np.pi) % (2 * np.pi) - np.pi) < np.pi / 4
            if sec.sum() < 2:
                break
            corners.append(rel[sec][int(np.argmax(rel[sec] @ e))])
        if len(corners) < 4:
            continue
        c = (np.array(corners) + [cc_, cr]) * f + (f - 1) / 2
        # the largest square inside the component: a start that a filled loop of scratches beside the
        # imprint, which moves the extreme points, leaves in place
        sl = ndimage.find_objects(comp.astype(np.int8))[0]
        dist = ndimage.distance_transform_edt(np.pad(comp[sl], 1))
        r0, c0_ = np.unravel_index(int(np.argmax(dist)), dist.shape)
        centre = np.array([c0_ - 1 + sl[1].start, r0 - 1 + sl[0].start], float)
        phi = theta + np.arange(4) * np.pi / 2
        sq = centre + np.sqrt(2.0) * dist.max() * np.column_stack([np.cos(phi), np.sin(phi)])
        out.append((c, c.mean(axis=0), sq * f + (f - 1) / 2))
    return out


def _mean_diagonal(c):
    """Mean of the two diagonals (corner 0-2, 1-3) of a quadrilateral (same units as ``c``)."""
    return 0.5 * (np.hypot(*(c[0] - c[2])) + np.hypot(*(c[1] - c[3])))


def _refine(img, corners, apex, d_px, square=None):
    """Coarse-to-fine quadrilateral fit.

    Returns corners (4, 2), apex (2,), edge bows (4,: px at mid-edge, outward positive, edge k from
    corner k to k + 1) and the model of the last level. The coarsest level fits straight edges; the
    finer ones let each edge bow (a parabola through its corners), so that the corners of bowed edges
    are their tips, where the edges meet, and not where the edges' average lines cross.
    """
    p = np.concatenate([apex, corners.ravel()])
    if not 0 < d_px < 1e6:                     # the pyramid loops below need a finite size
        raise MarkcalError(f"imprint size {d_px:g} px is out of range")
    f = 1
    while d_px / f > 48:
        f *= 2
    levels = []
    while f >= 1:
        levels.append(f)
        f //= 2
    model = None
    bow_max = MAX_BOW * d_px / 2
    for i, f in enumerate(levels):
        if i > 0 and _mean_diagonal(p[2:10].reshape(4, 2)) / f > FINEST_PX:
            # blocks of a few pixels of a large imprint place its corners well within 1 % (the SEM goal is
            # 2 %); the finer levels would cost seconds (a 628 px imprint: 5 s). Judged on the fitted size,
            # not the coarse outline's (a wide halo inflates that: the full-resolution level was skipped on
            # a 119 px OM imprint, +3 px)
            break
        band = None if i == 0 else max(6.0 * f, 0.06 * d_px)
        model = QuadModel(img, f, p[2:10].reshape(4, 2), p[:2], band)
        if len(model.z) < 60:
            continue
        if i == 0:
            # the coarse outline may hold a halo or pile-up: start from it and from shrunk copies, and
            # from the largest square inside it (``square``), that grown by 15 % and turned
            starts = [np.concatenate([p[:2], (p[:2] + shrink * (p[2:].reshape(4, 2) - p[:2])).ravel()])
                      for shrink in (1.0, 0.85, 0.7, 0.55)]
            if square is not None:
                # turned too: what is stuck to an imprint turns the outline's four-fold moment as well
                mid = square.mean(axis=0)
                for grow, turn_deg in ((1.0, 0), (1.15, 0), (1.0, -30), (1.0, -15), (1.0, 15), (1.0, 30)):
                    cs, sn = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
                    v = grow * (square - mid) @ np.array([[cs, sn], [-sn, cs]])
                    starts.append(np.concatenate([mid, (mid + v).ravel()]))
            # every start two steps, the six best four more (the winner after six steps was among the six
            # best after two in 63 of 64 fits of the micrograph tests and BSE renders)
            early = [lm(model, q, 0.05 * f, 2) for q in starts]
            cost = [soft_cost(model.residual(q)) for q in early]
            best = None
            for k in np.argsort(cost)[:6]:
                q = lm(model, early[k], 0.05 * f, 4)
                c = soft_cost(model.residual(q))
                if best is None or c < best[0]:
                    best = (c, q)
            p = np.concatenate([lm(model, best[1], 0.05 * f, 20), np.zeros(4)])
            if not _plausible(p[2:10].reshape(4, 2), p[:2]) and _plausible(p[2:10].reshape(4, 2), None):
                # a square whose facets barely differ (light from above): their ridges, and with them the
                # apex, are lost in the coarse blocks; the finer levels find them from its centre
                p[:2] = p[2:10].reshape(4, 2).mean(axis=0)
            if not _plausible(p[2:10].reshape(4, 2), p[:2]):
                # far from a square with its apex inside: the finer levels (most of the time) would not
                # make it one (grain pieces of a BSE image: 1.2 s each)
                return p[2:10].reshape(4, 2), p[:2], p[10:14], None
        elif i < len(levels) - 1:
            # to convergence (stops early): 8 iterations had left a bowed 220 px imprint at 202 px
            p = lm(model, p, 0.05 * f, 20, bow_max=bow_max)
        else:
            # last level: also from the corners pulled 2 px towards the apex (the outer flank of a dark
            # edge line is a local minimum a few pixels outside the edge)
            best = None
            for pull_px in (0.0, 2.0):
                c = p[2:10].reshape(4, 2)
                v = c - p[:2]
                q = np.concatenate([p[:2], (c - pull_px * v / np.hypot(*v.T)[:, None]).ravel(), p[10:]])
                q = lm(model, q, 0.05 * f, 8, bow_max=bow_max)
                cost = soft_cost(model.residual(q))
                if best is None or cost < best[0]:
                    best = (cost, q)
            p = best[1]
    if len(p) == 10:                           # no level had pixels enough to fit
        p = np.concatenate([p, np.zeros(4)])
    return p[2:10].reshape(4, 2), p[:2], p[10:14], model


def _unless_short_corner(work, corners, apex, bows, model):
    """The fit again from the square on its longer diagonal, kept when its soft-L1 cost is lower in both fits'
    windows.

    A corner on a faint edge (two facets as bright as the surroundings) sits on a cost that is flat over 15-40 px,
    and a start that is short there stays short: the diagonals then differ by 10-30 %, where a Vickers imprint's
    differ by a few percent (ISO 6507-1 asks for a note past 5 %). Returns corners, apex, bows and model.
    """
    k = 0 if np.hypot(*(corners[0] - corners[2])) >= np.hypot(*(corners[1] - corners[3])) else 1
    mid, half = 0.5 * (corners[k] + corners[k + 2]), 0.5 * (corners[k] - corners[k + 2])
    turned = np.array([-half[1], half[0]])
    if turned @ (corners[(k + 1) % 4] - mid) < 0:                    # the same order around the imprint
        turned = -turned
    square = np.empty((4, 2))
    square[k], square[k + 2] = mid + half, mid - half
    square[(k + 1) % 4], square[(k + 3) % 4] = mid + turned, mid - turned
    c2, a2, b2, m2 = _refine(work, square, mid, 2.0 * np.hypot(*half))
    if m2 is None:
        return corners, apex, bows, model
    p1, p2 = np.concatenate([apex, corners.ravel(), bows]), np.concatenate([a2, c2.ravel(), b2])
    if all(soft_cost(m.residual(p2)) < soft_cost(m.residual(p1)) for m in (model, m2)):
        return c2, a2, b2, m2
    return corners, apex, bows, model


def _unless_apex_adrift(model, corners, apex, bows, d_px):
    """The fit again from the apex at the corners' mean, kept when its soft-L1 cost is no higher (to
    ``APEX_COST_TOL`` of itself).

    Where the ridges do not show (back-scattered electrons with the facets paired in brightness), the cost is
    flat along the apex: on BSE seed 7 at +3 % the fit left it 0.070 d off the corners' mean, past
    ``MAX_APEX_OFF_CENTRE``, at a cost 0.04 below the true centre's of 13061, and the imprint was refused. A
    fit that went wrong on grain boundaries keeps its apex off centre, because centring it costs more.
    """
    p = np.concatenate([apex, corners.ravel(), bows])
    q = p.copy()
    q[:2] = corners.mean(axis=0)
    q = lm(model, q, 0.05 * model.f, 20, bow_max=MAX_BOW * d_px / 2)
    if soft_cost(model.residual(q)) <= (1.0 + APEX_COST_TOL) * soft_cost(model.residual(p)):
        return q[2:10].reshape(4, 2), q[:2], q[10:14]
    return corners, apex, bows


def _plausible(corners, apex) -> bool:
    """A coarse fit the finer levels can make an imprint: corner angles within ``COARSE_MAX_ANGLE_DEG``
    of 90, diagonals within a factor of 2, the apex (None: not judged) within ``COARSE_MAX_APEX_OFF`` of d
    from the centre (the final checks are 20 deg, 1.67 and ``MAX_APEX_OFF_CENTRE``)."""
    d1, d2 = np.hypot(*(corners[0] - corners[2])), np.hypot(*(corners[1] - corners[3]))
    if not (d1 > 0 and d2 > 0 and 0.5 < d1 / d2 < 2.0):
        return False
    off = 0.0 if apex is None else np.hypot(*(apex - corners.mean(axis=0))) / (0.5 * (d1 + d2))
    return bool(np.all(np.abs(_angles_deg(corners) - 90.0) < COARSE_MAX_ANGLE_DEG) and off < COARSE_MAX_APEX_OFF)


def _ridge_corners(img, corners, apex, noise, delta_px=2.5):
    """Move each corner to where the ridge between its two facets ends.

    Along the line from the apex through the fitted corner, the brightness difference
    across the ridge (samples ``delta_px`` either side, image smoothed by 1 px) is constant
    on the ridge and falls to zero beyond the corner; samples at lateral offset delta lie
    inside the facets only farther than delta / tan(alpha / 2) from the corner (alpha the
    corner's angle), so the corner is that far beyond the half-contrast point. A ridge whose
    contrast is under 4 noise levels leaves its corner as fitted.
    """
    out = corners.copy()
    ny, nx = img.shape
    lo = np.maximum(np.floor(np.min(np.vstack([corners, apex]), axis=0)).astype(int) - 40, 0)
    hi = np.minimum(np.ceil(np.max(np.vstack([corners, apex]), axis=0)).astype(int) + 41, [nx, ny])
    sm = ndimage.gaussian_filter(img[lo[1]:hi[1], lo[0]:hi[0]], 1.0)
    for k in range(4):
        v = corners[k] - apex
        length = float(np.hypot(*v))
        e = v / length
        nrm = np.array([-e[1], e[0]])
        a, b = corners[k - 1] - corners[k], corners[(k + 1) % 4] - corners[k]
        alpha = np.arccos(np.clip(a @ b / (np.hypot(*a) * np.hypot(*b)), -1, 1))
        t = np.arange(0.3 * length, 1.25 * length, 0.5)
        pts = apex + t[:, None] * e
        pl, pr = pts + delta_px * nrm, pts - delta_px * nrm
        il = ndimage.map_coordinates(sm, [pl[:, 1] - lo[1], pl[:, 0] - lo[0]], order=1, mode="nearest")
        ir = ndimage.map_coordinates(sm, [pr[:, 1] - lo[1], pr[:, 0] - lo[0]], order=1, mode="nearest")
        con = il - ir
        ridge = (t > 0.35 * length) & (t < 0.8 * length)
        if ridge.sum() < 4:                    # a corner on the apex (a failed candidate)
            continue
        c0 = float(np.median(con[ridge]))
        dn = np.diff(con[ridge][::2])
        sd = 1.4826 * np.median(np.abs(dn - np.median(dn))) / np.sqrt(2) + 1e-12
        if abs(c0) < 4 * max(sd, noise / 2):
            continue
        cn = ndimage.gaussian_filter1d(con / c0, 2.0)
        above = np.flatnonzero(cn >= 0.5)
        if not len(above) or above[-1] + 1 >= len(t):
            continue
        j = above[-1]
        t_half = t[j] + (cn[j] - 0.5) / max(cn[j] - cn[j + 1], 1e-9) * (t[j + 1] - t[j])
        t_c = t_half + delta_px / np.tan(alpha / 2)
        if abs(t_c - length) < 0.15 * length:
            out[k] = apex + t_c * e
    return out


#: the part of each edge, from its corner, that the corner's own fit sees (:func:`_corner_tips`)
CORNER_REACH = 0.3


def _corner_tips(img, corners, apex, d_px, bows=None):
    """Each corner refitted on the pixels near it only: where its two edges meet as they leave it.

    The whole-imprint fit gives each edge one parabolic bow; real edges bow otherwise (flatter in the
    middle, or one-sided). Near its corner an edge is straight to first order, so the same model (facets,
    surroundings, lines, halo, the fitted ``bows`` (4,) px, held) is fitted again on the pixels within
    :data:`CORNER_REACH` of an edge's length from each corner, with that corner and its two neighbours
    (which set the directions of its edges) free. A corner that would move by more than 5 % of the mean
    diagonal stays. On an independent render with bows of 3 % of d/2 the straight-edged fit alone read
    diagonals +3 and -1.2 to -3 %; see docs/indents.md for the bowed fit with and without this step.
    """
    out = corners.copy()
    f = 1
    while d_px / f > 2 * FINEST_PX:
        f *= 2
    band = max(6.0 * f, 0.06 * d_px)
    model = QuadModel(img, f, corners, apex, band)
    X, Y = model.X, model.Y
    for k in range(4):
        reach = CORNER_REACH * min(np.hypot(*(corners[k - 1] - corners[k])), np.hypot(*(corners[(k + 1) % 4] - corners[k])))
        near = np.hypot(X - corners[k, 0], Y - corners[k, 1]) < reach
        if near.sum() < 60:
            continue
        free = [2 + 2 * (j % 4) + c for j in (k - 1, k, k + 1) for c in (0, 1)]
        p0 = np.concatenate([apex, corners.ravel()] + ([] if bows is None else [bows]))
        tip = lm(model.restricted(near), p0, 0.05 * f, 8, free=free)[2 + 2 * k:4 + 2 * k]
        if np.hypot(*(tip - corners[k])) <= 0.05 * _mean_diagonal(corners):
            out[k] = tip
    return out


def _bowed_outline(corners, bows, n_per_edge=16):
    """Closed outline (px) of a quadrilateral whose edge k (corner k to k + 1) bows outwards by bows[k] at
    mid-edge along a parabola."""
    mid = corners.mean(axis=0)
    t = np.arange(n_per_edge) / n_per_edge
    pts = []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        v = b - a
        nrm = np.array([v[1], -v[0]]) / max(np.hypot(*v), 1e-12)
        if nrm @ (0.5 * (a + b) - mid) < 0:
            nrm = -nrm
        pts.append(a + t[:, None] * v + (bows[k] * 4.0 * t * (1.0 - t))[:, None] * nrm)
    pts = np.vstack(pts)
    return np.vstack([pts, pts[:1]])


def _angles_deg(c):
    out = []
    for k in range(4):
        a, b = c[k - 1] - c[k], c[(k + 1) % 4] - c[k]
        out.append(np.degrees(np.arccos(np.clip(a @ b / (np.hypot(*a) * np.hypot(*b)), -1, 1))))
    return np.array(out)


def find_imprints(img: np.ndarray, min_diagonal_px: float = MIN_DIAGONAL_PX) -> list:
    """Coarse candidates of single imprints: list of (corners (4, 2) [x, y] px, apex (2,) px, corners of
    the largest square inside the outline (4, 2) px)."""
    return _coarse(np.asarray(img, np.float64), min_diagonal_px)


def measure_micrograph(img: np.ndarray, pixel_um: float, min_diagonal_px: float = MIN_DIAGONAL_PX,
                       squares: bool = False) -> tuple:
    """Find and measure every single Vickers imprint in a light or electron micrograph.

    Parameters
    ----------
    img : ndarray (rows, cols)
        Grey values (any scale).
    pixel_um : float
        Pixel size (µm).
    min_diagonal_px : float
        Smallest mean diagonal (px) taken as an imprint.
    squares : bool
        Start the fits from squares with four clear edges (``indent_square_search``) instead of the
        outline detection's candidates: for grainy (BSE) images where the outline finds nothing.

    Returns
    -------
    imprints : list of Imprint
        Corners (µm, in order around the imprint), diagonals corner to corner, centre (the
        corners' mean), diameter of the circle through the corners, projected area inside the
        bowed edges, ``edge_bow`` (mean mid-edge bow / (d/2), outward positive); depth fields NaN.
        ``cut_by_border`` when a corner lies within a pixel of the border or beyond.
    bar_rows : int
        Rows of the information bar left out at the bottom (0: none).
    """
    img = np.asarray(img, np.float64)
    bad = ~np.isfinite(img)
    if bad.any():
        # missing pixels (NaN in a float TIFF) read as the typical grey: no edge, no imprint there
        img = np.where(bad, np.median(img[~bad]) if (~bad).any() else 0.0, img)
    bar = info_bar_rows(img)
    work = img[:img.shape[0] - bar] if bar else img
    # strong grain contrast (BSE) cuts the outline into pieces that start no fit near the imprint: squares
    # with four clear edges start the same fit and face the same checks (the flow's last resort: on an OM
    # array of 1 µm dots a square through several dots passed them)
    starts = square_candidates(work, min_diagonal_px) if squares else _coarse(work, min_diagonal_px)
    return _measure_all(work, pixel_um, min_diagonal_px, starts), bar


def _measure_all(work, pixel_um, min_diagonal_px, candidates) -> list:
    """The imprints the fit confirms from ``candidates`` (corners, apex, square), one per place."""
    candidates = list(candidates)
    found = [None] * len(candidates)

    def measure(k):
        found[k] = _measure_one(work, pixel_um, min_diagonal_px, *candidates[k])

    # one candidate per thread: most of a fit is the model's compiled kernel, which releases the GIL
    map_on_threads(measure, range(len(candidates)))
    return dedupe([m for m in found if m is not None])


def _measure_one(work, pixel_um, min_diagonal_px, corners0, apex0, square0):
    """One imprint fitted from a candidate, or None when it is too small or fails a check."""
    ny, nx = work.shape
    d0 = 0.5 * (np.hypot(*(corners0[0] - corners0[2])) + np.hypot(*(corners0[1] - corners0[3])))
    if d0 < min_diagonal_px:
        return None
    corners, apex, bows, model = _refine(work, corners0, apex0, d0, square0)
    if model is None:
        return None
    d1, d2 = np.hypot(*(corners[0] - corners[2])), np.hypot(*(corners[1] - corners[3]))
    if abs(d1 - d2) > UNEQUAL_DIAGONALS * 0.5 * (d1 + d2):
        corners, apex, bows, model = _unless_short_corner(work, corners, apex, bows, model)
    if np.hypot(*(apex - corners.mean(axis=0))) > MAX_APEX_OFF_CENTRE * _mean_diagonal(corners):
        corners, apex, bows = _unless_apex_adrift(model, corners, apex, bows, d0)
    lv, rms, glow = model.region_levels(np.concatenate([apex, corners.ravel(), bows]))
    # a corner whose fainter edge has less than half the contrast of the ridge between its
    # two facets is placed better by the end of that ridge
    edge_con = np.abs(lv[:4] - lv[4])
    ridge_con = np.abs(lv[[3, 0, 1, 2]] - lv[:4])                   # corner k: facets k-1 and k
    weak = [k for k in range(4) if min(edge_con[k - 1], edge_con[k]) < 0.5 * ridge_con[k]]
    if weak:
        # the ridge end overrides the fit only where they disagree by more than its own
        # uncertainty (about 2 px on renders), and by less than RIDGE_OVERRIDE_MAX of d (a 628 px SEM
        # imprint whose ridges glow past its corners: two corners 45 px out)
        moved = _ridge_corners(work, corners, apex, noise_level(work))
        shift = np.hypot(*(moved - corners).T)
        far = [k for k in weak if RIDGE_OVERRIDE_PX < shift[k] <= RIDGE_OVERRIDE_MAX * _mean_diagonal(corners)]
        corners = corners.copy()
        corners[far] = moved[far]
    corners = _corner_tips(work, corners, apex, d0, bows)
    d1 = np.hypot(*(corners[0] - corners[2]))
    d2 = np.hypot(*(corners[1] - corners[3]))
    contrast = float(np.max(np.abs(lv[:4] - lv[4])))
    # an SEM imprint may show mostly by the glow along its edges (facets within 2-3 noise levels
    # of the surroundings, glow 23 on an independent render)
    signal = max(contrast, abs(glow))
    off_centre = np.hypot(*(apex - corners.mean(axis=0))) / (0.5 * (d1 + d2))
    if not (min_diagonal_px <= 0.5 * (d1 + d2) and 0.6 < d1 / d2 < 1.67 and signal > 2 * model.noise
            and rms < max(MAX_FIT_RMS * model.noise, MAX_FIT_RMS_REL * contrast)
            and np.all(np.abs(_angles_deg(corners) - 90.0) < 20.0) and off_centre < MAX_APEX_OFF_CENTRE):
        return None
    c_um = corners * pixel_um
    dd1, dd2, orient = diagonals(c_um)
    cx, cy, crad = circle_fit(c_um)
    cut = bool(np.any((corners < 1.0) | (corners > np.array([nx, ny]) - 2.0)))
    x, y = c_um[:, 0], c_um[:, 1]
    edges_um = np.hypot(*(np.roll(c_um, -1, axis=0) - c_um).T)
    # the quadrilateral and the parabolic segments of the bowed edges (2/3 base x height each)
    area = (0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
            + float(np.sum(2.0 / 3.0 * edges_um * bows * pixel_um)))
    bow = float(np.mean(bows) / (0.25 * (d1 + d2)))
    nan = float("nan")
    return Imprint(x_um=float(x.mean()), y_um=float(y.mean()), diameter_um=float(2 * crad),
                   diag1_um=float(dd1), diag2_um=float(dd2), depth_nm=nan, hd_ratio=nan,
                   orientation_deg=float(orient), pileup_nm=nan, corners_um=c_um, fit_rms=rms / model.noise,
                   n_pixels=int(len(model.z)), contrast=contrast / max(abs(lv[4]), 1e-12), area_um2=area,
                   edge_bow=bow,
                   cut_by_border=cut, contour_um=_bowed_outline(corners, bows) * pixel_um,
                   floor_um=(float(apex[0] * pixel_um), float(apex[1] * pixel_um)))
