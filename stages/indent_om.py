"""OM/SEM image model of a Vickers imprint: illumination, dark-dot detection and the diamond model.

Each dark dot is fitted with an image model: a square (diamond) footprint of
diagonal ``d`` and orientation, darker towards the floor, with a bright rim,
blurred by an Airy PSF, over a linear background (:class:`_OmPatch`). A dot on its
own: :func:`measure_om`. The dots of one micrograph share darkness, rim and PSF:
:mod:`.indent_om_array`.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy import fft as sfft
from scipy.special import j1

from .indent_geometry import Imprint, diagonals as _diagonals
from .indent_om_fit import _NS_PLAIN, _OM_SHARED_STEP, CREASE_W_UM, _dev_shared, _om_joint_fit
from .indent_om_kernel import om_dev
from .quantile import median_filter

__all__ = ["om_background", "detect_dots", "measure_om", "airy_sigma_um", "airy_radius_um", "RESOLUTION_RADII"]


def om_background(img: np.ndarray, pixel_um: float, window_um: float = 6.0) -> np.ndarray:
    """Smooth illumination of a micrograph, the dots and their rims left out.

    Median over ``window_um`` on a coarser grid (4x, or coarser so the window spans about
    15 of its cells; dots and rims cover a small part of it), Gaussian smoothing, then
    bilinear interpolation back to every pixel (pixel centres aligned).
    """
    f = max(4, int(round(window_um / (15 * pixel_um))))
    ny, nx = img.shape
    py, px_ = (-ny) % f, (-nx) % f
    padded = np.pad(img.astype(np.float64), ((0, py), (0, px_)), mode="edge")
    small = padded.reshape(padded.shape[0] // f, f, padded.shape[1] // f, f).mean(axis=(1, 3))
    size = max(5, int(round(window_um / (pixel_um * f))) | 1)
    bg = median_filter(small, size)              # = ndimage.median_filter(mode="nearest"), 4x faster
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
#: fine cells between the patch and its periodic copy in the circular PSF convolution, by sub-pixel
#: factor (the model's tails reach the border of a large dot's patch, not a small one's); measured on
#: 1 and 3 µm dots: the Jacobian differs from a linear convolution's by < 2e-5 of its largest value
_WRAP_PAD = {1: 8, 2: 2}


def _airy(psf_um, sub_um, h=None):
    """Airy (diffraction-limited, in focus) intensity PSF whose Gaussian-equivalent sigma is ``psf_um``.

    sigma ~ 0.21 lambda / NA, so v = 2 pi NA r / lambda = 2 pi 0.21 r / sigma; sampled at
    ``sub_um`` out to 1.8 lambda / NA (or ``h`` samples), normalised to sum 1. Cached (read-only arrays).
    """
    key = (float(psf_um), float(sub_um), h)
    k = _AIRY_CACHE.get(key)
    if k is None:
        if len(_AIRY_CACHE) > 64:
            _AIRY_CACHE.clear()
        k = _AIRY_CACHE[key] = _airy_kernel(psf_um, sub_um, h)
        k.flags.writeable = False
    return k


def _airy_kernel(psf_um, sub_um, h=None):
    lam_na = psf_um / 0.21
    if h is None:
        h = max(2, int(np.ceil(1.8 * lam_na / sub_um)))
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1] * sub_um
    v = np.maximum(2 * np.pi * np.hypot(xx, yy) / lam_na, 1e-9)
    k = (2 * j1(v) / v) ** 2
    return k / k.sum()


_KERNEL_CACHE: dict = {}
# the blur's FFTs in single precision: 3.5 x faster per transform than double; the model is a reflectance
# near 1 fitted to grey values with 1 % noise, where float32's 1e-7 is far below anything that counts
_FFT_REAL, _FFT_COMPLEX = np.float32, np.complex64


def _box_fft(k, ss, shape):
    """Transform of the PSF ``k`` folded with the ss x ss pixel box, for a circular convolution on a
    grid of ``shape`` a few fine cells larger than the patch: the kernel is rolled so that pixel i's
    mean sits at fine index ss i. What wraps round comes from the far border of the patch, where the
    model is flat (reflectance - 1 ~ 0), so this is the linear convolution at about a third of its cost.
    """
    k2 = np.zeros(shape)
    for a in range(ss):
        for b in range(ss):
            k2[a:a + k.shape[0], b:b + k.shape[1]] += k / ss ** 2
    o = k.shape[0] // 2 + ss - 1                # linear convolution: pixel mean at h + ss - 1 + ss i
    return sfft.rfft2(np.roll(k2, (-o, -o), axis=(0, 1)))


class _OmPatch:
    """One dot's patch (grey values / illumination) and its image model.

    The model is evaluated on a 2x finer grid: relative reflectance (background 1) of a
    diamond of diagonal ``d``, darker to the floor, with a bright rim ``rim t^2 exp(2 (1 - t))``,
    t = (rho - 1) / rim_w, rho = (|u| + |v|) / (d / 2), anti-aliased edge (extended model: each
    facet's own brightness, darker to the floor by a fraction of it, and dark crease lines centred on
    the edges and ridges that take a fraction of the local light); blurred by an Airy PSF
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

    def _kernel_fft(self, psf, psf_step=None):
        """Transform of the PSF folded with the pixel box, its half-width and the FFT shape; with
        ``psf_step`` also the forward difference of the transform by the PSF width (same support).
        Shared by the patches of one fine-grid shape (cached)."""
        h = _airy(psf, self.sub).shape[0] // 2
        shape = tuple(sfft.next_fast_len(max(n + _WRAP_PAD[self.ss], 2 * h + self.ss + 1), real=True) for n in self.xf.shape)
        key = (psf, self.sub, self.ss, shape)
        got = _KERNEL_CACHE.get(key)
        if got is None:
            if len(_KERNEL_CACHE) > 64:
                _KERNEL_CACHE.clear()
            kf = _box_fft(_airy(psf, self.sub), self.ss, shape)
            got = _KERNEL_CACHE[key] = [kf.astype(_FFT_COMPLEX), h, shape, None, kf]
        if psf_step is not None and got[3] is None:
            got[3] = ((_box_fft(_airy(psf + psf_step, self.sub, h), self.ss, shape) - got[4]) / psf_step
                      ).astype(_FFT_COMPLEX)
        return got[:4]

    def dev(self, g, s):
        """Reflectance - 1 on the fine grid."""
        return self.dev_grad(g, s, False)

    def dev_grad(self, g, s, grad=True, shared=True):
        """Reflectance - 1 on the fine grid and (``grad``) its analytic derivatives: by the centre,
        diagonal and orientation, then (``shared``) by the shared parameters that change it
        (:func:`._dev_shared` order). The model is linear in all of those but the rim width.
        Computed by :func:`.indent_om_kernel.om_dev` (one fused pass)."""
        ext = len(s) > _NS_PLAIN
        n_grad = 0 if not grad else (4 if not shared else (12 if ext else 8))
        dev = np.empty(self.xf.shape)
        grads = np.empty((n_grad,) + self.xf.shape)
        om_dev(self.xf, self.yf, np.asarray(g, dtype=np.float64)[:4], np.asarray(s, dtype=np.float64), self.sub,
               CREASE_W_UM, ext, n_grad, dev, grads)
        return (dev, grads) if grad else dev

    def blur(self, dev, psf, psf_step=None):
        """PSF blur and pixel averaging of one or a stack of fine-grid arrays.

        With ``psf_step`` a stack gets one more layer: the forward difference of its first layer's
        blur by the PSF width.
        """
        kf, h, shape, dk = self._kernel_fft(float(psf), psf_step)
        spec = sfft.rfft2(dev.astype(_FFT_REAL, copy=False), shape)
        if psf_step is None:
            spec *= kf
        else:
            spec = np.concatenate([spec * kf, (spec[0] * dk)[None]])
        full = sfft.irfft2(spec, shape)
        ny, nx = self.patch.shape
        ss = self.ss
        return full[..., 0:ss * ny:ss, 0:ss * nx:ss]

    def lin(self, g):
        return g[4] + g[5] * self.dx + g[6] * self.dy

    def model(self, g, s):
        """Model grey values / illumination for own parameters ``g`` and shared ``s``."""
        return (1.0 + self.blur(self.dev(g, s), s[4])) * self.lin(g)

    def jac(self, g, s, shared=True):
        """Model and analytic Jacobian (pixels x (7 own [+ shared]) columns): the derivative images are
        blurred in one batched FFT (the blur is linear); the PSF column is the forward difference of the
        kernel."""
        dev0, grads = self.dev_grad(g, s, shared=shared)
        pix = self.blur(np.concatenate([dev0[None], grads]), s[4],
                        psf_step=_OM_SHARED_STEP[4] if shared else None)
        lin = self.lin(g)
        base = 1.0 + pix[0]
        m = base * lin
        cols = [pix[1 + j] * lin for j in range(4)]
        cols += [base, base * self.dx, base * self.dy]
        if shared:
            sh = {j: pix[5 + n] * lin for n, j in enumerate(_dev_shared(len(s)))}
            sh[4] = pix[-1] * lin
            cols += [sh[j] for j in range(len(s))]
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
#: shared-parameter index of the PSF width
_PSF = 4


