"""The pmcal flow: static calibration of a precision-marking machine (paper 000 §3).

Reads a session folder (``axes.csv``, ``pose.csv`` -- or an ``om/`` folder of OM
micrographs plus ``marks.csv``, measured here with the indents flow's OM model --,
``probe.csv``, optional ``drift.csv``), fits the machine model by the paper's GA, by least squares and
by GA + least squares, and, when a ``truth.json`` from the renderer lies beside
them, compares each with the truth (parameter errors, landing of 100 random
targets on the true machine). Also: ``run_command`` turns OM targets into stage
commands with a calibration.
"""
from __future__ import annotations

import csv
import os
import time
from dataclasses import dataclass

import numpy as np

from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor
from markcal.pipeline.tables import check_increasing, load_json, read_table
from markcal.stages import indent as ind
from markcal.stages.image_io import read_image
from markcal.stages.errors import MarkcalError
from markcal.stages.limits import max_abs_for
from markcal.stages.pm_fit import SessionData, fit_lsq, model_from_theta, residual_parts, terms_from_parts
from markcal.stages.pm_ga import GAOptions, run_ga
from markcal.stages.pm_model import PMModel, command_for_targets, landing_errors, model_from_dict, model_to_dict

__all__ = ["METHODS", "SESSION_FILES", "MARKS_COLUMNS", "PmcalResult", "read_session", "read_om_marks",
           "run_pmcal", "run_command", "read_calibration", "landing_check"]

METHODS = ("ga", "lsq", "ga+lsq")
#: session files; drift.csv is optional (E_dyn is then 0)
SESSION_FILES = ("axes.csv", "pose.csv", "probe.csv", "drift.csv")
#: marks.csv (om/ variant of pose.csv): commanded stage position of each mark (µm), the micrograph
#: in om/ that shows it, the OM-frame position of that image's centre and the OM z (µm)
MARKS_COLUMNS = ("x_pm_um", "y_pm_um", "z_pm_um", "image", "x_field_um", "y_field_um", "z_om_um")
#: an image's mark must measure within this factor of the median diagonal of all marks
MARK_SIZE_FACTOR = 2.0
#: a pose pair whose residual exceeds this after the fit is reported as mismatched (µm)
MISMATCH_UM = 1.0
#: parameters compared with the truth: key, unit
COMPARED = (("scale_x_ppm", "ppm"), ("scale_y_ppm", "ppm"), ("scale_z_ppm", "ppm"),
            ("nonorth_xy_urad", "µrad"), ("nonorth_xz_urad", "µrad"), ("nonorth_yz_urad", "µrad"),
            ("plane_tilt_x_urad", "µrad"), ("plane_tilt_y_urad", "µrad"))


@dataclass(frozen=True)
class MethodFit:
    """One calibration method's outcome."""
    method: str
    theta: np.ndarray
    model: PMModel
    terms: dict
    seconds: float
    residuals: tuple  # axes (N, 3), pose (M, 3), probe (K,) in µm
    truth_errors: dict | None  # parameter errors and landing statistics against truth.json


@dataclass(frozen=True)
class PmcalResult:
    """What the pmcal flow returns: the chosen fit, all three fits, GA convergence, the summary."""
    source: str
    method: str
    seed: int
    data: SessionData
    fits: dict
    ga_best_f: np.ndarray
    ga_mean_f: np.ndarray
    warnings: list
    truth: dict | None
    summary: dict

    @property
    def chosen(self) -> MethodFit:
        return self.fits[self.method]


def _xyz(t, names):
    return np.column_stack([t[n] for n in names])


def _check_not_collinear(xy: np.ndarray, what: str, path) -> None:
    if len(xy) < 3:
        raise MarkcalError(f"{len(xy)} {what}: need at least 3 non-collinear points", path)
    s = np.linalg.svd(xy - xy.mean(0), compute_uv=False)
    if s[1] <= 1e-6 * max(s[0], 1e-12):
        raise MarkcalError(f"the {what} are collinear (x, y on one line): a plane needs 3 non-collinear points", path)


