"""The test job for a hand-measured galvo calibration and its measuring sheet.

A rows x cols grid of marks (crosses or circles) centred on the field, in the
commanded (controller) frame, mm; written as DXF (ezdxf), as a JSON job the
path flow reads, or as G-code; plus ``measure.csv`` with the commanded
positions and empty measured columns for the user to fill in.
"""
from __future__ import annotations

import io
import os

import numpy as np

from markcal.stages.errors import MarkcalError

from .files import atomic_write_bytes, atomic_write_text, write_csv

MARKS = ("cross", "circle")
FORMATS = {"dxf": "grid_job.dxf", "json": "grid_job.json", "gcode": "grid_job.gcode"}


def grid_positions(rows: int, cols: int, field_mm: float) -> tuple:
    """Row, column and commanded position (n, 2) mm of each mark; the outer marks span ``field_mm``."""
    if rows < 3 or cols < 3:
        raise MarkcalError(f"a calibration grid needs at least 3 x 3 marks (got {rows} x {cols})")
    if not field_mm > 0:
        raise MarkcalError(f"--field-mm must be positive (got {field_mm})")
    row, col = np.divmod(np.arange(rows * cols), cols)
    xs = np.linspace(-field_mm / 2, field_mm / 2, cols)
    ys = np.linspace(-field_mm / 2, field_mm / 2, rows)
    return row, col, np.column_stack([xs[col], ys[row]])


def mark_strokes(centre_mm, mark: str, size_mm: float) -> list:
    """Polylines (each (k, 2) mm) that draw one mark centred on ``centre_mm``."""
    c = np.asarray(centre_mm, float)
    h = size_mm / 2
    if mark == "cross":
        return [c + [[-h, 0.0], [h, 0.0]], c + [[0.0, -h], [0.0, h]]]
    if mark == "circle":
        t = np.linspace(0, 2 * np.pi, 37)
        return [c + h * np.column_stack([np.cos(t), np.sin(t)])]
    raise MarkcalError(f"unknown mark {mark!r} (known: {', '.join(MARKS)})")


def _dxf_bytes(strokes, meta: str) -> bytes:
    import ezdxf
    doc = ezdxf.new("R2010", units=ezdxf.units.MM)
    msp = doc.modelspace()
    for s in strokes:
        msp.add_lwpolyline([tuple(p) for p in s.tolist()])
    doc.header["$PROJECTNAME"] = meta[:60]
    buf = io.StringIO()
    doc.write(buf)
    return buf.getvalue().encode("utf-8")


def _gcode_text(strokes, meta: str) -> str:
    out = [f"; {meta}", "G21 ; mm", "G90 ; absolute", "M5"]
    for s in strokes:
        out.append(f"G0 X{s[0, 0]:.4f} Y{s[0, 1]:.4f}")
        out.append("M3")
        out += [f"G1 X{x:.4f} Y{y:.4f}" for x, y in s[1:]]
        out.append("M5")
    out.append("M2")
    return "\n".join(out) + "\n"


def write_grid_job(out_dir, rows: int, cols: int, field_mm: float, mark: str = "cross", fmt: str = "dxf",
                   size_mm: float | None = None) -> dict:
    """Write the grid job (one format) and measure.csv into ``out_dir``; return name -> path."""
    if fmt not in FORMATS:
        raise MarkcalError(f"unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    row, col, xy = grid_positions(rows, cols, field_mm)
    pitch = field_mm / max(rows - 1, cols - 1)
    size = size_mm if size_mm else min(2.0, 0.25 * pitch)
    strokes = [s for c in xy for s in mark_strokes(c, mark, size)]
    meta = f"markcal grid job: {rows} x {cols} {mark}es over {field_mm:g} mm, pitch {pitch:g} mm, commanded frame"
    os.makedirs(out_dir, exist_ok=True)
    job = os.path.join(out_dir, FORMATS[fmt])
    if fmt == "dxf":
        atomic_write_bytes(job, _dxf_bytes(strokes, meta))
    elif fmt == "gcode":
        atomic_write_text(job, _gcode_text(strokes, meta))
    else:
        import json
        doc = {"units": "mm", "name": "markcal grid job", "description": meta,
               "strokes": [{"kind": "contour", "xy_mm": s[:-1].tolist()} if mark == "circle"
                           else {"kind": "polyline", "xy_mm": s.tolist()}
                           for s in strokes]}
        atomic_write_text(job, json.dumps(doc, indent=1) + "\n")
    sheet = os.path.join(out_dir, "measure.csv")
    empty = np.full(len(xy), np.nan)
    write_csv(sheet, {"id": np.arange(len(xy)), "row": row, "col": col, "x_cmd_mm": xy[:, 0], "y_cmd_mm": xy[:, 1],
                      "x_meas_mm": empty, "y_meas_mm": empty})
    return {"job": job, "measure.csv": sheet}
