"""Readers of hand-measured galvo grids: commanded vs measured mark positions.

Three layouts, told apart by content:

- CSV with a header ``x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm`` (optional ``id,row,col``);
- CSV with ``x_cmd_units,y_cmd_units`` (decimal or ``0x`` hex controller units)
  instead of the mm commands, converted with ``units_per_mm`` about ``centre_units``;
- the whitespace file users of open BJJCZ controllers write, one mark a line:
  ``measured_x_mm measured_y_mm i j galvo_x_hex galvo_y_hex`` (hex without ``0x``,
  16-bit units, centre 0x8000).

A CSV row whose measured cells are both empty is a mark not measured (it is
skipped and counted). Commands are in the controller's frame (mm); measured
positions in whatever frame the user measured in (mm).
"""
from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .limits import check_text_ends, max_abs_for

MIN_MARKS = 9
BJJCZ_CENTRE_UNITS = 0x8000


@dataclass(frozen=True)
class MeasuredGrid:
    """One measured grid. ``cmd_mm``, ``meas_mm`` (n, 2); ``row``, ``col`` (n,) int, -1 if not given.

    ``line`` is each mark's line number in the file; ``layout`` names the file
    layout; ``units_per_mm`` is set when the commands were in controller units.
    """

    cmd_mm: np.ndarray
    meas_mm: np.ndarray
    row: np.ndarray
    col: np.ndarray
    line: np.ndarray
    layout: str
    units_per_mm: float | None
    n_unmeasured: int


def _number(cell: str, what: str, line: int, hex_ok: bool = False) -> float:
    s = cell.strip()
    try:
        v = float(int(s, 16)) if hex_ok and s.lower().startswith(("0x", "-0x")) else float(s)
    except ValueError:
        raise MarkcalError(f"line {line}: {what} = {s!r} is not a number") from None
    if not np.isfinite(v):
        raise MarkcalError(f"line {line}: {what} is {s}")
    return v


def _units_scale(units_per_mm, what):
    if units_per_mm is None:
        raise MarkcalError(f"the commands are in controller units ({what}): give --units-per-mm "
                           "(controller units per mm, e.g. 65536 / lens field in mm)")
    if not (np.isfinite(units_per_mm) and units_per_mm > 0):
        raise MarkcalError(f"--units-per-mm must be positive (got {units_per_mm})")
    return float(units_per_mm)


