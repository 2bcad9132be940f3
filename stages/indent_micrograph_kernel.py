"""Compiled design matrix of the four-facet micrograph model (:class:`.indent_micrograph_model.QuadModel`),
and its derivatives.

One pass over the pixels fills the 20 columns for one trial geometry: the four facets' and the
surroundings' linear brightness (3 columns each), then the edge line outside and inside, the edge glow,
the ridge lines and the pile-up halo (:func:`quad_design`). The same pass can also give the derivatives
of the model, contracted with one or more brightness vectors, by the geometric parameters
(:func:`quad_design_jac`): by the chain rule through each pixel's signed distances to the four edges and
the four apex-corner rays. One such pass replaced a forward-difference Jacobian, which had re-evaluated the
design 10-14 times per iteration.
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
def _fill(X, Y, p, soft, line_px, halo_px, xm, ym, xs, coefs, free, a, jac):
    """Fill the design matrix ``a`` (n, 20) at ``p`` and, when ``free`` is not empty, ``jac`` (len(coefs), n,
    len(free)): the derivatives of ``a @ coefs[c]`` by the parameters ``p[free]``, by the chain rule through each
    pixel's signed distances to the four edges (e) and the four apex-corner rays (r)."""
    n = X.shape[0]
    want = free.shape[0] > 0
    n_par = p.shape[0]
    ax, ay = p[0], p[1]
    cx = np.empty(4)
    cy = np.empty(4)
    bow = np.zeros(4)
    for k in range(4):
        cx[k] = p[2 + 2 * k]
        cy[k] = p[3 + 2 * k]
        if n_par > 10:
            bow[k] = p[10 + k]
    area = 0.0
    for k in range(4):
        j = (k + 1) % 4
        area += 0.5 * (cx[k] * cy[j] - cx[j] * cy[k])
    sgn = 1.0 if area > 0 else -1.0
    # edges: unit direction, length; apex-corner rays: unit direction, length
    ex = np.empty(4)
    ey = np.empty(4)
    el = np.empty(4)
    rx = np.empty(4)
    ry = np.empty(4)
    rl = np.empty(4)
    for k in range(4):
        j = (k + 1) % 4
        dx, dy = cx[j] - cx[k], cy[j] - cy[k]
        el[k] = math.hypot(dx, dy) + 1e-12
        ex[k], ey[k] = dx / el[k], dy / el[k]
        dx, dy = cx[k] - ax, cy[k] - ay
        rl[k] = math.hypot(dx, dy) + 1e-12
        rx[k], ry[k] = dx / rl[k], dy / rl[k]
    e = np.empty(4)
    r = np.empty(4)
    tb = np.empty(4)          # position along each edge (0 at corner k, 1 at k + 1), unclamped
    h = np.empty(4)
    w = np.empty(4)
    sr = np.empty(4)
    wedge = np.empty(4)
    in_line = np.zeros(4, np.bool_)
    in_glow = np.zeros(4, np.bool_)
    in_ridge = np.zeros(4, np.bool_)
    beta = np.empty(5)
    g_e = np.empty(4)
    g_r = np.empty(4)
    g_wedge = np.empty(4)
    grad = np.empty(14)
    for i in range(n):
        x, y = X[i], Y[i]
        for k in range(4):
            px, py = x - cx[k], y - cy[k]
            e[k] = -sgn * (px * ey[k] - py * ex[k])                  # inside: positive
            tb[k] = (px * ex[k] + py * ey[k]) / el[k]
            if bow[k] != 0.0:
                t = min(max(tb[k], 0.0), 1.0)
                e[k] += bow[k] * 4.0 * t * (1.0 - t)
            r[k] = sgn * ((x - ax) * ry[k] - (y - ay) * rx[k])       # k+1's side: negative
        inside = 1.0
        wsum = 0.0
        edge_line = 0.0
        glow = 0.0
        ridge = 0.0
        dout = e[0]
        k_out = 0
        for k in range(4):
            sr[k] = _expit(r[k] / soft)
        for k in range(4):
            h[k] = _expit(e[k] / soft)
            inside *= h[k]
            wedge[k] = (1.0 - sr[k]) * sr[(k + 1) % 4]
            w[k] = h[k] * wedge[k]
            wsum += w[k]
            u = abs(e[k]) / line_px
            in_line[k] = wedge[k] > 1e-12 and u < 6.5
            in_glow[k] = wedge[k] > 1e-12 and u < 60.0          # terms under e^-20 are left out
            if in_line[k]:
                edge_line += math.exp(-0.5 * u * u) * wedge[k]
            if in_glow[k]:
                glow += math.exp(-u / 3.0) * wedge[k]
            u = abs(r[k]) / line_px
            in_ridge[k] = u < 6.5 and (x - ax) * rx[k] + (y - ay) * ry[k] > 0.0
            if in_ridge[k]:
                ridge += math.exp(-0.5 * u * u)
            if e[k] < dout:
                dout, k_out = e[k], k
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
        if not want:
            continue
        for ci in range(coefs.shape[0]):
            coef = coefs[ci]
            # d(a @ coef) by each pixel's e and r
            for k in range(5):
                beta[k] = coef[3 * k] + coef[3 * k + 1] * xr + coef[3 * k + 2] * yr
            big_w = wsum + 1e-12
            v = 0.0
            for k in range(4):
                v += w[k] * beta[k]
            d_inside = (v / big_w - beta[4] - coef[15] * edge_line + coef[16] * edge_line + coef[18] * ridge
                        - coef[19] * t * math.exp(1.0 - t))
            d_line = coef[15] * out + coef[16] * inside
            for k in range(4):
                d_w = inside * (beta[k] / big_w - v / (big_w * big_w))
                dh = h[k] * (1.0 - h[k]) / soft
                others = 1.0
                for m in range(4):
                    if m != k:
                        others *= h[m]
                g = d_inside * dh * others + d_w * dh * wedge[k]
                g_wedge[k] = d_w * h[k]
                u = abs(e[k]) / line_px
                if in_line[k]:
                    gl = math.exp(-0.5 * u * u)
                    g += d_line * (-gl * e[k] / (line_px * line_px)) * wedge[k]
                    g_wedge[k] += d_line * gl
                if in_glow[k]:
                    gg = math.exp(-u / 3.0)
                    g += coef[17] * (-gg * (1.0 if e[k] >= 0 else -1.0) / (3.0 * line_px)) * wedge[k]
                    g_wedge[k] += coef[17] * gg
                if k == k_out and dout < 0.0:
                    g += coef[19] * out * (1.0 - t) * math.exp(1.0 - t) * (-1.0 / halo_px)
                g_e[k] = g
            for k in range(4):
                km = (k + 3) % 4
                ds = sr[k] * (1.0 - sr[k]) / soft
                g = -g_wedge[k] * ds * sr[(k + 1) % 4] + g_wedge[km] * (1.0 - sr[km]) * ds
                if in_ridge[k]:
                    u = r[k] / line_px
                    g += coef[18] * inside * (-math.exp(-0.5 * u * u) * r[k] / (line_px * line_px))
                g_r[k] = g
            # ... and by the parameters: e_k moves with corners k, k + 1 and the bow of edge k, r_k with the apex
            # and corner k
            for q in range(14):
                grad[q] = 0.0
            for k in range(4):
                j = (k + 1) % 4
                px, py = x - cx[k], y - cy[k]
                g = -sgn * g_e[k] / el[k]
                sn = px * ey[k] - py * ex[k]
                grad[2 + 2 * k] += g * ((y - cy[j]) + sn * ex[k])
                grad[3 + 2 * k] += g * ((cx[j] - x) + sn * ey[k])
                grad[2 + 2 * j] += g * (-py - sn * ex[k])
                grad[3 + 2 * j] += g * (px - sn * ey[k])
                tc = min(max(tb[k], 0.0), 1.0)
                if bow[k] != 0.0 and 0.0 < tb[k] < 1.0:
                    dx, dy = ex[k] * el[k], ey[k] * el[k]
                    gb = g_e[k] * bow[k] * 4.0 * (1.0 - 2.0 * tc) / (el[k] * el[k])
                    grad[2 + 2 * k] += gb * (2.0 * tc * dx - dx - px)
                    grad[3 + 2 * k] += gb * (2.0 * tc * dy - dy - py)
                    grad[2 + 2 * j] += gb * (px - 2.0 * tc * dx)
                    grad[3 + 2 * j] += gb * (py - 2.0 * tc * dy)
                grad[10 + k] += g_e[k] * 4.0 * tc * (1.0 - tc)
                qx, qy = x - ax, y - ay
                g = sgn * g_r[k] / rl[k]
                sq = qx * ry[k] - qy * rx[k]
                grad[0] += g * ((y - cy[k]) + sq * rx[k])
                grad[1] += g * ((cx[k] - x) + sq * ry[k])
                grad[2 + 2 * k] += g * (-qy - sq * rx[k])
                grad[3 + 2 * k] += g * (qx - sq * ry[k])
            for m in range(free.shape[0]):
                jac[ci, i, m] = grad[free[m]]


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
    a = np.empty((X.shape[0], N_COLUMNS))
    _fill(X, Y, p, soft, line_px, halo_px, xm, ym, xs, np.zeros((0, N_COLUMNS)), np.zeros(0, np.int64), a,
          np.empty((0, 0, 0)))
    return a


@njit(cache=True, nogil=True)
def quad_design_jac(X, Y, p, coefs, free, soft, line_px, halo_px, xm, ym, xs):
    """Design matrix (n, 20) at ``p`` and the derivatives (len(coefs), n, len(free)) of ``design @ coefs[c]`` by
    the parameters ``p[free]`` (analytic; ``coefs`` (m, 20); the other arguments as :func:`quad_design`)."""
    a = np.empty((X.shape[0], N_COLUMNS))
    jac = np.empty((coefs.shape[0], X.shape[0], free.shape[0]))
    _fill(X, Y, p, soft, line_px, halo_px, xm, ym, xs, coefs, free, a, jac)
    return a, jac
