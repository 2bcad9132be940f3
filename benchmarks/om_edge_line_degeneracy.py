"""Can a bright-field image tell a thin dark line on an imprint's edge from the edge moved? (issue 20)

Usage: python benchmarks/om_edge_line_degeneracy.py

One Vickers footprint (a diamond, reflectance 0.5 inside, 1 outside) with a Gaussian dark line on its
edge (FWHM 60 nm, taking a fraction ``depth`` of the local light on both sides), imaged through the
in-focus Airy PSF of NA 0.9 at 550 nm and averaged over 0.1 µm pixels, 1 % white noise. For 1, 2 and
3 µm diagonals and line depths 0.3 and 0.8 it prints:

1. the diagonal a line-free model fits (facet and surface levels free) and that fit's chi-square;
2. the Cramér-Rao sigma of d with the line's depth free, the correlation of d with the depth, and the
   sigma with the depth known.

Independent of markcal's own model and renderers. Figures are in docs/indents.md ("Speed (session 11)").
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize, signal, special

PIXEL_UM, SUPER, FIELD_PX, NOISE = 0.1, 10, 40, 0.01
FINE_UM = PIXEL_UM / SUPER
LINE_SIGMA_UM = 0.06 / 2.355


def airy_psf(na=0.9, wavelength_um=0.55, half_um=2.0):
    """Normalised in-focus Airy intensity on the fine grid."""
    r = np.arange(-half_um, half_um + FINE_UM / 2, FINE_UM)
    x, y = np.meshgrid(r, r)
    v = 2 * math.pi * na * np.hypot(x, y) / wavelength_um
    v[v == 0] = 1e-9
    k = (2 * special.j1(v) / v) ** 2
    return k / k.sum()


PSF = airy_psf()
_XS = (np.arange(FIELD_PX * SUPER) + 0.5) * FINE_UM - FIELD_PX * PIXEL_UM / 2
X, Y = np.meshgrid(_XS, _XS)


def image(d_um, depth, facet=0.5):
    """Pixel image of the footprint of diagonal ``d_um`` with an edge line of ``depth``."""
    rho = (np.abs(X) + np.abs(Y)) / (d_um / 2)
    refl = np.where(rho < 1, facet, 1.0)
    dist = np.abs(rho - 1) * (d_um / 2) / math.sqrt(2)
    refl = refl * (1 - depth * np.exp(-0.5 * (dist / LINE_SIGMA_UM) ** 2))
    blurred = signal.fftconvolve(refl, PSF, mode="same")
    return blurred.reshape(FIELD_PX, SUPER, FIELD_PX, SUPER).mean(axis=(1, 3))


def line_free_fit(target, d_um):
    """Best diagonal of a line-free footprint (facet level and overall scale linear) and its chi-square."""
    def chi2(dp):
        b0, b1 = image(dp, 0.0, facet=0.0), image(dp, 0.0, facet=1.0)
        m = np.stack([b0.ravel(), (b1 - b0).ravel()], 1)
        coef = np.linalg.lstsq(m, target.ravel(), rcond=None)[0]
        return float(np.sum((target.ravel() - m @ coef) ** 2)) / NOISE ** 2
    r = optimize.minimize_scalar(chi2, bounds=(d_um - 0.3, d_um + 0.4), method="bounded", options={"xatol": 1e-4})
    return r.x, chi2(r.x)


def cramer_rao(d_um, depth):
    """sigma(d) with the depth free, corr(d, depth), sigma(d) with the depth known (µm)."""
    p0 = np.array([d_um, depth, 0.5])
    h = 1e-3

    def f(p):
        return image(*p).ravel()
    cols = [(f(p0 + h * e) - f(p0 - h * e)) / (2 * h) for e in np.eye(3)]
    jac = np.column_stack(cols + [f(p0)])                          # + overall scale
    cov = np.linalg.inv(jac.T @ jac) * NOISE ** 2
    known = jac[:, [0, 2, 3]]
    cov_k = np.linalg.inv(known.T @ known) * NOISE ** 2
    return math.sqrt(cov[0, 0]), cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]), math.sqrt(cov_k[0, 0])


def main():
    print(f"Airy NA 0.9, 550 nm; {PIXEL_UM} µm pixels; edge line FWHM 60 nm; noise {NOISE:.0%}")
    print("d_um depth  line-free d error_nm  chi2   sigma_d free_nm  corr(d,depth)  sigma_d known_nm")
    for d in (1.0, 2.0, 3.0):
        for depth in (0.3, 0.8):
            dp, c2 = line_free_fit(image(d, depth), d)
            s_free, corr, s_known = cramer_rao(d, depth)
            print(f"{d:4.1f} {depth:5.1f} {1000 * (dp - d):+20.0f} {c2:6.1f} {1000 * s_free:16.1f} "
                  f"{corr:14.3f} {1000 * s_known:17.1f}")


if __name__ == "__main__":
    main()
