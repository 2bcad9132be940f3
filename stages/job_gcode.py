"""G-code marking jobs: read the cuts as strokes, write the job back in a new order.

Reading follows the laser conventions of GRBL-like controllers: ``G0`` is a
travel; ``G1``/``G2``/``G3`` cut while the laser is on, which ``M3``/``M4``
switch on and ``M5`` or ``S0`` switch off (``M3`` on a router's spindle reads
the same way); ``G20``/``G21`` inch/mm, ``G90``/``G91`` absolute/relative,
``G90.1``/``G91.1`` arc centre mode, arcs by ``I J`` or ``R`` flattened to a
chordal tolerance. A stroke is a run of cuts with one laser state, feed and
power; a run ending where it started is a closed contour.

Writing keeps every line that is not an XY move (header, footer and each
stroke's lead-in such as a plunge and lead-out such as a lift) and rewrites the
travels and cuts in the new order, in the file's units.
"""
from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .job_formats import JobFile, build_job, decode_text, flatten_arc, fmt_num, marked_strokes, paths_to_strokes

__all__ = ["read_gcode", "write_gcode", "GcodePayload"]

_COMMENT = re.compile(r"\([^)]*\)|;.*$")
_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
#: G codes read without effect on the geometry
_PASSIVE_G = {4, 17, 40, 49, 54, 55, 56, 57, 58, 59, 61, 64, 80, 93, 94}
LASER_CONVENTION = "M3 or M4 (with S > 0 when S is given) before G1/G2/G3 cuts, M5 or S0 to switch off"


@dataclass(eq=False)
class _Stroke:
    path: list                 # xy_mm vertices, the start first
    first: int                 # line index of the first cut
    last: int                  # line index of the last cut
    factor: float              # mm per file unit when it was cut
    relative: bool             # G91 in effect
    f: float | None
    s: float | None


@dataclass(frozen=True, eq=False)
class GcodePayload:
    """What :func:`write_gcode` needs: the lines and, per stroke, lead-in / lead-out lines."""

    header: tuple
    footer: tuple
    leads: tuple               # per stroke: tuple of text lines
    tails: tuple
    factors: tuple             # mm per file unit, per stroke
    feeds: tuple               # (F, S) per stroke, None where not set
    g0: str                    # "G0" or "G00" as the file writes it
    g1: str
    travel_suffix: str         # e.g. " S0" when the file switched off by S0 on travels


def _words(code: str, lineno: int, source):
    words = _WORD.findall(code)
    rest = _WORD.sub("", code).strip()
    if rest and rest != "%":
        raise MarkcalError(f"line {lineno}: cannot read {rest[:20]!r} (truncated or not G-code?)", source)
    return [(k.upper(), float(v)) for k, v in words]


