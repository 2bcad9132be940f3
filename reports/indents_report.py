"""Self-contained HTML report of an indents flow result (paper 000 Figs. 6-9, Table 1).

Summary first, then warnings (imprints outside +-tolerance or with low H/D,
failed files), the Table 1 layout, levelled maps, a 3D view of one imprint, a
profile through one imprint of each size class, the positional errors and a
gallery of every imprint with its fitted outline. Figures are inline PNG.
"""
from __future__ import annotations

import os

import numpy as np

from markcal.pipeline.flows.indents import DIAGONALS_DIFFER_PCT
from markcal.reports.html import (arrow_key, arrow_scale, data_files_footer, drawable, esc, img, new_figure,
                                  nice_number, num, page, png_b64, table)
from markcal.stages.indent_om import RESOLUTION_RADII

__all__ = ["indents_report_html"]

DATA_FILES = (
    ("indents.csv", "one row per imprint: id, row, col, position, dx/dy, diameter, diagonals, depth, H/D, "
                    "orientation, pile-up, then file, kind, nominal, in_tolerance, fit quality"),
    ("sizes.csv", "per nominal size: n, mean and σ of diameter and H/D, max |error|, mean depth (paper Table 1)"),
    ("summary.json", "the summary values of the table above"),
)
MAX_GALLERY = 120


def _extent(f):
    ny, nx = f.image.shape
    return (-0.5 * f.pixel_um, (nx - 0.5) * f.pixel_um, (ny - 0.5) * f.pixel_um, -0.5 * f.pixel_um)


def _maps(files):
    parts = []
    for f in files[:6]:
        fig = new_figure(6.2, 5.2)
        ax = fig.add_subplot(111)
        if f.kind == "afm":
            z = f.image
            lo, hi = np.nanpercentile(z, [0.5, 99.9])
            im = ax.imshow(z, cmap="afmhot", extent=_extent(f), vmin=lo, vmax=max(hi, lo + 1))
            fig.colorbar(im, ax=ax, label="height (nm)")
        else:
            ax.imshow(f.image, cmap="gray", extent=_extent(f))
        good_col = "cyan" if f.kind == "afm" else "#1565c0"      # cyan vanishes on a light micrograph
        for m, i, ok in zip(f.imprints, f.table["id"], _judged(f)):
            c = np.vstack([m.corners_um, m.corners_um[:1]])
            ax.plot(c[:, 0], c[:, 1], "-", color=good_col if ok else "#d9342b", lw=0.8 if ok else 1.4)
            ax.annotate(str(int(i)), (m.x_um, m.y_um), xytext=(0, 6), textcoords="offset points", ha="center",
                        va="bottom", fontsize=6, color="k" if ok else "#d9342b",
                        bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.75))
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
        what = "levelled AFM height map" if f.kind == "afm" else "micrograph / illumination"
        parts.append(img(png_b64(fig), f.source, f"<code>{esc(os.path.basename(f.source))}</code>: {what} with "
                         "the fitted outlines (corners from the facet planes) and imprint ids"
                         + ("." if f.nominal_inferred else "; red: out of tolerance.")))
    return "".join(parts)


def _crop(f, m, k=1.4):
    px = f.pixel_um
    r = max(m.diameter_um * k / px, 6)
    ci, ri = m.x_um / px, m.y_um / px
    r0, r1 = max(0, int(ri - r)), min(f.image.shape[0], int(ri + r) + 1)
    c0, c1 = max(0, int(ci - r)), min(f.image.shape[1], int(ci + r) + 1)
    return f.image[r0:r1, c0:c1], (c0 * px - px / 2, (c1 - 0.5) * px, (r1 - 0.5) * px, r0 * px - px / 2), (r0, c0)


