"""Self-contained HTML report of one scan flow result (paper 004 Figs. 4, 7-9, Table 1).

Everything is inline: CSS in a ``<style>`` block, figures as base64 PNG. The
module draws with matplotlib's Agg canvas (no pyplot state, nothing to close; matplotlib is imported
by the functions that draw, so that only the processes that draw import it: :mod:`markcal.reports.drawing`);
the point cloud is projected with numpy (:mod:`markcal.reports.cloud_view`).
It neither prints nor writes files; the caller stores the returned string.
"""
from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from markcal.reports.cloud_view import IsoView, splat
from markcal.reports.drawing import draw_groups_later
from markcal.reports.html import (DPI, arrow_key, arrow_scale, data_files_footer, esc, img, new_figure, nice_number, num, page, png_b64,
                                  table)
from markcal.stages.plate import nominal_grid
from markcal.stages.deviation import GridCorrection

if TYPE_CHECKING:  # pragma: no cover
    from markcal.pipeline.flows.scan import ScanResult

__all__ = ["scan_report_html", "scan_report_later"]

#: data files the caller writes beside the report, with what they hold
DATA_FILES = (
    ("fiducials.csv", "one row per detected fiducial: nominal, measured and scanner-frame centres, fit quality"),
    ("deviations.csv", "per-fiducial deviations δ = nominal − measured (mm)"),
    ("correction_grid.csv", "regular grid of command offsets (mm) for the machine controller"),
    ("corrected_targets.csv", "corrected commands and galvo angles for the nominal targets"),
    ("model.json", "the RBF correction network (centres, weights, bias, spread; mm)"),
    ("summary.json", "the summary values of the table above"),
)
AREA_LABELS = {"full": "full field", "inner_150": "inner 150 × 150 mm", "inner_50": "inner 50 × 50 mm"}

def _rowcol(fid_id: int, cols: int) -> tuple:
    return divmod(int(fid_id), int(cols))


# ----------------------------------------------------------------------------- sections

def _verdict(s: dict, kind: str) -> str:
    n_exp, n_det = s.get("n_expected"), s.get("n_detected")
    parts = [f"{n_det} of {n_exp} fiducials detected"]
    if s.get("n_missing"):
        parts[0] += f" ({s['n_missing']} missing)"
    if kind == "validation":
        parts.append(f"residual after calibration: RMS {num(s.get('rms_mm'))}, max {num(s.get('max_mm'))}")
    else:
        parts.append(f"measured deviation: RMS {num(s.get('rms_mm'))}, max {num(s.get('max_mm'))}")
        if s.get("n_neurons") is not None:
            parts.append(f"correction model: {s.get('n_neurons')} neuron{'' if s.get('n_neurons') == 1 else 's'}, CV RMSE {num(s.get('cv_rmse_mm'))}, "
                         f"predicted residual RMS {num(s.get('predicted_residual_rms_mm'))}")
        else:
            parts.append(f"correction model: {s.get('model')}, CV RMSE {num(s.get('cv_rmse_mm'))}")
    return " · ".join(esc(p) for p in parts)


