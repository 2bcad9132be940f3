"""How well can an OM image of an indentation array determine the diagonals at all? (issue 20)

Usage: python benchmarks/om_information.py [--seeds 5300-5303] [--sizes 1,2,3] [--optics airy,gauss]

For each hard OM render (``fixtures/indent_micrograph``: one-sided shading, dark edge and ridge lines,
pile-up halo, vignetting, texture, noise; 5 x 5 at 8 µm, 480 x 480 at 0.1 µm) this:

1. measures the image as the flow does (``measure_om_array``) and keeps the final joint fit's dots;
2. starts the same joint fit again from the truth (each dot's true diagonal, the render's crease
   darkness 0.35) and lets it converge: the model's optimum next to the truth;
3. there, computes the Cramér-Rao bound of the image's mean diagonal: the Gauss-Newton covariance
   sigma^2 (J^T J)^-1 of every dot's own and the shared parameters, with the image's measured noise
   level. It counts the noise as white, so texture and model error are not in it: no unbiased
   estimator using this model does better.
4. repeats the bound with groups of shared parameters taken as known (PSF; crease darkness; the
   halo's height and width; ...), which shows which unknown the diagonal cannot be told apart from.

Prints one row per image. Figures are in docs/indents.md ("The information in a 1 µm image").
"""
from __future__ import annotations

import argparse

import numpy as np

from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
from markcal.stages import indent_om as om
from markcal.stages import indent_om_array as om_array
from markcal.stages.indent_om_fit import _NS_PLAIN, _om_block_fit

#: the render's crease (edge and ridge line) darkness (``MicrographOptions.lines``)
RENDER_CREASE = 0.35
#: shared parameters (``indent_om_fit._OM_SHARED`` order) taken as known, one group per column
KNOWN = {"psf": [4], "crease": [5], "halo": [2, 3], "halo+crease": [2, 3, 5]}


def _final_fit(img, pixel_um):
    """The flow's measurement; returns the patches, own and shared parameters of its last joint fit."""
    bg = om.om_background(img, pixel_um)
    cands, sig = om.detect_dots(img, pixel_um, background=bg)
    kept = {}

    def spy(patches, g, d0, s, noise_rel, n_iter=20, pin=None, fixed=()):
        out = _om_block_fit(patches, g, d0, s, noise_rel, n_iter=n_iter, pin=pin, fixed=fixed)
        if len(patches) > 1 and pin is None:
            kept["fit"] = (patches, out[1], d0, out[0])
        return out

    om_array._om_block_fit = spy
    try:
        om_array.measure_om_array(img, pixel_um, cands, sig, bg)
    finally:
        om_array._om_block_fit = _om_block_fit
    return kept["fit"], sig


def _bound(patches, g, s, sigma, known=()):
    """sd (µm) of the mean diagonal over the dots: Cramér-Rao bound with ``known`` shared parameters held."""
    k, ns = len(patches), len(s)
    n = 7 * k + ns
    h = np.zeros((n, n))
    for i, p in enumerate(patches):
        _m, jm = p.jac(g[i], s)
        cols = list(range(7 * i, 7 * i + 7)) + list(range(7 * k, n))
        h[np.ix_(cols, cols)] += jm.T @ jm
    free = [j for j in range(n) if j - 7 * k not in known]
    cov = np.linalg.pinv(h[np.ix_(free, free)]) * sigma ** 2
    di = [free.index(7 * i + 2) for i in range(k)]
    w = np.full(k, 1.0 / k)
    return float(np.sqrt(w @ cov[np.ix_(di, di)] @ w))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="5300-5303", help="first-last render seed")
    ap.add_argument("--sizes", default="1,2,3", help="nominal diagonals (µm)")
    ap.add_argument("--optics", default="airy,gauss", help="airy (NA 0.9, the issue's) and/or gauss (1 px)")
    a = ap.parse_args(argv)
    s0, s1 = (int(v) for v in a.seeds.split("-"))
    print("Cramér-Rao bound of each image's mean diagonal (nm, white noise of the measured level), at the model's "
          "optimum next to the truth; then with shared parameters known")
    print(f"{'optics':6s} {'d_um':>4s} {'seed':>5s} {'noise':>6s} {'fit_err':>7s} {'bound':>6s} "
          + " ".join(f"{'known ' + name:>18s}" for name in KNOWN))
    for optics in a.optics.split(","):
        for d_um in (float(v) for v in a.sizes.split(",")):
            for seed in range(s0, s1 + 1):
                r = render_micrograph(seed, MicrographOptions(rows=480, cols=480, grid=(5, 5, 8.0), d_um=d_um,
                                                              na=0.9 if optics == "airy" else None))
                img = r.data.astype(float)
                (patches, g, d0, s), sigma = _final_fit(img, r.pixel_um)
                truth = r.truth["imprints"]
                g = np.array(g, float)
                match = [min(truth, key=lambda t: np.hypot(t["x_um"] - gi[0], t["y_um"] - gi[1])) for gi in g]
                fit_err = 1000 * np.mean([gi[2] - t["d_um"] for gi, t in zip(g, match)])
                g[:, 2] = [t["d_um"] for t in match]
                if len(s) > _NS_PLAIN:                   # extended model: start from the render's crease darkness
                    s = s.copy()
                    s[_NS_PLAIN] = RENDER_CREASE
                    s, g, _r = _om_block_fit(patches, g, d0, s, sigma, n_iter=10, pin=(_NS_PLAIN, RENDER_CREASE))
                s, g, _r = _om_block_fit(patches, g, d0, s, sigma, n_iter=30)
                row = [1000 * _bound(patches, g, s, sigma, known) for known in KNOWN.values()]
                print(f"{optics:6s} {d_um:4.1f} {seed:5d} {sigma:6.3f} {fit_err:+7.1f} "
                      f"{1000 * _bound(patches, g, s, sigma):6.1f} " + " ".join(f"{v:18.1f}" for v in row), flush=True)


if __name__ == "__main__":
    main()
