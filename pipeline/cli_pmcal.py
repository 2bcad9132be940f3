"""``markcal pmcal``, ``markcal pmcal command``, ``markcal drift`` and ``markcal render pmcal``.

``pmcal`` has two sub-commands: ``calibrate`` (the default: ``markcal pmcal SESSION`` is
``markcal pmcal calibrate SESSION``) and ``command``. A session folder literally named
``command`` or ``calibrate`` must be given as ``./command``.
"""
from __future__ import annotations

import os

from markcal.pipeline.cli_common import Parser, add_context_options, add_run_options, choices_from
from markcal.pipeline.progress import progress
from markcal.stages.errors import MarkcalError


def cmd_pmcal(args) -> int:
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.registry import exit_status, run_and_write

    say = progress(args.quiet)
    res, paths = run_and_write("pmcal", args.session, args.out, progress=say, **run_options(args),
                               options={"method": args.method, "seed": args.seed, "no_report": args.no_report})
    for w in res.warnings:
        say(f"warning: {w}")
    s = res.summary
    msg = (f"{res.method}: F {s['F']:.4f}; non-orthogonality {s['nonorth_xy_urad']:.1f}/{s['nonorth_xz_urad']:.1f}/"
           f"{s['nonorth_yz_urad']:.1f} µrad; residual RMS axes {s['axes_rms_um']:.4f}, pose {s['pose_rms_um']:.4f} µm")
    if "landing_rms_um" in s:
        msg += f"; against truth: landing RMS {s['landing_rms_um']:.4f} µm, max {s['landing_max_um']:.4f} µm"
    say(msg)
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return exit_status(res.summary)


def cmd_pmcal_command(args) -> int:
    """``markcal pmcal command``: stage commands for targets from a calibration."""
    from markcal.pipeline.flows.pmcal import run_command
    from markcal.reports.files import write_csv

    if args.depth_um is None:
        raise MarkcalError("markcal pmcal command needs --depth-um")
    from markcal.reports.files import check_out_file
    out = os.path.abspath(args.out)
    check_out_file(args.out, [args.calibration, args.targets])
    say = progress(args.quiet)
    cols = run_command(args.calibration, args.targets, args.depth_um, progress=say)
    write_csv(out, cols)
    say(f"{len(cols['x_um'])} commands at depth {args.depth_um:g} µm")
    print(out)
    return 0


def cmd_drift(args) -> int:
    from markcal.pipeline.flows.drift import run_drift
    from markcal.reports.drift_outputs import write_drift_outputs

    from markcal.reports.files import check_out_dir
    check_out_dir(args.out, [p for p in (args.drift, args.truth) if p])       # before any computation
    from markcal.pipeline.cli_common import context_of
    from markcal.pipeline.registry import provenance

    say = progress(args.quiet)
    say(f"compensating {args.drift} ({args.method})")
    res = run_drift(args.drift, method=args.method, truth_path=args.truth, noise_um=args.noise_um, alpha=args.alpha)
    res.summary.update(provenance([p for p in (args.drift, args.truth) if p], context=context_of(args)))
    paths = write_drift_outputs(res, args.out, report=not args.no_report)
    s = res.summary
    say(f"{res.method}: η x {s['eta_x_pct']:.1f} %, y {s['eta_y_pct']:.1f} %, z {s['eta_z_pct']:.1f} % "
        f"({'against the true drift' if s['truth'] else 'at the samples'})")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return 0


def cmd_render_pmcal(args) -> int:
    import numpy as np

    from markcal.fixtures.pm_session import SessionOptions, render_pm_session
    from markcal.reports.files import write_csv, write_json

    if not (args.noise_um >= 0 and np.isfinite(args.noise_um)):
        raise MarkcalError(f"--noise-um must be a non-negative number (got {args.noise_um})")
    if args.pose_grid < 2:
        raise MarkcalError(f"--pose-grid must be at least 2 (got {args.pose_grid})")
    say = progress(args.quiet)
    say(f"rendering a pmcal session, seed {args.seed}")
    r = render_pm_session(args.seed, SessionOptions(noise_um=args.noise_um, pose_grid=args.pose_grid),
                          drift_kind=args.drift_kind)
    os.makedirs(args.out, exist_ok=True)
    write_csv(os.path.join(args.out, "axes.csv"), r.axes)
    if args.om_images:
        _write_om_marks(r, args.out, say)
    else:
        write_csv(os.path.join(args.out, "pose.csv"), r.pose)
    write_csv(os.path.join(args.out, "probe.csv"), r.probe)
    write_csv(os.path.join(args.out, "drift.csv"), r.drift)
    write_csv(os.path.join(args.out, "drift_true.csv"),
              {"t_min": r.drift_true_t_min, "dx_um": r.drift_true_um[:, 0], "dy_um": r.drift_true_um[:, 1],
               "dz_um": r.drift_true_um[:, 2]})
    write_json(os.path.join(args.out, "truth.json"), r.truth)
    print(os.path.abspath(args.out))
    return 0


