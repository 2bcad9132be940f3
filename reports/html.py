"""Building blocks shared by every self-contained HTML report.

Figures are drawn on matplotlib's Agg canvas (no pyplot state) and inlined as
base64 PNG; CSS is inline; pages need no network and no server.
"""
from __future__ import annotations

import base64
import html
import io

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

__all__ = ["CSS", "DPI", "esc", "num", "new_figure", "nice_number", "png_b64", "img", "table", "page", "data_files_footer"]

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
"""


def esc(x) -> str:
    """HTML-escape ``str(x)``."""
    return html.escape(str(x))


def num(v, unit: str = "mm") -> str:
    """A value with sensible digits and its unit; '–' for missing or NaN."""
    if v is None:
        return "–"
    try:
        v = float(v)
    except (TypeError, ValueError):
        return esc(v)
    if not np.isfinite(v):
        return "–"
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


def new_figure(w_in: float, h_in: float) -> Figure:
    """A matplotlib Figure on an Agg canvas, ``w_in`` x ``h_in`` inches."""
    fig = Figure(figsize=(w_in, h_in), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def png_b64(fig: Figure) -> str:
    """Render ``fig`` to PNG and return it base64-encoded (the figure is cleared)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    fig.clear()
    return base64.b64encode(buf.getvalue()).decode("ascii")


def img(b64: str, alt: str, caption: str) -> str:
    """A ``<figure>`` holding an inline PNG with a caption (caption is HTML)."""
    return (f'<figure><img src="data:image/png;base64,{b64}" alt="{esc(alt)}">'
            f"<figcaption>{caption}</figcaption></figure>")


def table(header, rows, left_cols: int = 1) -> str:
    """An HTML table; cells are HTML; the first ``left_cols`` columns are left-aligned."""
    h = "".join(f'<th class="{"l" if i < left_cols else ""}">{c}</th>' for i, c in enumerate(header))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left_cols else ""}">{c}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def data_files_footer(files) -> str:
    """Footer listing ``(name, description)`` data files written beside a report."""
    items = "".join(f"<li><code>{esc(n)}</code> — {esc(d)}</li>" for n, d in files)
    return f"<footer><b>Data files written beside this report</b><ul>{items}</ul></footer>"


def page(title: str, body_parts, source: str | None = None) -> str:
    """A whole self-contained HTML document: title, optional source line, then the parts."""
    head = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>", f"<h1>{esc(title)}</h1>"]
    if source is not None:
        head.append(f'<div class="src">source: {esc(source)}</div>')
    return "\n".join(head + list(body_parts) + ["</body></html>"])
