"""Detection and model-based measurement of Vickers micro-indentations (paper 000 sec. 4).

Positions are in the image frame: x = column index x pixel size, y = row index
x pixel size (pixel centres, µm, y down the rows). Angles are measured from +x
towards +y.

AFM: each imprint is the blend of four facets. The facet planes are fitted to
the heights (first one by one, then jointly as ``M = tau log sum exp(h_k / tau)``
with ``h_k = L_k + q_k L_k^2``, ``L_k`` a plane: one curvature term per facet
for facets bowed by elastic recovery; the blend fits the blunted floor and
rounded ridges; robust loss). Each facet meets the local original surface
(h = 0) on its line ``L_k = 0``; adjacent lines give the four corners; the
circle through the corners gives the centre and the equivalent diameter (paper
Fig. 6b); the minimum of ``M`` gives the floor and the depth.

OM: each dark dot is fitted with an image model: a square (diamond) footprint
of diagonal ``d`` and orientation, darker towards the floor, with a bright rim,
blurred by an Airy PSF, over a linear background. Darkness, rim and PSF are
shared by the dots of one micrograph (:func:`measure_om_array`: a joint fit,
block-arrow normal equations); each dot's fit gives the sub-pixel centre and the
apparent diameter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares
from scipy import fft as sfft
from scipy.special import j1

from .errors import MarkcalError
from .register import index_grid, robust_rigid_fit

__all__ = ["circle_fit", "Imprint", "detect_pits", "measure_afm", "detect_dots", "measure_om", "measure_om_array",
           "ArrayFit", "index_array", "size_stats", "IMPRINT_FIELDS"]

#: per-imprint fields (``Imprint`` attributes that go into indents.csv)
IMPRINT_FIELDS = ("x_um", "y_um", "diameter_um", "diag1_um", "diag2_um", "depth_nm", "hd_ratio",
                  "orientation_deg", "pileup_nm")


def circle_fit(points: np.ndarray) -> tuple:
    """Geometric least-squares circle through 2-D points.

    Returns
    -------
    cx, cy, r : float
        Centre and radius in the points' units.
    """
    p = np.asarray(points, float)
    a = np.column_stack([2 * p, np.ones(len(p))])
    b = (p ** 2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)       # Kasa start
    c = sol[:2]
    for _ in range(20):                                # Gauss-Newton on the geometric distances
        d = p - c
        r_i = np.hypot(d[:, 0], d[:, 1])
        r = r_i.mean()
        j = -d / r_i[:, None] + (d / r_i[:, None]).mean(axis=0)
        res = r_i - r
        step, *_ = np.linalg.lstsq(j, -res, rcond=None)
        c = c + step
        if np.hypot(*step) < 1e-12 * max(r, 1e-12):
            break
    d = p - c
    return float(c[0]), float(c[1]), float(np.hypot(d[:, 0], d[:, 1]).mean())


@dataclass(frozen=True)
class Imprint:
    """One measured imprint (image frame; lengths µm, heights nm).

    ``corners_um`` (4, 2) in order around the imprint; ``outline`` is what the
    report draws. AFM-only fields are NaN for OM.
    """

    x_um: float
    y_um: float
    diameter_um: float
    diag1_um: float
    diag2_um: float
    depth_nm: float
    hd_ratio: float
    orientation_deg: float
    pileup_nm: float
    corners_um: np.ndarray
    fit_rms: float
    n_pixels: int
    blend_nm: float = float("nan")          # AFM: tip/ridge blend tau of the facet model (nm)
    psf_um: float = float("nan")            # OM: fitted PSF, Gaussian-equivalent sigma (µm)
    contrast: float = float("nan")          # OM: interior darkness


# ----------------------------------------------------------------------------- helpers

def _wrap45(a_deg):
    return (a_deg + 45.0) % 90.0 - 45.0


def _diagonals(corners):
    """diag1 (the one within +-45 deg of +x), diag2 and the orientation of diag1 (deg)."""
    v_a = corners[0] - corners[2]
    v_b = corners[1] - corners[3]
    out = []
    for v in (v_a, v_b):
        ang = np.degrees(np.arctan2(v[1], v[0]))
        ang = (ang + 90.0) % 180.0 - 90.0
        out.append((np.hypot(*v), ang))
    (la, aa), (lb, ab) = out
    if abs(aa) <= 45.0:
        return la, lb, _wrap45(aa)
    return lb, la, _wrap45(ab)


def _robust_plane(x, y, z, n_iter=4):
    a = np.column_stack([x, y, np.ones_like(x)])
    keep = np.ones(len(z), bool)
    coef = np.zeros(3)
    for _ in range(n_iter):
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak + 1e-12 * np.eye(3), ak.T @ z[keep])
        if n_iter == 1:
            break
        r = z - a @ coef
        s = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep]))) + 1e-9
        new = np.abs(r) < 3.5 * s
        if new.sum() < 10 or np.array_equal(new, keep):
            break
        keep = new
    return coef


# ----------------------------------------------------------------------------- AFM

def detect_pits(z_nm: np.ndarray, noise_nm: float, pixel_um: float, min_depth_nm: float = 8.0,
                min_diameter_um: float = 0.35) -> list:
    """Candidate pits in a levelled map.

    Returns
    -------
    list of (row, col, radius_px)
        Deepest point (px) and a radius estimate from the area below threshold.
    """
    zs = ndimage.gaussian_filter(np.nan_to_num(z_nm), 1.0)
    thr = max(6 * noise_nm * 0.5, 0.5 * min_depth_nm)
    low = zs < -thr
    low = ndimage.binary_opening(low, structure=np.ones((2, 2), bool))
    lab, n = ndimage.label(low)
    out = []
    if n == 0:
        return out
    idx = np.arange(1, n + 1)
    area = ndimage.sum(low, lab, idx)
    mins = ndimage.minimum(zs, lab, idx)
    pos = ndimage.minimum_position(zs, lab, idx)
    objs = ndimage.find_objects(lab)
    min_area = 0.5 * (min_diameter_um / pixel_um) ** 2 * 0.4
    for k in range(n):
        sl = objs[k]
        h, w = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
        if area[k] < max(min_area, 4) or h < 3 or w < 3 or -mins[k] < min_depth_nm:
            continue
        if max(h, w) > 4 * min(h, w):            # streak, not a pit
            continue
        r_px = np.sqrt(2 * area[k]) / 2 * 1.15   # area of a square of diagonal d is d^2 / 2
        out.append((float(pos[k][0]), float(pos[k][1]), float(r_px)))
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
    p0[16] = np.clip(p0[16], lo[16] + 1e-6, hi[16] - 1e-6)
    r = least_squares(fun, p0, jac=jac, bounds=(lo, hi), loss="soft_l1", f_scale=max(3 * sigma, 0.3),
                      x_scale="jac", max_nfev=60)
    c, q, tau = unpack(r.x)
    return c, q, float(tau), r.fun


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
    for dth in np.radians([0.0, 45.0, 22.5, -22.5]):
        theta = theta0 + dth
        ct, st = np.cos(theta), np.sin(theta)
        u, v = x * ct + y * st, -x * st + y * ct
        q = _quadrant(u, v)
        sel = inner & (np.abs(u) > 0.7 * pixel_um) & (np.abs(v) > 0.7 * pixel_um)
        coef = np.zeros((4, 3))
        ok = True
        for k in range(4):
            s = sel & (q == k)
            if s.sum() < 3:
                s = inner & (q == k)
            if s.sum() < 3:
                ok = False
                break
            coef[k] = _robust_plane(x[s], y[s], zr[s], n_iter=1)
        if not ok:
            continue
        pm = (coef @ np.stack([x[inner], y[inner], np.ones(inner.sum())])).max(axis=0)
        cost = float(np.sum(np.minimum((pm - zr[inner]) ** 2, 100.0)))
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
            zs = ndimage.gaussian_filter(np.nan_to_num(zr), 0.8)
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
        coef, qk, tau, res = _fit_facets_joint(x[fit_px], y[fit_px], zr[fit_px], coef, tau, noise_nm, qk)
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
        fx, fy, fm = _floor(coef, tau, (ccx, ccy), qk)
        result = dict(corners=corners, ccx=ccx, ccy=ccy, crad=crad, depth=-fm, tau=tau, res=res, zr=zr,
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
    zs = ndimage.gaussian_filter(np.nan_to_num(f["zr"]), 1.0)
    ring = (rho > 1.05) & (rho < 2.0) & np.isfinite(f["zr"])
    pile = float(zs[ring].max()) if ring.any() else float("nan")
    res = f["res"]
    return Imprint(x_um=float(xc), y_um=float(yc), diameter_um=float(diameter), diag1_um=float(d1),
                   diag2_um=float(d2), depth_nm=float(depth), hd_ratio=float(depth / (1000 * diameter)),
                   orientation_deg=float(orient), pileup_nm=pile, corners_um=corners,
                   fit_rms=float(np.sqrt(np.mean(res ** 2))), n_pixels=int(f["fit_px"].sum()),
                   blend_nm=float(f["tau"]))


# ----------------------------------------------------------------------------- OM

def om_background(img: np.ndarray, pixel_um: float, window_um: float = 6.0) -> np.ndarray:
    """Smooth illumination of a micrograph, the dots and their rims left out.

    Median over ``window_um`` on a 4x coarser grid (dots and rims cover a
    small part of it), Gaussian smoothing, then bilinear interpolation back to
    every pixel (pixel centres aligned).
    """
    f = 4
    ny, nx = img.shape
    py, px_ = (-ny) % f, (-nx) % f
    padded = np.pad(img.astype(np.float64), ((0, py), (0, px_)), mode="edge")
    small = padded.reshape(padded.shape[0] // f, f, padded.shape[1] // f, f).mean(axis=(1, 3))
    size = max(5, int(round(window_um / (pixel_um * f))) | 1)
    bg = ndimage.median_filter(small, size=size, mode="nearest")
    bg = ndimage.gaussian_filter(bg, size / 4, mode="nearest")
    rr = (np.arange(ny) - (f - 1) / 2) / f
    cc = (np.arange(nx) - (f - 1) / 2) / f
    r2, c2 = np.meshgrid(rr, cc, indexing="ij")
    out = ndimage.map_coordinates(bg, [r2, c2], order=1, mode="nearest")
    return np.maximum(out, 1e-6 * max(float(img.max()), 1.0))


def detect_dots(img: np.ndarray, pixel_um: float, min_diameter_um: float = 0.4,
                background: np.ndarray | None = None) -> tuple:
    """Dark compact dots in a micrograph.

    ``background`` is :func:`om_background` of ``img`` when the caller has it already.

    Returns
    -------
    list of (row, col, radius_px), float
        Candidates (centroid of the dark area, px) and the relative noise level.
    """
    rel = img / (om_background(img, pixel_um) if background is None else background) - 1.0
    d = np.diff(rel, axis=1)
    sigma = float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2))
    rs = ndimage.gaussian_filter(rel, 1.0)
    thr = max(4 * sigma * 0.5, 0.06)
    low = rs < -thr
    lab, n = ndimage.label(low)
    out = []
    if n == 0:
        return out, sigma
    idx = np.arange(1, n + 1)
    area = ndimage.sum(low, lab, idx)
    com = ndimage.center_of_mass(-np.minimum(rs, 0), lab, idx)
    objs = ndimage.find_objects(lab)
    min_area = max(4.0, 0.3 * (min_diameter_um / pixel_um) ** 2 / 2)
    for k in range(n):
        sl = objs[k]
        h, w = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
        if area[k] < min_area or max(h, w) > 3 * min(h, w):
            continue
        out.append((float(com[k][0]), float(com[k][1]), float(np.sqrt(2 * area[k]) / 2)))
    return out, sigma


_AIRY_CACHE: dict = {}


def _airy(psf_um, sub_um):
    """Airy (diffraction-limited, in focus) intensity PSF whose Gaussian-equivalent sigma is ``psf_um``.

    sigma ~ 0.21 lambda / NA, so v = 2 pi NA r / lambda = 2 pi 0.21 r / sigma; sampled at
    ``sub_um`` out to 1.8 lambda / NA. Cached (read-only arrays).
    """
    key = (float(psf_um), float(sub_um))
    k = _AIRY_CACHE.get(key)
    if k is None:
        if len(_AIRY_CACHE) > 64:
            _AIRY_CACHE.clear()
        k = _AIRY_CACHE[key] = _airy_kernel(psf_um, sub_um)
        k.flags.writeable = False
    return k


def _airy_kernel(psf_um, sub_um):
    lam_na = psf_um / 0.21
    h = max(2, int(np.ceil(1.8 * lam_na / sub_um)))
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1] * sub_um
    v = np.maximum(2 * np.pi * np.hypot(xx, yy) / lam_na, 1e-9)
    k = (2 * j1(v) / v) ** 2
    return k / k.sum()


#: OM model parameters. Per dot: centre (µm), diagonal d (µm), orientation (rad), background
#: level, gradient x, y (1/µm). Shared by the dots of one micrograph (one objective, one
#: material): interior darkness at the edge and its increase to the floor, rim height and width
#: (in units of the half-diagonal), PSF (Gaussian-equivalent sigma, µm).
_OM_OWN = ("cx", "cy", "d", "theta", "bg", "gx", "gy")
_OM_SHARED = ("dark0", "dark1", "rim", "rim_w", "psf")
_OM_SHARED_LO = np.array([0.0, -1.0, -0.5, 0.03, 0.04])
_OM_SHARED_HI = np.array([1.0, 1.0, 2.0, 0.8, 0.6])
_OM_SHARED_STEP = np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-5])
_OM_OWN_STEP = np.array([1e-5, 1e-5, 1e-5, 1e-5, 1e-6, 1e-6, 1e-6])


class _OmPatch:
    """One dot's patch (grey values / illumination) and its image model.

    The model is evaluated on a 2x finer grid: relative reflectance (background 1) of a
    diamond of diagonal ``d``, darker to the floor, with a bright rim ``rim t^2 exp(2 (1 - t))``,
    t = (rho - 1) / rim_w, rho = (|u| + |v|) / (d / 2), anti-aliased edge; blurred by an Airy PSF
    and averaged over each pixel (one FFT convolution with the PSF folded with the 2 x 2 pixel
    box, its transform cached per PSF), times a linear background.
    """

    def __init__(self, img, background, pixel_um, row, col, radius_px):
        ny, nx = img.shape
        self.r_est = max(radius_px, 2.0)
        # a large dot (diagonal >= 16 px) needs no sub-pixel grid: its edge is anti-aliased
        self.ss = 1 if self.r_est >= 8 else 2
        half = int(np.ceil(self.r_est * 1.5 + 0.6 / pixel_um + 2))
        r0, r1 = max(0, int(round(row)) - half), min(ny, int(round(row)) + half + 1)
        c0, c1 = max(0, int(round(col)) - half), min(nx, int(round(col)) + half + 1)
        patch = img[r0:r1, c0:c1].astype(np.float64)
        self.ok = patch.shape[0] >= 7 and patch.shape[1] >= 7
        if background is not None:
            patch = patch / background[r0:r1, c0:c1]
        else:
            patch = patch / np.median(np.concatenate([patch[0], patch[-1], patch[:, 0], patch[:, -1]]))
        self.patch = patch
        self.row, self.col, self.pixel_um = row, col, pixel_um
        yy, xx = np.mgrid[r0:r1, c0:c1] * pixel_um
        self.xc0, self.yc0 = float(xx.mean()), float(yy.mean())
        self.dx, self.dy = xx - self.xc0, yy - self.yc0
        ss = self.ss
        self.sub = pixel_um / ss
        fr = (np.arange((r1 - r0) * ss) - (ss - 1) / 2) / ss + r0
        fc = (np.arange((c1 - c0) * ss) - (ss - 1) / 2) / ss + c0
        self.yf, self.xf = np.meshgrid(fr * pixel_um, fc * pixel_um, indexing="ij")
        self._kern = {}

    def _kernel_fft(self, psf):
        got = self._kern.get(psf)
        if got is None:
            k = _airy(psf, self.sub)
            h = k.shape[0] // 2
            # fold in the ss x ss pixel box: pixel mean = full[h + ss - 1 + ss i]
            ss = self.ss
            k2 = np.zeros((k.shape[0] + ss - 1, k.shape[1] + ss - 1))
            for a in range(ss):
                for b in range(ss):
                    k2[a:a + k.shape[0], b:b + k.shape[1]] += k / ss ** 2
            shape = tuple(sfft.next_fast_len(n + 2 * h + ss - 1, real=True) for n in self.xf.shape)
            got = (sfft.rfft2(k2, shape), h, shape)
            if len(self._kern) > 8:
                self._kern.clear()
            self._kern[psf] = got
        return got

    def dev(self, g, s):
        """Reflectance - 1 on the fine grid."""
        cx, cy, d, th = g[:4]
        dark0, dark1, rim, rim_w = s[:4]
        ct, st = np.cos(th), np.sin(th)
        ex, ey = self.xf - cx, self.yf - cy
        half = max(d / 2, 1e-3)
        rho = (np.abs(ex * ct + ey * st) + np.abs(ey * ct - ex * st)) / half
        inside = np.clip(0.5 - (rho - 1) * (half / np.sqrt(2) / self.sub), 0.0, 1.0)
        t = np.maximum(rho - 1, 0) / max(rim_w, 1e-3)
        return rim * t * t * np.exp(2 * (1 - t)) - inside * (dark0 + dark1 * np.clip(1 - rho, 0, 1))

    def blur(self, dev, psf):
        """PSF blur and pixel averaging of one or a stack of fine-grid arrays."""
        kf, h, shape = self._kernel_fft(float(psf))
        full = sfft.irfft2(sfft.rfft2(dev, shape) * kf, shape)
        ny, nx = self.patch.shape
        ss, o = self.ss, h + self.ss - 1
        return full[..., o:o + ss * ny:ss, o:o + ss * nx:ss]

    def lin(self, g):
        return g[4] + g[5] * self.dx + g[6] * self.dy

    def model(self, g, s):
        """Model grey values / illumination for own parameters ``g`` and shared ``s``."""
        return (1.0 + self.blur(self.dev(g, s), s[4])) * self.lin(g)

    def jac(self, g, s, shared=True):
        """Model and forward-difference Jacobian (pixels x (7 own [+ 5 shared]) columns)."""
        devs = [self.dev(g, s)]
        for j in range(4):
            gj = g.copy()
            gj[j] += _OM_OWN_STEP[j]
            devs.append(self.dev(gj, s))
        if shared:
            for j in range(4):
                sj = s.copy()
                sj[j] += _OM_SHARED_STEP[j]
                devs.append(self.dev(g, sj))
        pix = self.blur(np.stack(devs), s[4])
        lin = self.lin(g)
        base = 1.0 + pix[0]
        m = base * lin
        cols = [(pix[1 + j] - pix[0]) * lin / _OM_OWN_STEP[j] for j in range(4)]
        cols += [base, base * self.dx, base * self.dy]
        if shared:
            cols += [(pix[5 + j] - pix[0]) * lin / _OM_SHARED_STEP[j] for j in range(4)]
            cols.append((self.blur(devs[0], s[4] + _OM_SHARED_STEP[4]) - pix[0]) * lin / _OM_SHARED_STEP[4])
        return m.ravel(), np.stack([c.ravel() for c in cols], axis=1)

    def own_bounds(self, d0):
        x, y = self.col * self.pixel_um, self.row * self.pixel_um
        lo = np.array([x - 2 * d0, y - 2 * d0, 0.2 * d0, -np.inf, 0.5, -np.inf, -np.inf])
        hi = np.array([x + 2 * d0, y + 2 * d0, 3 * d0, np.inf, 2.0, np.inf, np.inf])
        return lo, hi

    def start(self, s):
        """Starting own parameters: candidate centre and size, best of four orientations."""
        d0 = 2 * self.r_est * self.pixel_um
        gs = [np.array([self.col * self.pixel_um, self.row * self.pixel_um, d0, th, 1.0, 0.0, 0.0])
              for th in np.radians([0.0, 22.5, 45.0, 67.5])]
        pix = self.blur(np.stack([self.dev(g, s) for g in gs]), s[4])
        cost = [np.sum(((1 + p) - self.patch) ** 2) for p in pix]
        return gs[int(np.argmin(cost))], d0


def _om_joint_fit(patches, g0, d0, s0, noise_rel, max_nfev=40):
    """Fit the shared parameters and every patch's own parameters jointly (robust loss).

    The Jacobian is built block by block: a patch depends only on its own seven parameters
    and the five shared ones.
    """
    k = len(patches)
    sizes = [p.patch.size for p in patches]
    offs = np.concatenate([[0], np.cumsum(sizes)])
    target = np.concatenate([p.patch.ravel() for p in patches])
    lo = [_OM_SHARED_LO]
    hi = [_OM_SHARED_HI]
    for p, d in zip(patches, d0):
        a, b = p.own_bounds(d)
        lo.append(a)
        hi.append(b)
    lo, hi = np.concatenate(lo), np.concatenate(hi)
    x0 = np.clip(np.concatenate([s0, np.ravel(g0)]), lo + 1e-9, hi - 1e-9)

    def split(x):
        return x[:5], x[5:].reshape(k, 7)

    def fun(x):
        s, g = split(x)
        return np.concatenate([p.model(g[i], s).ravel() for i, p in enumerate(patches)]) - target

    def jac(x):
        s, g = split(x)
        jm = np.zeros((offs[-1], x.size))
        for i, p in enumerate(patches):
            _m, jp = p.jac(g[i], s)
            rows = slice(offs[i], offs[i + 1])
            jm[rows, 5 + 7 * i:12 + 7 * i] = jp[:, :7]
            jm[rows, :5] = jp[:, 7:]
        return jm

    scale = np.concatenate([[0.05, 0.05, 0.05, 0.05, 0.02], np.tile([0.02, 0.02, 0.05, 0.05, 0.01, 0.001, 0.001], k)])
    r = least_squares(fun, x0, jac=jac, bounds=(lo, hi), loss="soft_l1", f_scale=max(3 * noise_rel, 0.005),
                      x_scale=scale, max_nfev=max_nfev)
    s, g = split(r.x)
    res = [r.fun[offs[i]:offs[i + 1]] for i in range(k)]
    return s, g, res


def _om_block_fit(patches, g, d0, s, noise_rel, n_iter=20):
    """Joint robust fit of many patches: shared and own parameters (Levenberg-Marquardt).

    The normal equations have a block-arrow structure (each patch couples its seven own
    parameters only with the five shared ones), solved through the Schur complement of the
    shared block, so the cost grows linearly with the number of dots. Soft-L1 loss by
    iteratively reweighted least squares; bounds by clipping.

    Returns
    -------
    s : ndarray (5,), g : ndarray (k, 7), res : list of residual arrays
    """
    f = max(3 * noise_rel, 0.005)
    bounds = [p.own_bounds(d) for p, d in zip(patches, d0)]
    lo_g = np.array([b[0] for b in bounds]) + 1e-9
    hi_g = np.array([b[1] for b in bounds]) - 1e-9
    g = np.clip(np.array(g, dtype=float), lo_g, hi_g)
    s = np.clip(np.array(s, dtype=float), _OM_SHARED_LO + 1e-9, _OM_SHARED_HI - 1e-9)
    targets = [p.patch.ravel() for p in patches]

    def cost_of(res):
        return float(sum(np.sum(2 * f * f * (np.sqrt(1 + (r / f) ** 2) - 1)) for r in res))

    lam = 1e-3
    res = None
    for _it in range(n_iter):
        U, W, ga = [], [], []
        V = np.zeros((5, 5))
        gb = np.zeros(5)
        res = []
        for i, p in enumerate(patches):
            m, jm = p.jac(g[i], s)
            r = m - targets[i]
            res.append(r)
            w = 1.0 / np.sqrt(1.0 + (r / f) ** 2)
            a, b = jm[:, :7], jm[:, 7:]
            aw, bw = a * w[:, None], b * w[:, None]
            U.append(a.T @ aw)
            W.append(aw.T @ b)
            ga.append(aw.T @ r)
            V += b.T @ bw
            gb += bw.T @ r
        cost = cost_of(res)
        improved = False
        for _try in range(5):
            uinv = [np.linalg.inv(u + lam * np.diag(np.diag(u)) + 1e-12 * np.eye(7)) for u in U]
            S = V + lam * np.diag(np.diag(V)) + 1e-12 * np.eye(5)
            rhs = gb.copy()
            for ui, wi, gi in zip(uinv, W, ga):
                S -= wi.T @ ui @ wi
                rhs -= wi.T @ ui @ gi
            ds = -np.linalg.solve(S, rhs)
            dg = np.array([-ui @ (gi + wi @ ds) for ui, wi, gi in zip(uinv, W, ga)])
            s_new = np.clip(s + ds, _OM_SHARED_LO + 1e-9, _OM_SHARED_HI - 1e-9)
            g_new = np.clip(g + dg, lo_g, hi_g)
            res_new = [p.model(g_new[i], s_new).ravel() - targets[i] for i, p in enumerate(patches)]
            c_new = cost_of(res_new)
            if c_new < cost:
                improved = True
                break
            lam *= 4.0
        if not improved:
            break
        rel = (cost - c_new) / max(cost, 1e-30)
        s, g, res = s_new, g_new, res_new
        lam = max(lam / 3.0, 1e-7)
        if rel < 1e-6:
            break
    if res is None:
        res = [p.model(g[i], s).ravel() - targets[i] for i, p in enumerate(patches)]
    return s, g, res


def _om_own_fit(p, g0, d0, s, noise_rel, max_nfev=40):
    """Fit one patch's own parameters with the shared ones fixed."""
    lo, hi = p.own_bounds(d0)
    target = p.patch.ravel()
    x0 = np.clip(g0, lo + 1e-9, hi - 1e-9)

    def fun(g):
        return p.model(g, s).ravel() - target

    def jac(g):
        return p.jac(g, s, shared=False)[1]

    r = least_squares(fun, x0, jac=jac, bounds=(lo, hi), loss="soft_l1", f_scale=max(3 * noise_rel, 0.005),
                      x_scale=np.array([0.02, 0.02, 0.05, 0.05, 0.01, 0.001, 0.001]), max_nfev=max_nfev)
    return r.x, r.fun


