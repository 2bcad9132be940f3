"""Files of the indents flow: indents.csv, sizes.csv, report.html, summary.json (last)."""
from __future__ import annotations

import os

from .files import atomic_write_text, start_outputs, write_csv, write_json

#: indents.csv: the issue's columns first, then file, kind, nominal and fit quality
INDENT_COLUMNS = ("id", "row", "col", "x_um", "y_um", "dx_um", "dy_um", "diameter_um", "diag1_um", "diag2_um",
                  "depth_nm", "hd_ratio", "orientation_deg", "pileup_nm",
                  "d_um", "area_um2", "apex_depth_nm", "hv", "pileup_volume_um3", "edge_bow", "cut_by_border",
                  "file", "kind", "nominal_um", "in_tolerance", "fit_rms", "n_pixels")
SIZE_COLUMNS = ("nominal_um", "n", "mean_diameter_um", "sd_diameter_um", "max_abs_error_um", "mean_hd", "sd_hd",
                "mean_depth_nm")


def write_indent_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of an indents result into ``out_dir``; summary.json last.

    Row and column are left empty without an array spec (and for imprints off the grid).

    Returns
    -------
    dict
        Output name -> path.
    """
    start_outputs(out_dir)
    p = {n: os.path.join(out_dir, n) for n in ("indents.csv", "sizes.csv", "report.html", "summary.json")}
    t = result.indents
    cols = {k: t[k] for k in INDENT_COLUMNS}
    for k in ("row", "col"):
        cols[k] = [("" if v < 0 else int(v)) for v in t[k]]
    write_csv(p["indents.csv"], cols)
    write_csv(p["sizes.csv"], {k: result.sizes[k] for k in SIZE_COLUMNS})
    if report:
        from .indent_report import render_indent_report_html
        atomic_write_text(p["report.html"], render_indent_report_html(result))
    else:
        p.pop("report.html")
    write_json(p["summary.json"], result.summary)
    return p
