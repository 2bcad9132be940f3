"""Height maps as Gwyddion's ASCII data matrix export (``stages/text_maps``): read against values written by
hand and against an independent reader (SurfaceTopography); files without what a map needs refused."""
from __future__ import annotations

import os

import numpy as np
import pytest

from markcal.fixtures.indent_single_ruled import render_single_ruled
from markcal.pipeline.cli import main
from markcal.stages.errors import MarkcalError
from markcal.stages.image_io import read_image
from markcal.stages.text_maps import text_matrix

#: three lines of four values, as Gwyddion writes them (header, tabs, 5 digits), heights in m
GWY_TEXT = ("# Channel: Height\n# Width: 40.000 µm\n# Height: 30.000 µm\n# Value units: m\n"
            "1.0000e-09\t2.0000e-09\t3.0000e-09\t4.0000e-09\n"
            "5.0000e-09\t6.0000e-09\t7.0000e-09\t8.0000e-09\n"
            "9.0000e-09\t1.0000e-08\t1.1000e-08\t1.2500e-08\n")


def _tile(text, times=4):
    """The 4 x 3 example repeated to 16 x 12 (markcal reads maps of 8 pixels or more each way); the field
    grows with it (Width 160 µm over 16 values: still 10 µm pixels)."""
    head, body = text.split("# Value units: m\n")
    lines = ["\t".join([ln] * times) for ln in body.strip().split("\n")] * times
    head = head.replace("40.000 µm", f"{40 * times}.000 µm").replace("30.000 µm", f"{30 * times}.000 µm")
    return head + "# Value units: m\n" + "\n".join(lines) + "\n"


def test_gwyddion_text_matrix_read_as_written(tmp_path):
    """Heights in m to nm; the pixel size is Width over the values per line (10 µm), top line first."""
    p = tmp_path / "map.txt"
    p.write_text(_tile(GWY_TEXT), encoding="utf-8")
    im = read_image(str(p))
    assert im.kind == "afm" and im.shape == (12, 16) and im.pixel_um == pytest.approx(10.0)
    assert im.data[0, :4] == pytest.approx([1.0, 2.0, 3.0, 4.0]) and im.data[2, 3] == pytest.approx(12.5)
    assert im.meta["format"] == "text" and im.meta["channel"] == "Height" and im.meta["z_unit_in_file"] == "m"
    assert "resampled" not in im.meta                           # 160 µm / 16 = 120 µm / 12: square pixels


def test_rectangular_pixels_resampled(tmp_path):
    """A field of 160 x 60 µm over 16 x 12 values: pixels of 10 x 5 µm, resampled to square ones of 5 µm."""
    p = tmp_path / "map.txt"
    p.write_text(_tile(GWY_TEXT).replace("# Height: 120.000 µm", "# Height: 60.000 µm"), encoding="utf-8")
    im = read_image(str(p))
    assert im.pixel_um == pytest.approx(5.0) and im.shape == (12, 32) and "resampled" in im.meta


def test_decimal_comma_and_any_extension(tmp_path):
    """A German locale writes decimal commas and translated labels; the file is recognised by its header
    whatever it is named."""
    text = _tile(GWY_TEXT).replace(".", ",").replace("# Channel", "# Kanal").replace("# Width", "# Breite")
    p = tmp_path / "export.xyz"
    p.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    im = read_image(str(p))
    assert im.pixel_um == pytest.approx(10.0) and im.data[2, 3] == pytest.approx(12.5)


def test_two_channels_in_one_file(tmp_path):
    """Several channels exported into one file: the height channel by default, the others by name; a
    channel that is no height is refused when named."""
    phase = _tile(GWY_TEXT).replace("Channel: Height", "Channel: Phase").replace("Value units: m", "Value units: deg")
    p = tmp_path / "two.txt"
    p.write_text(phase + _tile(GWY_TEXT).replace("e-09", "e-06"), encoding="utf-8")
    im = read_image(str(p))
    assert im.meta["channel"] == "Height" and im.meta["channels"] == ["Phase", "Height"]
    assert im.data[0, 0] == pytest.approx(1000.0)
    with pytest.raises(MarkcalError, match="'Phase' is in 'deg', not a height"):
        read_image(str(p), channel="phase")


