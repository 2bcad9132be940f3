"""Single imprints in OM and SEM micrographs (issue 20 part 5), against the renderer's geometric truth.

The renderer (fixtures/indent_micrograph) draws a pyramid over a general quadrilateral with an
off-centre apex; OM: one-sided facet shading, facets darker to the floor, thin dark ridge and
edge lines, a pile-up halo, vignetting, texture, noise; SEM: detector-side facet contrast, edge
glow, texture, noise and an information bar. Truth comes from the geometry, not from the
measuring code. Tolerances are the brief's: mean diagonal within 1 % (or 1 px, whichever is
larger), every corner within 1.5 px.
"""
import io
import json
import os
import time

import numpy as np
import pytest

from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
from markcal.pipeline.cli import main
from markcal.stages.indent_micrograph import info_bar_rows, measure_micrograph
from realdata import realdata_root

SEM_FILE = "sem_vickers/Indent_20230912_7kV_spot4.5_FOV100um_multiBSE_A_05.tif"


_realdata = realdata_root


def _corner_errors_px(measured_um, truth_um, px):
    """Distance (px) of every true corner to the nearest measured one."""
    m = np.asarray(measured_um) / px
    return np.array([np.min(np.hypot(*(m - t).T)) for t in np.asarray(truth_um) / px])


def _tiff(tmp_path, r, name="micrograph.tif"):
    import tifffile
    buf = io.BytesIO()
    tifffile.imwrite(buf, r.data, imagej=True, resolution=(1.0 / r.pixel_um, 1.0 / r.pixel_um),
                     metadata={"unit": "um"})
    path = os.path.join(str(tmp_path), name)
    with open(path, "wb") as fh:
        fh.write(buf.getvalue())
    return path


@pytest.mark.parametrize("style,seed", [("om", 0), ("om", 1), ("om", 2), ("sem", 0), ("sem", 1), ("sem", 2)])
def test_single_micrograph_against_truth(style, seed):
    r = render_micrograph(seed, MicrographOptions(style=style, bar_rows=40 if style == "sem" else 0))
    t = r.truth["imprints"][0]
    px = r.pixel_um
    imps, _bar = measure_micrograph(r.data, px)
    assert len(imps) == 1                                         # the imprint, nothing else
    m = imps[0]
    # worst on these six seeds: mean diagonal 0.38 px, a corner 0.78 px (goals 1 % or 1 px, 1.5 px; forward-difference
    # Jacobians before session 18: 0.66 and 0.56 px)
    assert abs(m.d_um - t["d_um"]) <= 1.0 * px
    assert np.all(_corner_errors_px(m.corners_um, t["corners_um"], px) <= 1.0)
    assert not m.cut_by_border


@pytest.mark.parametrize("seed", [10, 11, 12])
def test_small_om_imprint_not_short(seed):
    """95 px imprints in OM renders (dark edge lines, halo): a wedge-sum model of the blurred corners
    made them about 1.3 px short (fixed: worst 0.39 px on the diagonal, 0.31 px on a corner). Since each
    corner is refitted on its own pixels (bowed edges, session 9) the worst is 0.76 px on the diagonal (0.74 px
    with the analytic derivatives of session 18): the tolerance is the goal's 1 px (1 % is 0.95 px here)."""
    _check_one_imprint(render_micrograph(seed, MicrographOptions(style="om", d_um=9.5)), 1.0, 0.6)


def _check_one_imprint(r, d_tol_px, corner_tol_px):
    """One imprint found; mean diagonal and corners within the tolerances (px) of the truth."""
    t = r.truth["imprints"][0]
    px = r.pixel_um
    imps, _bar = measure_micrograph(r.data, px)
    assert len(imps) == 1
    assert abs(imps[0].d_um - t["d_um"]) <= d_tol_px * px
    assert np.all(_corner_errors_px(imps[0].corners_um, t["corners_um"], px) <= corner_tol_px)


def test_halo_does_not_skip_full_resolution_level():
    """OM seed 3119 (119 px, wide halo): the coarse outline held the halo (> 160 px), so the fit
    stopped at the 2x level, +3.0 px; the level is now chosen on the fitted size: +0.42 px, corners
    0.32 px (+0.52 and 0.45 px with the analytic derivatives of session 18, when the 2x level alone reads
    +0.58 px: this test no longer tells the two apart; tolerances about 2x the first figures)."""
    _check_one_imprint(render_micrograph(3119, MicrographOptions(style="om")), 0.8, 0.65)