def airy_sigma_um(na: float, wavelength_um: float = 0.55) -> float:
    """Gaussian-equivalent sigma (µm) of the in-focus Airy PSF of an objective: 0.21 lambda / NA.

    The OM model's PSF parameter, so the model draws exactly that objective's Airy pattern.
    """
    return 0.21 * wavelength_um / na


#: imprints smaller than this many Airy radii of the optics are near the resolution limit: there a dark line
#: on the edge or a bright halo beside it cannot be told from a larger or smaller imprint (docs/indents.md,
#: "The information in a 1 µm image"). Measured bounds of an image's mean diagonal: 1 µm under NA 0.9
#: (2.7 radii) 16-44 nm, under a 0.1 µm Gaussian (3.4 radii) 12-23 nm; 2 µm under NA 0.9 (5.4 radii) 3.5-6 nm
RESOLUTION_RADII = 4.0


def airy_radius_um(psf_um: float) -> float:
    """Radius of the Airy pattern's first dark ring, 0.61 lambda / NA, of a PSF whose Gaussian-equivalent
    sigma is ``psf_um`` (:func:`airy_sigma_um`): the optics' resolution (Rayleigh)."""
    return psf_um * 0.61 / 0.21


def _fix_psf(s, psf_um):
    """Hold the PSF at ``psf_um`` (set in ``s``): the ``fixed`` indices for the solvers."""
    if psf_um is None:
        return ()
    s[_PSF] = psf_um
    return (_PSF,)


def measure_om(img: np.ndarray, pixel_um: float, row: float, col: float, radius_px: float,
               noise_rel: float, background: np.ndarray | None = None,
               psf_um: float | None = None) -> Imprint | None:
    """Measure one dark dot on its own: sub-pixel centre and apparent diameter by an image-model fit.

    All model parameters (own and shared, see :func:`.indent_om_array.measure_om_array`) are fitted to
    this dot alone; with several dots in one micrograph ``measure_om_array`` is more
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
    psf_um : float, optional
        The PSF's Gaussian-equivalent sigma (µm) when the optics are known (:func:`airy_sigma_um`):
        held instead of fitted.

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
    fixed = _fix_psf(s0, psf_um)
    g0, d0 = p.start(s0)
    s, g, res = _om_joint_fit([p], g0[None], [d0], s0, noise_rel, max_nfev=60, fixed=fixed)
    g = g[0]
    if s[0] + max(s[1], 0) < 0.08 or s[4] > 0.45 or g[2] < 0.25:
        return None
    return _om_imprint(g, s, res[0], p.patch.size)
