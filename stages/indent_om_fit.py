"""Least-squares fits of the OM dot model (:mod:`.indent_om`): its parameter tables and three solvers.

- :func:`_om_joint_fit`: shared and own parameters of a few dots together (dense, scipy);
- :func:`_om_block_fit`: the same for every dot of a micrograph (block-arrow normal equations);
- :func:`_om_typical_fit`: the typical dots' fit: the first by :func:`_om_joint_fit`, the extended model's by
  :func:`_om_block_fit`;
- :func:`_om_own_fit`: one dot's own parameters, the shared ones fixed.

The solvers only call the patch's ``model``, ``jac`` and ``own_bounds``.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from .threads import map_on_threads

#: OM model parameters. Per dot: centre (µm), diagonal d (µm), orientation (rad), background
#: level, gradient x, y (1/µm). Shared by the dots of one micrograph (one objective, one
#: material): interior darkness at the edge and its increase to the floor, rim height and width
#: (in units of the half-diagonal), PSF (Gaussian-equivalent sigma, µm); the extended model adds
#: the darkness of the crease lines on the edges and ridges and the facets' shading from light on
#: one side (three contrasts between the quadrants of the dot's own frame: +-u, +-v, their product).
_OM_OWN = ("cx", "cy", "d", "theta", "bg", "gx", "gy")
_OM_SHARED = ("dark0", "dark1", "rim", "rim_w", "psf", "line", "shade_u", "shade_v", "shade_uv")
_OM_SHARED_LO = np.array([0.0, -1.0, -0.5, 0.03, 0.04, 0.0, -1.0, -1.0, -1.0])
_OM_SHARED_HI = np.array([1.0, 1.0, 2.0, 0.8, 0.6, 0.95, 1.0, 1.0, 1.0])
#: forward-difference steps of the shared parameters (only the PSF's is used: the other columns are analytic)
_OM_SHARED_STEP = np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-5, 1e-4, 1e-4, 1e-4, 1e-4])
#: Gaussian sigma (µm) of the dark crease lines: under the resolution, so their integrated darkness
#: (darkness x width) is what the fit sees
CREASE_W_UM = 0.06
#: the plain model uses the first five shared parameters; the extended one (lines, one-sided
#: shading) all of them
_NS_PLAIN = 5


def _dev_shared(ns):
    """Shared parameters that change the fine-grid reflectance: all but the PSF (index 4)."""
    return [j for j in range(ns) if j != 4]


def _om_joint_fit(patches, g0, d0, s0, noise_rel, max_nfev=40, fixed=()):
    """Fit the shared parameters and every patch's own parameters jointly (robust loss).

    The Jacobian is built block by block: a patch depends only on its own seven parameters
    and the shared ones. Shared parameters whose indices are in ``fixed`` keep their ``s0`` values.
    """
    k = len(patches)
    s_all = np.array(s0, dtype=float)
    free = np.array([j for j in range(len(s0)) if j not in fixed], dtype=int)
    ns = len(free)
    sizes = [p.patch.size for p in patches]
    offs = np.concatenate([[0], np.cumsum(sizes)])
    target = np.concatenate([p.patch.ravel() for p in patches])
    lo = [_OM_SHARED_LO[free]]
    hi = [_OM_SHARED_HI[free]]
    for p, d in zip(patches, d0):
        a, b = p.own_bounds(d)
        lo.append(a)
        hi.append(b)
    lo, hi = np.concatenate(lo), np.concatenate(hi)
    x0 = np.clip(np.concatenate([s_all[free], np.ravel(g0)]), lo + 1e-9, hi - 1e-9)

    def split(x):
        s = s_all.copy()
        s[free] = x[:ns]
        return s, x[ns:].reshape(k, 7)

    def fun(x):
        s, g = split(x)
        out = np.empty(offs[-1])

        def model(i):
            out[offs[i]:offs[i + 1]] = patches[i].model(g[i], s).ravel()

        _on_patches(model, k)
        return out - target

    def jac(x):
        s, g = split(x)
        jm = np.zeros((offs[-1], x.size))

        def block(i):
            _m, jp = patches[i].jac(g[i], s)
            rows = slice(offs[i], offs[i + 1])
            jm[rows, ns + 7 * i:ns + 7 + 7 * i] = jp[:, :7]
            jm[rows, :ns] = jp[:, 7 + free]

        _on_patches(block, k)
        return jm

    scale = np.concatenate([np.array([0.05, 0.05, 0.05, 0.05, 0.02] + [0.05] * (len(s0) - 5))[free], np.tile([0.02, 0.02, 0.05, 0.05, 0.01, 0.001, 0.001], k)])
    r = least_squares(fun, x0, jac=jac, bounds=(lo, hi), loss="soft_l1", f_scale=max(3 * noise_rel, 0.005),
                      x_scale=scale, max_nfev=max_nfev)
    s, g = split(r.x)
    res = [r.fun[offs[i]:offs[i + 1]] for i in range(k)]
    return s, g, res


#: damping increases the typical dots' block fit tries on a step before it stops (x4 four times, then x10).
#: The default five (up to 256 x) stopped it 4 % above scipy's cost on a 1 µm independent render at
#: 0.065 µm pixels (1.035 against 0.997). The block fits of every dot keep five: with twelve there too, the
#: 1 µm speed seeds 5700-5711 took a median 1.80 s instead of 1.26 s
TYPICAL_TRIES = 12


def _om_typical_fit(patches, g0, d0, s0, noise_rel, max_nfev=40, fixed=()):
    """Shared and own parameters of the typical dots: the plain model by scipy's trust region
    (:func:`_om_joint_fit`), the extended one by the block Levenberg-Marquardt (:func:`_om_block_fit`).

    The extended fit starts from a converged plain one. From there the block solver, which needs no SVD of
    the dense Jacobian (about 7600 x 44 for five 1 µm dots at 0.1 µm), reaches scipy's cost to 0.05 % on
    3 x 3 hard 1 µm renders 5000-5011 but one (5007: another minimum, 0.4 % higher), in a fifth to a half
    of the time. Near the resolution limit the minimum found depends on the path either way; the flow's
    1 µm results moved both ways with this change (see docs/indents.md, "Speed (session 11)"). The plain fit
    starts from the candidates' crude sizes and orientations, where the two paths part more: it stays on
    scipy's.
    """
    if len(s0) > _NS_PLAIN:
        return _om_block_fit(patches, g0, d0, s0, noise_rel, n_iter=max_nfev, fixed=fixed, tries=TYPICAL_TRIES)
    return _om_joint_fit(patches, g0, d0, s0, noise_rel, max_nfev=max_nfev, fixed=fixed)


def soft_l1_cost(res, noise_rel):
    """The solvers' robust cost of residual arrays: soft-L1 with the scale 3 noise levels (at least 0.005)."""
    f = max(3 * noise_rel, 0.005)
    return float(sum(np.sum(2 * f * f * (np.sqrt(1 + (r / f) ** 2) - 1)) for r in res))


