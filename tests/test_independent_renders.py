"""The indents flow on the two renderers written independently of markcal's model, against their truth.

fixtures/indent_single_ruled (AFM, one imprint: ruled facets to bowed edges, pile-up lobes, ball-
blunted indenter, sphere + cone tip, scanner artefacts) and fixtures/indent_om_aperture (OM, 5 x 5
arrays: aperture-model shading, dark ridge and edge lines, halo, Airy NA 0.9, noise). Tolerances are
the goals of benchmarks/bench_independent.py. AFM seed 2: pit and pile-up lobes fill rows 90-225 across
the whole width (the level under the floor comes from two bands; depth was +1.26 % before session 12);
seed 39: a scar runs along the floor's row over 60 % of its far field (depth was -2.64 %).
"""
import dataclasses
import itertools
import math

import numpy as np
import pytest

from markcal.fixtures.cracks import radial_cracks
from markcal.fixtures.indent_om_aperture import render_om_aperture, write_om_aperture
from markcal.fixtures.indent_single_ruled import render_single_ruled, write_single_ruled
from markcal.fixtures.line_flatten import flatten_lines
from markcal.pipeline.config import read_array_spec
from markcal.pipeline.flows.indents import IndentsOptions, run_indents


def _corners_um(tab, k):
    """Corners from indents.csv: centre, orientation_deg (direction of diagonal 1), diag1_um, diag2_um."""
    o = math.radians(tab["orientation_deg"][k])
    e1, e2 = np.array([math.cos(o), math.sin(o)]), np.array([-math.sin(o), math.cos(o)])
    c = np.array([tab["x_um"][k], tab["y_um"][k]])
    m1, m2 = tab["diag1_um"][k], tab["diag2_um"][k]
    return np.array([c + m1 / 2 * e1, c + m2 / 2 * e2, c - m1 / 2 * e1, c - m2 / 2 * e2])


@pytest.mark.parametrize("seed,margin", [(5, None), (6, 3.0), (2, None), (39, 3.0)])
def test_single_ruled_imprint_against_truth(tmp_path, seed, margin):
    r = render_single_ruled(seed, size_px=256, corner_margin_px=margin)
    gsf, _ = write_single_ruled(r, str(tmp_path), "map")
    _assert_single_goals(run_indents([gsf], None, IndentsOptions(load_mN=500.0)).indents, r)


@pytest.mark.parametrize("seed,how,axis", [(3, 0, 0), (5, "median", 0), (8, 1, 0), (11, 1, 0), (6, 1, 1)])
def test_single_ruled_imprint_flattened_line_by_line(tmp_path, seed, how, axis):
    """A scan flattened line by line before export, imprint and all (each row's mean, median or line taken
    off; seed 6: each column's): the rows through the imprint stand up to 300 nm off, and an order-1 flatten
    tilts them too. Session 14 met every goal on seeds 3 and 5 (mean, median) only; seeds 8 and 11 as
    line-flattened gave d -15.7 % / +25 % and depth -39 % / -28 %. The flatten is now recognised by its
    signature (every line's fit alike) and each line's fit is taken again from its far field, followed line
    by line (``stages/indent_unflatten``). Tolerances: the single-imprint goals."""
    r = render_single_ruled(seed, size_px=256, corner_margin_px=3.0 if seed % 3 == 0 else None)
    z = flatten_lines(r.height_nm, how, axis)
    gsf, _ = write_single_ruled(dataclasses.replace(r, height_nm=z.astype(np.float32)), str(tmp_path), "map")
    res = run_indents([gsf], None, IndentsOptions())
    _assert_single_goals(res.indents, r)
    line = "row" if axis == 0 else "column"
    what = {"median": "median", 0: "mean", 1: "line"}[how]
    assert res.files[0].info["line_flatten"] == res.summary["line_flatten"] == f"each {line}'s {what} taken off"