def test_info_bar_found_and_left_out():
    r = render_micrograph(5, MicrographOptions(style="sem", bar_rows=48))
    assert info_bar_rows(r.data.astype(float)) == 48 + 2          # the bar and two rows of margin
    plain = render_micrograph(5, MicrographOptions(style="om"))
    assert info_bar_rows(plain.data.astype(float)) == 0


def test_two_imprints_in_one_micrograph():
    r = render_micrograph(3, MicrographOptions(style="om", rows=400, cols=720, n_imprints=2, d_um=13.0))
    px = r.pixel_um
    imps, _ = measure_micrograph(r.data, px)
    assert len(imps) == 2
    for t in r.truth["imprints"]:
        m = min(imps, key=lambda q: np.hypot(q.x_um - t["x_um"], q.y_um - t["y_um"]))
        assert abs(m.d_um - t["d_um"]) <= max(0.01 * t["d_um"], px)
        assert np.all(_corner_errors_px(m.corners_um, t["corners_um"], px) <= 1.5)


def test_cli_measures_a_rendered_micrograph(tmp_path):
    r = render_micrograph(2, MicrographOptions(style="om"))
    out = str(tmp_path / "out")
    assert main(["indents", _tiff(tmp_path, r), "--out", out, "--quiet"]) in (0, 4)
    s = json.load(open(os.path.join(out, "summary.json")))
    assert s["n_imprints"] == 1
    t = r.truth["imprints"][0]
    assert abs(s["mean_d_um"] - t["d_um"]) <= max(0.01 * t["d_um"], r.pixel_um)
    html = open(os.path.join(out, "report.html")).read()
    assert "each corner magnified" in html


def test_cli_render_single_sem_and_measure(tmp_path):
    """``markcal render om --single --style sem`` writes image.tif + truth.json that the flow measures."""
    rdir, out = str(tmp_path / "r"), str(tmp_path / "o")
    assert main(["render", "om", "--single", "--style", "sem", "--seed", "1", "--out", rdir, "--quiet"]) == 0
    assert main(["indents", os.path.join(rdir, "image.tif"), "--out", out, "--quiet", "--no-report"]) in (0, 4)
    t = json.load(open(os.path.join(rdir, "truth.json")))["imprints"][0]
    s = json.load(open(os.path.join(out, "summary.json")))
    assert s["n_imprints"] == 1
    assert abs(s["mean_d_um"] - t["d_um"]) <= 0.1                 # 1 px; worst on the test seeds 0.66 px


def test_micrograph_without_imprint_is_refused(tmp_path, capsys):
    """Texture and noise only: one line, exit 1, no summary.json."""
    r = render_micrograph(1, MicrographOptions(style="om"))
    blank = np.random.default_rng(0).normal(30000, 400, r.data.shape).astype(np.uint16)
    path = _tiff(tmp_path, r.__class__(data=blank, pixel_um=r.pixel_um, kind="om", truth={}), "blank.tif")
    out = str(tmp_path / "o")
    assert main(["indents", path, "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ") and "blank.tif" in err[0]
    assert not os.path.exists(os.path.join(out, "summary.json"))


def test_real_sem_vickers_imprint(tmp_path):
    """The real FEI SEM image: one imprint of about 19-20 µm, corners inside, in reasonable time.

    A careful manual reading of the corners on the screen (915, 528), (752, 653), (622, 497),
    (783, 363) px gives d = 19.09 µm; the check here is the brief's: 17-23 µm, d1/d2 within 10 %.
    """
    path = _realdata() / SEM_FILE
    if not path.is_file():
        pytest.skip(f"real file {SEM_FILE} not present (../shared/realdata)")
    out = str(tmp_path / "sem")
    t0 = time.process_time()                  # CPU: the wall clock follows the other jobs' load
    assert main(["indents", str(path), "--out", out, "--quiet"]) in (0, 4)
    elapsed = time.process_time() - t0
    s = json.load(open(os.path.join(out, "summary.json")))
    assert s["n_imprints"] == 1
    rows = open(os.path.join(out, "indents.csv")).read().splitlines()
    head = rows[0].split(",")
    row = dict(zip(head, rows[1].split(",")))
    d1, d2 = float(row["diag1_um"]), float(row["diag2_um"])
    assert 17.0 <= d1 <= 23.0 and 17.0 <= d2 <= 23.0
    assert abs(d1 / d2 - 1) <= 0.10
    assert row["cut_by_border"] == "0"
    assert abs(s["mean_d_um"] - 19.09) <= 0.02 * 19.09             # the manual reading above, 2 %
    # the manual corners' diagonals differ by 1.02 % of their mean (294.6 and 291.7 px): within a point of it,
    # and under ISO 6507-1's 5 %, so nothing is stated
    assert abs(float(row["diagonal_difference_pct"]) - 1.02) <= 1.0 and s["n_diagonals_differ"] == 0
    assert elapsed < 15.0, f"SEM image took {elapsed:.1f} s CPU"


def test_real_sem_corners_and_area_against_manual_reading():
    """The real SEM image against the careful manual corner reading above (no reference is published).

    Tolerances from the SEM goal of 2 % on the mean diagonal: the quadrilateral's area within 4 % of the manual
    one (area goes as d^2); corners within 2 % of d (5.9 px) of the manual ones, except the bottom corner,
    where the ridge-end override puts it 6.8 px from the manual reading (docs/indents.md); that one within 3 %.
    The bowed outline's area exceeds the quadrilateral's when the edges bow outwards.
    """
    from markcal.stages.image_io import read_image
    path = _realdata() / SEM_FILE
    if not path.is_file():
        pytest.skip(f"real file {SEM_FILE} not present (../shared/realdata)")
    img = read_image(str(path))
    imps, bar = measure_micrograph(img.data, img.pixel_um)
    assert len(imps) == 1 and bar >= 80
    m = imps[0]
    manual = np.array([(915, 528), (752, 653), (622, 497), (783, 363)], float)
    c = m.corners_um / img.pixel_um
    dist = np.array([np.min(np.hypot(*(c - q).T)) for q in manual])
    d_px = 19.09 / img.pixel_um
    assert np.sum(dist <= 0.02 * d_px) >= 3 and np.all(dist <= 0.03 * d_px), dist

    def quad(p):
        return 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))

    assert abs(quad(m.corners_um) / quad(manual * img.pixel_um) - 1) <= 0.04
    assert np.isfinite(m.edge_bow) and (m.area_um2 > quad(m.corners_um)) == (m.edge_bow > 0)


