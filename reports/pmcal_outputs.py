"""Files of the pmcal and drift flows (summary.json always last).

pmcal: calibration.json, methods.csv, residuals.csv, ga_convergence.csv, report.html, summary.json.
drift: compensation.csv, drift_methods.csv, report.html, summary.json.
"""
from __future__ import annotations

import os

import numpy as np

from markcal.pipeline.flows.drift import DriftResult
from markcal.pipeline.flows.pmcal import COMPARED, PmcalResult
from markcal.reports.files import atomic_write_text, start_outputs, write_csv, write_json
from markcal.stages.pm_fit import TOLERANCES_UM, WEIGHTS
from markcal.stages.pm_model import model_to_dict

__all__ = ["calibration_dict", "methods_table", "residuals_table", "write_pmcal_outputs", "write_drift_outputs",
           "COMPENSATION_COLUMNS"]

#: compensation.csv columns
COMPENSATION_COLUMNS = ("t_min", "cx_um", "cy_um", "cz_um")


def calibration_dict(result: PmcalResult) -> dict:
    """calibration.json: every parameter with its unit in the key, the E terms and F, method and seed."""
    f = result.chosen
    d = {"method": result.method, "seed": result.seed, "units": "lengths µm, angles µrad, scale ppm"}
    d.update(model_to_dict(f.model))
    d.update({"E_ortho": f.terms["ortho"], "E_pose": f.terms["pose"], "E_flat": f.terms["flat"],
              "E_dyn": f.terms["dyn"], "F": f.terms["F"], "weights": dict(WEIGHTS),
              "tolerances_um": dict(TOLERANCES_UM)})
    return d


def methods_table(result: PmcalResult) -> dict:
    """methods.csv: one row per method: F, E terms, the main parameters and (with truth) their errors."""
    rows = []
    for name, f in result.fits.items():
        p = model_to_dict(f.model)
        r = {"method": name, "F": f.terms["F"], "E_ortho": f.terms["ortho"], "E_pose": f.terms["pose"],
             "E_flat": f.terms["flat"], "E_dyn": f.terms["dyn"]}
        for k, _ in COMPARED:
            r[k] = p[k]
        for i, a in enumerate("xyz"):
            r[f"rot_{a}_urad"] = p["rotvec_urad"][i]
        if f.truth_errors:
            r.update(f.truth_errors)
        rows.append(r)
    keys = list(rows[0])
    return {k: [r.get(k) for r in rows] for k in keys}


def residuals_table(result: PmcalResult) -> dict:
    """residuals.csv (chosen method): source (axes/pose/probe), row (0-based in its file), rx_um, ry_um, rz_um.

    Probe residuals are vertical (rz only; rx, ry are 0). Residual = measured − model.
    """
    ra, rp, rf = result.chosen.residuals
    src = ["axes"] * len(ra) + ["pose"] * len(rp) + ["probe"] * len(rf)
    row = list(range(len(ra))) + list(range(len(rp))) + list(range(len(rf)))
    r = np.vstack([ra, rp, np.column_stack([np.zeros(len(rf)), np.zeros(len(rf)), -rf])])
    return {"source": src, "row": row, "rx_um": r[:, 0], "ry_um": r[:, 1], "rz_um": r[:, 2]}


def write_pmcal_outputs(result: PmcalResult, out_dir, report: bool = True) -> dict:
    """Write all pmcal outputs atomically; ``summary.json`` last. Returns name -> path."""
    start_outputs(out_dir)
    paths = {}

    def put(name, writer, obj):
        p = os.path.join(out_dir, name)
        writer(p, obj)
        paths[name] = p
    put("calibration.json", write_json, calibration_dict(result))
    put("methods.csv", write_csv, methods_table(result))
    put("residuals.csv", write_csv, residuals_table(result))
    put("ga_convergence.csv", write_csv, {"generation": np.arange(1, len(result.ga_best_f) + 1),
                                          "best_F": result.ga_best_f, "mean_F": result.ga_mean_f})
    if report:
        from markcal.reports.pmcal_report import pmcal_report_html
        put("report.html", atomic_write_text, pmcal_report_html(result))
    put("summary.json", write_json, result.summary)
    return paths


def write_drift_outputs(result: DriftResult, out_dir, report: bool = True) -> dict:
    """Write compensation.csv (chosen method), drift_methods.csv, report.html, summary.json (last)."""
    start_outputs(out_dir)
    paths = {}
    c = result.comp_um[result.method]
    p = os.path.join(out_dir, "compensation.csv")
    write_csv(p, {"t_min": result.t_min, "cx_um": c[:, 0], "cy_um": c[:, 1], "cz_um": c[:, 2]})
    paths["compensation.csv"] = p
    rows = {"method": [], "axis": [], "pre_samples_um": [], "post_samples_um": [], "eta_samples_pct": [],
            "pre_true_um": [], "post_true_um": [], "eta_true_pct": []}
    for name, e in result.eta.items():
        for ax, a in enumerate("xyz"):
            rows["method"].append(name)
            rows["axis"].append(a)
            for k in list(rows)[2:]:
                rows[k].append(float(e[k][ax]) if k in e else None)
    p = os.path.join(out_dir, "drift_methods.csv")
    write_csv(p, rows)
    paths["drift_methods.csv"] = p
    if report:
        from markcal.reports.drift_report import drift_report_html
        p = os.path.join(out_dir, "report.html")
        atomic_write_text(p, drift_report_html(result))
        paths["report.html"] = p
    p = os.path.join(out_dir, "summary.json")
    write_json(p, result.summary)
    paths["summary.json"] = p
    return paths
