"""``markcal servo`` and ``markcal render servo``."""
from __future__ import annotations

import os

from markcal.pipeline.cli_common import add_alias, add_run_options
from markcal.stages.errors import MarkcalError


#: command-line flags of the drive-log options (flow option name -> flag)
LOG_FLAGS = {"time_col": "--time-col", "ref_col": "--ref-col", "pos_col": "--pos-col", "time_unit": "--time-unit",
             "pos_unit": "--pos-unit", "counts_per_mm": "--counts-per-mm", "settle_band_pct": "--settle-band-pct"}


def cmd_servo(args) -> int:
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.config import read_servo_config
    from markcal.pipeline.flows.servo import TRACE_OPTIONS, run_servo
    from markcal.pipeline.progress import progress
    from markcal.pipeline.registry import exit_status, run_and_write
    from markcal.reports.servo_outputs import write_servo_outputs

    say = progress(args.quiet)
    if args.trace and args.config:
        raise MarkcalError("give either CONFIG.toml (simulation) or --trace LOG (a drive log), not both")
    given = {k: getattr(args, k) for k in LOG_FLAGS if getattr(args, k) is not None}
    if args.trace:
        if args.reading is not None:
            raise MarkcalError("--reading: only for the simulation (a drive log is measured, not simulated)")
        if args.settle_band_um is not None and args.settle_band_pct is not None:
            raise MarkcalError("give --settle-band-um or --settle-band-pct, not both")
        opts = {**TRACE_OPTIONS, **given, "no_report": args.no_report}
        if args.settle_band_um is not None:
            opts["settle_band_um"] = args.settle_band_um
        if not opts["settle_band_pct"] and not opts["settle_band_um"] > 0:
            raise MarkcalError(f"--settle-band-um must be positive (got {opts['settle_band_um']})")
        res, paths = run_and_write("servo", args.trace, args.out, progress=say, options=opts, **run_options(args))
    else:
        if given:
            raise MarkcalError(f"{', '.join(LOG_FLAGS[k] for k in given)}: only with --trace LOG")
        if args.tol:
            raise MarkcalError("--tol: only with --trace LOG (the simulation compares with the paper instead)")
        from dataclasses import replace

        from markcal.reports.files import check_out_dir
        from markcal.stages.servo_cases import ServoConfig
        check_out_dir(args.out)                       # once, before any work
        cfg = read_servo_config(args.config) if args.config else ServoConfig()
        if args.settle_band_um is not None:
            cfg = replace(cfg, settle_band_um=args.settle_band_um)
        if args.reading is not None:
            from markcal.stages.servo_reading import NAMED_READINGS
            if args.reading not in NAMED_READINGS:
                raise MarkcalError(f"--reading {args.reading!r} unknown (one of {', '.join(NAMED_READINGS)})")
            cfg = replace(cfg, reading=NAMED_READINGS[args.reading])
        res = run_servo(cfg, source=os.path.abspath(args.config) if args.config else "paper defaults (no config)",
                        progress=say)
        from markcal.pipeline.cli_common import context_of
        from markcal.pipeline.registry import provenance
        res.summary.update(provenance([args.config] if args.config else [], context=context_of(args)))
        res.summary.update(verdict="no tolerance", checks="", check_labels="", failed_checks="",
                           verdict_note="a simulation of the paper's cases: compared with the paper's Tables 1-2 "
                                        "below, not judged against a tolerance (--tol applies to --trace LOG)")
        say("writing tables and report")
        paths = write_servo_outputs(res, args.out, report=not args.no_report)
    s = res.summary
    if res.mode == "simulation":
        say(f"{s['step_stroke_mm']:g} mm move: overshoot reduction {s['overshoot_reduction_pct']:.1f} %, settling "
            f"reduction {s['settling_reduction_pct']:.1f} %; STD reduction 0.1 Hz "
            f"{s.get('std_reduction_0p1hz_pct', float('nan')):.1f} %, 2 Hz {s.get('std_reduction_2hz_pct', float('nan')):.1f} %")
    elif s["trace_kind"] == "move":
        say(f"{s['n_moves']} move(s), {s['n_settled']} settled: settling median {s['settling_time_median_s'] * 1e3:.2f} ms, "
            f"overshoot median {s['overshoot_median_um']:.3f} µm; MAE {s['mae_um']:.3f} µm")
    else:
        say(f"tracking {s['frequency_hz']:.4g} Hz: MAE {s['mae_um']:.3f} µm, STD {s['std_um']:.3f} µm, "
            f"phase lag {s['phase_lag_deg']:.3f}°")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return exit_status(s) if res.mode == "trace" else 0


