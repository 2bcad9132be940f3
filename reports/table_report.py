"""A small report of a controller table read back (``markcal inspect``, and the note ``markcal export`` writes)."""
from __future__ import annotations

import numpy as np

from markcal.reports.html import arrow_key, arrow_scale, esc, img, new_figure, nice_number, num, page, png_b64, table

__all__ = ["table_report_html", "structure_rows"]


def _figure(t) -> str:
    fig = new_figure(14, 6.0)
    gs = fig.add_gridspec(1, 3, width_ratios=[2.2, 1, 1])      # the arrow map larger: its arrows stay visible
    ax = fig.add_subplot(gs[0, 0])
    step = max(1, len(t.x_mm) // 8)                            # about 9 arrows a side, each up to ⅓ of their spacing
    gx, gy = np.meshgrid(t.x_mm, t.y_mm)
    pitch = float(np.diff(t.x_mm[::step]).mean()) if len(t.x_mm) > step else 1.0
    vmax = float(np.hypot(t.u, t.v).max())
    k = arrow_scale(pitch, vmax)
    q = ax.quiver(gx[::step, ::step], gy[::step, ::step], t.u[::step, ::step] * k, t.v[::step, ::step] * k,
                  angles="xy", scale_units="xy", scale=1, color="#c0392b", width=0.006)
    key = nice_number(vmax) if vmax > 0 else 1.0
    arrow_key(ax, q, key * k, f"{key:g} {t.unit}")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{t.what}\narrows: 1 {t.unit} drawn as {k:g} mm", fontsize=9)
    dx = float(np.diff(t.x_mm).mean()) / 2 if len(t.x_mm) > 1 else 0.5
    dy = float(np.diff(t.y_mm).mean()) / 2 if len(t.y_mm) > 1 else 0.5
    extent = [t.x_mm[0] - dx, t.x_mm[-1] + dx, t.y_mm[0] - dy, t.y_mm[-1] + dy]
    for i, (comp, name) in enumerate(((t.u, "x component"), (t.v, "y component"))):
        axc = fig.add_subplot(gs[0, 1 + i])
        lim = float(np.max(np.abs(comp))) or 1.0
        im = axc.imshow(comp, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim, extent=extent)
        fig.colorbar(im, ax=axc, fraction=0.046, pad=0.04, label=t.unit)     # as tall as the map
        axc.set_xlabel("x (mm)")
        axc.set_title(name, fontsize=9)
    fig.subplots_adjust(wspace=0.5)
    return img(png_b64(fig), "table field",
               f"The {esc(t.what)} at each of the {t.u.size} nodes ({len(t.x_mm)} x {len(t.y_mm)}) as the reader "
               "interprets the file, x to the right and y up. A lens correction's x component changes sign across "
               "the vertical middle line and its y component across the horizontal one.")


def structure_rows(t) -> list:
    """``[label, value]`` rows: which index each stored component is odd along, the centre node, the verdict."""
    st = t.structure
    if st is None:
        return [["structure", "not checked (grid counts are not odd: no centre node)"]]
    names = ("first value", "second value") if t.format == "cor" else \
        ("X table", "Y table") if t.format == "ctb" else ("x column", "y column")
    rows = []
    for name, c in zip(names, (st.first, st.second)):
        rows.append([f"{name}: odd along inner / outer index",
                     f"{c.odd_inner:+.3f} / {c.odd_outer:+.3f} (1 odd, −1 even); centre node {c.centre:.6g}; "
                     f"largest |value − centre| on the middle lines {c.middle_inner_max:.6g} (inner) / "
                     f"{c.middle_outer_max:.6g} (outer); RMS {c.rms:.6g}"])
    verdict = {"inner": "the first component's axis runs along the inner index",
               "outer": "the first component's axis runs along the outer index",
               "none": f"fits no known layout: {st.reason}"}[st.first_along]
    rows.append(["structure", f"{verdict} (evidence {st.evidence:+.2f}); the layout read expects the "
                              f"{t.expected_along} index"])
    return rows


def table_report_html(t, title: str | None = None, note_rows: list | None = None, provenance: dict | None = None) -> str:
    """One self-contained page for an :class:`~markcal.pipeline.flows.export.Inspected` table.

    ``note_rows`` (the export note) come first when given; structural warnings
    are shown at the top in red; ``provenance`` (version, date, command, inputs) heads the page.
    """
    mag = np.hypot(t.u, t.v)
    parts = [f'<div class="note">{esc(w)}</div>' for w in t.warnings]
    if note_rows:
        parts += ["<h2>What was written</h2>", table(["", ""], [[esc(a), esc(b)] for a, b in note_rows])]
    rows = [["format", esc(t.format)], ["layout read", esc(t.layout)], ["nodes", f"{len(t.x_mm)} x {len(t.y_mm)}"],
            ["field", f"x {t.x_mm[0]:.3f}..{t.x_mm[-1]:.3f} mm, y {t.y_mm[0]:.3f}..{t.y_mm[-1]:.3f} mm"],
            ["max magnitude", num(mag.max(), t.unit)], ["RMS magnitude", num(np.sqrt(np.mean(mag ** 2)), t.unit)],
            ["at the centre node", f"({t.u[len(t.y_mm) // 2, len(t.x_mm) // 2]:.3f}, "
                                   f"{t.v[len(t.y_mm) // 2, len(t.x_mm) // 2]:.3f}) {t.unit}"]]
    rows += [[esc(k), esc(f"{v:.6g}" if isinstance(v, float) else v)] for k, v in t.facts.items()]
    parts += ["<h2>Table</h2>", table(["", ""], rows), "<h2>Structure of the stored entries</h2>",
              table(["", ""], [[esc(a), esc(b)] for a, b in structure_rows(t)]), "<h2>Field</h2>", _figure(t),
              "<p>What the public sources leave open about the format (node spacing, index order, sign) is "
              "read with the options shown above; see the README, section “Correction tables”.</p>"]
    return page(title or f"markcal inspect — {t.format} table", parts, source=t.path, summary=provenance)
