"""``markcal path`` and ``markcal render path``: marking-order optimisation of galvo jobs."""
from __future__ import annotations

import os

from markcal.pipeline.cli_common import LazyChoices, add_alias, add_run_options
from markcal.stages.errors import MarkcalError


def cmd_path(args) -> int:
    from markcal.pipeline.progress import progress
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.registry import exit_status, get_flow, run_and_write

    say = progress(args.quiet)
    options = {k: getattr(args, k) for k in get_flow("path").descriptor.options if getattr(args, k) is not None}
    res, paths = run_and_write("path", args.job, args.out, options=options, progress=say, **run_options(args))
    for n in res.notes:
        say(f"note: {n}")
    s = res.summary
    say(f"{res.method_used}: jumps {s['jump_length_mm']:.2f} mm ({s['length_reduction_vs_input_pct']:.1f} % "
        f"shorter than input, {s['length_reduction_vs_raster_pct']:.1f} % than raster), "
        f"job time {s['time_s']:.4g} s")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return exit_status(res.summary)


def cmd_render_path(args) -> int:
    from markcal.fixtures.path_jobs import render_job
    from markcal.pipeline.progress import progress
    from markcal.reports.files import write_csv, write_json

    say = progress(args.quiet)
    if args.n is not None and args.n < 1:
        raise MarkcalError("--n must be at least 1")
    job = render_job(args.kind, args.seed, args.n)
    os.makedirs(args.out, exist_ok=True)
    points_only = all(s.kind == "point" for s in job.strokes)
    fmt = args.format or ("csv" if points_only else "json")
    if fmt == "csv" and not points_only:
        raise MarkcalError(f"a {args.kind} job has polylines or contours: CSV holds points only (use --format json)")
    say(f"rendering a {args.kind} job, seed {args.seed}: {job.n} strokes")
    if fmt == "csv":
        path = os.path.join(args.out, "job.csv")
        write_csv(path, {"x_mm": [float(s.xy_mm[0, 0]) for s in job.strokes],
                         "y_mm": [float(s.xy_mm[0, 1]) for s in job.strokes]})
    else:
        path = os.path.join(args.out, "job.json")
        write_json(path, {"units": "mm", "name": f"markcal render path --kind {args.kind} --seed {args.seed}",
                          "strokes": [{"kind": s.kind, "xy_mm": (s.xy_mm[0] if s.kind == "point" else s.xy_mm)}
                                      for s in job.strokes]})
    print(os.path.abspath(path))
    return 0


def _method_names() -> list:
    from markcal.pipeline.flows.path import ALIASES, METHODS
    return list(METHODS) + sorted(ALIASES)


def register(sub, render_sub) -> None:
    """Add ``path`` to the top-level sub-commands and ``path`` to ``render``."""
    p = sub.add_parser("path", help="marking job -> marking order with short jumps (GA, local search), report",
                       description="Defaults of the options are the path flow's (see the README, 'markcal path').")
    p.add_argument("job", help="job file: .json strokes (point / polyline / contour, mm), .csv points (x_mm,y_mm), "
                               ".dxf, .svg, .plt/.hpgl or G-code (.gcode, .nc, .ngc)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--method", default=None, choices=LazyChoices(_method_names), metavar="METHOD",
                   help="order written out (%(choices)s): auto (default) = local search from nearest neighbour (ls); "
                        "the paper GA (ga), GA then local search (ga+ls, alias ga+2opt), or a baseline")
    p.add_argument("--chord-tolerance-mm", dest="tolerance_mm", type=float, default=None,
                   help="chordal tolerance for flattening arcs, circles, ellipses, splines and Béziers (mm)")
    add_alias(p, "--tolerance-mm", "--chord-tolerance-mm", dest="tolerance_mm")
    p.add_argument("--keep-layer-order", action="store_true",
                   help="order only inside each layer / group / pen; layers marked in input order")
    p.add_argument("--seed", type=int, default=None, help="seed of the GA and the local-search kicks")
    p.add_argument("--metric", choices=["distance", "time"], default=None,
                   help="minimise jump length or jump time (speed + settle)")
    p.add_argument("--jump-speed-mm-s", type=float, default=None, help="galvo jump speed (mm/s)")
    p.add_argument("--settle-us", type=float, default=None, help="settle delay after each jump (µs)")
    p.add_argument("--mark-speed-mm-s", type=float, default=None, help="marking speed (mm/s)")
    p.add_argument("--dwell-us", type=float, default=None, help="laser dwell per point (µs)")
    p.add_argument("--generations", type=int, default=None, help="GA generations")
    p.add_argument("--population", type=int, default=None, help="GA population size")
    p.add_argument("--ga-max-strokes", type=int, default=None,
                   help="larger jobs fall back from the GA to local search")
    p.add_argument("--kicks-per-stroke", type=float, default=None,
                   help="iterated local search: kicks per stroke (default 5; at least 2,000, at most 10,000 in all; 0: none)")
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(p)
    p.set_defaults(func=cmd_path)

    r = render_sub.add_parser("path", help="synthetic marking job (random points, paper-like, fiducial grid, text)")
    r.add_argument("--kind", choices=["random", "paper", "grid", "text"], default="random")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--n", type=int, default=None, help="points for random (default 1000) and paper (70)")
    r.add_argument("--format", choices=["json", "csv"], default=None,
                   help="default: csv for point jobs, json otherwise")
    r.add_argument("--out", required=True)
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=cmd_render_path)