def test_single_ruled_imprint_as_a_gwyddion_text_export(tmp_path):
    """Seed 8 flattened by each row's line and exported as Gwyddion's ASCII data matrix (heights in m to
    5 significant digits, the field's size in the header): read by its header, the flatten and its order
    recognised through the rounding, measured to the single-imprint goals."""
    from markcal.stages.text_maps import text_matrix
    r = render_single_ruled(8, size_px=256)
    rows, cols = r.height_nm.shape
    p = tmp_path / "map.txt"
    p.write_text(text_matrix(flatten_lines(r.height_nm, 1) * 1e-9, cols * r.pixel_um * 1e-6,
                             rows * r.pixel_um * 1e-6), encoding="utf-8")
    res = run_indents([str(p)], None, IndentsOptions())
    assert res.files[0].info["line_flatten"] == "each row's line taken off"
    _assert_single_goals(res.indents, r)


@pytest.mark.parametrize("seed", [3, 5, 8])
def test_flattened_scan_cropped_afterwards(tmp_path, seed):
    """Each row's mean taken off, then 24 columns cropped away from the imprint (a flatten, then a crop, in a
    viewer): the lines' means no longer agree, so the flatten is not recognised, and the levelling's first
    round works under the side strips' offsets (session 14: the first surface fitted through them bent 240 nm
    on seed 3 and masked 97 % of the field). Tolerances: the single-imprint goals."""
    r = render_single_ruled(seed, size_px=256, corner_margin_px=3.0 if seed % 3 == 0 else None)
    z = flatten_lines(r.height_nm, 0)
    right = np.mean([c["col"] for c in r.truth["corners"]]) > 128
    z = z[:, 24:] if right else z[:, :-24]
    shift = 24 * r.pixel_um if right else 0.0
    truth = dict(r.truth, corners=[dict(c, x_um=c["x_um"] - shift) for c in r.truth["corners"]])
    r = dataclasses.replace(r, height_nm=z.astype(np.float32), truth=truth)
    gsf, _ = write_single_ruled(r, str(tmp_path), "map")
    res = run_indents([gsf], None, IndentsOptions())
    assert "line_flatten" not in res.files[0].info
    _assert_single_goals(res.indents, r)


@pytest.mark.parametrize("seed", [5, 8])
def test_single_ruled_imprint_scanned_with_every_second_line(tmp_path, seed):
    """Every second line of the map left out: 128 lines of 256 points over the square field, pixels twice as
    tall as wide (a fast scan). Session 14 refused such files (`pixels are not square`); they are now
    resampled to square pixels, linear between the lines. Tolerances: the single-imprint goals, lengths in
    the line spacing (two of the render's pixels): d within 0.5 % or one spacing, corners within 1.5
    spacings; depth and area within 1 %. (Over seeds 1-12 the depth misses on two, -1.1 and -1.5 %: the floor
    falls between two lines.)"""
    from markcal.stages.image_io import gsf_bytes
    r = render_single_ruled(seed, size_px=256, corner_margin_px=3.0 if seed % 3 == 0 else None)
    field_m = 256 * r.pixel_um * 1e-6
    path = str(tmp_path / "half.gsf")
    with open(path, "wb") as fh:
        fh.write(gsf_bytes(r.height_nm[::2] * 1e-9, field_m, field_m))
    res = run_indents([path], None, IndentsOptions())
    assert res.files[0].info["resampled"] == res.summary["resampled"]
    assert res.summary["resampled"].startswith("256 x 128 samples of")
    tab, t = res.indents, r.truth
    line = 2 * r.pixel_um
    assert len(tab["x_um"]) == 1
    assert abs(tab["d_um"][0] - t["d_mean_um"]) <= max(0.005 * t["d_mean_um"], line)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    assert abs(tab["area_um2"][0] / t["area_below_original_level_um2"] - 1) <= 0.01
    mc = _corners_um(tab, 0)
    tc = np.array([[c["x_um"], c["y_um"]] for c in t["corners"]])
    assert min(np.max(np.hypot(*(mc[list(p)] - tc).T)) for p in itertools.permutations(range(4))) <= 1.5 * line


