"""The ``markcal`` command line."""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

import numpy as np

from markcal.stages.errors import MarkcalError


#: modules that add their own sub-commands: each has ``register(sub, render_sub)``
#: taking the top-level and the ``render`` sub-parser collections.
COMMAND_MODULES: tuple = (
    "markcal.pipeline.cli_indents",
    "markcal.pipeline.cli_selfcal",
    "markcal.pipeline.cli_pmcal",
    "markcal.pipeline.cli_path",
    "markcal.pipeline.cli_servo",
    "markcal.pipeline.cli_grid",
    "markcal.pipeline.cli_export",
    "markcal.pipeline.cli_batch",
)


def progress(quiet: bool):
    t0 = time.perf_counter()

    def say(msg: str) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)
    return say


def cmd_render_scan(args) -> int:
    from markcal.fixtures.gls import sample_true_galvo
    from markcal.fixtures.scan_plate import ScanOptions, render_scan
    from markcal.pipeline.config import plate_spec_toml
    from markcal.reports.files import atomic_write_text, read_csv, write_json, write_npy, write_ply
    from markcal.stages.deviation import GridCorrection
    from markcal.stages.plate import PlateSpec

    say = progress(args.quiet)
    spec = PlateSpec(rows=args.rows, cols=args.cols,
                     pitch_mm=args.pitch_mm if args.pitch_mm else PlateSpec().pitch_mm)
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
    opts = ScanOptions(z_convention=args.z_convention, n_contaminated=args.contaminated)
    say(f"rendering {'validation' if correction else 'calibration'} plate, seed {args.seed}")
    r = render_scan(args.seed, spec, opts, machine=machine, correction=correction)
    r.truth["machine_seed"] = int(mseed)
    os.makedirs(args.out, exist_ok=True)
    say(f"writing {len(r.xyz_mm):,} points")
    if "ply" in args.formats:
        write_ply(os.path.join(args.out, "cloud.ply"), r.xyz_mm, r.intensity)
    if "npy" in args.formats:
        write_npy(os.path.join(args.out, "cloud.npy"), np.column_stack([r.xyz_mm, r.intensity]))
    atomic_write_text(os.path.join(args.out, "plate.toml"), plate_spec_toml(spec))
    write_json(os.path.join(args.out, "truth.json"), r.truth)
    print(os.path.abspath(args.out))
    return 0


def cmd_scan(args) -> int:
    from markcal.pipeline.config import read_plate_spec
    from markcal.pipeline.flows.scan import ScanOptions, run_scan
    from markcal.reports.scan_outputs import write_scan_outputs

    say = progress(args.quiet)
    spec = read_plate_spec(args.plate)
    res = run_scan(args.cloud, spec, ScanOptions(seed=args.seed, validation=args.validation), progress=say)
    say("writing tables and report")
    paths = write_scan_outputs(res, args.out, report=not args.no_report)
    s = res.summary
    say(f"{s['n_detected']}/{s['n_expected']} fiducials, deviation RMS {s['rms_mm']:.4f} mm, "
        f"max {s['max_mm']:.4f} mm; RBF {s['n_neurons']} neurons, CV RMSE {s['cv_rmse_mm']:.4f} mm")
    if res.missing_ids:
        say(f"not detected: ids {res.missing_ids}")
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="markcal", description="Measure marked plates; write correction tables and reports.")
    sub = ap.add_subparsers(dest="command", required=True)

    sc = sub.add_parser("scan", help="3D scan of a galvo-marked plate -> deviations, correction, report")
    sc.add_argument("cloud", help="point cloud: .ply (with intensity), .pcd, .csv/.txt/.xyz, .npy (N x 4), mm")
    sc.add_argument("--plate", required=True, help="plate spec (PLATE.toml)")
    sc.add_argument("--out", required=True, help="output folder")
    sc.add_argument("--validation", action="store_true", help="label the report as a validation (post-calibration) scan")
    sc.add_argument("--seed", type=int, default=0, help="seed of the random steps (RANSAC, CV folds)")
    sc.add_argument("--no-report", action="store_true", help="skip report.html")
    sc.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    sc.set_defaults(func=cmd_scan)

    rd = sub.add_parser("render", help="render synthetic instrument data with ground truth")
    rsub = rd.add_subparsers(dest="what", required=True)
    rs = rsub.add_parser("scan", help="laser-line scan of a galvo-marked plate")
    rs.add_argument("--seed", type=int, default=0)
    rs.add_argument("--out", required=True)
    rs.add_argument("--rows", type=int, default=19)
    rs.add_argument("--cols", type=int, default=19)
    rs.add_argument("--pitch-mm", type=float, default=None)
    rs.add_argument("--correction", help="correction_grid.csv: render a validation plate marked through it")
    rs.add_argument("--machine-seed", type=int, default=None, help="seed of the true galvo (default: --seed)")
    rs.add_argument("--z-convention", choices=["random", "height", "range"], default="random")
    rs.add_argument("--contaminated", type=int, default=0, help="fiducials hidden under dirt")
    rs.add_argument("--formats", default="ply,npy", help="comma list of ply, npy")
    rs.add_argument("--quiet", action="store_true")
    rs.set_defaults(func=cmd_render_scan)

    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub, rsub)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except MarkcalError as exc:
        print(f"markcal: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("markcal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