def _summary_section(result) -> str:
    s = result.summary
    cols = result.spec.cols
    cv = num(s.get("cv_rmse_mm"))
    if s.get("cv_rmse_std_mm") is not None:      # mean ± std in one unit (not "0.00295 mm ± 0.113 µm")
        cv = f"{1e3 * s['cv_rmse_mm']:.2f} ± {1e3 * s['cv_rmse_std_mm']:.2f} µm"
    rows = [
        ("fiducials expected", num(s.get("n_expected"), ""), f"{result.spec.rows} × {cols} grid, "
         f"pitch {num(result.spec.pitch_mm)}"),
        ("fiducials detected", num(s.get("n_detected"), ""), ""),
        ("missing ids", esc(", ".join(str(i) for i in s.get("missing_ids", [])) or "none"), "id = row · cols + col"),
        ("deviation RMS |δ|", num(s.get("rms_mm")), "full field"),
        ("deviation max |δ|", num(s.get("max_mm")), "full field"),
        ("deviation RMS x", num(s.get("rms_x_mm")), ""),
        ("deviation RMS y", num(s.get("rms_y_mm")), ""),
        ("correction model", esc(str(s.get("model", "ols-rbf"))), "--model"),
        ("CV RMSE of the correction model", cv, f"{result.options.folds}-fold"
         + (", mean ± std over folds" if s.get("cv_rmse_std_mm") is not None else "")),
        *([("neurons", num(s.get("n_neurons"), ""), "Gaussian RBF centres"),
           ("spread σ", num(s.get("spread_mm")), "chosen by cross-validation"),
           ("MSE goal", f"{float(s.get('mse_goal_mm2', np.nan)):.1e} mm²", "chosen by cross-validation")]
          if s.get("n_neurons") is not None else []),
        ("plate tilt", num(s.get("plate_tilt_deg"), "°"), "plate normal vs scanner z"),
        ("in-plane rotation", num(s.get("in_plane_rotation_deg"), "°"),
         "scanner frame → galvo frame" + (", seen mirrored (from the back)" if s.get("mirrored") else "")),
        ("orientation chosen by", esc(str(s.get("orientation_method", ""))), "orientation mark, rotation hint, "
         "or galvo model (else the scan is refused)"),
        ("galvo-model orientation margin", num(s.get("orientation_margin"), ""),
         "residual of the best other orientation ÷ the chosen one's (≥ 2 decides alone)"),
        ("plane fit RMS", num(s.get("plane_rms_mm")), f"inlier fraction {num(s.get('plane_inlier_fraction'), '')}"),
        (("pixels in image" if "image_pixel_mm" in s else "points in cloud"), num(s.get("n_points"), ""), ""),
        ("runtime", num(s.get("runtime_s"), "s"), "whole scan flow"),
        ("model fitting", num(s.get("rbf_training_s"), "s"), "cross-validation and final fit"),
    ]
    out = ["<h2>Summary</h2>", table(["quantity", "value", "note"], rows, left_cols=1)]
    if result.missing_ids:
        items = []
        for i in result.missing_ids:
            r, c = _rowcol(i, cols)
            items.append(f"id {i} (row {r}, col {c})")
        out.append(f'<div class="note">not detected: {esc("; ".join(items))}</div>')
    return "\n".join(out)


def _quiver_figure(result) -> str:
    f = result.fiducials
    spec = result.spec
    x, y = np.asarray(f["x_nom_mm"], float), np.asarray(f["y_nom_mm"], float)
    dx, dy = np.asarray(f["dx_mm"], float), np.asarray(f["dy_mm"], float)
    mag = np.hypot(dx, dy)
    mmax = float(mag.max()) if len(mag) else 0.0
    k = arrow_scale(spec.pitch_mm, mmax)
    big = max(spec.rows, spec.cols) > 11                   # a 19 x 19 plate: a larger plot, smaller circles
    fig = new_figure(10.0, 8.8) if big else new_figure(7.6, 6.6)
    ax = fig.add_subplot(111)
    ax.scatter(x, y, s=14 if big else 36, facecolors="none", edgecolors="0.75", linewidths=0.6, zorder=1)
    q = ax.quiver(x, y, dx, dy, mag, angles="xy", scale_units="xy", scale=1.0 / k, cmap="viridis",
                  width=0.0035, zorder=3, clim=(0, mmax if mmax > 0 else 1))
    cb = fig.colorbar(q, ax=ax, shrink=0.85, pad=0.02)
    cb.set_label("|δ| (mm)")
    key = nice_number(mmax) if mmax > 0 else 0.1         # about the longest arrow, so it can be compared
    hx, hy = spec.half_extent_mm
    m = 0.9 * spec.pitch_mm
    ax.set_xlim(-hx - m, hx + m)
    ax.set_ylim(-hy - m, hy + m)                           # before arrow_key, which extends y below the data
    arrow_key(ax, q, key, f"{key:g} mm (magnified {k:g}×)")
    if result.missing_ids:
        _, _, q_all = nominal_grid(spec)
        miss = q_all[np.asarray(result.missing_ids, int)]
        ax.scatter(miss[:, 0], miss[:, 1], marker="x", s=70, c="red", linewidths=2, zorder=4,
                   label="not detected")
        ax.legend(loc="upper left", bbox_to_anchor=(0.0, 1.07), fontsize=8, frameon=False)
    ax.set_aspect("equal")
    ax.set_xlabel("x nominal (mm)")
    ax.set_ylabel("y nominal (mm)")
    ax.grid(alpha=0.25)
    cap = (f"Deviation vectors δ = nominal − measured at the nominal fiducial positions (grey circles), "
           f"coloured by |δ|. <b>Arrows magnified {k:g}×</b> (an arrow of length L mm on the plot is a "
           f"deviation of L/{k:g} mm; key arrow {key:g} mm). Red crosses: fiducials not detected. "
           f"(Paper Fig. 7.)")
    return img(png_b64(fig), "deviation quiver plot", cap)