def _read_csv(text, units_per_mm, centre_units):
    rows = [(i + 1, r) for i, r in enumerate(csv.reader(io.StringIO(text)))
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    header = [h.strip() for h in rows[0][1]]
    if {"x_cmd_mm", "y_cmd_mm"} <= set(header):
        cmd_cols, layout, scale = ("x_cmd_mm", "y_cmd_mm"), "csv-mm", None
    elif {"x_cmd_units", "y_cmd_units"} <= set(header):
        cmd_cols, layout = ("x_cmd_units", "y_cmd_units"), "csv-units"
        scale = _units_scale(units_per_mm, "columns x_cmd_units, y_cmd_units")
    else:
        raise MarkcalError("needs columns x_cmd_mm,y_cmd_mm (or x_cmd_units,y_cmd_units) and x_meas_mm,y_meas_mm "
                           f"(header: {','.join(header)})")
    missing = [c for c in ("x_meas_mm", "y_meas_mm") if c not in header]
    if missing:
        raise MarkcalError(f"missing column(s) {', '.join(missing)} (header: {','.join(header)})")
    col = {c: header.index(c) for c in header}
    cmd, meas, rc, lines, skipped = [], [], [], [], 0
    for line, r in rows[1:]:
        def cell(name):
            j = col.get(name)
            return r[j].strip() if j is not None and j < len(r) else ""
        mx, my = cell("x_meas_mm"), cell("y_meas_mm")
        if mx == "" and my == "":
            skipped += 1
            continue
        c = [_number(cell(k), k, line, hex_ok=scale is not None) for k in cmd_cols]
        if scale is not None:
            c = [(v - centre_units) / scale for v in c]
        cmd.append(c)
        meas.append([_number(mx, "x_meas_mm", line), _number(my, "y_meas_mm", line)])
        rc.append([int(_number(cell(k), k, line)) if cell(k) else -1 for k in ("row", "col")])
        lines.append(line)
    return cmd, meas, rc, lines, layout, scale, skipped


def _read_bjjcz(text, units_per_mm):
    scale = _units_scale(units_per_mm, "galvo_x_hex, galvo_y_hex")
    cmd, meas, ij, lines = [], [], [], []
    for i, raw in enumerate(text.splitlines()):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        tok = s.split()
        if len(tok) != 6:
            raise MarkcalError(f"line {i + 1}: expected 6 fields (measured_x_mm measured_y_mm i j galvo_x_hex "
                               f"galvo_y_hex), found {len(tok)}")
        meas.append([_number(tok[0], "measured_x_mm", i + 1), _number(tok[1], "measured_y_mm", i + 1)])
        ij.append([int(_number(tok[3], "j", i + 1)), int(_number(tok[2], "i", i + 1))])
        units = []
        for name, t in (("galvo_x_hex", tok[4]), ("galvo_y_hex", tok[5])):
            try:
                u = int(t, 16)
            except ValueError:
                raise MarkcalError(f"line {i + 1}: {name} = {t!r} is not hexadecimal") from None
            if not 0 <= u <= 0xFFFF:
                raise MarkcalError(f"line {i + 1}: {name} = {t} is outside 16 bits (0..FFFF)")
            units.append((u - BJJCZ_CENTRE_UNITS) / scale)
        cmd.append(units)
        lines.append(i + 1)
    rc = np.array(ij, int).reshape(-1, 2)
    if len(rc):
        rc = rc - rc.min(axis=0)
    return cmd, meas, rc.tolist(), lines, "bjjcz", scale, 0


def parse_grid(text: str, units_per_mm: float | None = None, centre_units: float = 32768.0) -> MeasuredGrid:
    """Parse the text of a measured grid file (any of the three layouts) and check it.

    Raises
    ------
    MarkcalError
        Unknown layout, a cell that is not a finite number, units without a
        scale, fewer than ``MIN_MARKS`` marks, duplicate commands, or marks on one line.
    """
    first = next((s.strip() for s in text.splitlines() if s.strip() and not s.lstrip().startswith("#")), "")
    if not first:
        raise MarkcalError("empty file")
    if "," in first:
        parsed = _read_csv(text, units_per_mm, centre_units)
    elif len(first.split()) == 6:
        parsed = _read_bjjcz(text, units_per_mm)
    else:
        raise MarkcalError("neither a CSV grid (x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm) nor a BJJCZ grid file "
                           "(measured_x_mm measured_y_mm i j galvo_x_hex galvo_y_hex)")
    cmd, meas, rc, lines, layout, scale, skipped = parsed
    cmd = np.array(cmd, float).reshape(-1, 2)
    meas = np.array(meas, float).reshape(-1, 2)
    rc = np.array(rc, int).reshape(-1, 2)
    lines = np.array(lines, int)
    for name, xy in (("commanded position (mm)", cmd), ("measured position (mm)", meas)):
        far = np.flatnonzero(np.abs(xy).max(axis=1, initial=0.0) > max_abs_for("xy_mm"))
        if len(far):
            raise MarkcalError(f"line {lines[far[0]]}: {name} {np.abs(xy[far[0]]).max():g} beyond the physical "
                               f"limit ±{max_abs_for('xy_mm'):g} mm")
    check_grid(cmd, meas, lines)
    return MeasuredGrid(cmd, meas, rc[:, 0], rc[:, 1], lines, layout, scale, skipped)


def check_grid(cmd_mm: np.ndarray, meas_mm: np.ndarray, lines: np.ndarray) -> None:
    """Refuse too few marks, repeated commanded positions and marks on one line."""
    n = len(cmd_mm)
    if n < MIN_MARKS:
        raise MarkcalError(f"only {n} measured marks: at least {MIN_MARKS} are needed")
    key = np.round(cmd_mm, 6)
    _, first, inv, counts = np.unique(key, axis=0, return_index=True, return_inverse=True, return_counts=True)
    if np.any(counts > 1):
        g = int(np.argmax(counts > 1))
        dup = lines[np.asarray(inv).ravel() == g]
        raise MarkcalError(f"duplicate commanded position ({key[first[g], 0]:g}, {key[first[g], 1]:g}) mm on "
                           f"lines {', '.join(map(str, dup))}")
    for name, xy in (("commanded", cmd_mm), ("measured", meas_mm)):
        s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
        if s[1] < 0.02 * s[0]:
            raise MarkcalError(f"the {name} positions lie on one line: a grid needs marks in two directions")


def read_grid(path, units_per_mm: float | None = None, centre_units: float = 32768.0) -> MeasuredGrid:
    """Read a measured grid file; errors name the file. See :func:`parse_grid`."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):
        raise MarkcalError("not a regular file (a folder, FIFO or device)", path)
    try:
        with open(path, encoding="utf-8-sig") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise MarkcalError("no such file", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MarkcalError(f"cannot read ({exc})", path) from None
    try:
        check_text_ends(text)
        return parse_grid(text, units_per_mm, centre_units)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
