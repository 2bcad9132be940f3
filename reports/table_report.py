"""A small report of a controller table read back (``markcal inspect``)."""
from __future__ import annotations

import numpy as np

from markcal.reports.html import esc, img, new_figure, nice_number, num, page, png_b64, table

__all__ = ["render_table_report_html"]


def _figure(t) -> str:
    mag = np.hypot(t.u, t.v)
    fig = new_figure(11, 5.2)
    ax = fig.add_subplot(1, 2, 1)
    step = max(1, len(t.x_mm) // 17)
    gx, gy = np.meshgrid(t.x_mm, t.y_mm)
    pitch = float(np.diff(t.x_mm[::step]).mean()) if len(t.x_mm) > step else 1.0
    vmax = float(mag.max())
    k = nice_number(0.8 * pitch / vmax) if vmax > 0 else 1.0
    ax.quiver(gx[::step, ::step], gy[::step, ::step], t.u[::step, ::step] * k, t.v[::step, ::step] * k,
              angles="xy", scale_units="xy", scale=1, color="#c0392b", width=0.003)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{t.what}, arrows × {k:g} (mm per {t.unit})", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    dx = float(np.diff(t.x_mm).mean()) / 2 if len(t.x_mm) > 1 else 0.5
    dy = float(np.diff(t.y_mm).mean()) / 2 if len(t.y_mm) > 1 else 0.5
    im = ax2.imshow(mag, origin="lower", cmap="viridis",
                    extent=[t.x_mm[0] - dx, t.x_mm[-1] + dx, t.y_mm[0] - dy, t.y_mm[-1] + dy])
    fig.colorbar(im, ax=ax2, shrink=0.85, label=f"magnitude ({t.unit})")
    ax2.set_xlabel("x (mm)")
    ax2.set_title("magnitude", fontsize=9)
    return img(png_b64(fig), "table field", f"The {esc(t.what)} stored at each of the {mag.size} nodes "
               f"({len(t.x_mm)} x {len(t.y_mm)}), as the reader interprets the file.")


def render_table_report_html(t) -> str:
    """One self-contained page for an :class:`~markcal.pipeline.flows.export.Inspected` table."""
    mag = np.hypot(t.u, t.v)
    rows = [["format", esc(t.format)], ["nodes", f"{len(t.x_mm)} x {len(t.y_mm)}"],
            ["field", f"x {t.x_mm[0]:.3f}..{t.x_mm[-1]:.3f} mm, y {t.y_mm[0]:.3f}..{t.y_mm[-1]:.3f} mm"],
            ["max magnitude", num(mag.max(), t.unit)], ["RMS magnitude", num(np.sqrt(np.mean(mag ** 2)), t.unit)],
            ["at the centre node", f"({t.u[len(t.y_mm) // 2, len(t.x_mm) // 2]:.3f}, "
                                   f"{t.v[len(t.y_mm) // 2, len(t.x_mm) // 2]:.3f}) {t.unit}"]]
    rows += [[esc(k), esc(f"{v:.6g}" if isinstance(v, float) else v)] for k, v in t.facts.items()]
    parts = [table(["", ""], rows), "<h2>Field</h2>", _figure(t),
             "<p>What the public sources leave open about the format (node spacing, index order, sign) is "
             "read with the options shown above; see the README, section “Correction tables”.</p>"]
    return page(f"markcal inspect — {t.format} table", parts, source=t.path)
