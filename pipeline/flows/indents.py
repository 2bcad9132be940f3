"""The indents flow: micro-indentation arrays from AFM height maps and OM images.

Paper 000 sec. 4 (Figs. 6-9, Table 1): per imprint centre, corners, diagonals,
equivalent diameter (circle through the corners), depth, H/D, orientation,
pile-up; array indexing, rigid registration to the nominal grid, positional
errors; per-size statistics pooled over all files of a batch.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from markcal.pipeline.config import _array_schema, load_toml, parse_config, read_array_spec
from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor, file_ext
from markcal.pipeline.flows.indents_afm import afm_map
from markcal.stages import indent as ind
from markcal.stages import indent_select as sel
from markcal.stages.afm_files import sniff_format
from markcal.stages.errors import MarkcalError
from markcal.stages.image_io import Image, read_image
from markcal.stages.indent_array import ArraySpec
from markcal.stages.indent_micrograph import measure_micrograph
from markcal.stages.indent_single import INDENTERS, hardness_hv
from markcal.stages.text_maps import is_text_matrix

#: QA limits (paper sec. 4): diameter within +-150 nm of nominal, H/D >= 0.04
TOLERANCE_UM = 0.15
MIN_HD = 0.04


@dataclass(frozen=True)
class IndentsOptions:
    """Settings of the indents flow."""

    kind: str | None = None                 # "afm" / "om"; None: from the file
    pixel_size_um: float | None = None      # overrides the file's pixel size
    channel: str | None = None              # AFM channel; None: the height/topography channel, trace
    tolerance_um: float = TOLERANCE_UM
    min_hd: float = MIN_HD
    load_mN: float | None = None            # indentation load: HV = 0.1891 F / d^2 (overrides the spec's)
    objective_na: float | None = None       # OM arrays: the objective's NA; the PSF is held at its Airy, not fitted
    wavelength_um: float = 0.55             # OM: wavelength of the light for objective_na
    optics_from: str | None = None          # OM arrays: micrograph of larger imprints (same material, indenter,
    #                                         objective) whose halo and crease are held on these (stages.indent_om_array)


@dataclass(frozen=True)
class FileResult:
    """One image measured.

    ``table`` maps indents.csv column -> array (one entry per imprint);
    ``imprints`` the stage records (corners for the report); ``image`` the
    levelled AFM map (nm) or the micrograph divided by its illumination.
    """

    source: str
    kind: str
    pixel_um: float
    table: dict
    imprints: list
    missing_ids: list
    nominal_um: float
    nominal_inferred: bool
    info: dict
    image: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class IndentsResult:
    """All files of a run: per-file results, failures, pooled tables and the summary."""

    files: list
    failed: list                            # (source, message)
    indents: dict                           # pooled indents.csv columns
    sizes: dict                             # sizes.csv columns
    summary: dict
    spec: ArraySpec | None
    options: IndentsOptions


def run_indents(paths, spec: ArraySpec | None = None, options: IndentsOptions | None = None,
                progress=None) -> IndentsResult:
    """Measure the imprints in one or more images and pool the statistics.

    Parameters
    ----------
    paths : list of path
        OM images (TIFF) or AFM maps (TIFF, GSF, GWY, IBW); one array per file.
    spec : ArraySpec, optional
        The array every file holds; without it all imprints are measured and
        no rows, columns or positional errors are given.

    Raises
    ------
    MarkcalError
        When no file could be measured (the first file's problem). A bad file
        among good ones is listed in ``failed`` instead.
    """
    opt = options or IndentsOptions()
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    held = optics_reference(opt.optics_from, opt, say) if opt.optics_from else None
    files, failed = [], []
    for p in paths:
        say(f"{os.path.basename(str(p))}: reading")
        try:
            files.append(measure_file(p, spec, opt, say, held))
        except MarkcalError as exc:
            exc = exc.with_path(p)
            failed.append((str(p), exc.message))
            say(f"{os.path.basename(str(p))}: failed: {exc.message}")
    if not files:
        src, msg = failed[0]
        raise MarkcalError(msg, src)
    indents = {k: np.concatenate([f.table[k] for f in files]) for k in files[0].table}
    sizes = ind.size_stats(indents["nominal_um"], indents["diameter_um"], indents["hd_ratio"],
                           indents["depth_nm"])
    summary = _summary(files, failed, indents, spec, opt, time.perf_counter() - t0)
    summary.update(_held_summary(opt, held))
    return IndentsResult(files=files, failed=failed, indents=indents, sizes=sizes, summary=summary,
                         spec=spec, options=opt)


def optics_reference(path, opt: IndentsOptions, say=lambda m: None) -> dict:
    """The halo and crease of an OM array micrograph of larger imprints (:func:`markcal.stages.indent_om_array.om_halo_crease`),
    to hold on imprints near the resolution limit imaged with the same objective.

    Raises
    ------
    MarkcalError
        The file is not a light micrograph of an array of at least three imprints larger than the resolution
        limit (an AFM map, single imprints, too few or too small ones).
    """
    img = read_image(path, opt.pixel_size_um, opt.kind, channel=opt.channel)
    if img.kind != "om":
        raise MarkcalError("optics reference: an AFM height map; the halo and crease come from a light micrograph",
                           path)
    with _one_blas_thread():
        single, _bar = measure_micrograph(img.data, img.pixel_um)      # the flow's own test for single imprints
        if single:
            raise MarkcalError(f"optics reference: a micrograph of {len(single)} single imprint(s) of "
                               f"{np.median([m.d_um for m in single]):.1f} µm, not an array: the halo and crease "
                               "come from an OM array of imprints", path)
        say(f"{os.path.basename(str(path))}: measuring the optics reference (halo and crease)")
        bg = ind.om_background(img.data, img.pixel_um)
        cands, sig = ind.detect_dots(img.data, img.pixel_um, background=bg)
        try:
            return ind.om_halo_crease(img.data, img.pixel_um, cands, sig, bg)
        except ValueError as exc:
            raise MarkcalError(f"optics reference: {exc}", path) from None


def _one_blas_thread():
    """Small matrices: one BLAS thread is fastest and never oversubscribes (a context manager)."""
    from threadpoolctl import threadpool_limits
    return threadpool_limits(1)


def _held_summary(opt: IndentsOptions, held) -> dict:
    """summary.json: the optics reference and the values held from it (null without one)."""
    h = held or {}
    return {"optics_from": os.path.basename(str(opt.optics_from)) if opt.optics_from else None,
            "held_rim": h.get("rim"), "held_rim_w": h.get("rim_w"), "held_crease": h.get("crease")}


def measure_file(path, spec: ArraySpec | None, opt: IndentsOptions, say=lambda m: None,
                 held: dict | None = None) -> FileResult:
    """Read, level (AFM), detect, measure and index the imprints of one image; ``held``: the halo and crease of
    :func:`optics_reference`, held on OM arrays."""
    t0 = time.perf_counter()
    img = read_image(path, opt.pixel_size_um, opt.kind, channel=opt.channel)
    try:
        with _one_blas_thread():
            return _measure(img, spec, opt, say, t0, held)
    except MarkcalError as exc:
        raise exc.with_path(path) from None


def _check_fits(img: Image, spec: ArraySpec):
    h_um, w_um = (np.array(img.shape) - 1) * img.pixel_um
    need_w = (spec.cols - 1) * spec.pitch_um + spec.nominal_diameter_um
    need_h = (spec.rows - 1) * spec.pitch_um + spec.nominal_diameter_um
    if need_w > w_um or need_h > h_um:
        raise MarkcalError(f"array spec ({spec.rows} x {spec.cols} at {spec.pitch_um:g} µm, "
                           f"{need_w:.1f} x {need_h:.1f} µm) does not fit the {w_um:.1f} x {h_um:.1f} µm image")
    if spec.nominal_diameter_um < 3 * img.pixel_um:
        raise MarkcalError(f"nominal diameter {spec.nominal_diameter_um:g} µm is under 3 pixels "
                           f"({img.pixel_um:.3f} µm): image too coarse for the array spec")


def _micrograph_single(img: Image, say, info, squares: bool = False) -> list:
    """Single imprints of a light or electron micrograph (empty when there are none this large); ``squares``:
    started from squares with four clear edges instead of the outline (grain contrast)."""
    name = os.path.basename(img.source)
    say(f"{name}: looking for " + ("imprints by their four edges" if squares else
                                   f"single imprints in {img.shape[0]} x {img.shape[1]} micrograph"))
    imps, bar = measure_micrograph(img.data, img.pixel_um, squares=squares)
    imps = sel.accept_imprints(imps, img.pixel_um)
    if imps:
        info.update(bar_rows=bar, method="four-facet quadrilateral fit (single imprints)")
        if bar:
            say(f"{name}: information bar of {bar} rows at the bottom left out")
    return imps


def _micrograph_dots(img: Image, spec, opt, say, info, held) -> tuple:
    """The dark dots of an OM array micrograph, fitted with one shared model.

    Without a spec, dark spots of every size (grain or dust) are first searched for a single imprint by its
    four edges; fitted dots with no common size are refused, and the four-edge search is the last resort.
    Returns the imprints, the image to draw them on (divided by the illumination for dots) and, when dots
    were refused for their sizes, why (else "").
    """
    name, px = os.path.basename(img.source), img.pixel_um
    say(f"{name}: detecting dots in {img.shape[0]} x {img.shape[1]} micrograph")
    bg = ind.om_background(img.data, px)
    cands, sig = ind.detect_dots(img.data, px, background=bg)
    squares = spec is None and sel.mixed_spots([c[2] for c in cands])
    if squares:
        # the dots' shared fit is slow on hundreds of grain specks (10-70 s on a BSE image) and not meant for them
        say(f"{name}: {len(cands)} dark spots of every size (grain or dust)")
        if imps := _micrograph_single(img, say, info, squares=True):
            return imps, img.data, ""
    say(f"{name}: fitting {len(cands)} candidates")
    # darkness, rim and PSF shared by the dots of one micrograph; dust the shared model
    # does not describe comes back as None
    psf = None if opt.objective_na is None else ind.airy_sigma_um(opt.objective_na, opt.wavelength_um)
    info.update(noise_rel=sig)
    imps = ind.measure_om_array(img.data, px, cands, sig, bg, psf_um=psf, held=held)
    if spec is not None:
        return imps, img.data / bg, ""
    imps, spots = sel.accept_imprints(imps, px), ""
    if not sel.one_size(imps):
        # grain or dust: an array of one load has one size
        d = np.array([m.d_um for m in imps])
        spots = (f"{len(imps)} dark spots of {np.percentile(d, 10):.2g}-{np.percentile(d, 90):.2g} µm have no "
                 "common size (grain or dust; an array spec measures them as imprints)")
        say(f"{name}: {spots}")
        imps = []
    if not imps and not squares:
        # the last resort: a single imprint whose outline strong grain contrast (BSE) cut into pieces
        return _micrograph_single(img, say, info, squares=True), img.data, spots
    return imps, img.data / bg, spots


def _measure(img: Image, spec, opt, say, t0, held=None):
    name = os.path.basename(img.source)
    if spec is not None:
        _check_fits(img, spec)
    px = img.pixel_um
    info = {"pixel_um": px, "shape": list(img.shape), "format": img.meta.get("format"),
            "channel": img.meta.get("channel", ""), "pixel_source": img.meta.get("pixel_source")}
    spots = ""                                      # why dark spots of a micrograph were refused
    if img.meta.get("resampled"):
        say(f"{name}: {img.meta['resampled']}")
        info["resampled"] = img.meta["resampled"]
    if img.kind == "afm":
        imps, floor, image = afm_map(img, spec, say, info)
    elif spec is None and (single := _micrograph_single(img, say, info)):
        # one or more single imprints (at least MIN_DIAGONAL_PX across): corners from the four-facet fit
        imps, floor, image = single, None, img.data
    else:
        imps, image, spots = _micrograph_dots(img, spec, opt, say, info, held)
        floor = None
    window = None if spec is None else (0.4 * spec.nominal_diameter_um, 2.0 * spec.nominal_diameter_um)
    imps = sel.accept_imprints(imps, px, floor, window, floor_clipped=bool(info.get("floor_clipped_px")))
    if not imps:
        raise MarkcalError("no imprint found" + (f": {spots}" if spots else ""))
    n = len(imps)
    xy = np.array([[m.x_um, m.y_um] for m in imps])
    missing = []
    if spec is not None:
        fit = ind.index_array(xy, spec.rows, spec.cols, spec.pitch_um)
        on = fit.row >= 0
        n_exp = spec.rows * spec.cols
        if on.sum() < max(1, n_exp / 2):
            raise MarkcalError(f"only {int(on.sum())} of {n_exp} imprints of the array spec found")
        off = n - int(on.sum()) - int(fit.stray.sum())     # on nodes beyond the spec's array: the spec is too small
        if off > max(2, 0.2 * n_exp):
            raise MarkcalError(f"{n} imprints found but the array spec has {spec.rows} x {spec.cols}: "
                               "the spec does not match the image")
        imps = [m for m, o in zip(imps, on) if o]
        row, col = fit.row[on], fit.col[on]
        dx, dy = fit.dx_um[on], fit.dy_um[on]
        ids = row * spec.cols + col
        order = np.argsort(ids)
        imps = [imps[i] for i in order]
        row, col, dx, dy, ids = row[order], col[order], dx[order], dy[order], ids[order]
        missing = sorted(set(range(n_exp)) - set(ids.tolist()))
        nominal, inferred = spec.nominal_diameter_um, False
        info.update(array_rotation_deg=fit.rotation_deg, n_expected=n_exp)
    else:
        d_med = np.median([m.diameter_um for m in imps])
        band = np.round(xy[:, 1] / max(2 * d_med, px))
        order = np.lexsort((xy[:, 0], band))
        imps = [imps[i] for i in order]
        ids = np.arange(n)
        row = col = np.full(n, -1)
        dx = dy = np.full(n, np.nan)
        nominal, inferred = float(max(0.5, np.round(2 * d_med) / 2)), True
        info.update(n_expected=None)
    k = len(imps)
    table = {"id": ids, "row": np.where(row >= 0, row, -1), "col": np.where(col >= 0, col, -1),
             "x_um": np.array([m.x_um for m in imps]), "y_um": np.array([m.y_um for m in imps]),
             "dx_um": dx, "dy_um": dy}
    for f in ind.IMPRINT_FIELDS[2:]:
        table[f] = np.array([getattr(m, f) for m in imps])
    table["cut_by_border"] = table["cut_by_border"].astype(int)
    table["diagonal_difference_pct"] = 100 * np.abs(table["diag1_um"] - table["diag2_um"]) / table["d_um"]
    load = opt.load_mN if opt.load_mN is not None else (spec.load_mN if spec is not None else None)
    table["hv"] = (hardness_hv(load, table["d_um"], INDENTERS[spec.indenter if spec else "vickers"])
                   if load is not None else np.full(len(imps), np.nan))
    table.update(file=np.array([name] * k, dtype=object), kind=np.array([img.kind] * k, dtype=object),
                 nominal_um=np.full(k, nominal), fit_rms=np.array([m.fit_rms for m in imps]),
                 n_pixels=np.array([m.n_pixels for m in imps]))
    table["in_tolerance"] = sel.tolerance_flags(table["diameter_um"], nominal, table["hd_ratio"], opt.tolerance_um,
                                                opt.min_hd)
    info["load_mN"] = load
    info["runtime_s"] = time.perf_counter() - t0
    say(f"{name}: {k} imprints, mean diameter {np.mean(table['diameter_um']):.3f} µm")
    return FileResult(source=img.source, kind=img.kind, pixel_um=px, table=table, imprints=imps,
                      missing_ids=missing, nominal_um=nominal, nominal_inferred=inferred, info=info, image=image)


def _rms(a):
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a ** 2))) if len(a) else None


def _nanmean(a):
    a = np.asarray(a, float)
    return float(np.nanmean(a)) if np.isfinite(a).any() else None


def _summary(files, failed, t, spec, opt, runtime_s):
    d = t["diameter_um"]
    err = d - t["nominal_um"]
    hd = t["hd_ratio"]
    n_exp = sum(f.info.get("n_expected") or 0 for f in files) if spec is not None else None
    out = {
        "source": files[0].source if len(files) + len(failed) == 1 else f"{len(files) + len(failed)} files",
        "n_files": len(files) + len(failed), "n_files_ok": len(files), "n_files_failed": len(failed),
        "failed_files": [f"{os.path.basename(s)}: {m}" for s, m in failed],
        "kinds": sorted({f.kind for f in files}),
        "array_spec": bool(spec is not None),
        "n_imprints": int(len(d)), "n_expected": n_exp,
        "n_missing": int(sum(len(f.missing_ids) for f in files)) if spec is not None else None,
        "missing": [f"{os.path.basename(f.source)}#{i}" for f in files for i in f.missing_ids],
        "mean_diameter_um": float(np.mean(d)), "sd_diameter_um": float(np.std(d, ddof=1)) if len(d) > 1 else None,
        "max_abs_error_um": float(np.max(np.abs(err))),
        "mean_depth_nm": float(np.nanmean(t["depth_nm"])) if np.isfinite(t["depth_nm"]).any() else None,
        "mean_hd": float(np.nanmean(hd)) if np.isfinite(hd).any() else None,
        "rms_dx_um": _rms(t["dx_um"]), "rms_dy_um": _rms(t["dy_um"]),
        "max_abs_dx_um": float(np.nanmax(np.abs(t["dx_um"]))) if np.isfinite(t["dx_um"]).any() else None,
        "max_abs_dy_um": float(np.nanmax(np.abs(t["dy_um"]))) if np.isfinite(t["dy_um"]).any() else None,
        "tolerance_um": opt.tolerance_um, "min_hd": opt.min_hd,
        # not applicable (null, no verdict on it): without an array spec there is no nominal size to be out of;
        # without depths (micrographs) no H/D
        "n_out_of_tolerance": int(np.sum(np.abs(err) > opt.tolerance_um)) if spec is not None else None,
        "n_low_hd": int(np.sum(np.isfinite(hd) & (hd < opt.min_hd))) if np.isfinite(hd).any() else None,
        "nominal_inferred": any(f.nominal_inferred for f in files),
        "pixel_um": files[0].pixel_um,
        "noise_nm": files[0].info.get("noise_nm"), "tilt_deg": files[0].info.get("tilt_deg"),
        "line_flatten": files[0].info.get("line_flatten", "none"),
        "resampled": files[0].info.get("resampled", "none"),
        "n_files_floor_clipped": int(sum(bool(f.info.get("floor_clipped_px")) for f in files)),
        "n_files_flatten_uncertain": int(sum(bool(f.info.get("line_flatten_uncertain")) for f in files)),
        "n_files_levelled_to_corners": int(sum(bool(f.info.get("levelled_to_corners")) for f in files)),
        "corner_level_nm": files[0].info.get("corner_level_nm") if files[0].info.get("levelled_to_corners") else None,
        "corner_level_weight": (files[0].info.get("corner_level_weight") if files[0].info.get("levelled_to_corners")
                                else None),
        "n_files_lag_removed": int(sum(f.info.get("scan_lag_px") is not None for f in files)),
        "scan_lag_px": files[0].info.get("scan_lag_px"),
        "imprint_shift_px": files[0].info.get("imprint_shift_px"),
        "n_imprints_both_directions": int(sum(f.info.get("n_both_directions", 0) for f in files)),
        "n_files_floor_missed": int(sum(bool(f.info.get("floor_missed")) for f in files)),
        "mean_d_um": float(np.mean(t["d_um"])),
        "mean_area_um2": _nanmean(t["area_um2"]),
        "mean_apex_depth_nm": _nanmean(t["apex_depth_nm"]),
        "mean_pileup_nm": _nanmean(t["pileup_nm"]),
        "mean_hv": _nanmean(t["hv"]),
        "load_mN": files[0].info.get("load_mN"),
        "n_cut_by_border": int(np.sum(t["cut_by_border"])),
        # ISO 6507-1: on a flat surface the diagonals should differ by at most 5 % of their mean, and a larger
        # difference is stated in the test report (a tilted sample, or a corner carried out by a crack or chip)
        "n_diagonals_differ": int(np.sum(t["diagonal_difference_pct"] > DIAGONALS_DIFFER_PCT)),
        **_resolution(files),
        "runtime_s": runtime_s,
    }
    return out


def _resolution(files) -> dict:
    """The optics' resolution (Airy radius from the fitted PSF, median over the OM-model imprints) and how many
    imprints are smaller than ``RESOLUTION_RADII`` of it (their diagonals lean on the model's assumptions);
    both null where no PSF was fitted (AFM, single-imprint micrographs)."""
    pairs = [(m.diameter_um, ind.airy_radius_um(m.psf_um)) for f in files for m in f.imprints if np.isfinite(m.psf_um)]
    if not pairs:
        return {"optics_resolution_um": None, "n_near_resolution": None}
    d, r = np.array(pairs).T
    return {"optics_resolution_um": float(np.median(r)),
            "n_near_resolution": int(np.sum(d < ind.RESOLUTION_RADII * r))}


#: diagonals differing by more than this (% of their mean) are stated in the report (ISO 6507-1)
DIAGONALS_DIFFER_PCT = 5.0

#: extensions of the height maps and micrographs the flow reads (others are recognised by content)
MAP_EXTENSIONS = (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".bmp", ".gsf", ".gwy", ".ibw", ".spm", ".nid", ".jpk",
                  ".stp", ".top")


def _claims(path) -> bool:
    e = file_ext(path)
    if e in MAP_EXTENSIONS or (len(e) == 4 and e[1:].isdigit()):       # Bruker .000 - .999
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return sniff_format(head) is not None or is_text_matrix(head)


def indents_options(o: dict) -> IndentsOptions:
    """:class:`IndentsOptions` from the descriptor's option dict ("" and 0 mean "from the file"); checks the values."""
    if o["kind"] not in ("", "afm", "om"):
        raise MarkcalError(f"kind must be afm or om (got {o['kind']!r})")
    for k in ("pixel_size_um", "load_mN"):
        if not 0 <= o[k] <= 1e6:
            raise MarkcalError(f"{k} must be positive and at most 1e6 (0: from the file) (got {o[k]!r})")
    na = o.get("objective_na", 0.0)
    if not 0 <= na <= 1.6:
        raise MarkcalError(f"objective_na must be in (0, 1.6] (0: fitted) (got {na!r})")
    return IndentsOptions(kind=o["kind"] or None, pixel_size_um=o["pixel_size_um"] or None,
                          channel=o["channel"] or None, load_mN=o["load_mN"] or None, objective_na=na or None,
                          optics_from=o.get("optics_from") or None)


def read_indents_spec(path) -> tuple:
    """Read a spec for ``markcal indents --array``: an array spec, or only an ``[indenter]`` table.

    Returns
    -------
    spec : ArraySpec or None
        None when the file has no ``[array]`` table (single imprints: every imprint found is measured).
    load_mN : float or None
        ``[indenter] load_mN`` (the Vickers hardness needs it).
    """
    doc = load_toml(path, "array spec")
    if "array" in doc:
        spec = read_array_spec(path)
        return spec, spec.load_mN
    c = parse_config(doc, {"indenter": _array_schema()["indenter"]}, os.fspath(path))
    return None, c["indenter"]["load_mN"]


def with_spec_load(options: dict, load_mN) -> dict:
    """Options with the spec's load where no load was given on the command line."""
    return {**options, "load_mN": options.get("load_mN") or load_mN or 0.0}


def _run_descriptor(path, spec_path, options, progress=None) -> IndentsResult:
    spec, load = read_indents_spec(spec_path) if spec_path else (None, None)
    options = with_spec_load(options, load)
    res = run_indents([path], spec, indents_options(options), progress=progress)
    if res.failed:
        raise MarkcalError(res.failed[0][1], res.failed[0][0])
    return res


FLOW = FlowDescriptor(
    name="indents", help="micro-indentation arrays and imprints from AFM height maps and micrographs",
    claims=_claims, run=_run_descriptor, spec_name="array.toml", validate_options=indents_options,
    options={"kind": "", "pixel_size_um": 0.0, "channel": "", "load_mN": 0.0, "objective_na": 0.0,
             "optics_from": "", "no_report": False},
    key_figures=(Figure("n_imprints", "imprints"), Figure("mean_diameter_um", "mean imprint diameter", "µm"),
                 Figure("n_out_of_tolerance", "imprints out of tolerance"), Figure("n_low_hd", "imprints with low H/D"),
                 Figure("n_missing", "expected imprints not found")),
    # an array with imprints not found fails: they may be unmeasured, and a missing row shifts the indexing
    tolerances={"max_n_out_of_tolerance": 0, "max_n_low_hd": 0, "max_n_missing": 0},
    trends=("mean_diameter_um",), cost=8.0)
