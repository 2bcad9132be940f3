"""Export a flow's correction as a controller table, and inspect a table file.

Sources are output folders of the scan flow (galvo: ``model.json``,
``fiducials.csv``, ``summary.json``) and of the selfcal flow (stage:
``stage_error.csv``). Format codecs and their open assumptions:
``stages/table_formats.py`` and the README ("Correction tables").
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from markcal.pipeline.tables import load_json, read_input_bytes, read_table
from markcal.stages import table_formats as fmt
from markcal.stages.ctable import TableStructure, check_interpolation, centred_nodes, sample_onto_nodes, table_structure
from markcal.stages.errors import MarkcalError
from markcal.pipeline.tables import read_rbf_model as load_model

__all__ = ["ScanSource", "StageSource", "load_scan_source", "load_stage_source", "export_table",
           "Inspected", "inspect_table", "inspect_bytes", "layout_text"]


@dataclass(frozen=True)
class ScanSource:
    """A scan flow result: its correction model and fiducial measurements (mm, GLS frame)."""

    folder: str
    model: object
    region_mm: tuple
    fiducials: dict
    kind: str
    n_not_detected: int | None = None      # marks the result says were not found (None: not recorded)

    def offset_mm(self, xy_mm):
        """Command offset (mm) at wanted positions (n, 2)."""
        return self.model(np.asarray(xy_mm, float))


@dataclass(frozen=True)
class StageSource:
    """A selfcal flow result: the stage error map G on its grid (µm), ``[iy, ix]``."""

    folder: str
    x_mm: np.ndarray
    y_mm: np.ndarray
    gx_um: np.ndarray
    gy_um: np.ndarray


#: the widest lens field accepted (mm)
MAX_LENS_MM = 5000.0


def _need(folder, name, what):
    p = os.path.join(folder, name)
    if not os.path.exists(p):
        raise MarkcalError(f"no {name}: not a {what} result folder", folder)
    return p


def _load_galvo_model(path) -> tuple:
    """The correction model of model.json and the region it declares valid (None: the fiducials' span).

    The scan flow writes an RBF network; the grid flow a ``markcal-grid-model-1``
    model valid over the whole lens field.
    """
    doc = load_json(path, "model file")
    if isinstance(doc, dict) and isinstance(doc.get("model"), dict) and doc["model"].get("format") == "markcal-grid-model-1":
        from markcal.stages.galvo_fit import GridModel
        try:
            region = tuple(float(v) for v in doc["valid_region_mm"])
            model = GridModel.from_dict(doc["model"])
        except (KeyError, TypeError, ValueError) as exc:
            raise MarkcalError(f"not a markcal grid model: {exc}", path) from None
        except MarkcalError as exc:
            raise exc.with_path(path) from None
        return model, region
    return load_model(path), None


def load_scan_source(folder) -> ScanSource:
    """Read a scan flow output folder."""
    folder = os.fspath(folder)
    model, region = _load_galvo_model(_need(folder, "model.json", "scan flow"))
    f = read_table(_need(folder, "fiducials.csv", "scan flow"),
                   ("row", "col", "x_nom_mm", "y_nom_mm", "x_meas_mm", "y_meas_mm"), int_columns=("row", "col"))
    spath = _need(folder, "summary.json", "scan flow")
    summary = load_json(spath, "summary file")
    if not isinstance(summary, dict) or summary.get("kind", "calibration") not in ("calibration", "validation"):
        raise MarkcalError("not a scan or grid result summary (its kind must be calibration or validation)", spath)
    region = region or (float(f["x_nom_mm"].min()), float(f["x_nom_mm"].max()),
                        float(f["y_nom_mm"].min()), float(f["y_nom_mm"].max()))
    missing = summary.get("missing_ids")
    return ScanSource(folder, model, region, f, summary.get("kind", "calibration"),
                      len(missing) if isinstance(missing, list) else None)


def load_stage_source(folder) -> StageSource:
    """Read a selfcal flow output folder."""
    folder = os.fspath(folder)
    t = read_table(_need(folder, "stage_error.csv", "selfcal flow"), ("x_mm", "y_mm", "gx_um", "gy_um"))
    xs, ys = np.unique(t["x_mm"]), np.unique(t["y_mm"])
    if len(xs) * len(ys) != len(t["x_mm"]):
        raise MarkcalError("stage_error.csv is not a full regular grid", folder)
    ix, iy = np.searchsorted(xs, t["x_mm"]), np.searchsorted(ys, t["y_mm"])
    gx = np.full((len(ys), len(xs)), np.nan)
    gy = gx.copy()
    gx[iy, ix], gy[iy, ix] = t["gx_um"], t["gy_um"]
    return StageSource(folder, xs, ys, gx, gy)


def _galvo_table(src: ScanSource, units_per_mm: float, spacing: float, allow_extrapolation: bool):
    nodes = centred_nodes(fmt.COR_NODES, spacing, units_per_mm)
    s = sample_onto_nodes(src.offset_mm, nodes, nodes, src.region_mm, 1.0 if allow_extrapolation else 0.5)
    # one controller unit, but not below 10 nm: the network itself is evaluated to ~1 nm
    err = check_interpolation(src.offset_mm, s.table, src.region_mm, max(1.0 / units_per_mm, 1e-5),
                              "the 65 x 65 table is")
    return s, err


def export_table(name: str, folder, **kw) -> tuple:
    """See :func:`_export_table`; every refusal names the source folder when it names no file."""
    try:
        return _export_table(name, folder, **kw)
    except MarkcalError as exc:
        raise exc.with_path(folder) from None


def _export_table(name: str, folder, *, lens_mm: float | None = None, cor: fmt.CorOptions = fmt.CorOptions(),
                 ctb: fmt.CtbOptions = fmt.CtbOptions(), rtc4: bool = False, fill_missing: bool = False,
                 ax1: int = 1, ax2: int = 2, sign: float = 1.0, allow_extrapolation: bool = False) -> tuple:
    """Build the bytes of a controller table from a flow result folder.

    Returns
    -------
    (bytes, dict)
        The file content and facts for the user (scale, extrapolated nodes,
        largest entry, interpolation error).
    """
    if name not in fmt.FORMATS:
        raise MarkcalError(f"unknown format '{name}' (known: {', '.join(fmt.FORMATS)})")
    if name == "a3200":
        if sign not in (1.0, -1.0):
            raise MarkcalError("--sign must be 1 or -1")
        st = load_stage_source(folder)
        text = fmt.encode_a3200(st.x_mm, st.y_mm, st.gx_um, st.gy_um, ax1=ax1, ax2=ax2, sign=sign)
        return text.encode("ascii"), {"nodes": f"{len(st.x_mm)} x {len(st.y_mm)}",
                                      "step_mm": float(st.x_mm[1] - st.x_mm[0]),
                                      "max_correction_um": float(np.nanmax(np.hypot(st.gx_um, st.gy_um)))}
    if lens_mm is None or not 0 < lens_mm <= MAX_LENS_MM:
        raise MarkcalError(f"--lens-mm (the lens field size, mm) is needed for {name} and must be positive and at "
                           f"most {MAX_LENS_MM:g} mm (got {lens_mm})")
    src = load_scan_source(folder)
    if name == "correxion":
        if src.kind == "validation":
            raise MarkcalError("this is a validation scan (marked through a correction): correXion needs the "
                               "uncorrected calibration scan", folder)
        return _correxion(src, lens_mm, rtc4, fill_missing)
    upm = 65536.0 / lens_mm
    if name == "cor":
        s, err = _galvo_table(src, upm, cor.node_spacing_units, allow_extrapolation)
        data = fmt.encode_cor(s.table, upm, cor)
    else:
        s, err = _galvo_table(src, upm, ctb.node_spacing_bits, allow_extrapolation)
        data = fmt.encode_ctb(s.table, upm, ctb)
    return data, {"units_per_mm": upm, "extrapolated_nodes": s.n_extrapolated,
                  "max_entry_units": float(np.max(np.abs(np.r_[s.table.dx_mm.ravel(), s.table.dy_mm.ravel()])) * upm),
                  "interpolation_error_units": err * upm}


def _correxion(src: ScanSource, lens_mm: float, rtc4: bool, fill_missing: bool) -> tuple:
    f = src.fiducials
    xs, ys = np.unique(np.round(f["x_nom_mm"], 9)), np.unique(np.round(f["y_nom_mm"], 9))
    rows, cols = int(f["row"].max()) + 1, int(f["col"].max()) + 1
    pitch_x = np.diff(xs).min() if len(xs) > 1 else 0.0
    pitch_y = np.diff(ys).min() if len(ys) > 1 else 0.0
    x_nodes = xs[0] + pitch_x * np.arange(cols) if cols > 1 else xs
    y_nodes = ys[0] + pitch_y * np.arange(rows) if rows > 1 else ys
    if not (np.allclose(x_nodes, -x_nodes[::-1], atol=1e-6) and np.allclose(y_nodes, -y_nodes[::-1], atol=1e-6)):
        raise MarkcalError("correXion needs a grid symmetric about the field centre", src.folder)
    meas = np.full((len(y_nodes), len(x_nodes), 2), np.nan)
    ix = np.rint((f["x_nom_mm"] - x_nodes[0]) / pitch_x).astype(int)
    iy = np.rint((f["y_nom_mm"] - y_nodes[0]) / pitch_y).astype(int)
    meas[iy, ix, 0], meas[iy, ix, 1] = f["x_meas_mm"], f["y_meas_mm"]
    missing = np.isnan(meas[..., 0])
    # sites left unmarked by design (an orientation mark) have no row and are not "not detected"
    not_detected = int(missing.sum()) if src.n_not_detected is None else min(src.n_not_detected, int(missing.sum()))
    if missing.any():
        if not_detected and not fill_missing:
            raise MarkcalError(f"{not_detected} fiducials were not detected; correXion needs every grid "
                               "point (use --fill-missing to fill them from the correction model)", src.folder)
        gx, gy = np.meshgrid(x_nodes, y_nodes)
        q = np.column_stack([gx[missing], gy[missing]])
        meas[missing] = q - src.offset_mm(q)      # landing ≈ nominal - command offset (first order)
    bpm = (2 ** 16 if rtc4 else 2 ** 20) / lens_mm
    text = fmt.encode_correxion(x_nodes, y_nodes, meas, bpm, rtc4=rtc4)
    return text.encode("ascii"), {"bits_per_mm": bpm, "grid": f"{len(x_nodes)} x {len(y_nodes)}",
                                  "filled_points": not_detected, "unmarked_sites": int(missing.sum()) - not_detected}


def layout_text(kind: str, cor: fmt.CorOptions = fmt.CorOptions(), ctb: fmt.CtbOptions = fmt.CtbOptions(),
                ax1: int = 1, ax2: int = 2) -> str:
    """How a format's entries are laid out with these options, in words."""
    if kind == "cor":
        return ("65 × 65 (first, second) int32 pairs, first value x; " +
                ("inner index along x (EZCAD's own layout)" if cor.outer == "y"
                 else "inner index along y (transposed: not the layout of EZCAD's files)"))
    if kind == "ctb":
        return ("X table then Y table, 65 × 65 uint16 each; " +
                ("inner index along x (SCANLAB's layout)" if ctb.outer == "y"
                 else "inner index along y (transposed: not SCANLAB's layout)"))
    if kind == "correxion":
        return "one line per grid point: Xn, Yn, X mm, Y mm measured; Xn runs fastest, top row (largest Yn) first"
    return (f"rows along axis {ax2} (y), columns along axis {ax1} (x); each entry a pair "
            f"(axis {ax1} correction, axis {ax2} correction), µm")


@dataclass(frozen=True)
class Inspected:
    """A table read back: vectors at nodes, ready to draw.

    ``u``, ``v`` are indexed ``[iy, ix]`` in ``unit``; ``what`` says what they are.
    ``structure`` is the symmetry of the entries as stored (file order),
    ``expected_along`` the index the first component runs along in the layout
    chosen for reading, ``warnings`` what contradicts it (one line each).
    """

    path: str
    format: str
    x_mm: np.ndarray
    y_mm: np.ndarray
    u: np.ndarray
    v: np.ndarray
    unit: str
    what: str
    facts: dict = field(default_factory=dict)
    layout: str = ""
    structure: TableStructure | None = None
    expected_along: str = "inner"
    warnings: tuple = ()


def _structure_warnings(st: TableStructure, expected: str, binary: bool) -> tuple:
    """One-line warnings when a table's structure contradicts the layout it is read with."""
    if st.first_along == "none":
        if not binary:          # a text format names its axes: no layout is assumed
            return ()
        return (f"the table fits no known layout ({st.reason}): shown as read, not interpreted",)
    if st.first_along == expected:
        return ()
    if binary:
        return (f"the file's structure contradicts the chosen layout: its first component is odd along the "
                f"{st.first_along} index, the layout read puts x along the {expected} index "
                f"(evidence {st.evidence:+.2f}); read it with --outer {'y' if st.first_along == 'inner' else 'x'}",)
    return (f"the x component is odd along y and the y component along x (evidence {st.evidence:+.2f}): "
            "the file's axes look swapped relative to its x/y labels",)


def _entry_range(a: np.ndarray) -> str:
    return f"{float(np.min(a)):.6g} … {float(np.max(a)):.6g}"


def inspect_bytes(data: bytes, path: str, *, lens_mm: float | None = None, cor: fmt.CorOptions = fmt.CorOptions(),
                  ctb: fmt.CtbOptions = fmt.CtbOptions(), sign: float = 1.0) -> Inspected:
    """Read a table's bytes into node vectors with a structural check (``path`` names it in messages)."""
    try:
        kind = fmt.sniff_format(data)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    if kind == "cor":
        t, upm = fmt.decode_cor(data, cor, path)
        raw = fmt.cor_file_order(data, path)
        st, expected = table_structure(raw[..., 0], raw[..., 1]), ("inner" if cor.outer == "y" else "outer")
        facts = {"scale (galvo units/mm)": upm, "lens field (mm)": 65536.0 / upm,
                 "node spacing (units)": cor.node_spacing_units, "outer index": cor.outer, "sign": cor.sign,
                 "first values (units)": _entry_range(raw[..., 0]), "second values (units)": _entry_range(raw[..., 1]),
                 "max |entry| (units)": float(np.max(np.abs(raw)))}
        x, y, u, v, what, binary = t.x_mm, t.y_mm, t.dx_mm * 1e3, t.dy_mm * 1e3, "command offset", True
        layout = layout_text(kind, cor=cor)
    elif kind == "ctb":
        if lens_mm is None:
            raise MarkcalError("a .ctb does not store its scale: give --lens-mm", path)
        bpm = 65536.0 / lens_mm
        t = fmt.decode_ctb(data, bpm, ctb, path)
        raw = fmt.ctb_file_order(data, path)
        st, expected = table_structure(raw[0], raw[1]), ("inner" if ctb.outer == "y" else "outer")
        facts = {"bits/mm (from --lens-mm)": bpm, "lens field (mm)": float(lens_mm), "content": ctb.content,
                 "outer index": ctb.outer, "node spacing (bits)": ctb.node_spacing_bits,
                 "X table (uint16)": _entry_range(raw[0] + 32767.5), "Y table (uint16)": _entry_range(raw[1] + 32767.5)}
        x, y, u, v, what, binary = t.x_mm, t.y_mm, t.dx_mm * 1e3, t.dy_mm * 1e3, "command offset", True
        layout = layout_text(kind, ctb=ctb)
    elif kind == "correxion":
        d = fmt.decode_correxion(data.decode("latin-1"), path)
        gx, gy = np.meshgrid(d["x_mm"], d["y_mm"])
        dev = (d["measured_xy_mm"] - np.stack([gx, gy], axis=-1)) * 1e3
        x, y, layout = d["x_mm"], d["y_mm"], layout_text(kind)
        facts = {"bits/mm": d["bits_per_mm"], "RTC4": d["rtc4"],
                 "lens field (mm)": (2 ** 16 if d["rtc4"] else 2 ** 20) / d["bits_per_mm"], "x deviation (µm)": _entry_range(dev[..., 0]),
                 "y deviation (µm)": _entry_range(dev[..., 1])}
        u, v, what, binary = dev[..., 0], dev[..., 1], "measured − nominal position", False
    else:
        d = fmt.decode_a3200(data.decode("latin-1"), sign, path)
        x, y, u, v = d["x_mm"], d["y_mm"], -sign * d["error_x_um"], -sign * d["error_y_um"]
        layout = layout_text(kind, ax1=d["ax1"], ax2=d["ax2"])
        facts = {"axes (x, y)": f"{d['ax1']}, {d['ax2']}", "sign": sign, "x corrections (µm)": _entry_range(u),
                 "y corrections (µm)": _entry_range(v)}
        what, binary = "table correction (= −sign × measured error)", False
    if not binary:      # text formats: rows along y, x fastest, so [iy, ix] is their file order
        st, expected = (table_structure(u, v) if u.shape[0] % 2 and u.shape[1] % 2 else None), "inner"
    warnings = _structure_warnings(st, expected, binary) if st is not None else ()
    return Inspected(path, kind, x, y, u, v, "µm", what, facts, layout, st, expected, warnings)


def inspect_table(path, *, lens_mm: float | None = None, cor: fmt.CorOptions = fmt.CorOptions(),
                  ctb: fmt.CtbOptions = fmt.CtbOptions(), sign: float = 1.0) -> Inspected:
    """Read any supported table file back into node vectors, with its structural check."""
    path = os.fspath(path)
    data = read_input_bytes(path, "table")
    return inspect_bytes(data, path, lens_mm=lens_mm, cor=cor, ctb=ctb, sign=sign)
