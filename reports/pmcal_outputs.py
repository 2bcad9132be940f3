"""Files of the pmcal flow: calibration.json, methods.csv, residuals.csv, ga_convergence.csv,
report.html, summary.json (always last)."""
from __future__ import annotations

import numpy as np

from markcal.pipeline.flows.pmcal import COMPARED, PmcalResult
from markcal.reports.files import OutputFolder
from markcal.reports.pmcal_report import pmcal_report_html
from markcal.stages.pm_fit import TOLERANCES_UM, WEIGHTS
from markcal.stages.pm_model import model_to_dict

__all__ = ["calibration_dict", "methods_table", "residuals_table", "write_pmcal_outputs"]


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
    out = OutputFolder(out_dir)
    out.json("calibration.json", calibration_dict(result))
    out.csv("methods.csv", methods_table(result))
    out.csv("residuals.csv", residuals_table(result))
    out.csv("ga_convergence.csv", {"generation": np.arange(1, len(result.ga_best_f) + 1),
                                   "best_F": result.ga_best_f, "mean_F": result.ga_mean_f})
    if report:
        out.text("report.html", pmcal_report_html(result))
    return out.finish(result.summary)
