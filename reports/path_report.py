"""Self-contained HTML report of one path flow result (paper 002 Fig. 7: path and convergence).

Figures are drawn on matplotlib's Agg canvas and inlined as base64 PNG; the
module neither prints nor writes files.
"""
from __future__ import annotations

import os

import numpy as np

from markcal.reports.html import data_files_footer, esc, img, new_figure, num, page, png_b64, table
from markcal.stages.job_formats import job_writer
from markcal.stages.path_job import tour_points
from markcal.stages.stats import pct_less

__all__ = ["path_report_html"]

LABELS = {"input": "input order", "raster": "raster (serpentine)", "nn": "nearest neighbour",
          "ga": "paper GA", "ls": "local search (2-opt, Or-opt, kicks)", "ga+ls": "GA + local search"}


def ordered_names(result) -> list:
    """File names of the ordered job: ``ordered.csv``; ``ordered.json``; or ``ordered.<ext>`` and ``ordered.json``."""
    if result.inp.fmt == "csv":
        return ["ordered.csv"]
    if job_writer(result.inp.fmt) is not None:
        return [f"ordered{os.path.splitext(result.source)[1].lower()}", "ordered.json"]
    return ["ordered.json"]


def _draw_path(ax, job, tour, title):
    from matplotlib.collections import LineCollection      # matplotlib only when a report is drawn
    segs = []
    pts = []
    for st in job.strokes:
        p = np.asarray(st.xy_mm)
        if st.kind == "point":
            pts.append(p[0])
        else:
            q = np.vstack([p, p[:1]]) if st.kind == "contour" else p
            segs.append(q)
    if segs:
        ax.add_collection(LineCollection(segs, colors="#222", linewidths=0.9))
    if pts:
        pts = np.array(pts)
        ax.plot(pts[:, 0], pts[:, 1], "o", ms=2.5, color="#222")
    ein, eout = tour_points(job, tour)
    nxt = np.roll(ein, -1, axis=0)
    jumps = np.stack([eout, nxt], axis=1)
    ax.add_collection(LineCollection(jumps, colors="#d9342b", linewidths=0.7, linestyles="--"))
    ax.plot(ein[0, 0], ein[0, 1], "s", ms=6, color="#3b7dd8", label="start")
    ax.set_aspect("equal")
    ax.autoscale()
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")


def _path_figure(res):
    fig = new_figure(11, 5.2)
    a1 = fig.add_subplot(1, 2, 1)
    a2 = fig.add_subplot(1, 2, 2)
    s = res.stats
    _draw_path(a1, res.inp.job, res.tours["input"],
               f"input order: jumps {s['input']['jump_length_mm']:.1f} mm")
    u = res.method_used
    _draw_path(a2, res.inp.job, res.tour, f"{LABELS[u]}: jumps {s[u]['jump_length_mm']:.1f} mm")
    return png_b64(fig)


def _convergence_figure(res):
    ga = res.ga
    fig = new_figure(8, 4)
    ax = fig.add_subplot(1, 1, 1)
    g = np.arange(len(ga.curve))
    unit = "mm" if res.options.timing.metric == "distance" else "s"
    ax.plot(g, ga.mean_curve, color="#aaa", lw=1, label="GA population mean")
    ax.plot(g, ga.curve, color="#3b7dd8", lw=1.5, label="GA best")
    key = "jump_length_mm" if unit == "mm" else "jump_time_s"
    styles = {"nn": ("#e0a100", ":"), "raster": ("#7a4", "-."), "ga+ls": ("#d9342b", "--"), "ls": ("#d9342b", "--")}
    for name, (c, ls) in styles.items():
        if name in res.stats:
            ax.axhline(res.stats[name][key], color=c, ls=ls, lw=1.2, label=f"{LABELS[name]}")
    ax.set_xlabel("generation")
    ax.set_ylabel(f"tour jump cost ({unit})")
    lo = min(min(v[key] for v in res.stats.values()), float(ga.curve.min()))
    hi = max(float(ga.curve[0]), res.stats["nn"][key])
    ax.set_ylim(lo * 0.95, hi * 1.05)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return png_b64(fig)


