"""OM/SEM image model of a Vickers imprint: illumination, dark-dot detection and the diamond fit.

Each dark dot is fitted with an image model: a square (diamond) footprint of
diagonal ``d`` and orientation, darker towards the floor, with a bright rim,
blurred by an Airy PSF, over a linear background. Darkness, rim and PSF are
shared by the dots of one micrograph (:func:`measure_om_array`: a joint fit,
block-arrow normal equations); each dot's fit gives the sub-pixel centre and the
apparent diameter.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy import fft as sfft
from scipy.special import j1

from .indent_geometry import Imprint, diagonals as _diagonals
from .indent_om_fit import (_NS_PLAIN, _OM_SHARED, _OM_SHARED_STEP, CREASE_W_UM, _dev_shared,
                            _om_block_fit, _on_patches, _om_joint_fit, _om_own_fit,
                            soft_l1_cost)
from .indent_om_kernel import om_dev
from .quantile import median_filter

__all__ = ["om_background", "detect_dots", "measure_om", "measure_om_array", "airy_sigma_um", "airy_radius_um",
           "RESOLUTION_RADII", "om_halo_crease"]


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
            got = _KERNEL_CACHE[key] = [_box_fft(_airy(psf, self.sub), self.ss, shape), h, shape, None]
        if psf_step is not None and got[3] is None:
            got[3] = (_box_fft(_airy(psf + psf_step, self.sub, h), self.ss, shape) - got[0]) / psf_step
        return got

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
        spec = sfft.rfft2(dev, shape)
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

    All model parameters (own and shared, see :func:`measure_om_array`) are fitted to
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


def measure_om_array(img: np.ndarray, pixel_um: float, candidates: list, noise_rel: float,
                     background: np.ndarray | None = None, n_joint: int = 8,
                     refine_all: bool = True, psf_um: float | None = None, held: dict | None = None) -> list:
    """Measure every dark dot of one micrograph with shared darkness, rim and PSF.

    One objective blurs every imprint alike and one material darkens them alike, so the
    interior darkness, its increase to the floor, the rim height and width and the PSF are
    fitted once, jointly on up to ``n_joint`` typical dots (size nearest the median); every
    dot is then fitted with those fixed (centre, diagonal, orientation, linear background):
    this removes the size-versus-darkness ambiguity of a barely resolved dot. Dots that the
    shared model does not describe (residual > 3 x the median and > 3 noise levels, e.g.
    out-of-focus dust) are returned as None. With fewer than three candidates every dot is
    fitted on its own (:func:`measure_om`). When the Bayesian information criterion on the typical
    dots prefers it (:func:`_choose_model`), the shared model is extended: dark crease lines centred
    on the edges and the ridges (one darkness for both; they absorb a fraction of the local light)
    and facets shaded from light on one side (three contrasts between the quadrants).

    Parameters
    ----------
    candidates : list of (row, col, radius_px)
        From :func:`detect_dots`.
    psf_um : float, optional
        Known optics (:func:`airy_sigma_um`): the PSF is held at this Gaussian-equivalent sigma (µm)
        instead of fitted.
    held : dict, optional
        The halo and crease of :func:`om_halo_crease` (from larger imprints of the same material under the
        same objective): held instead of fitted, which the imprints near the resolution limit cannot do.

    Returns
    -------
    list of Imprint or None
        One entry per candidate (same order); ``psf_um`` and ``contrast`` are the shared values.
    """
    if len(candidates) < 3:
        return [measure_om(img, pixel_um, r, c, rad, noise_rel, background, psf_um) for r, c, rad in candidates]
    return _om_array_pass(img, pixel_um, candidates, noise_rel, background, n_joint, refine_all, psf_um, held)[0]


#: what :func:`om_halo_crease` passes on: shared-parameter indices of the halo (rim height, rim width in
#: half-diagonals) and of the crease darkness (extended model only)
_HELD = {"rim": 2, "rim_w": 3, "crease": 5}


def om_halo_crease(img: np.ndarray, pixel_um: float, candidates: list, noise_rel: float,
                   background: np.ndarray | None = None) -> dict:
    """The halo (rim height and width) and crease darkness of an OM array, to hold on smaller imprints.

    Near the resolution limit (:data:`RESOLUTION_RADII`) a bright halo beside the edge and a dark line on it
    cannot be told from a larger or smaller imprint (docs/indents.md, "The information in a 1 µm image").
    On larger imprints of the same material, indenter and objective they can: the halo scales with the
    imprint (the rim width is in half-diagonals) and the crease line keeps its width.

    Returns
    -------
    dict
        ``rim``, ``rim_w`` and, when the extended model describes the image, ``crease``.

    Raises
    ------
    ValueError
        Fewer than three dots measured, or imprints themselves near the resolution limit.
    """
    if len(candidates) < 3:
        raise ValueError(f"{len(candidates)} dot(s) found: at least 3 are needed")
    out, s = _om_array_pass(img, pixel_um, candidates, noise_rel, background, 8, True)
    d = [m.diameter_um for m in out if m is not None]
    if len(d) < 3:
        raise ValueError("fewer than 3 imprints measured")
    r = airy_radius_um(float(s[_PSF]))
    if np.median(d) < RESOLUTION_RADII * r:
        raise ValueError(f"its imprints ({np.median(d):.2f} µm) are near the resolution limit too (under "
                         f"{RESOLUTION_RADII:g} x {r:.2f} µm): use larger ones")
    return {k: float(s[j]) for k, j in _HELD.items() if j < len(s)}


#: starting crease darkness of the extended model's joint fit on the typical dots
CREASE_START = 0.25
#: crease darknesses of the profile over every dot (:func:`_om_array_pass`)
CREASE_PROFILE = (0.0, 0.15, 0.3, 0.45, 0.6)
#: block-fit steps at the first profile value and at each following one (warm-started)
CREASE_STEPS = (4, 2)


def _extended(s_plain):
    """Extended-model shared parameters that draw the same dots as the plain ones ``s_plain``.

    Plain interior 1 - dark0 - dark1 (1 - rho); extended (1 - dark0) (1 - dark1' (1 - rho)), no
    creases, no shading.
    """
    s = np.concatenate([s_plain, np.zeros(len(_OM_SHARED) - _NS_PLAIN)])
    s[1] = s_plain[1] / max(1.0 - s_plain[0], 1e-6)
    return s


def _choose_model(patches, g0, d0, s_plain, noise_rel, fixed=(), crease=None):
    """Plain or extended shared model for the typical dots.

    The plain model is fitted, then the extended one (creases, one-sided shading) when the Bayesian
    information criterion
    prefers it: ``N ln(SSR_plain / SSR_ext) > k ln N`` (N pixels, k = 4 extra parameters), SSR_ext
    from one Gauss-Newton step of the extended model from the plain solution (cheap: no fit is
    made for images the plain model describes).

    With ``crease`` (a held crease darkness, index 5 in ``fixed``) the extended model is used without asking.

    Returns
    -------
    s : ndarray (shared parameters of the chosen model), g : ndarray (k, 7), extended : bool
    """
    s_p, g_p, res_p = _om_joint_fit(patches, g0, d0, s_plain, noise_rel, fixed=fixed)
    g_p = _one_branch(g_p)                      # the plain model does not see the branch
    n = sum(r.size for r in res_p)

    def ext_fit(line0, max_nfev):
        s0 = _extended(s_p)
        s0[_NS_PLAIN] = line0
        s_e, g_e, res_e = _om_joint_fit(patches, g_p, d0, s0, noise_rel, max_nfev=max_nfev, fixed=fixed)
        return sum(float(np.sum(r * r)) for r in res_e), s_e, g_e

    # one Gauss-Newton step of the extended model from the plain solution (all parameters free):
    # how much do its extra terms lower the residual?
    if crease is not None:
        _ssr, s_e, g_e = ext_fit(crease, 40)
        return s_e, g_e, True
    ns, k = len(_OM_SHARED), len(patches)
    s_lin = _extended(s_p)
    jm = np.zeros((n, ns + 7 * k))
    rr = np.zeros(n)
    o = 0
    for i, (p, gi) in enumerate(zip(patches, g_p)):
        m, jp = p.jac(gi, s_lin)
        jm[o:o + m.size, 7 * i:7 * i + 7] = jp[:, :7]
        jm[o:o + m.size, 7 * k:] = jp[:, 7:]
        rr[o:o + m.size] = p.patch.ravel() - m
        o += m.size
    jm[:, [7 * k + j for j in fixed if j < ns]] = 0.0
    col = np.maximum(np.sqrt(np.sum(jm ** 2, axis=0)), 1e-30)
    step = np.linalg.lstsq(jm / col, rr, rcond=1e-9)[0] / col
    ssr_lin = float(np.sum((rr - jm @ step) ** 2))
    ssr_p = float(np.sum(rr ** 2))
    n_extra = ns - _NS_PLAIN
    gain = n * np.log(ssr_p / max(ssr_lin, 1e-300)) / (n_extra * np.log(n))
    if gain <= 1.0:
        return s_p, g_p, False
    _ssr, s_e, g_e = ext_fit(CREASE_START, 40)
    return s_e, g_e, True


def _one_branch(g, ref=None):
    """Own parameters ``g`` (k, 7) with each orientation turned by a multiple of 90 deg to within 45 deg of the
    common one: the same square footprint, but facet i of every dot then faces the same way, as the shared
    one-sided shading (quadrants of the dot's frame) assumes. Found on a render (seed 6007, 1 µm): 6 of 25 dots
    had converged 86 deg off the others, their centres pulled 27-37 nm towards the darker facet.

    The common orientation is that of the rows ``ref`` of ``g`` (default: all): their mean on the 90-degree
    circle (the argument of the mean of exp(4 i theta), / 4; a plain median of angles on two branches is not
    on either), put on the branch of the first of them.
    """
    g = np.array(g, dtype=float)
    q = np.pi / 2
    th = g[:, 3] if ref is None else g[ref, 3]
    common = float(np.angle(np.mean(np.exp(4j * th)))) / 4
    common += q * np.round((th[0] - common) / q)
    g[:, 3] = common + np.mod(g[:, 3] - common + q / 2, q) - q / 2
    return g


#: restart of the shared fit (:func:`_unless_rim_under_resolution`): the dots at this fraction of their size
RESTART_SIZE = 0.7


def _unless_rim_under_resolution(patches, g, d0, s, res, noise_rel, fixed):
    """The joint fit of every dot again from smaller dots, when its rim is narrower than half the blur.

    Near the resolution limit the fit can stop in a second minimum: dots up to 1.5 x their size, lighter
    inside, with a bright rim narrower than the PSF just outside them (found on an independent render of
    1 um imprints with pits between them: diagonals +550 nm on average, rim 0.05 half-diagonals). Restarted
    from dots at :data:`RESTART_SIZE` of that size, the shared parameters at their defaults, the fit reached a
    lower cost there (12.9 against 14.4). The lower of the two costs is kept.
    """
    d_typ = float(np.median([gi[2] for gi in g]))
    if s[3] * d_typ / 2 >= 0.5 * s[4] or _HELD["rim_w"] in fixed:
        return s, g, res
    s0 = _OM_S0.copy() if len(s) == _NS_PLAIN else _extended(_OM_S0)
    s0[4] = s[4]
    if len(s) > _NS_PLAIN:
        s0[_NS_PLAIN] = CREASE_START
    s0[list(fixed)] = s[list(fixed)]
    g0 = [np.r_[gi[:2], gi[2] * RESTART_SIZE, gi[3:]] for gi in g]
    s1, g1, res1 = _om_block_fit(patches, g0, d0, s0, noise_rel, fixed=fixed)
    if soft_l1_cost(res1, noise_rel) < soft_l1_cost(res, noise_rel):
        return s1, g1, res1
    return s, g, res


def _om_array_pass(img, pixel_um, candidates, noise_rel, background, n_joint, refine_all, psf_um=None,
                   held=None):
    """:func:`measure_om_array` (the shared model chosen by :func:`_choose_model` on the typical dots);
    ``held``: :func:`om_halo_crease` values held.

    Returns the imprints (or None) and the shared parameters.
    """
    radii = np.array([rad for _r, _c, rad in candidates], dtype=float)
    big = radii > 4 * np.median(radii)            # a stain or a shading, not a mark of this array
    patches = [None if b else _OmPatch(img, background, pixel_um, r, c, rad)
               for (r, c, rad), b in zip(candidates, big)]
    ok = [i for i, p in enumerate(patches) if p is not None and p.ok]
    out = [None] * len(candidates)
    if not ok:
        return out, None
    s = _OM_S0.copy()
    s[0] = float(np.clip(1 - np.median([patches[i].patch.min() for i in ok]), 0.1, 0.9))
    fixed = _fix_psf(s, psf_um)
    held = held or {}
    for name, j in _HELD.items():
        if name in held:
            fixed += (j,)
            if j < len(s):
                s[j] = held[name]
    starts = {}

    def start(j):
        starts[ok[j]] = patches[ok[j]].start(s)

    _on_patches(start, len(ok))
    rad = np.array([patches[i].r_est for i in ok])
    # typical dots: radius nearest the median, then the darkest
    order = [ok[j] for j in np.argsort(np.abs(rad - np.median(rad)) / np.median(rad))]
    # enough pixels to pin the shared parameters down, few enough to keep the joint fit cheap
    n_joint = int(np.clip(8000 // np.median([patches[i].patch.size for i in ok]), 3, n_joint))
    joint = order[:n_joint]
    s, g, extended_fitted = _choose_model([patches[i] for i in joint], np.array([starts[i][0] for i in joint]),
                                          [starts[i][1] for i in joint], s, noise_rel, fixed, held.get("crease"))
    for i, gi in zip(joint, g):
        starts[i] = (gi, starts[i][1])
    # every dot's frame on the typical dots' branch, so the shared shading and creases fall on the same facets
    g_all = _one_branch([starts[i][0] for i in order], ref=slice(0, n_joint))
    for i, gi in zip(order, g_all):
        starts[i] = (gi, starts[i][1])
    excluded = set()
    for _round in range(3):
        joint = [i for i in order if i not in excluded][:n_joint]
        # the extended model was just fitted on these dots (the plain one is only a start there): no refit
        if not (_round == 0 and extended_fitted):
            s, g, _ = _om_joint_fit([patches[i] for i in joint], np.array([starts[i][0] for i in joint]),
                                    [starts[i][1] for i in joint], s, noise_rel, fixed=fixed)
            for i, gi in zip(joint, g):
                starts[i] = (gi, starts[i][1])
        fits = {}

        def own(i, g0, into):
            gi, res = _om_own_fit(patches[i], g0, starts[i][1], s, noise_rel)
            p = patches[i]
            core = np.hypot(p.dx + p.xc0 - gi[0], p.dy + p.yc0 - gi[1]).ravel() < gi[2] / 2 + 0.3
            into[i] = (gi, float(np.sqrt(np.mean(res ** 2))), res, float(np.sqrt(np.mean(res[core] ** 2))))

        _on_patches(lambda j: own(ok[j], starts[ok[j]][0], fits), len(ok))
        core = np.array([fits[i][3] for i in ok])
        limit = 3.0 * max(float(np.median(core)), noise_rel)
        bad = sorted(i for i in ok if fits[i][3] > limit)
        if bad and len(bad) < len(ok):
            # a dot the model misses may be dust, or a dot whose start (its candidate's size, one of four
            # orientations) led its own fit astray (seen on an independent render: 10 of 25 1 um dots at
            # 1.5x their size). Again from the typical dot's size, orientation and background: kept if
            # the model then describes it.
            typ = np.median([fits[i][0] for i in ok if fits[i][3] <= limit], axis=0)
            again = {}
            _on_patches(lambda j: own(bad[j], np.r_[starts[bad[j]][0][:2], typ[2:5], 0.0, 0.0], again), len(bad))
            fits.update({i: f for i, f in again.items() if f[3] <= limit})
        bad = {i for i in ok if fits[i][3] > limit}
        if not (bad & set(joint)):
            break
        excluded |= bad
    # final: the shared parameters from every dot the shared model describes, all jointly
    good = [i for i in ok if fits[i][3] <= limit]
    if refine_all and len(good) > len(joint):
        bp, bg0, bd = [patches[i] for i in good], [fits[i][0] for i in good], [starts[i][1] for i in good]
        if len(s) > _NS_PLAIN and np.median([p.ss for p in bp]) > 1 and _NS_PLAIN not in fixed:
            # on small dots (< 16 px) the crease darkness is weakly determined (a line on the edge
            # looks like a wider dot, the ridges are short): profile it over every dot, a few steps
            # at each of a few values (each value started from the previous one's fit), then free it
            best = None
            sp, gp = s, bg0
            for k, line in enumerate(CREASE_PROFILE):
                sp, gp, rp = _om_block_fit(bp, gp, bd, np.where(np.arange(len(s)) == _NS_PLAIN, line, sp), noise_rel,
                                           n_iter=CREASE_STEPS[k > 0], pin=(_NS_PLAIN, line), fixed=fixed)
                c = soft_l1_cost(rp, noise_rel)
                if best is None or c < best[0]:
                    best = (c, sp, gp)
            s, bg0 = best[1], list(best[2])
        s, g, res = _om_block_fit(bp, bg0, bd, s, noise_rel, fixed=fixed)
        s, g, res = _unless_rim_under_resolution(bp, g, bd, s, res, noise_rel, fixed)
        for i, gi, r in zip(good, g, res):
            fits[i] = (gi, 0.0, r, 0.0)
    if s[0] + max(s[1], 0) < 0.08 or s[4] > 0.45:
        return out, s
    for i in good:
        gi, _r, res, _c = fits[i]
        if gi[2] < 0.25:
            continue
        out[i] = _om_imprint(gi, s, res, patches[i].patch.size)
    return out, s
