"""Self-contained HTML report of a pmcal flow result: the three methods compared, GA convergence, residuals."""
from __future__ import annotations

import numpy as np

from markcal.pipeline.flows.pmcal import COMPARED, PmcalResult
from markcal.reports.html import (arrow_key, arrow_scale, data_files_footer, esc, img, new_figure, nice_number, num, page, png_b64,
                                  table)
from markcal.stages.pm_model import model_to_dict

__all__ = ["pmcal_report_html", "DATA_FILES"]

#: human labels of the compared model parameters
PARAM_LABELS = {"scale_x_ppm": "scale error x", "scale_y_ppm": "scale error y", "scale_z_ppm": "scale error z",
                "nonorth_xy_urad": "non-orthogonality x–y", "nonorth_xz_urad": "non-orthogonality x–z",
                "nonorth_yz_urad": "non-orthogonality y–z", "plane_tilt_x_urad": "surface slope along x",
                "plane_tilt_y_urad": "surface slope along y"}

DATA_FILES = (("calibration.json", "the chosen method's parameters with units, E terms and F, method, seed"),
              ("methods.csv", "one row per method: F, E terms, time, parameters, errors against truth if known"),
              ("residuals.csv", "measured − model per axis point, pose pair and probe point (µm)"),
              ("ga_convergence.csv", "best and mean F per GA generation"),
              ("summary.json", "flat summary of the run"))


def _convergence(result: PmcalResult) -> str:
    fig = new_figure(6.4, 3.4)
    ax = fig.add_subplot(111)
    g = np.arange(1, len(result.ga_best_f) + 1)
    ax.semilogy(g, result.ga_best_f, label="best F", color="#c0392b")
    ax.semilogy(g, result.ga_mean_f, label="population mean F", color="#999")
    for name, f in result.fits.items():
        if name != "ga":
            ax.axhline(f.terms["F"], ls="--", lw=0.8, color="#2c7fb8" if name == "lsq" else "#27ae60", label=f"{name} F")
    ax.set_xlabel("generation")
    ax.set_ylabel("F (eq. 9)")
    ax.legend(fontsize=8)
    return img(png_b64(fig), "GA convergence", "GA convergence: best and mean fitness F per generation "
               "(population 60, Pc 0.9, Pm 0.05); dashed: the least-squares optima.")


def _residuals(result: PmcalResult) -> str:
    ra, rp, rf = result.chosen.residuals
    d = result.data
    fig = new_figure(9.6, 3.2)
    ax = fig.add_subplot(131)
    for j, a in enumerate("xyz"):
        sel = np.abs(d.c_axes[:, j]) > 0
        ax.plot(d.c_axes[sel, j] / 1000, np.linalg.norm(ra[sel], axis=1) * 1e3, ".", label=f"{a} axis")
    ax.set_xlabel("commanded position (mm)")
    ax.set_ylabel("|residual| (nm)")
    ax.set_title("axis trajectories")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(132)
    span_mm = np.ptp(d.c_pose[:, :2], axis=0) / 1000                   # marks spread over the field: mean spacing
    pitch_mm = float(np.sqrt(max(span_mm[0] * span_mm[1], 1e-12) / max(len(d.c_pose) - 1, 1))) or 1.0
    rmax_um = float(np.hypot(rp[:, 0], rp[:, 1]).max())
    k = arrow_scale(pitch_mm, rmax_um)          # mm drawn per µm of residual
    q = ax.quiver(d.c_pose[:, 0] / 1000, d.c_pose[:, 1] / 1000, rp[:, 0] * k, rp[:, 1] * k, angles="xy",
                  scale_units="xy", scale=1, color="#c0392b", width=0.006)
    key_um = nice_number(0.6 * max(rmax_um, 1e-12))
    arrow_key(ax, q, key_um * k, f"{key_um * 1e3:g} nm")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_title("pose pairs: XY residual")
    ax = fig.add_subplot(133)
    sc = ax.scatter(d.c_probe[:, 0] / 1000, d.c_probe[:, 1] / 1000, c=rf * 1e3, cmap="coolwarm")
    fig.colorbar(sc, ax=ax, label="nm")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_title("probe: height residual")
    return img(png_b64(fig), "residuals", f"Residuals of the chosen method ({esc(result.method)}).")


