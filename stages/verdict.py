"""Pass/fail verdicts: a flow's summary checked against ``max_<key>`` / ``min_<key>`` limits."""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from markcal.stages.errors import MarkcalError

__all__ = ["Verdict", "evaluate", "parse_tolerance", "PASS", "FAIL", "NO_TOLERANCE"]

PASS, FAIL, NO_TOLERANCE = "pass", "fail", "no tolerance"


@dataclass(frozen=True)
class Verdict:
    """The outcome of checking a summary.

    Attributes
    ----------
    status : str
        ``pass``, ``fail`` or ``no tolerance`` (no limits given).
    checks : str
        The limits applied, ``"; "``-joined, e.g. ``"rms_mm <= 0.05"``.
    failed : str
        The violated ones with their values (``""`` when all hold).
    """

    status: str
    checks: str
    failed: str


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def evaluate(summary: dict, tolerances: dict) -> Verdict:
    """Check a summary against ``max_<key>``/``min_<key>`` limits.

    A key the summary does not have fails ("missing"); a key whose value is
    null/NaN is not applicable to this input (e.g. the overshoot of a trace
    without moves) and is skipped. When no limit applies the status is
    ``no tolerance``, not ``pass``: nothing was checked.
    """
    checks, failed, applied = [], [], 0
    for tk in tolerances:                   # in the given order: a flow's defaults list the deciding figure first
        lim = tolerances[tk]
        key, op = tk[4:], ("<=" if tk.startswith("max_") else ">=")
        checks.append(f"{key} {op} {lim:g}")
        if key not in summary:
            failed.append(f"{key} missing")
            continue
        v = summary[key]
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            continue
        applied += 1
        if not _finite(v):
            failed.append(f"{key} not a number")
        elif (op == "<=" and v > lim) or (op == ">=" and v < lim):
            failed.append(f"{key} {v:.4g} {'>' if op == '<=' else '<'} {lim:g}")
    status = FAIL if failed else (PASS if applied else NO_TOLERANCE)
    return Verdict(status, "; ".join(checks), "; ".join(failed))


_TOL = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=)\s*([-+0-9.eEinfINF]+)\s*$")


def parse_tolerance(text: str) -> tuple:
    """``"rms_mm<=0.05"`` -> ``("max_rms_mm", 0.05)``; ``"key>=v"`` -> ``("min_key", v)``."""
    m = _TOL.match(text)
    if not m:
        raise MarkcalError(f"--tol {text!r}: expected KEY<=VALUE or KEY>=VALUE (e.g. rms_mm<=0.05)")
    try:
        v = float(m.group(3))
    except ValueError:
        raise MarkcalError(f"--tol {text!r}: {m.group(3)!r} is not a number") from None
    if not math.isfinite(v):
        raise MarkcalError(f"--tol {text!r}: the limit must be finite")
    return ("max_" if m.group(2) == "<=" else "min_") + m.group(1), v
