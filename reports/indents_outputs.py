"""Files of the indents flow: indents.csv, sizes.csv, report.html, summary.json (last)."""
from __future__ import annotations

from markcal.reports.files import OutputFolder
from markcal.reports.indents_report import indents_report_html

#: indents.csv: the issue's columns first, then file, kind, nominal and fit quality
INDENT_COLUMNS = ("id", "row", "col", "x_um", "y_um", "dx_um", "dy_um", "diameter_um", "diag1_um", "diag2_um",
                  "depth_nm", "hd_ratio", "orientation_deg", "pileup_nm",
                  "d_um", "area_um2", "apex_depth_nm", "hv", "pileup_volume_um3", "edge_bow", "cut_by_border",
                  "chipped_area_um2", "diagonal_difference_pct",
                  "file", "kind", "nominal_um", "in_tolerance", "fit_rms", "n_pixels")
SIZE_COLUMNS = ("nominal_um", "n", "mean_diameter_um", "sd_diameter_um", "max_abs_error_um", "mean_hd", "sd_hd",
                "mean_depth_nm")


def write_indents_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of an indents result into ``out_dir``; summary.json last.

    Row and column are left empty without an array spec (and for imprints off the grid).

    Returns
    -------
    dict
        Output name -> path.
    """
    out = OutputFolder(out_dir)
    t = result.indents
    cols = {k: t[k] for k in INDENT_COLUMNS}
    for k in ("row", "col"):
        cols[k] = [("" if v < 0 else int(v)) for v in t[k]]
    out.csv("indents.csv", cols)
    out.csv("sizes.csv", {k: result.sizes[k] for k in SIZE_COLUMNS})
    if report:
        out.text("report.html", indents_report_html(result))
    return out.finish(result.summary)
