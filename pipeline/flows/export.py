"""Export a flow's correction as a controller table, and inspect a table file.

Sources are output folders of the scan flow (galvo: ``model.json``,
``fiducials.csv``, ``summary.json``) and of the selfcal flow (stage:
``stage_error.csv``). Formats and their open assumptions: ``reports/export.py``
and the README ("Correction tables").
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from markcal.pipeline.tables import read_table
from markcal.reports import export as fmt
from markcal.stages.ctable import check_interpolation, centred_nodes, sample_onto_nodes
from markcal.stages.errors import MarkcalError
from markcal.stages.rbf import load_model

__all__ = ["ScanSource", "StageSource", "load_scan_source", "load_stage_source", "export_table",
           "Inspected", "inspect_table"]


@dataclass(frozen=True)
class ScanSource:
    """A scan flow result: its correction model and fiducial measurements (mm, GLS frame)."""

    folder: str
    model: object
    region_mm: tuple
    fiducials: dict
    kind: str

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
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, ValueError) as exc:
        raise MarkcalError(f"cannot read model: {exc}", path) from None
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
    with open(_need(folder, "summary.json", "scan flow"), encoding="utf-8") as fh:
        summary = json.load(fh)
    region = region or (float(f["x_nom_mm"].min()), float(f["x_nom_mm"].max()),
                        float(f["y_nom_mm"].min()), float(f["y_nom_mm"].max()))
    return ScanSource(folder, model, region, f, summary.get("kind", "calibration"))


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


def export_table(name: str, folder, *, lens_mm: float | None = None, cor: fmt.CorOptions = fmt.CorOptions(),
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
    if lens_mm is None or not lens_mm > 0:
        raise MarkcalError(f"--lens-mm (the lens field size, mm) is needed for {name} and must be positive")
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
    if missing.any():
        if not fill_missing:
            raise MarkcalError(f"{int(missing.sum())} fiducials were not detected; correXion needs every grid "
                               "point (use --fill-missing to fill them from the correction model)", src.folder)
        gx, gy = np.meshgrid(x_nodes, y_nodes)
        q = np.column_stack([gx[missing], gy[missing]])
        meas[missing] = q - src.offset_mm(q)      # landing ≈ nominal - command offset (first order)
    bpm = (2 ** 16 if rtc4 else 2 ** 20) / lens_mm
    text = fmt.encode_correxion(x_nodes, y_nodes, meas, bpm, rtc4=rtc4)
    return text.encode("ascii"), {"bits_per_mm": bpm, "grid": f"{len(x_nodes)} x {len(y_nodes)}",
                                  "filled_points": int(missing.sum())}


@dataclass(frozen=True)
class Inspected:
    """A table read back: vectors at nodes, ready to draw.

    ``u``, ``v`` are indexed ``[iy, ix]`` in ``unit``; ``what`` says what they are.
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


def inspect_table(path, *, lens_mm: float | None = None, cor: fmt.CorOptions = fmt.CorOptions(),
                  ctb: fmt.CtbOptions = fmt.CtbOptions(), sign: float = 1.0) -> Inspected:
    """Read any supported table file back into node vectors."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        raise MarkcalError("no such file", path) from None
    except OSError as exc:
        raise MarkcalError(f"cannot read ({exc})", path) from None
    try:
        kind = fmt.sniff_format(data)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    if kind == "cor":
        t, upm = fmt.decode_cor(data, cor, path)
        return Inspected(path, kind, t.x_mm, t.y_mm, t.dx_mm * 1e3, t.dy_mm * 1e3, "µm",
                         "command offset", {"scale (galvo units/mm)": upm, "lens field (mm)": 65536.0 / upm,
                                            "node spacing (units)": cor.node_spacing_units, "outer index": cor.outer,
                                            "sign": cor.sign, "max |entry| (units)":
                                                float(np.max(np.abs(np.r_[t.dx_mm.ravel(), t.dy_mm.ravel()])) * upm)})
    if kind == "ctb":
        if lens_mm is None:
            raise MarkcalError("a .ctb does not store its scale: give --lens-mm", path)
        bpm = 65536.0 / lens_mm
        t = fmt.decode_ctb(data, bpm, ctb, path)
        return Inspected(path, kind, t.x_mm, t.y_mm, t.dx_mm * 1e3, t.dy_mm * 1e3, "µm", "command offset",
                         {"bits/mm (from --lens-mm)": bpm, "content": ctb.content,
                          "node spacing (bits)": ctb.node_spacing_bits})
    text = data.decode("latin-1")
    if kind == "correxion":
        d = fmt.decode_correxion(text, path)
        gx, gy = np.meshgrid(d["x_mm"], d["y_mm"])
        dev = d["measured_xy_mm"] - np.stack([gx, gy], axis=-1)
        return Inspected(path, kind, d["x_mm"], d["y_mm"], dev[..., 0] * 1e3, dev[..., 1] * 1e3, "µm",
                         "measured − nominal position", {"bits/mm": d["bits_per_mm"], "RTC4": d["rtc4"]})
    d = fmt.decode_a3200(text, sign, path)
    return Inspected(path, kind, d["x_mm"], d["y_mm"], -sign * d["error_x_um"], -sign * d["error_y_um"], "µm",
                     "table correction (= −sign × measured error)", {"axes (x, y)": f"{d['ax1']}, {d['ax2']}"})
