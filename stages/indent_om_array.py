"""OM micrographs of indentation arrays: the dots of one micrograph fitted with shared optics and material.

One objective blurs every imprint alike and one material darkens them alike, so the darkness, rim, PSF (and,
in the extended model, the crease lines and the one-sided facet shading) are shared by the dots of a micrograph:
fitted jointly on a few typical dots, then every dot on its own with them fixed, then everything jointly over
every dot (block-arrow normal equations, :mod:`.indent_om_fit`). The dot's image model is
:class:`.indent_om._OmPatch`.
"""
from __future__ import annotations

import numpy as np

from .indent_om import (_OM_S0, _PSF, RESOLUTION_RADII, _fix_psf, _om_imprint, _OmPatch, airy_radius_um,
                        measure_om)
from .indent_om_fit import (_NS_PLAIN, _OM_SHARED, _om_block_fit, _om_joint_fit, _om_own_fit, _om_typical_fit,
                            _on_patches, soft_l1_cost)

__all__ = ["measure_om_array", "om_halo_crease"]


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
        s_e, g_e, res_e = _om_typical_fit(patches, g_p, d0, s0, noise_rel, max_nfev=max_nfev, fixed=fixed)
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
            s, g, _ = _om_typical_fit([patches[i] for i in joint], np.array([starts[i][0] for i in joint]),
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
