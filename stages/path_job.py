"""Marking jobs for the path flow: strokes, jump cost and timing, ordered tours.

A job is a sequence of strokes in the galvo field (mm): a point, an open
polyline (markable either way) or a closed contour (entered, and left, at
any of its vertices). A *tour* says in which order the strokes are marked,
which way each open stroke runs and at which vertex each closed contour is
entered; the laser returns to where it started (paper 002: the tour is closed).

Everything here is pure: arrays and small frozen dataclasses, no file I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError

__all__ = ["KINDS", "Stroke", "Job", "Timing", "Tour", "make_job", "endpoints", "tour_points",
           "jump_lengths_mm", "jump_cost", "tour_cost", "tour_stats", "duplicate_groups", "input_tour"]

#: stroke kinds and the fewest vertices each needs
KINDS = {"point": 1, "polyline": 2, "contour": 3}
POINT, POLYLINE, CONTOUR = 0, 1, 2
_KIND_CODE = {"point": POINT, "polyline": POLYLINE, "contour": CONTOUR}


@dataclass(frozen=True, eq=False)
class Stroke:
    """One stroke of a marking job.

    Attributes
    ----------
    kind : str
        ``"point"``, ``"polyline"`` (open, either direction) or ``"contour"`` (closed).
    xy_mm : ndarray, shape (k, 2)
        Vertices in the galvo field frame, mm. A contour's closing vertex is not
        repeated (the segment from the last back to the first vertex is implied).
    """

    kind: str
    xy_mm: np.ndarray

    @property
    def length_mm(self) -> float:
        """Marked length (laser on), mm; 0 for a point."""
        if self.kind == "point":
            return 0.0
        p = self.xy_mm
        if self.kind == "contour":
            p = np.vstack([p, p[:1]])
        return float(np.hypot(*np.diff(p, axis=0).T).sum())


@dataclass(frozen=True, eq=False)
class Job:
    """A marking job: strokes in input order (mm, galvo field frame)."""

    strokes: tuple

    @property
    def n(self) -> int:
        return len(self.strokes)

    @property
    def kinds(self) -> np.ndarray:
        """Kind code per stroke: 0 point, 1 polyline, 2 contour."""
        return np.array([_KIND_CODE[s.kind] for s in self.strokes], dtype=np.int64)

    @property
    def mark_length_mm(self) -> float:
        return float(sum(s.length_mm for s in self.strokes))

    def contour_vertices(self):
        """Padded vertices of the contours: (ids (c,), vertices (c, vmax, 2), counts (c,))."""
        ids = np.flatnonzero(self.kinds == CONTOUR)
        vmax = max([len(self.strokes[i].xy_mm) for i in ids], default=1)
        v = np.zeros((len(ids), vmax, 2))
        cnt = np.zeros(len(ids), np.int64)
        for k, i in enumerate(ids):
            p = self.strokes[i].xy_mm
            v[k, :len(p)] = p
            v[k, len(p):] = p[-1]          # pad with a real vertex: never a better entry than it
            cnt[k] = len(p)
        return ids, v, cnt


@dataclass(frozen=True)
class Timing:
    """Galvo timing used for the jump cost and the time estimates.

    A jump of length d takes ``d / jump_speed_mm_s + settle_s`` (no settle for a
    zero-length jump); marking takes ``length / mark_speed_mm_s`` plus
    ``point_dwell_s`` per point. ``metric`` is what the optimiser minimises:
    ``"distance"`` (jump length, mm) or ``"time"`` (jump time, s).
    """

    metric: str = "distance"
    jump_speed_mm_s: float = 3000.0
    settle_s: float = 200e-6
    mark_speed_mm_s: float = 1000.0
    point_dwell_s: float = 500e-6

    def __post_init__(self):
        if self.metric not in ("distance", "time"):
            raise MarkcalError(f"unknown jump cost metric {self.metric!r} (distance or time)")
        for k in ("jump_speed_mm_s", "mark_speed_mm_s"):
            if not 0 < getattr(self, k) <= 1e9:
                raise MarkcalError(f"{k} must be > 0 and at most 1e9 (got {getattr(self, k)})")
        if not (0 <= self.settle_s <= 3600 and 0 <= self.point_dwell_s <= 3600):
            raise MarkcalError("settle_s and point_dwell_s must be >= 0 and at most an hour")

    @property
    def cost_coefficients(self) -> tuple:
        """(a, b): the jump cost is ``a * d + b * (d > 0)``."""
        if self.metric == "distance":
            return 1.0, 0.0
        return 1.0 / self.jump_speed_mm_s, float(self.settle_s)


@dataclass(frozen=True, eq=False)
class Tour:
    """A marking order.

    Attributes
    ----------
    order : ndarray of int, shape (n,)
        Stroke indices in marking order.
    reverse : ndarray of bool, shape (n,)
        Per position: the open stroke runs from its last vertex to its first.
    entry : ndarray of int, shape (n,)
        Per position: the vertex a contour is entered (and left) at; 0 otherwise.
    """

    order: np.ndarray
    reverse: np.ndarray
    entry: np.ndarray


# ----------------------------------------------------------------------------- building

#: largest coordinate of a job (mm): point jobs also carry TSPLIB boards, whose unit-less coordinates reach
#: ~1e5; the CAD readers (DXF, SVG, HPGL, G-code) hold their files to the physical ±10 m of
#: :mod:`markcal.stages.limits`
MAX_ABS_MM = 1e7


def check_number_leaves(xy, what: str, source=None) -> None:
    """Refuse coordinates given as strings, booleans or anything but JSON numbers (nested lists)."""
    stack = [xy]
    while stack:
        o = stack.pop()
        if isinstance(o, (list, tuple)):
            stack.extend(o)
        elif isinstance(o, bool) or not isinstance(o, (int, float)):
            raise MarkcalError(f"{what}: coordinates must be numbers, not {type(o).__name__} {o!r}", source)


def make_job(strokes, source=None) -> Job:
    """Check strokes and build a :class:`Job`.

    Parameters
    ----------
    strokes : iterable of (kind, xy)
        ``kind`` in :data:`KINDS`; ``xy`` array-like (k, 2) or (2,) for a point, mm.
    source : path, optional
        Named in errors.

    Raises
    ------
    MarkcalError
        Empty job, unknown kind, non-finite coordinates, too few vertices.
    """
    out = []
    for i, (kind, xy) in enumerate(strokes):
        if kind not in KINDS:
            raise MarkcalError(f"stroke {i}: unknown kind {kind!r} (point, polyline or contour)", source)
        try:
            p = np.asarray(xy, dtype=float).reshape(-1, 2)
        except (TypeError, ValueError):
            raise MarkcalError(f"stroke {i} ({kind}): coordinates must be pairs of numbers (x_mm, y_mm)",
                               source) from None
        if not np.all(np.isfinite(p)):
            raise MarkcalError(f"stroke {i} ({kind}): NaN or infinite coordinate", source)
        if np.abs(p).max(initial=0.0) > MAX_ABS_MM:
            raise MarkcalError(f"stroke {i} ({kind}): coordinate {np.abs(p).max():g} mm beyond ±{MAX_ABS_MM:g} mm",
                               source)
        if kind == "contour" and len(p) > 1 and np.array_equal(p[0], p[-1]):
            p = p[:-1]                              # closing vertex written out
        if kind == "point" and len(p) != 1:
            raise MarkcalError(f"stroke {i} (point): needs exactly 1 vertex, has {len(p)}", source)
        if len(p) < KINDS[kind]:
            raise MarkcalError(f"stroke {i} ({kind}): needs at least {KINDS[kind]} vertices, has {len(p)}",
                               source)
        p.setflags(write=False)
        out.append(Stroke(kind, p))
    if not out:
        raise MarkcalError("the job has no strokes", source)
    return Job(tuple(out))


def endpoints(job: Job) -> tuple:
    """First and last vertex of every stroke (contours: first vertex twice), mm, shapes (n, 2)."""
    a = np.array([s.xy_mm[0] for s in job.strokes], dtype=float).reshape(-1, 2)
    b = np.array([s.xy_mm[0] if s.kind == "contour" else s.xy_mm[-1] for s in job.strokes],
                 dtype=float).reshape(-1, 2)
    return a, b


def input_tour(job: Job) -> Tour:
    """The job as given: input order, input directions, contours entered at their first vertex."""
    n = job.n
    return Tour(np.arange(n), np.zeros(n, bool), np.zeros(n, np.int64))


def tour_points(job: Job, tour: Tour) -> tuple:
    """Entry and exit point of each position of a tour, mm, shapes (n, 2)."""
    a, b = endpoints(job)
    o = tour.order
    entry = np.where(tour.reverse[:, None], b[o], a[o])
    exit_ = np.where(tour.reverse[:, None], a[o], b[o])
    cont = job.kinds[o] == CONTOUR
    if cont.any():
        v = np.array([job.strokes[s].xy_mm[e] for s, e in zip(o[cont], tour.entry[cont])]).reshape(-1, 2)
        entry[cont] = v
        exit_[cont] = v
    return entry, exit_


def jump_lengths_mm(job: Job, tour: Tour) -> np.ndarray:
    """Length of each jump (exit of position k to entry of k+1, the last one back to the start), mm."""
    entry, exit_ = tour_points(job, tour)
    return np.hypot(*(np.roll(entry, -1, axis=0) - exit_).T)


def jump_cost(d_mm, timing: Timing):
    """Cost of jumps of length ``d_mm`` under ``timing.metric`` (mm or s)."""
    a, b = timing.cost_coefficients
    d = np.asarray(d_mm, dtype=float)
    return a * d + b * (d > 0)


def tour_cost(job: Job, tour: Tour, timing: Timing) -> float:
    """Total jump cost of a closed tour (mm or s)."""
    return float(jump_cost(jump_lengths_mm(job, tour), timing).sum())


def tour_stats(job: Job, tour: Tour, timing: Timing) -> dict:
    """Jump length (mm), jump count, estimated jump, mark and total time (s) of a closed tour."""
    d = jump_lengths_mm(job, tour)
    nz = d > 0
    jump_t = float((d[nz] / timing.jump_speed_mm_s).sum() + timing.settle_s * nz.sum())
    n_points = int((job.kinds == POINT).sum())
    mark_t = job.mark_length_mm / timing.mark_speed_mm_s + timing.point_dwell_s * n_points
    return {"jump_length_mm": float(d.sum()), "n_jumps": int(nz.sum()), "jump_time_s": jump_t,
            "mark_time_s": float(mark_t), "time_s": float(jump_t + mark_t)}


def check_tour(job: Job, tour: Tour) -> None:
    """Raise ``ValueError`` unless ``tour`` visits every stroke once with valid entries."""
    n = job.n
    if sorted(tour.order.tolist()) != list(range(n)):
        raise ValueError("tour is not a permutation of the strokes")
    for s, e in zip(tour.order, tour.entry):
        if not 0 <= e < len(job.strokes[s].xy_mm):
            raise ValueError("entry vertex out of range")


def duplicate_groups(job: Job, tol_mm: float = 1e-9) -> list:
    """Groups (lists of stroke indices, input order) of strokes that are the same stroke.

    Same kind and the same vertices within ``tol_mm``; an open stroke also
    matches its reverse, a contour any rotation or reversal of itself.
    """
    def key(s):
        p = np.round(np.asarray(s.xy_mm) / max(tol_mm, 1e-12)).astype(np.int64) if tol_mm > 0 else s.xy_mm
        rows = [tuple(r) for r in p.tolist()]
        if s.kind == "polyline":
            rows = min(rows, rows[::-1])
        elif s.kind == "contour":
            cands = []
            for seq in (rows, rows[::-1]):
                k = seq.index(min(seq))
                cands.append(seq[k:] + seq[:k])
            rows = min(cands)
        return (s.kind, tuple(rows))

    groups = {}
    for i, s in enumerate(job.strokes):
        groups.setdefault(key(s), []).append(i)
    return [g for g in groups.values() if len(g) > 1]