def _on_patches(fn, n):
    """``fn(i)`` for every patch index, the patches split in two halves on two threads when there are
    several (the model's kernel and the FFTs release the GIL)."""
    if n < 4:
        for i in range(n):
            fn(i)
        return
    map_on_threads(lambda part: [fn(i) for i in part], [range(0, n, 2), range(1, n, 2)])   # here on one thread


def _om_block_fit(patches, g, d0, s, noise_rel, n_iter=20, pin=None, fixed=(), tries=5):
    """Joint robust fit of many patches: shared and own parameters (Levenberg-Marquardt).

    The normal equations have a block-arrow structure (each patch couples its seven own
    parameters only with the shared ones), solved through the Schur complement of the
    shared block, so the cost grows linearly with the number of dots. Soft-L1 loss by
    iteratively reweighted least squares; bounds by clipping.

    ``pin`` = (index, value) holds one shared parameter at a value (by clipping each step); those in
    ``fixed`` keep theirs (left out of the solve). ``tries``: damping increases tried on a step before
    the fit stops (x4, after the fourth x10).

    Returns
    -------
    s : ndarray (shared,), g : ndarray (k, 7), res : list of residual arrays
    """
    f = max(3 * noise_rel, 0.005)
    bounds = [p.own_bounds(d) for p, d in zip(patches, d0)]
    lo_g = np.array([b[0] for b in bounds]) + 1e-9
    hi_g = np.array([b[1] for b in bounds]) - 1e-9
    g = np.clip(np.array(g, dtype=float), lo_g, hi_g)
    ns = len(s)
    s_lo, s_hi = _OM_SHARED_LO[:ns] + 1e-9, _OM_SHARED_HI[:ns] - 1e-9
    s = np.array(s, dtype=float)
    for j in fixed:
        if j < ns:                               # the extended model's indices are ignored by the plain one
            s_lo[j] = s_hi[j] = s[j]
    free = np.array([j for j in range(ns) if s_lo[j] < s_hi[j]], dtype=int)
    if pin is not None:
        # held by clipping: the other parameters take the step of the unconstrained solve
        s_lo[pin[0]] = s_hi[pin[0]] = pin[1]
    s = np.clip(s, s_lo, s_hi)
    nf = len(free)
    targets = [p.patch.ravel() for p in patches]

    lam = 1e-3
    res = None
    for _it in range(n_iter):
        terms = [None] * len(patches)

        def normal_terms(i):
            # patch i's residual and its blocks of the weighted normal equations
            m, jm = patches[i].jac(g[i], s, shared=nf > 0)
            r = m - targets[i]
            w = 1.0 / np.sqrt(1.0 + (r / f) ** 2)
            a, b = jm[:, :7], jm[:, 7 + free] if nf else np.zeros((m.size, 0))
            aw, bw = a * w[:, None], b * w[:, None]
            terms[i] = (r, a.T @ aw, aw.T @ b, aw.T @ r, b.T @ bw, bw.T @ r)

        _on_patches(normal_terms, len(patches))
        res = [t[0] for t in terms]
        U, W, ga = [t[1] for t in terms], [t[2] for t in terms], [t[3] for t in terms]
        V = sum((t[4] for t in terms), np.zeros((nf, nf)))
        gb = sum((t[5] for t in terms), np.zeros(nf))
        cost = soft_l1_cost(res, noise_rel)
        improved = False
        for _try in range(tries):
            uinv = [np.linalg.inv(u + lam * np.diag(np.diag(u)) + 1e-12 * np.eye(7)) for u in U]
            S = V + lam * np.diag(np.diag(V)) + 1e-12 * np.eye(nf)
            rhs = gb.copy()
            for ui, wi, gi in zip(uinv, W, ga):
                S -= wi.T @ ui @ wi
                rhs -= wi.T @ ui @ gi
            ds = -np.linalg.solve(S, rhs) if nf else np.zeros(0)
            dg = np.array([-ui @ (gi + wi @ ds) for ui, wi, gi in zip(uinv, W, ga)])
            s_new = s.copy()
            s_new[free] = np.clip(s[free] + ds, s_lo[free], s_hi[free])
            g_new = np.clip(g + dg, lo_g, hi_g)
            res_new = [None] * len(patches)

            def residual(i):
                res_new[i] = patches[i].model(g_new[i], s_new).ravel() - targets[i]

            _on_patches(residual, len(patches))
            c_new = soft_l1_cost(res_new, noise_rel)
            if c_new < cost:
                improved = True
                break
            lam *= 4.0 if _try < 4 else 10.0
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


def _om_own_fit(p, g0, d0, s, noise_rel, max_iter=20):
    """Fit one patch's own parameters with the shared ones fixed (:func:`_om_block_fit` on one patch)."""
    s_, g, res = _om_block_fit([p], [g0], [d0], s, noise_rel, n_iter=max_iter, fixed=range(len(s)))
    return g[0], res[0]
