"""Files of the scan flow: CSV tables, model.json, summary.json, report.html."""
from __future__ import annotations

import numpy as np

from markcal.reports.files import OutputFolder

FIDUCIAL_COLUMNS = ("id", "row", "col", "x_nom_mm", "y_nom_mm", "x_meas_mm", "y_meas_mm", "dx_mm", "dy_mm",
                    "x_scanner_mm", "y_scanner_mm", "z_scanner_mm", "ring_radius_scale", "line_width_mm",
                    "contrast", "fit_rms", "n_samples", "used_in_registration")


def deviations_table(fiducials: dict) -> dict:
    """deviations.csv of a galvo flow (scan, grid): id, nominal position, δ and |δ| (mm)."""
    f = fiducials
    return {"id": f["id"], "x_nom_mm": f["x_nom_mm"], "y_nom_mm": f["y_nom_mm"], "dx_mm": f["dx_mm"],
            "dy_mm": f["dy_mm"], "d_mm": np.hypot(f["dx_mm"], f["dy_mm"])}


def write_scan_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of a scan flow result into ``out_dir``; summary.json last.

    Returns
    -------
    dict
        Output name -> path.
    """
    out = OutputFolder(out_dir)
    if report:                        # the figures are drawn while the tables are written
        from markcal.reports.scan_report import scan_report_later      # here: matplotlib loads only for reports
        report_html = scan_report_later(result)
    f = result.fiducials
    out.csv("fiducials.csv", {k: f[k] for k in FIDUCIAL_COLUMNS})
    out.csv("deviations.csv", deviations_table(f))
    out.csv("correction_grid.csv", {"x_mm": result.grid_xy_mm[:, 0], "y_mm": result.grid_xy_mm[:, 1],
                                    "dx_mm": result.grid_dxy_mm[:, 0], "dy_mm": result.grid_dxy_mm[:, 1]})
    out.csv("corrected_targets.csv", result.targets)
    out.json("model.json", _model_document(result))
    if report:
        out.text("report.html", report_html())
    return out.finish(result.summary)


def _model_document(result) -> dict:
    """model.json: the OLS RBF network, or a ``markcal-grid-model-1`` galvo model (as the grid flow writes)."""
    if result.grid_model is not None:
        f = result.fiducials
        return {
            "description": "Galvo model: command (mm, controller frame) -> landing (mm); the command for a "
                           "wanted position is found by inverting it. Load with markcal.stages.galvo_fit.GridModel.",
            "model": result.grid_model.model.to_dict(),
            "valid_region_mm": [float(np.min(f["x_nom_mm"])), float(np.max(f["x_nom_mm"])),
                                float(np.min(f["y_nom_mm"])), float(np.max(f["y_nom_mm"]))],
            "cv_rmse_mm": result.grid_model.cv_rmse_mm, "folds": result.grid_model.folds,
            "galvo": {"d_mm": result.spec.d_mm, "e_mm": result.spec.e_mm},
        }
    return {
        "description": "Command offset for a wanted position in the GLS frame: the command for a target "
                       "(x, y) is (x + dx, y + dy). Load with markcal.pipeline.tables.read_rbf_model.",
        "input": "wanted position (x_mm, y_mm), GLS frame",
        "model": result.model.to_dict(),
        "selection": {"spread_mm": result.selection.spread_mm, "mse_goal_mm2": result.selection.mse_goal_mm2,
                      "cv_rmse_mm": result.selection.cv_rmse_mm, "folds": result.options.folds},
        "galvo": {"d_mm": result.spec.d_mm, "e_mm": result.spec.e_mm},
    }
