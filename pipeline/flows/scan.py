"""The scan flow: 3D scan of a galvo-marked plate -> deviations, correction model, tables.

Paper 004 sec. 2.2-2.8: plane fit, projection, detection, 2D -> 3D,
registration, deviation, RBF network, corrected targets, joint commands.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from markcal.pipeline.config import read_plate_spec
from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor, csv_header, file_ext, spec_beside
from markcal.stages import detect, galvo, orientation, rbf
from markcal.stages.deviation import deviation_stats, grid_nodes
from markcal.stages.errors import MarkcalError
from markcal.stages.io import read_cloud
from markcal.stages.plane import Plane, fit_plane, from_plane
from markcal.stages.plate import PURPOSES, PlateSpec, nominal_grid
from markcal.stages.plate_image import (IMAGE_EXTS, MAX_KEYSTONE, MAX_KEYSTONE_SCANNER_DPI, VIEWS,
                                        check_flat_view, check_image_size, coarse_raster, flat_plane,
                                        image_raster, read_plate_image)
from markcal.stages.project import Raster, project
from markcal.stages.galvo_fit import KINDS, choose_model
from markcal.stages.register import Rigid2D, lattice_coords, rigid_fit, robust_rigid_fit

#: spreads tried by the cross-validation, in units of the grid pitch
SPREADS_PER_PITCH = (1.0, 1.5, 2.0, 3.0, 4.5, 6.5, 9.0)
#: MSE goals tried (mm^2); the paper used 5e-4
MSE_GOALS_MM2 = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 5e-4, 1e-3)
#: areas of paper Table 1: name -> half width (None: the full field)
AREAS = {"full": None, "inner_150": 75.0, "inner_50": 25.0}
#: correction models: the paper's OLS RBF network, or the grid flow's galvo models (stages/galvo_fit)
MODELS = ("ols-rbf", *KINDS, "auto")
#: without a hint or an orientation mark: "auto" (the galvo model decides, or the flow refuses)
#: or "upright" (the same as a rotation hint of 0 deg)
ORIENTATIONS = ("auto", "upright")
MIRRORS = ("no", "yes", "auto")
#: coarse scans: raster cells this many point spacings wide (1.2 was measured worse: 270 vs 284 of 294 found)
COARSE_CELL = 1.0
#: rasters coarser than this (mm) add template-match candidates to the Hough ones (0.2 mm spacing: Hough
#: alone found 284 of 294 marks over seeds 5-10, every miss without a candidate near it)
COARSE_TEMPLATE_PX_MM = 0.15
#: default limits of a calibration plate (marked without correction): what the correction will achieve, from
#: paper 004: its network's 5-fold CV RMSE 0.047 mm (sec. 3) and its post-calibration RMS 0.071 mm (Table 1)
CALIBRATION_TOLERANCES = {"max_predicted_residual_rms_mm": 0.071, "max_cv_rmse_mm": 0.047, "max_n_missing": 0}
#: default limits of a validation plate (marked through the correction): paper 004 Table 1, 190 x 190 mm
VALIDATION_TOLERANCES = {"max_rms_mm": 0.071, "max_max_mm": 0.252}
#: clouds whose points are sparser than this many per ring gap are refused: at 0.5 (0.4 mm spacing on the
#: 2.5/2.7 mm ring) the fits are junk and the grid was indexed wrongly; 1.0 (0.2 mm) finds every mark
MIN_GAP_SAMPLES = 0.6


@dataclass(frozen=True)
class ScanOptions:
    """Settings of the scan flow. Lengths mm."""

    pixel_mm: float = 0.1
    median_px: int = 5
    folds: int = 5
    seed: int = 0
    max_neurons: int = 200
    validation: bool = False
    model: str = "ols-rbf"
    rotation_hint_deg: float | None = None
    orientation: str = "auto"        # no hint, no mark: "auto" (galvo model or refusal) or "upright" (hint 0)
    mirror: str = "no"               # the measurement seen from the back: "no", "yes", "auto"
    pixel_size_mm: float | None = None   # images: overrides the file's resolution tags
    view: str = "auto"               # images: "auto" refuses perspective (a camera), "flatbed" takes it as flat


@dataclass(frozen=True)
class ScanResult:
    """Everything the scan flow found; ``reports`` turns it into files.

    ``fiducials`` maps column name -> array, one entry per detected
    fiducial (see README for the columns). Positions ``x_meas_mm`` etc. are in
    the GLS frame after registration; ``*_scanner_mm`` in the scanner frame.
    """

    source: str
    spec: PlateSpec
    options: ScanOptions
    fiducials: dict
    missing_ids: list
    stats: dict                     # area -> deviation_stats (measured deviations)
    model: rbf.RBFModel             # wanted position -> command offset (trained P -> Q - P)
    model_eq9: rbf.RBFModel         # paper eq. 9: nominal Q -> delta
    forward_model: rbf.RBFModel     # nominal Q -> landing error P - Q (for the estimates)
    selection: rbf.Selection
    grid_xy_mm: np.ndarray          # (n, 2) correction grid nodes
    grid_dxy_mm: np.ndarray         # (n, 2) command offsets
    targets: dict                   # corrected targets, column -> array
    predicted: dict                 # method -> deviation_stats of the predicted residual
    summary: dict
    plane: Plane = field(repr=False)
    raster: Raster = field(repr=False)
    edges: detect.EdgeImages = field(repr=False)
    preview_xyz_mm: np.ndarray = field(repr=False)
    preview_intensity: np.ndarray = field(repr=False)
    registration_angle_deg: float = 0.0
    orientation: orientation.Choice | None = field(default=None, repr=False)
    grid_model: object = field(default=None, repr=False)   # galvo_fit.ModelChoice (models other than ols-rbf)


def run_scan(cloud_path, spec: PlateSpec, options: ScanOptions | None = None, progress=None) -> ScanResult:
    """Run the scan flow on one cloud or image.

    Parameters
    ----------
    cloud_path : path
        PLY, PCD, CSV/TXT or NPY cloud in mm (scanner frame), or a TIFF/PNG/JPEG
        image of the plate (pixel size from its dpi tags or ``options.pixel_size_mm``).
    spec : PlateSpec
        What was marked.
    progress : callable, optional
        Called with a short text before each step.

    Raises
    ------
    MarkcalError
        Bad input; the message names the file.
    """
    opt = options or ScanOptions()
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    try:
        if file_ext(cloud_path) in IMAGE_EXTS:
            say("reading image")
            image = read_plate_image(cloud_path, opt.pixel_size_mm, refuse_camera=opt.view == "auto")
            return _run_image(image, str(cloud_path), spec, opt, say, t0)
        say("reading cloud")
        cloud = read_cloud(cloud_path)
        return _run(cloud, str(cloud_path), spec, opt, say, t0)
    except MarkcalError as exc:
        raise exc.with_path(cloud_path) from None


def _detect(raster, spec, opt, say, fine=None, spacing_mm=None):
    """Coarse centres on ``raster``, sub-pixel ring fits on ``fine`` (default: the same raster)."""
    say("median filter, Canny, closing")
    # the median filter spans about 0.5 mm (5 cells of 0.1 mm) whatever the cell size
    med = max(3, int(round(opt.median_px * 0.1 / raster.pixel_mm)) | 1) if raster.pixel_mm > 0.1 else opt.median_px
    filtered = detect.filter_raster(raster, med)
    edges = detect.edge_images(filtered)
    say("circular Hough transform")
    px = raster.pixel_mm
    r_px = max(spec.ring_radii_mm) / px
    coarse = detect.hough_centres(edges.filled, r_px, 0.5 * spec.pitch_mm / px, 2 * spec.n_fiducials + 20)
    if len(coarse) == 0:
        raise MarkcalError("no circles found on the plate" + _what_i_saw(spec, raster, spacing_mm))
    if px > COARSE_TEMPLATE_PX_MM:
        # coarse rasters: Canny leaves weak rings open and Hough misses them; add the template's peaks
        more = detect.template_centres(edges.filtered, [r / px for r in spec.ring_radii_mm], 0.5 * spec.pitch_mm / px)
        if len(more):
            far = cKDTree(coarse).query(more)[0] > 0.25 * spec.pitch_mm / px
            coarse = np.vstack([coarse, more[far]])
    coarse = detect.match_centres(edges.filtered, coarse, [r / px for r in spec.ring_radii_mm])
    say(f"sub-pixel ring fits of {len(coarse)} candidates")
    fit = detect.refine_rings(fine or raster, raster.to_mm(coarse), spec.ring_radii_mm,
                              coarse=raster if fine is not None else None)
    return edges, fit


def _run(cloud, source, spec, opt, say, t0):
    say("robust plane fit")
    plane = fit_plane(cloud.xyz_mm, seed=opt.seed)
    say("projecting onto the plate plane")
    raster = project(cloud.xyz_mm, cloud.intensity, plane, opt.pixel_mm)
    spacing = point_spacing_mm(raster)
    radii = sorted(spec.ring_radii_mm)
    if radii[-1] - radii[0] > 0 and (radii[-1] - radii[0]) / spacing < MIN_GAP_SAMPLES:
        raise MarkcalError("the scan is too coarse to resolve the double rings" + _what_i_saw(spec, raster, spacing))
    if spacing > 1.3 * opt.pixel_mm:
        # a coarse scan: one cell per point, so the rings are not broken up by empty cells
        say(f"coarse scan (points {spacing:.2f} mm apart): re-projecting on {spacing:.2f} mm cells")
        raster = project(cloud.xyz_mm, cloud.intensity, plane, float(np.round(COARSE_CELL * spacing, 3)))
    edges, fit = _detect(raster, spec, opt, say, spacing_mm=spacing)
    step = max(1, len(cloud.xyz_mm) // 150_000)
    extra = {"plate_tilt_deg": plane.tilt_deg, "plane_rms_mm": plane.rms_mm,
             "plane_inlier_fraction": plane.inlier_fraction, "n_points": int(len(cloud.xyz_mm)),
             "point_spacing_mm": spacing, "raster_pixel_mm": raster.pixel_mm}
    return _finish(fit, edges, raster, plane, source, spec, opt, say, t0, extra,
                   cloud.xyz_mm[::step].astype(np.float32), cloud.intensity[::step].astype(np.float32))


def _run_image(image, source, spec, opt, say, t0):
    """An image of the plate: no plane, no projection; Hough on a ~0.1 mm copy, ring fits on the pixels."""
    check_image_size(image, spec)
    fine = image_raster(image)
    coarse = coarse_raster(fine, opt.pixel_mm)
    edges, fit = _detect(coarse, spec, opt, say, fine=fine, spacing_mm=image.pixel_mm)
    extra = {"image_pixel_mm": image.pixel_mm, "image_pixel_size_from": image.pixel_size_from,
             "image_shape": list(image.intensity.shape), "image_bits": image.bits,
             "image_inverted": image.inverted, "n_points": int(image.intensity.size)}
    return _finish(fit, edges, coarse, flat_plane(), source, spec, opt, say, t0, extra,
                   np.zeros((0, 3), np.float32), np.zeros(0, np.float32))


def _finish(fit, edges, raster, plane, source, spec, opt, say, t0, extra, preview_xyz, preview_i):
    n_exp = len(spec.marked_ids)
    ok = fit.ok
    if ok.sum() >= 3:
        scale = float(np.median(fit.radius_scale[ok]))
    else:
        scale = 1.0
    if ok.sum() < n_exp / 2:
        seen = extra.get("point_spacing_mm", extra.get("image_pixel_mm"))
        radii = sorted(spec.ring_radii_mm)
        resolved = seen is None or (radii[-1] - radii[0]) / seen >= 2     # below 2 the blobs merge
        raise MarkcalError(_few_found_message(int(ok.sum()), n_exp, edges if resolved else None, spec, raster)
                           + _what_i_saw(spec, raster, seen))
    if abs(scale - 1) > 0.04:
        raise MarkcalError(f"ring radii in the scan are {scale:.3f} x the spec's "
                           f"{list(spec.ring_radii_mm)} mm: wrong plate spec?")
    idx = np.flatnonzero(ok)
    idx = idx[detect.dedupe(fit.uv_mm[idx], fit.contrast[idx] / np.maximum(fit.rms[idx], 1e-9),
                      0.5 * spec.pitch_mm)]
    say("identifying rows, columns and the plate's orientation")
    uv_all = fit.uv_mm[idx]
    if "image_pixel_mm" in extra:       # a camera's perspective is refused, not calibrated (docs/scan.md)
        limit = MAX_KEYSTONE if extra["image_pixel_size_from"] == "--pixel-size-mm" else MAX_KEYSTONE_SCANNER_DPI
        extra["image_keystone"] = check_flat_view(uv_all, spec.pitch_mm, opt.view == "auto", limit).keystone
    r_all, c_all, q_all = nominal_grid(spec)
    choice = _orientation(uv_all, spec, q_all, opt)
    cand = choice.chosen
    on = cand.ids >= 0
    idx, uv, row, col, ids = idx[on], uv_all[on], cand.row[on], cand.col[on], cand.ids[on]
    # two candidates on one site: keep the better fit
    order = np.lexsort((-fit.contrast[idx] / np.maximum(fit.rms[idx], 1e-9), ids))
    first = np.r_[True, ids[order][1:] != ids[order][:-1]]
    sel = order[first]
    idx, uv, row, col, ids = idx[sel], uv[sel], row[sel], col[sel], ids[sel]
    if len(ids) < n_exp / 2:
        raise MarkcalError(f"only {len(ids)} of {n_exp} fiducials could be placed on the grid")

    say("rigid registration to the nominal grid")
    q = q_all[ids]
    flip = np.diag([1.0, -1.0]) if cand.mirrored else np.eye(2)
    tf_f, used = robust_rigid_fit(uv @ flip, q, outlier_mm=0.3 * spec.pitch_mm)
    tf = Rigid2D(rotation=tf_f.rotation @ flip, translation_mm=tf_f.translation_mm)
    if not cand.mirrored:
        mirrored = rigid_fit(uv[used], q[used], allow_reflection=True)
        if mirrored.reflection:
            r_proper = np.sqrt(np.mean(np.sum((tf.apply(uv[used]) - q[used]) ** 2, axis=1)))
            r_mirror = np.sqrt(np.mean(np.sum((mirrored.apply(uv[used]) - q[used]) ** 2, axis=1)))
            if r_mirror < 0.5 * r_proper:
                raise MarkcalError("the grid registers only through a reflection: the scanner's x and y "
                                   "axes are mirrored relative to the galvo's (use --mirror yes or auto)")
    if used.sum() < n_exp / 2:
        raise MarkcalError("registration failed: too few fiducials agree with the nominal grid")
    p = tf.apply(uv)
    delta = q - p
    xyz = from_plane(uv, plane)

    fid = {
        "id": ids, "row": row, "col": col,
        "x_nom_mm": q[:, 0], "y_nom_mm": q[:, 1],
        "x_meas_mm": p[:, 0], "y_meas_mm": p[:, 1],
        "dx_mm": delta[:, 0], "dy_mm": delta[:, 1],
        "x_scanner_mm": xyz[:, 0], "y_scanner_mm": xyz[:, 1], "z_scanner_mm": xyz[:, 2],
        "ring_radius_scale": fit.radius_scale[idx], "line_width_mm": fit.width_mm[idx],
        "contrast": fit.contrast[idx], "fit_rms": fit.rms[idx], "n_samples": fit.n_points[idx],
        "used_in_registration": used.astype(int),
    }
    missing = sorted(set(spec.marked_ids) - set(ids.tolist()))
    stats = {name: deviation_stats(q, delta, hw) for name, hw in AREAS.items()}

    hx, hy = spec.half_extent_mm
    nodes = grid_nodes(hx, hy, spec.grid_step_mm)
    t_rbf = time.perf_counter()
    if opt.model == "ols-rbf":
        say("RBF network: cross-validated spread and MSE goal")
        fitted = _fit_ols_rbf(p, q, delta, nodes, q_all, spec, opt)
    else:
        say(f"galvo model {opt.model}: k-fold cross-validation")
        fitted = _fit_galvo_model(p, q, nodes, q_all, spec, opt)
    rbf_s = time.perf_counter() - t_rbf
    dxy, k = fitted["dxy"], fitted["k"]
    ax, ay, dfr = galvo.inverse(k[:, 0], k[:, 1], spec.d_mm, spec.e_mm)
    targets = {"id": np.arange(spec.n_fiducials), "row": r_all, "col": c_all,
               "x_target_mm": q_all[:, 0], "y_target_mm": q_all[:, 1],
               "x_cmd_mm": k[:, 0], "y_cmd_mm": k[:, 1],
               "alpha_x_deg": np.degrees(ax), "alpha_y_deg": np.degrees(ay), "dfr_mm": dfr}
    targets = {key: v[spec.marked_ids] for key, v in targets.items()} if spec.mark_id is not None else targets
    predicted = fitted["predicted"]
    sel_ = fitted["selection"]
    model = fitted["model"]

    full = stats["full"]
    summary = {
        "source": source,
        "kind": "validation" if opt.validation else "calibration",
        "n_expected": n_exp, "n_detected": int(len(ids)), "n_missing": len(missing),
        "missing_ids": missing,
        "rms_mm": full["rms_mm"], "max_mm": full["max_mm"],
        "rms_x_mm": full["rms_x_mm"], "rms_y_mm": full["rms_y_mm"],
        "max_x_mm": full["max_x_mm"], "max_y_mm": full["max_y_mm"],
        "rms_150_mm": stats["inner_150"].get("rms_mm"), "max_150_mm": stats["inner_150"].get("max_mm"),
        "rms_50_mm": stats["inner_50"].get("rms_mm"), "max_50_mm": stats["inner_50"].get("max_mm"),
        **fitted["summary"],
        **extra,
        # direction of the plate's x axis in the scan frame (mirrored too): what --rotation-hint-deg takes
        "in_plane_rotation_deg": float(np.degrees(np.arctan2(tf.rotation[0, 1], tf.rotation[0, 0]))),
        "mirrored": bool(cand.mirrored),
        "orientation_method": choice.method,
        "orientation_margin": choice.margin if np.isfinite(choice.margin) else None,
        "orientation_candidates": [f"{c.label}: {c.phys_rms_mm * 1000:.2f} um" for c in choice.candidates],
        "model": opt.model if opt.model != "auto" else f"auto: {fitted['grid_model'].model.kind}",
        "rbf_training_s": rbf_s,
        "runtime_s": time.perf_counter() - t0,
    }
    return ScanResult(
        source=source, spec=spec, options=opt, fiducials=fid, missing_ids=missing, stats=stats,
        model=model, model_eq9=fitted["model_eq9"], forward_model=fitted["forward"], selection=sel_,
        grid_xy_mm=nodes, grid_dxy_mm=dxy, targets=targets, predicted=predicted, summary=summary,
        plane=plane, raster=raster, edges=edges,
        preview_xyz_mm=preview_xyz, preview_intensity=preview_i,
        registration_angle_deg=tf.angle_deg, orientation=choice, grid_model=fitted["grid_model"])


def _orientation(uv, spec, q_all, opt) -> orientation.Choice:
    """Index the lattice and choose the plate's orientation (mark, hint, galvo model).

    Without an orientation mark or a hint (``orientation="upright"`` is a hint
    of 0) only the galvo model is left, and it cannot tell a turn by 180 deg
    (``orientation.choose`` then refuses with the margin).
    """
    lat = lattice_coords(uv, spec.pitch_mm)
    cands = orientation.candidates(uv, lat, q_all, spec.rows, spec.cols, spec.d_mm, spec.e_mm,
                                   mirror=opt.mirror != "no")
    if opt.mirror == "yes":
        cands = [c for c in cands if c.mirrored]
    hint = opt.rotation_hint_deg
    if hint is None and opt.orientation == "upright":
        hint = 0.0
    return orientation.choose(cands, spec.mark_id, hint)


def _fit_ols_rbf(p, q, delta, nodes, q_all, spec, opt) -> dict:
    """The paper's OLS RBF network (sec. 2.6), spread and goal by cross-validation."""
    spreads = np.array(SPREADS_PER_PITCH) * spec.pitch_mm
    sel_ = rbf.select(p, delta, spreads, MSE_GOALS_MM2, opt.folds, opt.seed, opt.max_neurons)
    model = rbf.train(p, delta, sel_.spread_mm, sel_.mse_goal_mm2, opt.max_neurons)
    model_eq9 = rbf.train(q, delta, sel_.spread_mm, sel_.mse_goal_mm2, opt.max_neurons)
    forward = rbf.train(q, -delta, sel_.spread_mm, sel_.mse_goal_mm2, opt.max_neurons)
    hx, hy = spec.half_extent_mm
    inside = np.all(np.abs(nodes) <= [hx, hy], axis=1)
    tgt = nodes[inside]
    predicted = {}
    # predicted residuals with the fitted forward model: landing(K) ~ K + fwd(K)
    for name, cmd in (("inverse", tgt + model(tgt)), ("eq9", tgt + model_eq9(tgt))):
        land = cmd + forward(cmd)
        predicted[name] = deviation_stats(tgt, land - tgt)
    summary = {"cv_rmse_mm": sel_.cv_rmse_mm, "cv_rmse_std_mm": sel_.cv_rmse_std_mm,
               "n_neurons": model.n_neurons, "spread_mm": sel_.spread_mm, "mse_goal_mm2": sel_.mse_goal_mm2,
               "predicted_residual_rms_mm": predicted["inverse"]["rms_mm"],
               "predicted_residual_eq9_rms_mm": predicted["eq9"]["rms_mm"]}
    return {"dxy": model(nodes), "k": q_all + model(q_all), "predicted": predicted, "selection": sel_,
            "model": model, "model_eq9": model_eq9, "forward": forward, "grid_model": None, "summary": summary}


