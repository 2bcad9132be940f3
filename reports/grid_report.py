"""Self-contained HTML report of one grid flow result (hand-measured galvo grid).

Summary first, then the model comparison (k-fold CV of every model on the same
folds), the registration, the deviations, the correction over the lens field
and the nodes it extrapolates. Figures on matplotlib's Agg canvas, inline PNG.
"""
from __future__ import annotations

import numpy as np

from markcal.reports.html import (arrow_key, arrow_scale, data_files_footer, esc, img, new_figure, nice_number, num, page, png_b64,
                                  table)
from markcal.stages.galvo_fit import KINDS, PARAM_NAMES

__all__ = ["grid_report_html"]

DATA_FILES = (
    ("fiducials.csv", "one row per measured mark: commanded (nominal) and registered measured positions, input "
                      "positions, fit and cross-validation residuals (mm)"),
    ("deviations.csv", "per-mark deviations δ = nominal − measured (mm)"),
    ("correction_grid.csv", "command offsets (mm) on a grid over the whole lens field; extrapolated = more than "
                            "one pitch outside the marks' hull"),
    ("stage_error.csv", "the same command offsets in µm, in the selfcal flow's layout (for markcal export a3200)"),
    ("model.json", "the fitted model (physical galvo parameters, spline or cubic); markcal export reads it"),
    ("summary.json", "the summary values of this report"),
)
MODEL_LABELS = {"physical+rbf": "physical galvo + thin-plate spline", "rbf": "thin-plate spline alone",
                "poly3": "cubic polynomial"}
#: at most this many extrapolated nodes are listed one by one
MAX_LISTED = 20


def _summary(result) -> str:
    s = result.summary
    rows = [
        ("marks measured", num(s["n_marks"], ""), f"{s['n_unmeasured']} rows without a measurement"
         if s["n_unmeasured"] else ""),
        ("input layout", esc(s["layout"]), esc(f"{s['units_per_mm']:g} units/mm") if s.get("units_per_mm") else ""),
        ("pitch", num(s["pitch_mm"]), "median nearest-neighbour spacing of the commands"),
        ("lens field", num(s["lens_mm"]), "correction grid covers ± half of it"),
        ("measured deviation RMS |δ|", num(s["rms_mm"]), "after rigid registration"),
        ("measured deviation max |δ|", num(s["max_mm"]), ""),
        ("model", esc(MODEL_LABELS[s["model"]]), f"requested: {esc(s['model_requested'])}"),
        (f"{s['folds']}-fold CV prediction error (RMS)", num(s["cv_rmse_mm"]), "held-out marks, Euclidean"),
        ("fit residual RMS", num(s["fit_rms_mm"]), "all marks"),
        ("largest correction", num(s["max_correction_mm"]), "over the lens field"),
        ("extrapolated nodes", num(s["n_extrapolated"], ""), f"of {s['n_nodes']}, more than one pitch outside "
                                                               "the measured hull"),
    ]
    return "<h2>Summary</h2>" + table(["quantity", "value", "note"], rows, left_cols=1)


def _comparison(result) -> str:
    cv = result.choice.cv_rmse_mm
    best = min(cv, key=cv.get)
    rows = []
    for k in KINDS:
        mark = " (used)" if k == result.model.kind else ""
        rel = f"{100 * (cv[k] / cv[best] - 1):+.1f} %" if k != best else "lowest"
        rows.append((esc(MODEL_LABELS[k] + mark), num(cv[k]), rel))
    return ("<h2>Models compared</h2><p>Each model is fitted again without each fold (every choice inside it, "
            "such as the spline's smoothing, made on the training marks only) and predicts the held-out marks; "
            "all models use the same folds.</p>" + table(["model", "k-fold CV error", "vs lowest"], rows))


