"""The path flow: marking-order optimisation of a galvo marking job (paper 002).

Reads a job (JSON strokes, CSV points, DXF, SVG, HPGL/PLT or G-code; mm),
evaluates the input order and the raster and nearest-neighbour baselines, runs
the chosen method (``auto``: the local search; the paper's GA, or the GA
followed by local search) and returns the tours, their jump lengths and
estimated times, and the GA's convergence curve. With ``keep_layer_order`` the
strokes are ordered inside each layer / group only, the groups in input order.
"""
from __future__ import annotations

import csv
import io
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from markcal.pipeline.flows.descriptor import Figure, FlowDescriptor, csv_header, file_ext
from markcal.pipeline.tables import load_json
from markcal.stages.errors import MarkcalError
from markcal.stages.limits import check_text_ends
from markcal.stages.job_formats import JobFile
from markcal.stages.path_ga import GAOptions, GAResult, run_ga
from markcal.stages.path_job import CONTOUR, MAX_ABS_MM, POINT, POLYLINE, Job, Timing, Tour, check_number_leaves, check_tour, \
    duplicate_groups, input_tour, make_job, tour_stats
from markcal.stages.path_layers import join_group_tours, split_groups
from markcal.stages.path_tour import LocalSearchOptions, best_entries, local_search, n_kicks_for, \
    nearest_neighbour_tour, raster_tour
from markcal.stages.stats import pct_less

#: methods a user can choose; ``auto`` (the default) is the local search, ``ga+2opt`` another name of ``ga+ls``
METHODS = ("auto", "input", "raster", "nn", "ls", "ga", "ga+ls")
ALIASES = {"ga+2opt": "ga+ls", "ga+local": "ga+ls", "local": "ls", "2opt": "ls"}
#: job file extensions by format
FORMATS = {".json": "json", ".csv": "csv", ".txt": "csv", ".dxf": "dxf", ".svg": "svg",
           ".plt": "hpgl", ".hpgl": "hpgl", ".hpg": "hpgl", ".hgl": "hpgl",
           ".gcode": "gcode", ".nc": "gcode", ".ngc": "gcode", ".gc": "gcode", ".g": "gcode", ".tap": "gcode"}
#: keys of a JSON job and of its strokes
JOB_KEYS = {"units", "name", "description", "strokes"}
KIND_ALIASES = {"point": "point", "polyline": "polyline", "open": "polyline", "line": "polyline",
                "contour": "contour", "closed": "contour"}


@dataclass(frozen=True)
class PathOptions:
    """Settings of the path flow."""

    method: str = "auto"
    seed: int = 0
    timing: Timing = field(default_factory=Timing)
    ga: GAOptions = field(default_factory=GAOptions)
    ls: LocalSearchOptions = field(default_factory=LocalSearchOptions)
    ga_max_strokes: int = 500
    tolerance_mm: float = 0.01
    keep_layer_order: bool = False

    def __post_init__(self):
        if not (np.isfinite(self.tolerance_mm) and self.tolerance_mm > 0):
            raise MarkcalError(f"--tolerance-mm must be > 0 (got {self.tolerance_mm})")


#: the job as read (kept under its old name for callers)
PathInput = JobFile


@dataclass(frozen=True, eq=False)
class PathResult:
    """Everything the path flow found; ``reports`` turns it into files."""

    source: str
    inp: JobFile
    options: PathOptions
    method_used: str
    tours: dict                  # name -> Tour (input, raster, nn, then the methods run)
    stats: dict                  # name -> tour_stats dict
    runtimes_s: dict             # name -> s
    ga: GAResult | None
    duplicates: list             # groups of stroke indices
    notes: list                  # what the user should know (fallback, duplicates, unsupported entities)
    summary: dict
    layered: bool = False        # ordered inside each group only, groups in input order

    @property
    def tour(self) -> Tour:
        """The tour written out (the chosen method's)."""
        return self.tours[self.method_used]


# ----------------------------------------------------------------------------- reading