def _render3d(files):
    afm = [f for f in files if f.kind == "afm" and f.imprints]
    if not afm:
        return ""
    f = afm[0]
    m = f.imprints[len(f.imprints) // 2]
    z, ext, (r0, c0) = _crop(f, m, 1.6)
    ny, nx = z.shape
    xx, yy = np.meshgrid(c0 * f.pixel_um + np.arange(nx) * f.pixel_um, r0 * f.pixel_um + np.arange(ny) * f.pixel_um)
    fig = new_figure(6.5, 4.8)
    ax = fig.add_subplot(111, projection="3d")
    ax.plot_surface(xx, yy, np.nan_to_num(z), cmap="afmhot", linewidth=0, antialiased=True)
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    ax.set_zlabel("z (nm)")
    ax.view_init(elev=35, azim=-60)
    return img(png_b64(fig), "3D imprint", f"3D view of imprint {int(f.table['id'][len(f.imprints) // 2])} of "
               f"<code>{esc(os.path.basename(f.source))}</code>: diameter {num(m.diameter_um, 'µm')}, depth "
               f"{num(m.depth_nm, 'nm')} (paper Fig. 6c).")


def _profiles(files):
    afm = [f for f in files if f.kind == "afm" and f.imprints]
    if not afm:
        return ""
    by_size = {}
    for f in afm:
        by_size.setdefault(f.nominal_um, (f, f.imprints[len(f.imprints) // 2]))
    fig = new_figure(7.5, 3.6)
    ax = fig.add_subplot(111)
    for nominal, (f, m) in sorted(by_size.items()):
        # profile along diagonal 1 through the centre, bilinear samples
        from scipy import ndimage
        ang = np.radians(m.orientation_deg)
        s = np.linspace(-1.5 * m.diameter_um, 1.5 * m.diameter_um, 241)
        x = (m.x_um + s * np.cos(ang)) / f.pixel_um
        y = (m.y_um + s * np.sin(ang)) / f.pixel_um
        z = ndimage.map_coordinates(np.nan_to_num(f.image), [y, x], order=1, mode="nearest")
        ax.plot(s, z, label=f"{nominal:g} µm (measured {m.diameter_um:.3f} µm, {m.depth_nm:.1f} nm)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("distance along diagonal 1 (µm)")
    ax.set_ylabel("height (nm)")
    ax.legend(fontsize=8)
    return img(png_b64(fig), "profiles", "Height profile along diagonal 1 through one imprint of each size class "
               "(paper Fig. 7b); 0 is the original surface.")


def _floor_warning(files, key, amount, title, text) -> list:
    """A warning naming the files whose ``info[key]`` is set, each with ``amount(info)``, followed by ``text``; no
    warning where none is."""
    hit = [f for f in files if f.info.get(key)]
    if not hit:
        return []
    names = ", ".join(f"<code>{esc(os.path.basename(f.source))}</code> ({amount(f.info)})" for f in hit)
    return [f'<div class="warn"><b>{title}</b> in {names} {esc(text)}</div>']


def _positions(res):
    t = res.indents
    ok = np.isfinite(t["dx_um"])
    if not ok.any():
        return "<p>No array spec: no positional errors (give <code>--array ARRAY.toml</code>).</p>"
    fig = new_figure(11.5, 4.2)
    ax = fig.add_subplot(121)
    k = np.arange(ok.sum())
    ax.plot(k, 1000 * t["dx_um"][ok], "o-", ms=3, label="dx")
    ax.plot(k, 1000 * t["dy_um"][ok], "s-", ms=3, label="dy")
    ax.axhline(100, color="r", lw=0.6, ls="--", label="±100 nm")
    ax.axhline(-100, color="r", lw=0.6, ls="--")
    ax.set_xlabel("imprint (file order)")
    ax.set_ylabel("error (nm)")
    ax.legend(fontsize=8, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)  # above the data
    name, mag = _error_field(fig.add_subplot(122), res.files)
    fig.subplots_adjust(wspace=0.3)
    return img(png_b64(fig), "positional errors",
               "Positional errors after rigid registration of each array to its nominal grid: registered measured "
               f"minus nominal (paper Fig. 9); dashed: ±100 nm. Right: the same errors as arrows at each imprint of "
               f"<code>{esc(name)}</code> (the file with the largest RMS error), <b>magnified {mag:g}×</b>.")


def _error_field(ax, files) -> tuple:
    """Arrows of the positional errors at their imprints, in the map's frame (y down), for the file with the largest
    RMS error; returns its name and the arrows' magnification."""
    def rms(f):
        dx, dy = np.asarray(f.table["dx_um"], float), np.asarray(f.table["dy_um"], float)
        return float(np.nanmean(dx ** 2 + dy ** 2)) if np.isfinite(dx).any() else -1.0
    worst = max(files, key=rms)
    x, y, dx, dy = (np.asarray(worst.table[c], float) for c in ("x_um", "y_um", "dx_um", "dy_um"))
    ok = np.isfinite(dx) & np.isfinite(dy)
    x, y, dx, dy = x[ok], y[ok], dx[ok], dy[ok]
    length = np.hypot(dx, dy)
    pitch = _spacing_um(x, y)
    mag = arrow_scale(pitch, float(length.max()))
    q = ax.quiver(x, y, 1000 * dx, 1000 * dy, 1000 * length, angles="xy", scale_units="xy", scale=1000.0 / mag,
                  cmap="viridis", width=0.005)
    ax.figure.colorbar(q, ax=ax, shrink=0.85, pad=0.02).set_label("|error| (nm)")
    ax.set_aspect("equal")
    pad = 0.6 * pitch
    ax.set_xlim(x.min() - pad, x.max() + pad)
    ax.set_ylim(y.max() + pad, y.min() - pad)                     # the map's frame: y down
    key = nice_number(0.6 * float(length.max()) * 1000) if length.max() > 0 else 10.0
    arrow_key(ax, q, key, f"{key:g} nm, ×{mag:g}")
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    name = os.path.basename(worst.source)
    ax.set_title(drawable(name), fontsize=9)
    return name, mag


def _spacing_um(x, y) -> float:
    """Median distance from each imprint to its nearest neighbour (µm); 1 for a single imprint."""
    if len(x) < 2:
        return 1.0
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _judged(f):
    """Each imprint's tolerance flag as the report draws it: all good without an array spec, where the nominal
    size is only inferred and nothing is judged (the verdict says so)."""
    n = len(f.imprints)
    return [1] * n if f.nominal_inferred else f.table.get("in_tolerance", [1] * n)


def _gallery(files):
    items = [(f, m, i, ok) for f in files
             for m, i, ok in zip(f.imprints, f.table["id"], _judged(f))
             ][:MAX_GALLERY]
    if not items:
        return ""
    ncol = 10
    nrow = int(np.ceil(len(items) / ncol))
    fig = new_figure(11, 1.15 * nrow + 0.3)
    for j, (f, m, i, ok) in enumerate(items):
        ax = fig.add_subplot(nrow, ncol, j + 1)
        z, ext, _ = _crop(f, m)
        ax.imshow(z, cmap="afmhot" if f.kind == "afm" else "gray", extent=ext)
        c = np.vstack([m.corners_um, m.corners_um[:1]])
        ax.plot(c[:, 0], c[:, 1], "-", color="cyan", lw=0.7)
        th = np.linspace(0, 2 * np.pi, 60)
        ax.plot(m.x_um + m.diameter_um / 2 * np.cos(th), m.y_um + m.diameter_um / 2 * np.sin(th), "--",
                color="lime", lw=0.5)
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{int(i)}: {m.diameter_um:.2f} µm", fontsize=6, color="k" if ok else "#d9342b",
                     fontweight="normal" if ok else "bold")
        if not ok:                      # out of tolerance: a red frame
            for sp in ax.spines.values():
                sp.set_edgecolor("#d9342b")
                sp.set_linewidth(2)
    more = sum(len(f.imprints) for f in files) - len(items)
    judged = not all(f.nominal_inferred for f in files)
    cap = ("Every imprint with its fitted outline (cyan: corners joined; green dashed: circle through the corners, "
           "paper Fig. 6b); title: id and diameter."
           + (" Red title and frame: out of tolerance (diameter or H/D)." if judged else "")
           + (f" {more} more not shown." if more > 0 else ""))
    return img(png_b64(fig), "gallery", cap)


def indents_report_html(res) -> str:
    """The whole report page of an :class:`IndentsResult`."""
    s = res.summary
    t = res.indents
    parts = []
    verdict = (f"{s['n_imprints']} imprint{'s' if s['n_imprints'] != 1 else ''} in {s['n_files_ok']} of {s['n_files']} file(s); mean diameter "
               f"{num(s['mean_diameter_um'], 'µm')}"
               + (f"; {s['n_out_of_tolerance']} outside ±{s['tolerance_um'] * 1000:.0f} nm of the nominal"
                  if s["n_out_of_tolerance"] is not None else "; no array spec, so no nominal size to judge against")
               + (f"; {s['n_low_hd']} with H/D &lt; {s['min_hd']}" if s["n_low_hd"] is not None else "")
               + (f"; {s['n_missing']} of {s['n_expected']} expected not found" if s["n_missing"] else "") + ".")
    parts.append(f'<div class="verdict">{verdict}</div>')
    rows = [("files measured / failed", f"{s['n_files_ok']} / {s['n_files_failed']}"),
            ("kinds", esc(", ".join(s["kinds"]))),
            ("imprints found", num(s["n_imprints"], "")),
            ("expected (array spec)", num(s["n_expected"], "") if s["n_expected"] is not None else "– (no spec)"),
            ("missing", esc(", ".join(s["missing"])) or "none"),
            (("mean / σ diameter", f"{num(s['mean_diameter_um'], 'µm')} / {num(s['sd_diameter_um'], 'µm')}")
             if s["n_imprints"] > 1 else ("diameter", num(s["mean_diameter_um"], "µm"))),
            ("max |diameter − nominal|", num(s["max_abs_error_um"], "µm") if not s["nominal_inferred"] else ""),
            ("mean depth", num(s["mean_depth_nm"], "nm")), ("mean H/D", num(s["mean_hd"], "")),
            ("RMS dx / dy", f"{num(s['rms_dx_um'], 'µm')} / {num(s['rms_dy_um'], 'µm')}"),
            ("pixel size", num(s["pixel_um"], "µm")),
            ("optics' resolution (Airy radius of the fitted PSF)", num(s.get("optics_resolution_um"), "µm")),
            ("AFM noise", num(s["noise_nm"], "nm")),
            ("sample tilt removed", num(s["tilt_deg"], "°")),
            ("z loop's lag along the fast axis, from trace and retrace (the map shown moved back by it; an "
             "imprint measured on both has its centre and corners the means of both directions)",
             (f'{num(s["scan_lag_px"], "px")} ({num(1e3 * s["scan_lag_px"] * s["pixel_um"], "nm")})'
              + (f', {s["n_files_lag_removed"]} file(s)' if s.get("n_files_lag_removed", 0) > 1 else "")
              + f'; {s.get("n_imprints_both_directions", 0)} imprint(s) measured on both'
              + (f'; positions moved back by the imprints\' own shift, {num(s["imprint_shift_px"], "px")} (five '
                 'or fewer measured on the retrace too)' if s.get("imprint_shift_px") is not None else ""))
             if s.get("scan_lag_px") is not None else ""),
            ("flattened line by line before export (each line's fit taken again from its far field)",
             esc(s["line_flatten"]) if s.get("line_flatten", "none") != "none" else ""),
            ("non-square pixels resampled", esc(s["resampled"]) if s.get("resampled", "none") != "none" else ""),
            ("levelled to the surface beyond the corners (pile-up's tails under the far field)",
             (f'{s["n_files_levelled_to_corners"]} file(s)' + (f', the far field {num(-s["corner_level_nm"], "nm")} '
                                                               "above it" if s.get("corner_level_nm") is not None else "")
              + (f', levelled {100 * s["corner_level_weight"]:.0f} % of the way (the strips scatter nearly as much)'
                 if s.get("corner_level_weight") is not None and s["corner_level_weight"] < 1 else ""))
             if s.get("n_files_levelled_to_corners") else ""),
            ("floor clipped (the scanner's Z range): depths are lower bounds",
             f'{s["n_files_floor_clipped"]} file(s)' if s.get("n_files_floor_clipped") else ""),
            ("floor reached on neither scan direction (z loop too slow): depths are lower bounds",
             f'{s["n_files_floor_missed"]} file(s)' if s.get("n_files_floor_missed") else ""),
            ("runtime", num(s["runtime_s"], "s"))]
    rows = [r for r in rows if r[1].replace("–", "").replace("/", "").strip()]     # no "–" rows (AFM-only on OM)
    parts.append(table(["quantity", "value"], rows))
    parts += _floor_warning(res.files, "floor_clipped_px", lambda i: f"{i['floor_clipped_px']} px", "Floor clipped:",
                            "that many pixels hold the map's lowest height exactly: the scanner reached the end of its "
                            "Z range, so the floor is cut flat and the depths (and H/D) are lower bounds. The "
                            "diagonals and areas do not depend on it.")
    parts += _floor_warning(res.files, "floor_missed", lambda i: f"{i['floor_separation_px']:.1f} px",
                            "Floor not reached:",
                            "the trace's deepest point lies that far right of the retrace's, beyond the z loop's lag. "
                            "The tip fell more slowly than the facets and met the far facet above the floor on both "
                            "scan directions, so the depths (and H/D) are lower bounds. Scan more slowly or raise the "
                            "loop's gains. The diagonals, taken from both directions, do not depend on it.")
    unsure = [f for f in res.files if f.info.get("line_flatten_uncertain")]
    if unsure:
        names = ", ".join(f"<code>{esc(os.path.basename(f.source))}</code>: {f.info['line_flatten_short_lines']} lines"
                          for f in unsure)
        parts.append('<div class="warn"><b>Flatten undone with little far field</b> (' + names + "). These maps "
                     "had been flattened line by line, and that many of their lines have under 15 % of their length "
                     "on the far field (pile-up or the imprint reaches both ends). Their level before the flatten "
                     "is taken from their neighbours, so the depth and the contact area can be off by several "
                     "percent, up to 30 % where pile-up lobes reach the border (docs/indents.md, \"The flatten "
                     "recognised and undone\"). An export without the flatten avoids it.</div>")
    if s.get("n_diagonals_differ"):
        which = [f"<code>{esc(os.path.basename(str(t['file'][k])))}</code> #{int(t['id'][k])} "
                 f"({num(t['diagonal_difference_pct'][k], '')} %)"
                 for k in np.flatnonzero(t["diagonal_difference_pct"] > DIAGONALS_DIFFER_PCT)]
        more = f" and {len(which) - 12} more" if len(which) > 12 else ""
        parts.append(f'<div class="warn"><b>{s["n_diagonals_differ"]} imprint(s) whose diagonals differ by more than '
                     f'{DIAGONALS_DIFFER_PCT:g} % of their mean:</b> {", ".join(which[:12])}{more}. ISO 6507-1 asks '
                     "that this be stated in the test report: on a flat surface it means a tilted sample, or a corner "
                     "that a crack or a chip carried out (check the corners on the map).</div>")
    from .indent_single_report import single_section
    parts.append(single_section(res.files))
    if s["nominal_inferred"]:
        parts.append('<div class="warn">No array spec: the nominal size of each file is its median diameter '
                     "rounded to 0.5 µm.</div>")
    for src, msg in res.failed:
        parts.append(f'<div class="note">failed: <code>{esc(os.path.basename(src))}</code>: {esc(msg)}</div>')
    if s.get("n_near_resolution") and s.get("optics_from"):
        parts.append(f'<div class="verdict"><b>{s["n_near_resolution"]} imprint(s) near the resolution limit</b> (smaller '
                     f'than {RESOLUTION_RADII:g} × the optics\' resolution, {num(s["optics_resolution_um"], "µm")}): '
                     f'their halo and edge-line darkness were held at the values measured on '
                     f'<code>{esc(s["optics_from"])}</code> (halo height {num(s["held_rim"], "")}, width '
                     f'{num(s["held_rim_w"], "")} half-diagonals, edge-line darkness {num(s["held_crease"], "")}), '
                     "which the image alone cannot give.</div>")
    elif s.get("n_near_resolution"):
        parts.append(f'<div class="warn"><b>{s["n_near_resolution"]} imprint(s) near the resolution limit:</b> smaller '
                     f'than {RESOLUTION_RADII:g} × the optics\' resolution ({num(s["optics_resolution_um"], "µm")}, the '
                     "Airy radius of the fitted PSF). At this size a dark line on the edge or a bright halo beside it "
                     "looks like a larger or smaller imprint, so the diagonals rest on the model's assumptions and can be "
                     "off by tens of nm (docs/indents.md, \"The information in a 1 µm image\"). A micrograph of "
                     "larger imprints under the same objective (<code>--optics-from</code>), a higher NA, a shorter "
                     "wavelength or larger imprints avoid it.</div>")
    err = t["diameter_um"] - t["nominal_um"]
    low = np.isfinite(t["hd_ratio"]) & (t["hd_ratio"] < s["min_hd"])
    off = np.abs(err) > s["tolerance_um"] if s["n_out_of_tolerance"] is not None else np.zeros(len(err), bool)
    bad = np.flatnonzero(off | low)
    if len(bad):
        items = "".join(f"<li><code>{esc(t['file'][i])}</code> #{int(t['id'][i])}: diameter "
                        f"{num(t['diameter_um'][i], 'µm')} (nominal {num(t['nominal_um'][i], 'µm')}, error "
                        f"{1000 * err[i]:+.0f} nm)" + (f", H/D {num(t['hd_ratio'][i], '')}" if np.isfinite(t['hd_ratio'][i]) else "")
                        + "</li>" for i in bad[:50])
        parts.append(f'<div class="warn"><b>{len(bad)} imprint(s) outside the tolerance '
                     f'±{s["tolerance_um"] * 1000:.0f} nm '
                     f"or with H/D &lt; {s['min_hd']}</b><ul>{items}</ul></div>")
    parts.append("<h2>Per-size statistics (paper Table 1)</h2>")
    z = res.sizes
    head = ["nominal size", "N", "mean diameter", "σ diameter", "max |error|", "mean H/D", "σ H/D", "mean depth"]
    body = [[num(z["nominal_um"][i], "µm"), num(z["n"][i], ""), num(z["mean_diameter_um"][i], "µm"),
             num(z["sd_diameter_um"][i], "µm"), num(z["max_abs_error_um"][i], "µm"),
             num(z["mean_hd"][i], ""), num(z["sd_hd"][i], ""), num(z["mean_depth_nm"][i], "nm")]
            for i in range(len(z["n"]))]
    keep = [j for j in range(len(head)) if any(r[j] != "–" for r in body)] or list(range(len(head)))
    parts.append(table([head[j] for j in keep], [[r[j] for j in keep] for r in body]))   # no all-"–" columns
    from .indent_single_report import MAX_SINGLE
    if all(len(f.imprints) <= MAX_SINGLE for f in res.files):   # the single-imprint view above shows them all
        in3d = _render3d(res.files)
        parts += ["<h2>The imprint in 3D</h2>", in3d] if in3d else []
        parts += ["<h2>Positional error</h2>", _positions(res)] if s["n_expected"] is not None else []
    else:
        parts += ["<h2>Maps</h2>", _maps(res.files)]
        in3d = _render3d(res.files) + _profiles(res.files)
        parts += ["<h2>One imprint in 3D and profiles</h2>", in3d] if in3d else []   # AFM only: none for images
        parts += ["<h2>Positional error</h2>", _positions(res), "<h2>Every imprint</h2>", _gallery(res.files)]
    parts.append(data_files_footer(DATA_FILES))
    return page("markcal indents report", parts, source=s["source"], summary=s)
