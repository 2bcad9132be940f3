"""``markcal scan`` and ``markcal render scan``."""
from __future__ import annotations

import os

import numpy as np

from markcal.pipeline.progress import progress
from markcal.stages.errors import MarkcalError


def cmd_scan(args) -> int:
    from markcal.pipeline.registry import run_and_write

    say = progress(args.quiet)
    res, paths = run_and_write("scan", args.cloud, args.out, spec_path=args.plate,
                               options={"seed": args.seed, "validation": args.validation,
                                        "no_report": args.no_report, "model": args.model,
                                        "rotation_hint_deg": (float("nan") if args.rotation_hint_deg is None
                                                              else args.rotation_hint_deg),
                                        "orientation": args.orientation, "mirror": args.mirror},
                               progress=say)
    s = res.summary
    say(f"orientation {s['in_plane_rotation_deg']:.1f} deg{' mirrored' if s['mirrored'] else ''} "
        f"({s['orientation_method']}; galvo-model margin {s['orientation_margin'] or float('inf'):.2f})")
    say(f"{s['n_detected']}/{s['n_expected']} fiducials, deviation RMS {s['rms_mm']:.4f} mm, "
        f"max {s['max_mm']:.4f} mm; model {s['model']}, CV RMSE {s['cv_rmse_mm']:.4f} mm")
    if s["orientation_method"].startswith("assumed"):
        say("warning: orientation assumed upright (within 35 deg); the galvo field cannot tell quarter turns "
            "apart, so a plate laid otherwise needs --rotation-hint-deg or an orientation mark")
    if res.missing_ids:
        say(f"not detected: ids {res.missing_ids}")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return 0


def cmd_render_scan(args) -> int:
    from markcal.fixtures.gls import sample_true_galvo
    from markcal.fixtures.scan_plate import ScanOptions, render_scan, save_scan
    from markcal.reports.files import read_csv
    from markcal.stages.deviation import GridCorrection
    from markcal.stages.plate import PlateSpec

    say = progress(args.quiet)
    mark = ()
    if args.orientation_mark:
        try:
            mark = tuple(int(v) for v in args.orientation_mark.split(","))
        except ValueError:
            mark = (-1,)
        if len(mark) != 2 or not (0 <= mark[0] < args.rows and 0 <= mark[1] < args.cols):
            raise MarkcalError(f"--orientation-mark must be ROW,COL inside the grid (got {args.orientation_mark!r})")
    spec = PlateSpec(rows=args.rows, cols=args.cols,
                     pitch_mm=args.pitch_mm if args.pitch_mm else PlateSpec().pitch_mm, orientation_mark=mark)
    correction = None
    if args.correction:
        try:
            t = read_csv(args.correction)
            grid = GridCorrection.from_nodes(np.column_stack([t["x_mm"], t["y_mm"]]),
                                             np.column_stack([t["dx_mm"], t["dy_mm"]]))
        except (OSError, KeyError, IndexError, ValueError) as exc:
            raise MarkcalError(f"cannot read correction grid ({exc})", args.correction) from None
        except MarkcalError as exc:
            raise exc.with_path(args.correction) from None
        correction = grid.command
    mseed = args.seed if args.machine_seed is None else args.machine_seed
    machine = sample_true_galvo(np.random.default_rng([mseed, 1]), spec.d_mm, spec.e_mm)
    opts = ScanOptions(z_convention=args.z_convention, n_contaminated=args.contaminated,
                       rotation_deg=args.rotation_deg, mirror=args.mirror)
    say(f"rendering {'validation' if correction else 'calibration'} plate, seed {args.seed}")
    r = render_scan(args.seed, spec, opts, machine=machine, correction=correction)
    r.truth["machine_seed"] = int(mseed)
    say(f"writing {len(r.xyz_mm):,} points")
    save_scan(args.out, r, "cloud", formats=tuple(args.formats.split(",")))
    print(os.path.abspath(args.out))
    return 0


def register(sub, render_sub) -> None:
    """Add ``scan`` to the top-level commands and ``scan`` to ``render``."""
    sc = sub.add_parser("scan", help="3D scan of a galvo-marked plate -> deviations, correction, report")
    sc.add_argument("cloud", help="point cloud: .ply (with intensity), .pcd, .csv/.txt/.xyz, .npy (N x 4), mm")
    sc.add_argument("--plate", required=True, help="plate spec (PLATE.toml)")
    sc.add_argument("--out", required=True, help="output folder")
    sc.add_argument("--validation", action="store_true", help="label the report as a validation (post-calibration) scan")
    sc.add_argument("--seed", type=int, default=0, help="seed of the random steps (RANSAC, CV folds)")
    sc.add_argument("--model", default="ols-rbf", choices=["ols-rbf", "physical+rbf", "rbf", "poly3", "auto"],
                    help="correction model: the paper's OLS RBF network (default), the galvo model of paper 004 "
                         "eqs. 1-5 plus a thin-plate spline, a spline, a cubic, or auto (lowest k-fold CV error)")
    sc.add_argument("--rotation-hint-deg", type=float, default=None,
                    help="the plate's approximate in-plane angle in the scan (deg, +-35): picks the orientation")
    sc.add_argument("--orientation", default="upright", choices=["upright", "auto"],
                    help="without a hint or an orientation mark: assume the plate lies within +-35 deg of upright "
                         "(default), or let the galvo model choose (refused unless its margin is wide)")
    sc.add_argument("--mirror", default="no", choices=["no", "yes", "auto"],
                    help="the measurement sees the plate from the back (flatbed face down): no, yes, auto")
    sc.add_argument("--no-report", action="store_true", help="skip report.html")
    sc.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    sc.set_defaults(func=cmd_scan)

    rs = render_sub.add_parser("scan", help="laser-line scan of a galvo-marked plate")
    rs.add_argument("--seed", type=int, default=0)
    rs.add_argument("--out", required=True)
    rs.add_argument("--rows", type=int, default=19)
    rs.add_argument("--cols", type=int, default=19)
    rs.add_argument("--pitch-mm", type=float, default=None)
    rs.add_argument("--correction", help="correction_grid.csv: render a validation plate marked through it")
    rs.add_argument("--machine-seed", type=int, default=None, help="seed of the true galvo (default: --seed)")
    rs.add_argument("--z-convention", choices=["random", "height", "range"], default="random")
    rs.add_argument("--contaminated", type=int, default=0, help="fiducials hidden under dirt")
    rs.add_argument("--rotation-deg", type=float, default=None, help="in-plane turn of the plate (default: random +-15)")
    rs.add_argument("--mirror", action="store_true", help="render the cloud as seen from the back")
    rs.add_argument("--orientation-mark", default=None, help="ROW,COL of a grid site left unmarked")
    rs.add_argument("--formats", default="ply,npy", help="comma list of ply, npy")
    rs.add_argument("--quiet", action="store_true")
    rs.set_defaults(func=cmd_render_scan)
