"""Strict reading of the CSV input tables users hand to the flows."""
from __future__ import annotations

import csv
import os

import numpy as np

from markcal.stages.errors import MarkcalError

__all__ = ["read_table", "check_increasing", "read_rbf_model"]


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
        Missing file or column, an empty table, a value that is not a finite
        number, or a repeated key; the message names the line.
    """
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):
        raise MarkcalError("not a regular file (a folder, FIFO or device)", path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except FileNotFoundError:
        raise MarkcalError("no such file", path) from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise MarkcalError(f"cannot read as CSV ({exc})", path) from None
    if not rows:
        raise MarkcalError("empty file", path)
    header = [h.strip() for h in rows[0]]
    missing = [c for c in columns if c not in header]
    if missing:
        raise MarkcalError(f"missing column(s) {', '.join(missing)} (header: {','.join(header)})", path)
    if len(rows) < 2:
        raise MarkcalError("no data rows", path)
    idx = {c: header.index(c) for c in columns}
    out = {c: np.empty(len(rows) - 1, np.int64 if c in int_columns else np.float64) for c in columns}
    for i, r in enumerate(rows[1:]):
        line = i + 2
        for c, j in idx.items():
            cell = r[j].strip() if j < len(r) else ""
            try:
                v = float(cell)
            except ValueError:
                raise MarkcalError(f"line {line}: {c} = {cell!r} is not a number", path) from None
            if not np.isfinite(v):
                raise MarkcalError(f"line {line}: {c} is {cell or 'empty'}", path)
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
    import json

    from markcal.stages.rbf import RBFModel
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
    except (OSError, ValueError) as exc:
        raise MarkcalError(f"cannot read model: {exc}", path) from None
    return RBFModel.from_dict(d.get("model", d))
