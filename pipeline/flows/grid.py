"""The grid flow: a hand-measured galvo grid -> deviations, correction model over the lens field, tables.

Reads commanded vs measured mark positions (``stages/grid_input``), registers
the measured frame to the commanded one by rotation and translation (a
reflection when the plate was measured from the back), fits the physical galvo
model of paper 004 sec. 2.3 plus a smoothing thin-plate spline (or a spline
alone, or a cubic; ``auto`` picks the lowest k-fold CV error) and samples the
correction on a grid over the whole lens field.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor, csv_header, file_ext
from markcal.stages.deviation import deviation_stats, grid_nodes
from markcal.stages.errors import MarkcalError
from markcal.stages.galvo_fit import (KINDS, PARAM_NAMES, ModelChoice, choose_model, fit_physical,
                                      hull_distance_mm, nominal_geometry, rms_mm)
from markcal.stages.grid_input import MeasuredGrid, read_grid
from markcal.stages.register import Rigid2D, rigid_or_mirrored_fit

#: fraction of the pitch a mark may miss the fitted model by before its numbering is called wrong
MAX_RESIDUAL_PITCH = 1.0 / 3.0


#: the most correction nodes over the lens field (``--grid-step-mm`` floor)
MAX_NODES = 1_000_000


@dataclass(frozen=True)
class GridOptions:
    """Settings of the grid flow. Lengths mm; None: derived from the input."""

    model: str = "physical+rbf"
    units_per_mm: float | None = None
    centre_units: float = 32768.0
    lens_mm: float | None = None
    d_mm: float | None = None
    e_mm: float | None = None
    grid_step_mm: float | None = None
    folds: int = 5
    seed: int = 0

    def __post_init__(self):
        if self.model != "auto" and self.model not in KINDS:
            raise MarkcalError(f"unknown model {self.model!r} (known: {', '.join(KINDS)}, auto)")
        if self.folds < 2:
            raise MarkcalError(f"--folds must be at least 2 (got {self.folds})")
        if not np.isfinite(self.centre_units):
            raise MarkcalError(f"--centre-units must be finite (got {self.centre_units})")
        for k in ("units_per_mm", "lens_mm", "d_mm", "grid_step_mm"):
            v = getattr(self, k)
            if v is not None and not 0 < v <= 1e6:
                raise MarkcalError(f"--{k.replace('_', '-')} must be positive and at most 1e6 (got {v})")
        if self.e_mm is not None and not 0 <= self.e_mm <= 1e6:
            raise MarkcalError(f"--e-mm must be >= 0 and at most 1e6 (got {self.e_mm})")


@dataclass(frozen=True)
class GridResult:
    """Everything the grid flow found; ``reports`` turns it into files.

    ``fiducials`` maps column -> array, one entry per measured mark; ``x_meas_mm``
    etc. are in the controller frame after registration. ``grid_xy_mm`` (n, 2)
    are the correction nodes over the lens field, ``grid_dxy_mm`` their command
    offsets, ``grid_hull_mm`` how far each lies outside the marks' convex hull.
    """

    source: str
    options: GridOptions
    grid: MeasuredGrid
    fiducials: dict
    registration: Rigid2D
    choice: ModelChoice
    pitch_mm: float
    lens_mm: float
    d_mm: float
    e_mm: float
    grid_xy_mm: np.ndarray
    grid_dxy_mm: np.ndarray
    grid_hull_mm: np.ndarray
    summary: dict

    @property
    def model(self):
        return self.choice.model

    @property
    def extrapolated(self) -> np.ndarray:
        """Nodes more than one pitch outside the measured hull."""
        return self.grid_hull_mm > self.pitch_mm


def _row_col(grid: MeasuredGrid) -> tuple:
    """Row and column of each mark: the file's, or ranks of the commanded y and x on a regular lattice."""
    if np.all(grid.row >= 0) and np.all(grid.col >= 0):
        return grid.row, grid.col
    out = []
    for v in (grid.cmd_mm[:, 1], grid.cmd_mm[:, 0]):
        u = np.unique(np.round(v, 3))
        step = np.min(np.diff(u)) if len(u) > 1 else 1.0
        out.append(np.rint((v - u[0]) / step).astype(int))
    return out[0], out[1]


