"""Files of the path flow: the ordered job (same format as the input), summary.json, report.html."""
from __future__ import annotations

import copy
import csv
import io
import os

import numpy as np

from markcal.stages.errors import MarkcalError

from .files import atomic_write_text, start_outputs, write_json


def ordered_csv_text(result) -> str:
    """The CSV job's rows in marking order, same header and fields as the input."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(result.inp.csv_header)
    for s in result.tour.order:
        w.writerow(result.inp.csv_rows[int(s)])
    return buf.getvalue()


def ordered_json_doc(result) -> dict:
    """The JSON job with its strokes in marking order.

    Every stroke keeps its keys; ``xy_mm`` is rewritten in marking direction
    (an open stroke run backwards is reversed; a contour starts at its entry
    vertex), and ``source_index`` (position in the input), ``reversed`` (open
    strokes) and ``entry_vertex`` (contours, index into the input vertices) are added.
    """
    doc = {k: copy.deepcopy(v) for k, v in result.inp.document.items() if k != "strokes"}
    src = result.inp.document["strokes"]
    job = result.inp.job
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
        strokes.append(d)
    doc["strokes"] = strokes
    return doc


def write_path_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of a path flow result into ``out_dir``; summary.json last.

    Returns
    -------
    dict
        Output name -> path.
    """
    ordered = "ordered.csv" if result.inp.fmt == "csv" else "ordered.json"
    p = {name: os.path.join(out_dir, name) for name in (ordered, "report.html", "summary.json")}
    src = os.path.abspath(result.source)
    for name, path in p.items():
        if os.path.abspath(path) == src:
            raise MarkcalError(f"--out would overwrite the input job ({name})", result.source)
    start_outputs(out_dir)
    if result.inp.fmt == "csv":
        atomic_write_text(p[ordered], ordered_csv_text(result))
    else:
        write_json(p[ordered], ordered_json_doc(result))
    if report:
        from .path_report import render_path_report_html
        atomic_write_text(p["report.html"], render_path_report_html(result))
    else:
        p.pop("report.html")
    write_json(p["summary.json"], result.summary)
    return p


__all__ = ["write_path_outputs", "ordered_csv_text", "ordered_json_doc"]
