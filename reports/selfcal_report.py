"""Self-contained HTML report of a selfcal flow result (paper 001 Figs. 4-5, Tables 1-2)."""
from __future__ import annotations

import numpy as np

from markcal.reports.html import (arrow_key, arrow_scale, data_files_footer, esc, img, new_figure, nice_number, num, page, png_b64,
                                  table)
from markcal.stages.selfcal import site_xy_mm

__all__ = ["selfcal_report_html", "DATA_FILES"]

#: the data files written beside the report, with what they hold
DATA_FILES = (
    ("stage_error.csv", "m,n,x_mm,y_mm,gx_um,gy_um: the stage error G at each site (the stage reads p + G(p))"),
    ("stage_error_theta.csv", "k,theta_deg,gtheta_deg: the rotary stage error at each angular line"),
    ("correction_grid.csv", "x_mm,y_mm,dx_um,dy_um: command (x + dx, y + dy) to reach true (x, y); dx = Gx"),
    ("summary.json", "O, R, misalignments, residuals, noise levels, bounds, truth comparison when known"),
)

#: paper 001 Table 1 and 2 (noise 0.02 µm / 0.001° and 0.002 µm / 0.0001°): EGθ max, min, std (deg);
#: the EGx, EGy rows did not survive the text extraction
PAPER_GTHETA = {"0.001": (1.5877e-3, -1.2065e-3, 7.1184e-4), "0.0001": (2.9963e-4, -6.9733e-4, 7.6657e-5)}


def _grid(result):
    M = result.setup.half
    m, n = np.meshgrid(np.arange(-M, M + 1), np.arange(-M, M + 1), indexing="ij")
    return site_xy_mm(result.setup, m, n)


def _quiver(result) -> str:
    sol = result.solution
    x, y = _grid(result)
    mag = np.hypot(sol.gx_um, sol.gy_um)
    scale_mm_per_um = arrow_scale(result.setup.pitch_mm, float(mag.max()))
    fig = new_figure(6.4, 6.0)
    ax = fig.add_subplot(111)
    ax.plot(x, y, ".", color="#999", ms=3)
    if result.truth:        # truth first, wide and pale, so the estimate drawn over it stays visible
        N = result.setup.n
        tx = np.asarray(result.truth["gx_um"]).reshape(N, N)
        ty = np.asarray(result.truth["gy_um"]).reshape(N, N)
        ax.quiver(x, y, tx * scale_mm_per_um, ty * scale_mm_per_um, angles="xy", scale_units="xy",
                  scale=1, color="#8ec1e6", width=0.011, zorder=2, label="truth")
    q = ax.quiver(x, y, sol.gx_um * scale_mm_per_um, sol.gy_um * scale_mm_per_um, angles="xy",
                  scale_units="xy", scale=1, color="#c0392b", width=0.004, zorder=3, label="estimate")
    key_um = nice_number(0.6 * max(float(mag.max()), 1e-12))
    arrow_key(ax, q, key_um * scale_mm_per_um, f"{key_um:g} µm")
    if result.truth:
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)   # beside the map
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"stage error G, arrows × {scale_mm_per_um * 1e3:,.0f}")
    cap = (f"Stage error map: each arrow is G at a site, drawn {scale_mm_per_um * 1e3:,.0f}× (paper Fig. 4). "
           + ("Red (narrow): estimate, drawn over the truth (pale blue, wide)." if result.truth else ""))
    return img(png_b64(fig), "stage error quiver", cap)


