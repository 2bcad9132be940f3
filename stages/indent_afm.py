"""AFM facet model of a Vickers imprint (paper 000 sec. 4): detection of pits and the four-facet fit.

Each imprint is the blend of four facets. The facet planes are fitted to the
heights (first one by one, then jointly as ``M = tau log sum exp(h_k / tau)``
with ``h_k = L_k + q_k L_k^2``, ``L_k`` a plane: one curvature term per facet
for facets bowed by elastic recovery; the blend fits the blunted floor and
rounded ridges; robust loss). Each facet meets the local original surface
(h = 0) on its line ``L_k = 0``; adjacent lines give the four corners; the
circle through the corners gives the centre and the equivalent diameter (paper
Fig. 6b); the minimum of ``M`` gives the apex depth of the model.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .cv_filters import gaussian
from .indent_geometry import (Imprint, circle_fit, diagonals as _diagonals, lm_soft_l1, plane_moments,
                              planes_from_moments, robust_plane as _robust_plane)

__all__ = ["detect_pits", "measure_afm"]


def detect_pits(z_nm: np.ndarray, noise_nm: float, pixel_um: float, min_depth_nm: float = 8.0,
                min_diameter_um: float = 0.35) -> list:
    """Candidate pits in a levelled map.

    Returns
    -------
    list of (row, col, radius_px)
        Deepest point (px) and a radius estimate from the area below threshold.
    """
    zs = gaussian(np.nan_to_num(z_nm), 1.0)
    thr = max(6 * noise_nm * 0.5, 0.5 * min_depth_nm)
    low = zs < -thr
    low = ndimage.binary_opening(low, structure=np.ones((2, 2), bool))
    lab, n = ndimage.label(low)
    out = []
    if n == 0:
        return out
    area = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    objs = ndimage.find_objects(lab)
    min_area = 0.5 * (min_diameter_um / pixel_um) ** 2 * 0.4
    for k in range(n):
        sl = objs[k]
        h, w = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
        if area[k] < max(min_area, 4) or h < 3 or w < 3:
            continue
        if max(h, w) > 4 * min(h, w):            # streak, not a pit
            continue
        # deepest point of the component (first in row-major order, as ndimage.minimum_position)
        zk = np.where(lab[sl] == k + 1, zs[sl], np.inf)
        j = int(np.argmin(zk))
        if -zk.flat[j] < min_depth_nm:
            continue
        pos_k = np.unravel_index(j, zk.shape)
        r_px = np.sqrt(2 * area[k]) / 2 * 1.15   # area of a square of diagonal d is d^2 / 2
        out.append((float(pos_k[0] + sl[0].start), float(pos_k[1] + sl[1].start), float(r_px)))
    return out


def _lse(planes, tau):
    m = planes.max(axis=0)
    e = np.exp((planes - m) / tau)
    s = e.sum(axis=0)
    return m + tau * np.log(s), e / s


def _quadrant(u, v):
    """Facet index 0..3 for (+u,+v), (-u,+v), (-u,-v), (+u,-v)."""
    return np.where(u >= 0, np.where(v >= 0, 0, 3), np.where(v >= 0, 1, 2))


def _facet_heights(coef, q, a):
    """Facet heights h_k = L_k + q_k L_k^2 (L_k = plane k) at the points ``a`` = [x, y, 1]."""
    lin = coef @ a.T
    return lin + q[:, None] * lin * lin, lin


def _fit_facets_joint(x, y, z, coef0, tau0, sigma, q0=None):
    """Joint robust fit of M = tau LSE(h_k / tau) to (x, y, z).

    Each facet is ``h_k = L_k + q_k L_k^2`` with the plane ``L_k = a x + b y + c``: a facet
    curved across its height (convex after elastic recovery for q_k < 0) whose line where
    it meets the original surface (h = 0) is still ``L_k = 0``. Returns coef (4, 3), q (4,),
    tau and the residuals.
    """
    a = np.column_stack([x, y, np.ones_like(x)])

    def unpack(p):
        return p[:12].reshape(4, 3), p[12:16], np.exp(p[16])

    def fun(p):
        c, q, tau = unpack(p)
        h, _ = _facet_heights(c, q, a)
        m, _ = _lse(h, tau)
        return m - z

    def jac(p):
        c, q, tau = unpack(p)
        h, lin = _facet_heights(c, q, a)
        m, w = _lse(h, tau)
        j = np.empty((len(z), 17))
        for k in range(4):
            j[:, 3 * k:3 * k + 3] = (w[k] * (1 + 2 * q[k] * lin[k]))[:, None] * a
            j[:, 12 + k] = w[k] * lin[k] * lin[k]
        j[:, 16] = m - (w * h).sum(axis=0)
        return j

    q0 = np.zeros(4) if q0 is None else np.asarray(q0, dtype=float)
    p0 = np.concatenate([coef0.ravel(), q0, [np.log(max(tau0, 1e-3))]])
    lo = np.full(17, -np.inf)
    hi = np.full(17, np.inf)
    lo[16], hi[16] = np.log(1e-3), np.log(1e3)
    # dense 17 x 17 normal equations per step (a general solver's SVD cost 10 x more here)
    pf = lm_soft_l1(fun, p0, 40, f_scale=max(3 * sigma, 0.3), jac=jac, ftol=1e-9, xtol=0.0, lo=lo, hi=hi)
    c, q, tau = unpack(pf)
    return c, q, float(tau), fun(pf)


def _floor(coef, tau, start=None, q=None):
    """Minimum of M = tau LSE(h_k / tau), h_k = L_k + q_k L_k^2: damped Newton from the planes' apex.

    Returns (x, y, M) in the planes' coordinates.
    """
    g_k = coef[:, :2]
    q = np.zeros(4) if q is None else np.asarray(q, dtype=float)

    def val(p):
        lin = coef @ np.array([p[0], p[1], 1.0])
        h = lin + q * lin * lin
        m = h.max()
        e = np.exp((h - m) / tau)
        return m + tau * np.log(e.sum()), e / e.sum(), lin

    # apex: least-squares point where the four planes meet
    a = np.column_stack([g_k, -np.ones(4)])
    apex, *_ = np.linalg.lstsq(a, -coef[:, 2], rcond=None)
    p = apex[:2].copy()
    f, w, lin = val(p)
    for _ in range(60):
        gk = g_k * (1 + 2 * q * lin)[:, None]
        g = w @ gk
        h = (gk.T * w) @ gk / tau - np.outer(g, g) / tau + (g_k.T * (2 * q * w)) @ g_k
        h += (1e-9 + 1e-6 * abs(np.trace(h))) * np.eye(2)
        step = np.linalg.solve(h, g)
        if g @ step <= 0:
            step = g / max(abs(np.trace(h)), 1e-12)
        t = 1.0
        while t > 1e-6:
            qq = p - t * step
            fq, wq, lq = val(qq)
            if fq <= f - 1e-4 * t * (g @ step) or fq <= f:
                break
            t *= 0.5
        else:
            break
        if abs(f - fq) < 1e-12 and t * np.hypot(*step) < 1e-9:
            p, f, w, lin = qq, fq, wq, lq
            break
        p, f, w, lin = qq, fq, wq, lq
    half = abs(float(np.mean(coef[:, 2]))) / max(float(np.mean(np.hypot(*g_k.T))), 1e-12)  # ~ half-diagonal
    if not (np.all(np.isfinite(p)) and np.isfinite(f) and np.hypot(p[0] - apex[0], p[1] - apex[1]) < 0.3 * half):
        # the curved facets sent Newton away: take the best point near the planes' apex
        r = 0.2 * half
        gx, gy = np.meshgrid(np.linspace(-r, r, 41) + apex[0], np.linspace(-r, r, 41) + apex[1])
        vals = [val((a_, b_))[0] for a_, b_ in zip(gx.ravel(), gy.ravel())]
        j = int(np.argmin(vals))
        return float(gx.ravel()[j]), float(gy.ravel()[j]), float(vals[j])
    return p[0], p[1], float(f)


def _initial_facets(x, y, zr, inner, theta0, pixel_um):
    """Four facet planes fitted one by one; quadrants about the window origin.

    The orientation from the gradients can be off by 45 deg on small pits, so
    several orientations are tried and the best max-of-planes fit is kept.
    """
    best, best_cost = None, np.inf
    xi, yi, zi = x[inner], y[inner], zr[inner]
    # moments for per-facet least-squares planes: sums over each quadrant in one product
    mom = plane_moments(xi, yi, zi)
    for dth in np.radians([0.0, 45.0, 22.5, -22.5]):
        theta = theta0 + dth
        ct, st = np.cos(theta), np.sin(theta)
        u, v = xi * ct + yi * st, -xi * st + yi * ct
        q = _quadrant(u, v)
        sel = (np.abs(u) > 0.7 * pixel_um) & (np.abs(v) > 0.7 * pixel_um)
        onehot = (q[:, None] == np.arange(4)).astype(float)
        s_all = onehot.T @ mom                                   # (4, 9): all pixels of each quadrant
        s_sel = (onehot * sel[:, None]).T @ mom                  # clear of the diagonals
        use = np.where((s_sel[:, 5] >= 3)[:, None], s_sel, s_all)
        if np.any(use[:, 5] < 3):
            continue
        coef = planes_from_moments(use)
        pm = (coef @ np.stack([xi, yi, np.ones_like(xi)])).max(axis=0)
        cost = float(np.sum(np.minimum((pm - zi) ** 2, 100.0)))
        if cost < best_cost:
            best, best_cost = coef, cost
    return best


def measure_afm(z_nm: np.ndarray, pixel_um: float, row: float, col: float, radius_px: float,
                noise_nm: float, others: np.ndarray | None = None,
                unreliable: np.ndarray | None = None) -> Imprint | None:
    """Measure one imprint in a levelled map by fitting its four facets.

    Parameters
    ----------
    z_nm : ndarray (rows, cols)
        Levelled heights (nm).
    pixel_um : float
        Pixel size (µm).
    row, col, radius_px : float
        Candidate from :func:`detect_pits` (px).
    noise_nm : float
        Pixel noise (nm).
    others : ndarray of bool, optional
        Pixels of other features, left out of the reference surface.
    unreliable : ndarray of bool, optional
        Pixels not to fit (e.g. interpolated by scar removal).

    Returns
    -------
    Imprint or None
        None if the pit does not look like a four-sided pyramid.
    """
    ny, nx = z_nm.shape
    r_est = max(radius_px, 2.5)
    cy, cx = row, col
    result = None
    coef = None
    tau = None
    qk = None
    shift = np.zeros(2)
    for it in range(3):
        win = int(np.ceil(max(3.6 * r_est, r_est + 8)))
        r0, r1 = max(0, int(cy) - win), min(ny, int(cy) + win + 1)
        c0, c1 = max(0, int(cx) - win), min(nx, int(cx) + win + 1)
        zz = z_nm[r0:r1, c0:c1]
        rr, cc = np.mgrid[r0:r1, c0:c1]
        x = (cc - cx) * pixel_um
        y = (rr - cy) * pixel_um
        fin = np.isfinite(zz)
        if unreliable is not None:
            fin &= ~unreliable[r0:r1, c0:c1]
        rad = np.hypot(x, y) / pixel_um
        ok_ref = fin & (rad > 2.2 * r_est) & (rad < 3.6 * r_est)
        if others is not None:
            ok_ref &= ~others[r0:r1, c0:c1]
        if ok_ref.sum() < 30:
            ok_ref = fin & (rad > 1.8 * r_est)
            if others is not None:
                ok_ref &= ~others[r0:r1, c0:c1]
        if ok_ref.sum() < 12:
            return None
        ref = _robust_plane(x[ok_ref], y[ok_ref], zz[ok_ref])
        zr = zz - (ref[0] * x + ref[1] * y + ref[2])
        if coef is None:
            # orientation from the facet gradients (4-fold), centre from the deepest point
            zs = gaussian(np.nan_to_num(zr), 0.8)
            gy, gx = np.gradient(zs)
            zmin = zs[rad < 1.2 * r_est].min()
            sel = (zs < 0.2 * zmin) & (zs > 0.85 * zmin) & (rad < 1.2 * r_est)
            if sel.sum() < 4:
                return None
            phi = np.arctan2(gy[sel], gx[sel])
            th_grad = np.angle(np.sum(np.hypot(gx[sel], gy[sel]) * np.exp(4j * phi))) / 4
            inner = fin & (zr < -max(4 * noise_nm, 3.0, 0.1 * -zmin)) & (rad < 1.3 * r_est)
            coef = _initial_facets(x, y, zr, inner, th_grad - np.pi / 4, pixel_um)
            if coef is None:
                return None
            tau = max(0.02 * -zmin, 0.5)
        else:
            # re-centred window: shift the planes into the new coordinates
            coef = coef.copy()
            coef[:, 2] += coef[:, 0] * shift[0] + coef[:, 1] * shift[1]
        planes = coef @ np.stack([x.ravel(), y.ravel(), np.ones(x.size)])
        pmax = planes.max(axis=0).reshape(x.shape)
        h_apex = -pmax.min()
        fit_px = fin & (pmax < -max(3.0, 4 * noise_nm, 0.06 * h_apex)) & (rad < 1.6 * r_est)
        if fit_px.sum() < 16:
            return None
        use = fit_px
        if fit_px.sum() > 1500:
            # a large imprint: an even subsample of its pixels pins the 17 parameters down as well
            use = fit_px.copy()
            idx = np.flatnonzero(fit_px)
            use.ravel()[idx] = False
            use.ravel()[idx[::int(np.ceil(len(idx) / 1500))]] = True
        coef, qk, tau, res = _fit_facets_joint(x[use], y[use], zr[use], coef, tau, noise_nm, qk)
        # facets must slope up outwards, one per quadrant around the apex
        corners = []
        for k, k2 in ((3, 0), (0, 1), (1, 2), (2, 3)):
            m = np.array([coef[k, :2], coef[k2, :2]])
            if abs(np.linalg.det(m)) < 1e-12:
                return None
            corners.append(np.linalg.solve(m, -np.array([coef[k, 2], coef[k2, 2]])))
        corners = np.array(corners)
        ccx, ccy, crad = circle_fit(corners)
        if not np.isfinite(crad) or crad <= 0:
            return None
        result = dict(corners=corners, ccx=ccx, ccy=ccy, crad=crad, coef=coef, q=qk, tau=tau, res=res, zr=zr,
                      x=x, y=y, fit_px=fit_px, origin=(cx * pixel_um, cy * pixel_um))
        # next round: window centred on the circle, radius from the corners; shifting the
        # origin changes the plane offsets: c' = c + a dx + b dy
        shift = np.array([ccx, ccy])
        new_cx, new_cy = cx + ccx / pixel_um, cy + ccy / pixel_um
        if np.hypot(new_cx - cx, new_cy - cy) > 3 * r_est:
            return None
        done = abs(crad / pixel_um - r_est) < 0.05 * r_est and np.hypot(new_cx - cx, new_cy - cy) < 0.05
        r_est = crad / pixel_um
        cx, cy = new_cx, new_cy
        if done:
            break
    # the model's floor, of the last fit only
    result["depth"] = -_floor(result["coef"], result["tau"], (result["ccx"], result["ccy"]), result["q"])[2]
    return _imprint_from_fit(result, pixel_um)


def _imprint_from_fit(f, pixel_um):
    """Imprint record from the last window fit (window coordinates about ``origin``)."""
    ox, oy = f["origin"]
    corners = f["corners"] + [ox, oy]
    xc, yc = f["ccx"] + ox, f["ccy"] + oy
    diameter = 2 * f["crad"]
    depth = f["depth"]
    if not (depth > 0 and diameter > 0):
        return None
    d1, d2, orient = _diagonals(corners)
    # pile-up: highest smoothed height just outside the edges
    lc = f["corners"] - [f["ccx"], f["ccy"]]
    a_half = np.hypot(*(lc[0] - lc[2])) / 2
    b_half = np.hypot(*(lc[1] - lc[3])) / 2
    ua = (lc[0] - lc[2]) / (2 * a_half)
    xr, yr = f["x"] - f["ccx"], f["y"] - f["ccy"]
    u = xr * ua[0] + yr * ua[1]
    v = -xr * ua[1] + yr * ua[0]
    rho = np.abs(u) / a_half + np.abs(v) / b_half
    zs = gaussian(np.nan_to_num(f["zr"]), 1.0)
    ring = (rho > 1.05) & (rho < 2.0) & np.isfinite(f["zr"])
    pile = float(zs[ring].max()) if ring.any() else float("nan")
    res = f["res"]
    return Imprint(x_um=float(xc), y_um=float(yc), diameter_um=float(diameter), diag1_um=float(d1),
                   diag2_um=float(d2), depth_nm=float(depth), hd_ratio=float(depth / (1000 * diameter)),
                   orientation_deg=float(orient), pileup_nm=pile, corners_um=corners,
                   fit_rms=float(np.sqrt(np.mean(res ** 2))), n_pixels=int(f["fit_px"].sum()),
                   blend_nm=float(f["tau"]))