def read_session(folder) -> tuple:
    """Read and check a session folder.

    Returns
    -------
    SessionData, list of str, (str, ndarray)
        The data, the warnings, and the pose pairs' file (pose.csv or marks.csv) with the line of
        each pair in it.
    """
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise MarkcalError("no such session folder", folder)
    om_variant = (not os.path.isfile(os.path.join(folder, "pose.csv"))
                  and os.path.isdir(os.path.join(folder, "om")))
    for name in SESSION_FILES[:3]:
        if name == "pose.csv" and om_variant:
            if not os.path.isfile(os.path.join(folder, "marks.csv")):
                raise MarkcalError("an om/ image folder needs marks.csv beside it (columns "
                                   f"{','.join(MARKS_COLUMNS)}), or give pose.csv", os.path.join(folder, "marks.csv"))
            continue
        if not os.path.isfile(os.path.join(folder, name)):
            raise MarkcalError(f"missing {name} (a session holds {', '.join(SESSION_FILES[:3])}; drift.csv optional)",
                               os.path.join(folder, name))
    warnings = []
    p = os.path.join(folder, "axes.csv")
    t = read_table(p, ("cx_um", "cy_um", "cz_um", "px_um", "py_um", "pz_um"))
    c_ax, p_ax = _xyz(t, ("cx_um", "cy_um", "cz_um")), _xyz(t, ("px_um", "py_um", "pz_um"))
    for j in range(3):
        if len(np.unique(c_ax[:, j])) < 3:
            raise MarkcalError(f"axis {'xyz'[j]} takes fewer than 3 distinct commanded positions: "
                               "cannot fit its scale and straightness", p)
    if om_variant:
        p = os.path.join(folder, "marks.csv")
        c_pose, x_om, lines, om_warn = read_om_marks(folder)
        warnings.extend(om_warn)
    else:
        p = os.path.join(folder, "pose.csv")
        t = read_table(p, ("x_pm_um", "y_pm_um", "z_pm_um", "x_om_um", "y_om_um", "z_om_um"))
        c_pose, x_om = _xyz(t, ("x_pm_um", "y_pm_um", "z_pm_um")), _xyz(t, ("x_om_um", "y_om_um", "z_om_um"))
        lines = np.arange(len(c_pose)) + 2
    pose_path = p
    _check_not_collinear(c_pose[:, :2], "pose marks", p)
    if len(c_pose) < 6:
        warnings.append(f"{os.path.basename(p)}: only {len(c_pose)} mark pairs; the pose is poorly determined below 6")
    p = os.path.join(folder, "probe.csv")
    t = read_table(p, ("x_um", "y_um", "z_um"), key=("x_um", "y_um"))
    c_probe = _xyz(t, ("x_um", "y_um", "z_um"))
    _check_not_collinear(c_probe[:, :2], "probe points", p)
    nx, ny = len(np.unique(c_probe[:, 0])), len(np.unique(c_probe[:, 1]))
    if len(c_probe) < 25 or nx < 5 or ny < 5:
        warnings.append(f"probe.csv: {len(c_probe)} points ({nx} x positions, {ny} y positions), fewer than "
                        "the paper's 5 x 5 grid; the plane is less certain")
    drift = np.zeros((0, 3))
    p = os.path.join(folder, "drift.csv")
    if os.path.isfile(p):
        t = read_table(p, ("t_min", "dx_um", "dy_um", "dz_um"))
        check_increasing(t["t_min"], "t_min", p)
        drift = _xyz(t, ("dx_um", "dy_um", "dz_um"))
    else:
        warnings.append("no drift.csv: E_dyn is 0")
    return SessionData(c_ax, p_ax, c_pose, x_om, c_probe, drift), warnings, (pose_path, lines)


def _image_column(path, n) -> list:
    """The ``image`` column of marks.csv (file names, one per data line)."""
    with open(path, newline="", encoding="utf-8-sig") as fh:
        rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    head = [h.strip() for h in rows[0]]
    if "image" not in head:
        raise MarkcalError(f"missing column 'image' (marks.csv columns: {','.join(MARKS_COLUMNS)})", path)
    j = head.index("image")
    names = [r[j].strip() if j < len(r) else "" for r in rows[1:]]
    if len(names) != n:
        raise MarkcalError(f"{len(names)} image names for {n} data lines", path)
    for i, name in enumerate(names):
        if not name or os.path.basename(name) != name:
            raise MarkcalError(f"line {i + 2}: image must be a file name in om/ (got {name!r})", path)
    return names