def _heatmaps(result) -> str:
    sol = result.solution
    x, y = _grid(result)
    ext = [x.min() - result.setup.pitch_mm / 2, x.max() + result.setup.pitch_mm / 2,
           y.min() - result.setup.pitch_mm / 2, y.max() + result.setup.pitch_mm / 2]
    fields = [("Gx (µm)", sol.gx_um, "RdBu_r"), ("Gy (µm)", sol.gy_um, "RdBu_r"),
              ("Fx (µm): Gx without O, R", sol.fx_um, "RdBu_r"), ("Fy (µm)", sol.fy_um, "RdBu_r"),
              ("predicted sd of Gx (µm)", sol.predicted_sd_gx_um, "viridis"),
              ("predicted sd of Gy (µm)", sol.predicted_sd_gy_um, "viridis")]
    fig = new_figure(11, 6.6)
    for i, (title, f, cmap) in enumerate(fields):
        ax = fig.add_subplot(2, 3, i + 1)
        lim = float(np.abs(f).max()) or 1.0
        kw = dict(vmin=-lim, vmax=lim) if cmap == "RdBu_r" else {}
        im = ax.imshow(f.T, origin="lower", extent=ext, cmap=cmap, **kw)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        if i >= 3:
            ax.set_xlabel("x (mm)", fontsize=8)
        if i % 3 == 0:
            ax.set_ylabel("y (mm)", fontsize=8)
        cb = fig.colorbar(im, ax=ax, shrink=0.8)
        cb.set_label("µm", fontsize=8)
        cb.ax.tick_params(labelsize=7)
    cap = ("Heat maps over the stage (x right, y up, mm). F is the stage error without its linear "
           "non-orthogonality and scale-difference terms. The predicted standard deviation comes from "
           "the least-squares covariance with the noise level estimated from the residuals: it is the "
           "bound the solution reaches on this data.")
    return img(png_b64(fig), "stage error heat maps", cap)


def _theta(result) -> str:
    sol = result.solution
    K = sol.gtheta_deg.size
    th = np.arange(K) * 360.0 / K
    fig = new_figure(8, 3.4)
    ax = fig.add_subplot(111)
    ax.errorbar(th, sol.gtheta_deg * 1e3, yerr=sol.predicted_sd_gtheta_deg * 1e3, fmt="o-", ms=3,
                color="#c0392b", label="estimate ± predicted sd")
    if result.truth and "gtheta_deg" in result.truth:
        ax.plot(th, np.asarray(result.truth["gtheta_deg"]) * 1e3, "s", ms=4, mfc="none", color="#2c7fb8",
                label="truth")
    ax.axhline(0, color="#999", lw=0.8)
    ax.set_xlabel("θz (deg)")
    ax.set_ylabel("Gθ (millidegree)")
    ax.set_xticks(np.arange(0, 361, 45))
    ax.legend(fontsize=8)
    return img(png_b64(fig), "rotary stage error", "Rotary stage error Gθ at each angular line (paper Fig. 5).")


def _truth_tables(result) -> str:
    e, sol = result.errors, result.solution
    rows = []
    sd_xy = result.summary["predicted_sd_gxy_um"]
    # shown in nm and millidegrees: plain decimals, no exponents
    for name, key, unit, bound in (("E<sub>Gx</sub>", "gx_um", "nm", sd_xy), ("E<sub>Gy</sub>", "gy_um", "nm", sd_xy),
                                   ("E<sub>Gθ</sub>", "gtheta_deg", "m°", result.summary.get("predicted_sd_gtheta_deg"))):
        if key not in e:
            continue
        st = e[key]
        rows.append([f"{name} ({unit})", *(f"{1e3 * st[k]:.2f}" for k in ("max", "min", "std")),
                     f"{1e3 * bound:.2f}" if bound is not None else "not available",
                     f"{st['std'] / bound:.2f}" if bound else "not available"])
    noise_th = result.truth.get("noise_theta_deg")
    ref = PAPER_GTHETA.get(f"{noise_th:g}") if noise_th is not None else None
    note = ""
    if ref:
        note = (f"<p>Paper 001 reports, for the same noise level, E<sub>Gθ</sub> max {1e3 * ref[0]:.2f} m°, "
                f"min {1e3 * ref[1]:.2f} m°, std {1e3 * ref[2]:.2f} m° (its E<sub>Gx</sub>, E<sub>Gy</sub> rows are lost "
                "in the text; it states their std is below the noise).</p>")
    return ("<h2>Accuracy against truth (paper Tables 1–2 layout)</h2>"
            f"<p>Rendered session: measurement noise {num(result.truth.get('noise_xy_um'), 'µm')} and "
            f"{num(noise_th, '°')} per reading, mean of {result.truth.get('repeats', 1)} repeat(s). "
            "E = G − Ĝ. The bound is the standard deviation the full least-squares solution is predicted "
            "to reach on this data (its covariance); a ratio near 1 means the estimate is as good as the "
            "data allow.</p>"
            + table(["", "max", "min", "std", "bound (LSQ covariance)", "std / bound"], rows)
            + table(["", "truth", "estimate"], [
                ["non-orthogonality O (µrad)", f"{result.truth['nonorthogonality_urad']:.4f}",
                 f"{sol.nonorthogonality_urad:.4f}"],
                ["scale difference R (ppm)", f"{result.truth['scale_difference_ppm']:.4f}",
                 f"{sol.scale_difference_ppm:.4f}"]])
            + note)