def cmd_render_servo(args) -> int:
    from markcal.fixtures.servo_trace import TraceOptions, render_servo_trace, save_servo_trace
    from markcal.pipeline.progress import progress

    say = progress(args.quiet)
    opts = TraceOptions(kind=args.kind, controller=args.controller, stroke_mm=args.stroke_mm,
                        amplitude_mm=args.amplitude_mm, frequency_hz=args.frequency_hz, periods=args.periods,
                        noise_nm=args.noise_um * 1e3)
    say(f"rendering a {args.kind} trace ({args.controller}), seed {args.seed}")
    r = render_servo_trace(args.seed, opts)
    os.makedirs(args.out, exist_ok=True)
    save_servo_trace(os.path.join(args.out, "trace.csv"), r, os.path.join(args.out, "truth.json"))
    print(os.path.abspath(args.out))
    return 0


def cmd_render_servo_log(args) -> int:
    from markcal.fixtures.servo_log import LogOptions, render_servo_log, save_servo_log
    from markcal.pipeline.progress import progress

    say = progress(args.quiet)
    opts = LogOptions(kind=args.kind, n_moves=args.moves, stroke_mm=args.stroke_mm, hold_s=args.hold_s,
                      ts_s=args.sample_period_ms * 1e-3, fn_hz=args.fn_hz, zeta=args.zeta, dc_gain=args.dc_gain,
                      amplitude_mm=args.amplitude_mm, frequency_hz=args.frequency_hz, periods=args.periods,
                      noise_nm=args.noise_um * 1e3, jitter=args.jitter, time_unit=args.time_unit, pos_unit=args.pos_unit,
                      counts_per_mm=args.counts_per_mm, layout=args.layout, band_um=args.settle_band_um,
                      n_lines=args.lines)
    say(f"rendering a {opts.kind} drive log ({opts.layout}, time in {opts.time_unit}, positions in "
        f"{opts.pos_unit}), seed {args.seed}")
    r = render_servo_log(args.seed, opts)
    os.makedirs(args.out, exist_ok=True)
    ext = {"csv": "csv", "tsv": "tsv", "ws": "txt"}[opts.layout]
    read = save_servo_log(os.path.join(args.out, f"log.{ext}"), r, os.path.join(args.out, "truth.json"))
    flags = " ".join(f"--{k.replace('_', '-')} {v:g}" if isinstance(v, float) else f"--{k.replace('_', '-')} {v}"
                     for k, v in read.items())
    say(f"read it with: markcal servo --trace {os.path.join(args.out, f'log.{ext}')} {flags} --settle-band-um "
        f"{opts.band_um:g} --out OUT")
    print(os.path.abspath(args.out))
    return 0


