"""Files of the path flow: the ordered job (same format as the input, and ordered.json), summary.json,
report.html."""
from __future__ import annotations

import copy
import csv
import io
import os

import numpy as np


from markcal.reports.files import OutputFolder
from markcal.reports.path_report import ordered_names, path_report_html
from markcal.stages.job_formats import job_writer

def ordered_job_bytes(result) -> bytes:
    """The job file in marking order in the input's own format (DXF, SVG, HPGL, G-code)."""
    out = job_writer(result.inp.fmt)(result.inp, result.tour)
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


def write_path_outputs(result, out_dir, report: bool = True) -> dict:
    """Write every output of a path flow result into ``out_dir``; summary.json last.

    Returns
    -------
    dict
        Output name -> path.
    """
    names = ordered_names(result)
    out = OutputFolder(out_dir)
    if result.inp.fmt == "csv":
        out.text("ordered.csv", ordered_csv_text(result))
    else:
        out.json("ordered.json", ordered_json_doc(result))
    if job_writer(result.inp.fmt) is not None:
        out.bytes(names[0], ordered_job_bytes(result))
    if report:
        out.text("report.html", path_report_html(result))
    return out.finish(result.summary)


__all__ = ["write_path_outputs", "ordered_csv_text", "ordered_json_doc", "ordered_job_bytes"]
