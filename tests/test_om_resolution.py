"""OM arrays near the optics' resolution limit: summary figures and the report's warning (issue 20)."""
from __future__ import annotations

import os

import pytest

from markcal.fixtures.indent_maps import AfmOptions, array_toml, render_afm, tiff_bytes
from markcal.pipeline.flows.indents import IndentsOptions, read_array_spec, run_indents
from markcal.reports.indents_report import indents_report_html
from markcal.stages.indent_om import RESOLUTION_RADII, airy_radius_um, airy_sigma_um
from om_arrays import write_hard_array

WARNING = "near the resolution limit"


def test_airy_radius_is_rayleighs():
    """0.61 lambda / NA from the Gaussian-equivalent sigma of that objective's Airy PSF."""
    for na in (0.3, 0.9, 1.3):
        assert airy_radius_um(airy_sigma_um(na, 0.55)) == pytest.approx(0.61 * 0.55 / na, rel=1e-12)


def _run(tmp_path, d_um, na):
    path, spec, _truth = write_hard_array(tmp_path, 5003, d_um, na)
    return run_indents([path], read_array_spec(spec), IndentsOptions(kind="om"))


def test_1um_imprints_under_na_0_9_are_flagged(tmp_path):
    """1 µm under Airy NA 0.9 is 2.7 Airy radii (0.373 µm): every imprint is flagged, and the report says so.
    The radius comes from the fitted PSF: within 10 % of the render's optics (measured 0.371 and 0.395 µm at
    1 and 3 µm: the fitted PSF also takes up what the model's shorter Airy kernel leaves out)."""
    res = _run(tmp_path, 1.0, 0.9)
    s = res.summary
    assert s["optics_resolution_um"] == pytest.approx(0.61 * 0.55 / 0.9, rel=0.1)
    assert 1.0 < RESOLUTION_RADII * s["optics_resolution_um"]
    assert s["n_near_resolution"] == s["n_imprints"] == 9
    assert WARNING in indents_report_html(res)


def test_3um_imprints_are_not_flagged(tmp_path):
    """3 µm under the same optics is 8 radii: nothing flagged, no warning."""
    res = _run(tmp_path, 3.0, 0.9)
    assert res.summary["n_near_resolution"] == 0
    assert res.summary["optics_resolution_um"] == pytest.approx(0.61 * 0.55 / 0.9, rel=0.1)
    assert WARNING not in indents_report_html(res)


def test_afm_maps_have_no_optics(tmp_path):
    """AFM maps are not imaged through a PSF: both figures are null (not applicable), no warning."""
    r = render_afm(1000, AfmOptions(size_px=256))
    path, spec = os.path.join(tmp_path, "m.tif"), os.path.join(tmp_path, "a.toml")
    with open(path, "wb") as fh:
        fh.write(tiff_bytes(r.data, r.pixel_um, zunit="nm"))
    t = r.truth
    with open(spec, "w") as fh:
        fh.write(array_toml(t["rows"], t["cols"], t["pitch_um"], t["nominal_diameter_um"]))
    res = run_indents([path], read_array_spec(spec))
    assert res.summary["optics_resolution_um"] is None and res.summary["n_near_resolution"] is None
    assert WARNING not in indents_report_html(res)