def _bins(v: np.ndarray) -> int:
    return int(np.clip(np.sqrt(max(len(v), 1)) * 1.5, 8, 40))


def _histogram_figures(result) -> str:
    from matplotlib.ticker import MaxNLocator
    f = result.fiducials
    dx, dy = np.asarray(f["dx_mm"], float), np.asarray(f["dy_mm"], float)
    mag = np.hypot(dx, dy)
    fig = new_figure(11.0, 3.2)
    for i, (v, lab, col) in enumerate(((dx, "δx (mm)", "#3b7dd8"), (dy, "δy (mm)", "#e07b39"),
                                       (mag, "|δ| (mm)", "#4c9a4c"))):
        ax = fig.add_subplot(1, 3, i + 1)
        ax.xaxis.set_major_locator(MaxNLocator(5))          # "−0.006−0.004…" ran together at 7 ticks
        if len(v):
            ax.hist(v, bins=_bins(v), color=col, edgecolor="white", linewidth=0.5)
            ax.axvline(float(np.mean(v)), color="k", lw=1, ls="--")
        ax.set_xlabel(lab)
        ax.set_ylabel("fiducials")
        ax.grid(alpha=0.25)
    # fixed margins, no layout pass; wide enough for the tick labels of a 19 x 19 plate (a label beyond the canvas
    # costs png_bytes a second drawing)
    fig.subplots_adjust(left=0.075, right=0.975, bottom=0.19, top=0.96, wspace=0.28)
    out = [img(png_b64(fig), "deviation histograms",
                "Histograms of the deviation components δx, δy and of |δ| (mm); dashed line: mean. "
                "(Paper Fig. 8.)")]

    fig = new_figure(6.0, 3.6)
    fig.subplots_adjust(bottom=0.16)           # the x label inside the canvas: one drawing pass (html.png_bytes)
    ax = fig.add_subplot(111)
    if len(mag):
        srt = np.sort(mag)
        frac = np.arange(1, len(srt) + 1) / len(srt) * 100
        ax.hist(mag, bins=max(_bins(mag), 20), cumulative=True, density=True, histtype="stepfilled",
                color="#4c9a4c", alpha=0.35, weights=None)
        ax.step(srt, frac / 100, where="post", color="#2a6b2a", lw=1.2)
        p80 = float(np.percentile(mag, 80))
        ax.axhline(0.8, color="red", lw=1, ls="--")
        ax.axvline(p80, color="red", lw=1, ls=":")
        ax.annotate(f"80 % of fiducials ≤ {p80:.3g} mm", (p80, 0.8), xytext=(-6, 6), ha="right",
                    textcoords="offset points", color="red", fontsize=9)
        out_p80 = p80
    else:
        out_p80 = float("nan")
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("|δ| (mm)")
    ax.set_ylabel("cumulative fraction of fiducials")
    ax.grid(alpha=0.25)
    out.append(img(png_b64(fig), "cumulative histogram",
                    f"Cumulative histogram of |δ|; dashed red line: the 80 % level, reached at "
                    f"{esc(num(out_p80))}. (Paper Fig. 9.)"))
    return "\n".join(out)


def _stats_table(stats: dict) -> str:
    keys = ("max_x_mm", "max_y_mm", "max_mm", "rms_x_mm", "rms_y_mm", "rms_mm")
    rows = []
    for name, st in stats.items():
        st = st or {}
        vals = ["–"] * 6 if not st.get("n") else [num(st.get(k), "") for k in keys]
        rows.append([esc(AREA_LABELS.get(name, name)), num(st.get("n", 0), "")] + vals)
    head = ("<tr><th class='l' rowspan='2'>area</th><th rowspan='2'>n</th>"
            "<th colspan='3'>max (mm)</th><th colspan='3'>RMS (mm)</th></tr>"
            "<tr><th>u<sub>x</sub></th><th>u<sub>y</sub></th><th>|δ|</th>"
            "<th>u<sub>x</sub></th><th>u<sub>y</sub></th><th>|δ|</th></tr>")
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i == 0 else ""}">{c}</td>' for i, c in enumerate(r))
                   + "</tr>" for r in rows)
    return ("<h2>Deviation by area (paper Table 1)</h2>"
            f"<table>{head}{body}</table>"
            "<p>Areas are centred squares in the galvo frame selected by the nominal positions; "
            "u<sub>x</sub>, u<sub>y</sub> are the components of δ.</p>")


