"""The four-facet model of a Vickers imprint in a micrograph, and its fit (:mod:`.indent_micrograph`).

Four triangular facets (apex + quadrilateral, each edge optionally bowed) and the surroundings, each of
a linear brightness, with dark edge and ridge lines, an edge glow and a pile-up halo: the design matrix
(:func:`.indent_micrograph_kernel.quad_design`) for a trial geometry, the brightnesses in closed form
(variable projection), the residual in noise units, and its analytic derivatives with the exact gradient
of a reweighted (soft-L1) cost; :func:`lm` fits the geometry.
"""
from __future__ import annotations

import copy

import numpy as np

from .indent_geometry import lm_soft_l1
from .indent_micrograph_kernel import quad_design, quad_design_jac

__all__ = ["QuadModel", "block_mean", "noise_level", "lm", "soft_cost", "EDGE_SOFT_PX"]

#: softness (logistic scale, px) of the edges at full resolution: a step blurred by a Gaussian of
#: about 1 px (the optics or beam at usual sampling, plus pixel integration)
EDGE_SOFT_PX = 0.57


def block_mean(img, f):
    """``img`` averaged over blocks of f x f pixels (the rows and columns past the last whole block dropped)."""
    if f == 1:
        return img
    ny, nx = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    return img[:ny, :nx].reshape(ny // f, f, nx // f, f).mean(axis=(1, 3))


def noise_level(img):
    """Pixel noise (grey levels) from the robust spread of differences along the rows."""
    d = np.diff(img, axis=1)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)) + 1e-12


class QuadModel:
    """Four facets (apex + quadrilateral) and the surroundings, each a linear brightness."""

    def __init__(self, img, f, corners, apex, band_px=None):
        self.f = f
        small = block_mean(img, f)
        self.small = small
        c0 = apex
        ext = 1.35 * np.max(np.hypot(*(corners - c0).T)) + 4 * f
        # coordinates of the block centres on the full-res grid
        lo = np.floor((c0 - ext - (f - 1) / 2) / f).astype(int)
        hi = np.ceil((c0 + ext - (f - 1) / 2) / f).astype(int) + 1
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [small.shape[1], small.shape[0]])
        cols, rows = np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1])
        X, Y = np.meshgrid(cols * f + (f - 1) / 2, rows * f + (f - 1) / 2)
        z = small[lo[1]:hi[1], lo[0]:hi[0]]
        keep = np.isfinite(z)
        if band_px is not None:
            d = np.full(X.shape, np.inf)
            for k in range(4):
                for a, b in ((corners[k], corners[(k + 1) % 4]), (apex, corners[k])):
                    d = np.minimum(d, _seg_dist(X, Y, a, b))
            keep &= d < band_px
        self.X, self.Y, self.z = X[keep], Y[keep], z[keep]
        self.xm, self.ym = float(self.X.mean()), float(self.Y.mean())
        self.xs = max(float(np.ptp(self.X)), 1.0)
        self.soft = max(0.45 * f, EDGE_SOFT_PX)
        self.line_px = max(1.2, 0.6 * f)                    # ridge and edge lines: width (full-res px)
        d_est = 2 * np.max(np.hypot(*(corners - apex).T))
        self.halo_px = max(0.08 * d_est, 2.0 * f)            # pile-up halo outside: distance of its crest
        self.noise = noise_level(small) + 1e-12
        self.shape = z.shape
        self._last = None          # (p, design, normal matrix, brightnesses) of the last residual

    def design(self, p):
        """Design matrix (n, 20): facets and surroundings (linear brightness each), edge lines outside
        and inside, edge glow, ridge lines, halo (:func:`.indent_micrograph_kernel.quad_design`)."""
        return quad_design(self.X, self.Y, np.asarray(p, np.float64), self.soft, self.line_px, self.halo_px,
                           self.xm, self.ym, self.xs)

    def residual(self, p):
        """Residuals (noise units) at geometry ``p``, the brightnesses solved in closed form (kept for
        :meth:`jacobian` and :meth:`region_levels` at the same ``p``)."""
        p = np.asarray(p, np.float64)
        a = self.design(p)
        ata = a.T @ a
        normal = ata + 1e-9 * np.trace(ata) / len(ata) * np.eye(len(ata))
        coef = np.linalg.solve(normal, a.T @ self.z)
        self._last = (p.copy(), a, normal, coef)
        return (a @ coef - self.z) / self.noise

    def _at(self, p):
        """(design, normal matrix, brightnesses) at ``p``: those of the last residual when it was taken there."""
        if self._last is None or not np.array_equal(self._last[0], p):
            self.residual(p)
        return self._last[1:]

    def jacobian(self, p, free, wr):
        """Variable-projection derivatives of :meth:`residual` by ``p[free]``, analytic, in one pass over the pixels.

        Returns Kaufman's Jacobian (n, len(free)) (the brightnesses held at their optimum, projected off the
        design's columns) and what it leaves out of the gradient ``jacobian.T @ wr`` of a reweighted cost
        (``wr``: the weighted residuals at ``p``): r.T d(A u)/dp with u = (A.T A)^-1 A.T wr, the brightnesses' own
        response. Subtracted, the gradient is exact; without it, it is exact only for unweighted residuals,
        and the fit stalled where many pixels lie beyond the loss's scale.
        """
        p = np.asarray(p, np.float64)
        a, normal, coef = self._at(p)
        u = np.linalg.solve(normal, a.T @ wr)
        _a, d = quad_design_jac(self.X, self.Y, p, np.vstack([coef, u]), np.asarray(free, np.int64), self.soft,
                                self.line_px, self.halo_px, self.xm, self.ym, self.xs)
        jac = (d[0] - a @ np.linalg.solve(normal, a.T @ d[0])) / self.noise
        return jac, d[1].T @ ((a @ coef - self.z) / self.noise)

    def brightnesses(self, p):
        """The 20 linear coefficients at ``p`` (facets' and surroundings' brightness, lines, glow, halo)."""
        return self._at(np.asarray(p, np.float64))[2]

    def region_levels(self, p):
        """Mean brightness of each facet and of the surroundings (fitted), the residual RMS and the
        height of the glow along the edges (SEM edge effect), all in grey levels."""
        a, _normal, coef = self._at(np.asarray(p, np.float64))
        lv = coef[:15].reshape(5, 3)[:, 0]
        return lv, float(np.sqrt(np.mean((a @ coef - self.z) ** 2))), float(coef[17])

    def restricted(self, keep):
        """The same model on the pixels ``keep`` (bool over :attr:`z`) only."""
        out = copy.copy(self)
        out.X, out.Y, out.z = self.X[keep], self.Y[keep], self.z[keep]
        out._last = None
        return out


