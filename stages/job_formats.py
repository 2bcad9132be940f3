"""What the job-format readers and writers share (DXF, SVG, HPGL, G-code).

A reader turns a file's bytes into a :class:`JobFile`: the strokes as the path
flow knows them (:class:`markcal.stages.path_job.Job`, mm), the group (layer,
pen, colour) of each stroke, the entities it does not support (type -> count)
and a format-specific ``payload`` its writer needs to write the ordered job
back with everything else in the file kept. Everything here is pure.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import MarkcalError
from .path_job import Job, Tour, make_job

__all__ = ["JobFile", "flatten_arc", "chord_steps", "paths_to_strokes", "marked_strokes", "fmt_num",
           "decode_text", "build_job", "CLOSE_TOL_MM"]

#: a path whose last vertex is this close to its first is a closed contour (mm)
CLOSE_TOL_MM = 1e-9


@dataclass(frozen=True, eq=False)
class JobFile:
    """A job read from a file.

    Attributes
    ----------
    job : Job
        Strokes in file order, mm.
    fmt : str
        ``"dxf"``, ``"svg"``, ``"hpgl"``, ``"gcode"``, ``"json"`` or ``"csv"``.
    groups : tuple of str
        Per stroke: its layer / group / pen ("" when the format has none).
    unsupported : dict
        Entity or command type -> how many the reader skipped.
    notes : tuple of str
        What the user should know about the reading (assumed units ...).
    payload : object
        What this format's writer needs (the source text, entity handles ...).
    """

    job: Job
    fmt: str
    groups: tuple = ()
    unsupported: dict = field(default_factory=dict)
    notes: tuple = ()
    payload: object = None

    @property
    def group_names(self) -> list:
        """Groups in the order they first appear."""
        return list(dict.fromkeys(self.groups))


def chord_steps(radius: float, sweep_rad: float, tol: float) -> int:
    """Segments needed so a chord of an arc of ``radius`` strays at most ``tol`` from it."""
    if radius <= tol or sweep_rad == 0:
        return 1
    half = math.acos(max(-1.0, 1.0 - tol / radius))          # half the angle a chord may span
    return max(1, int(math.ceil(abs(sweep_rad) / (2.0 * half) - 1e-12)))


def flatten_arc(center, radius: float, a0_rad: float, sweep_rad: float, tol: float) -> np.ndarray:
    """Vertices of a circular arc after its start, within chordal tolerance ``tol``.

    Parameters
    ----------
    center : (2,) array-like
    radius, tol : float
        Same length unit.
    a0_rad, sweep_rad : float
        Start angle and signed sweep (positive counter-clockwise).

    Returns
    -------
    ndarray, shape (k, 2)
        The vertices after the start point, the last one the arc's end.
    """
    k = chord_steps(radius, sweep_rad, tol)
    t = a0_rad + sweep_rad * np.arange(1, k + 1) / k
    return np.asarray(center, float) + radius * np.column_stack([np.cos(t), np.sin(t)])


def paths_to_strokes(paths, closed_flags=None):
    """Flattened paths (k, 2) -> ``(kind, xy)``: one vertex is a point, a path ending where it
    started (or flagged closed) a contour, anything else an open polyline.

    Consecutive repeated vertices are dropped. Paths that collapse to a single
    vertex but were drawn as lines become points.
    """
    out = []
    for i, p in enumerate(paths):
        p = np.asarray(p, float).reshape(-1, 2)
        if len(p) > 1:
            keep = np.r_[True, np.any(np.abs(np.diff(p, axis=0)) > 0, axis=1)]
            p = p[keep]
        closed = bool(closed_flags[i]) if closed_flags is not None else False
        if len(p) > 1 and np.hypot(*(p[-1] - p[0])) <= CLOSE_TOL_MM:
            closed = True
            p = p[:-1] if len(p) > 2 else p
        if len(p) == 1:
            out.append(("point", p[0]))
        elif closed and len(p) >= 3:
            out.append(("contour", p))
        else:
            out.append(("polyline", p))
    return out


def marked_strokes(job: Job, tour: Tour):
    """Yield ``(stroke index, kind, xy_mm in marking order)`` along a tour.

    Open strokes run reversed where the tour says so; a contour starts at its
    entry vertex (its closing vertex is not repeated).
    """
    for s, rev, e in zip(tour.order, tour.reverse, tour.entry):
        st = job.strokes[int(s)]
        p = np.asarray(st.xy_mm)
        if st.kind == "polyline" and rev:
            p = p[::-1]
        elif st.kind == "contour":
            p = np.roll(p, -int(e), axis=0)
        yield int(s), st.kind, p


def fmt_num(v: float, decimals: int = 9) -> str:
    """A coordinate as short text that reads back to within ``0.5 * 10**-decimals``."""
    s = f"{round(float(v), decimals):.{decimals}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def decode_text(data: bytes, what: str, source=None) -> str:
    """Bytes of a text format as str; binary or non-text data is a user error."""
    if b"\x00" in data[:4096]:
        raise MarkcalError(f"not a text {what} file (binary data)", source)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        try:
            return data.decode("latin-1")
        except UnicodeDecodeError:                   # pragma: no cover - latin-1 decodes anything
            raise MarkcalError(f"not a text {what} file", source) from None


def build_job(strokes, source=None) -> Job:
    """:func:`make_job` with the format's own message when nothing was drawn."""
    if not strokes:
        raise MarkcalError("no geometry: the job has no strokes the path flow can mark", source)
    return make_job(strokes, source)


#: writers of the job formats that carry an order: format -> (module, function)
_WRITERS = {"dxf": ("job_dxf", "write_dxf"), "svg": ("job_svg", "write_svg"),
            "hpgl": ("job_hpgl", "write_hpgl"), "gcode": ("job_gcode", "write_gcode")}


def job_writer(fmt: str):
    """The function writing a job back in format ``fmt`` (``writer(job_file, tour) -> bytes | str``), or None."""
    if fmt not in _WRITERS:
        return None
    import importlib
    mod, fn = _WRITERS[fmt]
    return getattr(importlib.import_module(f"markcal.stages.{mod}"), fn)