def _write_om_marks(r, out, say) -> None:
    """om/mark_NNN.tif (16-bit ImageJ TIFF with the pixel size) and marks.csv instead of pose.csv."""
    from markcal.fixtures.indent_maps import tiff_bytes
    from markcal.fixtures.pm_session import render_om_marks
    from markcal.reports.files import atomic_write_bytes, write_csv

    say(f"rendering {len(r.pose['x_pm_um'])} OM micrographs of the pose marks")
    om = render_om_marks(r)
    os.makedirs(os.path.join(out, "om"), exist_ok=True)
    for name, img in zip(om.marks["image"], om.images):
        atomic_write_bytes(os.path.join(out, "om", name), tiff_bytes(img, om.pixel_um))
    write_csv(os.path.join(out, "marks.csv"), om.marks)


class _DefaultSubcommandParser(Parser):
    """A parser whose first word, when it names none of its sub-commands, runs ``default_subcommand``.

    ``markcal pmcal SESSION`` then means ``markcal pmcal calibrate SESSION``.
    """

    default_subcommand = "calibrate"

    def parse_known_args(self, args=None, namespace=None):
        import sys
        args = list(sys.argv[1:] if args is None else args)
        names = {n for a in self._subparsers._group_actions for n in getattr(a, "choices", None) or ()} \
            if self._subparsers else set()
        if args and args[0] not in names and args[0] not in ("-h", "--help"):
            args.insert(0, self.default_subcommand)
        return super().parse_known_args(args, namespace)


def register(sub, render_sub) -> None:
    """Add ``pmcal`` (sub-commands ``calibrate``, the default, and ``command``) and ``drift`` to ``sub``,
    and ``pmcal`` to ``render_sub``."""
    pc = sub.add_parser("pmcal", help="precision-marking machine calibration (GA / least squares); "
                        "'pmcal command' makes stage commands",
                        description="markcal pmcal [calibrate] SESSION_DIR --out DIR: calibrate from a session; "
                        "markcal pmcal command CALIBRATION.json TARGETS.csv --depth-um D --out COMMANDS.csv: "
                        "stage commands. A session folder named like a sub-command must be given as ./NAME.")
    pc.__class__ = _DefaultSubcommandParser
    psub = pc.add_subparsers(dest="pmcal_command", required=True, metavar="{calibrate,command}", parser_class=Parser)
    ca = psub.add_parser("calibrate", help="calibrate from a session folder (the default: 'markcal pmcal SESSION' "
                         "works too)")
    ca.add_argument("session", help="session folder (axes.csv, pose.csv or om/ + marks.csv, probe.csv, drift.csv)")
    ca.add_argument("--out", required=True, metavar="DIR", help="output folder")
    ca.add_argument("--method", choices=choices_from("markcal.pipeline.flows.pmcal", "METHODS"), default="ga+lsq",
                    metavar="METHOD", help="calibration written: %(choices)s")
    ca.add_argument("--seed", type=int, default=0, help="GA seed")
    ca.add_argument("--no-report", action="store_true", help="skip report.html")
    ca.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(ca)
    ca.set_defaults(func=cmd_pmcal)

    co = psub.add_parser("command", help="stage commands for targets from a calibration",
                         description="markcal pmcal command CALIBRATION.json TARGETS.csv --depth-um D --out COMMANDS.csv")
    co.add_argument("calibration", metavar="CALIBRATION.json", help="calibration.json written by 'markcal pmcal'")
    co.add_argument("targets", metavar="TARGETS.csv", help="targets: x_um,y_um in the OM frame")
    co.add_argument("--depth-um", type=float, default=None, help="depth along the surface normal, µm (required)")
    co.add_argument("--out", required=True, metavar="COMMANDS.csv", help="commands file to write")
    co.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    co.set_defaults(func=cmd_pmcal_command)

    dr = sub.add_parser("drift", help="online drift compensation from reference-array samples; η per axis")
    dr.add_argument("drift", help="drift.csv: t_min,dx_um,dy_um,dz_um")
    dr.add_argument("--out", required=True, help="output folder")
    dr.add_argument("--method", choices=choices_from("markcal.stages.drift", "METHODS"), default="kalman",
                    metavar="METHOD", help="compensation written: %(choices)s")
    dr.add_argument("--truth", default=None, help="true drift at fine resolution (drift_true.csv) to judge between samples")
    dr.add_argument("--noise-um", type=float, default=0.005, help="noise of one drift sample, µm (Kalman filters)")
    dr.add_argument("--alpha", type=float, default=0.8, help="α of the paper's filter")
    dr.add_argument("--no-report", action="store_true", help="skip report.html")
    dr.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_context_options(dr)
    dr.set_defaults(func=cmd_drift)

    rp = render_sub.add_parser("pmcal", help="calibration session of a precision-marking machine (paper 000)")
    rp.add_argument("--seed", type=int, default=0)
    rp.add_argument("--out", required=True)
    rp.add_argument("--noise-um", type=float, default=0.010, help="measurement noise (1 σ), µm")
    rp.add_argument("--drift-kind", choices=["thermal", "wander"], default="thermal")
    rp.add_argument("--pose-grid", type=int, default=7, help="pose marks per side (7: 49 marks)")
    rp.add_argument("--om-images", action="store_true",
                    help="write om/ micrographs of the pose marks and marks.csv instead of pose.csv")
    rp.add_argument("--quiet", action="store_true")
    rp.set_defaults(func=cmd_render_pmcal)