def _cv_figure(sel) -> str:
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle
    cv_table = np.asarray(sel.table, float)
    spreads = np.asarray(sel.spreads_mm, float)
    goals = np.asarray(sel.goals_mm2, float)
    h_in = 0.45 * len(spreads) + 1.6
    fig = new_figure(7.4, h_in)
    fig.subplots_adjust(bottom=1.0 / h_in)     # room for the slanted goal labels inside the canvas
    ax = fig.add_subplot(111)
    cv_um = cv_table * 1000.0                     # the cell numbers and the colour bar in the same unit
    good = cv_um[np.isfinite(cv_um) & (cv_um > 0)]
    norm = LogNorm(vmin=good.min(), vmax=good.max()) if len(good) and good.max() > good.min() else None
    im = ax.imshow(cv_um, cmap="viridis_r", norm=norm, aspect="auto", origin="upper")
    cb = fig.colorbar(im, ax=ax, pad=0.02)
    cb.set_label("mean CV RMSE (µm)")
    from matplotlib.ticker import LogLocator, StrMethodFormatter
    cb.ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    cb.ax.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    cb.ax.yaxis.set_minor_formatter(StrMethodFormatter(""))
    ax.set_xticks(range(len(goals)))
    ax.set_xticklabels([f"{g:.0e}" for g in goals], rotation=35, ha="right", fontsize=8)
    ax.set_yticks(range(len(spreads)))
    ax.set_yticklabels([f"{s:.1f}" for s in spreads], fontsize=8)
    ax.set_xlabel("MSE goal (mm²)")
    ax.set_ylabel("spread σ (mm)")
    if len(good):
        thr = np.sqrt(good.min() * good.max())
        for i in range(cv_um.shape[0]):
            for j in range(cv_um.shape[1]):
                v = cv_um[i, j]
                if np.isfinite(v):
                    ax.text(j, i, f"{v:.1f}", ha="center", va="center", fontsize=7,
                            color="white" if v > thr else "black")
    bi = int(np.argmin(np.abs(spreads - sel.spread_mm)))
    bj = int(np.argmin(np.abs(np.log(goals) - np.log(sel.mse_goal_mm2))))
    ax.add_patch(Rectangle((bj - 0.5, bi - 0.5), 1, 1, fill=False, edgecolor="red", lw=2.2))
    return img(png_b64(fig), "cross-validation grid",
                f"Mean cross-validated RMSE over the (spread, MSE goal) grid; numbers in µm. "
                f"Red box: the chosen cell (σ = {num(sel.spread_mm)}, goal {sel.mse_goal_mm2:.0e} mm², "
                f"CV RMSE {num(sel.cv_rmse_mm)} ± {num(sel.cv_rmse_std_mm)}).")


