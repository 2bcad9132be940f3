"""Single real-like imprints (issue 20): measured against the renderer's geometric truth.

The renderer (fixtures/indent_single) bows the edges (+-8 % of d/2), puts pile-up lobes of up
to 30 % of the depth beside two opposite edges, blunts the apex, and adds tilt, bow, line
offsets, scars and noise; its truth comes from the geometry, not from the measuring code.
Tolerances are the issue's goals: mean diagonal within 0.5 % (or 1 px), depth 1 %, area 1 %,
corners 1.5 px.
"""
import dataclasses
import json
import os

import numpy as np
import pytest

from markcal.fixtures.indent_afm_feedback import render_feedback
from markcal.fixtures.indent_maps import AfmOptions, render_afm
from markcal.fixtures.indent_single import SingleOptions, render_single, single_ibw
from markcal.pipeline.cli import main
from markcal.pipeline.flows.indents import IndentsOptions, run_indents
from markcal.stages.indent_level import level_map, level_single
from markcal.stages.indent_single import hardness_hv
from markcal.stages.level import level_afm


def _ibw(tmp_path, r, name="map.ibw"):
    path = os.path.join(str(tmp_path), name)
    with open(path, "wb") as fh:
        fh.write(single_ibw(r))
    return path


@pytest.mark.parametrize("seed,margin", [(1, None), (2, None), (6, 3.0), (7, 3.0)])
def test_single_imprint_against_truth(tmp_path, seed, margin):
    r = render_single(seed, SingleOptions(corner_margin_px=margin))
    t = r.truth["imprints"][0]
    px = r.pixel_um
    res = run_indents([_ibw(tmp_path, r)], None, IndentsOptions(load_mN=500.0))
    tab = res.indents
    assert len(tab["id"]) == 1                                  # one imprint, nothing else
    d = tab["d_um"][0]
    assert abs(d - t["d_um"]) <= max(0.005 * t["d_um"], px)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    assert abs(tab["area_um2"][0] / t["area_um2"] - 1) <= 0.01
    corners = res.files[0].imprints[0].corners_um
    tc = np.array(t["corners_um"])
    err_px = [np.min(np.hypot(*(tc - c).T)) / px for c in corners]
    assert max(err_px) <= 1.5
    assert tab["cut_by_border"][0] == 0
    # pile-up: the lobe's height within 5 % (the smoothing takes a little off the top)
    assert abs(tab["pileup_nm"][0] / t["pileup_nm"] - 1) <= 0.05
    # pile-up volume above the original surface: worst -4.3 % on these seeds (the lobes' feet
    # under the noise threshold are left out)
    assert abs(tab["pileup_volume_um3"][0] / t["pileup_volume_um3"] - 1) <= 0.08
    # HV = 0.1891 F / d^2, F in N, d in mm: 500 mN on d µm
    assert tab["hv"][0] == pytest.approx(0.1891 * 0.5 / (d * 1e-3) ** 2, rel=1e-12)
    assert np.isfinite(tab["apex_depth_nm"][0])


@pytest.mark.parametrize("seed", [1, 3])
def test_two_imprints_in_a_filled_map_both_measured(tmp_path, seed):
    """A second, smaller imprint beside one that fills the field: both found and both measured again after the
    level beyond the corners (only the pits within the imprints found first are measured again)."""
    r = render_single(seed, SingleOptions(fill=0.55))
    px, n = r.pixel_um, r.data.shape[0]
    c_um, half_um = 0.13 * n * px, 0.06 * n * px              # a pyramid (diagonals along the axes) in a corner
    y, x = np.mgrid[0:n, 0:n] * px
    depth_nm = 0.1 * 2e3 * half_um
    small = -depth_nm * np.clip(1 - (np.abs(x - c_um) + np.abs(y - c_um)) / half_um, 0, None)
    res = run_indents([_ibw(tmp_path, dataclasses.replace(r, data=r.data + small))], None, IndentsOptions())
    tab = res.indents
    assert len(tab["id"]) == 2
    big = r.truth["imprints"][0]
    for x_um, y_um, d_um in ((big["x_um"], big["y_um"], big["d_um"]), (c_um, c_um, 2 * half_um)):
        k = int(np.argmin(np.hypot(tab["x_um"] - x_um, tab["y_um"] - y_um)))
        assert np.hypot(tab["x_um"][k] - x_um, tab["y_um"][k] - y_um) <= px
        assert abs(tab["d_um"][k] - d_um) <= max(0.005 * d_um, px)


