"""Files of a selfcal flow result: tables, correction grid, summary, report."""
from __future__ import annotations

import os

import numpy as np

from markcal.reports.files import atomic_write_text, start_outputs, write_csv, write_json
from markcal.stages.selfcal import site_xy_mm

__all__ = ["write_selfcal_outputs", "DATA_FILES"]

#: the data files written beside the report, with what they hold
DATA_FILES = (
    ("stage_error.csv", "m,n,x_mm,y_mm,gx_um,gy_um: the stage error G at each site (the stage reads p + G(p))"),
    ("stage_error_theta.csv", "k,theta_deg,gtheta_deg: the rotary stage error at each angular line"),
    ("correction_grid.csv", "x_mm,y_mm,dx_um,dy_um: command (x + dx, y + dy) to reach true (x, y); dx = Gx"),
    ("summary.json", "O, R, misalignments, residuals, noise levels, bounds, truth comparison when known"),
)


def write_selfcal_outputs(result, out_dir, report: bool = True) -> dict:
    """Write the tables, ``report.html`` and (last) ``summary.json``; return name -> path."""
    summary_path = start_outputs(out_dir)
    setup, sol = result.setup, result.solution
    M = setup.half
    m, n = np.meshgrid(np.arange(-M, M + 1), np.arange(-M, M + 1), indexing="ij")
    x, y = site_xy_mm(setup, m, n)
    paths = {}
    p = paths["stage_error.csv"] = os.path.join(out_dir, "stage_error.csv")
    write_csv(p, {"m": m.ravel(), "n": n.ravel(), "x_mm": x.ravel(), "y_mm": y.ravel(),
                  "gx_um": sol.gx_um.ravel(), "gy_um": sol.gy_um.ravel()})
    if sol.gtheta_deg.size:
        k = np.arange(sol.gtheta_deg.size)
        p = paths["stage_error_theta.csv"] = os.path.join(out_dir, "stage_error_theta.csv")
        write_csv(p, {"k": k, "theta_deg": k * 360.0 / sol.gtheta_deg.size, "gtheta_deg": sol.gtheta_deg})
    p = paths["correction_grid.csv"] = os.path.join(out_dir, "correction_grid.csv")
    write_csv(p, {"x_mm": x.ravel(), "y_mm": y.ravel(), "dx_um": sol.gx_um.ravel(), "dy_um": sol.gy_um.ravel()})
    if report:
        from markcal.reports.selfcal_report import render_selfcal_report_html
        p = paths["report.html"] = os.path.join(out_dir, "report.html")
        atomic_write_text(p, render_selfcal_report_html(result))
    write_json(summary_path, result.summary)
    paths["summary.json"] = summary_path
    return paths
