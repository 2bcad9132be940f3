"""``markcal servo`` and ``markcal render servo``."""
from __future__ import annotations

import os

from markcal.stages.errors import MarkcalError


def cmd_servo(args) -> int:
    from markcal.pipeline.progress import progress
    from markcal.pipeline.config import read_servo_config
    from markcal.pipeline.flows.servo import run_servo
    from markcal.pipeline.registry import run_and_write
    from markcal.reports.servo_outputs import write_servo_outputs

    say = progress(args.quiet)
    if args.trace and args.config:
        raise MarkcalError("give either CONFIG.toml (simulation) or --trace TRACE.csv, not both")
    if args.trace:
        band = args.settle_band_um if args.settle_band_um is not None else 1.0
        if not band > 0:
            raise MarkcalError(f"--settle-band-um must be positive (got {band})")
        res, paths = run_and_write("servo", args.trace, args.out, progress=say,
                                   options={"settle_band_um": band, "no_report": args.no_report})
    else:
        from dataclasses import replace

        from markcal.stages.servo_cases import ServoConfig
        cfg = read_servo_config(args.config) if args.config else ServoConfig()
        if args.settle_band_um is not None:
            cfg = replace(cfg, settle_band_um=args.settle_band_um)
        res = run_servo(cfg, source=os.path.abspath(args.config) if args.config else "paper defaults (no config)",
                        progress=say)
        say("writing tables and report")
        paths = write_servo_outputs(res, args.out, report=not args.no_report)
    s = res.summary
    if res.mode == "simulation":
        say(f"{s['step_stroke_mm']:g} mm move: overshoot reduction {s['overshoot_reduction_pct']:.1f} %, settling "
            f"reduction {s['settling_reduction_pct']:.1f} %; STD reduction 0.1 Hz "
            f"{s.get('std_reduction_0p1hz_pct', float('nan')):.1f} %, 2 Hz {s.get('std_reduction_2hz_pct', float('nan')):.1f} %")
    else:
        say(f"{s['trace_kind']}: MAE {s['mae_um']:.3f} µm, STD {s['std_um']:.3f} µm")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return 0


def cmd_render_servo(args) -> int:
    from markcal.fixtures.servo_trace import TraceOptions, render_servo_trace, save_servo_trace
    from markcal.pipeline.progress import progress

    say = progress(args.quiet)
    opts = TraceOptions(kind=args.kind, controller=args.controller, stroke_mm=args.stroke_mm,
                        amplitude_mm=args.amplitude_mm, frequency_hz=args.frequency_hz, periods=args.periods,
                        noise_nm=args.noise_nm)
    say(f"rendering a {args.kind} trace ({args.controller}), seed {args.seed}")
    r = render_servo_trace(args.seed, opts)
    os.makedirs(args.out, exist_ok=True)
    save_servo_trace(os.path.join(args.out, "trace.csv"), r, os.path.join(args.out, "truth.json"))
    print(os.path.abspath(args.out))
    return 0


def register(sub, render_sub) -> None:
    """Add ``servo`` to the top-level commands and ``servo`` to ``render``."""
    sv = sub.add_parser("servo", help="macro-stage servo: composite controller vs baseline, or a measured trace")
    sv.add_argument("config", nargs="?", help="CONFIG.toml (default: the paper's simulation parameters)")
    sv.add_argument("--trace", help="measured encoder trace CSV with columns t_s,ref_mm,pos_mm")
    sv.add_argument("--out", required=True, help="output folder")
    sv.add_argument("--settle-band-um", type=float, default=None, help="settling band half width, µm (default 1)")
    sv.add_argument("--no-report", action="store_true", help="skip report.html")
    sv.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
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
    rs.add_argument("--noise-nm", type=float, default=5.0, help="encoder noise, 1 sigma, nm")
    rs.add_argument("--quiet", action="store_true")
    rs.set_defaults(func=cmd_render_servo)