def test_against_surfacetopography(tmp_path):
    """The independent reader (SurfaceTopography's text reader, which knows Gwyddion's header) gives the same
    heights and field size for a rendered map written to 5 digits."""
    st = pytest.importorskip("SurfaceTopography")
    r = render_single_ruled(5, size_px=96)
    rows, cols = r.height_nm.shape
    p = tmp_path / "map.txt"
    p.write_text(text_matrix(r.height_nm * 1e-9, cols * r.pixel_um * 1e-6, rows * r.pixel_um * 1e-6),
                 encoding="utf-8")
    im = read_image(str(p))
    ref = st.read_topography(str(p))
    assert ref.unit == "m" and ref.nb_grid_pts == (cols, rows)
    assert np.abs(im.data - ref.heights().T * 1e9).max() < 1e-9                  # (x, y) order there
    assert im.pixel_um == pytest.approx(ref.physical_sizes[0] * 1e6 / cols, rel=1e-12)
    assert np.abs(im.data - r.height_nm).max() <= 5e-5 * np.abs(r.height_nm).max()  # 5 digits


@pytest.mark.parametrize("text,message", [
    ("1.0 2.0 3.0\n" * 12, "no header with its height unit"),
    (GWY_TEXT.replace("Value units: m", "Value units: V"), "in 'V', not a height"),
    (GWY_TEXT + "1.0e-09\t2.0e-09\n", "lines hold 2 to 4 values"),
    (GWY_TEXT.replace("5.0000e-09", "5.0000e-0x"), "line 6 of the text matrix is neither a header nor numbers"),
    ("# Channel: Height\n# Value units: m\n", "holds no numbers"),
])
def test_bad_text_matrix_is_one_line_error(tmp_path, capsys, text, message):
    p = tmp_path / "bad.txt"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(MarkcalError, match=message):
        read_image(str(p))
    out = str(tmp_path / "out")
    assert main(["indents", str(p), "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ") and "bad.txt" in err[0]
    assert not os.path.exists(os.path.join(out, "summary.json"))


def test_no_lateral_unit_asks_for_the_pixel_size(tmp_path):
    p = tmp_path / "map.txt"
    p.write_text(_tile(GWY_TEXT).replace("160.000 µm", "160.000"), encoding="utf-8")
    with pytest.raises(MarkcalError, match="has no length unit: give --pixel-size-um"):
        read_image(str(p))
    assert read_image(str(p), pixel_size_um=0.5).pixel_um == 0.5


def test_renderer_writes_the_text_export(tmp_path):
    """`markcal render afm --single --formats txt` writes heights.txt beside the other formats: the same map
    as heights.gsf, to the export's 5 digits, and the same pixel size."""
    out = str(tmp_path / "r")
    assert main(["render", "afm", "--single", "--seed", "3", "--size-px", "96", "--formats", "gsf,txt",
                 "--out", out, "--quiet"]) == 0
    txt, gsf = read_image(os.path.join(out, "heights.txt")), read_image(os.path.join(out, "heights.gsf"))
    assert txt.pixel_um == pytest.approx(gsf.pixel_um, rel=1e-5) and txt.shape == gsf.shape
    assert np.abs(txt.data - gsf.data).max() <= 5e-5 * np.abs(gsf.data).max()


def test_batch_claims_text_matrices_by_their_header(tmp_path):
    """`markcal batch` measures a Gwyddion text export in a folder (claimed by its header, not its extension)
    and leaves other text files alone."""
    import json
    src = tmp_path / "in"
    src.mkdir()
    r = render_single_ruled(5, size_px=128)
    rows, cols = r.height_nm.shape
    (src / "map.txt").write_text(text_matrix(r.height_nm * 1e-9, cols * r.pixel_um * 1e-6, rows * r.pixel_um * 1e-6),
                                 encoding="utf-8")
    (src / "notes.txt").write_text("measured on Tuesday\n", encoding="utf-8")
    out = tmp_path / "out"
    assert main(["batch", str(src), "-o", str(out), "--workers", "1", "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["map"]
    s = json.loads((out / "map" / "summary.json").read_text())
    assert s["n_imprints"] == 1 and abs(s["mean_d_um"] / r.truth["d_mean_um"] - 1) <= 0.01