def selfcal_report_html(result) -> str:
    """Render a selfcal flow result as one self-contained HTML page."""
    s, sol = result.summary, result.solution
    verdict = (f"Stage error over {s['n']} × {s['n']} sites at {num(s['pitch_mm'])}: RMS "
               f"Gx {num(s['gx_rms_um'], 'µm')}, Gy {num(s['gy_rms_um'], 'µm')}; non-orthogonality "
               f"O = {s['nonorthogonality_urad']:.3f} µrad, scale difference R = {s['scale_difference_ppm']:.3f} ppm. "
               f"Estimated to ± {num(s['predicted_sd_gxy_um'], 'µm')} (1σ) from readings with "
               f"{num(s['sigma_xy_um'], 'µm')} noise.")
    if s["k"]:
        verdict += (f" Rotary error Gθ over {s['k']} lines: RMS {num(s['gtheta_rms_deg'], '°')}, "
                    f"± {num(s['predicted_sd_gtheta_deg'], '°')}.")
    parts = [f'<div class="verdict">{esc(verdict)}</div>']
    if sol.notes:
        parts.append('<div class="warn">' + "<br>".join(esc(n) for n in sol.notes) + "</div>")
    mis = []
    for v in range(4):
        if f"view{v}_rotation_deg" in s:
            off = ([f"{s[f'view{v}_offset_x_um']:.3f}", f"{s[f'view{v}_offset_y_um']:.3f}"]
                   if f"view{v}_offset_x_um" in s else ["no XY readings", "(angle view)"])
            mis.append([f"view {v}", f"{s[f'view{v}_rotation_deg']:.5f}", *off])
    parts += [
        "<h2>Summary</h2>",
        table(["quantity", "value"], [
            ["sites, pitch", f"{s['n']} × {s['n']}, {num(s['pitch_mm'])}"],
            ["angular lines K", str(s["k"]) if s["k"] else "– (XY only)"],
            ["grid / angle readings", f"{s['n_grid_readings']} / {s['n_angle_readings']}"],
            ["residual RMS, grid", num(s["residual_rms_xy_um"], "µm")],
            ["residual RMS, angles", num(s["residual_rms_theta_deg"], "°")],
            ["noise estimated from residuals", f"{num(s['sigma_xy_um'], 'µm')}, {num(s['sigma_theta_deg'], '°')}"],
            ["condition number (1-norm, constrained system)", f"{s['condition_1norm']:.3g}"],
            ["Gauss–Newton iterations", str(s["iterations"])],
            ["runtime", num(s["runtime_s"], "s")],
        ]),
        "<h3>Misalignment of each view</h3>",
        table(["view", "rotation (°)", "offset x (µm)", "offset y (µm)"], mis),
        "<h2>Stage error map</h2>", _quiver(result), _heatmaps(result),
    ]
    if sol.gtheta_deg.size:
        parts += ["<h2>Rotary stage error</h2>", _theta(result)]
    if result.errors:
        parts.append(_truth_tables(result))
    parts.append("<h2>Method</h2><p>All unknowns (stage map G, artifact errors A, Gθ, Aθ, every view's "
                 "misalignment) are solved at once by sparse equality-constrained least squares, with the "
                 "misalignment rotations kept exact (Gauss–Newton). Gauge: G has no translation, rotation or "
                 "magnification, A no translation or rotation (paper eqs. 5, 11); Gθ on the four half axes is "
                 "tied to the mean angle deviation of the XY map there (paper eq. 9), entered as least-squares "
                 "equations as in paper eq. 27. Equations are weighted by the noise level of their group, "
                 "estimated from the residuals.</p>")
    parts.append(data_files_footer(DATA_FILES))
    return page("markcal selfcal report — XYθz stage self-calibration", parts, source=result.source, summary=result.summary)