@pytest.mark.parametrize("seed", [1, 8])
def test_scan_lines_left_out_through_the_floor(tmp_path, seed):
    """Three scan lines left out (NaN), one of them through the imprint's centre: the levelling kept them
    out, and the measurement set them to the original surface's level before smoothing, so the floor was
    missed (seeds 1-12: depth -0.2 to -4.9 %, 4 of 12 met every goal; seeds 1 and 8 -3.4 and -4.9 %). Runs of
    up to two missing lines are now filled from two pixels either side (the higher of the two straight
    continuations: a V stays a V): 12 of 12. Tolerances: the single-imprint goals."""
    r = render_single_ruled(seed, size_px=256, corner_margin_px=3.0 if seed % 3 == 0 else None)
    z = r.height_nm.astype(float).copy()
    ci = int(r.truth["centre_um"][1] / r.pixel_um)
    z[[10, ci, min(ci + 40, 250)], :] = np.nan
    gsf, _ = write_single_ruled(dataclasses.replace(r, height_nm=z.astype(np.float32)), str(tmp_path), "map")
    _assert_single_goals(run_indents([gsf], None, IndentsOptions()).indents, r)


@pytest.mark.parametrize("seed", [1, 12])
def test_floor_clipped_by_the_z_range(tmp_path, seed):
    """The scanner's Z range ends just above the floor: the lowest 0.2 % of the map read one value. The flat
    floor made the pit a flat-bottomed one (a grating's), refused: "no imprint found" on seeds 1 and 12
    (their deepest fifth 9-10 % of the pit). Equal lowest heights on 8 pixels or more now mark the floor as
    clipped: the imprint is measured, the file flagged, the depth a lower bound. Tolerances: the
    single-imprint goals for d, area and corners; the depth at most the depth of the cut plus 1 %."""
    r = render_single_ruled(seed, size_px=256, corner_margin_px=3.0 if seed % 3 == 0 else None)
    z = r.height_nm.astype(float)
    cut = np.percentile(z, 0.2)
    z = np.maximum(z, cut)
    gsf, _ = write_single_ruled(dataclasses.replace(r, height_nm=z.astype(np.float32)), str(tmp_path), "map")
    res = run_indents([gsf], None, IndentsOptions())
    assert res.files[0].info["floor_clipped_px"] >= 8 and res.summary["n_files_floor_clipped"] == 1
    tab, t, px = res.indents, r.truth, r.pixel_um
    assert len(tab["x_um"]) == 1
    assert abs(tab["d_um"][0] - t["d_mean_um"]) <= max(0.005 * t["d_mean_um"], px)
    assert abs(tab["area_um2"][0] / t["area_below_original_level_um2"] - 1) <= 0.01
    assert tab["depth_nm"][0] < t["depth_nm"]
    mc = _corners_um(tab, 0)
    tc = np.array([[c["x_um"], c["y_um"]] for c in t["corners"]])
    assert min(np.max(np.hypot(*(mc[list(p)] - tc).T)) for p in itertools.permutations(range(4))) <= 1.5 * px
    if seed == 1:
        from markcal.pipeline.cli import main
        assert main(["indents", gsf, "--out", str(tmp_path / "out"), "--quiet"]) == 0
        html = (tmp_path / "out" / "report.html").read_text()
        assert "Floor clipped:" in html and "lower bounds" in html
        assert "(a lower bound: the floor was cut flat)" in html          # the imprint's depth row too


