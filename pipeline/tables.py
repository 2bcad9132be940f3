"""Strict reading of the CSV input tables users hand to the flows."""
from __future__ import annotations

import csv
import io
import json
import os
import re

import numpy as np

from markcal.stages.errors import MarkcalError
from markcal.stages.limits import check_text_ends, check_values, max_abs_for

__all__ = ["read_table", "check_increasing", "read_rbf_model", "load_json", "read_input_bytes"]

#: deepest nesting of lists and objects accepted in a JSON input
JSON_MAX_DEPTH = 64


def _refuse_constant(name):
    raise ValueError(f"{name} is not a number JSON allows")


def read_input_bytes(path, what: str = "file", missing: str = "no such file") -> bytes:
    """The bytes of an input file; a missing (``missing`` says so), non-regular (FIFO: it would hang) or
    unreadable one is refused."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):
        raise MarkcalError("not a regular file (a folder, FIFO or device)", path)
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except FileNotFoundError:
        raise MarkcalError(missing, path) from None
    except OSError as exc:
        raise MarkcalError(f"cannot read {what} ({exc.strerror or exc})", path) from None


def load_json(path, what: str = "JSON file"):
    """Read a JSON input strictly: UTF-8, no NaN/Infinity, nesting at most ``JSON_MAX_DEPTH``, numbers
    within ±1e15.

    Raises
    ------
    MarkcalError
        Missing or non-regular file, not UTF-8, not JSON, NaN/Infinity, too deep, a number too large.
    """
    path = os.fspath(path)
    raw = read_input_bytes(path, what)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise MarkcalError(f"not UTF-8 text (byte {exc.start}): a {what} must be UTF-8 JSON", path) from None
    # nesting depth before parsing (json recurses once per level): brackets outside strings
    br = np.frombuffer(re.sub(r'"(?:[^"\\]|\\.)*"', "", text).encode("utf-8"), np.uint8)
    step = (br == ord("[")).astype(np.int64) + (br == ord("{")) - (br == ord("]")) - (br == ord("}"))
    if len(step) and np.cumsum(step).max() > JSON_MAX_DEPTH:
        raise MarkcalError(f"JSON nested deeper than {JSON_MAX_DEPTH} levels", path)
    try:
        doc = json.loads(text, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as exc:
        msg = exc.msg if isinstance(exc, json.JSONDecodeError) else str(exc)
        line = f", line {exc.lineno}" if isinstance(exc, json.JSONDecodeError) else ""
        raise MarkcalError(f"not valid JSON ({msg}{line})", path) from None
    stack = [doc]
    while stack:
        o = stack.pop()
        if isinstance(o, dict):
            stack.extend(o.values())
        elif isinstance(o, list):
            stack.extend(o)
        elif isinstance(o, (int, float)) and not isinstance(o, bool) and not abs(o) <= 1e15:
            raise MarkcalError(f"a number ({o:g}) beyond ±1e15: not a measurement", path)
    return doc


def check_increasing(values: np.ndarray, name: str, path) -> None:
    """Refuse a column (read by :func:`read_table`) that does not strictly increase; name the lines."""
    bad = np.flatnonzero(np.diff(values) <= 0)
    if len(bad):
        i = int(bad[0])
        raise MarkcalError(f"out of time order: line {i + 3} has {name} = {values[i + 1]:g} after "
                           f"{values[i]:g} on line {i + 2} (times must increase)", path)


def read_table(path, columns, int_columns=(), key=None) -> dict:
    """Read a CSV input table with a header row into numeric columns.

    Parameters
    ----------
    path : str or os.PathLike
        The CSV file.
    columns : sequence of str
        Columns that must be present (others are ignored).
    int_columns : sequence of str
        Of those, the ones that must hold integers.
    key : sequence of str, optional
        Columns whose combination must be unique (a repeated key is an error).

    Returns
    -------
    dict
        Column name -> 1-D array (int64 for ``int_columns``, float64 otherwise).

    Raises
    ------
    MarkcalError
        Missing file or column, an empty table, a row with more or fewer fields
        than the header, a file cut inside its last row, a value that is not a
        finite number or lies beyond the physical limit of its unit
        (:func:`markcal.stages.limits.max_abs_for`), or a repeated key; the
        message names the line.
    """
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):
        raise MarkcalError("not a regular file (a folder, FIFO or device)", path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            text = fh.read()
        check_text_ends(text, path)
        reader = csv.reader(io.StringIO(text))
        lines = [(reader.line_num, r) for r in reader]
    except FileNotFoundError:
        raise MarkcalError("no such file", path) from None
    except UnicodeDecodeError as exc:
        raise MarkcalError(f"not a UTF-8 text file (byte {exc.start})", path) from None
    except (OSError, csv.Error) as exc:
        raise MarkcalError(f"cannot read as CSV ({exc})", path) from None
    kept = [(i, r) for i, r in lines if r and any(c.strip() for c in r)]
    line_of, rows = [i for i, _ in kept], [r for _, r in kept]
    if not rows:
        raise MarkcalError("empty file", path)
    header = [h.strip() for h in rows[0]]
    missing = [c for c in columns if c not in header]
    if missing:
        raise MarkcalError(f"missing column(s) {', '.join(missing)} (header: {','.join(header)})", path)
    if len(rows) < 2:
        raise MarkcalError("no data rows", path)
    idx = {c: header.index(c) for c in columns}
    limit = {c: max_abs_for(c) for c in columns}
    out = {c: np.empty(len(rows) - 1, np.int64 if c in int_columns else np.float64) for c in columns}
    for i, r in enumerate(rows[1:]):
        line = line_of[i + 1]
        if len(r) != len(header):
            raise MarkcalError(f"line {line}: {len(r)} fields, the header has {len(header)}", path)
        for c, j in idx.items():
            cell = r[j].strip()
            try:
                v = float(cell)
            except ValueError:
                raise MarkcalError(f"line {line}: {c} = {cell!r} is not a number", path) from None
            if not np.isfinite(v):
                raise MarkcalError(f"line {line}: {c} is {cell or 'empty'}", path)
            if abs(v) > limit[c]:
                check_values([v], c, path, line)
            if c in int_columns and v != int(v):
                raise MarkcalError(f"line {line}: {c} = {cell!r} is not an integer", path)
            out[c][i] = v
    if key:
        keys = np.column_stack([out[c] for c in key])
        _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
        if np.any(counts > 1):
            row = keys[first[np.argmax(counts > 1)]]
            dup = np.flatnonzero((keys == row).all(axis=1)) + 2
            desc = ", ".join(f"{c}={v:g}" for c, v in zip(key, row))
            raise MarkcalError(f"duplicate rows for {desc} (lines {', '.join(map(str, dup))})", path)
    return out


def read_rbf_model(path):
    """Read the RBF correction model of a ``model.json`` written by the scan flow."""
    from markcal.stages.rbf import RBFModel
    d = load_json(path, "model file")
    if not isinstance(d, dict):
        raise MarkcalError("not a markcal RBF model (not a JSON object)", path)
    try:
        return RBFModel.from_dict(d.get("model", d))
    except MarkcalError as exc:
        raise exc.with_path(path) from None
