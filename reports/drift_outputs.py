"""Files of the drift flow: compensation.csv, drift_methods.csv, report.html, summary.json (last)."""
from __future__ import annotations

from markcal.pipeline.flows.drift import DriftResult
from markcal.reports.drift_report import drift_report_html
from markcal.reports.files import OutputFolder

__all__ = ["write_drift_outputs", "COMPENSATION_COLUMNS"]

#: compensation.csv columns
COMPENSATION_COLUMNS = ("t_min", "cx_um", "cy_um", "cz_um")


def write_drift_outputs(result: DriftResult, out_dir, report: bool = True) -> dict:
    """Write compensation.csv (chosen method), drift_methods.csv, report.html, summary.json (last)."""
    out = OutputFolder(out_dir)
    c = result.comp_um[result.method]
    out.csv("compensation.csv", {"t_min": result.t_min, "cx_um": c[:, 0], "cy_um": c[:, 1], "cz_um": c[:, 2]})
    rows = {"method": [], "axis": [], "pre_samples_um": [], "post_samples_um": [], "eta_samples_pct": [],
            "pre_true_um": [], "post_true_um": [], "eta_true_pct": []}
    for name, e in result.eta.items():
        for ax, a in enumerate("xyz"):
            rows["method"].append(name)
            rows["axis"].append(a)
            for k in list(rows)[2:]:
                rows[k].append(float(e[k][ax]) if k in e else None)
    out.csv("drift_methods.csv", rows)
    if report:
        out.text("report.html", drift_report_html(result))
    return out.finish(result.summary)