def _measure_marks(images: list, pixel_um: float) -> list:
    """Centre of the one mark in each micrograph, µm from the image centre (x right, y down the rows).

    The micrographs are laid side by side (bottom-padded to one height) and measured together
    with :func:`markcal.stages.indent.measure_om_array`, each divided by its own illumination:
    one objective and one material, so the darkness, rim and PSF are shared, as within one
    array micrograph (a lone dot fitted with all twelve parameters on its own is slower and can
    trade size for darkness). Per image the imprint nearest the centre among those whose
    diagonal is within ``MARK_SIZE_FACTOR`` of the median is the mark.

    Returns
    -------
    list of (ndarray (2,) or None, str)
        Offset (µm) or None, and a note (why not found, or how many candidates there were).
    """
    h = max(im.shape[0] for im in images)
    tiles, bgs, cands, sigs, x0 = [], [], [], [], 0
    for i, im in enumerate(images):
        bg = ind.om_background(im, pixel_um)
        c, sig = ind.detect_dots(im, pixel_um, background=bg)
        pad = ((0, h - im.shape[0]), (0, 0))
        tiles.append(np.pad(im, pad, mode="edge"))
        bgs.append(np.pad(bg, pad, mode="edge"))
        cands += [(r, cc + x0, rad, i, x0) for r, cc, rad in c]
        sigs.append(sig)
        x0 += im.shape[1]
    found = [[] for _ in images]
    if cands:
        imps = ind.measure_om_array(np.concatenate(tiles, axis=1), pixel_um, [c[:3] for c in cands],
                                    float(np.median(sigs)), np.concatenate(bgs, axis=1))
        for c, m in zip(cands, imps):
            if m is not None:
                found[c[3]].append((m, c[4]))
    dias = [m.diameter_um for f in found for m, _ in f]
    med = float(np.median(dias)) if dias else 0.0
    out = []
    for im, f in zip(images, found):
        cy, cx = (np.array(im.shape) - 1) / 2 * pixel_um
        ok = [(np.array([m.x_um - x0 * pixel_um - cx, m.y_um - cy]), m) for m, x0 in f
              if med / MARK_SIZE_FACTOR <= m.diameter_um <= med * MARK_SIZE_FACTOR]
        if not ok:
            out.append((None, "no mark found" if not f else f"no mark of the usual size ({med:.2f} µm) found"))
            continue
        ok.sort(key=lambda t: float(np.hypot(*t[0])))
        out.append((ok[0][0], f"{len(ok)} candidates, the nearest the centre taken" if len(ok) > 1 else ""))
    return out


def read_om_marks(folder) -> tuple:
    """The pose pairs of an om/ session: measure each micrograph's mark with the indents OM model.

    ``marks.csv`` gives per mark the commanded stage position (``x_pm_um, y_pm_um, z_pm_um``), the
    micrograph in ``om/`` (``image``), the OM-frame position of the image centre (``x_field_um,
    y_field_um``) and the OM z (``z_om_um``). Image axes: x along the columns = OM +x, y down the
    rows = OM +y. The mark's OM position is the field position plus its offset from the image
    centre. A mark not found drops that pair (reported in the warnings).

    Returns
    -------
    c_pose (n, 3), x_om (n, 3) : ndarray
        Commanded positions and measured OM positions of the kept pairs, µm.
    lines : ndarray of int
        marks.csv line of each kept pair.
    warnings : list of str
    """
    folder = os.fspath(folder)
    p = os.path.join(folder, "marks.csv")
    num = [c for c in MARKS_COLUMNS if c != "image"]
    t = read_table(p, num)
    names = _image_column(p, len(t["x_pm_um"]))
    images, px = [], None
    for i, name in enumerate(names):
        img = read_image(os.path.join(folder, "om", name), None, "om")
        if px is None:
            px = img.pixel_um
        elif abs(img.pixel_um - px) > 1e-6 * px:
            raise MarkcalError(f"pixel size {img.pixel_um:g} µm differs from the first image's {px:g} µm: "
                               "one objective per session", img.source)
        images.append(img.data)
    res = _measure_marks(images, px)
    keep = np.array([o is not None for o, _ in res])
    warnings = [f"marks.csv line {i + 2} ({names[i]}): {note}; pair dropped"
                for i, (o, note) in enumerate(res) if o is None]
    warnings += [f"marks.csv line {i + 2} ({names[i]}): {note}" for i, (o, note) in enumerate(res) if o is not None and note]
    if keep.sum() < 3:
        raise MarkcalError(f"only {int(keep.sum())} of {len(names)} OM images show a measurable mark: "
                           "need at least 3 pose pairs", os.path.join(folder, "om"))
    off = np.array([o for o, _ in res if o is not None])
    c_pose = _xyz(t, ("x_pm_um", "y_pm_um", "z_pm_um"))[keep]
    x_om = np.column_stack([t["x_field_um"][keep] + off[:, 0], t["y_field_um"][keep] + off[:, 1],
                            t["z_om_um"][keep]])
    return c_pose, x_om, np.flatnonzero(keep) + 2, warnings


