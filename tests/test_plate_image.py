"""Images of the marked plate through the scan flow: centres against the renderer's truth, formats,
pixel size, mirror, bad input. Truth: fixtures/plate_image.py (box lines blurred and pixel-integrated,
rings marked through the true galvo), not the flow's Gaussian ring model."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from markcal.fixtures.plate_image import ImageOptions, render_plate_image, save_plate_image
from markcal.pipeline.flows.scan import FLOW
from markcal.pipeline.flows.scan import ScanOptions as FlowOptions
from markcal.pipeline.flows.scan import run_scan
from markcal.stages.errors import MarkcalError
from markcal.stages.plate import PlateSpec
from markcal.stages.plate_image import read_plate_image

SPEC = PlateSpec(rows=5, cols=5)
MARKED = PlateSpec(rows=5, cols=5, orientation_mark=(0, 1))
GOAL_PX = 0.1          # issue 22: centre error <= 0.1 px RMS at 1200 dpi
# SPEC has no orientation mark, so the flow refuses unless told how the plate lay (images render within +-5 deg)
UPRIGHT = FlowOptions(orientation="upright")


def _pixel_errors(res, render):
    f, t = res.fiducials, render.truth["fiducials"]
    ids = f["id"]
    col = f["x_scanner_mm"] / render.pixel_mm - 0.5
    row = f["y_scanner_mm"] / render.pixel_mm - 0.5
    return np.hypot(col - np.array(t["col_px"])[ids], row - np.array(t["row_px"])[ids])


@pytest.fixture(scope="module")
def tif_1200(tmp_path_factory):
    r = render_plate_image(11, SPEC, ImageOptions(dpi=1200))
    return r, save_plate_image(str(tmp_path_factory.mktemp("img")), r, fmt="tif")


def test_1200_dpi_centres_within_a_tenth_of_a_pixel(tif_1200):
    r, paths = tif_1200
    res = run_scan(paths["image"], SPEC, UPRIGHT)
    e = _pixel_errors(res, r)
    assert res.summary["n_detected"] == 25
    assert np.sqrt(np.mean(e ** 2)) <= GOAL_PX and e.max() <= 3 * GOAL_PX
    assert res.summary["image_pixel_mm"] == pytest.approx(25.4 / 1200, rel=1e-9)
    assert res.summary["image_inverted"] is True          # anodised: bright marks


@pytest.mark.parametrize("fmt,kw", [("png", {"material": "paper", "bits": 16, "dpi": 800}),
                                    ("jpg", {"rgb": True, "dpi": 600, "jpeg_quality": 80})])
def test_formats_depths_and_materials(tmp_path, fmt, kw):
    r = render_plate_image(12, SPEC, ImageOptions(**kw))
    paths = save_plate_image(str(tmp_path), r, fmt=fmt)
    res = run_scan(paths["image"], SPEC, UPRIGHT)
    e = _pixel_errors(res, r)
    assert res.summary["n_detected"] == 25 and np.sqrt(np.mean(e ** 2)) <= GOAL_PX
    assert res.summary["image_bits"] == kw.get("bits", 8)


def test_face_down_plate_at_any_angle_with_an_orientation_mark(tmp_path):
    r = render_plate_image(13, MARKED, ImageOptions(dpi=600, mirror=True, rotation_deg=-120.0))
    paths = save_plate_image(str(tmp_path), r, fmt="png")
    res = run_scan(paths["image"], MARKED, FlowOptions(mirror="auto"))
    e = _pixel_errors(res, r)
    assert res.summary["mirrored"] is True and res.summary["orientation_method"].startswith("orientation mark")
    assert res.summary["n_detected"] == 24 and e.max() <= 0.5     # a wrong index is >= 1 pitch (500 px) off


def test_pixel_size_option_overrides_and_missing_dpi_is_refused(tmp_path):
    r = render_plate_image(14, SPEC, ImageOptions(dpi=600))
    paths = save_plate_image(str(tmp_path), r, fmt="png", dpi_tags=False)
    with pytest.raises(MarkcalError, match="no pixel size.*--pixel-size-mm"):
        read_plate_image(paths["image"])
    res = run_scan(paths["image"], SPEC, FlowOptions(pixel_size_mm=25.4 / 600, orientation="upright"))
    assert np.sqrt(np.mean(_pixel_errors(res, r) ** 2)) <= GOAL_PX


def test_screen_default_dpi_is_not_a_pixel_size(tmp_path):
    from PIL import Image
    p = tmp_path / "screen.png"
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(p, dpi=(72, 72))
    with pytest.raises(MarkcalError, match="72 dpi"):
        read_plate_image(p)


def _cli(args):
    return subprocess.run([sys.executable, "-m", "markcal.pipeline.cli", *args], capture_output=True, text=True)


@pytest.mark.parametrize("case", ["no_dpi", "too_small", "no_marks", "too_coarse"])
def test_bad_images_one_line_exit_1_nothing_written(tmp_path, case):
    from PIL import Image
    from markcal.fixtures.scan_plate import plate_spec_toml
    plate = tmp_path / "plate.toml"
    plate.write_text(plate_spec_toml(SPEC))
    img = tmp_path / "plate.png"
    rng = np.random.default_rng(0)
    if case == "no_dpi":
        Image.fromarray(rng.integers(0, 255, (400, 400), dtype=np.uint8)).save(img)
        want = "no pixel size"
    elif case == "too_small":
        Image.fromarray(rng.integers(0, 255, (200, 200), dtype=np.uint8)).save(img, dpi=(1200, 1200))
        want = "too small"
    elif case == "no_marks":
        Image.fromarray((120 + rng.normal(0, 3, (1200, 1200))).astype(np.uint8)).save(img, dpi=(600, 600))
        want = "no circles|fiducials found"
    else:
        Image.fromarray(rng.integers(0, 255, (400, 400), dtype=np.uint8)).save(img, dpi=(150, 150))
        want = "ring gap"
    out = tmp_path / "out"
    p = _cli(["scan", str(img), "--plate", str(plate), "--out", str(out), "--quiet"])
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert lines[0].startswith(f"markcal: error: {img}") and __import__("re").search(want, lines[0]), lines[0]
    assert not (out / "summary.json").exists()


def test_cli_render_and_scan_image(tmp_path):
    folder = tmp_path / "r"
    p = _cli(["render", "scan-image", "--rows", "5", "--cols", "5", "--dpi", "600", "--seed", "5",
              "--format", "jpg", "--rgb", "--out", str(folder), "--quiet"])
    assert p.returncode == 0, p.stderr
    p = _cli(["scan", str(folder / "plate.jpg"), "--plate", str(folder / "plate.toml"), "--out",
              str(tmp_path / "out"), "--quiet", "--model", "physical+rbf", "--no-report"])
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    # a calibration plate (the default purpose) is judged on the correction: every mark found, CV RMSE <= 0.047 mm
    # (the physical+rbf model has no predicted residual); its own deviation is what it measures
    assert p.returncode == 0 and s["verdict"] == "pass" and s["checks"].endswith("n_missing <= 0"), p.stderr
    assert s["n_detected"] == 24 and s["model"] == "physical+rbf"      # site 0,1 left unmarked by default and s["image_pixel_size_from"].startswith("600 dpi")


def test_batch_claims_images_only_beside_a_plate_spec(tmp_path):
    from PIL import Image
    img = tmp_path / "a.tif"
    Image.fromarray(np.zeros((32, 32), np.uint8)).save(img)
    assert not FLOW.claims(img)
    (tmp_path / "a.toml").write_text("[array]\nrows = 2\n")          # an indents array spec
    assert not FLOW.claims(img)
    (tmp_path / "a.toml").write_text("[grid]\nrows = 5\ncols = 5\n")
    assert FLOW.claims(img)
