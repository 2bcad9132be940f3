"""Single-imprint section of the indents report: the hardness lab's numbers first, then the map
with corners, diagonals, contact outline and pile-up, and the profiles along both diagonals."""
from __future__ import annotations

import os

import numpy as np

from markcal.reports.html import esc, img, new_figure, num, png_b64, table

__all__ = ["single_section"]

MAX_SINGLE = 3          # a file with at most this many imprints gets the single-imprint view


def _singles(files):
    return [(f, k) for f in files if len(f.imprints) <= MAX_SINGLE for k in range(len(f.imprints))]


def _numbers(f, k):
    t = f.table
    cut = "yes: cut by the border, not measured whole" if t["cut_by_border"][k] else "no"
    return [("mean diagonal d (ISO 6507)", num(t["d_um"][k], "µm")),
            ("diagonals d1 / d2", f"{num(t['diag1_um'][k], 'µm')} / {num(t['diag2_um'][k], 'µm')}"),
            ("diagonals differ by (ISO 6507-1: at most 5 % on a flat surface)",
             f"{num(t['diagonal_difference_pct'][k], '')} % of d"),
            ("projected contact area", num(t["area_um2"][k], "µm²")),
            ("chipped beside the edges (not in the area)", num(t["chipped_area_um2"][k], "µm²")),
            ("depth (far-field plane to measured floor)", num(t["depth_nm"][k], "nm")
             + (" (a lower bound: the floor was cut flat)" if f.info.get("floor_clipped_px") else "")
             + (" (a lower bound: neither scan direction reached the floor)" if f.info.get("floor_missed") else "")),
            ("apex depth (facet model)", num(t["apex_depth_nm"][k], "nm")),
            ("H/D", num(t["hd_ratio"][k], "")),
            ("Vickers hardness", num(t["hv"][k], "HV") if np.isfinite(t["hv"][k]) else "– (give --load-mN)"),
            ("pile-up height / volume", f"{num(t['pileup_nm'][k], 'nm')} / {num(t['pileup_volume_um3'][k], 'µm³')}"),
            ("mean edge bow (of d/2, + out)", num(t["edge_bow"][k], "")),
            ("cut by the border", cut)]


def _legend_above(ax):
    """The legend in a row above the plot: drawn inside, it hid the corner of an imprint that fills the field."""
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=4, fontsize=7, frameon=False)


def _map(f, m):
    px = f.pixel_um
    ny, nx = f.image.shape
    ext = (-0.5 * px, (nx - 0.5) * px, (ny - 0.5) * px, -0.5 * px)
    fig = new_figure(8.0, 7.0)
    ax = fig.add_subplot(111)
    if f.kind == "afm":
        z = f.image
        lo, hi = np.nanpercentile(z, [0.5, 99.5])
        im = ax.imshow(z, cmap="afmhot", extent=ext, vmin=lo, vmax=max(hi, lo + 1))
        fig.colorbar(im, ax=ax, label="height (nm)", shrink=0.8)
        noise = f.info.get("noise_nm") or 1.0
        yy, xx = (np.mgrid[0:ny, 0:nx] + 0.0) * px
        ax.contour(xx, yy, np.nan_to_num(z), [max(5 * noise, 0.05 * (m.pileup_nm if np.isfinite(m.pileup_nm) else 0))],
                   colors="lime", linewidths=0.8)
    else:
        ax.imshow(f.image, cmap="gray", extent=ext)
        bar = f.info.get("bar_rows") or 0
        if bar:
            yb = (ny - bar - 0.5) * px
            ax.axhline(yb, color="orange", lw=0.8, ls="--", label=f"information bar ({bar} rows) left out")
    if m.contour_um is not None and f.kind == "afm":
        ax.plot(m.contour_um[:, 0], m.contour_um[:, 1], "-", color="cyan", lw=0.9, label="contact boundary")
    for i, chip in enumerate(m.chips_um or ()):
        ax.fill(chip[:, 0], chip[:, 1], facecolor="none", edgecolor="magenta", hatch="////", lw=0.9,
                label="chip (not in the area)" if i == 0 else None)
    c = m.corners_um
    for a, b in ((0, 2), (1, 3)):
        ax.plot(c[[a, b], 0], c[[a, b], 1], "--", color="white", lw=0.8)
    ax.plot(c[:, 0], c[:, 1], "o", ms=7, mfc="none", mec="red", mew=1.5, label="corners")
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    _legend_above(ax)
    both = " from both scan directions, each where its scan leaves the imprint" if f.info.get("n_both_directions") else ""
    what = (f"contact boundary at the original-surface level (cyan{';' if both else ''}{both}), pile-up above 5 noise "
            "levels (green)"
            + (", chips spalled beside the edges, drawn past and left out of the area (magenta, hatched)."
               if m.chips_um else ".")
            if f.kind == "afm" else "information bar left out (orange dashed) where there is one.")
    cap = f"<code>{esc(os.path.basename(f.source))}</code>: corners (red), diagonals (white dashed), {what}"
    return img(png_b64(fig), f.source, cap)


