"""Files of the servo flow: metrics.csv, traces.csv, moves.csv (drive logs), summary.json (last), report.html."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from markcal.pipeline.flows.servo import METRIC_COLUMNS, ServoResult
from markcal.stages.servo_log import MOVE_COLUMNS
from markcal.reports.files import OutputFolder
from markcal.reports.servo_report import servo_report_html

#: traces.csv columns
TRACE_COLUMNS = ("case", "controller", "amplitude_mm", "frequency_hz", "t_s", "ref_mm", "pos_mm", "err_um")


def metrics_table(result: ServoResult) -> dict:
    """metrics.csv as columns (see ``METRIC_COLUMNS``)."""
    return {c: [getattr(r, c) for r in result.runs] for c in METRIC_COLUMNS}


def traces_table(result: ServoResult, max_points: int = 1000) -> dict:
    """traces.csv as columns: each run decimated to at most ``max_points`` samples.

    Moves: the whole record; sinusoids: the evaluated (last) period; a drive log:
    the whole log once (at most 10,000 samples).
    """
    cols = {c: [] for c in TRACE_COLUMNS}
    runs = result.runs
    if result.mode == "trace":
        runs = [replace(result.runs[0], window=slice(None))]
        max_points = max(max_points, 10000)
    for r in runs:
        idx = np.arange(len(r.sim.t_s))[r.window]
        step = max(1, int(np.ceil(len(idx) / max_points)))
        idx = idx[::step]
        n = len(idx)
        cols["case"] += [r.case] * n
        cols["controller"] += [r.controller] * n
        cols["amplitude_mm"] += [r.amplitude_mm] * n
        cols["frequency_hz"] += [r.frequency_hz] * n
        cols["t_s"] += list(r.sim.t_s[idx])
        cols["ref_mm"] += list(r.sim.ref_mm[idx])
        cols["pos_mm"] += list(r.sim.pos_mm[idx])
        cols["err_um"] += list(r.sim.err_mm[idx] * 1e3)
    return cols


def write_servo_outputs(result: ServoResult, out_dir, report: bool = True) -> dict:
    """Write all outputs atomically; ``summary.json`` last. Returns name -> path."""
    out = OutputFolder(out_dir)
    out.csv("metrics.csv", metrics_table(result))
    out.csv("traces.csv", traces_table(result))
    if result.trace is not None and result.trace.move_cols is not None:
        mc = result.trace.move_cols
        out.csv("moves.csv", {c: (mc[c].astype(int) if c == "move" else mc[c]) for c in MOVE_COLUMNS})
    if report:
        out.text("report.html", servo_report_html(result))
    return out.finish(result.summary)
