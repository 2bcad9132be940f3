"""Compiled design matrix of the four-facet micrograph model (:class:`.indent_micrograph._QuadModel`).

One pass over the pixels fills the 20 columns for one trial geometry: the four facets' and the
surroundings' linear brightness (3 columns each), then the edge line outside and inside, the edge glow,
the ridge lines and the pile-up halo. The fit evaluates it some hundred times per imprint (a
forward-difference Jacobian per iteration); the fused loop replaces about sixty numpy passes.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

#: columns of the design matrix
N_COLUMNS = 20


@njit(cache=True, nogil=True)
def _expit(x):
    if x > 40.0:
        return 1.0
    if x < -40.0:
        return 0.0
    if x >= 0.0:
        return 1.0 / (1.0 + math.exp(-x))
    ex = math.exp(x)
    return ex / (1.0 + ex)


@njit(cache=True, nogil=True)
def quad_design(X, Y, p, soft, line_px, halo_px, xm, ym, xs):
    """Design matrix (n, 20) of the model at parameters ``p``.

    Parameters
    ----------
    X, Y : 1-D arrays
        Pixel centres (full-resolution px).
    p : 1-D array
        Apex (2), corners (8, in order around the imprint), optionally the four edges' bows (px at
        mid-edge, outward positive; edge k runs from corner k to k + 1).
    soft : float
        Logistic scale of the edges (px).
    line_px : float
        Width of the ridge and edge lines (Gaussian sigma, px); the glow decays over three of it.
    halo_px : float
        Distance of the halo's crest outside the edge (px).
    xm, ym, xs : float
        Centre and scale of the linear brightness terms' coordinates.
    """
    n = X.shape[0]
    a = np.empty((n, N_COLUMNS))
    ax, ay = p[0], p[1]
    cx = np.empty(4)
    cy = np.empty(4)
    bow = np.zeros(4)
    for k in range(4):
        cx[k] = p[2 + 2 * k]
        cy[k] = p[3 + 2 * k]
        if p.shape[0] > 10:
            bow[k] = p[10 + k]
    area = 0.0
    for k in range(4):
        j = (k + 1) % 4
        area += 0.5 * (cx[k] * cy[j] - cx[j] * cy[k])
    sgn = 1.0 if area > 0 else -1.0
    # edges: unit direction, length; apex-corner rays: unit direction
    ex = np.empty(4)
    ey = np.empty(4)
    el = np.empty(4)
    rx = np.empty(4)
    ry = np.empty(4)
    for k in range(4):
        j = (k + 1) % 4
        dx, dy = cx[j] - cx[k], cy[j] - cy[k]
        el[k] = math.hypot(dx, dy) + 1e-12
        ex[k], ey[k] = dx / el[k], dy / el[k]
        dx, dy = cx[k] - ax, cy[k] - ay
        ln = math.hypot(dx, dy) + 1e-12
        rx[k], ry[k] = dx / ln, dy / ln
    e = np.empty(4)
    r = np.empty(4)
    w = np.empty(4)
    sr = np.empty(4)
    for i in range(n):
        x, y = X[i], Y[i]
        for k in range(4):
            px, py = x - cx[k], y - cy[k]
            e[k] = -sgn * (px * ey[k] - py * ex[k])                  # inside: positive
            if bow[k] != 0.0:
                t = (px * ex[k] + py * ey[k]) / el[k]
                t = min(max(t, 0.0), 1.0)
                e[k] += bow[k] * 4.0 * t * (1.0 - t)
            r[k] = sgn * ((x - ax) * ry[k] - (y - ay) * rx[k])       # k+1's side: negative
        inside = 1.0
        wsum = 0.0
        edge_line = 0.0
        glow = 0.0
        ridge = 0.0
        dout = e[0]
        for k in range(4):
            sr[k] = _expit(r[k] / soft)
        for k in range(4):
            half = _expit(e[k] / soft)
            inside *= half
            wedge = (1.0 - sr[k]) * sr[(k + 1) % 4]
            w[k] = half * wedge
            wsum += w[k]
            u = abs(e[k]) / line_px
            if wedge > 1e-12 and u < 60.0:                  # terms under e^-20 are left out
                if u < 6.5:
                    edge_line += math.exp(-0.5 * u * u) * wedge
                glow += math.exp(-u / 3.0) * wedge
            u = abs(r[k]) / line_px
            if u < 6.5 and (x - ax) * rx[k] + (y - ay) * ry[k] > 0.0:
                ridge += math.exp(-0.5 * u * u)
            dout = min(dout, e[k])
        out = min(max(1.0 - inside, 0.0), 1.0)
        t = max(-dout, 0.0) / halo_px
        xr, yr = (x - xm) / xs, (y - ym) / xs
        for k in range(5):
            wk = w[k] / (wsum + 1e-12) * inside if k < 4 else out
            a[i, 3 * k] = wk
            a[i, 3 * k + 1] = wk * xr
            a[i, 3 * k + 2] = wk * yr
        a[i, 15] = edge_line * out
        a[i, 16] = edge_line * inside
        a[i, 17] = glow
        a[i, 18] = ridge * inside
        a[i, 19] = out * t * math.exp(1.0 - t)
    return a