def _micrograph_zoom(f, m):
    """The imprint enlarged, with its four corners, and each corner at high magnification."""
    px = f.pixel_um
    ny, nx = f.image.shape
    ext = (-0.5 * px, (nx - 0.5) * px, (ny - 0.5) * px, -0.5 * px)
    c = m.corners_um
    closed = m.contour_um if m.contour_um is not None else np.vstack([c, c[:1]])
    lo, hi = np.nanpercentile(f.image, [0.5, 99.5])
    fig = new_figure(11.0, 5.6)
    gs = fig.add_gridspec(2, 4)
    ax = fig.add_subplot(gs[:, :2])
    ax.imshow(f.image, cmap="gray", extent=ext, vmin=lo, vmax=hi)
    ax.plot(closed[:, 0], closed[:, 1], "-", color="cyan", lw=0.7)
    for a, b in ((0, 2), (1, 3)):
        ax.plot(c[[a, b], 0], c[[a, b], 1], "--", color="yellow", lw=0.6)
    ax.plot(c[:, 0], c[:, 1], "+", ms=12, color="red", mew=1.2)
    half = 0.7 * max(m.diag1_um, m.diag2_um)
    ax.set_xlim(m.x_um - half, m.x_um + half)
    ax.set_ylim(m.y_um + half, m.y_um - half)
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    win = max(0.08 * m.d_um, 12 * px)
    for k in range(4):
        axk = fig.add_subplot(gs[k // 2, 2 + k % 2])
        axk.imshow(f.image, cmap="gray", extent=ext, vmin=lo, vmax=hi, interpolation="nearest")
        axk.plot(closed[:, 0], closed[:, 1], "-", color="cyan", lw=0.6)
        axk.plot(c[k, 0], c[k, 1], "+", ms=16, color="red", mew=1.2)
        axk.set_xlim(c[k, 0] - win, c[k, 0] + win)
        axk.set_ylim(c[k, 1] + win, c[k, 1] - win)
        axk.set_title(f"corner {k + 1} ({c[k, 0]:.2f}, {c[k, 1]:.2f}) µm", fontsize=8)
        axk.tick_params(labelsize=6)
    cap = (f"<code>{esc(os.path.basename(f.source))}</code>: the imprint enlarged with its corners (red +), "
           "fitted outline with its edges' bows (cyan) and diagonals (yellow); right: each corner magnified (±"
           f"{win:.2f} µm) so a person can check that it sits where the facet edges end.")
    return img(png_b64(fig), f.source + " corners", cap)


def _profiles(f, m):
    from scipy import ndimage
    px = f.pixel_um
    fig = new_figure(8.0, 3.4)
    ax = fig.add_subplot(111)
    c = m.corners_um
    for (a, b), col in (((0, 2), "tab:blue"), ((1, 3), "tab:orange")):
        p0, p1 = c[a], c[b]
        ln = np.hypot(*(p1 - p0))
        s = np.linspace(-0.15, 1.15, 400)
        pts = p0 + s[:, None] * (p1 - p0)
        v = ndimage.map_coordinates(np.nan_to_num(f.image), [pts[:, 1] / px, pts[:, 0] / px], order=1, mode="nearest")
        ax.plot((s - 0.5) * ln, v, color=col, lw=1, label=f"diagonal {a + 1}–{b + 1} ({ln:.2f} µm)")
    if f.kind == "afm":
        ax.axhline(0, color="gray", lw=0.8, ls="--", label="original surface")
        if np.isfinite(m.depth_nm):
            ax.axhline(-m.depth_nm, color="red", lw=0.8, ls=":", label=f"floor −{m.depth_nm:.1f} nm")
        ax.set_ylabel("height (nm)")
    else:
        ax.set_ylabel("grey value" if f.info.get("bar_rows") is not None else "grey value / illumination")
    ax.set_xlabel("distance from the middle of the diagonal (µm)")
    _legend_above(ax)
    return img(png_b64(fig), f.source + " profiles", "Profiles along both diagonals, corner to corner and 15 % beyond.")


def single_section(files) -> str:
    """HTML of every file with at most ``MAX_SINGLE`` imprints: numbers, map, diagonal profiles."""
    parts = []
    for f, k in _singles(files):
        m = f.imprints[k]
        parts.append(f"<h2>Imprint {int(f.table['id'][k])} of <code>{esc(os.path.basename(f.source))}</code></h2>")
        parts.append(table(["quantity", "value"], _numbers(f, k)))
        parts.append(_map(f, m))
        if f.kind != "afm":
            parts.append(_micrograph_zoom(f, m))
        parts.append(_profiles(f, m))
    return "".join(parts)