def test_floor_clipped_deep_still_measured(tmp_path):
    """Ruled seed 2 with the lowest 3.5 % of the map read as one value (the floor cut at 68 % of the depth): 43 % of
    the pit lies deeper than half the depth read, as on a grating's flat-bottomed pits, so only the clipped floor's
    flag keeps it from being refused. Measured: d -0.43 %, area +0.83 %; held to the single-imprint goals (d 0.5 %
    or 1 px, area 1 %)."""
    r = render_single_ruled(2, size_px=256)
    z = r.height_nm.astype(float)
    z = np.maximum(z, np.percentile(z, 3.5))
    gsf, _ = write_single_ruled(dataclasses.replace(r, height_nm=z.astype(np.float32)), str(tmp_path), "map")
    res = run_indents([gsf], None, IndentsOptions())
    assert res.summary["n_files_floor_clipped"] == 1
    tab, t = res.indents, r.truth
    assert len(tab["x_um"]) == 1
    assert abs(tab["d_um"][0] - t["d_mean_um"]) <= max(0.005 * t["d_mean_um"], r.pixel_um)
    assert abs(tab["area_um2"][0] / t["area_below_original_level_um2"] - 1) <= 0.01


@pytest.mark.parametrize("seed, pct, d_tol_pct", [(5, 3.5, 0.5), (1, 2.0, 3.0)])
def test_floor_clipped_at_half_its_depth_keeps_its_corners(tmp_path, seed, pct, d_tol_pct):
    """Ruled seeds 5 and 1 with the lowest 3.5 and 2 % of the map cut flat (the floor cut at 58 and 54 % of the
    depth). The cut is flat in the raw heights and tilted once levelled; rays from its lowest pixel, at its edge,
    missed the valleys: d -5.68 and -18.7 %. From the middle of the clipped pixels: -0.32 and -1.95 %. Held: seed 5
    to the single-imprint goal (0.5 %), seed 1 to the real-map goal (3 %); area within 1 % on both."""
    r = render_single_ruled(seed, size_px=256)
    z = r.height_nm.astype(float)
    z = np.maximum(z, np.percentile(z, pct))
    gsf, _ = write_single_ruled(dataclasses.replace(r, height_nm=z.astype(np.float32)), str(tmp_path), "map")
    res = run_indents([gsf], None, IndentsOptions())
    tab, t = res.indents, r.truth
    assert res.summary["n_files_floor_clipped"] == 1 and len(tab["x_um"]) == 1
    assert abs(100 * (tab["d_um"][0] / t["d_mean_um"] - 1)) <= d_tol_pct, tab["d_um"][0]
    assert abs(tab["area_um2"][0] / t["area_below_original_level_um2"] - 1) <= 0.01


def _inverted_cli(tmp_path, capsys, seed):
    """Seed ``seed`` of the ruled renderer with its heights negated, through the CLI: exit code and stderr lines."""
    from markcal.pipeline.cli import main
    r = render_single_ruled(seed, size_px=256)
    gsf, _ = write_single_ruled(dataclasses.replace(r, height_nm=(-r.height_nm).astype(np.float32)), str(tmp_path),
                                "map")
    out = tmp_path / "out"
    code = main(["indents", gsf, "--out", str(out), "--quiet"])
    assert not out.exists()
    return code, gsf, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("seed", [1, 5])
def test_inverted_heights_are_refused(tmp_path, capsys, seed):
    """A map whose heights are inverted (a channel of the other sign): the imprint stands up as a pyramid, and
    the pits beside its pile-up lobes had been reported as one or two imprints of 3-10 µm (seed 1: 5.0 and 4.9 µm
    for 10.8). What stands up is 3.3-25 times what lies down on four renderers' maps negated, 0.04-0.44 as drawn:
    over 1, and when the map turned over holds an imprint, the map is refused, the reason named (maps of
    particles stand up too: the real legacy Bruker map, 0.025 µm³ up against 0.0003 µm³ down, holds no imprint
    turned over)."""
    code, gsf, err = _inverted_cli(tmp_path, capsys, seed)
    assert code == 1 and len(err) == 1
    assert err[0].startswith(f"markcal: error: {gsf}: the map holds 1 imprint standing up (") and "inverted" in err[0]