@pytest.mark.parametrize("seed", [11, 141])
def test_level_map_tells_filled_maps_from_arrays(seed):
    """An imprint filling 89 % or 40 % of the field (feedback renderer) is levelled from the far field only, an
    array of 25 as a whole, and so is a dense one (8 x 8 imprints of 3 µm at a 5 µm pitch), which masks 37 % of the
    field in all but 1 % in its largest feature."""
    fb = render_feedback(seed)
    lv, filled = level_map(fb.height_nm, fb.pixel_um)
    assert filled
    assert np.array_equal(lv.z_nm, level_single(fb.height_nm, fb.pixel_um).z_nm, equal_nan=True)
    for arr in (render_afm(seed, AfmOptions(size_px=256)),
                render_afm(1, AfmOptions(rows=8, cols=8, pitch_um=5.0, nominal_um=3.0, field_um=46.0, size_px=512))):
        lv, filled = level_map(arr.data, arr.pixel_um)
        assert not filled
        assert np.array_equal(lv.z_nm, level_afm(arr.data, arr.pixel_um).z_nm, equal_nan=True)


def test_level_map_of_tiny_maps():
    """Maps a few pixels across (the readers refuse under 8) are levelled as a whole, without an error."""
    for shape in ((100, 1), (9, 13)):
        z = np.random.default_rng(0).normal(size=shape)
        lv, filled = level_map(z, 0.1)
        assert not filled and lv.z_nm.shape == shape and np.isfinite(lv.z_nm).all()


@pytest.mark.parametrize("seed,crack_nm", [(2001, 30.0), (2003, 300.0)])
def test_radial_cracks_do_not_lengthen_the_diagonals(tmp_path, seed, crack_nm):
    """Cracks from all four corners (grooves 1-2 px wide, 30-300 nm deep as the tip sees them, running
    0.4-1 half-diagonals out): the level contour followed them; before the crack fill of session 12 these
    two had a corner 1.6 px out (30 nm) and d +2.9 % (300 nm). Tolerances: the single-imprint goals."""
    r = render_single(seed, SingleOptions(corner_margin_px=3.0, cracks=4, crack_depth_nm=crack_nm))
    t = r.truth["imprints"][0]
    assert len(r.truth["cracks"]) == 4
    px = r.pixel_um
    res = run_indents([_ibw(tmp_path, r)], None, IndentsOptions())
    tab = res.indents
    assert len(tab["id"]) == 1
    assert abs(tab["d_um"][0] - t["d_um"]) <= max(0.005 * t["d_um"], px)
    assert abs(tab["area_um2"][0] / t["area_um2"] - 1) <= 0.01
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    tc = np.array(t["corners_um"])
    assert max(np.min(np.hypot(*(tc - c).T)) for c in res.files[0].imprints[0].corners_um) / px <= 1.5


def test_strong_scanner_bow_levelled_from_the_ring(tmp_path):
    """A scanner bow of up to 300 nm over the field (seed 2007: 271 nm): left in by the first round's
    20 nm feature mask, the bow fitted to parts of the ring put the level under the imprint 30 nm off;
    session 11 read d 25.4 µm for 16.3. Now the ring's own quadratic comes first. Tolerances: the goals."""
    r = render_single(2007, SingleOptions(corner_margin_px=3.0, bow_nm=300.0))
    t = r.truth["imprints"][0]
    px = r.pixel_um
    tab = run_indents([_ibw(tmp_path, r)], None, IndentsOptions()).indents
    assert len(tab["id"]) == 1
    assert abs(tab["d_um"][0] - t["d_um"]) <= max(0.005 * t["d_um"], px)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    assert abs(tab["area_um2"][0] / t["area_um2"] - 1) <= 0.01


def test_line_offsets_make_no_second_imprint(tmp_path):
    """White line offsets of 5 nm (our renderer's default is 2): seed 2005 had a second "imprint" of
    0.69 µm and 11 nm (H/D 0.016) beside the real one. Without an array spec, pits under H/D 0.02 are
    not imprints; the real one is measured within the goals."""
    r = render_single(2005, SingleOptions(corner_margin_px=3.0, line_offset_nm=5.0))
    t = r.truth["imprints"][0]
    tab = run_indents([_ibw(tmp_path, r)], None, IndentsOptions()).indents
    assert len(tab["id"]) == 1
    assert abs(tab["d_um"][0] - t["d_um"]) <= max(0.005 * t["d_um"], r.pixel_um)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01


