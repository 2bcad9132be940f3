"""Self-contained HTML report of a drift flow result: drift before/after per axis (paper Table 2) and curves."""
from __future__ import annotations

import numpy as np

from markcal.pipeline.flows.drift import DriftResult
from markcal.reports.html import data_files_footer, esc, img, new_figure, num, page, png_b64, table
from markcal.stages.drift import METHODS, in_force

__all__ = ["drift_report_html", "DATA_FILES"]

DATA_FILES = (("compensation.csv", "t_min, cx_um, cy_um, cz_um: compensation computed at t_min, in force until the next sample"),
              ("drift_methods.csv", "per method and axis: mean |error| before/after and η, at the samples and (with truth) between them"),
              ("summary.json", "flat summary of the run"))


def _curves(result: DriftResult) -> str:
    fig = new_figure(9.6, 7.0)
    fine = result.true_t_min if result.true_t_min is not None else np.arange(result.t_min[0], result.t_min[-1] + 1)
    for ax_i, a in enumerate("xyz"):
        ax = fig.add_subplot(3, 1, ax_i + 1)
        if result.true_um is not None:
            ax.plot(fine, result.true_um[:, ax_i] * 1e3, color="#222", lw=1, label="true drift")
        ax.plot(result.t_min, result.meas_um[:, ax_i] * 1e3, "o", color="#222", ms=3, label="samples")
        for name, col in (("paper", "#e67e22"), (result.method, "#2c7fb8")):
            c = in_force(result.t_min, result.comp_um[name], fine)[:, ax_i]
            ref = result.true_um[:, ax_i] if result.true_um is not None else np.interp(fine, result.t_min, result.meas_um[:, ax_i])
            ax.plot(fine, (ref - c) * 1e3, color=col, lw=1, label=f"residual, {name}")
        ax.axhline(0, color="#aaa", lw=0.5)
        ax.set_ylabel(f"{a} (nm)")
        if ax_i == 0:
            ax.legend(fontsize=7, ncol=4)
    ax.set_xlabel("t (min)")
    cap = ("Drift over time and the residual after compensation (compensation held between samples). "
           + ("Residuals against the true drift at 1-min resolution." if result.true_um is not None
              else "No true drift given: residuals against the samples interpolated linearly (indicative only)."))
    return img(png_b64(fig), "drift curves", cap)


def drift_report_html(result: DriftResult) -> str:
    """The whole report page."""
    s = result.summary
    src = "true" if result.true_um is not None else "samples"
    parts = [f'<div class="verdict">Method <b>{esc(result.method)}</b>: η = {num(s["eta_x_pct"], "%")} (x), '
             f'{num(s["eta_y_pct"], "%")} (y), {num(s["eta_z_pct"], "%")} (z), '
             + ("against the true drift between samples." if src == "true" else "judged at the samples.") + "</div>"]
    parts.append("<h2>Drift before and after compensation (paper Table 2)</h2>")
    head = ["method", "axis", "mean |drift| before", "mean |error| after", "η"]
    rows = []
    for name in METHODS:
        e = result.eta[name]
        for ax, a in enumerate("xyz"):
            rows.append([esc(name) + (" (chosen)" if name == result.method else ""), a,     # nm, as the curves
                         num(e[f"pre_{src}_um"][ax] * 1e3, "nm"), num(e[f"post_{src}_um"][ax] * 1e3, "nm"),
                         num(e[f"eta_{src}_pct"][ax], "%")])
    parts.append(table(head, rows, left_cols=2))
    if src == "true":
        parts.append("<p>At the samples alone (error at t<sub>k+1</sub> = m<sub>k+1</sub> − C<sub>k</sub>): "
                     + ", ".join(f"{esc(n)} η = " + "/".join(num(v, "%") for v in result.eta[n]["eta_samples_pct"])
                                 for n in METHODS) + ".</p>")
    parts.append("<p>The paper (Table 2) reports η = 76 % (X/Y) and 78 % (Z) for its filter (α = 0.8).</p>")
    parts.append(_curves(result))
    parts.append(data_files_footer(DATA_FILES))
    return page("markcal drift: online drift compensation", parts, source=result.source, summary=s)
