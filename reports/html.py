"""Building blocks shared by every self-contained HTML report.

Figures are drawn on matplotlib's Agg canvas (no pyplot state) and inlined as
base64 PNG; CSS is inline; pages need no network and no server.
"""
from __future__ import annotations

import base64
import contextvars
import html
import io
import time

import numpy as np

__all__ = ["CSS", "DPI", "esc", "num", "new_figure", "nice_number", "png_b64", "img", "table", "page", "png_bytes", "figure_progress", "data_files_footer", "verdict_banner",
           "provenance_line", "arrow_key", "arrow_scale"]

DPI = 100

CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;margin:24px auto;max-width:1100px;
 color:#222;line-height:1.45;padding:0 16px}
h1{font-size:1.55em;margin-bottom:.2em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:3px;
 margin-top:1.8em}
.src{color:#555;font-family:monospace;font-size:.9em;word-break:break-all}
.verdict{font-size:1.05em;background:#eef4fb;border-left:4px solid #3b7dd8;padding:8px 12px;margin:10px 0}
.note{background:#fdecea;border-left:4px solid #d9342b;padding:8px 12px;margin:10px 0;font-weight:600}
.warn{background:#fff6e0;border-left:4px solid #e0a100;padding:8px 12px;margin:10px 0}
.pass{background:#e6f4ea}.fail{background:#fdecea}
table{border-collapse:collapse;margin:8px 0 12px 0;font-size:.93em}
th,td{border:1px solid #ccc;padding:3px 9px;text-align:right}
th{background:#f2f2f2}td.l,th.l{text-align:left}
figure{margin:10px 0 16px 0}figure img{max-width:100%;height:auto;border:1px solid #ddd}
figcaption{font-size:.9em;color:#444;margin-top:4px;max-width:900px}
footer{margin-top:2.5em;border-top:1px solid #ccc;padding-top:8px;font-size:.9em;color:#444}
code{background:#f4f4f4;padding:0 3px}
.banner{display:flex;flex-wrap:wrap;align-items:center;gap:4px 18px;padding:10px 14px;margin:8px 0 6px 0;
 border-radius:4px;border:2px solid #999}
.banner .big{font-size:2.1em;font-weight:800;letter-spacing:.04em}
.banner.pass{border-color:#2e7d32}.banner.pass .big{color:#2e7d32}
.banner.fail{border-color:#d9342b}.banner.fail .big{color:#d9342b}
.banner.none .big{color:#666;font-size:1.5em}
.banner table{margin:0}
.prov{color:#555;font-size:.85em;margin:2px 0 10px 0;word-break:break-all}
@page{size:A4;margin:14mm}
@media print{body{max-width:none;margin:0;padding:0;font-size:10pt}figure,table{break-inside:avoid}
 h2{break-after:avoid}.filters{display:none}a{color:inherit;text-decoration:none}}
"""


def esc(x) -> str:
    """HTML-escape ``str(x)``."""
    return html.escape(str(x))


#: a length below 0.001 of these units is written in the next smaller one (where .3g would use an exponent)
SMALLER = {"mm": "µm", "µm": "nm"}


def num(v, unit: str = "mm") -> str:
    """A value with sensible digits and its unit; '–' for missing or NaN; no exponents for small lengths."""
    if v is None:
        return "–"
    try:
        v = float(v)
    except (TypeError, ValueError):
        return esc(v)
    if not np.isfinite(v):
        return "–"
    if unit in SMALLER and 0 < abs(v) < 1e-3:      # 2.86e-05 mm reads as 0.0286 µm, not in exponent form
        return num(v * 1000.0, SMALLER[unit])
    if v == int(v) and abs(v) < 1e9 and not unit:
        s = f"{int(v):,}"
    elif v == 0:
        s = "0"
    elif abs(v) >= 100:
        s = f"{v:.1f}"
    elif abs(v) >= 10:
        s = f"{v:.2f}"
    elif abs(v) >= 0.1:
        s = f"{v:.3f}"
    else:
        s = f"{v:.3g}"
    return f"{s} {unit}" if unit else s


def nice_number(x: float) -> float:
    """Largest of 1, 2, 5 x 10^k not above ``x`` (x > 0): a round scale factor."""
    k = np.floor(np.log10(x))
    for m in (5.0, 2.0, 1.0):
        if m * 10 ** k <= x:
            return float(m * 10 ** k)
    return float(10 ** k)


def arrow_scale(pitch: float, max_len: float) -> float:
    """Magnification (1, 2 or 5 × 10^k, the nearest) making the longest arrow about ⅓ of ``pitch``.

    ``pitch`` is in plot units, ``max_len`` in arrow units; 1 when there is no arrow to draw.
    """
    if not (np.isfinite(max_len) and max_len > 0 and np.isfinite(pitch) and pitch > 0):
        return 1.0
    x = pitch / (3.0 * max_len)
    k = np.floor(np.log10(x))
    cands = [m * 10.0 ** (k + e) for e in (-1, 0, 1) for m in (1.0, 2.0, 5.0)]
    return float(min(cands, key=lambda c: abs(np.log(c / x))))


def new_figure(w_in: float, h_in: float):
    """A matplotlib Figure on an Agg canvas, ``w_in`` x ``h_in`` inches (matplotlib loads on first use)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(w_in, h_in), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def arrow_key(ax, q, length: float, label: str) -> None:
    """Draw the key arrow of quiver ``q`` inside ``ax`` (lower right, on a white box).

    ``length`` is in the units of the arrows as passed to ``quiver``; ``label`` says what it means
    in real units. Inside the axes, the key survives the tight cropping of :func:`png_b64`; the y range
    is extended downwards so that the key's box sits below the data instead of over it.
    """
    from matplotlib.patches import Rectangle
    ax.autoscale_view()
    y0, y1 = ax.get_ylim()
    if y1 > y0:                                   # an upward y axis: room at the bottom for the key
        ax.set_ylim(y0 - 0.13 * (y1 - y0), y1)
    else:                                         # image-like (inverted) axis: the bottom is the larger value
        ax.set_ylim(y0 + 0.13 * (y0 - y1), y1)
    ax.add_patch(Rectangle((0.60, 0.01), 0.385, 0.08, transform=ax.transAxes, facecolor="white", edgecolor="0.55",
                           alpha=0.92, zorder=5))
    key = ax.quiverkey(q, 0.90, 0.05, length, label, labelpos="W", coordinates="axes", color="k",
                       fontproperties={"size": 8})
    key.set_zorder(6)


def drawable(text):
    """Text matplotlib can draw: a non-UTF-8 file name's bytes (surrogate escapes) shown as ``\\udcXX``."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8") if isinstance(text, str) else text


#: zlib level of the report PNGs: 1 encodes several times faster than matplotlib's 6 for files ~10-20 % larger
PNG_COMPRESS_LEVEL = 1
#: white margin kept around the drawn content (pixels; matplotlib's ``pad_inches=0.1`` at :data:`DPI`)
PAD_PX = 10


#: this thread's figure counter: (say, figures drawn, time of the last line); None: no progress lines
_FIGURE_PROGRESS = contextvars.ContextVar("markcal_figure_progress", default=None)
#: shortest time between two "figures drawn" lines (s)
FIGURE_PROGRESS_EVERY_S = 1.0


def figure_progress(say) -> None:
    """Report figures drawn from now on in this thread through ``say(msg)`` (None: stop).

    A line ``report: N figures drawn`` goes out after a figure when the last one went out at
    least :data:`FIGURE_PROGRESS_EVERY_S` ago, so a long report never leaves the terminal silent
    for long. Other threads (and worker processes) are not affected.
    """
    _FIGURE_PROGRESS.set(None if say is None else [say, 0, time.perf_counter()])


def _figure_drawn() -> None:
    st = _FIGURE_PROGRESS.get()
    if st is None:
        return
    st[1] += 1
    now = time.perf_counter()
    if now - st[2] >= FIGURE_PROGRESS_EVERY_S:
        st[0](f"report: {st[1]} figure{'' if st[1] == 1 else 's'} drawn")
        st[2] = now


def png_bytes(fig) -> bytes:
    """Render ``fig`` once on its Agg canvas, crop it to its tight bounding box and return PNG bytes.

    The picture is what ``savefig(bbox_inches="tight")`` gives, without its second drawing pass: the
    tight box is measured on the drawn canvas and cut out of it. A figure with an artist beyond the
    canvas goes through ``savefig`` with the measured box (one more drawing); a see-through background
    through ``savefig(bbox_inches="tight")``. The figure is left as it is (clearing it rebuilt every
    axis' ticks, 10 % of a report's drawing time); the garbage collector frees it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    canvas = fig.canvas
    box = "tight"
    if isinstance(canvas, FigureCanvasAgg) and fig.get_facecolor()[3] == 1.0:
        try:
            canvas.draw()
        except (TypeError, UnicodeError):           # a text FreeType cannot take (a file name's stray bytes)
            _drawable_texts(fig)
            canvas.draw()
        tight = fig.get_tightbbox(canvas.get_renderer())      # inches; the text sizes are known by now
        w_in, h_in = fig.get_size_inches()
        tol = 0.5 / DPI
        if tight.x0 >= -tol and tight.y0 >= -tol and tight.x1 <= w_in + tol and tight.y1 <= h_in + tol:
            data = _crop_png(np.asarray(canvas.buffer_rgba()), tight, h_in, fig.dpi)
            _figure_drawn()
            return data
        box = tight.padded(PAD_PX / DPI)                 # measured: savefig need not lay the figure out again
    _drawable_texts(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches=box, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    _figure_drawn()
    return buf.getvalue()


def _crop_png(rgba: np.ndarray, box, h_in: float, dpi: float) -> bytes:
    """PNG of the canvas pixels inside ``box`` (inches, origin lower left) plus :data:`PAD_PX` of white."""
    from PIL import Image
    c0, c1 = int(round(box.x0 * dpi)) - PAD_PX, int(round(box.x1 * dpi)) + PAD_PX
    r0, r1 = int(round((h_in - box.y1) * dpi)) - PAD_PX, int(round((h_in - box.y0) * dpi)) + PAD_PX
    h, w = rgba.shape[:2]
    crop = rgba[max(r0, 0):min(r1, h), max(c0, 0):min(c1, w), :3]
    pad = ((max(-r0, 0), max(r1 - h, 0)), (max(-c0, 0), max(c1 - w, 0)), (0, 0))
    if any(p for pp in pad for p in pp):                # the box touches the canvas edge: white beyond it
        crop = np.pad(crop, pad, constant_values=255)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(crop)).save(buf, format="png", compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _drawable_texts(fig) -> None:
    """Make every text of ``fig`` drawable (:func:`drawable`); walks all artists, so only when needed."""
    from matplotlib.text import Text
    for t in fig.findobj(Text):
        t.set_text(drawable(t.get_text()))


def png_b64(fig) -> str:
    """Render ``fig`` to PNG (:func:`png_bytes`) and return it base64-encoded."""
    return base64.b64encode(png_bytes(fig)).decode("ascii")


def img(b64: str, alt: str, caption: str) -> str:
    """A ``<figure>`` holding an inline PNG with a caption (caption is HTML)."""
    return (f'<figure><img src="data:image/png;base64,{b64}" alt="{esc(alt)}">'
            f"<figcaption>{caption}</figcaption></figure>")


def table(header, rows, left_cols: int = 1) -> str:
    """An HTML table; cells are HTML; the first ``left_cols`` columns are left-aligned."""
    h = "".join(f'<th class="{"l" if i < left_cols else ""}">{c}</th>' for i, c in enumerate(header))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left_cols else ""}">{c}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    head = f"<tr>{h}</tr>" if any(str(c) for c in header) else ""     # no empty grey header bar
    return f"<table>{head}{body}</table>"


def data_files_footer(files) -> str:
    """Footer listing ``(name, description)`` data files written beside a report."""
    items = "".join(f"<li><code>{esc(n)}</code> — {esc(d)}</li>" for n, d in files)
    return f"<footer><b>Data files written beside this report</b><ul>{items}</ul></footer>"


def _check_rows(summary: dict) -> list:
    rows = []
    failed = summary.get("failed_checks") or ""
    checks = (summary.get("checks") or "").split("; ")
    labels = (summary.get("check_labels") or "").split("; ")
    labels = labels if len(labels) == len(checks) else [""] * len(checks)
    for c, label in zip(checks, labels):
        parts = c.split(" ")
        if len(parts) != 3:
            continue
        key, op, lim = parts
        v = summary.get(key)
        bad = any(f.split(" ")[0] == key for f in failed.split("; ") if f)
        na = isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v)
        val = "–" if na else f"{v:.4g}"
        rows.append([esc(label if label and label != key else key) + (f" <code>{esc(key)}</code>" if label and label != key else ""), val, f"{'≤' if op == '<=' else '≥'} {esc(lim)}",
                     '<b style="color:#d9342b">out</b>' if bad else ("not applicable" if na else "ok")])
    return rows


def provenance_line(summary: dict) -> str:
    """The provenance line of a report (version, date, context, inputs with SHA-256, command); "" without one."""
    if not summary.get("markcal_version"):
        return ""
    prov = [f"markcal {esc(summary.get('markcal_version', '?'))}", esc(summary.get("date_utc", ""))]
    for k in ("machine", "lens", "operator", "note"):
        if summary.get(k):
            prov.append(f"{k}: {esc(summary[k])}")
    if summary.get("input"):
        prov.append(f"input {esc(summary['input'])} (SHA-256 {esc(str(summary.get('input_sha256', ''))[:16])}…)")
    if summary.get("data_time"):
        prov.append(f"measured {esc(summary['data_time'])} (the file's own timestamp)")
    if summary.get("spec"):
        prov.append(f"spec {esc(summary['spec'])} (SHA-256 {esc(str(summary.get('spec_sha256', ''))[:16])}…)")
    if summary.get("command"):
        prov.append(f"command <code>{esc(summary['command'])}</code>")
    if summary.get("batch_index"):
        prov.append(f'<a href="{esc(summary["batch_index"])}">back to the batch index</a>')
    return f'<div class="prov">{" · ".join(prov)}</div>'


def verdict_banner(summary: dict) -> str:
    """PASS / FAIL / NO TOLERANCE in large type with the checks, then the provenance line.

    Without a verdict (a flow judged against the paper, not a tolerance), only the provenance line.
    """
    status = summary.get("verdict")
    if not status:
        return provenance_line(summary)
    cls = {"pass": "pass", "fail": "fail"}.get(status, "none")
    rows = _check_rows(summary)
    checks = table(["figure", "value", "limit", ""], rows) if rows else \
        f"<span>{esc(summary['verdict_note'])}</span>" if summary.get("verdict_note") else \
        "<span>no tolerance given: <code>--tol KEY&lt;=VALUE</code> or the spec's / batch.toml's limits</span>"
    return (f'<div class="banner {cls}" id="verdict"><span class="big">{esc(status.upper())}</span>{checks}</div>'
            + provenance_line(summary))


def page(title: str, body_parts, source: str | None = None, summary: dict | None = None) -> str:
    """A whole self-contained HTML document: title, the verdict banner (when ``summary`` has one),
    optional source line, then the parts."""
    head = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>", f"<h1>{esc(title)}</h1>"]
    if summary:
        head.append(verdict_banner(summary))
    if source is not None:
        head.append(f'<div class="src">source: {esc(source)}</div>')
    return "\n".join(head + list(body_parts) + ["</body></html>"])
