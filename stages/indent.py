"""Detection and model-based measurement of Vickers micro-indentations (paper 000 sec. 4).

Positions are in the image frame: x = column index x pixel size, y = row index
x pixel size (pixel centres, µm, y down the rows). Angles are measured from +x
towards +y.

AFM: each imprint is the blend of four facet planes. The planes are fitted to
the heights (first one by one, then jointly as ``M = tau log sum exp(P_k / tau)``,
which also fits the blunted floor and rounded ridges; robust loss). Adjacent
facets intersected with the local original surface give the four corners; the
circle through the corners gives the centre and the equivalent diameter (paper
Fig. 6b); the minimum of ``M`` gives the floor and the depth.

OM: each dark dot is fitted with an image model: a square (diamond) footprint
of diagonal ``d`` and orientation, darker towards the floor, with a bright rim,
blurred by an Airy PSF, over a linear background; the fit gives the sub-pixel
centre and the apparent diameter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.signal import fftconvolve
from scipy.special import j1

from .errors import MarkcalError
from .register import index_grid, robust_rigid_fit

__all__ = ["circle_fit", "Imprint", "detect_pits", "measure_afm", "detect_dots", "measure_om",
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


def _fit_facets_joint(x, y, z, coef0, tau0, sigma):
    """Joint robust fit of M = tau LSE(P_k / tau) to (x, y, z); coef (4, 3) for z = a x + b y + c."""
    a = np.column_stack([x, y, np.ones_like(x)])

    def unpack(p):
        return p[:12].reshape(4, 3), np.exp(p[12])

    def fun(p):
        c, tau = unpack(p)
        planes = c @ a.T
        m, _ = _lse(planes, tau)
        return m - z

    def jac(p):
        c, tau = unpack(p)
        planes = c @ a.T
        m, w = _lse(planes, tau)
        j = np.empty((len(z), 13))
        for k in range(4):
            j[:, 3 * k:3 * k + 3] = w[k][:, None] * a
        j[:, 12] = m - (w * planes).sum(axis=0)
        return j

    p0 = np.concatenate([coef0.ravel(), [np.log(max(tau0, 1e-3))]])
    lo = np.full(13, -np.inf)
    hi = np.full(13, np.inf)
    lo[12], hi[12] = np.log(1e-3), np.log(1e3)
    p0[12] = np.clip(p0[12], lo[12] + 1e-6, hi[12] - 1e-6)
    r = least_squares(fun, p0, jac=jac, bounds=(lo, hi), loss="soft_l1", f_scale=max(3 * sigma, 0.3),
                      x_scale="jac", max_nfev=60)
    c, tau = unpack(r.x)
    return c, float(tau), r.fun


def _floor(coef, tau, start=None):
    """Minimum of the convex M = tau LSE(P_k / tau): damped Newton from the facets' apex.

    Returns (x, y, M) in the planes' coordinates.
    """
    g_k = coef[:, :2]

    def val(p):
        planes = coef @ np.array([p[0], p[1], 1.0])
        m = planes.max()
        e = np.exp((planes - m) / tau)
        return m + tau * np.log(e.sum()), e / e.sum()

    # apex: least-squares point where the four planes meet
    a = np.column_stack([g_k, -np.ones(4)])
    apex, *_ = np.linalg.lstsq(a, -coef[:, 2], rcond=None)
    p = apex[:2].copy()
    f, w = val(p)
    for _ in range(60):
        g = w @ g_k
        h = (g_k.T * w) @ g_k / tau - np.outer(g, g) / tau
        h += (1e-9 + 1e-6 * np.trace(h)) * np.eye(2)
        step = np.linalg.solve(h, g)
        t = 1.0
        while t > 1e-6:
            q = p - t * step
            fq, wq = val(q)
            if fq <= f - 1e-4 * t * (g @ step) or fq <= f:
                break
            t *= 0.5
        else:
            break
        if abs(f - fq) < 1e-12 and t * np.hypot(*step) < 1e-9:
            p, f, w = q, fq, wq
            break
        p, f, w = q, fq, wq
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
        coef, tau, res = _fit_facets_joint(x[fit_px], y[fit_px], zr[fit_px], coef, tau, noise_nm)
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
        fx, fy, fm = _floor(coef, tau, (ccx, ccy))
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


def detect_dots(img: np.ndarray, pixel_um: float, min_diameter_um: float = 0.4) -> tuple:
    """Dark compact dots in a micrograph.

    Returns
    -------
    list of (row, col, radius_px), float
        Candidates (centroid of the dark area, px) and the relative noise level.
    """
    rel = img / om_background(img, pixel_um) - 1.0
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


def _airy(psf_um, sub_um):
    """Airy (diffraction-limited, in focus) intensity PSF whose Gaussian-equivalent sigma is ``psf_um``.

    sigma ~ 0.21 lambda / NA, so v = 2 pi NA r / lambda = 2 pi 0.21 r / sigma.
    """
    lam_na = psf_um / 0.21
    h = max(2, int(np.ceil(1.3 * lam_na / sub_um)))
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1] * sub_um
    v = np.maximum(2 * np.pi * np.hypot(xx, yy) / lam_na, 1e-9)
    k = (2 * j1(v) / v) ** 2
    return k / k.sum()


def _om_model(p, xf, yf, ss, sub_um):
    """Relative dot image (background 1): dark diamond darker to the floor, bright rim outside.

    Evaluated on an ``ss``-times finer grid (``xf``, ``yf`` µm) with an
    anti-aliased edge, blurred by an Airy PSF (Gaussian-equivalent sigma ``psf`` µm) and averaged
    over each pixel. The rim is ``rim t^2 exp(2 (1 - t))``, t = (rho - 1) / rim_w,
    rho = (|u| + |v|) / (d / 2) (1 at the edge).
    """
    cx, cy, d, th, dark0, dark1, rim, rim_w, psf = p
    ct, st = np.cos(th), np.sin(th)
    u = (xf - cx) * ct + (yf - cy) * st
    v = -(xf - cx) * st + (yf - cy) * ct
    half = max(d / 2, 1e-3)
    rho = (np.abs(u) + np.abs(v)) / half
    inside = np.clip(0.5 - (rho - 1) * half / np.sqrt(2) / sub_um, 0.0, 1.0)
    t = np.maximum(rho - 1, 0) / max(rim_w, 1e-3)
    refl = 1.0 - inside * (dark0 + dark1 * np.clip(1 - rho, 0, 1)) + rim * t * t * np.exp(2 * (1 - t))
    refl = fftconvolve(np.pad(refl - 1.0, 0), _airy(psf, sub_um), mode="same") + 1.0
    ny, nx = refl.shape[0] // ss, refl.shape[1] // ss
    return refl.reshape(ny, ss, nx, ss).mean(axis=(1, 3))


def measure_om(img: np.ndarray, pixel_um: float, row: float, col: float, radius_px: float,
               noise_rel: float, background: np.ndarray | None = None) -> Imprint | None:
    """Measure one dark dot: sub-pixel centre and apparent diameter by an image-model fit.

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
    ny, nx = img.shape
    r_est = max(radius_px, 2.0)
    half = int(np.ceil(r_est * 1.5 + 0.6 / pixel_um + 2))
    r0, r1 = max(0, int(round(row)) - half), min(ny, int(round(row)) + half + 1)
    c0, c1 = max(0, int(round(col)) - half), min(nx, int(round(col)) + half + 1)
    patch = img[r0:r1, c0:c1].astype(np.float64)
    if patch.shape[0] < 7 or patch.shape[1] < 7:
        return None
    if background is not None:
        patch = patch / background[r0:r1, c0:c1]
    else:
        patch = patch / np.median(np.concatenate([patch[0], patch[-1], patch[:, 0], patch[:, -1]]))
    yy, xx = np.mgrid[r0:r1, c0:c1] * pixel_um
    xc0, yc0 = xx.mean(), yy.mean()
    ss = 2
    sub = pixel_um / ss
    fr = (np.arange((r1 - r0) * ss) - (ss - 1) / 2) / ss + r0
    fc = (np.arange((c1 - c0) * ss) - (ss - 1) / 2) / ss + c0
    yf, xf = np.meshgrid(fr * pixel_um, fc * pixel_um, indexing="ij")

    # q: cx, cy, d, theta, bg, gx, gy, dark0, dark1, rim, rim_w, psf
    def resid(q):
        m = _om_model((*q[:4], *q[7:12]), xf, yf, ss, sub)
        return (m * (q[4] + q[5] * (xx - xc0) + q[6] * (yy - yc0)) - patch).ravel()

    d0 = 2 * r_est * pixel_um
    dark = float(np.clip(1 - patch.min(), 0.1, 0.9))
    lo = np.array([col * pixel_um - 2 * d0, row * pixel_um - 2 * d0, 0.2 * d0, -np.inf, 0.5, -np.inf, -np.inf,
                   0.0, -1.0, -0.5, 0.03, 0.04])
    hi = np.array([col * pixel_um + 2 * d0, row * pixel_um + 2 * d0, 3 * d0, np.inf, 2.0, np.inf, np.inf,
                   1.0, 1.0, 2.0, 0.8, 0.6])
    best = None
    for th in np.radians([0.0, 22.5, 45.0, 67.5]):
        q0 = np.array([col * pixel_um, row * pixel_um, d0, th, 1.0, 0.0, 0.0, dark, 0.0, 0.1, 0.2, 0.15])
        c = float(np.sum(resid(q0) ** 2))
        if best is None or c < best[0]:
            best = (c, q0)
    q0 = np.clip(best[1], lo + 1e-9, hi - 1e-9)
    r = least_squares(resid, q0, bounds=(lo, hi), loss="soft_l1", f_scale=max(3 * noise_rel, 0.005),
                      x_scale=np.array([0.02, 0.02, 0.05, 0.05, 0.01, 0.001, 0.001, 0.05, 0.05, 0.05, 0.05,
                                        0.02]), max_nfev=60)
    q = r.x
    cx, cy, d, th = q[:4]
    dark0, dark1, psf = q[7], q[8], q[11]
    # an imprint has a dark core with a sharp edge; soft dust blobs do not
    if dark0 + max(dark1, 0) < 0.08 or psf > 0.45 or d < 0.25:
        return None
    ct, st = np.cos(th), np.sin(th)
    corners = np.array([[d / 2 * ct, d / 2 * st], [-d / 2 * st, d / 2 * ct],
                        [-d / 2 * ct, -d / 2 * st], [d / 2 * st, -d / 2 * ct]]) + [cx, cy]
    d1, d2, orient = _diagonals(corners)
    nan = float("nan")
    return Imprint(x_um=float(cx), y_um=float(cy), diameter_um=float(d), diag1_um=float(d1), diag2_um=float(d2),
                   depth_nm=nan, hd_ratio=nan, orientation_deg=float(orient), pileup_nm=nan, corners_um=corners,
                   fit_rms=float(np.sqrt(np.mean(r.fun ** 2))), n_pixels=int(patch.size),
                   psf_um=float(psf),
                   contrast=float(dark0))


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
