"""Square outlines in a micrograph whose imprints the outline detection misses (strong grain contrast).

In a backscattered-electron image of a polished metal every grain has its own grey level; the grain
boundaries cut an imprint's coarse outline into pieces, and no piece starts the fit near the imprint.
What grains do not make is four straight edges of equal length at right angles. :func:`square_candidates`
scores every square of a coarse grid of positions, sizes and turns by the weakest of its four edges
(the mean gradient across that edge, along its whole length) and returns the best few squares.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .threads import map_on_threads

__all__ = ["square_candidates"]

TURN_STEP_DEG = 5.0        # turns of the square searched, 0 .. 90 deg
SIZE_STEP = 1.05           # ratio of successive side lengths
COARSE_MAX_PX = 320        # longest side of the coarse image searched
MIN_SCORE_OF_BEST = 0.85   # squares whose weakest edge is weaker than this fraction of the best one's: not tried


def _turned(img, theta):
    """``img`` sampled on a grid turned by ``theta`` (rad) about its centre, large enough to hold it all.

    Returns the turned image, its validity mask, and the map from turned (x, y) to image (x, y).
    """
    ny, nx = img.shape
    c, s = np.cos(theta), np.sin(theta)
    w = int(np.ceil(abs(nx * c) + abs(ny * s)))
    h = int(np.ceil(abs(nx * s) + abs(ny * c)))
    ic = np.array([(nx - 1) / 2, (ny - 1) / 2])
    oc = np.array([(w - 1) / 2, (h - 1) / 2])
    rot = np.array([[c, -s], [s, c]])                       # turned frame -> image frame

    def to_image(xy):
        return (np.asarray(xy, float) - oc) @ rot.T + ic

    yy, xx = np.mgrid[0:h, 0:w]
    src = to_image(np.column_stack([xx.ravel(), yy.ravel()]))
    inside = ((src[:, 0] >= 0) & (src[:, 0] <= nx - 1) & (src[:, 1] >= 0) & (src[:, 1] <= ny - 1)).reshape(h, w)
    out = ndimage.map_coordinates(img, [src[:, 1], src[:, 0]], order=1, mode="nearest").reshape(h, w)
    return out, inside, to_image


def _best_squares(gy, gx, inside, sides):
    """The best (score, x1, y1, side) axis-aligned square of each side length on edge maps ``gy`` (across rows), ``gx`` (across columns)."""
    h, w = gy.shape
    cy = np.concatenate([np.zeros((h, 1)), np.cumsum(gy, axis=1)], axis=1).astype(np.float32)   # along rows
    cx = np.concatenate([np.zeros((1, w)), np.cumsum(gx, axis=0)], axis=0).astype(np.float32)   # along columns
    ok = ndimage.binary_erosion(inside, iterations=2)
    g = np.concatenate([gy[inside], gx[inside]])
    mu, sd = float(np.mean(g)), float(np.std(g)) + 1e-12
    found = []
    for L in sides:
        if L >= min(h, w) - 1:
            break
        n_r, n_c = h - L, w - L
        top = (cy[:n_r, L:L + n_c] - cy[:n_r, :n_c]) / L
        bottom = (cy[L:L + n_r, L:L + n_c] - cy[L:L + n_r, :n_c]) / L
        left = (cx[L:L + n_r, :n_c] - cx[:n_r, :n_c]) / L
        right = (cx[L:L + n_r, L:L + n_c] - cx[:n_r, L:L + n_c]) / L
        score = np.minimum(np.minimum(top, bottom), np.minimum(left, right))
        score[~(ok[:n_r, :n_c] & ok[L:L + n_r, L:L + n_c] & ok[:n_r, L:L + n_c] & ok[L:L + n_r, :n_c])] = 0.0
        r, c = np.unravel_index(int(np.argmax(score)), score.shape)
        # the weakest edge's excess over the typical gradient, in standard errors of a mean over L pixels:
        # a short edge on texture or dust reaches a high mean by chance (a 57 px square beat the real SEM
        # image's 290 px imprint by its plain mean)
        found.append(((float(score[r, c]) - mu) * np.sqrt(L) / sd, c, r, L))
    return found


def square_candidates(img: np.ndarray, min_d_px: float, n_best: int = 3) -> list:
    """The ``n_best`` squares with the strongest weakest edge, as fit starts.

    Parameters
    ----------
    img : ndarray (rows, cols)
        Grey values (information bar already cut off).
    min_d_px : float
        Smallest diagonal (px) searched.
    n_best : int
        Squares returned at most, best first; squares centred within half a better one's half-diagonal
        and squares under ``MIN_SCORE_OF_BEST`` of the best score are skipped.

    Returns
    -------
    list of (corners (4, 2) [x, y] px, apex (2,) px, corners (4, 2) px)
        In the form of the outline detection's candidates (the square twice).
    """
    f = max(1, int(np.ceil(max(img.shape) / COARSE_MAX_PX)))
    ny, nx = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    small = img[:ny, :nx].reshape(ny // f, f, nx // f, f).mean(axis=(1, 3))
    small = ndimage.gaussian_filter(small, 1.0)
    side_min = max(4.0, min_d_px / np.sqrt(2) / f)
    sides = np.unique(np.ceil(side_min * SIZE_STEP ** np.arange(200)).astype(int))
    sides = sides[sides < 0.95 * min(small.shape)]
    thetas = np.radians(np.arange(0.0, 90.0, TURN_STEP_DEG))
    per_turn = [None] * len(thetas)

    def score_turn(i):
        turned, inside, to_image = _turned(small, thetas[i])
        gy = ndimage.maximum_filter1d(np.abs(ndimage.sobel(turned, axis=0)), 3, axis=0)
        gx = ndimage.maximum_filter1d(np.abs(ndimage.sobel(turned, axis=1)), 3, axis=1)
        gy[~inside], gx[~inside] = 0.0, 0.0
        per_turn[i] = [(score, to_image(np.array([[x1, y1], [x1 + L, y1], [x1 + L, y1 + L], [x1, y1 + L]], float)))
                       for score, x1, y1, L in _best_squares(gy, gx, inside, sides)]

    # the turns on the thread pool: numpy's and scipy's array loops release the GIL
    map_on_threads(score_turn, range(len(thetas)))
    scored = [s for turn in per_turn for s in turn]
    scored.sort(key=lambda t: -t[0])
    out = []
    for score, sq in scored:
        if score < MIN_SCORE_OF_BEST * scored[0][0]:
            break
        centre = sq.mean(axis=0)
        half = 0.5 * np.hypot(*(sq[0] - sq[2]))
        if any(np.hypot(*(centre - c.mean(axis=0) / f)) < 0.5 * max(half, 0.5 * np.hypot(*(c[0] - c[2])) / f)
               for c, _, _ in out):
            continue
        corners = sq * f + (f - 1) / 2
        out.append((corners, corners.mean(axis=0), corners))
        if len(out) == n_best:
            break
    return out
