"""Single-imprint micrographs from a renderer written without knowledge of markcal (fixtures/indent_micrograph_independent):
edges bowed by 3 % of d/2 either way. Tolerance: the mean diagonal within 1 % (the SEM goal is 2 %; an operator reads
to 0.5-1 %). Before each corner was refitted on its own pixels the straight-edge fit read +3.0 / -1.2 % (OM) and
+3.1 / -3.2 % (SEM)."""
import numpy as np
import pytest

from markcal.fixtures.indent_micrograph_independent import render_micrograph_independent
from markcal.stages.indent_micrograph import measure_micrograph


@pytest.mark.parametrize("seed,kind,bow", [(4, "om", -0.03), (4, "om", 0.03), (6, "sem", -0.03), (6, "sem", 0.03)])
def test_bowed_edges_corner_to_corner(seed, kind, bow):
    img, px, truth = render_micrograph_independent(seed, kind, bow)
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 1
    t = truth["imprints"][0]
    assert abs(imps[0].d_um / t["d_um"] - 1) <= 0.01
    assert abs(imps[0].x_um - t["x_um"]) <= px and abs(imps[0].y_um - t["y_um"]) <= px


def _truth_area_um2(t):
    """Area inside the renderer's bowed outline: the quadrilateral and four parabolic segments (2/3 base x
    height; the renderer's bow is inward positive)."""
    c = np.array(t["corners_um"])
    x, y = c[:, 0], c[:, 1]
    quad = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    edges = np.hypot(*(np.roll(c, -1, axis=0) - c).T)
    return quad - float(np.sum(2.0 / 3.0 * edges * t["bow_um"]))


@pytest.mark.parametrize("bow", [-0.03, 0.03])
def test_bowed_edges_bow_and_area(bow):
    """Bowed edges were refused as no imprint before the model bowed them (residual 4-5 noise levels at a contrast
    of 75): now found, the bow within 0.005 of d/2 (0.6 px here) and the area within 1 % (the goal for AFM areas)."""
    img, px, truth = render_micrograph_independent(5, "om", bow)
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 1
    t = truth["imprints"][0]
    assert abs(imps[0].d_um / t["d_um"] - 1) <= 0.005
    assert abs(imps[0].edge_bow - (-t["bow_um"] / (t["d_um"] / 2))) <= 0.005
    assert abs(imps[0].area_um2 / _truth_area_um2(t) - 1) <= 0.01


def test_two_imprints_with_scratches_between():
    """Two crossing scratches closed a loop with the left imprint, whose filled outline then started the fit turned
    by 20 degrees: one imprint of two found (before), both within 0.5 % now."""
    img, px, truth = render_micrograph_independent(3, "om", -0.03)
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 2
    for t in truth["imprints"]:
        m = min(imps, key=lambda m: np.hypot(m.x_um - t["x_um"], m.y_um - t["y_um"]))
        assert np.hypot(m.x_um - t["x_um"], m.y_um - t["y_um"]) <= 2 * px
        assert abs(m.d_um / t["d_um"] - 1) <= 0.005


def test_imprint_whose_facets_barely_differ_is_found():
    """OM seed 7: the right-hand imprint's facets barely differ (light from near above), so at the coarsest
    blocks its ridges and apex were lost: the fitted square was right, but its apex lay 0.22 d off the centre
    and the candidate was dropped (one imprint of two found). The apex now restarts from the square's centre
    when the square alone is plausible: both found, within 0.5 % and 2 px."""
    img, px, truth = render_micrograph_independent(7, "om", None)
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 2
    for t in truth["imprints"]:
        m = min(imps, key=lambda m: np.hypot(m.x_um - t["x_um"], m.y_um - t["y_um"]))
        assert np.hypot(m.x_um - t["x_um"], m.y_um - t["y_um"]) <= 2 * px
        assert abs(m.d_um / t["d_um"] - 1) <= 0.005


def test_sem_imprints_seen_by_their_edge_glow():
    """Facets within 2-3 noise levels of the surroundings, edges glowing at 23: both imprints found, within 1 %."""
    img, px, truth = render_micrograph_independent(3, "sem", 0.03)
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 2
    for t in truth["imprints"]:
        m = min(imps, key=lambda m: np.hypot(m.x_um - t["x_um"], m.y_um - t["y_um"]))
        assert abs(m.d_um / t["d_um"] - 1) <= 0.01