def _real_sem_by_squares():
    """The real SEM image's imprints fitted from the BSE fallback's squares alone, the squares, the manual
    corners, and the pixel size; None without the file."""
    from markcal.stages.image_io import read_image
    from markcal.stages.indent_micrograph import MIN_DIAGONAL_PX, _measure_all
    from markcal.stages.indent_square_search import square_candidates
    path = _realdata() / SEM_FILE
    if not path.is_file():
        pytest.skip(f"real file {SEM_FILE} not present (../shared/realdata)")
    img = read_image(str(path))
    work = img.data[:img.data.shape[0] - info_bar_rows(img.data)]
    cands = square_candidates(work, MIN_DIAGONAL_PX)
    manual = np.array([(915, 528), (752, 653), (622, 497), (783, 363)], float)
    return _measure_all(work, img.pixel_um, MIN_DIAGONAL_PX, cands), cands, manual, img.pixel_um


def test_real_sem_square_search_lands_on_the_imprint():
    """The real SEM image through the BSE fallback alone (squares with four clear edges as fit starts; the
    outline detection finds this imprint, so the flow never runs the fallback on it). A dark dust blob of
    40 px had won while squares under the minimum diagonal were scored (nothing found); and a short edge's
    mean gradient can beat a long one's by chance, so the score is the weakest edge's significance. Now a
    square lies on the imprint (within a fifth of d of the manual centre) and the fit from it finds one
    imprint centred within 5 % of d of the manual corners' mean (ranked by the plain mean, the squares led the
    fit to 10.6 um)."""
    imps, cands, manual, px = _real_sem_by_squares()
    d_px = 19.09 / px
    assert any(np.hypot(*(c[1] - manual.mean(axis=0))) < 0.2 * d_px for c in cands)
    assert len(imps) == 1
    assert np.hypot(imps[0].x_um / px - manual[:, 0].mean(), imps[0].y_um / px - manual[:, 1].mean()) < 0.05 * d_px


def test_real_sem_square_search_diagonal_against_manual_reading():
    """The same imprint's mean diagonal against the manual 19.09 um, to the SEM goal of 2 %. From the squares'
    start the right-hand corner lies on a faint edge where the cost is flat over 40 px; with forward-difference
    Jacobians the fit stopped 48 px short there (17.93 um, -6.1 %). With the exact gradient of the reweighted
    cost it reaches the corner: 19.23 um (+0.7 %); three corners within 1.5 px of the manual reading, the bottom
    one 5.8 px."""
    imps, _cands, _manual, _px = _real_sem_by_squares()
    assert len(imps) == 1 and abs(imps[0].d_um / 19.09 - 1) <= 0.02