def _om_imprint(g, s, res, n_pixels):
    cx, cy, d, th = g[:4]
    ct, st = np.cos(th), np.sin(th)
    corners = np.array([[d / 2 * ct, d / 2 * st], [-d / 2 * st, d / 2 * ct],
                        [-d / 2 * ct, -d / 2 * st], [d / 2 * st, -d / 2 * ct]]) + [cx, cy]
    d1, d2, orient = _diagonals(corners)
    nan = float("nan")
    return Imprint(x_um=float(cx), y_um=float(cy), diameter_um=float(d), diag1_um=float(d1), diag2_um=float(d2),
                   depth_nm=nan, hd_ratio=nan, orientation_deg=float(orient), pileup_nm=nan, corners_um=corners,
                   fit_rms=float(np.sqrt(np.mean(res ** 2))), n_pixels=int(n_pixels), psf_um=float(s[4]),
                   contrast=float(s[0]))


_OM_S0 = np.array([0.4, 0.1, 0.15, 0.2, 0.15])


def measure_om(img: np.ndarray, pixel_um: float, row: float, col: float, radius_px: float,
               noise_rel: float, background: np.ndarray | None = None) -> Imprint | None:
    """Measure one dark dot on its own: sub-pixel centre and apparent diameter by an image-model fit.

    All twelve model parameters (own and shared, see :func:`measure_om_array`) are fitted to
    this dot alone; with several dots in one micrograph :func:`measure_om_array` is more
    accurate (the darkness, rim and PSF correlate with the diameter of a small dot).

    Parameters
    ----------
    img : ndarray (rows, cols)
        Grey values.
    row, col, radius_px : float
        Candidate from :func:`detect_dots` (px).
    noise_rel : float
        Relative noise of the grey values.
    background : ndarray, optional
        Illumination (:func:`om_background`); a linear term per patch refines it.

    Returns
    -------
    Imprint or None
        None for a blob that is not an imprint (no sharp edge, no dark core).
    """
    p = _OmPatch(img, background, pixel_um, row, col, radius_px)
    if not p.ok:
        return None
    s0 = _OM_S0.copy()
    s0[0] = float(np.clip(1 - p.patch.min(), 0.1, 0.9))
    g0, d0 = p.start(s0)
    s, g, res = _om_joint_fit([p], g0[None], [d0], s0, noise_rel, max_nfev=60)
    g = g[0]
    if s[0] + max(s[1], 0) < 0.08 or s[4] > 0.45 or g[2] < 0.25:
        return None
    return _om_imprint(g, s, res[0], p.patch.size)


