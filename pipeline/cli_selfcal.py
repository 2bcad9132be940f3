"""``markcal selfcal`` and ``markcal render selfcal``."""
from __future__ import annotations

import os

from markcal.pipeline.cli_common import add_alias, add_run_options
from markcal.pipeline.progress import progress


def cmd_selfcal(args) -> int:
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.registry import exit_status, run_and_write

    say = progress(args.quiet)
    res, paths = run_and_write("selfcal", args.session, args.out, options={"no_report": args.no_report},
                               progress=say, **run_options(args))
    s = res.summary
    msg = (f"stage error RMS Gx {s['gx_rms_um']:.4f} µm, Gy {s['gy_rms_um']:.4f} µm (± {s['predicted_sd_gxy_um']:.4f}); "
           f"O {s['nonorthogonality_urad']:.3f} µrad, R {s['scale_difference_ppm']:.3f} ppm")
    if s.get("error_sd_gx_um") is not None:
        msg += f"; against truth: sd E_Gx {s['error_sd_gx_um']:.4f} µm, E_Gy {s['error_sd_gy_um']:.4f} µm"
        if s.get("error_sd_gtheta_deg") is not None:
            msg += f", E_Gθ {s['error_sd_gtheta_deg']:.2e}°"
    say(msg)
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return exit_status(res.summary)


def cmd_render_selfcal(args) -> int:
    from markcal.fixtures.selfcal_stage import SelfcalOptions, render_selfcal, save_selfcal_session
    from markcal.stages.errors import MarkcalError

    if args.k < 4:      # n, pitch and k's divisibility are checked by SelfcalSetup
        raise MarkcalError(f"--k must be a positive multiple of 4 (got {args.k})")
    if args.repeats < 1 or args.noise_um < 0 or args.noise_theta_deg < 0:
        raise MarkcalError("--repeats must be >= 1 and the noise levels >= 0")
    say = progress(args.quiet)
    opts = SelfcalOptions(n=args.n, pitch_mm=args.pitch_mm, k=args.k, noise_xy_um=args.noise_um,
                          noise_theta_deg=args.noise_theta_deg, repeats=args.repeats,
                          missing_marks=args.missing_marks)
    say(f"rendering a {args.n} x {args.n} self-calibration session, K = {args.k}, seed {args.seed}")
    save_selfcal_session(args.out, render_selfcal(args.seed, opts))
    print(os.path.abspath(args.out))
    return 0


def register(sub, render_sub) -> None:
    """Add ``selfcal`` to ``sub`` and ``selfcal`` to ``render_sub``."""
    sc = sub.add_parser("selfcal", help="XY(θz) stage self-calibration from an artifact plate in four views")
    sc.add_argument("session", help="folder with setup.toml, grid_views.csv and angle_views.csv")
    sc.add_argument("--out", required=True, help="output folder")
    sc.add_argument("--no-report", action="store_true", help="skip report.html")
    sc.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(sc)
    sc.set_defaults(func=cmd_selfcal)

    rs = render_sub.add_parser("selfcal", help="self-calibration session of an XYθz stage (paper 001 §4)")
    rs.add_argument("--seed", type=int, default=0)
    rs.add_argument("--out", required=True)
    rs.add_argument("--n", type=int, default=11, help="sites per side (odd); default 11 as in the paper")
    rs.add_argument("--pitch-mm", type=float, default=10.0)
    rs.add_argument("--k", type=int, default=24, help="angular lines (multiple of 4); the paper's 15 deg: 24")
    rs.add_argument("--noise-um", type=float, default=0.02, help="measurement noise of a mark position, 1 σ per axis, µm")
    add_alias(rs, "--noise-xy-um", "--noise-um")
    rs.add_argument("--noise-theta-deg", type=float, default=0.001)
    rs.add_argument("--repeats", type=int, default=1, help="readings averaged per mark (the paper's P)")
    rs.add_argument("--missing-marks", type=int, default=0, help="grid readings to drop at random")
    rs.add_argument("--quiet", action="store_true")
    rs.set_defaults(func=cmd_render_selfcal)
