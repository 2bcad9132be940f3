"""``markcal scan`` and ``markcal render scan``."""
from __future__ import annotations

import argparse
import os

import numpy as np

from markcal.pipeline.cli_common import add_run_options
from markcal.pipeline.progress import progress
from markcal.stages.errors import MarkcalError
from markcal.stages.plate import DEFAULT_ORIENTATION_MARK

DEFAULT_MARK_TEXT = ",".join(str(v) for v in DEFAULT_ORIENTATION_MARK)


def cmd_scan(args) -> int:
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.registry import exit_status, run_and_write

    say = progress(args.quiet)
    res, paths = run_and_write("scan", args.cloud, args.out, spec_path=args.plate,
                               options={"seed": args.seed, "purpose": args.purpose or "",
                                        "no_report": args.no_report, "model": args.model,
                                        "rotation_hint_deg": (float("nan") if args.rotation_hint_deg is None
                                                              else args.rotation_hint_deg),
                                        "orientation": args.orientation, "mirror": args.mirror,
                                        "pixel_size_mm": (float("nan") if args.pixel_size_mm is None
                                                          else args.pixel_size_mm), "view": args.view},
                               progress=say, **run_options(args))
    s = res.summary
    say(f"orientation {s['in_plane_rotation_deg']:.1f} deg{' mirrored' if s['mirrored'] else ''} "
        f"({s['orientation_method']}; galvo-model margin {s['orientation_margin'] or float('inf'):.2f})")
    say(f"{s['n_detected']}/{s['n_expected']} fiducials, deviation RMS {s['rms_mm']:.4f} mm, "
        f"max {s['max_mm']:.4f} mm; model {s['model']}, CV RMSE {s['cv_rmse_mm']:.4f} mm")
    if res.missing_ids:
        say(f"not detected: ids {res.missing_ids}")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return exit_status(res.summary)


def cmd_render_scan(args) -> int:
    from markcal.fixtures.gls import sample_true_galvo
    from markcal.fixtures.scan_plate import ScanOptions, render_scan, save_scan
    from markcal.reports.files import read_csv
    from markcal.stages.deviation import GridCorrection
    from markcal.stages.plate import PlateSpec

    say = progress(args.quiet)
    mark = _parse_mark(args.orientation_mark, args.rows, args.cols)
    spec = PlateSpec(rows=args.rows, cols=args.cols,
                     pitch_mm=args.pitch_mm if args.pitch_mm else PlateSpec().pitch_mm, orientation_mark=mark,
                     purpose="validation" if args.correction else "calibration")
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
    r = render_scan(args.seed, spec, opts, machine=machine, correction=correction, say=say)
    r.truth["machine_seed"] = int(mseed)
    say(f"writing {len(r.xyz_mm):,} points")
    save_scan(args.out, r, "cloud", formats=tuple(args.formats.split(",")))
    print(os.path.abspath(args.out))
    return 0


def cmd_render_scan_image(args) -> int:
    from markcal.fixtures.plate_camera import CameraOptions, render_camera_image
    from markcal.fixtures.plate_image import MATERIALS, ImageOptions, render_plate_image, save_plate_image
    from markcal.stages.plate import PlateSpec

    say = progress(args.quiet)
    if not 100 <= args.dpi <= 4800:
        raise MarkcalError(f"--dpi must be within 100..4800 (got {args.dpi:g})")
    if args.material not in MATERIALS:
        raise MarkcalError(f"--material must be one of {', '.join(MATERIALS)}")
    mark = _parse_mark(args.orientation_mark, args.rows, args.cols)
    spec = PlateSpec(rows=args.rows, cols=args.cols,
                     pitch_mm=args.pitch_mm if args.pitch_mm else PlateSpec().pitch_mm, orientation_mark=mark)
    opts = ImageOptions(dpi=args.dpi, rotation_deg=args.rotation_deg, mirror=args.mirror, material=args.material,
                        bits=args.bits, rgb=args.rgb, jpeg_quality=args.jpeg_quality, n_dust=args.dust)
    if args.camera:
        if not (0 <= args.tilt_deg < 30 and 1 <= args.focal_mm <= 1000):
            raise MarkcalError(f"--tilt-deg must be within 0..30 and --focal-mm within 1..1000 (got {args.tilt_deg:g}, "
                               f"{args.focal_mm:g})")
        cam = CameraOptions(focal_mm=args.focal_mm, tilt_deg=args.tilt_deg, k1=args.k1, k2=args.k2)
        say(f"rendering a camera image ({args.tilt_deg:g} deg tilt, {args.dpi:g} dpi at the plate centre) of a "
            f"{args.rows} x {args.cols} plate, seed {args.seed}")
        r = render_camera_image(args.seed, spec, opts, cam)
    else:
        say(f"rendering a {args.dpi:g} dpi image of a {args.rows} x {args.cols} plate, seed {args.seed}")
        r = render_plate_image(args.seed, spec, opts)
    save_plate_image(args.out, r, fmt=args.format, dpi_tags=not (args.no_dpi or args.camera))
    print(os.path.abspath(args.out))
    return 0


def _parse_mark(text, rows, cols) -> tuple:
    """``ROW,COL`` of the site the rendered plate leaves unmarked; ``none``: every site marked."""
    if text.strip().lower() == "none":
        return ()
    try:
        mark = tuple(int(v) for v in text.split(","))
    except ValueError:
        mark = (-1,)
    if len(mark) != 2 or not (0 <= mark[0] < rows and 0 <= mark[1] < cols):
        raise MarkcalError(f"--orientation-mark must be ROW,COL inside the grid (got {text!r})")
    return mark


