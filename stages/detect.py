"""Fiducial detection on the plate raster: paper 004 sec. 2.4, plus sub-pixel refinement.

median filter -> Canny -> morphological closing and hole filling -> circular
Hough transform (coarse centres) -> robust model fit of the double ring to
the raw samples around each candidate (sub-pixel centres).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.feature import peak_local_max
from skimage.transform import hough_circle

from .project import Raster
from .quantile import percentiles
from .threads import map_on_threads, thread_count

#: the fine ring fit uses the samples within this distance of the rings (mm)
RING_BAND_MM = 0.3
#: sample spacing enough for the wide-line capture pass of the ring fits on scan rasters (mm)
CAPTURE_STEP_MM = 0.2


@dataclass(frozen=True)
class EdgeImages:
    """Intermediate images of the detection, for the report."""

    filtered: np.ndarray   # median-filtered intensity, float32
    edges: np.ndarray      # Canny edges, bool
    filled: np.ndarray     # closed and filled, bool


def filter_raster(raster: Raster, median_px: int = 5) -> np.ndarray:
    """Fill empty cells from their neighbours, then median filter.

    A scan grid turned against the raster leaves bands of empty cells (moire);
    each is filled with the mean of the valid cells in its 3 x 3 neighbourhood
    (normalised convolution; 5 x 5 where that is empty too, else the plate's
    median), so rings keep their shape through the median filter.
    """
    if raster.valid is None:
        return cv2.medianBlur(np.ascontiguousarray(raster.intensity, np.float32), median_px)
    valid = raster.valid.astype(np.float32)
    img = np.where(raster.valid, raster.intensity, 0).astype(np.float32)
    out = img.copy()
    todo = ~raster.valid
    for k in (3, 5):
        num = cv2.boxFilter(img, -1, (k, k), normalize=False)
        den = cv2.boxFilter(valid, -1, (k, k), normalize=False)
        fill = todo & (den > 0)
        out[fill] = num[fill] / den[fill]
        todo &= ~fill
    out[todo] = percentiles(img[raster.valid], [50])[0]      # np.median without sorting every cell
    return cv2.medianBlur(out, median_px)


def edge_images(filtered: np.ndarray, close_px: int = 5, sigma_px: float = 1.0) -> EdgeImages:
    """Canny edges of the filtered image, closed and hole-filled (paper Fig. 4, centre)."""
    lo, hi = percentiles(filtered.ravel(), [0.5, 99.5])
    img8 = np.clip((filtered - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    img8 = cv2.GaussianBlur(img8, (0, 0), sigma_px)
    gx = cv2.Sobel(img8, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(img8, cv2.CV_32F, 0, 1)
    mag = np.hypot(gx, gy)
    high = float(percentiles(mag.ravel(), [97])[0])
    edges = cv2.Canny(img8, 0.4 * high, high, L2gradient=True) > 0
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close_px, close_px))
    closed = cv2.morphologyEx(edges.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    # fill holes: flood the background from the border; what it cannot reach is inside
    pad = np.pad(closed, 1)
    flood = pad.copy()
    mask = np.zeros((pad.shape[0] + 2, pad.shape[1] + 2), np.uint8)
    cv2.floodFill(flood, mask, (0, 0), 1)
    filled = (pad | (flood == 0))[1:-1, 1:-1].astype(bool)
    return EdgeImages(filtered=filtered, edges=edges, filled=filled)


def hough_centres(filled: np.ndarray, radius_px: float, min_distance_px: float,
                  max_peaks: int, downsample: int = 2, threshold: float = 0.35) -> np.ndarray:
    """Coarse circle centres by the circular Hough transform (paper Fig. 4, right).

    Runs on the outline of the filled discs at ``downsample`` x coarser pixels.

    Returns
    -------
    ndarray, shape (k, 2)
        (col, row) in full-resolution pixels, strongest first.
    """
    f = downsample
    h, w = filled.shape
    small = cv2.resize(filled.astype(np.uint8), (w // f, h // f), interpolation=cv2.INTER_AREA)
    outline = small ^ ndimage.binary_erosion(small, iterations=1)
    r = radius_px / f
    radii = np.arange(max(2, int(np.floor(r)) - 1), int(np.ceil(r)) + 2)
    acc = hough_circle(outline, radii, normalize=True, full_output=False).max(axis=0)
    peaks = peak_local_max(acc, min_distance=max(1, int(min_distance_px / f)),
                           threshold_abs=threshold, num_peaks=max_peaks, exclude_border=False)
    return (peaks[:, ::-1].astype(float) + 0.5) * f - 0.5


def template_centres(filtered: np.ndarray, radii_px, min_distance_px: float,
                     threshold: float = 0.35) -> np.ndarray:
    """Coarse centres as peaks of the double-ring template's normalised match over the whole image.

    On coarse rasters (0.2 mm cells, 3 samples across the ring gap) Canny
    leaves some rings open, so their discs do not fill and the Hough
    transform misses them; the match sees the ring pattern itself.

    Returns
    -------
    ndarray, shape (k, 2)
        (col, row) pixel centres, strongest first.
    """
    tpl = ring_template(radii_px)
    score = cv2.matchTemplate(np.ascontiguousarray(filtered, np.float32), tpl, cv2.TM_CCOEFF_NORMED)
    peaks = peak_local_max(score, min_distance=max(1, int(min_distance_px)), threshold_abs=threshold,
                           exclude_border=False)
    return peaks[:, ::-1].astype(float) + tpl.shape[0] // 2


def ring_template(radii_px, width_px: float = 1.2) -> np.ndarray:
    """Dark double ring on a zero-mean background, for template matching."""
    half = int(np.ceil(max(radii_px) + 4 * width_px))
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    rho = np.hypot(xx, yy)
    t = -sum(np.exp(-0.5 * ((rho - r) / width_px) ** 2) for r in radii_px)
    return (t - t.mean()).astype(np.float32)


def match_centres(filtered: np.ndarray, colrow: np.ndarray, radii_px, search_px: int = 12) -> np.ndarray:
    """Move coarse centres to the best normalised match of the ring template.

    Hough centres of discs that a scratch or a dropout has deformed can be a
    few tenths of a mm off; the double ring's own pattern pins them to a pixel.

    Returns
    -------
    ndarray, shape (k, 2)
        (col, row) pixel centres.
    """
    tpl = ring_template(radii_px)
    half = tpl.shape[0] // 2
    h, w = filtered.shape
    img = filtered.astype(np.float32)
    out = np.asarray(colrow, float).copy()
    for k, (c, r) in enumerate(np.rint(colrow).astype(int)):
        r0, r1 = r - half - search_px, r + half + search_px + 1
        c0, c1 = c - half - search_px, c + half + search_px + 1
        if r0 < 0 or c0 < 0 or r1 > h or c1 > w:
            continue
        score = cv2.matchTemplate(img[r0:r1, c0:c1], tpl, cv2.TM_CCOEFF_NORMED)
        dr, dc = np.unravel_index(int(np.argmax(score)), score.shape)
        out[k] = (c - search_px + dc, r - search_px + dr)
    return out


@dataclass(frozen=True)
class RingFit:
    """Sub-pixel fits of the double ring, one row per candidate.

    ``uv_mm`` centre in the plate frame; ``radius_scale`` fitted radii over the
    spec radii; ``width_mm`` Gaussian line width; ``contrast`` ring depth in
    intensity units (positive = darker rings); ``rms`` robust residual scale;
    ``n_points`` samples used; ``ok`` passed the quality checks.
    """

    uv_mm: np.ndarray
    radius_scale: np.ndarray
    width_mm: np.ndarray
    contrast: np.ndarray
    rms: np.ndarray
    n_points: np.ndarray
    shift_mm: np.ndarray
    ok: np.ndarray


def _window(raster: Raster, uv0_mm: np.ndarray, reach_mm: float, inner_mm: float, stride: int = 1):
    """Raw samples (u, v, I) of the valid cells (every ``stride``-th) in a square window around each
    centre that lie between ``inner_mm`` and ``reach_mm`` of it, packed at the front of each row, in one
    compiled pass.

    Returns
    -------
    mask, u, v, i : ndarray, shape (k, width)
        Row ``j`` holds its samples in its first ``mask[j].sum()`` entries.
    """
    half = int(np.ceil(reach_mm / raster.pixel_mm)) + 1
    offs = np.arange(-(half // stride) * stride, half + 1, stride)
    cr = np.rint(raster.to_pixel(uv0_mm)).astype(np.int64)
    uv0 = np.ascontiguousarray(uv0_mm, float)
    if raster.u_mm is None:
        empty = np.zeros((0, 0))
        u, v, i, n = _window_kernel(empty, empty, np.zeros((0, 0), bool), raster.intensity, cr, offs, uv0,
                                    float(reach_mm), float(inner_mm), True, raster.pixel_mm, raster.u0_mm,
                                    raster.v0_mm)
    else:
        u, v, i, n = _window_kernel(raster.u_mm, raster.v_mm, raster.valid, raster.intensity, cr, offs, uv0,
                                    float(reach_mm), float(inner_mm), False, raster.pixel_mm, raster.u0_mm,
                                    raster.v0_mm)
    width = max(int(n.max()) if len(n) else 1, 1)
    mask = np.arange(width)[None, :] < n[:, None]
    return mask, u[:, :width], v[:, :width], i[:, :width]


@njit(cache=True, nogil=True)
def _window_kernel(um, vm, valid, inten, cr, offs, uv0, reach, inner, centres, pixel, u0, v0):  # pragma: no cover
    """Samples within (inner, reach) of each centre, row-major over the window; see :func:`_window`."""
    k = len(cr)
    m = len(offs)
    nrow, ncol = inten.shape
    U = np.zeros((k, m * m))
    V = np.zeros((k, m * m))
    Y = np.zeros((k, m * m))
    n = np.zeros(k, np.int64)
    for j in range(k):
        c = 0
        for a in range(m):
            r = cr[j, 1] + offs[a]
            if r < 0 or r >= nrow:
                continue
            for b in range(m):
                q = cr[j, 0] + offs[b]
                if q < 0 or q >= ncol:
                    continue
                if centres:
                    su = (q + 0.5) * pixel + u0
                    sv = (r + 0.5) * pixel + v0
                else:
                    if not valid[r, q]:
                        continue
                    su = um[r, q]
                    sv = vm[r, q]
                rho = np.hypot(su - uv0[j, 0], sv - uv0[j, 1])
                if rho < reach and rho > inner:
                    U[j, c] = su
                    V[j, c] = sv
                    Y[j, c] = inten[r, q]
                    c += 1
        n[j] = c
    return U, V, Y, n


def _masked_median(a, mask):
    """Row-wise median of ``a`` over ``mask`` (0 for empty rows)."""
    srt = np.sort(np.where(mask, a, np.inf), axis=1)
    cnt = mask.sum(axis=1)
    mid = np.take_along_axis(srt, np.maximum(cnt // 2, 0)[:, None], axis=1)[:, 0]
    return np.where(cnt > 0, mid, 0.0)


def _gauss_newton(p, u, v, y, mask, radii, n_iter, free, huber_k=2.0):
    """Batched Levenberg-Marquardt with Huber IRLS weights; ``free`` masks parameters.

    A step is kept only where it lowers the weighted cost; elsewhere the
    damping grows, so no fit runs away. Each row's samples must be packed at
    its front (:func:`_window`). Compiled (:func:`_lm_rows`); the robust scale
    of wide rows (fine images) comes from every ``sub``-th sample.
    """
    sub = max(1, mask.shape[1] // 2048)
    p = np.array(p, float)
    u, v, y = (np.ascontiguousarray(a, float) for a in (u, v, y))
    counts = mask.sum(axis=1).astype(np.int64)
    rad, fr = np.asarray(radii, float), np.asarray(free, float)
    scale = np.empty(len(p))

    def rows(ab):
        a, b = ab
        scale[a:b] = _lm_rows(p[a:b], u[a:b], v[a:b], y[a:b], counts[a:b], rad, int(n_iter), fr, float(huber_k), sub)

    cuts = np.linspace(0, len(p), thread_count(len(p)) + 1).astype(int)     # one block of rows per thread
    map_on_threads(rows, zip(cuts[:-1], cuts[1:]))         # the kernel releases the GIL
    return p, scale


@njit(cache=True, nogil=True)
def _ring_model(p, u, v, radii, jac):  # pragma: no cover - compiled
    """Double-ring model at samples ``u``, ``v`` (one row); fills ``jac`` (n, 8) unless it has no rows.

    b + a * sum_k exp(-(rho - r_k (1 + m))^2 / (2 w^2)) + gu * du + gv * dv, p = (cu, cv, b, a, m, w, gu, gv).
    """
    cu, cv, b, a, m, w, gu, gv = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    n = len(u)
    f = np.empty(n)
    want = jac.shape[0] > 0
    iw = 1.0 / w
    iw2 = iw * iw
    iw3 = iw2 * iw
    for i in range(n):
        du = u[i] - cu
        dv = v[i] - cv
        rho = np.sqrt(du * du + dv * dv) + 1e-12
        g = 0.0
        dg_drho = 0.0
        dg_dm = 0.0
        dg_dw = 0.0
        for r in radii:
            t = rho - r * (1 + m)
            tw = t * iw
            e = np.exp(-0.5 * tw * tw)
            g += e
            if want:
                et = e * t
                dg_drho -= et * iw2
                dg_dm += et * iw2 * r
                dg_dw += et * t * iw3
        f[i] = b + a * g + gu * du + gv * dv
        if want:
            irho = 1.0 / rho
            jac[i, 0] = a * dg_drho * (-du * irho) - gu
            jac[i, 1] = a * dg_drho * (-dv * irho) - gv
            jac[i, 2] = 1.0
            jac[i, 3] = g
            jac[i, 4] = a * dg_dm
            jac[i, 5] = a * dg_dw
            jac[i, 6] = du
            jac[i, 7] = dv
    return f


@njit(cache=True, nogil=True)
def _lm_rows(P, U, V, Y, counts, radii, n_iter, free, huber_k, sub):  # pragma: no cover - compiled
    """Levenberg-Marquardt of every row of ``P`` (k, 8) in place; returns the robust residual scales."""
    k = P.shape[0]
    scales = np.ones(k)
    for row in range(k):
        n = counts[row]
        u = U[row, :n]
        v = V[row, :n]
        y = Y[row, :n]
        p = P[row].copy()
        lam = 1e-3
        scale = 1.0
        jac = np.empty((n, 8))
        jac_new = np.empty((n, 8))
        absr = np.empty(n)
        wts = np.empty(n)
        f = _ring_model(p, u, v, radii, jac)        # the model and Jacobian at p; a kept step brings its own
        for _ in range(n_iter):
            for i in range(n):
                absr[i] = abs(y[i] - f[i])
            ns = (n + sub - 1) // sub
            if ns > 0:
                scale = max(np.partition(absr[::sub], ns // 2)[ns // 2] * 1.4826, 1e-9)
            else:
                scale = 1e-9
            cost = 0.0
            jtj = np.zeros((8, 8))
            jtr = np.zeros(8)
            jf = np.empty(8)
            for i in range(n):
                r = y[i] - f[i]
                wt = min(1.0, huber_k * scale / max(absr[i], 1e-12))
                wts[i] = wt
                cost += wt * r * r
                for a in range(8):
                    jf[a] = jac[i, a] * free[a]
                for a in range(8):
                    ja = jf[a] * wt
                    jtr[a] += ja * r
                    for b in range(a, 8):
                        jtj[a, b] += ja * jf[b]
            for a in range(8):
                for b in range(a):
                    jtj[a, b] = jtj[b, a]
            A = jtj.copy()
            for a in range(8):
                A[a, a] += lam * (jtj[a, a] + 1e-12) + (1.0 - free[a])
            step = np.linalg.solve(A, jtr)
            trial = p + step
            trial[5] = min(max(trial[5], 0.02), 0.4)
            f_new = _ring_model(trial, u, v, radii, jac_new)
            c_new = 0.0
            for i in range(n):
                d = y[i] - f_new[i]
                c_new += wts[i] * d * d
            ok = c_new < cost and abs(trial[4]) < 0.25
            for a in range(8):
                ok = ok and np.isfinite(trial[a])
            if ok:
                p = trial
                f = f_new
                jac, jac_new = jac_new, jac
                lam /= 3
            else:
                lam *= 4
        P[row] = p
        scales[row] = scale
    return scales


def refine_rings(raster: Raster, uv0_mm: np.ndarray, radii_mm, chunk: int = 96,
                 coarse: Raster | None = None) -> RingFit:
    """Sub-pixel double-ring centres by a robust fit to the raw samples.

    The model is b + a * sum_k exp(-(rho - r_k (1 + m))^2 / (2 w^2)) plus a
    linear background, rho the distance from the centre; it is fitted to the
    projected points themselves (their exact in-plane positions, not cell
    centres) with Huber weights, so scratches, dust and dropouts only remove
    samples instead of pulling the centre. A wide-line pass (w fixed at
    0.15 mm) widens the capture range before the free fit.

    Parameters
    ----------
    raster : Raster
        The projected plate.
    uv0_mm : ndarray, shape (k, 2)
        Starting centres, plate frame (mm).
    radii_mm : sequence of float
        Nominal ring radii.
    coarse : Raster, optional
        An area-averaged copy of a fine ``raster`` (images): the wide-line
        capture pass runs on it, the fine fit on ``raster``.
    """
    radii = tuple(float(r) for r in radii_mm)
    # fine images (cells < 0.05 mm): every stride-th cell (~0.06 mm apart, 3 across the 0.2 mm ring gap);
    # the fine fit takes the band of +-RING_BAND_MM around the rings; about 100 rings per batch at 0.1 mm
    # cells, fewer on fine images
    fine = raster.pixel_mm < 0.05
    stride = max(1, int(round(0.06 / raster.pixel_mm))) if fine else 1
    # on scan rasters the wide-line capture pass (a 0.15 mm line) takes a sample every ~0.2 mm; fine images
    # keep theirs (from starts 0.3 mm off, fewer samples missed the rings' fine structure there)
    first, stride1 = ((coarse, 1) if coarse is not None else
                      (raster, stride if fine else max(1, int(CAPTURE_STEP_MM / raster.pixel_mm + 1e-9))))
    cell = raster.pixel_mm * stride
    chunk = max(2, min(chunk, int(chunk * (cell / 0.1) ** 2)))
    reach = max(radii) + 0.5
    inner = max(min(radii) - 0.5, 0.0)
    reach_b, inner_b = max(radii) + RING_BAND_MM, max(min(radii) - RING_BAND_MM, 0.0)
    out = {k: [] for k in ("uv", "m", "w", "a", "rms", "n", "shift")}
    free_a = np.array([1, 1, 1, 1, 1, 0, 1, 1], float)
    free_b = np.ones(8)
    for s in range(0, len(uv0_mm), chunk):
        uv0 = np.asarray(uv0_mm[s:s + chunk], float)
        mask, u, v, y = _window(first, uv0, reach, inner, stride1)
        b0 = _masked_median(y, mask)
        lo = -_masked_median(-np.where(mask, y, -np.inf), mask & (y < b0[:, None]))
        p = np.zeros((len(uv0), 8))
        p[:, 0:2] = uv0
        p[:, 2] = b0
        p[:, 3] = (lo - b0)
        p[:, 5] = 0.15
        p, _ = _gauss_newton(p, u, v, y, mask, radii, 6, free_a)
        # re-centre the window on the new centre before the fine fit
        mask, u, v, y = _window(raster, p[:, :2], reach_b, inner_b, stride)
        p[:, 5] = np.clip(p[:, 5], 0.03, 0.1)
        p, scale = _gauss_newton(p, u, v, y, mask, radii, 7, free_b)
        out["uv"].append(p[:, :2])
        out["m"].append(p[:, 4])
        out["w"].append(p[:, 5])
        out["a"].append(-p[:, 3])
        out["rms"].append(scale)
        out["n"].append(mask.sum(axis=1))
        out["shift"].append(np.hypot(*(p[:, :2] - uv0).T))
    cat = {k: np.concatenate(v) for k, v in out.items()}
    n_full = np.pi * (reach_b ** 2 - inner_b ** 2) / cell ** 2
    ok = ((np.abs(cat["m"]) < 0.06) & (np.abs(cat["a"]) > 3 * cat["rms"] / np.sqrt(10))
          & (cat["shift"] < 1.5) & (cat["n"] > 0.4 * n_full) & np.all(np.isfinite(cat["uv"]), axis=1))
    return RingFit(uv_mm=cat["uv"], radius_scale=1 + cat["m"], width_mm=cat["w"], contrast=cat["a"],
                   rms=cat["rms"], n_points=cat["n"], shift_mm=cat["shift"], ok=ok)


def dedupe(xy: np.ndarray, score: np.ndarray, min_dist) -> np.ndarray:
    """Keep the best-scoring point of each cluster of points closer than ``min_dist``.

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
        Positions (any length unit, the same as ``min_dist``).
    score : ndarray, shape (n,)
        Higher is better (ties: the earlier point).
    min_dist : float or ndarray, shape (n,)
        One distance, or a radius per point: points i and j are one cluster
        when they lie within ``max(r_i, r_j)`` of each other.

    Returns
    -------
    ndarray of int
        Indices of the kept points, ascending.
    """
    xy = np.asarray(xy, float).reshape(-1, 2)
    r = np.broadcast_to(np.asarray(min_dist, float), (len(xy),))
    if len(xy) == 0:
        return np.zeros(0, int)
    order = np.argsort(-np.asarray(score, float), kind="stable")
    tree = cKDTree(xy)
    r_max = float(r.max())
    taken = np.zeros(len(xy), bool)
    keep = []
    for i in order:
        if taken[i]:
            continue
        keep.append(i)
        near = np.asarray(tree.query_ball_point(xy[i], max(r[i], r_max)), int)
        d = np.hypot(*(xy[near] - xy[i]).T)
        taken[near[d <= np.maximum(r[i], r[near])]] = True
    return np.array(sorted(keep), int)