def read_gcode(data: bytes, tolerance_mm: float = 0.01, source=None) -> JobFile:
    """Read a G-code job (bytes of the file).

    Parameters
    ----------
    data : bytes
    tolerance_mm : float
        Chordal tolerance of flattened arcs, mm.
    source : path, optional
        Named in errors.

    Raises
    ------
    MarkcalError
        Not text, unreadable words, no cut moves, no laser-on command, bad arcs.
    """
    lines = decode_text(data, "G-code", source).splitlines()
    factor, relative, arc_abs = 1.0, False, False
    motion, laser, s_val, f_val, epoch = None, False, None, None, 0
    saw_units, saw_on, saw_cut_move, saw_arc = False, False, False, False
    x = y = 0.0
    role = [None] * len(lines)          # "cut", ("travel", residual), "off", or None (other)
    strokes, cur, key = [], None, None
    unsupported = Counter()
    g0_text, g1_text, travel_s0 = "G0", "G1", 0
    for i, raw in enumerate(lines):
        code = _COMMENT.sub("", raw).strip()
        if not code:
            continue
        words = _words(code, i + 1, source)
        letters = {k for k, _ in words}
        was_on = laser and (s_val is None or s_val > 0)
        for k, v in words:
            if k == "G":
                g = round(v, 1)
                if g in (0, 1, 2, 3):
                    motion = int(g)
                    m = re.search(r"G\s*0*%d(?!\d)" % int(g), code, re.I)
                    if m and g in (0, 1):
                        txt = m.group(0).upper().replace(" ", "")
                        if g == 0:
                            g0_text = txt
                        else:
                            g1_text = txt
                elif g == 20:
                    factor, saw_units = 25.4, True
                elif g == 21:
                    factor, saw_units = 1.0, True
                elif g == 90:
                    relative = False
                elif g == 91:
                    relative = True
                elif g == 90.1:
                    arc_abs = True
                elif g == 91.1:
                    arc_abs = False
                elif int(g) != g or int(g) not in _PASSIVE_G:
                    unsupported[f"G{fmt_num(g)}"] += 1
            elif k == "M":
                if v in (3, 4):
                    laser = True
                elif v == 5:
                    laser = False
            elif k == "S":
                s_val = v
            elif k == "F":
                f_val = v
        on = laser and (s_val is None or s_val > 0)
        saw_on |= on
        if on and not was_on:
            epoch += 1
        if not on and was_on:
            role[i] = "off"
        moves = letters & {"X", "Y", "I", "J", "R"} if motion in (2, 3) else letters & {"X", "Y"}
        if not moves:
            continue
        if motion is None:
            raise MarkcalError(f"line {i + 1}: X/Y without a motion mode (G0/G1/G2/G3)", source)
        w = dict(words)
        nx = (x + w.get("X", 0.0) * factor) if relative else (w["X"] * factor if "X" in w else x)
        ny = (y + w.get("Y", 0.0) * factor) if relative else (w["Y"] * factor if "Y" in w else y)
        if motion == 0 or not on:
            if motion != 0:
                saw_cut_move = True
                travel_s0 += int("S" in letters and s_val == 0)
            residual = _WORD.sub(lambda mm: "" if mm.group(1).upper() in "XYIJRG" else mm.group(0), code).strip()
            role[i] = ("travel", residual)
            cur = None
            x, y = nx, ny
            continue
        saw_cut_move = True
        if cur is None or key != (epoch, f_val, s_val):
            cur = _Stroke([(x, y)], i, i, factor, relative, f_val, s_val)
            strokes.append(cur)
            key = (epoch, f_val, s_val)
        if motion == 1:
            cur.path.append((nx, ny))
        else:
            saw_arc = True
            cur.path.extend(_arc(x, y, nx, ny, w, factor, relative or not arc_abs, motion == 2,
                                 tolerance_mm, i + 1, source))
        cur.last = i
        role[i] = "cut"
        x, y = nx, ny
    if not saw_cut_move:
        raise MarkcalError("no geometry: no G1/G2/G3 cut moves", source)
    if not saw_on:
        raise MarkcalError(f"no laser-on command: expected the convention {LASER_CONVENTION}", source)
    if not strokes:
        raise MarkcalError("no geometry: no cut moves while the laser is on", source)
    job = build_job(paths_to_strokes([s.path for s in strokes]), source)
    notes = []
    if not saw_units:
        notes.append("no G20/G21 in the G-code: read as mm (G21)")
    if saw_arc:
        notes.append("G2/G3 arcs are written back as G1 chords within --tolerance-mm")
    payload = _layout(lines, role, strokes, g0_text, g1_text, " S0" if travel_s0 else "")
    return JobFile(job, "gcode", ("",) * job.n, dict(unsupported), tuple(notes), payload)


def _arc(x, y, nx, ny, w, factor, ij_incremental, clockwise, tol, lineno, source):
    """Flattened vertices of a G2 (clockwise) / G3 arc from (x, y) to (nx, ny), mm."""
    if w.get("P", 1) != 1:
        raise MarkcalError(f"line {lineno}: arcs of several turns (P = {w['P']:g}) are not supported", source)
    if "R" in w:
        r = abs(w["R"]) * factor
        dx, dy = nx - x, ny - y
        q = math.hypot(dx, dy)
        if q == 0 or q > 2 * r * (1 + 1e-9):
            raise MarkcalError(f"line {lineno}: arc radius R too small for its end point", source)
        h = math.sqrt(max(r * r - q * q / 4, 0.0))
        # the centre on the side that gives the short arc for R > 0, the long one for R < 0
        sgn = (1 if clockwise else -1) * (1 if w["R"] > 0 else -1)
        cx, cy = x + dx / 2 + sgn * h * dy / q, y + dy / 2 - sgn * h * dx / q
    else:
        i, j = w.get("I", 0.0) * factor, w.get("J", 0.0) * factor
        cx, cy = (x + i, y + j) if ij_incremental else (i, j)
    r0 = math.hypot(x - cx, y - cy)
    r1 = math.hypot(nx - cx, ny - cy)
    if r0 == 0 or abs(r0 - r1) > max(1e-3, 1e-3 * r0):
        raise MarkcalError(f"line {lineno}: arc end point is not on the arc ({r0:.6g} vs {r1:.6g} mm "
                           "from the centre)", source)
    a0 = math.atan2(y - cy, x - cx)
    a1 = math.atan2(ny - cy, nx - cx)
    sweep = (a1 - a0) % (2 * math.pi)
    if clockwise:
        sweep = sweep - 2 * math.pi
    if abs(sweep) < 1e-12:
        sweep = -2 * math.pi if clockwise else 2 * math.pi      # a full circle
    v = flatten_arc((cx, cy), r0, a0, sweep, tol)
    v[-1] = (nx, ny)
    return [tuple(p) for p in v]


