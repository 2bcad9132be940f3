"""Files of the grid flow: the scan flow's tables, model.json, summary.json, report.html.

The folder has the layout ``markcal export`` reads from a scan flow folder
(``fiducials.csv`` with nominal and measured positions, ``model.json``,
``summary.json``) and, for ``export a3200``, the selfcal flow's ``stage_error.csv``
(the command offset over the lens field, µm); ``model.json`` holds a grid model (``markcal-grid-model-1``)
with the region where it is valid (the whole lens field).
"""
from __future__ import annotations

import numpy as np

from markcal.reports.files import OutputFolder
from markcal.reports.scan_outputs import deviations_table

FIDUCIAL_COLUMNS = ("id", "row", "col", "line", "x_nom_mm", "y_nom_mm", "x_meas_mm", "y_meas_mm", "dx_mm", "dy_mm",
                    "x_input_mm", "y_input_mm", "fit_dx_mm", "fit_dy_mm", "cv_dx_mm", "cv_dy_mm")


def model_document(result) -> dict:
    """The content of model.json."""
    half = result.lens_mm / 2
    return {
        "description": "Galvo correction fitted to a hand-measured grid. The model maps a command (mm, controller "
                       "frame) to where it lands; the command offset for a wanted position (x, y) is the "
                       "command that lands there minus (x, y). Load with markcal.stages.galvo_fit.GridModel.from_dict.",
        "input": "wanted position (x_mm, y_mm), controller frame",
        "model": result.model.to_dict(),
        "valid_region_mm": [-half, half, -half, half],
        "selection": {"requested": result.options.model, "chosen": result.model.kind,
                      "folds": result.options.folds, "seed": result.options.seed,
                      "cv_rmse_mm": result.choice.cv_rmse_mm},
        "galvo": {"d_mm": result.d_mm, "e_mm": result.e_mm},
    }


def write_grid_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of a grid flow result into ``out_dir``; summary.json last.

    Returns
    -------
    dict
        Output name -> path.
    """
    out = OutputFolder(out_dir)
    f = result.fiducials
    out.csv("fiducials.csv", {k: f[k] for k in FIDUCIAL_COLUMNS})
    out.csv("deviations.csv", deviations_table(f))
    xy, dxy = result.grid_xy_mm, result.grid_dxy_mm
    out.csv("correction_grid.csv", {"x_mm": xy[:, 0], "y_mm": xy[:, 1], "dx_mm": dxy[:, 0], "dy_mm": dxy[:, 1],
                                    "outside_hull_mm": result.grid_hull_mm,
                                    "extrapolated": result.extrapolated.astype(int)})
    # the selfcal flow's layout (command x + G to reach x, µm) so that `markcal export a3200` reads the galvo too
    xs, ys = np.unique(xy[:, 0]), np.unique(xy[:, 1])
    out.csv("stage_error.csv", {"m": np.searchsorted(ys, xy[:, 1]), "n": np.searchsorted(xs, xy[:, 0]),
                                "x_mm": xy[:, 0], "y_mm": xy[:, 1],
                                "gx_um": 1e3 * dxy[:, 0], "gy_um": 1e3 * dxy[:, 1]})
    out.json("model.json", model_document(result))
    if report:
        from markcal.reports.grid_report import grid_report_html      # here: matplotlib loads only for reports
        out.text("report.html", grid_report_html(result))
    return out.finish(result.summary)