@pytest.mark.parametrize("seed", [2004, 2007])
def test_drifting_scan_lines_within_goals(tmp_path, seed):
    """Line offsets of 10 nm plus a drift of 2 nm per line (about 30 nm over the scan): the drift stood
    above the first round's 20 nm feature threshold, 95 % of the field was masked and no line offset was
    removed (seed 2004: d +10 %, 2007: +66 %). The first mask now comes from the map with each line's
    side-strip median removed when that masks less."""
    r = render_single(seed, SingleOptions(line_offset_nm=10.0))
    t = r.truth["imprints"][0]
    tab = run_indents([_ibw(tmp_path, r)], None, IndentsOptions()).indents
    assert len(tab["id"]) == 1
    assert abs(tab["d_um"][0] - t["d_um"]) <= max(0.005 * t["d_um"], r.pixel_um)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    assert abs(tab["area_um2"][0] / t["area_um2"] - 1) <= 0.01


def test_edge_bow_signs_against_truth():
    """Mid-edge bows (fraction of d/2) within 0.02 of truth, matched edge by edge by their midpoints."""
    from markcal.stages.indent_afm import detect_pits
    from markcal.stages.indent_level import level_single
    from markcal.stages.indent_single import measure_single
    r = render_single(1)
    px = r.pixel_um
    lv = level_single(r.data.astype(float), px)
    c = max(detect_pits(lv.z_nm, lv.noise_nm, px), key=lambda q: q[2])
    m = measure_single(lv.z_nm, px, lv.noise_nm, *c)
    tc = np.array(r.truth["imprints"][0]["corners_um"])
    true_bow = r.truth["imprints"][0]["edge_bow"]
    tmid = (tc + np.roll(tc, -1, axis=0)) / 2
    mmid = (m.corners_um + np.roll(m.corners_um, -1, axis=0)) / 2
    for j in range(4):
        k = int(np.argmin(np.hypot(*(tmid - mmid[j]).T)))
        assert abs(m.edge_bow[j] - true_bow[k]) <= 0.02, (j, m.edge_bow, true_bow)


def test_hardness_formula():
    # 1 N on a 0.1 mm diagonal: HV 18.91
    assert hardness_hv(1000.0, 100.0) == pytest.approx(18.91)


def test_cut_by_border_flagged(tmp_path):
    """A corner outside the field: flagged, no area, never silently whole."""
    r = render_single(3, SingleOptions(corner_margin_px=-12.0, fill=0.8))
    res = run_indents([_ibw(tmp_path, r)])
    tab = res.indents
    assert len(tab["id"]) == 1
    assert tab["cut_by_border"][0] == 1
    assert np.isnan(tab["area_um2"][0])
    assert res.summary["n_cut_by_border"] == 1


def test_edge_across_the_border_flagged_with_corners_inside():
    """Edges along the axes, bowed outwards by 8 % of d/2; the right corners 1 px inside the last column, the
    right edge's middle 5 px beyond it: the contact boundary is open, so the imprint is cut (no area), though
    every corner was found inside the field (where they are: within 0.2 px)."""
    from markcal.stages.indent_single import measure_single
    n, px, a, depth, bow = 200, 0.1, 60.0, 800.0, 0.08
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    cx, cy = n - 2 - a, 100.0
    u, v = xx - cx, yy - cy
    ru = np.abs(u) / (a * (1 + bow * (1 - np.clip(v / a, -1, 1) ** 2)))
    rv = np.abs(v) / (a * (1 + bow * (1 - np.clip(u / a, -1, 1) ** 2)))
    z = -depth * np.clip(1 - np.maximum(ru, rv), 0, None) + np.random.default_rng(0).normal(0, 0.5, (n, n))
    m = measure_single(z, px, 0.5, cy, cx, a)
    true_rc = np.array([[cy + sr * a, cx + sc * a] for sr in (-1, 1) for sc in (-1, 1)])
    got_rc = m.corners_um[:, ::-1] / px
    assert max(np.min(np.hypot(*(got_rc - t).T)) for t in true_rc) <= 0.2
    assert got_rc[:, 1].max() < n - 1
    assert m.cut_by_border and np.isnan(m.area_um2)


