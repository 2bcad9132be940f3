"""OM arrays with known optics (``objective_na``) and the analytic Jacobian of the OM dot model."""
from __future__ import annotations


import numpy as np
import pytest

from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
from markcal.pipeline.flows.indents import IndentsOptions, indents_options, measure_file, read_array_spec
from markcal.stages import indent_om
from markcal.stages.errors import MarkcalError
from markcal.stages.indent_om_fit import _OM_SHARED_STEP
from om_arrays import errors_nm, write_hard_array


def _hard_airy(tmp_path, seed, d_um, objective_na):
    path, spec, truth = write_hard_array(tmp_path, seed, d_um)
    f = measure_file(path, read_array_spec(spec), IndentsOptions(kind="om", objective_na=objective_na))
    return errors_nm(f.table, truth), f


def test_objective_na_holds_the_psf_at_the_airy_of_that_na(tmp_path):
    """A hard OM array (Airy NA 0.9 optics, lines, one-sided shading), 2 µm, measured with the objective's
    NA given: the PSF is the Airy of NA 0.9 at 550 nm, not fitted. Measured (seed 5002): d +16..+35 nm,
    centre RMS 5.3 nm (PSF fitted: +15..+34 nm, 5.3 nm)."""
    e, f = _hard_airy(tmp_path, 5002, 2.0, 0.9)
    assert len(e) == 9
    assert all(m.psf_um == pytest.approx(0.21 * 0.55 / 0.9, rel=1e-12) for m in f.imprints)
    assert np.all(np.abs(e[:, 2]) <= 55.0)
    assert np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)) <= 9.0


def test_objective_na_out_of_range_is_refused():
    o = {"kind": "", "pixel_size_um": 0.0, "channel": "", "load_mN": 0.0, "objective_na": 2.0}
    with pytest.raises(MarkcalError, match="objective_na must be in"):
        indents_options(o)
    assert indents_options({**o, "objective_na": 0.0}).objective_na is None


@pytest.mark.parametrize("n_shared", [5, 9])
def test_om_jacobian_is_the_model_derivative(n_shared, monkeypatch):
    """The analytic Jacobian (own and shared columns) against central differences of the model.

    The fits blur in single precision; the central differences (steps of 1e-6) are taken on the model
    blurred in double precision, where they resolve the derivative."""
    r = render_micrograph(5300, MicrographOptions(rows=200, cols=200, grid=(2, 2, 8.0), d_um=1.0, na=0.9))
    img = r.data.astype(float)
    bg = indent_om.om_background(img, r.pixel_um)
    cands, _sig = indent_om.detect_dots(img, r.pixel_um, background=bg)
    c = min(cands, key=lambda q: abs(q[0] - 100) + abs(q[1] - 100))
    p = indent_om._OmPatch(img, bg, r.pixel_um, *c)
    s = np.array([0.4, 0.1, 0.15, 0.2, 0.128, 0.3, 0.05, -0.03, 0.02])[:n_shared]
    g = p.start(s)[0] + np.array([0.013, -0.007, 0.02, 0.1, 0.0, 0.0, 0.0])
    _m, jac = p.jac(g, s)
    for j in range(7 + n_shared):
        h = 1e-6 if j < 7 else _OM_SHARED_STEP[j - 7] / 10
        gp, gm, sp, sm = g.copy(), g.copy(), s.copy(), s.copy()
        if j < 7:
            gp[j] += h
            gm[j] -= h
        else:
            sp[j - 7] += h
            sm[j - 7] -= h
        with monkeypatch.context() as mp:
            mp.setattr(indent_om, "_FFT_REAL", np.float64)
            mp.setattr(indent_om, "_FFT_COMPLEX", np.complex128)
            mp.setattr(indent_om, "_KERNEL_CACHE", {})
            ref = (p.model(gp, sp) - p.model(gm, sm)).ravel() / (2 * h)
        # the PSF column is a forward difference of the kernel (step 1e-5 µm)
        tol = 2e-3 if j == 7 + 4 else 1e-5
        assert np.abs(jac[:, j] - ref).max() <= tol * np.abs(ref).max(), j
