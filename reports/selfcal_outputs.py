"""Files of a selfcal flow result: tables, correction grid, summary, report."""
from __future__ import annotations

import numpy as np

from markcal.reports.files import OutputFolder
from markcal.reports.selfcal_report import selfcal_report_html
from markcal.stages.selfcal import site_xy_mm

__all__ = ["write_selfcal_outputs"]


def write_selfcal_outputs(result, out_dir, report: bool = True) -> dict:
    """Write the tables, ``report.html`` and (last) ``summary.json``; return name -> path."""
    out = OutputFolder(out_dir)
    setup, sol = result.setup, result.solution
    M = setup.half
    m, n = np.meshgrid(np.arange(-M, M + 1), np.arange(-M, M + 1), indexing="ij")
    x, y = site_xy_mm(setup, m, n)
    out.csv("stage_error.csv", {"m": m.ravel(), "n": n.ravel(), "x_mm": x.ravel(), "y_mm": y.ravel(),
                                "gx_um": sol.gx_um.ravel(), "gy_um": sol.gy_um.ravel()})
    if sol.gtheta_deg.size:
        k = np.arange(sol.gtheta_deg.size)
        out.csv("stage_error_theta.csv",
                {"k": k, "theta_deg": k * 360.0 / sol.gtheta_deg.size, "gtheta_deg": sol.gtheta_deg})
    out.csv("correction_grid.csv",
            {"x_mm": x.ravel(), "y_mm": y.ravel(), "dx_um": sol.gx_um.ravel(), "dy_um": sol.gy_um.ravel()})
    if report:
        out.text("report.html", selfcal_report_html(result))
    return out.finish(result.summary)
