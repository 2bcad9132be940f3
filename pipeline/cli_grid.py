"""``markcal grid``, ``markcal render grid`` and ``markcal render grid-job``."""
from __future__ import annotations

import os

from markcal.pipeline.cli_common import add_alias, add_run_options, choices_from
from markcal.stages.errors import MarkcalError


def cmd_grid(args) -> int:
    from markcal.pipeline.progress import progress
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.registry import exit_status, get_flow, run_and_write

    say = progress(args.quiet)
    if args.cor:
        from markcal.reports.files import check_out_file
        check_out_file(args.cor, [args.measured], option="--cor")          # before the fit
    options = {k: getattr(args, k) for k in get_flow("grid").descriptor.options if getattr(args, k) is not None}
    for k in ("units_per_mm", "lens_mm", "d_mm", "grid_step_mm"):       # 0 means "from the input" only in batch.toml
        if k in options and not options[k] > 0:
            raise MarkcalError(f"--{k.replace('_', '-')} must be positive (got {options[k]})")
    res, paths = run_and_write("grid", args.measured, args.out, options=options, progress=say, **run_options(args))
    s = res.summary
    cv = ", ".join(f"{k} {v:.4f}" for k, v in res.choice.cv_rmse_mm.items())
    say(f"{s['n_marks']} marks{' (mirrored)' if s['mirrored'] else ''}, deviation RMS {s['rms_mm']:.4f} mm; "
        f"{s['folds']}-fold CV error (mm): {cv}; using {s['model']}; {s['n_extrapolated']} of {s['n_nodes']} "
        "nodes extrapolated")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    if args.cor:
        # what `markcal export cor OUT --lens-mm LENS --out FILE --no-report` writes, without a second start-up
        from markcal.pipeline.flows.export import export_table
        from markcal.reports.files import atomic_write_bytes
        data, facts = export_table("cor", args.out, lens_mm=res.lens_mm)
        atomic_write_bytes(args.cor, data)
        say(f".cor over the {res.lens_mm:g} mm lens field ({facts['units_per_mm']:.4g} units/mm), largest entry "
            f"{facts['max_entry_units']:.1f} units")
        print(os.path.abspath(args.cor))
    return exit_status(res.summary)


def cmd_render_grid(args) -> int:
    from markcal.fixtures.measured_grid import GridRenderOptions, render_grid, save_measured_grid
    from markcal.pipeline.progress import progress

    say = progress(args.quiet)
    opt = GridRenderOptions(rows=args.rows, cols=args.cols, lens_mm=args.lens_mm, fill=args.fill,
                            noise_mm=args.noise_um * 1e-3, mirror=args.mirror, n_missing=args.missing_marks)
    if not (3 <= opt.rows <= 101 and 3 <= opt.cols <= 101 and opt.lens_mm > 0 and 0 < opt.fill <= 1
            and opt.noise_mm >= 0 and 0 <= opt.n_missing < opt.rows * opt.cols):
        raise MarkcalError("render grid: rows/cols 3..101, --lens-mm > 0, 0 < --fill <= 1, --noise-um >= 0, "
                           "--missing-marks below the number of marks")
    say(f"rendering a hand-measured {opt.rows} x {opt.cols} grid, seed {args.seed}")
    r = render_grid(args.seed, opt)
    print(os.path.abspath(save_measured_grid(args.out, r, args.format)))
    return 0


def cmd_render_grid_job(args) -> int:
    from markcal.reports.grid_job import write_grid_job
    paths = write_grid_job(args.out, args.rows, args.cols, args.field_mm, args.mark, args.format, args.mark_size_mm)
    print(os.path.abspath(paths["job"]))
    print(os.path.abspath(paths["measure.csv"]))
    return 0


def register(sub, render_sub) -> None:
    """Add ``grid`` to the top-level commands and ``grid``, ``grid-job`` to ``render``."""
    g = sub.add_parser("grid", help="hand-measured galvo grid -> physical model, correction over the lens field, report")
    g.add_argument("measured", help="measured grid: CSV (x_cmd_mm,y_cmd_mm,x_meas_mm,y_meas_mm or x_cmd_units,...) "
                                    "or a BJJCZ whitespace file")
    g.add_argument("--out", required=True, help="output folder")
    g.add_argument("--model", choices=choices_from("markcal.stages.galvo_fit", "KINDS", extra=("auto",)), metavar="MODEL", default=None,
                   help="correction model: %(choices)s (auto: lowest k-fold CV error; default physical+rbf)")
    g.add_argument("--units-per-mm", type=float, default=None, help="controller units per mm (commands in units)")
    g.add_argument("--centre-units", type=float, default=None, help="controller units at the field centre")
    g.add_argument("--lens-mm", type=float, default=None,
                   help="lens field (mm) the correction covers (default: 65536 / units-per-mm, else the grid + one pitch)")
    g.add_argument("--d-mm", type=float, default=None, help="controller's nominal mirror-to-field distance d (mm)")
    g.add_argument("--e-mm", type=float, default=None, help="controller's nominal mirror spacing e (mm)")
    g.add_argument("--grid-step-mm", type=float, default=None, help="correction_grid.csv step (default lens / 50)")
    g.add_argument("--folds", type=int, default=None, help="k of the k-fold cross-validation")
    g.add_argument("--seed", type=int, default=None, help="seed of the CV folds")
    g.add_argument("--cor", metavar="FILE", default=None,
                   help="also write the correction as a .cor table over the lens field (what `markcal export cor "
                        "OUT --lens-mm LENS --out FILE` writes with its defaults)")
    g.add_argument("--no-report", action="store_true", help="skip report.html")
    g.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(g)
    g.set_defaults(func=cmd_grid)

    rg = render_sub.add_parser("grid", help="synthetic hand-measured galvo grid with truth")
    rg.add_argument("--seed", type=int, default=0)
    rg.add_argument("--out", required=True)
    rg.add_argument("--rows", type=int, default=9)
    rg.add_argument("--cols", type=int, default=9)
    rg.add_argument("--lens-mm", type=float, default=110.0, help="lens field (mm)")
    rg.add_argument("--fill", type=float, default=0.8, help="fraction of the lens field the marks span")
    rg.add_argument("--noise-um", type=float, default=20.0, help="measurement noise, 1 σ per axis, µm")
    add_alias(rg, "--noise-mm", "--noise-um", factor=1e3)
    rg.add_argument("--mirror", action="store_true", help="measured from the back (mirrored)")
    rg.add_argument("--missing-marks", type=int, default=2, help="marks left unmeasured")
    add_alias(rg, "--missing", "--missing-marks", type=int)
    rg.add_argument("--format", choices=["csv", "units", "bjjcz"], default="csv",
                    help="csv (mm), units (CSV in controller units, 65536 per lens field) or bjjcz (whitespace)")
    rg.add_argument("--quiet", action="store_true")
    rg.set_defaults(func=cmd_render_grid)

    rj = render_sub.add_parser("grid-job", help="the marking job of a calibration grid and its measuring sheet")
    rj.add_argument("--out", required=True)
    rj.add_argument("--rows", type=int, default=9)
    rj.add_argument("--cols", type=int, default=9)
    rj.add_argument("--field-mm", type=float, default=110.0, help="span of the outer marks (mm)")
    rj.add_argument("--mark", choices=["cross", "circle"], default="cross")
    rj.add_argument("--mark-size-mm", type=float, default=None, help="mark size (default min(2, pitch / 4))")
    rj.add_argument("--format", choices=["dxf", "json", "gcode"], default="dxf")
    rj.add_argument("--quiet", action="store_true")
    rj.set_defaults(func=cmd_render_grid_job)