def _registration(result) -> str:
    s = result.summary
    parts = ["<h2>Registration</h2>"]
    if s["mirrored"]:
        parts.append('<div class="warn">The measurement is <b>mirrored</b> relative to the commanded grid (the '
                     "plate was measured from the back or with a flipped axis): it was registered with a "
                     f"reflection (RMS {num(s['registration_rms_mirrored_mm'])} against "
                     f"{num(s['registration_rms_proper_mm'])} without).</div>")
    parts.append(f"<p>Measured frame turned by {s['rotation_deg']:.3f}° onto the commanded frame; rigid "
                 f"registration RMS {num(s['registration_rms_mm'])} (this is the machine's distortion plus "
                 "measurement noise).</p>")
    return "".join(parts)


#: the physical galvo model's parameters as a reader knows them: label, unit, factor from the stored value
PARAM_LABELS = {"dd_mm": ("Δd, change of the X-mirror distance", "mm", 1.0),
                "de_mm": ("Δe, change of the mirror spacing", "mm", 1.0),
                "gain_x_err": ("X mirror gain error", "%", 100.0), "gain_y_err": ("Y mirror gain error", "%", 100.0),
                "zero_x_rad": ("X mirror zero offset", "mrad", 1e3), "zero_y_rad": ("Y mirror zero offset", "mrad", 1e3),
                "coupling_xy": ("coupling of Y's angle into X", "mrad/rad", 1e3),
                "coupling_yx": ("coupling of X's angle into Y", "mrad/rad", 1e3),
                "lens_k3_mm": ("lens radial term k3 at the lens radius", "mm", 1.0),
                "lens_p1_mm": ("lens decentring term p1 at the lens radius", "mm", 1.0),
                "lens_p2_mm": ("lens decentring term p2 at the lens radius", "mm", 1.0),
                "tilt_x": ("plate tilt about the y axis", "°", 1.0), "tilt_y": ("plate tilt about the x axis", "°", 1.0)}


def _physical(result) -> str:
    phys = result.model.physical
    if phys is None:
        return ""
    rows = [("d, X mirror to the plane centre (controller's nominal)", f"{phys.d0_mm:.2f} mm"),
             ("e, between the mirror axes (controller's nominal)", f"{phys.e0_mm:.2f} mm")]
    for k, v in zip(PARAM_NAMES, phys.params):
        label, unit, factor = PARAM_LABELS[k]
        v = np.degrees(np.arctan(v)) if unit == "°" else v * factor
        rows.append((f"{esc(label)} <code>{esc(k)}</code>", f"{v:.4g} {unit}".strip()))
    return ("<h2>Physical galvo model</h2><p>Paper 004 eqs. 1–5: mirror distances, gains and zero offsets, "
            "axis coupling, lens terms at radius " + num(phys.radius_mm) + ", plate tilt.</p>"
            + table(["parameter", "value"], rows))


def _deviation_figure(result) -> str:
    f = result.fiducials
    x, y, dx, dy = (np.asarray(f[k], float) for k in ("x_nom_mm", "y_nom_mm", "dx_mm", "dy_mm"))
    mag = np.hypot(dx, dy)
    mmax = float(mag.max()) if len(mag) else 0.0
    k = arrow_scale(result.pitch_mm, mmax)
    fig = new_figure(7.2, 6.2)
    ax = fig.add_subplot(111)
    h = result.lens_mm / 2
    ax.plot([-h, h, h, -h, -h], [-h, -h, h, h, -h], color="0.5", lw=1, label="lens field")
    q = ax.quiver(x, y, dx, dy, mag, angles="xy", scale_units="xy", scale=1.0 / k, cmap="viridis", width=0.004)
    cb = fig.colorbar(q, ax=ax, shrink=0.85, pad=0.02)
    cb.set_label("|δ| (mm)")
    key = nice_number(0.6 * mmax) if mmax > 0 else 0.1
    arrow_key(ax, q, key, f"{key:g} mm (magnified {k:g}×)")
    cv = np.hypot(f["cv_dx_mm"], f["cv_dy_mm"])
    worst = np.argsort(-cv)[:3]
    ax.scatter(x[worst], y[worst], s=90, facecolors="none", edgecolors="red", label="largest CV error")
    ax.set_aspect("equal")
    ax.set_xlabel("x commanded (mm)")
    ax.set_ylabel("y commanded (mm)")
    ax.legend(loc="upper left", fontsize=8, frameon=False, bbox_to_anchor=(0.0, 1.08), ncol=2)
    ax.grid(alpha=0.25)
    cap = (f"Deviation δ = commanded − measured at each mark, <b>arrows magnified {k:g}×</b>. Red circles: "
           f"the three marks the model predicts worst when they are held out.")
    return img(png_b64(fig), "deviation vectors", cap)


