"""The scan report's output side: one-pass PNG figures, the numpy cloud view, fast CSV, figure progress lines."""
from __future__ import annotations

import base64
import csv
import io
import re
import threading

import numpy as np
import pytest
from PIL import Image

from markcal.reports import drawing, html
from markcal.reports.cloud_view import VIEW_DIR, IsoView, splat
from markcal.reports.files import _fmt, write_csv


def _png_size(data: bytes) -> tuple:
    return Image.open(io.BytesIO(data)).size


def _figure(title="a plot", outside=False):
    fig = html.new_figure(4.0, 3.0)
    fig.subplots_adjust(bottom=0.2, top=0.85)
    ax = fig.add_subplot(111)
    ax.plot([0, 1, 2], [1, 0, 2])
    ax.set_xlabel("x (mm)")
    ax.set_title(title)
    if outside:                                   # an artist beyond the canvas' right edge
        fig.text(1.15, 0.5, "outside the canvas", transform=fig.transFigure)
    return fig


def test_png_crop_matches_savefig_tight():
    ref = io.BytesIO()
    _figure().savefig(ref, format="png", dpi=html.DPI, bbox_inches="tight")
    w_ref, h_ref = _png_size(ref.getvalue())
    w, h = _png_size(html.png_bytes(_figure()))
    # the same tight box cut from the one drawing: the same size to a pixel of rounding
    assert abs(w - w_ref) <= 1 and abs(h - h_ref) <= 1, (w, h, w_ref, h_ref)
    assert w < 400 and h < 300                      # cropped: the canvas is 400 x 300 px


def test_png_keeps_artists_outside_the_canvas():
    w, _ = _png_size(html.png_bytes(_figure(outside=True)))
    assert w > 400 + 60                             # the outside text widened the picture as savefig tight does


def test_png_draws_a_title_with_stray_bytes():
    data = html.png_bytes(_figure(title="plate_\udcff.ply"))
    assert _png_size(data)[0] > 100


def test_figure_progress_lines_only_in_the_registering_thread(monkeypatch):
    said = []
    monkeypatch.setattr(html, "FIGURE_PROGRESS_EVERY_S", 0.0)
    html.figure_progress(said.append)
    try:
        html.png_b64(_figure())
        html.png_b64(_figure())
        t = threading.Thread(target=lambda: html.png_b64(_figure()))
        t.start()
        t.join()
    finally:
        html.figure_progress(None)
    html.png_b64(_figure())
    assert said == ["report: 1 figure drawn", "report: 2 figures drawn"]


def test_figure_progress_is_throttled(monkeypatch):
    said = []
    monkeypatch.setattr(html, "FIGURE_PROGRESS_EVERY_S", 3600.0)
    html.figure_progress(said.append)
    try:
        html.png_b64(_figure())
    finally:
        html.figure_progress(None)
    assert said == []


def _csv_module(columns: dict) -> str:
    """The cell-by-cell writer write_csv replaced, as the reference."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(list(columns))
    cols = [np.asarray(c) for c in columns.values()]
    for i in range(len(cols[0]) if cols else 0):
        w.writerow([_fmt(c[i]) for c in cols])
    return buf.getvalue()


@pytest.mark.parametrize("columns", [
    {"x_mm": np.random.default_rng(1).normal(size=40) * 10.0 ** np.arange(-20, 20), "id": np.arange(40),
     "f32": np.linspace(0, 1, 40, dtype=np.float32), "used": np.arange(40) % 3 == 0,
     "u8": np.arange(40, dtype=np.uint8)},
    {"v": np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-300, 5e-324])},
    {"a": np.array([], float), "b": np.array([], int)},
    {"name": np.array(["a,b", 'q"r', "plain"]), "v": np.array([1.0, np.nan, 3.0])},
    {},
])
def test_write_csv_same_bytes_as_the_csv_module(tmp_path, columns):
    p = tmp_path / "t.csv"
    write_csv(p, columns)
    assert p.read_text() == _csv_module(columns)


def test_iso_view_projects_like_the_isometric_camera():
    pts = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100]])
    v = IsoView(pts, 400, 300)
    px = v.to_pixel(pts)
    assert np.allclose(v.to_pixel(VIEW_DIR * 50.0), v.to_pixel([0.0, 0, 0]), atol=1e-9)   # along the view: one pixel
    assert np.allclose(v.direction([0, 0, 1]), [0, -1], atol=1e-12)                       # z straight up
    dx, dy = v.direction([1, 0, 0]), v.direction([0, 1, 0])
    assert dx[0] < 0 < dy[0] and dx[1] > 0 and dy[1] > 0                                 # x down-left, y down-right
    assert np.all((px >= 0) & (px <= [400, 300]))                                        # framed
    assert v.depth([0.0, 0, 0]) > v.depth(VIEW_DIR * 10)                                  # nearer the camera


def test_splat_shows_the_nearest_point_and_leaves_gaps_empty():
    v = IsoView(np.array([[-50.0, -50, 0], [50, 50, 0]]), 200, 200)
    far, near = np.array([0.0, 0, 0]), VIEW_DIR * 20.0             # same pixel, near one in front
    pic = splat(v, np.array([far, near]), np.array([1.0, 7.0]), size_px=2)
    c, r = np.floor(v.to_pixel(far)[0]).astype(int)
    assert pic[r, c] == 7.0 and pic[r + 1, c + 1] == 7.0
    assert np.isnan(pic[0, 0]) and np.count_nonzero(np.isfinite(pic)) == 4


def test_scan_report_draws_every_figure_in_one_pass(small_result, monkeypatch):
    from markcal.reports.scan_report import scan_report_html
    monkeypatch.setattr(drawing, "_fork_helps", lambda: False)     # every figure in this process, to count
    calls = {"savefig": 0}
    from matplotlib.figure import Figure
    orig = Figure.savefig

    def savefig(self, *a, **k):
        calls["savefig"] += 1
        return orig(self, *a, **k)
    monkeypatch.setattr(Figure, "savefig", savefig)
    page = scan_report_html(small_result)
    pngs = re.findall(r'data:image/png;base64,([A-Za-z0-9+/=]+)"\s+alt="([^"]+)"', page)
    assert [a for _, a in pngs] == ["deviation quiver plot", "deviation histograms", "cumulative histogram",
                                    "cross-validation grid", "correction field", "point cloud", "fiducial crops"]
    assert calls["savefig"] == 0                     # no figure needed the second (savefig tight) pass
    assert "unavailable" not in page
    cloud = Image.open(io.BytesIO(base64.b64decode(dict((a, b) for b, a in pngs)["point cloud"])))
    grey = np.asarray(cloud.convert("RGB"), float)
    red = (grey[..., 0] > 150) & (grey[..., 1] < 60) & (grey[..., 2] < 60)
    assert red.sum() > 100                         # the plate normal's arrow is drawn
