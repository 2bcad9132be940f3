"""Physical limits and size budgets every reader checks before any computation (issue 17).

A number in an input file is refused when it is not finite or lies beyond what any
instrument markcal serves can give: a length beyond ±10 m in its unit, a time beyond a
year. A declared size is refused when the arrays it implies would pass the memory
budget, before anything is allocated.
"""
from __future__ import annotations

import os

import numpy as np

from .errors import MarkcalError

__all__ = ["MEMORY_BUDGET_B", "max_abs_for", "check_values", "check_budget", "check_text_ends", "check_file_ends"]

#: the most bytes the arrays an input declares may take (``MARKCAL_MEMORY_BUDGET_GB`` overrides)
MEMORY_BUDGET_B = int(float(os.environ.get("MARKCAL_MEMORY_BUDGET_GB", "4")) * 2 ** 30)

#: largest magnitude of a value by the unit its name ends in: ±10 m of length, a year of time
UNIT_LIMITS = (("_nm", 1e10), ("_um", 1e7), ("_mm", 1e4), ("_m", 10.0), ("_min", 525_600.0),
               ("_ms", 3.2e10), ("_us", 3.2e13), ("_s", 3.2e7), ("_deg", 3.6e6), ("_urad", 6.3e12),
               ("_rad", 6.3e4), ("_hz", 1e9), ("_v", 1e6))
#: largest magnitude of a value whose name carries no known unit (counts, indices, intensities)
OTHER_LIMIT = 1e15


def max_abs_for(name: str) -> float:
    """The largest magnitude accepted for a value named ``name`` (its unit suffix decides)."""
    low = name.lower()
    for suffix, lim in UNIT_LIMITS:
        if low.endswith(suffix):
            return lim
    return OTHER_LIMIT


def check_values(values, name: str, path=None, first_line: int | None = None, limit: float | None = None) -> None:
    """Refuse non-finite values or values beyond the physical limit of ``name``.

    Parameters
    ----------
    values : array_like
        The numbers (any shape).
    name : str
        Their name (with its unit suffix) for the limit and the message.
    path : path, optional
        The file they come from, named in the message.
    first_line : int, optional
        File line of ``values[0]`` when each value is one line (rows of a table).
    limit : float, optional
        Overrides :func:`max_abs_for`.
    """
    a = np.asarray(values)
    if a.dtype.kind not in "iuf":
        raise MarkcalError(f"{name} must be real numbers (got {a.dtype})", path)
    if a.size == 0:
        return
    lim = max_abs_for(name) if limit is None else limit
    lo, hi = a.min(), a.max()            # two passes without temporaries; NaN comes through both
    if np.isfinite(lo) and np.isfinite(hi) and -lim <= lo and hi <= lim:
        return
    bad = ~np.isfinite(a) if a.dtype.kind == "f" else np.zeros(a.shape, bool)
    with np.errstate(invalid="ignore"):
        bad |= np.abs(a) > lim
    if bad.any():
        i = int(np.flatnonzero(bad.ravel())[0])
        v = a.ravel()[i]
        where = f"line {first_line + i}: " if first_line is not None and a.ndim == 1 else ""
        what = "is not finite" if not np.isfinite(v) else f"= {v:g} is beyond the physical limit ±{lim:g}"
        raise MarkcalError(f"{where}{name} {what}", path)


def check_budget(n_bytes: float, what: str, path=None) -> None:
    """Refuse an input whose declared sizes imply more than :data:`MEMORY_BUDGET_B` bytes."""
    if not n_bytes <= MEMORY_BUDGET_B:
        raise MarkcalError(f"{what} would take {n_bytes / 2 ** 30:.3g} GiB; at most {MEMORY_BUDGET_B / 2 ** 30:g} GiB "
                           "are read (set MARKCAL_MEMORY_BUDGET_GB to change the budget)", path)


def check_text_ends(data, path=None) -> None:
    """Refuse a text table whose last line has no line end: it was cut inside its last row."""
    if isinstance(data, str):
        tail = data.rstrip(" \t")
    else:
        tail = bytes(data).rstrip(b" \t").decode("ascii", "replace")
    if tail and tail[-1] not in "\r\n\x1a":
        raise MarkcalError("the last line has no line end: the file looks truncated inside its last row "
                           "(end the file with a newline if it is whole)", path)


def check_file_ends(path) -> None:
    """:func:`check_text_ends` on the last 4 kB of a file."""
    with open(path, "rb") as fh:
        fh.seek(max(0, os.path.getsize(path) - 4096))
        check_text_ends(fh.read(), path)