def _read_json(path) -> PathInput:
    if os.path.isfile(path) and os.path.getsize(path) == 0:
        raise MarkcalError("empty file: the job has no strokes", path)
    doc = load_json(path, "job file")
    if not isinstance(doc, dict) or "strokes" not in doc:
        raise MarkcalError('a JSON job is an object with a "strokes" list', path)
    unknown = sorted(set(doc) - JOB_KEYS)
    if unknown:
        raise MarkcalError(f"unknown key(s) {', '.join(map(repr, unknown))} (allowed: {', '.join(sorted(JOB_KEYS))})",
                           path)
    if doc.get("units", "mm") != "mm":
        raise MarkcalError(f'units must be "mm", not {doc.get("units")!r}', path)
    strokes = doc["strokes"]
    if not isinstance(strokes, list):
        raise MarkcalError('"strokes" must be a list', path)
    items = []
    for i, s in enumerate(strokes):
        if not isinstance(s, dict) or "kind" not in s or "xy_mm" not in s:
            raise MarkcalError(f'stroke {i}: needs "kind" and "xy_mm"', path)
        kind = KIND_ALIASES.get(str(s["kind"]).lower())
        if kind is None:
            raise MarkcalError(f"stroke {i}: unknown kind {s['kind']!r} (point, polyline or contour)", path)
        xy = s["xy_mm"]
        check_number_leaves(xy, f"stroke {i} ({kind}) xy_mm", path)
        try:
            xy = np.array(xy, dtype=float)
        except (TypeError, ValueError):
            raise MarkcalError(f"stroke {i} ({kind}): xy_mm must hold numbers (x_mm, y_mm pairs)", path) from None
        if kind == "point" and xy.ndim == 1 and xy.size != 2:
            raise MarkcalError(f"stroke {i} (point): xy_mm must be [x, y]", path)
        if xy.ndim == 2 and xy.shape[1] != 2 or xy.ndim > 2:
            raise MarkcalError(f"stroke {i} ({kind}): xy_mm must be a list of [x, y] pairs", path)
        items.append((kind, xy))
    job = make_job(items, path)
    return JobFile(job, "json", ("",) * job.n, {}, (), doc)


def _read_csv(path) -> PathInput:
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            text = fh.read()
        check_text_ends(text, path)
        rows = list(csv.reader(io.StringIO(text)))
    except OSError as exc:
        raise MarkcalError(f"cannot read job ({exc.strerror})", path) from None
    except UnicodeDecodeError:
        raise MarkcalError("not a text CSV file", path) from None
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise MarkcalError("empty file: the job has no strokes", path)
    header = [c.strip() for c in rows[0]]
    if "x_mm" not in header or "y_mm" not in header:
        raise MarkcalError(f"CSV header must name x_mm and y_mm (has {', '.join(header)})", path)
    ix, iy = header.index("x_mm"), header.index("y_mm")
    body = rows[1:]
    if not body:
        raise MarkcalError("the job has no strokes (header only)", path)
    xy = np.empty((len(body), 2))
    for k, r in enumerate(body):
        if len(r) != len(header):
            raise MarkcalError(f"row {k + 2}: {len(r)} fields, the header has {len(header)}", path)
        try:
            xy[k] = float(r[ix]), float(r[iy])
        except ValueError:
            raise MarkcalError(f"row {k + 2}: x_mm, y_mm must be numbers ({r[ix]!r}, {r[iy]!r})", path) from None
        if not np.all(np.isfinite(xy[k])):
            raise MarkcalError(f"row {k + 2} (point {k}): NaN or infinite coordinate", path)
        if np.abs(xy[k]).max() > MAX_ABS_MM:             # point CSVs also carry TSPLIB boards (up to ~1e5)
            raise MarkcalError(f"row {k + 2} (point {k}): coordinate {np.abs(xy[k]).max():g} mm beyond the "
                               f"limit ±{MAX_ABS_MM:g} mm", path)
    job = make_job([("point", p) for p in xy], path)
    return JobFile(job, "csv", ("",) * job.n, {}, (), (header, body))


def _reader(fmt):
    if fmt == "dxf":
        from markcal.stages.job_dxf import read_dxf
        return read_dxf
    if fmt == "svg":
        from markcal.stages.job_svg import read_svg
        return read_svg
    if fmt == "hpgl":
        from markcal.stages.job_hpgl import read_hpgl
        return read_hpgl
    from markcal.stages.job_gcode import read_gcode
    return read_gcode