def landing_check(true_model: PMModel, model: PMModel, n: int = 100, depth_um: float = 0.5, seed: int = 12345,
                  half_um: float = 20000.0) -> dict:
    """Land ``n`` random OM targets (within ±half_um) commanded through ``model`` on ``true_model``."""
    xy = np.random.default_rng(seed).uniform(-half_um, half_um, (n, 2))
    c = command_for_targets(model, xy, depth_um)
    lat, dep = landing_errors(true_model, xy, depth_um, c)
    return {"landing_rms_um": float(np.sqrt(np.mean(lat ** 2))), "landing_max_um": float(lat.max()),
            "depth_err_max_um": float(np.abs(dep).max()), "depth_err_rms_um": float(np.sqrt(np.mean(dep ** 2)))}


def _truth_errors(model: PMModel, truth: dict, true_model: PMModel) -> dict:
    est = model_to_dict(model)
    out = {f"err_{k}": est[k] - truth[k] for k, _ in COMPARED}
    out["err_pose_rot_urad"] = float(np.linalg.norm(np.array(est["rotvec_urad"]) - truth["rotvec_urad"]))
    out.update(landing_check(true_model, model))
    return out


def _read_truth(folder):
    p = os.path.join(folder, "truth.json")
    if not os.path.isfile(p):
        return None, None
    truth = load_json(p, "truth file")
    try:
        return truth, model_from_dict(truth)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MarkcalError(f"cannot read truth ({exc})", p) from None


def check_pmcal_options(options: dict) -> None:
    """Refuse an unknown ``method`` (the flow's options, CLI or batch.toml)."""
    if options["method"] not in METHODS:
        raise MarkcalError(f"unknown method {options['method']!r} (choose from {', '.join(METHODS)})")


def run_pmcal(folder, method: str = "ga+lsq", seed: int = 0, progress=None) -> PmcalResult:
    """Calibrate from a session folder with all three methods; ``method`` is the one returned as chosen."""
    say = progress or (lambda msg: None)
    check_pmcal_options({"method": method})
    folder = os.fspath(folder)
    data, warnings, (pose_path, pose_lines) = read_session(folder)
    truth, true_model = _read_truth(folder)
    fits = {}
    t0 = time.perf_counter()
    ga = run_ga(data, GAOptions(seed=seed))
    t_ga = time.perf_counter() - t0
    say(f"GA: F = {ga.terms['F']:.4f} after {len(ga.best_f)} generations ({t_ga:.2f} s)")
    t0 = time.perf_counter()
    lsq = fit_lsq(data)
    t_lsq = time.perf_counter() - t0
    t0 = time.perf_counter()
    gl = fit_lsq(data, ga.theta)
    t_gl = time.perf_counter() - t0 + t_ga
    for name, th, sec in (("ga", ga.theta, t_ga), ("lsq", lsq.theta, t_lsq), ("ga+lsq", gl.theta, t_gl)):
        model = model_from_theta(th)
        parts = residual_parts(th, data)
        terms = {k: float(v[0]) for k, v in terms_from_parts(*parts, data).items()}
        ra, rp, rf = parts[:3]
        te = _truth_errors(model, truth, true_model) if truth is not None else None
        fits[name] = MethodFit(name, th, model, terms, sec, (ra[0], rp[0], rf[0]), te)
    ch = fits[method]
    rp_norm = np.linalg.norm(ch.residuals[1], axis=1)
    if rp_norm.max() > MISMATCH_UM:
        i = int(np.argmax(rp_norm))
        raise MarkcalError(f"line {pose_lines[i]}: this pose pair does not match the others (residual {rp_norm[i]:.2f} µm "
                           f"after the fit, limit {MISMATCH_UM:g} µm): mismatched PM and OM sides?",
                           pose_path)
    s = {"method": method, "seed": int(seed), "n_axis_points": len(data.c_axes), "n_pose_pairs": len(data.c_pose),
         "pose_source": os.path.basename(pose_path),
         "n_probe_points": len(data.c_probe), "n_drift_samples": len(data.drift_um),
         "n_warnings": len(warnings)}
    for k in ("ortho", "pose", "flat", "dyn", "F"):
        s[f"E_{k}" if k != "F" else "F"] = ch.terms[k]
    s["axes_rms_um"] = float(np.sqrt(np.mean(np.sum(ch.residuals[0] ** 2, 1))))
    s["pose_rms_um"] = float(np.sqrt(np.mean(np.sum(ch.residuals[1] ** 2, 1))))
    s["probe_rms_um"] = float(np.sqrt(np.mean(ch.residuals[2] ** 2)))
    d = model_to_dict(ch.model)
    for k in ("scale_x_ppm", "scale_y_ppm", "scale_z_ppm", "nonorth_xy_urad", "nonorth_xz_urad", "nonorth_yz_urad",
              "plane_a", "plane_b", "plane_c_um", "plane_tilt_x_urad", "plane_tilt_y_urad"):
        s[k] = d[k]
    for name, f in fits.items():
        s[f"F_{name.replace('+', '_')}"] = f.terms["F"]
    if ch.truth_errors:
        for k, v in ch.truth_errors.items():
            s[k] = v
    return PmcalResult(os.path.abspath(folder), method, int(seed), data, fits, ga.best_f, ga.mean_f, warnings,
                       truth, s)


