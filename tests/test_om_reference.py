"""OM arrays near the resolution limit measured with the halo and crease of a reference micrograph of larger
imprints under the same objective (``--optics-from``; issue 20)."""
from __future__ import annotations

import numpy as np
import pytest

from markcal.fixtures.indent_maps import AfmOptions, render_afm, tiff_bytes
from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
from markcal.pipeline.cli import main
from markcal.pipeline.flows.indents import IndentsOptions, read_array_spec, run_indents
from om_arrays import errors_nm, write_hard_array
from test_indent_micrograph import SEM_FILE, _realdata


def test_1um_array_with_a_3um_reference_meets_the_goal(tmp_path):
    """1 µm under NA 0.9 (2.7 Airy radii): with the halo and crease of a 3 µm array (another seed) held, every
    diagonal within the issue's ±50 nm and the centres within 10 nm RMS. Measured (seeds 5003 / 5103):
    d −20.5 to +5.4 nm and centre RMS 5.0 nm with the reference; +90.9 to +118.9 nm and 10.7 nm without."""
    path, spec, truth = write_hard_array(tmp_path / "small", 5003, 1.0)
    ref, _spec, _t = write_hard_array(tmp_path / "ref", 5103, 3.0)
    res = run_indents([path], read_array_spec(spec), IndentsOptions(kind="om", optics_from=str(ref)))
    e = errors_nm(res.indents, truth)
    assert len(e) == 9
    assert np.all(np.abs(e[:, 2]) <= 50.0), e[:, 2]
    assert np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)) <= 10.0
    s = res.summary
    assert s["optics_from"] == "om.tif" and s["n_near_resolution"] == 9
    assert 0.0 < s["held_rim"] and 0.0 < s["held_rim_w"] and 0.0 < s["held_crease"] < 0.95


def _cli(tmp_path, ref):
    path, spec, _t = write_hard_array(tmp_path / "small", 5003, 1.0)
    out = tmp_path / "out"
    code = main(["indents", path, "--array", spec, "--optics-from", str(ref), "--out", str(out), "--quiet"])
    return code, out


def test_missing_reference_fails_alone(tmp_path, capsys):
    code, out = _cli(tmp_path, tmp_path / "nothere.tif")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out.exists()
    assert err == [f"markcal: error: {tmp_path / 'nothere.tif'}: no such file"]


def test_afm_map_as_reference_is_refused(tmp_path, capsys):
    r = render_afm(1000, AfmOptions(size_px=128))
    ref = tmp_path / "afm.tif"
    ref.write_bytes(tiff_bytes(r.data, r.pixel_um, zunit="nm"))
    code, out = _cli(tmp_path, ref)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out.exists()
    assert len(err) == 1 and err[0].startswith(f"markcal: error: {ref}: optics reference: an AFM height map")


def test_reference_without_an_array_is_refused(tmp_path, capsys):
    """A micrograph of one imprint has no array to take the halo and crease from."""
    r = render_micrograph(3000, MicrographOptions(rows=200, cols=200, d_um=4.0))
    ref = tmp_path / "single.tif"
    ref.write_bytes(tiff_bytes(r.data, r.pixel_um))
    code, out = _cli(tmp_path, ref)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out.exists()
    assert len(err) == 1 and err[0].startswith(f"markcal: error: {ref}: optics reference: ")


def test_reference_near_the_resolution_limit_is_refused(tmp_path, capsys):
    """A reference of 1 µm imprints cannot give what the 1 µm image lacks."""
    ref, _spec, _t = write_hard_array(tmp_path / "ref", 5104, 1.0)
    code, out = _cli(tmp_path, ref)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out.exists()
    assert len(err) == 1 and "near the resolution limit too" in err[0] and err[0].startswith(f"markcal: error: {ref}: ")


def test_real_sem_single_imprint_is_refused_as_a_reference(tmp_path, capsys):
    """The real FEI SEM image (../shared/realdata, one ~19 µm imprint) is not an array: refused, nothing written.
    Without this check its facet texture and dust were taken as 0.6 µm "imprints" and a rim of -0.18 held."""
    ref = _realdata() / SEM_FILE
    if not ref.is_file():
        pytest.skip(f"real file {SEM_FILE} not present (../shared/realdata)")
    code, out = _cli(tmp_path, ref)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out.exists()
    assert err == [f"markcal: error: {ref}: optics reference: a micrograph of 1 single imprint(s) of 19.2 µm, "
                   "not an array: the halo and crease come from an OM array of imprints"]


def test_real_sem_image_has_no_optics_figures(tmp_path):
    """Measured on its own the real SEM imprint keeps its diagonal (19.16 µm against the careful manual 19.09 µm,
    goal 2 %) and, with no PSF fitted, null optics figures and no resolution warning."""
    path = _realdata() / SEM_FILE
    if not path.is_file():
        pytest.skip(f"real file {SEM_FILE} not present (../shared/realdata)")
    res = run_indents([str(path)])
    s = res.summary
    assert abs(s["mean_d_um"] - 19.09) <= 0.02 * 19.09
    assert s["optics_resolution_um"] is None and s["n_near_resolution"] is None and s["optics_from"] is None