def pmcal_report_html(result: PmcalResult) -> str:
    """The whole report page."""
    s = result.summary
    ch = result.chosen
    parts = [f'<div class="verdict">Method <b>{esc(result.method)}</b>: F = {num(ch.terms["F"], "")} '
             f'(E_ortho {num(ch.terms["ortho"], "")}, E_pose {num(ch.terms["pose"], "")}, '
             f'E_flat {num(ch.terms["flat"], "")}, E_dyn {num(ch.terms["dyn"], "")}); residual RMS: axes '
             f'{num(s["axes_rms_um"], "µm")}, pose {num(s["pose_rms_um"], "µm")}, probe {num(s["probe_rms_um"], "µm")}.'
             + (f' Against the truth: 100 targets land within RMS {num(s["landing_rms_um"], "µm")}, '
                f'max {num(s["landing_max_um"], "µm")}, depth error max {num(s["depth_err_max_um"], "µm")}.'
                if "landing_rms_um" in s else "") + "</div>"]
    src = s.get("pose_source", "pose.csv")
    parts.append(f"<p>{s['n_pose_pairs']} pose pairs from <code>{esc(src)}</code>"
                 + (" (mark centres measured in the om/ micrographs with the indents OM model; OM position = "
                    "image-centre position + offset, x along the columns, y down the rows)" if src == "marks.csv"
                    else "") + ".</p>")
    for w in result.warnings:
        parts.append(f'<div class="warn">{esc(w)}</div>')
    parts.append("<h2>The three methods</h2>")
    head = ["method", "F", "E_ortho", "E_pose", "E_flat", "E_dyn", "time"]
    rows = [[esc(n), num(f.terms["F"], ""), num(f.terms["ortho"], ""), num(f.terms["pose"], ""),
             num(f.terms["flat"], ""), num(f.terms["dyn"], ""), num(f.seconds, "s")] for n, f in result.fits.items()]
    parts.append(table(head, rows))
    head = ["parameter"] + list(result.fits) + (["truth"] if result.truth else [])
    rows = []
    dicts = {n: model_to_dict(f.model) for n, f in result.fits.items()}
    for k, unit in COMPARED:
        rows.append([esc(PARAM_LABELS.get(k, k))] + [num(dicts[n][k], unit) for n in result.fits]
                    + ([num(result.truth[k], unit)] if result.truth else []))
    for i, a in enumerate("xyz"):
        rows.append([f"pose rotation {a}"] + [num(dicts[n]["rotvec_urad"][i], "µrad") for n in result.fits]
                    + ([num(result.truth["rotvec_urad"][i], "µrad")] if result.truth else []))
    for i, a in enumerate("xyz"):
        rows.append([f"T {a}"] + [num(dicts[n]["T_um"][i], "µm") for n in result.fits]
                    + ([num(result.truth["T_um"][i], "µm")] if result.truth else []))
    rows.append(["surface height at the origin"] + [num(dicts[n]["plane_c_um"], "µm") for n in result.fits]
                + ([num(result.truth["plane_c_um"], "µm")] if result.truth else []))
    parts.append(table(head, rows))
    if result.truth:
        parts.append("<h2>Against the truth</h2>")
        keys = [k for k, _ in COMPARED] + ["pose_rot_urad"]
        head = ["error against the truth"] + list(result.fits)
        units = dict(COMPARED, pose_rot_urad="µrad")
        labels = dict(PARAM_LABELS, pose_rot_urad="pose rotation")
        rows = [[f"{esc(labels.get(k, k))} ({units[k]})"] + [num(result.fits[n].truth_errors[f"err_{k}"], "")
                                                            for n in result.fits] for k in keys]
        for k, lab in (("landing_rms_um", "landing RMS (µm)"), ("landing_max_um", "landing max (µm)"),
                       ("depth_err_max_um", "depth error max (µm)")):
            rows.append([lab] + [num(result.fits[n].truth_errors[k], "") for n in result.fits])
        parts.append(table(head, rows))
        parts.append("<p>Goals: landing RMS ≤ 0.05 µm, max ≤ 0.10 µm, depth within ±0.005 µm; non-orthogonality "
                     "within 2 µrad, scale within 5 ppm, pose rotation within 10 µrad, plane tilt within 2 µrad.</p>")
    parts.append("<h2>GA convergence</h2>")
    parts.append(_convergence(result))
    parts.append("<h2>Residuals</h2>")
    parts.append(_residuals(result))
    parts.append(data_files_footer(DATA_FILES))
    return page("markcal pmcal: precision-marking machine calibration", parts, source=result.source, summary=result.summary)