def test_profile_crossing_where_the_valley_fit_fails():
    """The fallback corner (a line through the interpolated profile before the coarse corner): on a ramp of
    40 nm/px meeting the surface at column 80.3, with the coarse corner 1.7 px beyond, it crosses at 80.3."""
    from scipy import ndimage
    from markcal.stages.indent_corners import _profile_crossing
    cc = np.mgrid[0:60, 0:120][1].astype(float)
    z = np.minimum(40.0 * (cc - 80.3), 0.0)
    zc = ndimage.spline_filter(z, order=3, mode="nearest")
    rc0 = np.array([30.0, 20.0])
    s0 = _profile_crossing(zc, rc0, np.array([0.0, 1.0]), 60.3 + 1.7, 40.0, 0.5)
    assert s0 == pytest.approx(60.3, abs=0.1)


def test_cli_render_single_and_measure(tmp_path, capsys):
    out = str(tmp_path / "r")
    assert main(["render", "afm", "--single", "--seed", "5", "--out", out, "--quiet"]) == 0
    truth = json.load(open(os.path.join(out, "truth.json")))
    res_dir = str(tmp_path / "m")
    assert main(["indents", os.path.join(out, "heights.ibw"), "--out", res_dir, "--load-mN", "300", "--quiet"]) == 0
    s = json.load(open(os.path.join(res_dir, "summary.json")))
    t = truth["imprints"][0]
    assert abs(s["mean_d_um"] - t["d_um"]) <= max(0.005 * t["d_um"], truth["pixel_um"])
    assert s["mean_hv"] == pytest.approx(0.1891 * 0.3 / (s["mean_d_um"] * 1e-3) ** 2, rel=1e-9)
    html = open(os.path.join(res_dir, "report.html")).read()
    assert "HV" in html
    assert "from both scan directions" not in html                 # the trace alone: its boundary
    # the same heights as GSF (the default formats tif,gsf beside the IBW) read to the same diagonal
    gsf_dir = str(tmp_path / "g")
    assert main(["indents", os.path.join(out, "heights.gsf"), "--out", gsf_dir, "--quiet"]) == 0
    assert json.load(open(os.path.join(gsf_dir, "summary.json")))["mean_d_um"] == pytest.approx(s["mean_d_um"],
                                                                                               rel=1e-6)


def test_flat_map_is_refused(tmp_path, capsys):
    """A map with no imprint: one line, exit 1, no summary.json."""
    r = render_single(4)
    flat = r.__class__(data=np.random.default_rng(0).normal(0, 0.5, r.data.shape).astype(np.float32),
                       pixel_um=r.pixel_um, kind="afm", truth=r.truth)
    path = _ibw(tmp_path, flat, "flat.ibw")
    out = str(tmp_path / "o")
    assert main(["indents", path, "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ") and "flat.ibw" in err[0]
    assert not os.path.exists(os.path.join(out, "summary.json"))


def test_spec_with_only_an_indenter_table(tmp_path):
    """A spec holding only [indenter] load_mN: single imprints measured, HV from that load."""
    r = render_single(1)
    spec = tmp_path / "indenter.toml"
    spec.write_text("[indenter]\nkind = \"vickers\"\nload_mN = 500\n")
    out = str(tmp_path / "out")
    assert main(["indents", _ibw(tmp_path, r), "--array", str(spec), "--out", out, "--quiet", "--no-report"]) in (0, 4)
    rows = open(os.path.join(out, "indents.csv")).read().splitlines()
    row = dict(zip(rows[0].split(","), rows[1].split(",")))
    d_mm = float(row["d_um"]) * 1e-3
    assert len(rows) == 2
    assert float(row["hv"]) == pytest.approx(0.1891 * 0.5 / d_mm ** 2, rel=1e-9)
    assert json.load(open(os.path.join(out, "summary.json")))["load_mN"] == 500.0


def test_interrupted_scan_blank_lines_left_out(tmp_path):
    """A scan stopped 12 lines below the imprint: the lines never scanned hold 0 in the file. Left in, they
    stood as a plateau beside the map (session 11 found two imprints on this seed). They are now left
    out, with a progress line; the imprint is measured within the goals."""
    import dataclasses
    r = render_single(2001, SingleOptions(fill=0.5))
    t = r.truth["imprints"][0]
    z = r.data.copy()
    last = int(max(c[1] for c in t["corners_um"]) / r.pixel_um) + 12
    z[last:] = 0.0
    r = dataclasses.replace(r, data=z)
    msgs = []
    res = run_indents([_ibw(tmp_path, r)], None, IndentsOptions(), progress=msgs.append)
    tab = res.indents
    assert len(tab["id"]) == 1
    assert abs(tab["d_um"][0] - t["d_um"]) <= max(0.005 * t["d_um"], r.pixel_um)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    assert any(f"{z.shape[0] - last} constant scan lines" in m for m in msgs)


def test_missing_lines_filled_along_the_columns():
    """A V down the columns (the floor between two facets, 30 nm per line) and a plane, with one and two
    lines missing: filled exactly (the higher continuation); three lines, or a line next to the border,
    stay missing."""
    from markcal.stages.indent_single import _fill_line_gaps
    rows = np.arange(20, dtype=float)[:, None]
    v = 30.0 * np.abs(rows - 9.0) + 0.5 * np.arange(6)[None, :] - 300.0
    plane = 2.0 * rows + 0.3 * np.arange(6)[None, :]
    for truth in (v, plane):
        for gap in ([9], [9, 10], [8, 9]):
            z = truth.copy()
            z[gap] = np.nan
            np.testing.assert_allclose(_fill_line_gaps(z), truth, atol=1e-9)
    z = v.copy()
    z[[8, 9, 10]] = np.nan
    z[1] = np.nan
    out = _fill_line_gaps(z)
    assert np.isnan(out[[1, 8, 9, 10]]).all()


def test_clipped_floor_only_where_heights_are_equal():
    """The Z range's end: eight or more pixels at exactly the lowest height. A noisy floor, or a pyramid's floor
    stored in integer steps of 0.2 nm (16 bits over 13 µm), has its lowest height on one or two pixels."""
    from markcal.stages.indent_select import clipped_floor
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:64, 0:64]
    pyramid = -np.clip(800.0 - 25.0 * np.maximum(np.abs(xx - 32.3), np.abs(yy - 31.6)), 0, None)
    noisy = pyramid + rng.normal(0, 0.7, pyramid.shape)
    assert clipped_floor(noisy) is None
    assert clipped_floor(np.round(noisy / 0.2) * 0.2) is None
    cut = np.maximum(noisy, -760.0)
    low = clipped_floor(cut)
    assert np.array_equal(low, noisy <= -760.0) and int(low.sum()) >= 8