def register(sub, render_sub) -> None:
    """Add ``scan`` to the top-level commands and ``scan`` to ``render``."""
    sc = sub.add_parser("scan", help="3D scan of a galvo-marked plate -> deviations, correction, report")
    sc.add_argument("cloud", help="point cloud: .ply (with intensity), .pcd, .csv/.txt/.xyz, .npy (N x 4), mm; "
                                  "or an image of the plate: .tif/.png/.jpg (flatbed, grey or RGB, 8/16 bit)")
    sc.add_argument("--pixel-size-mm", type=float, default=None,
                    help="images: pixel size on the plate (default: from the file's dpi tags; refused when absent)")
    sc.add_argument("--view", default="auto", choices=["auto", "flatbed"],
                    help="images: auto refuses an image whose marks show perspective (a camera view); flatbed takes "
                         "the view as flat (a plate marked with no lens correction can look like perspective)")
    sc.add_argument("--plate", required=True, help="plate spec (PLATE.toml)")
    sc.add_argument("--out", required=True, help="output folder")
    sc.add_argument("--purpose", choices=["calibration", "validation"], default=None,
                    help="calibration: a plate marked without correction, judged on what the correction will achieve "
                         "(predicted residual, CV error, every mark found); validation: marked through the correction, "
                         "judged on its deviation (default: the plate spec's [plate] purpose, else calibration)")
    sc.add_argument("--validation", dest="purpose", action="store_const", const="validation",
                    help=argparse.SUPPRESS)     # old spelling of --purpose validation
    sc.add_argument("--seed", type=int, default=0, help="seed of the random steps (RANSAC, CV folds)")
    sc.add_argument("--model", default="ols-rbf", choices=["ols-rbf", "physical+rbf", "rbf", "poly3", "auto"],
                    help="correction model: the paper's OLS RBF network (default), the galvo model of paper 004 "
                         "eqs. 1-5 plus a thin-plate spline, a spline, a cubic, or auto (lowest k-fold CV error)")
    sc.add_argument("--rotation-hint-deg", type=float, default=None,
                    help="the plate's in-plane angle in the scan to within +-44 deg (0: laid upright): picks the "
                         "orientation when the plate spec declares no orientation mark")
    sc.add_argument("--orientation", default="auto", choices=["auto", "upright"],
                    help="without a hint or an orientation mark: let the galvo model choose, which refuses unless its "
                         "margin is wide (default; a turn by 180 deg always ties), or upright (= --rotation-hint-deg 0)")
    sc.add_argument("--mirror", default="no", choices=["no", "yes", "auto"],
                    help="the measurement sees the plate from the back (flatbed face down): no, yes, auto")
    sc.add_argument("--no-report", action="store_true", help="skip report.html")
    sc.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(sc)
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
    rs.add_argument("--orientation-mark", default=DEFAULT_MARK_TEXT,
                    help="ROW,COL of the grid site left unmarked, so the scan can tell the plate's orientation "
                         "(default 0,1; none: every site marked, the scan then needs --rotation-hint-deg)")
    rs.add_argument("--formats", default="ply,npy", help="comma list of ply, npy")
    rs.add_argument("--quiet", action="store_true")
    rs.set_defaults(func=cmd_render_scan)

    ri = render_sub.add_parser("scan-image", help="flatbed or camera image of a galvo-marked plate, with truth")
    ri.add_argument("--seed", type=int, default=0)
    ri.add_argument("--out", required=True)
    ri.add_argument("--rows", type=int, default=19)
    ri.add_argument("--cols", type=int, default=19)
    ri.add_argument("--pitch-mm", type=float, default=None)
    ri.add_argument("--dpi", type=float, default=1200.0,
                    help="flatbed resolution (600-2400 typical); with --camera, the pixel's footprint at the plate centre")
    ri.add_argument("--camera", action="store_true",
                    help="a pinhole camera over the plate (tilt, lens distortion, vignetting), written with no dpi")
    ri.add_argument("--tilt-deg", type=float, default=3.0, help="--camera: tilt of the optical axis")
    ri.add_argument("--focal-mm", type=float, default=35.0, help="--camera: focal length (3.45 um sensor pixels)")
    ri.add_argument("--k1", type=float, default=-0.05, help="--camera: radial distortion k1 (normalised coordinates)")
    ri.add_argument("--k2", type=float, default=0.01, help="--camera: radial distortion k2")
    ri.add_argument("--rotation-deg", type=float, default=None, help="in-plane turn (default: random +-5)")
    ri.add_argument("--mirror", action="store_true", help="plate face down on the glass")
    ri.add_argument("--material", default="anodised", help="anodised (bright marks) or paper (dark marks)")
    ri.add_argument("--bits", type=int, choices=[8, 16], default=8)
    ri.add_argument("--rgb", action="store_true")
    ri.add_argument("--jpeg-quality", type=int, default=None, help="pass the pixels through JPEG at this quality")
    ri.add_argument("--dust", type=int, default=60, help="dust specks")
    ri.add_argument("--orientation-mark", default=DEFAULT_MARK_TEXT,
                    help="ROW,COL of the grid site left unmarked, so the scan can tell the plate's orientation "
                         "(default 0,1; none: every site marked, the scan then needs --rotation-hint-deg)")
    ri.add_argument("--format", choices=["tif", "png", "jpg"], default="tif")
    ri.add_argument("--no-dpi", action="store_true", help="write no resolution tags (the scan then needs --pixel-size-mm)")
    ri.add_argument("--quiet", action="store_true")
    ri.set_defaults(func=cmd_render_scan_image)