def run_grid(path, options: GridOptions | None = None, progress=None) -> GridResult:
    """Run the grid flow on one measured grid file.

    Raises
    ------
    MarkcalError
        Bad input; the message names the file.
    """
    opt = options or GridOptions()
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    say("reading the measured grid")
    grid = read_grid(path, opt.units_per_mm, opt.centre_units)
    try:
        from threadpoolctl import threadpool_limits
        with threadpool_limits(1):          # small matrices: one BLAS thread is fastest and never oversubscribes
            return _run(grid, str(path), opt, say, t0)
    except MarkcalError as exc:
        raise exc.with_path(path) from None


def _run(grid: MeasuredGrid, source: str, opt: GridOptions, say, t0) -> GridResult:
    folds = min(opt.folds, len(grid.cmd_mm) // 2)       # a small grid: fewer folds, at least two marks in each
    cmd = grid.cmd_mm
    dist, _ = cKDTree(cmd).query(cmd, k=2)
    pitch = float(np.median(dist[:, 1]))
    span = float(np.max(cmd.max(axis=0) - cmd.min(axis=0)))
    if opt.lens_mm is not None:
        lens = float(opt.lens_mm)
    elif grid.units_per_mm:
        lens = 65536.0 / grid.units_per_mm
    else:
        lens = span + 2 * pitch
    d0, e0 = nominal_geometry(lens)
    d0 = d0 if opt.d_mm is None else float(opt.d_mm)
    e0 = e0 if opt.e_mm is None else float(opt.e_mm)

    say("registering the measured frame to the commanded one")
    tf, rms_proper, rms_mirror = rigid_or_mirrored_fit(grid.meas_mm, cmd)
    land = tf.apply(grid.meas_mm)
    phys = fit_physical(cmd, land, d0, e0)
    res = np.hypot(*(land - phys.land(cmd)).T)
    worst = int(np.argmax(res))
    if res[worst] > MAX_RESIDUAL_PITCH * pitch:
        raise MarkcalError(
            f"line {grid.line[worst]}: the mark commanded at ({cmd[worst, 0]:g}, {cmd[worst, 1]:g}) mm lies "
            f"{res[worst]:.2f} mm from where the fitted galvo puts it, more than a third of the pitch "
            f"({pitch:.2f} mm): wrong row/column numbering or a swapped measurement?")

    say(f"fitting and cross-validating {', '.join(KINDS)} ({folds}-fold)")
    choice = choose_model(opt.model, cmd, land, d0, e0, folds, opt.seed)
    model = choice.model
    fitted = model.land(cmd)

    say("correction over the lens field")
    step = opt.grid_step_mm if opt.grid_step_mm else lens / 50.0
    if (lens / step + 1) ** 2 > MAX_NODES:
        raise MarkcalError(f"--grid-step-mm {step:g} gives {(lens / step + 1) ** 2:.3g} correction nodes over the "
                           f"{lens:g} mm lens field; at most {MAX_NODES:,} (a coarser step)")
    nodes = grid_nodes(lens / 2, lens / 2, step)
    dxy = model(nodes)
    hull = hull_distance_mm(nodes, cmd)

    row, col = _row_col(grid)
    delta = cmd - land
    cv_err = choice.cv_errors_mm[model.kind]
    fid = {"id": np.arange(len(cmd)), "row": row, "col": col, "line": grid.line,
           "x_nom_mm": cmd[:, 0], "y_nom_mm": cmd[:, 1], "x_meas_mm": land[:, 0], "y_meas_mm": land[:, 1],
           "dx_mm": delta[:, 0], "dy_mm": delta[:, 1],
           "x_input_mm": grid.meas_mm[:, 0], "y_input_mm": grid.meas_mm[:, 1],
           "fit_dx_mm": fitted[:, 0] - land[:, 0], "fit_dy_mm": fitted[:, 1] - land[:, 1],
           "cv_dx_mm": cv_err[:, 0], "cv_dy_mm": cv_err[:, 1]}
    full = deviation_stats(cmd, delta)
    extrap = hull > pitch
    summary = {
        "source": source, "kind": "calibration", "layout": grid.layout,
        "n_marks": int(len(cmd)), "n_unmeasured": grid.n_unmeasured,
        "pitch_mm": pitch, "lens_mm": lens, "d_mm": d0, "e_mm": e0,
        "units_per_mm": grid.units_per_mm,
        "mirrored": tf.reflection, "rotation_deg": tf.angle_deg,
        "registration_rms_mm": min(rms_proper, rms_mirror) if tf.reflection else rms_proper,
        "registration_rms_proper_mm": rms_proper, "registration_rms_mirrored_mm": rms_mirror,
        "rms_mm": full["rms_mm"], "max_mm": full["max_mm"], "rms_x_mm": full["rms_x_mm"],
        "rms_y_mm": full["rms_y_mm"], "max_x_mm": full["max_x_mm"], "max_y_mm": full["max_y_mm"],
        "model_requested": opt.model, "model": model.kind, "folds": folds,
        "cv_rmse_mm": choice.cv_rmse_mm[model.kind],
        **{f"cv_rmse_{k.replace('+', '_')}_mm": v for k, v in choice.cv_rmse_mm.items()},
        "fit_rms_mm": rms_mm(fitted - land),
        "physical_fit_rms_mm": rms_mm(phys.land(cmd) - land),
        "grid_step_mm": step, "n_nodes": int(len(nodes)), "n_extrapolated": int(extrap.sum()),
        "max_correction_mm": float(np.max(np.hypot(*dxy.T))),
        "max_correction_measured_area_mm": float(np.max(np.hypot(*dxy[hull <= 0].T))) if np.any(hull <= 0) else None,
        **({f"physical_{k}": float(v) for k, v in zip(PARAM_NAMES, model.physical.params)}
           if model.physical is not None else {}),
        "runtime_s": time.perf_counter() - t0,
    }
    return GridResult(source=source, options=opt, grid=grid, fiducials=fid, registration=tf, choice=choice,
                      pitch_mm=pitch, lens_mm=lens, d_mm=d0, e_mm=e0, grid_xy_mm=nodes, grid_dxy_mm=dxy,
                      grid_hull_mm=hull, summary=summary)


def _claims(path) -> bool:
    e = file_ext(path)
    if e == ".csv":
        h = csv_header(path)
        return ("x_cmd_mm" in h or "x_cmd_units" in h) and "x_meas_mm" in h
    if e != ".txt":
        return False
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            first = next((s for s in (line.split() for line in fh) if s and not s[0].startswith("#")), [])
    except OSError:
        return False
    if len(first) != 6 or not all(re.fullmatch(r"[0-9A-Fa-f]{4}", v) for v in first[4:]):
        return False
    try:
        [float(v) for v in first[:2]] + [int(v) for v in first[2:4]]    # measured x, y (mm); i, j (whole)
    except ValueError:
        return False
    return True


def grid_options(o: dict) -> GridOptions:
    """:class:`GridOptions` from the descriptor's option dict (0 means "from the input")."""
    def given(k):
        return o[k] if o[k] else None
    return GridOptions(model=o["model"], units_per_mm=given("units_per_mm"), centre_units=o["centre_units"],
                       lens_mm=given("lens_mm"), d_mm=given("d_mm"), e_mm=given("e_mm"),
                       grid_step_mm=given("grid_step_mm"), folds=int(o["folds"]), seed=int(o["seed"]))


FLOW = FlowDescriptor(
    name="grid", help="hand-measured galvo grid -> physical model, correction over the lens field, report",
    claims=_claims,
    run=lambda path, spec, options, progress=None: run_grid(path, grid_options(options), progress=progress),
    validate_options=grid_options,
    options={"model": "physical+rbf", "units_per_mm": 0.0, "centre_units": 32768.0, "lens_mm": 0.0, "d_mm": 0.0,
             "e_mm": 0.0, "grid_step_mm": 0.0, "folds": 5, "seed": 0, "no_report": False},
    key_figures=(Figure("n_marks", "marks"), Figure("rms_mm", "grid deviation RMS", "mm"),
                 Figure("max_mm", "deviation max", "mm"), Figure("model", "model"),
                 Figure("n_extrapolated", "nodes extrapolated")),
    trends=("rms_mm",), cost=1.0)