def _correction_figure(result) -> str:
    xy, dxy = result.grid_xy_mm, result.grid_dxy_mm
    xs, ys = np.unique(xy[:, 0]), np.unique(xy[:, 1])
    mag = np.hypot(*dxy.T).reshape(len(ys), len(xs))
    fig = new_figure(7.2, 6.2)
    ax = fig.add_subplot(111)
    im = ax.pcolormesh(xs, ys, mag, shading="nearest", cmap="magma")
    cb = fig.colorbar(im, ax=ax, shrink=0.85, pad=0.02)
    cb.set_label("|command offset| (mm)")
    cmd = result.grid.cmd_mm
    ax.scatter(cmd[:, 0], cmd[:, 1], s=10, c="cyan", label="measured marks")
    ex = result.extrapolated
    if ex.any():
        ax.scatter(xy[ex, 0], xy[ex, 1], s=6, c="white", edgecolors="0.35", linewidths=0.4, marker="o", label="extrapolated nodes")
    ax.set_aspect("equal")
    ax.set_xlabel("x wanted (mm)")
    ax.set_ylabel("y wanted (mm)")
    ax.legend(loc="upper left", fontsize=8, frameon=False, bbox_to_anchor=(0.0, 1.08), ncol=2)
    cap = ("Size of the command offset over the whole lens field. White dots: nodes more than one pitch "
           f"({num(result.pitch_mm)}) outside the convex hull of the measured marks, where the model extrapolates.")
    return img(png_b64(fig), "correction over the lens field", cap)


def _extrapolated_list(result) -> str:
    ex = np.flatnonzero(result.extrapolated)
    head = (f"<h2>Extrapolated nodes</h2><p>{len(ex)} of {len(result.grid_xy_mm)} correction nodes lie more than "
            f"one pitch ({num(result.pitch_mm)}) outside the measured hull; their offsets come from the model "
            "alone.</p>")
    if not len(ex):
        return head
    order = ex[np.argsort(-result.grid_hull_mm[ex])][:MAX_LISTED]
    rows = [tuple(f"{v:.3f}" for v in (*result.grid_xy_mm[i], result.grid_hull_mm[i], *result.grid_dxy_mm[i]))
            for i in order]
    more = (f"<p>The {MAX_LISTED} furthest outside are listed; {len(ex) - MAX_LISTED} more are in "
            "correction_grid.csv.</p>") if len(ex) > MAX_LISTED else ""
    return head + table(["x, mm", "y, mm", "outside the hull by, mm", "dx, mm", "dy, mm"], rows, left_cols=0) + more


def grid_report_html(result) -> str:
    """Render a grid flow result as one self-contained HTML page (no scripts, no external URLs)."""
    s = result.summary
    verdict = (f"{s['n_marks']} marks · measured deviation RMS {num(s['rms_mm'])} · {esc(MODEL_LABELS[s['model']])}: "
               f"{s['folds']}-fold CV error {num(s['cv_rmse_mm'])} · correction over a {num(s['lens_mm'])} field, "
               f"{s['n_extrapolated']} nodes extrapolated" + (" · <b>mirrored measurement</b>" if s["mirrored"] else ""))
    parts = [f'<div class="verdict">{verdict}</div>', _summary(result), _comparison(result), _registration(result),
             "<h2>Deviations</h2>", _deviation_figure(result), "<h2>Correction over the lens field</h2>",
             _correction_figure(result), _physical(result), _extrapolated_list(result), data_files_footer(DATA_FILES)]
    return page("markcal grid report — hand-measured galvo grid", parts, source=s.get("source", result.source), summary=s)
