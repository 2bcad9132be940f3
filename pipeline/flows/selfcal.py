"""The selfcal flow: stage error map from an artifact plate measured in four views (paper 001).

Reads ``setup.toml``, ``grid_views.csv`` and (optionally) ``angle_views.csv``
from a session folder, solves the self-calibration and, when a ``truth.json``
from the renderer lies beside them, compares the result with the truth.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

import numpy as np

from markcal.pipeline.config import read_selfcal_setup
from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor
from markcal.pipeline.tables import read_table
from markcal.stages.errors import MarkcalError
from markcal.stages.selfcal import (AngleViews, GridViews, SelfcalSetup, SelfcalSolution, solve_selfcal,
                                    view_site)

__all__ = ["SelfcalResult", "read_session", "run_selfcal", "SESSION_FILES"]

#: the files of a session folder (angle_views.csv and truth.json are optional)
SESSION_FILES = ("setup.toml", "grid_views.csv", "angle_views.csv")


@dataclass(frozen=True)
class SelfcalResult:
    """What the selfcal flow returns.

    ``errors`` holds the truth comparison (paper Tables 1-2: max, min and std
    of E = G - Ĝ) when the session has a ``truth.json``, else None.
    """

    source: str
    setup: SelfcalSetup
    solution: SelfcalSolution
    errors: dict | None
    truth: dict | None
    summary: dict


def read_session(folder) -> tuple:
    """Read a session folder; return ``(setup, grid, angle_or_None, truth_or_None)``."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise MarkcalError("not a session folder (expected setup.toml, grid_views.csv, angle_views.csv)", folder)
    setup = read_selfcal_setup(os.path.join(folder, "setup.toml"))
    M = setup.half
    gpath = os.path.join(folder, "grid_views.csv")
    g = read_table(gpath, ("view", "m", "n", "vx_um", "vy_um"), int_columns=("view", "m", "n"),
                   key=("view", "m", "n"))
    bad = np.flatnonzero((np.abs(g["m"]) > M) | (np.abs(g["n"]) > M))
    if len(bad):
        raise MarkcalError(f"line {bad[0] + 2}: mark (m={g['m'][bad[0]]}, n={g['n'][bad[0]]}) is outside "
                           f"the {setup.n} x {setup.n} plate (m, n in -{M}..{M})", gpath)
    bad = np.flatnonzero(~np.isin(g["view"], (0, 1, 3)))
    if len(bad):
        raise MarkcalError(f"line {bad[0] + 2}: view {g['view'][bad[0]]}: grid marks are measured in "
                           "views 0, 1 and 3 only", gpath)
    v3 = g["view"] == 3
    off = np.flatnonzero(v3 & (view_site(3, g["m"], g["n"])[0] > M))
    if len(off):
        raise MarkcalError(f"line {off[0] + 2}: in view 3 mark m={M} sits off the stage field and cannot "
                           "have been measured", gpath)
    not_listed = sorted(set(np.unique(g["view"]).tolist()) - set(setup.views))
    if not_listed:
        raise MarkcalError(f"views {not_listed} are measured but setup.toml lists views {list(setup.views)}", gpath)
    grid = GridViews(view=g["view"], m=g["m"], n=g["n"], vx_um=g["vx_um"], vy_um=g["vy_um"])
    apath = os.path.join(folder, "angle_views.csv")
    angle = None
    if setup.k and os.path.exists(apath):
        a = read_table(apath, ("view", "k", "vtheta_deg"), int_columns=("view", "k"), key=("view", "k"))
        bad = np.flatnonzero((a["k"] < 0) | (a["k"] >= setup.k))
        if len(bad):
            raise MarkcalError(f"line {bad[0] + 2}: k = {a['k'][bad[0]]} is outside 0..{setup.k - 1}", apath)
        bad = np.flatnonzero(~np.isin(a["view"], (0, 1, 2, 3)))
        if len(bad):
            raise MarkcalError(f"line {bad[0] + 2}: view {a['view'][bad[0]]} is not one of 0, 1, 2, 3", apath)
        angle = AngleViews(view=a["view"], k=a["k"], vtheta_deg=a["vtheta_deg"])
    elif setup.k:
        raise MarkcalError(f"setup.toml has k = {setup.k} angular lines but there is no angle_views.csv "
                           "(set k = 0 for an XY-only session)", folder)
    truth = None
    tpath = os.path.join(folder, "truth.json")
    if os.path.exists(tpath):
        try:
            with open(tpath, encoding="utf-8") as fh:
                truth = json.load(fh)
        except (OSError, ValueError) as exc:
            raise MarkcalError(f"cannot read truth ({exc})", tpath) from None
    return setup, grid, angle, truth


def _stats(e: np.ndarray) -> dict:
    return {"max": float(np.max(e)), "min": float(np.min(e)), "std": float(np.std(e, ddof=1))}


