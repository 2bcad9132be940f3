"""HPGL / PLT marking jobs: pen-down runs as strokes, written back in a new order.

Reads ``IN``, ``SP`` (the pen is the stroke's group), ``PU``, ``PD``, ``PA`` and
``PR`` with plotter units of 0.025 mm (40 per mm). Other instructions are
listed as unsupported and kept: before the first stroke in the header, between
strokes as the next stroke's lead-in, after the last in the footer. ``SC``
(user units) changes what the numbers mean and is refused.
"""
from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .job_formats import JobFile, build_job, decode_text, fmt_num, marked_strokes, paths_to_strokes

__all__ = ["read_hpgl", "write_hpgl", "UNITS_PER_MM", "HpglPayload"]

UNITS_PER_MM = 40.0
_INSTR = re.compile(r"([A-Za-z]{2})([^A-Za-z;]*)")
_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")


@dataclass(frozen=True, eq=False)
class HpglPayload:
    header: tuple              # instruction texts
    footer: tuple
    leads: tuple               # per stroke: instruction texts before it (not moves)
    pens: tuple                # per stroke: pen number (None: no SP seen)


def _split(text: str, source):
    """Instructions as (mnemonic, parameter text). Labels (LB) run to the terminator."""
    out = []
    pos = 0
    text = text.replace("\x1b", "")
    while pos < len(text):
        ch = text[pos]
        if ch in " \t\r\n;,":
            pos += 1
            continue
        m = _INSTR.match(text, pos)
        if not m:
            raise MarkcalError(f"cannot read HPGL at character {pos} ({text[pos:pos + 12]!r})", source)
        mn = m.group(1).upper()
        if mn == "LB":                                  # label text up to ETX (chr 3)
            end = text.find("\x03", m.start(2))
            end = len(text) if end < 0 else end + 1
            out.append((mn, text[m.start(2):end]))
            pos = end
            continue
        out.append((mn, m.group(2)))
        pos = m.end()
    return out


def _numbers(mn, params, k, source):
    body = params.strip().strip(",").strip()
    if not body:
        return []
    parts = [p for p in re.split(r"[\s,]+", body) if p]
    if any(not _NUM.fullmatch(p) for p in parts):
        raise MarkcalError(f"instruction {k} ({mn}): parameters must be numbers ({body[:20]!r})", source)
    return [float(p) for p in parts]


def read_hpgl(data: bytes, tolerance_mm: float = 0.01, source=None) -> JobFile:
    """Read an HPGL/PLT job (bytes of the file); ``tolerance_mm`` is unused (lines only).

    Raises
    ------
    MarkcalError
        Not text, unreadable instruction, odd number of coordinates, ``SC``, no pen-down move.
    """
    text = decode_text(data, "HPGL", source)
    instr = _split(text, source)
    if not instr:
        raise MarkcalError("no geometry: no HPGL instructions", source)
    pen_down, absolute, pen = False, True, None
    x = y = 0.0
    paths, pens = [], []
    cur = None
    pending = []                            # instruction indices of passive instructions since the last move
    leads, header_end = [], None
    unsupported = Counter()
    last_draw = -1
    for k, (mn, params) in enumerate(instr):
        if mn in ("PU", "PD", "PA", "PR"):
            nums = _numbers(mn, params, k, source)
            if len(nums) % 2:
                raise MarkcalError(f"instruction {k} ({mn}): odd number of coordinates (truncated?)", source)
            if mn == "PU":
                pen_down = False
                cur = None
            elif mn == "PD":
                pen_down = True
            else:
                absolute = mn == "PA"
            for j in range(0, len(nums), 2):
                nx, ny = nums[j] / UNITS_PER_MM, nums[j + 1] / UNITS_PER_MM
                if not absolute:
                    nx, ny = x + nx, y + ny
                if pen_down:
                    if cur is None:
                        cur = [(x, y)]
                        paths.append(cur)
                        pens.append(pen)
                        leads.append(tuple(instr[i] for i in pending))
                        if header_end is None:
                            header_end = k
                        pending = []
                    cur.append((nx, ny))
                    last_draw = k
                x, y = nx, ny
            continue
        if mn == "SP":
            nums = _numbers(mn, params, k, source)
            pen = int(nums[0]) if nums else 0
            cur = None
            continue
        if mn == "IN":
            pen_down, absolute, cur = False, True, None
            x = y = 0.0
            continue
        if mn == "SC" and params.strip():
            raise MarkcalError("unsupported units: SC scales to user units (only plotter units, 40 per mm)",
                               source)
        unsupported[mn] += 1
        pending.append(k)
    if not paths:
        raise MarkcalError("no geometry: no pen-down (PD) moves", source)
    job = build_job(paths_to_strokes(paths), source)
    # header: every instruction before the first drawing move (the first lead-in with it);
    # footer: every instruction after the last drawing move
    header = [_text(m, p) for m, p in instr[:header_end]]
    footer = [_text(m, p) for m, p in instr[last_draw + 1:]]
    lead_txt = [()] + [tuple(_text(m, p) for m, p in ld) for ld in leads[1:]]
    groups = tuple("" if p is None else f"pen {p}" for p in pens)
    return JobFile(job, "hpgl", groups, dict(unsupported), (),
                   HpglPayload(tuple(header), tuple(footer), tuple(lead_txt), tuple(pens)))


def _text(mn, params):
    return mn + params.strip()


def write_hpgl(jf: JobFile, tour) -> str:
    """The HPGL job in the order of ``tour``: header, per stroke ``SP`` when the pen changes,
    its lead-in, ``PU`` to its entry and ``PD`` through its vertices (absolute, ``PA``); footer."""
    p: HpglPayload = jf.payload
    out = list(p.header) + ["PA"]
    pen = object()
    for s, kind, xy in marked_strokes(jf.job, tour):
        if kind == "contour":
            xy = np.vstack([xy, xy[:1]])
        if p.pens[s] is not None and p.pens[s] != pen:
            out.append(f"SP{p.pens[s]}")
            pen = p.pens[s]
        out.extend(p.leads[s])
        q = np.asarray(xy) * UNITS_PER_MM
        out.append(f"PU{fmt_num(q[0, 0])},{fmt_num(q[0, 1])}")
        rest = q[1:] if len(q) > 1 else q
        out.append("PD" + ",".join(f"{fmt_num(a)},{fmt_num(b)}" for a, b in rest))
    out.append("PU")
    out.extend(p.footer)
    return ";".join(out) + ";\n"