def _field_figure(result) -> str:
    xy = np.asarray(result.grid_xy_mm, float)
    d = np.asarray(result.grid_dxy_mm, float)
    mag = np.hypot(d[:, 0], d[:, 1])
    fig = new_figure(6.6, 5.6)
    ax = fig.add_subplot(111)
    grid = GridCorrection.from_nodes(xy, d)
    xs, ys = grid.x_mm, grid.y_mm
    hx, hy = (xs[1] - xs[0]) / 2, (ys[1] - ys[0]) / 2
    im = ax.imshow(np.hypot(grid.dx_mm, grid.dy_mm), origin="lower",
                   extent=(xs[0] - hx, xs[-1] + hx, ys[0] - hy, ys[-1] + hy),
                   cmap="magma", interpolation="nearest")
    # about 25 arrows a side, symmetric about the grid centre
    sx, sy = int(np.ceil(len(xs) / 25)), int(np.ceil(len(ys) / 25))
    ix = np.searchsorted(xs, np.round(xy[:, 0], 9))
    iy = np.searchsorted(ys, np.round(xy[:, 1], 9))
    pick = np.flatnonzero(np.isin(ix, np.arange((len(xs) - 1) % sx // 2, len(xs), sx))
                          & np.isin(iy, np.arange((len(ys) - 1) % sy // 2, len(ys), sy)))
    step = min(sx * (xs[1] - xs[0]), sy * (ys[1] - ys[0]))
    cb = fig.colorbar(im, ax=ax, pad=0.02, shrink=0.9)
    cb.set_label("|command offset| (mm)")
    mmax = float(np.nanmax(mag)) if len(mag) else 0.0
    k = arrow_scale(step, mmax)
    q = ax.quiver(xy[pick, 0], xy[pick, 1], d[pick, 0], d[pick, 1], angles="xy", scale_units="xy",
                  scale=1.0 / k, color="white", edgecolor="black", linewidth=0.3, width=0.004)
    key = nice_number(0.6 * mmax) if mmax > 0 else 0.1
    arrow_key(ax, q, key, f"{key:g} mm (magnified {k:g}×)")
    ax.set_title("command offset K − Q (mm)", fontsize=10, loc="left", pad=10)
    ax.set_aspect("equal")
    ax.set_xlabel("wanted x (mm)")
    ax.set_ylabel("wanted y (mm)")
    return img(png_b64(fig), "correction field",
                f"Correction field of the model: command offset K − Q over the correction grid "
                f"({len(xy):,} nodes, colour = magnitude in mm); arrows show the offset at {len(pick)} "
                f"subsampled nodes, <b>magnified {k:g}×</b> (key arrow {key:g} mm).")


def _cv_edge_note(sel) -> str:
    """A warning when the chosen spread or goal sits at the edge of the searched grid."""
    spreads = np.asarray(sel.spreads_mm, float)
    goals = np.asarray(sel.goals_mm2, float)
    notes = []
    if len(spreads) > 1 and np.isclose(sel.spread_mm, spreads.max()):
        notes.append(f"the largest spread tried ({spreads.max():.4g} mm)")
    elif len(spreads) > 1 and np.isclose(sel.spread_mm, spreads.min()):
        notes.append(f"the smallest spread tried ({spreads.min():.4g} mm)")
    if len(goals) > 1 and np.isclose(sel.mse_goal_mm2, goals.min()):
        notes.append(f"the smallest MSE goal tried ({goals.min():.0e} mm²)")
    elif len(goals) > 1 and np.isclose(sel.mse_goal_mm2, goals.max()):
        notes.append(f"the largest MSE goal tried ({goals.max():.0e} mm²)")
    if not notes:
        return ""
    return ("The cross-validation chose " + " and ".join(notes)
            + ": the best setting may lie outside the searched grid.")


def _galvo_model_section(result, field_figure: str) -> str:
    mc = result.grid_model
    rows = [[esc(k), num(v, "")] for k, v in mc.cv_rmse_mm.items()]
    out = ["<h2>Correction model</h2>",
           f"<p>Model <b>{esc(mc.model.kind)}</b> (the grid flow's galvo models: paper 004 eqs. 1–5 physical "
           f"scanner plus a smoothing thin-plate spline, a spline alone, or a cubic), fitted to nominal → "
           f"measured positions; {mc.folds}-fold cross-validation of every model on the same folds:</p>",
           table(["model", "CV RMSE (mm)"], rows), field_figure]
    return "\n".join(out)


def _model_section(result, field_figure: str, cv_figure: str) -> str:
    """The correction model's section around its figures (drawn by :func:`_field_figure`, :func:`_cv_figure`)."""
    if result.grid_model is not None:
        return _galvo_model_section(result, field_figure)
    sel = result.selection
    out = ["<h2>Correction model</h2>",
           f"<p>Gaussian RBF network with <b>{int(result.model.n_neurons)} neurons</b>, spread σ = "
           f"{esc(num(sel.spread_mm))}, MSE goal {sel.mse_goal_mm2:.0e} mm², trained by orthogonal least "
           f"squares on the measured positions P → Q − P.</p>",
           cv_figure]
    edge = _cv_edge_note(sel)
    if edge:
        out.append(f'<div class="warn">{esc(edge)}</div>')
    out.append(field_figure)
    pr = result.predicted or {}
    rows = []
    for key, lab in (("inverse", "markcal: fitted inverse map (wanted Q → command K)"),
                     ("eq9", "paper eq. 9: K = Q + δ̂(Q)")):
        st = pr.get(key) or {}
        rows.append([esc(lab), num(st.get("rms_mm"), "") if st.get("n") else "–",
                     num(st.get("max_mm"), "") if st.get("n") else "–"])
    out.append("<h3>Predicted residual after correction</h3>")
    out.append(table(["method", "RMS |δ| (mm)", "max |δ| (mm)"], rows))
    out.append("<p>Both values are estimates: the landing position of each corrected command is "
               "predicted with the fitted forward model (nominal → landing error) on the correction grid "
               "inside the fiducial field. Eq. 9 (K = Q + δ̂(Q)) is only first order, because the machine "
               "errs at the command K, not at the wanted position Q; markcal instead fits the map from "
               "wanted position to command directly (trained on measured P → Q − P), so no error is "
               "evaluated at the wrong place.</p>")
    return "\n".join(out)


def _image_section(result) -> tuple:
    s = result.summary
    h, w = s.get("image_shape", [0, 0])
    note = (f"Image {w} × {h} pixels, {s.get('image_bits')} bit, pixel {num(s.get('image_pixel_mm'))} "
            f"(from the {s.get('image_pixel_size_from')}); "
            + ("marks brighter than the plate, so the grey values were inverted; " if s.get("image_inverted") else "")
            + "no plane fit or projection: the image is the plate raster (x = columns, y = rows).")
    return ("<h2>Image</h2>", f"<p>{esc(note)}</p>")


def _view_section(result) -> str:
    """The image note (image input) or the 3D view of the cloud."""
    return "\n".join(_image_section(result)) if "image_pixel_mm" in result.summary else _render_3d(result)


def _render_3d(result) -> str:
    xyz = np.asarray(result.preview_xyz_mm, float)
    inten = np.asarray(result.preview_intensity, float)
    if len(xyz) == 0:
        return '<div class="warn">3D view unavailable: no preview points</div>'
    fig = _cloud_figure(xyz, inten, np.asarray(result.plane.origin_mm, float), np.asarray(result.plane.normal, float))
    return img(png_b64(fig), "point cloud",
               f"Point cloud ({len(xyz):,} of {int(result.summary.get('n_points', len(xyz))):,} points shown), "
               f"isometric view, grey = backscatter intensity; red arrow: fitted plate normal at the plane origin "
               f"(60 mm long); tilt {esc(num(result.summary.get('plate_tilt_deg'), '°'))}.")


def _cloud_figure(xyz, inten, origin_mm, normal, arrow_mm: float = 60.0):
    """Isometric picture of the cloud (:mod:`markcal.reports.cloud_view`) with the plate normal and axes."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    w_px, h_px = 860, 560
    view = IsoView(np.vstack([xyz, origin_mm + arrow_mm * normal]), w_px, h_px)
    pic = splat(view, xyz, inten, size_px=2)
    lo, hi = np.percentile(inten, [1, 99])
    hi = max(hi, lo + 1e-6)
    w_fig, h_fig = w_px + 120, h_px + 30                    # pixels at the report's DPI: room for the colour bar
    fig = new_figure(w_fig / DPI, h_fig / DPI)
    x0, y0 = 0, 15
    grey = np.full(pic.shape, 255, np.uint8)                # white where no point landed
    seen = np.isfinite(pic)
    grey[seen] = np.round(np.clip((pic[seen] - lo) / (hi - lo), 0, 1) * 255)     # the "gray" colour map
    fig.figimage(np.repeat(grey[:, :, None], 3, axis=2), xo=x0, yo=y0, origin="upper")   # pixel for pixel
    ax = fig.add_axes((x0 / w_fig, y0 / h_fig, w_px / w_fig, h_px / h_fig))      # the picture's pixels as data units
    ax.patch.set_alpha(0.0)
    ax.set_zorder(1)                                        # above the picture
    ax.set_xlim(0, w_px)
    ax.set_ylim(h_px, 0)
    ax.set_axis_off()
    (c0, r0), (c1, r1) = view.to_pixel(np.vstack([origin_mm, origin_mm + arrow_mm * normal]))
    ax.annotate("", (c1, r1), (c0, r0), arrowprops={"arrowstyle": "-|>,head_length=0.9,head_width=0.45",
                                                       "color": "#c00000", "lw": 3.0, "shrinkA": 0, "shrinkB": 0})
    ax.plot([c0], [r0], "o", color="#c00000", ms=4)
    base = np.array([45.0, h_px - 40.0])
    for vec, lab, col in (((1, 0, 0), "x", "#e8603c"), ((0, 1, 0), "y", "#3aa655"), ((0, 0, 1), "z", "#1f4fd1")):
        d = view.direction(vec) * 32
        ax.annotate("", tuple(base + d), tuple(base), arrowprops={"arrowstyle": "-|>", "color": col, "lw": 1.6,
                                                                "shrinkA": 0, "shrinkB": 0})
        ax.text(*(base + 1.3 * d), lab, color=col, fontsize=9, ha="center", va="center", fontweight="bold")
    cax = fig.add_axes((ax.get_position().x1 + 0.02, 0.2, 0.025, 0.6))
    cb = fig.colorbar(ScalarMappable(Normalize(lo, hi), "gray"), cax=cax)
    cb.set_label("intensity")
    return fig


def _fiducial_uv(result, i: int) -> np.ndarray:
    f = result.fiducials
    p = np.array([f["x_scanner_mm"][i], f["y_scanner_mm"][i], f["z_scanner_mm"][i]], float)
    r = p - np.asarray(result.plane.origin_mm, float)
    return np.array([r @ np.asarray(result.plane.e_u, float), r @ np.asarray(result.plane.e_v, float)])


def _crop(image, raster, uv, half_mm):
    """Slice of ``image`` around ``uv`` and its imshow extent (mm)."""
    pix = raster.pixel_mm
    cr = raster.to_pixel(np.array([[uv[0] - half_mm, uv[1] - half_mm], [uv[0] + half_mm, uv[1] + half_mm]]))
    c0 = int(np.clip(np.floor(cr[0, 0] + 0.5), 0, image.shape[1]))
    c1 = int(np.clip(np.ceil(cr[1, 0] + 0.5), 0, image.shape[1]))
    r0 = int(np.clip(np.floor(cr[0, 1] + 0.5), 0, image.shape[0]))
    r1 = int(np.clip(np.ceil(cr[1, 1] + 0.5), 0, image.shape[0]))
    ext = (raster.u0_mm + c0 * pix, raster.u0_mm + c1 * pix, raster.v0_mm + r0 * pix, raster.v0_mm + r1 * pix)
    return image[r0:r1, c0:c1], ext, (r0, r1, c0, c1)


def _crop_panels(result) -> list:
    """The crops :func:`_fiducial_crops` draws, cut from the raster here (small and picklable): per picked
    fiducial its title, centre (u, v mm), fitted radius scale, crop extent and the four panels."""
    f = result.fiducials
    n = len(f["id"])
    if n == 0:
        return []
    centre = int(np.argmin(np.hypot(f["x_nom_mm"], f["y_nom_mm"])))
    rms = np.asarray(f["fit_rms"], float)
    worst = int(np.nanargmax(rms)) if np.isfinite(rms).any() else centre
    picks = [(centre, "nearest the field centre")]
    if worst != centre:
        picks.append((worst, "worst ring fit (largest fit RMS)"))
    raster, edges = result.raster, result.edges
    half = _crop_half_mm(result)
    out = []
    for i, why in picks:
        uv = _fiducial_uv(result, i)
        inten, ext, (r0, r1, c0, c1) = _crop(raster.intensity, raster, uv, half)
        inten = np.asarray(inten, float)
        valid = (np.ones(inten.shape, bool) if raster.valid is None
                 else np.asarray(raster.valid)[r0:r1, c0:c1])
        title = (f"id {int(f['id'][i])} (row {int(f['row'][i])}, col {int(f['col'][i])}): {why}\n"
                 f"fit RMS {float(f['fit_rms'][i]):.3g}, radius scale {float(f['ring_radius_scale'][i]):.4f}")
        panels = [(np.ma.masked_array(inten, ~valid), "intensity (raster)"),
                  (np.array(edges.filtered[r0:r1, c0:c1]), "median filtered"),
                  (np.array(edges.edges[r0:r1, c0:c1]), "Canny edges"),
                  (np.array(edges.filled[r0:r1, c0:c1]), "closed + filled")]
        out.append((title, uv, float(f["ring_radius_scale"][i]), ext, panels))
    return out


def _crop_half_mm(result) -> float:
    return max(4.0, 1.2 * max(result.spec.ring_radii_mm))


def _fiducial_crops(crops: list, radii: tuple, half: float) -> str:
    """Raster crops around the fiducials of :func:`_crop_panels` with their fitted rings and centres."""
    from matplotlib.patches import Circle
    from matplotlib.ticker import MaxNLocator
    if not crops:
        return "<p>No fiducials detected.</p>"
    h_in = 3.5 * len(crops)
    fig = new_figure(13.0, h_in)
    # fixed margins (inches: 0.5 for the x labels, 0.55 for the two-line titles) instead of a layout pass
    fig.subplots_adjust(left=0.045, right=0.99, bottom=0.5 / h_in, top=1 - 0.55 / h_in, wspace=0.32,
                        hspace=1.05 / (3.5 - 1.05))
    for k, (title, uv, scale, ext, panels) in enumerate(crops):
        for j, (im, name) in enumerate(panels):
            ax = fig.add_subplot(len(crops), len(panels), len(panels) * k + j + 1)
            if im.size == 0:
                ax.text(0.5, 0.5, "outside the raster", ha="center", va="center", transform=ax.transAxes)
                continue
            grey = j < 2
            if grey:
                vals = im.compressed() if np.ma.isMaskedArray(im) else im.ravel()
                lo, hi = (np.percentile(vals, [1, 99]) if vals.size else (0, 1))
                ax.imshow(im, cmap="gray", origin="lower", extent=ext, vmin=lo, vmax=hi, interpolation="nearest")
            else:
                ax.imshow(im.astype(float), cmap="gray", origin="lower", extent=ext, vmin=0, vmax=1,
                          interpolation="nearest")
            for rr in radii:
                ax.add_patch(Circle((uv[0], uv[1]), rr * scale, fill=False, edgecolor="#ff3b30",
                                    lw=0.9, ls=(0, (4, 3)) if grey else "-", alpha=0.85))
            ax.plot(uv[0], uv[1], "+", color="#00c8ff", ms=10, mew=1.5)
            ax.set_xlim(uv[0] - half, uv[0] + half)
            ax.set_ylim(uv[1] - half, uv[1] + half)
            ax.set_aspect("equal")
            ax.set_xlabel("u (mm)", fontsize=8)
            ax.set_ylabel("v (mm)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.xaxis.set_major_locator(MaxNLocator(5, steps=[1, 2, 5, 10]))   # fewer tick objects to lay out and draw
            ax.yaxis.set_major_locator(MaxNLocator(5, steps=[1, 2, 5, 10]))
            if j == 0:
                ax.set_title(title, fontsize=8.5, loc="left", y=1.0)   # a fixed y: no title placement pass
            else:
                ax.set_title(name, fontsize=9, y=1.0)
    radii_txt = ", ".join(f"{x:g}" for x in radii)
    return img(png_b64(fig), "fiducial crops",
                f"Raster crops ({2 * half:.0f} × {2 * half:.0f} mm, plate frame u, v) of {len(crops)} detected "
                f"fiducial(s) with the fitted rings (red, dashed on the grey images; spec radii {radii_txt} mm "
                f"× fitted radius scale) and the fitted centre (blue cross). Left to right: raster intensity, "
                f"median filtered, Canny edges, closed and hole-filled edges as fed to the Hough transform "
                f"(paper Fig. 4). Fit RMS is the robust residual scale in intensity units.")


def _footer() -> str:
    return data_files_footer(DATA_FILES)


# ----------------------------------------------------------------------------- entry point

def scan_report_html(result: "ScanResult") -> str:
    """Render a scan flow result as one self-contained HTML page.

    Parameters
    ----------
    result : ScanResult
        What ``markcal.pipeline.flows.scan.run_scan`` returned.

    Returns
    -------
    str
        The HTML document: inline CSS, figures as base64 PNG, no scripts and
        no external URLs.
    """
    return scan_report_later(result)()


def scan_report_later(result: "ScanResult"):
    """:func:`scan_report_html` in two steps: the figures start drawing now (in the drawing processes
    when they run), and the returned function (call it once) waits for them and returns the page."""
    s = result.summary
    kind = s.get("kind", "calibration")
    title = ("markcal scan report — validation plate (post-calibration)" if kind == "validation"
             else "markcal scan report — calibration plate")
    # the figures in two groups of about equal drawing time (measured on the 19 x 19 plate), drawn side by side
    # in other processes when a core is free (reports.drawing); they get the result without its raster and edge
    # images, whose crops are cut here
    light = replace(result, raster=None, edges=None)
    crops = (_crop_panels(result), tuple(result.spec.ring_radii_mm), _crop_half_mm(result))
    cv = [(_cv_figure, (light.selection,))] if light.grid_model is None else []
    drawn = draw_groups_later(
        [[(_fiducial_crops, crops), (_histogram_figures, (light,))],
         [(_quiver_figure, (light,)), (_view_section, (light,)), (_field_figure, (light,)), *cv]])

    def finish() -> str:
        (crop_figure, hist), (quiver, view, field, *cv_figure) = drawn()
        model = _model_section(result, field, cv_figure[0] if cv_figure else "")
        parts = [
            f'<div class="verdict">{_verdict(s, kind)}</div>',
            _summary_section(result),
            "<h2>Deviations</h2>",
            quiver,
            hist,
            _stats_table(result.stats),
            model,
            *(() if "image_pixel_mm" in s else ("<h2>Point cloud</h2>",)),
            view,
            "<h2>Detected fiducials</h2>",
            crop_figure,
            _footer(),
        ]
        return page(title, parts, source=s.get("source", result.source), summary=s)
    return finish