def read_calibration(path) -> tuple:
    """calibration.json -> (PMModel, dict)."""
    d = load_json(path, "calibration file")
    try:
        return model_from_dict(d), d
    except (KeyError, ValueError, TypeError) as exc:
        raise MarkcalError(f"not a pmcal calibration (bad or missing {exc})", path) from None


def check_depth_um(depth_um: float) -> None:
    """Refuse a machining depth that is not finite or beyond the physical limit."""
    if not abs(depth_um) <= max_abs_for("depth_um"):
        raise MarkcalError(f"--depth-um must be a finite number within ±{max_abs_for('depth_um'):g} µm (got {depth_um})")


def run_command(calibration_path, targets_path, depth_um: float, progress=None) -> dict:
    """Targets ``x_um,y_um`` (OM frame, on the workpiece) -> columns of commands.csv.

    The depth is checked first, before ``progress(msg)`` says what is being done.
    """
    check_depth_um(depth_um)
    if progress:
        progress(f"stage commands for {targets_path} from {calibration_path}")
    model, _ = read_calibration(calibration_path)
    t = read_table(targets_path, ("x_um", "y_um"))
    xy = np.column_stack([t["x_um"], t["y_um"]])
    c = command_for_targets(model, xy, depth_um)
    return {"x_um": xy[:, 0], "y_um": xy[:, 1], "x_cmd_um": c[:, 0], "y_cmd_um": c[:, 1], "z_cmd_um": c[:, 2]}


def _claims(path) -> bool:
    return os.path.isdir(path) and sum(os.path.isfile(os.path.join(path, f)) for f in SESSION_FILES[:3]) >= 2


FLOW = FlowDescriptor(
    name="pmcal", help="precision-marking machine calibration (GA, least squares) from a session folder",
    claims=_claims, folder=True,
    run=lambda path, spec, options, progress=None: run_pmcal(path, method=options["method"],
                                                             seed=int(options["seed"]), progress=progress),
    options={"method": "ga+lsq", "seed": 0, "no_report": False}, validate_options=check_pmcal_options,
    key_figures=(Figure("F", "fitness F (eq. 9)"), Figure("axes_rms_um", "axis residual RMS", "µm"),
                 Figure("pose_rms_um", "pmcal pose residual RMS", "µm"),
                 Figure("nonorth_xy_urad", "non-orthogonality xy", "µrad"),
                 Figure("nonorth_xz_urad", "non-orthogonality xz", "µrad"),
                 Figure("nonorth_yz_urad", "non-orthogonality yz", "µrad"),
                 Figure("landing_rms_um", "landing RMS (truth)", "µm")),
    trends=("pose_rms_um",), cost=8.0)