def test_pits_beside_lobes_are_no_imprints(tmp_path, capsys, monkeypatch):
    """The same pits with the volume check off: their contact areas are 1.6 times d^2 / 2 (imprints on five
    renderers: 0.76-1.22), so they are refused as imprints: no imprint found."""
    from markcal.stages import indent_select
    monkeypatch.setattr(indent_select, "raised_and_sunk_um3", lambda z, noise, px: (0.0, 1.0))
    code, gsf, err = _inverted_cli(tmp_path, capsys, 1)
    assert code == 1 and err == [f"markcal: error: {gsf}: no imprint found"]


def _assert_single_goals(tab, r):
    """The issue's goals for one rendered imprint, against the ruled renderer's truth."""
    t, px = r.truth, r.pixel_um
    assert len(tab["x_um"]) == 1                                         # one imprint, nothing else
    # goal: mean diagonal within 0.5 % or 1 px, whichever is larger
    assert abs(tab["d_um"][0] - t["d_mean_um"]) <= max(0.005 * t["d_mean_um"], px)
    # goal: depth within 1 % of the true floor (lowest point of the blunted surface)
    assert abs(tab["depth_nm"][0] / t["depth_nm"] - 1) <= 0.01
    # goal: area within 1 % (markcal's area: inside where the surface meets the original level)
    assert abs(tab["area_um2"][0] / t["area_below_original_level_um2"] - 1) <= 0.01
    # goal: every corner within 1.5 px (best assignment of measured to true corners)
    mc = _corners_um(tab, 0)
    tc = np.array([[c["x_um"], c["y_um"]] for c in t["corners"]])
    worst = min(np.max(np.hypot(*(mc[list(p)] - tc).T)) for p in itertools.permutations(range(4)))
    assert worst <= 1.5 * px


def test_single_ruled_imprint_with_radial_cracks(tmp_path):
    """Seed 8 with 300 nm cracks (fixtures/cracks) from all four corners: d 11.15 µm for 8.11 (+37 %)
    before the crack fill of session 12 (the level contour ran out along the cracks). Tolerances: the
    single-imprint goals."""
    r = render_single_ruled(8, size_px=256)
    t, px = r.truth, r.pixel_um
    corners = np.array([[c["x_um"], c["y_um"]] for c in t["corners"]])
    groove, cracks = radial_cracks(r.height_nm.shape, px, t["centre_um"], corners, np.random.default_rng([8, 7]),
                                   depth_nm=300.0)
    assert len(cracks) == 4
    r = dataclasses.replace(r, height_nm=(r.height_nm + groove).astype(np.float32))
    gsf, _ = write_single_ruled(r, str(tmp_path), "map")
    _assert_single_goals(run_indents([gsf], None, IndentsOptions()).indents, r)


def test_single_ruled_imprint_with_strongly_sunk_in_edges(tmp_path):
    """Unseen seed 127: edges sunk in by 6.4-7.4 % of d/2 make each corner a cusp. The corners' V, fitted
    within 3 px of the diagonal, came out too shallow and every corner 0.3-0.8 px short: d -1.22 px (goal
    1 px). Fitted within 5 px (3 px where a crack runs down the valley). Tolerances: the single-imprint
    goals."""
    r = render_single_ruled(127, size_px=256)
    gsf, _ = write_single_ruled(r, str(tmp_path), "map")
    _assert_single_goals(run_indents([gsf], None, IndentsOptions()).indents, r)