def _methods_table(res):
    s = res.stats
    base = s["input"]
    rows = []
    for name, st in s.items():
        red = pct_less(st["jump_length_mm"], base["jump_length_mm"])
        tred = pct_less(st["time_s"], base["time_s"])
        chosen = " <b>(written)</b>" if name == res.method_used else ""
        rows.append([esc(LABELS[name]) + chosen, num(st["jump_length_mm"]), f"{red:.1f} %",
                     num(st["jump_time_s"], "s"), num(st["time_s"], "s"), f"{tred:.1f} %",
                     num(res.runtimes_s[name], "s")])
    return table(["order", "jump length", "vs input", "jump time", "job time", "vs input", "runtime"], rows)


def path_report_html(res) -> str:
    """The whole report page for a :class:`markcal.pipeline.flows.path.PathResult`."""
    s = res.summary
    u = res.method_used
    parts = []
    verdict = (f"{s['n_strokes']} strokes; {esc(LABELS[u])}: jumps {num(s['jump_length_mm'])} "
               f"({s['length_reduction_vs_input_pct']:.1f} % shorter than the input order, "
               f"{s['length_reduction_vs_raster_pct']:.1f} % shorter than raster), estimated job time "
               f"{num(s['time_s'], 's')} ({s['time_reduction_vs_input_pct']:.1f} % less than the input order).")
    parts.append(f'<div class="verdict">{verdict}</div>')
    for n in res.notes:
        parts.append(f'<div class="warn">{esc(n)}</div>')
    rows = [["strokes (points / polylines / contours)",
             f"{s['n_strokes']} ({s['n_points']} / {s['n_polylines']} / {s['n_contours']})"],
            ["marked length (laser on)", num(s["mark_length_mm"])],
            ["method asked / used", esc(f"{s['method']} / {s['method_used']}")],
            ["optimised cost", esc(s["metric"])],
            ["galvo jump speed, settle per jump", f"{num(s['jump_speed_mm_s'], 'mm/s')}, "
                                                 f"{num(s['settle_s'] * 1e6, 'µs')}"],
            ["mark speed, dwell per point", f"{num(s['mark_speed_mm_s'], 'mm/s')}, "
                                            f"{num(s['point_dwell_s'] * 1e6, 'µs')}"],
            ["duplicate strokes (kept)", str(s["n_duplicate_strokes"])],
            ["job format, groups (layers / pens / colours)", esc(f"{s['format']}, {s['n_groups']}")],
            ["order", "inside each group, groups in input order (--keep-layer-order)" if s["keep_layer_order"]
             else "free across groups"],
            ["curve tolerance (chordal)", num(s["tolerance_mm"])],
            ["seed", str(s["seed"])],
            ["runtime", num(s["runtime_s"], "s")]]
    parts.append("<h2>Summary</h2>" + table(["", ""], rows))
    if s["unsupported"]:
        parts.append("<h2>Not read (unsupported)</h2>" + table(
            ["entity / command", "count"], [[esc(k), str(v)] for k, v in s["unsupported"].items()]) +
            "<p>Kept unchanged in the written job; not part of the marking order.</p>")
    parts.append("<h2>Orders compared</h2>" + _methods_table(res) +
                 "<p>Jump length: laser-off travel from the end of each stroke to the start of the next, "
                 "the last one back to the start (closed tour, as in the paper). Job time = jump time "
                 "(length / jump speed + settle per jump) + mark time (length / mark speed + dwell per point).</p>")
    parts.append("<h2>Path before and after</h2>" + img(
        _path_figure(res), "path before and after",
        "Strokes in black, jumps (laser off) as red dashes, the start as a blue square. Left: the input "
        f"order; right: {esc(LABELS[u])} (paper Fig. 7B)."))
    if res.ga is not None:
        ga = res.ga
        cap = (f"Best and mean jump cost of the population over {len(ga.curve) - 1} generations "
               f"(population {res.options.ga.population}, CP {res.options.ga.crossover_p}, "
               f"MP {res.options.ga.mutation_p}; paper Fig. 7C), with the baselines and the local-search "
               "result as lines.")
        parts.append("<h2>GA convergence</h2>" + img(_convergence_figure(res), "GA convergence", cap))
    files = [(name, "the job in marking order (same format as the input)" if k == 0 else
              "the strokes in marking order (mm) with their input index, direction and entry vertex")
             for k, name in enumerate(ordered_names(res))]
    files.append(("summary.json", "the values of the tables above"))
    parts.append(data_files_footer(files))
    return page("markcal path: marking order", parts, source=res.source, summary=res.summary)
