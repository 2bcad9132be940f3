"""Files of the path flow: the ordered job (same format as the input, and ordered.json), summary.json,
report.html."""
from __future__ import annotations

import copy
import csv
import io
import os

import numpy as np

from markcal.stages.errors import MarkcalError

from .files import atomic_write_bytes, atomic_write_text, start_outputs, write_json

#: writers of the job formats that carry an order: format -> (module, function)
_WRITERS = {"dxf": ("job_dxf", "write_dxf"), "svg": ("job_svg", "write_svg"),
            "hpgl": ("job_hpgl", "write_hpgl"), "gcode": ("job_gcode", "write_gcode")}


def ordered_job_bytes(result) -> bytes:
    """The job file in marking order in the input's own format (DXF, SVG, HPGL, G-code)."""
    import importlib
    mod, fn = _WRITERS[result.inp.fmt]
    out = getattr(importlib.import_module(f"markcal.stages.{mod}"), fn)(result.inp, result.tour)
    return out if isinstance(out, bytes) else out.encode("utf-8")


def ordered_csv_text(result) -> str:
    """The CSV job's rows in marking order, same header and fields as the input."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    header, rows = result.inp.payload
    w.writerow(header)
    for s in result.tour.order:
        w.writerow(rows[int(s)])
    return buf.getvalue()


def ordered_json_doc(result) -> dict:
    """The JSON job with its strokes in marking order.

    Every stroke keeps its keys; ``xy_mm`` is rewritten in marking direction
    (an open stroke run backwards is reversed; a contour starts at its entry
    vertex), and ``source_index`` (position in the input), ``reversed`` (open
    strokes) and ``entry_vertex`` (contours, index into the input vertices) are added.
    """
    job = result.inp.job
    if result.inp.fmt == "json":
        document = result.inp.payload
    else:
        document = {"units": "mm", "name": os.path.basename(result.source),
                    "strokes": [{"kind": st.kind} for st in job.strokes]}
    doc = {k: copy.deepcopy(v) for k, v in document.items() if k != "strokes"}
    src = document["strokes"]
    strokes = []
    t = result.tour
    for s, rev, e in zip(t.order, t.reverse, t.entry):
        s = int(s)
        d = copy.deepcopy(src[s])
        st = job.strokes[s]
        p = np.asarray(st.xy_mm)
        if st.kind == "point":
            xy = p[0].tolist()
        elif st.kind == "polyline":
            xy = (p[::-1] if rev else p).tolist()
            d["reversed"] = bool(rev)
        else:
            xy = np.roll(p, -int(e), axis=0).tolist()
            d["entry_vertex"] = int(e)
        d["xy_mm"] = xy
        d["source_index"] = s
        if result.inp.groups and result.inp.groups[s]:
            d["group"] = result.inp.groups[s]
        strokes.append(d)
    doc["strokes"] = strokes
    return doc


def ordered_names(result) -> list:
    """File names of the ordered job: ``ordered.csv``; ``ordered.json``; or ``ordered.<ext>`` and ``ordered.json``."""
    if result.inp.fmt == "csv":
        return ["ordered.csv"]
    if result.inp.fmt in _WRITERS:
        ext = os.path.splitext(result.source)[1].lower()
        return [f"ordered{ext}", "ordered.json"]
    return ["ordered.json"]


def write_path_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of a path flow result into ``out_dir``; summary.json last.

    Returns
    -------
    dict
        Output name -> path.
    """
    names = ordered_names(result)
    p = {name: os.path.join(out_dir, name) for name in names + ["report.html", "summary.json"]}
    src = os.path.abspath(result.source)
    for name, path in p.items():
        if os.path.abspath(path) == src:
            raise MarkcalError(f"--out would overwrite the input job ({name})", result.source)
    start_outputs(out_dir)
    if result.inp.fmt == "csv":
        atomic_write_text(p["ordered.csv"], ordered_csv_text(result))
    else:
        write_json(p["ordered.json"], ordered_json_doc(result))
    if result.inp.fmt in _WRITERS:
        atomic_write_bytes(p[names[0]], ordered_job_bytes(result))
    if report:
        from .path_report import render_path_report_html
        atomic_write_text(p["report.html"], render_path_report_html(result))
    else:
        p.pop("report.html")
    write_json(p["summary.json"], result.summary)
    return p


__all__ = ["write_path_outputs", "ordered_csv_text", "ordered_json_doc", "ordered_job_bytes", "ordered_names"]