@pytest.mark.parametrize("seed", [4, 8, 9])
def test_single_ruled_imprint_with_wide_radial_cracks(tmp_path, seed):
    """Cracks of 4-7 px FWHM and 100 nm (a scan's lag widens a crack's trace beyond the fill's 5 px disc) from
    all four corners, several running to the border: before session 17 the corners ran out along them to
    the border (d +17 % and +23 %) and the imprint was flagged cut, without an area. The valley is now traced
    out from the half-depth region and the cracks' tongues lifted out of the boundary. Seed 9: the valley's V
    fitted again within 3 px where a crack runs down it (fitted over 5 px only, d -0.08 -> -0.77 %). Tolerances:
    the single-imprint goals (d, depth, area, corners), and the imprint not flagged cut by the border."""
    r = render_single_ruled(seed, size_px=256)
    t, px = r.truth, r.pixel_um
    corners = np.array([[c["x_um"], c["y_um"]] for c in t["corners"]])
    groove, cracks = radial_cracks(r.height_nm.shape, px, t["centre_um"], corners,
                                   np.random.default_rng([seed, 7]), depth_nm=100.0, width_px=(4.0, 7.0))
    assert len(cracks) == 4
    r = dataclasses.replace(r, height_nm=(r.height_nm + groove).astype(np.float32))
    gsf, _ = write_single_ruled(r, str(tmp_path), "map")
    tab = run_indents([gsf], None, IndentsOptions()).indents
    _assert_single_goals(tab, r)
    assert not tab["cut_by_border"][0]


def test_om_aperture_array_against_truth(tmp_path):
    r = render_om_aperture(3, 3.0, size_px=480, pixel_um=0.1, tie_lines=True)
    tif, toml = write_om_aperture(r, str(tmp_path), "om")
    tab = run_indents([tif], read_array_spec(toml)).indents
    imps = r.truth["imprints"]
    txy = np.array([[i["x_um"], i["y_um"]] for i in imps])
    d_err, c_err = {}, {}
    for x, y, dm in zip(tab["x_um"], tab["y_um"], tab["diameter_um"]):
        j = int(np.argmin(np.hypot(*(txy - (x, y)).T)))
        assert j not in d_err and np.hypot(*(txy[j] - (x, y))) < 1.0    # no stray or doubled imprint
        d_err[j] = 1e3 * (dm - imps[j]["d_um"])
        c_err[j] = 1e3 * (np.array([x, y]) - txy[j])
    assert len(d_err) == 25                                              # goal: all 25 found
    assert max(abs(v) for v in d_err.values()) <= 50.0                   # goal: every d within +-50 nm
    e = np.array(list(c_err.values()))
    assert np.sqrt(np.mean(np.sum(e ** 2, axis=1))) <= 10.0              # goal: centre RMS <= 10 nm
    assert np.hypot(*e.mean(axis=0)) <= 10.0                             # goal: image-wide bias <= 10 nm


def test_om_aperture_1um_at_65nm_pixels_leaves_the_sub_resolution_rim(tmp_path):
    """1 µm imprints at 0.065 µm pixels: the joint fit had stopped with a bright rim narrower than the PSF
    around dots 1.25 x too large (diagonals +241 nm on average, up to +328 nm; centres 19.8 nm RMS). The restart from
    smaller dots finds the lower minimum. Tolerances: every diagonal within ±100 nm (at 1 µm under NA 0.9
    the ±50 nm goal is not met from the image alone: docs/indents.md), centres the goal's 10 nm RMS."""
    r = render_om_aperture(1, 1.0, size_px=739, pixel_um=0.065)
    tif, toml = write_om_aperture(r, str(tmp_path), "om65")
    tab = run_indents([tif], read_array_spec(toml)).indents
    imps = r.truth["imprints"]
    txy = np.array([[i["x_um"], i["y_um"]] for i in imps])
    j = [int(np.argmin(np.hypot(*(txy - (x, y)).T))) for x, y in zip(tab["x_um"], tab["y_um"])]
    assert sorted(j) == list(range(25))
    d_err = 1e3 * (np.asarray(tab["diameter_um"]) - np.array([imps[k]["d_um"] for k in j]))
    assert np.abs(d_err).max() <= 100.0
    c_err = 1e3 * (np.column_stack([tab["x_um"], tab["y_um"]]) - txy[j])
    assert np.sqrt(np.mean(np.sum(c_err ** 2, axis=1))) <= 10.0