def measure_om_array(img: np.ndarray, pixel_um: float, candidates: list, noise_rel: float,
                     background: np.ndarray | None = None, n_joint: int = 8,
                     refine_all: bool = True) -> list:
    """Measure every dark dot of one micrograph with shared darkness, rim and PSF.

    One objective blurs every imprint alike and one material darkens them alike, so the
    interior darkness, its increase to the floor, the rim height and width and the PSF are
    fitted once, jointly on up to ``n_joint`` typical dots (size nearest the median); every
    dot is then fitted with those fixed (centre, diagonal, orientation, linear background):
    this removes the size-versus-darkness ambiguity of a barely resolved dot. Dots that the
    shared model does not describe (residual > 3 x the median and > 3 noise levels, e.g.
    out-of-focus dust) are returned as None. With fewer than three candidates every dot is
    fitted on its own (:func:`measure_om`).

    Parameters
    ----------
    candidates : list of (row, col, radius_px)
        From :func:`detect_dots`.

    Returns
    -------
    list of Imprint or None
        One entry per candidate (same order); ``psf_um`` and ``contrast`` are the shared values.
    """
    if len(candidates) < 3:
        return [measure_om(img, pixel_um, r, c, rad, noise_rel, background) for r, c, rad in candidates]
    radii = np.array([rad for _r, _c, rad in candidates], dtype=float)
    big = radii > 4 * np.median(radii)            # a stain or a shading, not a mark of this array
    patches = [None if b else _OmPatch(img, background, pixel_um, r, c, rad)
               for (r, c, rad), b in zip(candidates, big)]
    ok = [i for i, p in enumerate(patches) if p is not None and p.ok]
    out = [None] * len(candidates)
    if not ok:
        return out
    s = _OM_S0.copy()
    s[0] = float(np.clip(1 - np.median([patches[i].patch.min() for i in ok]), 0.1, 0.9))
    starts = {i: patches[i].start(s) for i in ok}
    rad = np.array([patches[i].r_est for i in ok])
    # typical dots: radius nearest the median, then the darkest
    order = [ok[j] for j in np.argsort(np.abs(rad - np.median(rad)) / np.median(rad))]
    # enough pixels to pin the shared parameters down, few enough to keep the joint fit cheap
    n_joint = int(np.clip(8000 // np.median([patches[i].patch.size for i in ok]), 3, n_joint))
    excluded = set()
    for _round in range(3):
        joint = [i for i in order if i not in excluded][:n_joint]
        s, g, _ = _om_joint_fit([patches[i] for i in joint], np.array([starts[i][0] for i in joint]),
                                [starts[i][1] for i in joint], s, noise_rel)
        for i, gi in zip(joint, g):
            starts[i] = (gi, starts[i][1])
        fits = {}
        for i in ok:
            gi, res = _om_own_fit(patches[i], starts[i][0], starts[i][1], s, noise_rel)
            p = patches[i]
            core = np.hypot(p.dx + p.xc0 - gi[0], p.dy + p.yc0 - gi[1]).ravel() < gi[2] / 2 + 0.3
            fits[i] = (gi, float(np.sqrt(np.mean(res ** 2))), res, float(np.sqrt(np.mean(res[core] ** 2))))
        core = np.array([fits[i][3] for i in ok])
        limit = 3.0 * max(float(np.median(core)), noise_rel)
        bad = {i for i in ok if fits[i][3] > limit}
        if not (bad & set(joint)):
            break
        excluded |= bad
    # final: the shared parameters from every dot the shared model describes, all jointly
    good = [i for i in ok if fits[i][3] <= limit]
    if refine_all and len(good) > len(joint):
        s, g, res = _om_block_fit([patches[i] for i in good], [fits[i][0] for i in good],
                                  [starts[i][1] for i in good], s, noise_rel)
        for i, gi, r in zip(good, g, res):
            fits[i] = (gi, 0.0, r, 0.0)
    if s[0] + max(s[1], 0) < 0.08 or s[4] > 0.45:
        return out
    for i in good:
        gi, _r, res, _c = fits[i]
        if gi[2] < 0.25:
            continue
        out[i] = _om_imprint(gi, s, res, patches[i].patch.size)
    return out


# ----------------------------------------------------------------------------- array

@dataclass(frozen=True)
class ArrayFit:
    """Imprints placed on the nominal array and registered to it (µm, array frame).

    ``row``/``col`` -1: not on the grid. ``dx_um``, ``dy_um``: registered
    measured position minus nominal (NaN when not placed or fewer than 2 placed).
    """

    row: np.ndarray
    col: np.ndarray
    dx_um: np.ndarray
    dy_um: np.ndarray
    rotation_deg: float
    pitch_um: float
    used: np.ndarray


def index_array(xy_um: np.ndarray, rows: int, cols: int, pitch_um: float) -> ArrayFit:
    """Give each imprint its row and column and register the array rigidly to the nominal grid.

    The nominal grid is centred on the origin: column c at x = (c - (cols-1)/2) pitch,
    row r at y = (r - (rows-1)/2) pitch, rows growing with y (image rows).

    Raises
    ------
    MarkcalError
        If the spacing of the imprints does not match ``pitch_um``.
    """
    xy = np.asarray(xy_um, float)
    n = len(xy)
    if n >= 2:
        from scipy.spatial import cKDTree
        dist, _ = cKDTree(xy).query(xy, k=2)
        nn = float(np.median(dist[:, 1]))
        if n >= 4 and abs(nn / pitch_um - 1) > 0.1:
            raise MarkcalError(f"imprint spacing in the image is {nn:.2f} µm but the array spec says "
                               f"pitch_um = {pitch_um:g}")
    if n >= 5 and rows * cols >= 5:
        gi = index_grid(xy, rows, cols, pitch_um, pitch_tolerance=0.1)
        row, col, rot = gi.row.copy(), gi.col.copy(), gi.rotation_deg
    else:
        # few imprints: nearest node after centring on the grid (no rotation)
        rel = (xy - xy.mean(axis=0)) / pitch_um
        k = np.rint(rel + [(cols - 1) / 2, (rows - 1) / 2]).astype(int)
        col, row = k[:, 0].copy(), k[:, 1].copy()
        bad = (col < 0) | (col >= cols) | (row < 0) | (row >= rows)
        col[bad], row[bad] = -1, -1
        rot = 0.0
    # two imprints on one node: keep the first, drop the other
    ids = row * cols + col
    seen = set()
    for i in range(n):
        if row[i] < 0:
            continue
        if ids[i] in seen:
            row[i] = col[i] = -1
        seen.add(ids[i])
    on = row >= 0
    dxy = np.full((n, 2), np.nan)
    used = np.zeros(n, bool)
    if on.sum() >= 2:
        q = np.column_stack([(col[on] - (cols - 1) / 2) * pitch_um, (row[on] - (rows - 1) / 2) * pitch_um])
        tf, u = robust_rigid_fit(xy[on], q, 0.3 * pitch_um)
        dxy[on] = tf.apply(xy[on]) - q
        used[np.flatnonzero(on)[u]] = True
        rot = -tf.angle_deg
    return ArrayFit(row=row, col=col, dx_um=dxy[:, 0], dy_um=dxy[:, 1], rotation_deg=float(rot),
                    pitch_um=float(pitch_um), used=used)


def size_stats(nominal_um: np.ndarray, diameter_um: np.ndarray, hd: np.ndarray, depth_nm: np.ndarray) -> dict:
    """Per-nominal-size statistics (paper Table 1): columns of sizes.csv.

    Standard deviations use n - 1 (NaN for one imprint); ``max_abs_error_um`` is
    the largest |diameter - nominal|.
    """
    nominal_um = np.asarray(nominal_um, float)
    sizes = np.unique(nominal_um[np.isfinite(nominal_um)])
    cols = {k: [] for k in ("nominal_um", "n", "mean_diameter_um", "sd_diameter_um", "max_abs_error_um",
                            "mean_hd", "sd_hd", "mean_depth_nm")}

    def sd(a):
        a = a[np.isfinite(a)]
        return float(np.std(a, ddof=1)) if len(a) > 1 else float("nan")

    def mean(a):
        a = a[np.isfinite(a)]
        return float(np.mean(a)) if len(a) else float("nan")

    for s in sizes:
        m = nominal_um == s
        d = np.asarray(diameter_um, float)[m]
        cols["nominal_um"].append(float(s))
        cols["n"].append(int(m.sum()))
        cols["mean_diameter_um"].append(mean(d))
        cols["sd_diameter_um"].append(sd(d))
        cols["max_abs_error_um"].append(float(np.nanmax(np.abs(d - s))))
        cols["mean_hd"].append(mean(np.asarray(hd, float)[m]))
        cols["sd_hd"].append(sd(np.asarray(hd, float)[m]))
        cols["mean_depth_nm"].append(mean(np.asarray(depth_nm, float)[m]))
    return {k: np.array(v) for k, v in cols.items()}