def _seg_dist(X, Y, a, b):
    ab = b - a
    t = np.clip(((X - a[0]) * ab[0] + (Y - a[1]) * ab[1]) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.hypot(X - a[0] - t * ab[0], Y - a[1] - t * ab[1])


def lm(model, p, step, n_iter, f_scale=3.0, bow_max=None, free=None):
    """Levenberg-Marquardt with a soft-L1 loss (:func:`indent_geometry.lm_soft_l1`) on ``model``'s residual and
    analytic Jacobian (:meth:`QuadModel.jacobian`): a dense 10 x 10 or 14 x 14 system per iteration. It stops
    when no step exceeds a tenth of ``step`` (px). ``free``: the indices of ``p`` fitted (the others held; None:
    all); with ``bow_max`` (px) the four bows (``p[10:14]``) are kept within +-bow_max."""
    p = np.asarray(p, np.float64)
    idx = np.arange(len(p)) if free is None else np.asarray(free)
    lo = hi = None
    if bow_max is not None:
        lo, hi = np.full(len(p), -np.inf), np.full(len(p), np.inf)
        lo[10:14], hi[10:14] = -bow_max, bow_max
        lo, hi = lo[idx], hi[idx]

    def whole(q):
        out = p.copy()
        out[idx] = q
        return out

    q = lm_soft_l1(lambda q: model.residual(whole(q)), p[idx], n_iter, f_scale=f_scale, step=step, lo=lo, hi=hi,
                   vp_jac=lambda q, wr: model.jacobian(whole(q), idx, wr))
    return whole(q)


def soft_cost(r, f_scale=3.0):
    """Soft-L1 cost of residuals (noise units), as :func:`lm` minimises it (up to a constant)."""
    return float(np.sum(np.sqrt(1 + (r / f_scale) ** 2)))