def _fit_galvo_model(p, q, nodes, q_all, spec, opt) -> dict:
    """The grid flow's galvo models (physical + spline, spline, cubic; auto by k-fold CV)."""
    mc = choose_model(opt.model, q, p, spec.d_mm, spec.e_mm, opt.folds, opt.seed)
    gm = mc.model
    summary = {"cv_rmse_mm": mc.cv_rmse_mm[gm.kind], "cv_rmse_std_mm": None,
               "cv_rmse_by_model_mm": dict(mc.cv_rmse_mm), "n_neurons": None, "spread_mm": None,
               "mse_goal_mm2": None, "predicted_residual_rms_mm": None, "predicted_residual_eq9_rms_mm": None}
    return {"dxy": gm(nodes), "k": q_all + gm(q_all), "predicted": {}, "selection": None, "model": None,
            "model_eq9": None, "forward": None, "grid_model": mc, "summary": summary}


def point_spacing_mm(raster) -> float:
    """Typical distance (mm) between points: the cell size over the root of the filled fraction of cells
    in the middle half of the raster (where the plate is; the frame around it is left out)."""
    h, w = raster.valid.shape
    mid = raster.valid[h // 4: 3 * h // 4, w // 4: 3 * w // 4]
    frac = float(mid.mean()) if mid.size else 1.0
    return raster.pixel_mm / np.sqrt(max(frac, 1e-3))


def _what_i_saw(spec, raster, spacing_mm) -> str:
    """Point spacing and how many samples span the ring gap and the ring line."""
    if spacing_mm is None:
        return ""
    radii = sorted(spec.ring_radii_mm)
    gap = radii[-1] - radii[0]
    msg = f"; points are {spacing_mm:.3f} mm apart"
    if gap > 0:
        msg += f", so the {gap:g} mm gap between the rings spans {gap / spacing_mm:.1f} samples"
        if gap / spacing_mm < 1:
            msg += (f" (at least {MIN_GAP_SAMPLES:g} are needed, a point spacing of "
                    f"{gap / MIN_GAP_SAMPLES:.2f} mm; every mark is found at 1)")
    return msg


def _few_found_message(n_found, n_exp, edges, spec, raster):
    """Say how many were found and, when the discs have another size, what size."""
    from scipy import ndimage
    lab, n = ndimage.label(edges.filled) if edges is not None else (None, 0)
    msg = f"only {n_found} of {n_exp} fiducials found (fewer than half the grid)"
    if edges is None:          # rings not resolved: the blobs' size says nothing about the radius
        return msg
    if n:
        area = np.bincount(lab.ravel())[1:] * raster.pixel_mm ** 2
        big = area[area > 2.0]
        if len(big) >= 4:
            r = float(np.sqrt(np.median(big) / np.pi))
            if abs(r / max(spec.ring_radii_mm) - 1) > 0.1:
                msg += (f"; the marks in the scan have an outer radius of about {r:.2f} mm, "
                        f"the plate spec says {max(spec.ring_radii_mm)} mm")
    return msg


def _claims(path) -> bool:
    e = file_ext(path)
    if e in IMAGE_EXTS:
        return _plate_spec_beside(path)
    if e in (".ply", ".pcd", ".xyz", ".npy"):
        return True
    if e in (".csv", ".txt"):
        h = csv_header(path)
        return not ({"t_s", "ref_mm", "pos_mm"} & set(h)) and (len(h) >= 3 or not any(c.isalpha() for c in "".join(h)))
    return False


def _plate_spec_beside(path) -> bool:
    """An image is a plate image when ``<stem>.toml`` or ``plate.toml`` beside it has a ``[grid]`` section
    (the indents flow, which also reads TIFF, uses ``[array]`` specs)."""
    import tomllib
    spec = spec_beside(path, "plate.toml")
    if spec is None:
        return False
    try:
        with open(spec, "rb") as fh:
            return isinstance(tomllib.load(fh).get("grid"), dict)
    except (OSError, ValueError):
        return False


def scan_options(options: dict) -> ScanOptions:
    """ScanOptions from the descriptor's option dict (CLI or batch.toml), checked."""
    model, orient, mirror = str(options["model"]), str(options["orientation"]), str(options["mirror"])
    for name, v, allowed in (("model", model, MODELS), ("orientation", orient, ORIENTATIONS),
                             ("mirror", mirror, MIRRORS)):
        if v not in allowed:
            raise MarkcalError(f"unknown {name} {v!r} (known: {', '.join(allowed)})")
    hint = options.get("rotation_hint_deg")
    hint = None if hint is None or not np.isfinite(float(hint)) else float(hint)     # NaN: no hint
    px = options.get("pixel_size_mm")
    px = None if px is None or not np.isfinite(float(px)) else float(px)              # NaN: from the file
    if px is not None and not 0 < px <= 10.0:
        raise MarkcalError(f"pixel_size_mm must be in (0, 10] mm (got {px:g})")
    view = str(options.get("view", "auto"))
    if view not in VIEWS:
        raise MarkcalError(f"unknown view {view!r} (known: {', '.join(VIEWS)})")
    purpose = str(options.get("purpose") or "") or ("validation" if options.get("validation") else "")
    if purpose not in ("", *PURPOSES):
        raise MarkcalError(f"unknown purpose {purpose!r} (known: {', '.join(PURPOSES)})")
    return ScanOptions(seed=int(options["seed"]), validation=purpose == "validation", model=model,
                       rotation_hint_deg=hint, orientation=orient, mirror=mirror, pixel_size_mm=px, view=view)


def _run_descriptor(path, spec_path, options, progress=None) -> ScanResult:
    spec = read_plate_spec(spec_path)
    if not (options.get("purpose") or options.get("validation")):      # not given: the plate spec's purpose
        options = {**options, "purpose": spec.purpose}
    return run_scan(path, spec, scan_options(options), progress=progress)


FLOW = FlowDescriptor(
    name="scan", help="3D scan or flatbed image of a galvo-marked plate -> deviations, correction, report",
    claims=_claims, run=_run_descriptor, spec_name="plate.toml", needs_spec=True, validate_options=scan_options,
    options={"seed": 0, "purpose": "", "validation": False, "no_report": False, "model": "ols-rbf",
             "rotation_hint_deg": float("nan"), "orientation": "auto", "mirror": "no",
             "pixel_size_mm": float("nan"), "view": "auto"},
    key_figures=(Figure("kind", "purpose"), Figure("n_detected", "fiducials detected"),
                 Figure("n_expected", "fiducials expected"), Figure("n_missing", "fiducials missing"),
                 Figure("rms_mm", "scan deviation RMS", "mm"), Figure("max_mm", "deviation max", "mm"),
                 Figure("predicted_residual_rms_mm", "predicted residual RMS after correction", "mm"),
                 Figure("cv_rmse_mm", "model CV RMSE", "mm")),
    # paper 004: CV RMSE 0.047 mm (sec. 3), post-calibration RMS 0.071 mm, max 0.252 mm (Table 1, 190 x 190 mm)
    tolerances=CALIBRATION_TOLERANCES, tolerances_by_kind={"validation": VALIDATION_TOLERANCES},
    trends=("rms_mm",), cost=4.0)
