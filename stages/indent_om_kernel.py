"""Compiled fine-grid reflectance of the OM dot model (:class:`.indent_om._OmPatch`) and its derivatives.

One pass over the fine grid computes the model's reflectance - 1 and, on request, its analytic
derivatives by the dot's centre, diagonal and orientation and by the shared parameters that change it
(dark0, dark1, rim, rim_w, then for the extended model crease darkness and the three facet contrasts).
The patches are small (a few thousand cells), so one fused loop replaces some hundred numpy passes.
"""
from __future__ import annotations

import math

from numba import njit

SQRT2 = math.sqrt(2.0)
#: the rim profile t^2 exp(2 (1 - t)) is 2e-11 at this t, its derivatives (times the rim width) below 1e-9
RIM_TAIL_T = 16.0


@njit(cache=True, nogil=True)
def om_dev(xf, yf, g, s, sub, crease_w, ext, n_grad, dev, grads):
    """Fill ``dev`` (fine grid) and the first ``n_grad`` layers of ``grads``.

    Parameters
    ----------
    xf, yf : 2-D arrays
        Fine-grid coordinates (µm).
    g : 1-D array
        cx, cy, d, theta (µm, rad).
    s : 1-D array
        Shared parameters (5 plain, 9 extended; the PSF, s[4], is not used here).
    sub : float
        Fine-grid step (µm).
    crease_w : float
        Gaussian sigma of the crease lines (µm).
    ext : bool
        Extended model (creases and facet shading).
    n_grad : int
        0 (value only), 4 (own: cx, cy, d, theta) or 4 + shared (4 plain, 8 extended) layers.
    """
    cx, cy, d, th = g[0], g[1], g[2], g[3]
    dark0, dark1, rim, rim_w = s[0], s[1], s[2], s[3]
    ct, st = math.cos(th), math.sin(th)
    half = max(d / 2, 1e-3)
    d_half = 0.5 if d / 2 > 1e-3 else 0.0
    k_in = half / SQRT2 / sub
    rw = max(rim_w, 1e-3)
    w2 = -0.5 / (crease_w * crease_w)
    cut2 = 36.0 * crease_w * crease_w
    line = s[5] if ext else 0.0
    sh_u = s[6] if ext else 0.0
    sh_v = s[7] if ext else 0.0
    sh_uv = s[8] if ext else 0.0
    # rho - 1 beyond which nothing is drawn: the rim at t > RIM_TAIL_T, the edge ramp, the edge line at 6 sigma
    far = max(RIM_TAIL_T * rw, 0.5 / k_in, (6.0 * crease_w * SQRT2 / half) if ext else 0.0)
    ny, nx = xf.shape
    for i in range(ny):
        for j in range(nx):
            ex, ey = xf[i, j] - cx, yf[i, j] - cy
            u, v = ex * ct + ey * st, ey * ct - ex * st
            au, av = abs(u), abs(v)
            rho = (au + av) / half
            if rho - 1 > far:
                # beyond the rim's tail, the anti-aliased edge and the edge line: the model and every
                # derivative are 0 (to 2e-8)
                dev[i, j] = 0.0
                for k in range(n_grad):
                    grads[k, i, j] = 0.0
                continue
            ramp = 0.5 - (rho - 1) * k_in
            inside = min(max(ramp, 0.0), 1.0)
            t = max(rho - 1, 0.0) / rw
            e2 = math.exp(2 * (1 - t)) if t > 0 else 0.0        # every rim term has a factor t
            shape_rim = t * t * e2
            floor = min(max(1 - rho, 0.0), 1.0)
            if ext:
                su, sv = min(max(u / sub, -1.0), 1.0), min(max(v / sub, -1.0), 1.0)
                bright = 1.0 - dark0 - sh_u * su - sh_v * sv - sh_uv * su * sv
                fall = 1.0 - dark1 * floor
                out = rim * shape_rim + inside * (bright * fall - 1.0)
                edge = (rho - 1) * half / SQRT2
                ridge = min(au, av)
                # beyond 6 sigma a line is < 2e-8 of its depth: left out
                e_edge = math.exp(w2 * edge * edge) if edge * edge < cut2 else 0.0
                e_ridge = math.exp(w2 * ridge * ridge) if ridge * ridge < cut2 else 0.0
                on_edge = e_edge >= inside * e_ridge
                crease = e_edge if on_edge else inside * e_ridge
                keep = 1.0 - line * crease
                dev[i, j] = (1.0 + out) * keep - 1.0
            else:
                su = sv = bright = fall = out = edge = ridge = e_edge = e_ridge = crease = 0.0
                on_edge = True
                keep = 1.0
                dev[i, j] = rim * shape_rim - inside * (dark0 + dark1 * floor)
            if n_grad == 0:
                continue
            in_ramp = 1.0 if 0 < ramp < 1 else 0.0
            d_rim_rho = (2 * t - 2 * t * t) * e2 / rw if rho > 1 else 0.0
            d_floor_rho = -1.0 if 0 < rho < 1 else 0.0
            d_in_rho = -k_in * in_ramp                    # d inside / d rho at fixed half
            d_in_half = in_ramp / (SQRT2 * sub)          # d inside / d half at fixed |u| + |v|
            sgu = 1.0 if u > 0 else (-1.0 if u < 0 else 0.0)
            sgv = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
            if ext:
                p_rho = rim * d_rim_rho - inside * bright * dark1 * d_floor_rho
                p_in = bright * fall - 1.0
                dc = -line * (1.0 + out)
                d_edge = e_edge * 2 * w2 * edge if on_edge else 0.0
                c_in = 0.0 if on_edge else e_ridge
                g_rho = keep * (p_rho + p_in * d_in_rho) + dc * (d_edge * half / SQRT2 + c_in * d_in_rho)
                g_half = keep * (-p_rho * rho / half + p_in * d_in_half) + dc * (-d_edge / SQRT2 + c_in * d_in_half)
                g_su = keep * inside * fall * (-sh_u - sh_uv * sv)
                g_sv = keep * inside * fall * (-sh_v - sh_uv * su)
                g_ridge = 0.0 if on_edge else dc * inside * e_ridge * 2 * w2 * ridge
                g_u = sgu * (g_rho / half + (g_ridge if au < av else 0.0)) + (g_su / sub if au < sub else 0.0)
                g_v = sgv * (g_rho / half + (g_ridge if au >= av else 0.0)) + (g_sv / sub if av < sub else 0.0)
            else:
                p_rho = rim * d_rim_rho - inside * dark1 * d_floor_rho
                p_in = -(dark0 + dark1 * floor)
                g_rho = p_rho + p_in * d_in_rho
                g_half = -p_rho * rho / half + p_in * d_in_half
                g_u, g_v = sgu * g_rho / half, sgv * g_rho / half
            grads[0, i, j] = -ct * g_u + st * g_v
            grads[1, i, j] = -st * g_u - ct * g_v
            grads[2, i, j] = d_half * g_half
            grads[3, i, j] = v * g_u - u * g_v
            if n_grad == 4:
                continue
            d_rw = -2.0 * t * t * (1 - t) * e2 / rw if rim_w > 1e-3 else 0.0
            if ext:
                ik = inside * keep
                ikf = ik * fall
                grads[4, i, j] = -ikf
                grads[5, i, j] = -ik * bright * floor
                grads[6, i, j] = shape_rim * keep
                grads[7, i, j] = rim * d_rw * keep
                grads[8, i, j] = -(1.0 + out) * crease
                grads[9, i, j] = -ikf * su
                grads[10, i, j] = -ikf * sv
                grads[11, i, j] = -ikf * su * sv
            else:
                grads[4, i, j] = -inside
                grads[5, i, j] = -inside * floor
                grads[6, i, j] = shape_rim
                grads[7, i, j] = rim * d_rw