def read_job(path, tolerance_mm: float = 0.01) -> JobFile:
    """Read a job file: ``.json`` strokes, ``.csv`` points (header ``x_mm,y_mm``), DXF, SVG,
    HPGL/PLT or G-code (curves flattened to ``tolerance_mm``), mm.

    Raises
    ------
    MarkcalError
        Missing, unreadable or truncated file, bad syntax, no strokes, NaN, unsupported units.
    """
    ext = os.path.splitext(str(path))[1].lower()
    if not os.path.exists(path):
        raise MarkcalError("no such file", path)
    fmt = FORMATS.get(ext)
    if fmt is None:
        raise MarkcalError(f"unknown job format {ext!r} (use {', '.join(sorted(FORMATS))})", path)
    if fmt == "json":
        return _read_json(path)
    if fmt == "csv":
        return _read_csv(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise MarkcalError(f"cannot read job ({exc.strerror})", path) from None
    if not data.strip():
        raise MarkcalError("empty file: the job has no strokes", path)
    return _reader(fmt)(data, tolerance_mm, path)


# ----------------------------------------------------------------------------- flow

def _method(name: str) -> str:
    m = ALIASES.get(name, name)
    if m not in METHODS:
        raise MarkcalError(f"unknown method {name!r} (choose from {', '.join(METHODS + tuple(ALIASES))})")
    return m


def run_path(job_path, options: PathOptions | None = None, progress=None) -> PathResult:
    """Run the path flow on one job file.

    Parameters
    ----------
    job_path : path
        JSON job, CSV points, DXF, SVG, HPGL/PLT or G-code.
    options : PathOptions, optional
    progress : callable, optional
        Called with a short text before each step.

    Raises
    ------
    MarkcalError
        Bad input; the message names the file.
    """
    opt = options or PathOptions()
    method = _method(opt.method)
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    say("reading job")
    inp = read_job(job_path, opt.tolerance_mm)
    try:
        return _run(inp, str(job_path), opt, method, say, t0)
    except MarkcalError as exc:
        raise exc.with_path(job_path) from None


def optimise_job(job: Job, options: PathOptions | None = None, progress=None) -> tuple:
    """Baselines and the chosen method on a job in memory.

    Returns
    -------
    (method_used, tours, runtimes_s, ga_result, notes)
    """
    opt = options or PathOptions()
    method = _method(opt.method)
    say = progress or (lambda msg: None)
    tm = opt.timing
    tours, rt, notes = {}, {}, []
    tours["input"] = input_tour(job)
    rt["input"] = 0.0
    t = time.perf_counter()
    tours["raster"] = raster_tour(job)
    rt["raster"] = time.perf_counter() - t
    t = time.perf_counter()
    tours["nn"] = best_entries(job, nearest_neighbour_tour(job), tm)
    rt["nn"] = time.perf_counter() - t
    ga = None
    used = "ls" if method == "auto" else method
    if method in ("ga", "ga+ls") and job.n > opt.ga_max_strokes:
        used = "ls"
        notes.append(f"{job.n} strokes is more than the GA's limit of {opt.ga_max_strokes} (--ga-max-strokes): "
                     f"method {method} fell back to local search (ls)")
    if used in ("ga", "ga+ls"):
        gopt = GAOptions(**{**opt.ga.__dict__, "seed": opt.seed})
        say(f"GA: population {gopt.population}, {gopt.generations} generations, CP {gopt.crossover_p}, "
            f"MP {gopt.mutation_p}")
        ga = run_ga(job, tm, gopt, progress=lambda g, c: say(f"GA generation {g}: best {c:.6g}")
                    if g % 1000 == 0 else None)
        tours["ga"] = ga.tour
        rt["ga"] = ga.runtime_s
    if used in ("ls", "ga+ls"):
        lopt = LocalSearchOptions(**{**opt.ls.__dict__, "seed": opt.seed})
        start_name = "ga" if used == "ga+ls" else "nn"
        say(f"local search from the {start_name} tour (2-opt, Or-opt, {n_kicks_for(job.n, lopt)} kicks)")
        t = time.perf_counter()
        tours[used] = local_search(job, tours[start_name], tm, lopt)
        rt[used] = time.perf_counter() - t + (rt["ga"] if used == "ga+ls" else rt["nn"])
    for tr in tours.values():
        check_tour(job, tr)
    return used, tours, rt, ga, notes


def _optimise_layers(inp: JobFile, opt: PathOptions, say) -> tuple:
    """:func:`optimise_job` inside each group, the groups joined in input order."""
    parts = split_groups(inp.job, inp.groups)
    say(f"keeping the layer order: {len(parts)} groups ordered one by one")
    per = []
    for name, idx, sub in parts:
        per.append((idx, sub, optimise_job(sub, opt, None)))
    used = per[0][2][0]
    notes = sorted({n for *_, r in per for n in r[4]})
    names = [k for k in per[0][2][1] if all(k in r[1] for *_, r in per)]
    tours = {k: join_group_tours([(idx, sub, r[1][k]) for idx, sub, r in per], opt.timing, rotate=k != "input")
             for k in names}
    rt = {k: float(sum(r[2][k] for *_, r in per)) for k in names}
    if used not in tours:                       # the GA ran in some groups only: the local search in all
        used = "ls"
    for tr in tours.values():
        check_tour(inp.job, tr)
    return used, tours, rt, None, notes


def _run(inp: JobFile, source: str, opt: PathOptions, method: str, say, t0) -> PathResult:
    job = inp.job
    tm = opt.timing
    dups = duplicate_groups(job)
    notes = []
    if dups:
        extra = sum(len(g) - 1 for g in dups)
        shown = "; ".join(",".join(map(str, g)) for g in dups[:5]) + ("; ..." if len(dups) > 5 else "")
        notes.append(f"{extra} duplicate stroke(s) kept and marked again (same strokes: {shown})")
    say(f"{job.n} strokes ({int((job.kinds == POINT).sum())} points, {int((job.kinds == POLYLINE).sum())} "
        f"polylines, {int((job.kinds == CONTOUR).sum())} contours)")
    if inp.unsupported:
        listed = ", ".join(f"{k} x{v}" for k, v in sorted(inp.unsupported.items()))
        notes.append(f"not read (unsupported, kept in the written job): {listed}")
    notes.extend(inp.notes)
    mopt = PathOptions(**{**opt.__dict__, "method": method})
    layered = opt.keep_layer_order and len(inp.group_names) > 1
    if layered:
        used, tours, rt, ga, more = _optimise_layers(inp, mopt, say)
    else:
        used, tours, rt, ga, more = optimise_job(job, mopt, say)
    notes = more + notes
    stats = {k: tour_stats(job, t, tm) for k, t in tours.items()}
    summary = _summary(inp, source, opt, method, used, stats, rt, ga, dups, notes, time.perf_counter() - t0)
    return PathResult(source, inp, opt, used, tours, stats, rt, ga, dups, notes, summary, layered)


def _summary(inp, source, opt, method, used, stats, rt, ga, dups, notes, runtime_s) -> dict:
    job = inp.job
    tm = opt.timing
    s = stats[used]
    out = {
        "kind": "path", "source": source, "format": inp.fmt,
        "n_strokes": job.n, "n_points": int((job.kinds == POINT).sum()),
        "n_polylines": int((job.kinds == POLYLINE).sum()), "n_contours": int((job.kinds == CONTOUR).sum()),
        "n_vertices": int(sum(len(st.xy_mm) for st in job.strokes)),
        "mark_length_mm": job.mark_length_mm,
        "method": method, "method_used": used, "fallback": used != method,
        "metric": tm.metric, "jump_speed_mm_s": tm.jump_speed_mm_s, "settle_s": tm.settle_s,
        "mark_speed_mm_s": tm.mark_speed_mm_s, "point_dwell_s": tm.point_dwell_s, "seed": opt.seed,
        "jump_length_mm": s["jump_length_mm"], "jump_time_s": s["jump_time_s"],
        "mark_time_s": s["mark_time_s"], "time_s": s["time_s"],
        "length_reduction_vs_input_pct": pct_less(s["jump_length_mm"], stats["input"]["jump_length_mm"]),
        "length_reduction_vs_raster_pct": pct_less(s["jump_length_mm"], stats["raster"]["jump_length_mm"]),
        "length_reduction_vs_nn_pct": pct_less(s["jump_length_mm"], stats["nn"]["jump_length_mm"]),
        "time_reduction_vs_input_pct": pct_less(s["time_s"], stats["input"]["time_s"]),
    }
    for name, st in stats.items():
        key = name.replace("+", "_")
        out[f"{key}_jump_length_mm"] = st["jump_length_mm"]
        out[f"{key}_time_s"] = st["time_s"]
        out[f"{key}_runtime_s"] = float(rt[name])
    if ga is not None:
        out.update({"ga_population": opt.ga.population, "ga_generations": len(ga.curve) - 1,
                    "ga_crossover_p": opt.ga.crossover_p, "ga_mutation_p": opt.ga.mutation_p,
                    "ga_evaluations": ga.evaluations})
        if "ga+ls" in stats:
            out["ga_ls_improvement_vs_ga_pct"] = pct_less(stats["ga+ls"]["jump_length_mm"],
                                                      stats["ga"]["jump_length_mm"])
    out["n_groups"] = len(inp.group_names)
    out["keep_layer_order"] = bool(opt.keep_layer_order)
    out["tolerance_mm"] = opt.tolerance_mm
    out["unsupported"] = dict(sorted(inp.unsupported.items()))
    out["n_unsupported"] = int(sum(inp.unsupported.values()))
    out["n_duplicate_strokes"] = int(sum(len(g) - 1 for g in dups))
    out["duplicate_strokes"] = [list(map(int, g)) for g in dups]
    out["notes"] = list(notes)
    out["runtime_s"] = float(runtime_s)
    return out


def _claims(path) -> bool:
    e = file_ext(path)
    if e == ".csv":             # a point job: x_mm,y_mm[,...] without z
        h = csv_header(path)
        return h[:2] == ["x_mm", "y_mm"] and "z_mm" not in h
    if e in FORMATS and FORMATS[e] in ("dxf", "svg", "hpgl", "gcode"):
        return True
    if e != ".json" or os.path.getsize(path) > 50_000_000:
        return False
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(d, dict) and "strokes" in d


#: caps of the GA (its iteration cap: generations; population x strokes is its memory)
MAX_GENERATIONS = 1_000_000
MAX_POPULATION = 10_000


def path_options(o: dict) -> PathOptions:
    """:class:`PathOptions` from the descriptor's option dict (CLI or batch.toml); checks the values."""
    _method(o["method"])
    for k, most in (("generations", MAX_GENERATIONS), ("population", MAX_POPULATION), ("ga_max_strokes", 100_000)):
        if not 1 <= o[k] <= most:
            raise MarkcalError(f"--{k.replace('_', '-')} must be at least 1 and at most {most:,} (got {o[k]})")
    if not o["kicks_per_stroke"] >= 0:
        raise MarkcalError("--kicks-per-stroke must be >= 0")
    timing = Timing(metric=o["metric"], jump_speed_mm_s=o["jump_speed_mm_s"], settle_s=o["settle_us"] * 1e-6,
                    mark_speed_mm_s=o["mark_speed_mm_s"], point_dwell_s=o["dwell_us"] * 1e-6)
    return PathOptions(method=o["method"], seed=int(o["seed"]), timing=timing,
                       ga=GAOptions(population=int(o["population"]), generations=int(o["generations"])),
                       ls=LocalSearchOptions(kicks_per_stroke=o["kicks_per_stroke"]),
                       ga_max_strokes=int(o["ga_max_strokes"]), tolerance_mm=o["tolerance_mm"],
                       keep_layer_order=o["keep_layer_order"])


FLOW = FlowDescriptor(
    name="path", help="marking job -> marking order with short jumps (GA, local search), report",
    claims=_claims,
    run=lambda path, spec, options, progress=None: run_path(path, path_options(options), progress=progress),
    validate_options=path_options,
    options={"method": "auto", "seed": 0, "tolerance_mm": 0.01, "keep_layer_order": False, "metric": "distance",
             "jump_speed_mm_s": 3000.0, "settle_us": 200.0, "mark_speed_mm_s": 1000.0, "dwell_us": 500.0,
             "generations": 3000, "population": 100, "ga_max_strokes": 500,
             "kicks_per_stroke": float(LocalSearchOptions().kicks_per_stroke),
             "no_report": False},
    key_figures=(Figure("jump_length_mm", "jump length", "mm"),
                 Figure("length_reduction_vs_input_pct", "jump length reduction vs input order", "%"),
                 Figure("time_s", "marking time", "s")),
    trends=("length_reduction_vs_input_pct",), cost=2.0)