def register(sub, render_sub) -> None:
    """Add ``servo`` to the top-level commands and ``servo`` to ``render``."""
    sv = sub.add_parser("servo", help="macro-stage servo: composite controller vs baseline, or a measured trace")
    sv.add_argument("config", nargs="?", help="CONFIG.toml (default: the paper's simulation parameters)")
    sv.add_argument("--trace", metavar="LOG", help="measured drive log: CSV, TSV or whitespace-separated, with "
                    "time, reference and position columns (many moves are cut at the reference's steps)")
    sv.add_argument("--out", required=True, help="output folder")
    sv.add_argument("--time-col", help="time column of the log: name or 0-based index (default t_s)")
    sv.add_argument("--ref-col", help="reference (target/demand) column: name or 0-based index (default ref_mm)")
    sv.add_argument("--pos-col", help="measured position column: name or 0-based index (default pos_mm)")
    sv.add_argument("--time-unit", choices=["s", "ms", "us"], help="unit of the time column (default s)")
    sv.add_argument("--pos-unit", choices=["mm", "um", "counts"],
                    help="unit of the reference and position columns (default mm)")
    sv.add_argument("--counts-per-mm", type=float, help="encoder counts per mm (with --pos-unit counts)")
    sv.add_argument("--settle-band-um", type=float, default=None,
                    help="settling band half width, µm (default: 1 for logs, the reading's band for the simulation)")
    sv.add_argument("--settle-band-pct", type=float, default=None,
                    help="settling band half width in %% of each move's stroke (logs; instead of --settle-band-um)")
    sv.add_argument("--reading", metavar="NAME", default=None,
                    help="how the paper's garbled plant and unit-less gains are read, a named reading "
                         "(simulation; default: the config's [model] reading, else 'best'; names in docs/servo.md)")
    sv.add_argument("--no-report", action="store_true", help="skip report.html")
    sv.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(sv)
    sv.set_defaults(func=cmd_servo)

    rs = render_sub.add_parser("servo", help="synthetic measured encoder trace of the macro stage")
    rs.add_argument("--seed", type=int, default=0)
    rs.add_argument("--out", required=True)
    rs.add_argument("--kind", choices=["step", "sine"], default="step")
    rs.add_argument("--controller", choices=["baseline", "cca"], default="cca")
    rs.add_argument("--stroke-mm", type=float, default=10.0)
    rs.add_argument("--amplitude-mm", type=float, default=5.0)
    rs.add_argument("--frequency-hz", type=float, default=1.0)
    rs.add_argument("--periods", type=float, default=3.0)
    rs.add_argument("--noise-um", type=float, default=0.005, help="encoder noise, 1 σ, µm")
    add_alias(rs, "--noise-nm", "--noise-um", factor=1e-3)
    rs.add_argument("--quiet", action="store_true")
    rs.set_defaults(func=cmd_render_servo)

    rl = render_sub.add_parser("servo-log", help="synthetic drive log (second-order moves or sine tracking) + truth")
    rl.add_argument("--seed", type=int, default=0)
    rl.add_argument("--out", required=True)
    rl.add_argument("--kind", choices=["square", "steps", "sine"], default="square")
    rl.add_argument("--moves", type=int, default=8, help="number of moves (square / steps)")
    rl.add_argument("--lines", type=int, default=0, help="fill this many lines instead (e.g. 1000000)")
    rl.add_argument("--stroke-mm", type=float, default=1.0)
    rl.add_argument("--hold-s", type=float, default=0.2, help="time between steps, s")
    rl.add_argument("--sample-period-ms", type=float, default=0.1, help="sample period, ms")
    add_alias(rl, "--ts-ms", "--sample-period-ms")
    rl.add_argument("--fn-hz", type=float, default=40.0, help="natural frequency of the stage loop, Hz")
    rl.add_argument("--zeta", type=float, default=0.4, help="damping ratio")
    rl.add_argument("--dc-gain", type=float, default=1.0, help="static gain K (steady-state error (1 - K) x target)")
    rl.add_argument("--amplitude-mm", type=float, default=1.0)
    rl.add_argument("--frequency-hz", type=float, default=2.0)
    rl.add_argument("--periods", type=float, default=3.0)
    rl.add_argument("--noise-um", type=float, default=0.005, help="encoder noise, 1 σ, µm")
    add_alias(rl, "--noise-nm", "--noise-um", factor=1e-3)
    rl.add_argument("--jitter", type=float, default=0.1, help="timestamp jitter, peak-to-peak fraction of the step")
    rl.add_argument("--time-unit", choices=["s", "ms", "us"], default="s")
    rl.add_argument("--pos-unit", choices=["mm", "um", "counts"], default="mm")
    rl.add_argument("--counts-per-mm", type=float, default=100_000.0, help="encoder counts per mm (--pos-unit counts)")
    rl.add_argument("--layout", choices=["csv", "tsv", "ws"], default="csv",
                    help="csv: header t_<unit>,ref_<unit>,pos_<unit>; tsv: drive export time/target/demand/actual/"
                         "current_A; ws: whitespace, no header, comment lines, columns sample time actual target")
    rl.add_argument("--settle-band-um", type=float, default=5.0, help="settling band of the truth, µm")
    add_alias(rl, "--band-um", "--settle-band-um")
    rl.add_argument("--quiet", action="store_true")
    rl.set_defaults(func=cmd_render_servo_log)