def compare_with_truth(setup: SelfcalSetup, sol: SelfcalSolution, truth: dict) -> dict:
    """Paper Tables 1-2: max, min and std of E = G - Ĝ (µm, deg), plus O and R errors."""
    N = setup.n
    if truth.get("n") != N:
        raise MarkcalError(f"truth.json is for n = {truth.get('n')}, the setup has n = {N}")
    out = {"gx_um": _stats(np.asarray(truth["gx_um"]).reshape(N, N) - sol.gx_um),
           "gy_um": _stats(np.asarray(truth["gy_um"]).reshape(N, N) - sol.gy_um)}
    if sol.gtheta_deg.size and "gtheta_deg" in truth:
        out["gtheta_deg"] = _stats(np.asarray(truth["gtheta_deg"]) - sol.gtheta_deg)
    out["nonorthogonality_urad"] = float(truth["nonorthogonality_urad"] - sol.nonorthogonality_urad)
    out["scale_difference_ppm"] = float(truth["scale_difference_ppm"] - sol.scale_difference_ppm)
    return out


def run_selfcal(folder, progress=None) -> SelfcalResult:
    """Run the selfcal flow on a session folder.

    Parameters
    ----------
    folder : str or os.PathLike
        Folder with ``setup.toml``, ``grid_views.csv`` and ``angle_views.csv``
        (and ``truth.json`` for a rendered session).
    progress : callable, optional
        Called with one-line progress messages.

    Returns
    -------
    SelfcalResult
    """
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    setup, grid, angle, truth = read_session(folder)
    say(f"{len(grid.view)} grid and {0 if angle is None else len(angle.view)} angle readings, "
        f"{setup.n} x {setup.n} sites, K = {setup.k if angle is not None else 0}")
    try:
        sol = solve_selfcal(setup, grid, angle)
    except MarkcalError as exc:
        raise exc.with_path(folder) from None
    for note in sol.notes:
        say(note)
    errors = compare_with_truth(setup, sol, truth) if truth else None
    s = {
        "source": os.path.abspath(folder), "n": setup.n, "pitch_mm": setup.pitch_mm,
        "k": setup.k if angle is not None else 0,
        "nonorthogonality_urad": sol.nonorthogonality_urad, "scale_difference_ppm": sol.scale_difference_ppm,
        **sol.misalignment,
        "residual_rms_xy_um": sol.residual_rms_xy_um, "residual_rms_theta_deg": sol.residual_rms_theta_deg,
        "sigma_xy_um": sol.sigma_xy_um, "sigma_theta_deg": sol.sigma_theta_deg,
        "predicted_sd_gxy_um": float(np.sqrt(np.mean(np.r_[sol.predicted_sd_gx_um.ravel() ** 2,
                                                           sol.predicted_sd_gy_um.ravel() ** 2]))),
        "predicted_sd_gtheta_deg": (float(np.sqrt(np.mean(sol.predicted_sd_gtheta_deg ** 2)))
                                    if sol.gtheta_deg.size else None),
        "condition_1norm": sol.condition_1norm,
        "gx_rms_um": float(np.sqrt(np.mean(sol.gx_um ** 2))), "gy_rms_um": float(np.sqrt(np.mean(sol.gy_um ** 2))),
        "gtheta_rms_deg": float(np.sqrt(np.mean(sol.gtheta_deg ** 2))) if sol.gtheta_deg.size else None,
        "n_grid_readings": sol.n_grid_rows // 2, "n_angle_readings": int(0 if angle is None else len(angle.view)),
        "iterations": sol.iterations, "notes": "; ".join(sol.notes),
    }
    if errors:
        s["error_sd_gx_um"] = errors["gx_um"]["std"]
        s["error_sd_gy_um"] = errors["gy_um"]["std"]
        s["error_sd_gtheta_deg"] = errors.get("gtheta_deg", {}).get("std")
    s["runtime_s"] = time.perf_counter() - t0
    return SelfcalResult(source=os.path.abspath(folder), setup=setup, solution=sol, errors=errors,
                         truth=truth, summary=s)


def _claims(path) -> bool:
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, "setup.toml")) and (
        os.path.isfile(os.path.join(path, "grid_views.csv")) or os.path.isfile(os.path.join(path, "angle_views.csv")))


FLOW = FlowDescriptor(
    name="selfcal", help="XYθz stage self-calibration from an artifact plate measured in several views",
    claims=_claims, folder=True,
    run=lambda path, spec, options, progress=None: run_selfcal(path, progress=progress),
    options={"no_report": False},
    key_figures=(Figure("n", "sites per side"), Figure("gx_rms_um", "stage error RMS Gx", "µm"),
                 Figure("gy_rms_um", "stage error RMS Gy", "µm"),
                 Figure("predicted_sd_gxy_um", "predicted SD of Gx, Gy", "µm"),
                 Figure("nonorthogonality_urad", "non-orthogonality", "µrad"),
                 Figure("scale_difference_ppm", "scale difference", "ppm"),
                 Figure("residual_rms_xy_um", "residual RMS", "µm")),
    tolerances={"max_residual_rms_xy_um": 0.1},
    trends=("gx_rms_um",))