def _layout(lines, role, strokes, g0, g1, travel_suffix) -> GcodePayload:
    """Split the file's other lines into header, per-stroke lead-in / lead-out, and footer."""
    def kept(a, b):
        out = []
        for i in range(a, b):
            r = role[i]
            if isinstance(r, tuple):
                if r[1] and r[1].upper() not in (g0, g1, "G0", "G1", "G00", "G01"):
                    out.append(r[1])
            elif r != "cut":
                out.append(lines[i])
        return out

    def travels(a, b):
        return [i for i in range(a, b) if isinstance(role[i], tuple)]

    first = strokes[0].first
    tr = travels(0, first)
    header = lines[:tr[-1]] if tr else []
    leads = [kept(tr[-1] + 1 if tr else 0, first)]
    tails = []
    for a, b in zip(strokes[:-1], strokes[1:]):
        tr = travels(a.last + 1, b.first)
        if tr:
            tails.append(kept(a.last + 1, tr[0]))
            leads.append(kept(tr[0] + 1, b.first))
        else:
            offs = [i for i in range(a.last + 1, b.first) if role[i] == "off"]
            cut = offs[-1] + 1 if offs else a.last + 1
            tails.append(kept(a.last + 1, cut))
            leads.append(kept(cut, b.first))
    end = strokes[-1].last + 1
    tr = travels(end, len(lines))
    if tr:
        tails.append(kept(end, tr[0]))
        footer = lines[tr[0]:]
    else:
        common = Counter(tuple(t) for t in tails).most_common(1)
        tails.append(list(common[0][0]) if common else [])
        footer = lines[end:]
    return GcodePayload(tuple(header), tuple(footer), tuple(map(tuple, leads)), tuple(map(tuple, tails)),
                        tuple(s.factor for s in strokes),
                        tuple((s.f, s.s) for s in strokes), g0, g1, travel_suffix)


_DIST = re.compile(r"G\s*0*9([01])(?![\d.])", re.I)


def _distance_mode(lines, relative: bool) -> bool:
    """Whether G91 is in effect after ``lines`` (starting in ``relative``)."""
    for line in lines:
        for m in _DIST.finditer(_COMMENT.sub("", line)):
            relative = m.group(1) == "1"
    return relative


def write_gcode(jf: JobFile, tour) -> str:
    """The G-code job in the order of ``tour``: header, then per stroke a travel to its entry,
    its lead-in lines, its cuts (in the file's units, absolute), its lead-out lines; the footer.

    Travels and cuts are written absolute: where the kept lines leave ``G91`` in effect they are
    written between ``G90`` and ``G91``.
    """
    p: GcodePayload = jf.payload
    out = list(p.header)
    rel = _distance_mode(p.header, False)
    for s, kind, xy in marked_strokes(jf.job, tour):
        f = p.factors[s]
        if kind == "contour":
            xy = np.vstack([xy, xy[:1]])
        if rel:
            out.append("G90")
        out.append(f"{p.g0} X{fmt_num(xy[0, 0] / f)} Y{fmt_num(xy[0, 1] / f)}{p.travel_suffix}")
        if rel:
            out.append("G91")
        out.extend(p.leads[s])
        rel = _distance_mode(p.leads[s], rel)
        if rel:
            out.append("G90")
        feed, power = p.feeds[s]
        extra = (f" F{fmt_num(feed)}" if feed is not None else "") + (f" S{fmt_num(power)}" if power is not None
                                                                      else "")
        pts = xy[1:] if len(xy) > 1 else xy
        for k, q in enumerate(pts):
            out.append(f"{p.g1} X{fmt_num(q[0] / f)} Y{fmt_num(q[1] / f)}{extra if k == 0 else ''}")
        if rel:
            out.append("G91")
        out.extend(p.tails[s])
        rel = _distance_mode(p.tails[s], rel)
    out.extend(p.footer)
    return "\n".join(out) + "\n"