def _pyramid_in_pile_up(n=129, a=56.0, depth=800.0, noise=0.3, seed=0):
    """A square pyramid (diagonals along the axes, half-diagonal ``a`` px) filling an n x n map (apex on the centre pixel) whose every
    pixel outside it stands 20 nm up (pile-up), but for a patch in the top-left corner (x + y < 40 px) on the
    original surface, tilted by 0.075 nm/px along x + y (heights within +-1.5 nm of 0)."""
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    c = (n - 1) / 2
    r = (np.abs(xx - c) + np.abs(yy - c)) / a
    z = np.where(r <= 1, -depth * (1 - r), 20.0)
    patch = xx + yy < 40
    z[patch] = 0.075 * (xx[patch] + yy[patch] - 20.0)
    return z + np.random.default_rng(seed).normal(0, noise, (n, n)), c


def test_far_field_on_one_side_gives_no_tilt():
    """The only far field is a patch in one corner of the map (a filled map's far field, or what the pile-up left
    of it): a plane fitted to it and extrapolated under the imprint put the level 8 nm off at the floor (depth
    and d +1.0 %; on feedback seed 12 with one noise draw, 170 nm). Far field in fewer than three quadrants about the pit
    gives the level only: depth within 0.2 % of 800 nm, d within 0.2 % of 2 a."""
    from markcal.stages.indent_single import _surrounds, measure_single
    z, c = _pyramid_in_pile_up()
    m = measure_single(z, 0.1, 0.3, c, c, 56.0)
    assert m.depth_nm == pytest.approx(800.0, rel=0.002)
    assert m.d_um == pytest.approx(2 * 56.0 * 0.1, rel=0.002)
    rows, cols = np.nonzero(np.add.outer(np.arange(129), np.arange(129)) < 40)
    assert not _surrounds(rows, cols, c, c)
    # a few stray pixels (5) in each other quadrant pin no tilt either
    stray = np.array([[r, q] for r, q in ((120, 5), (5, 120), (120, 120)) for _ in range(5)])
    assert not _surrounds(np.r_[rows, stray[:, 0]], np.r_[cols, stray[:, 1]], c, c)
    ring = np.hypot(*np.mgrid[0:129, 0:129] - c) > 60
    assert _surrounds(*np.nonzero(ring), c, c)