def test_large_sem_imprint_corners_not_moved_to_glowing_ridge_ends():
    """A 628 px SEM imprint: fitted on blocks of up to 4 px (the finest level has at most 160 blocks across), its
    ridges glowing past two corners had moved them 45 px out (+7 %) through the ridge-end override; now within 0.5 %."""
    img, px, truth = render_micrograph_independent(10, "sem")
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 1
    t = truth["imprints"][0]
    assert t["d_um"] / px > 600
    assert abs(imps[0].d_um / t["d_um"] - 1) <= 0.005


def test_missing_pixels_do_not_hide_the_imprint():
    """NaN pixels (a float TIFF with a masked spot) away from the imprint: before, the background fit of the
    detection turned NaN and nothing was found; now they read as the typical grey."""
    img, px, truth = render_micrograph_independent(5, "om", 0.03)
    img = img.astype(float)
    img[10:30, 10:30] = np.nan
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 1
    assert abs(imps[0].d_um / truth["imprints"][0]["d_um"] - 1) <= 0.005


def test_jpeg_colour_micrograph_through_the_cli(tmp_path):
    """An OM micrograph saved as a colour JPEG (quality 85), the pixel size given on the command line, as a camera
    on a light microscope writes it: read as luminance and measured within 1 % (PNG, JPEG and BMP were not read)."""
    import csv
    from PIL import Image
    from markcal.pipeline.cli import main
    img, px, truth = render_micrograph_independent(2, "om")
    tint = np.stack([img * 0.9, img, img * 0.8], axis=-1).clip(0, 255).astype(np.uint8)
    p = tmp_path / "om.jpg"
    Image.fromarray(tint).save(p, quality=85)
    out = tmp_path / "out"
    assert main(["indents", str(p), "--pixel-size-um", f"{px:.9f}", "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "indents.csv")))
    assert len(rows) == 1
    assert abs(float(rows[0]["d_um"]) / truth["imprints"][0]["d_um"] - 1) <= 0.01


def _bse_file(tmp_path, seed, rows=slice(None), cols=slice(None)):
    """A BSE render (or a crop of it) written as a 16-bit TIFF without a pixel size; its pixel size and truth."""
    import tifffile
    img, px, truth = render_micrograph_independent(seed, "sem")
    path = str(tmp_path / f"bse{seed}.tif")
    tifffile.imwrite(path, img[rows, cols].astype(np.uint16))
    return path, px, truth


def test_bse_grain_contrast_square_search(tmp_path):
    """BSE images whose grains (3-8 % contrast) cut the imprint's outline into pieces: no imprint was found
    (seeds 1, 7 and 8). Seed 1's 265 dark grain spots come in every size (90th/10th percentile radius 2.2); the
    flow then looks for squares with four clear edges before the dots' shared fit, which had reported 120 grain
    specks as imprints in 9-13 s."""
    from markcal.pipeline.flows.indents import IndentsOptions, measure_file
    path, px, truth = _bse_file(tmp_path, 1)
    said = []
    f = measure_file(path, None, IndentsOptions(pixel_size_um=px), say=said.append)
    assert len(f.imprints) == len(truth["imprints"]) == 1
    t, m = truth["imprints"][0], f.imprints[0]
    assert np.hypot(m.x_um - t["x_um"], m.y_um - t["y_um"]) <= 2 * px
    assert abs(m.d_um / t["d_um"] - 1) <= 0.01
    assert any("265 dark spots of every size" in s for s in said)
    assert not any("fitting" in s for s in said)           # the dots' shared fit never ran


def test_grain_spots_of_one_imprint_refused_by_their_sizes(tmp_path, monkeypatch):
    """The same image with the spots' size check before the fit switched off: the dots' fit reports 41 spots
    of 0.3-0.91 µm (one imprint of the array has one size; 96-100 % of the dots of every OM array render lie
    within 20 % of their median diagonal, of these 55 %), refuses them, and the four-edge search finds the
    imprint (a crop of 600 x 700 px around it, to keep the fit short)."""
    from markcal.pipeline.flows.indents import IndentsOptions, measure_file
    from markcal.stages import indent_select
    monkeypatch.setattr(indent_select, "mixed_spots", lambda radii: False)
    path, px, truth = _bse_file(tmp_path, 1, slice(150, 750), slice(600, 1300))
    said = []
    f = measure_file(path, None, IndentsOptions(pixel_size_um=px), say=said.append)
    assert len(f.imprints) == 1
    t, m = truth["imprints"][0], f.imprints[0]
    assert np.hypot(m.x_um + 600 * px - t["x_um"], m.y_um + 150 * px - t["y_um"]) <= 2 * px
    assert abs(m.d_um / t["d_um"] - 1) <= 0.01
    assert any("have no common size" in s for s in said) and any("fitting" in s for s in said)


def test_grain_without_an_imprint_is_no_imprint(tmp_path, capsys):
    """A crop of seed 1 beside the imprint (grain only): one line, exit 1, nothing written. The dark spots were
    reported as imprints of 0.3-1.1 µm before."""
    from markcal.pipeline.cli import main
    path, px, truth = _bse_file(tmp_path, 1, slice(150, 650), slice(1080, 1536))
    t = truth["imprints"][0]
    assert t["x_um"] + t["d_um"] / 2 < 1080 * px                     # the imprint lies left of the crop
    out = tmp_path / "out"
    assert main(["indents", path, "--pixel-size-um", f"{px:.9f}", "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"markcal: error: {path}: no imprint found: ")
    assert "have no common size" in err[0] and not out.exists()


def test_spot_size_rules():
    """Spots of every size against an array's; the share of imprints within 20 % of the median diagonal."""
    from types import SimpleNamespace
    from markcal.stages.indent_select import mixed_spots, one_size
    rng = np.random.default_rng(0)
    assert not mixed_spots(rng.normal(7.0, 0.2, 25))                           # an array's dots
    assert not mixed_spots(np.r_[rng.normal(7.0, 0.2, 25), [2.0, 2.5]])        # and two dust specks
    assert mixed_spots(1.7 + rng.exponential(0.8, 200))                        # grain down to the detection floor
    assert not mixed_spots([2.0, 6.0, 9.0])                                     # too few to tell
    imps = lambda d: [SimpleNamespace(d_um=v) for v in d]                       # noqa: E731
    assert one_size(imps(rng.normal(1.0, 0.03, 25)))
    assert one_size(imps(np.r_[np.full(20, 1.0), np.full(5, 0.4)]))            # 80 % within 20 %
    assert not one_size(imps(np.r_[np.full(18, 1.0), np.full(7, 0.4)]))        # 72 %
    assert one_size(imps([0.3, 1.0, 3.0]))                                      # fewer than 5: no judgement

def test_corner_short_on_a_faint_edge_fitted_again():
    """BSE seed 1, edges bowed by -3 %: one corner lies where two facets as bright as the surroundings meet, the cost
    is flat there, and the outline's start left that corner 42 px short (d -5.7 %, diagonals 26 % apart). A fit whose
    diagonals differ by more than 5 % is tried again from the square on its longer diagonal and the lower cost kept:
    -0.17 %. Tolerance: the SEM goal of 2 %, and the imprint where the truth has it (2 px)."""
    _one_imprint_to_the_sem_goal(1, -0.03)


def test_apex_adrift_where_the_ridges_do_not_show():
    """BSE seed 12, edges bowed by -3 %: the facets pair up in brightness, the ridges hardly show, and the cost is flat
    along the apex; the fit left it more than 0.06 d off the corners' mean and the imprint was refused (no imprint
    found, after 3.9 s of fallbacks). The apex is refitted from the corners' mean and kept at no higher cost: found,
    -0.28 %. Tolerance: the SEM goal of 2 %, the centre within 2 px."""
    _one_imprint_to_the_sem_goal(12, -0.03)


def _one_imprint_to_the_sem_goal(seed, bow):
    """One imprint found in SEM render ``seed``, its mean diagonal within the SEM goal of 2 %, its centre within 2 px."""
    img, px, truth = render_micrograph_independent(seed, "sem", bow)
    imps, _bar = measure_micrograph(img, px)
    assert len(imps) == 1
    t = truth["imprints"][0]
    assert abs(imps[0].d_um / t["d_um"] - 1) <= 0.02
    assert np.hypot(imps[0].x_um - t["x_um"], imps[0].y_um - t["y_um"]) <= 2 * px
