"""Benchmark of the grid flow (issue 14): accuracy against the true machine, model comparison, speed.

Prints:
1. 9 x 9 marks over a 110 mm lens, 0.02 mm noise, several seeds: landing RMS left
   by the correction on the true machine over the measured area and over the
   lens field (goals 0.03 / 0.08 mm), and the 5-fold CV error over the noise
   (Euclidean CV error / (sqrt(2) sigma); goal <= 1.3).
2. Synthetic cases from 7 x 7 to 21 x 21 over 50-300 mm lenses, noise 0.01-0.1 mm:
   k-fold CV error of physical+rbf against rbf (thin-plate spline alone), both
   against the measurements (what a user sees) and against the noise-free
   landings (what the model predicts); goal: physical+rbf >= 10 % better.
3. Wall time of ``markcal grid`` and ``markcal export cor`` as commands on 81
   marks (median of repeats; goal <= 1 s for both together).

Usage: ``python benchmarks/bench_grid.py [--seeds 8] [--repeats 5]``
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.gls import correction_residual
from markcal.fixtures.measured_grid import GridRenderOptions, render_grid
from markcal.pipeline.flows.grid import GridOptions, run_grid
from markcal.reports.files import write_csv


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1))))


def _run(r, folder, lens_mm, model="physical+rbf"):
    path = os.path.join(folder, "measured.csv")
    write_csv(path, {"x_cmd_mm": r.cmd_mm[:, 0], "y_cmd_mm": r.cmd_mm[:, 1],
                     "x_meas_mm": r.meas_mm[:, 0], "y_meas_mm": r.meas_mm[:, 1]})
    return run_grid(path, GridOptions(model=model, lens_mm=lens_mm))


def _clean_registered(r, res):
    """Noise-free measured positions, registered like the measured ones."""
    t = r.truth
    a = np.radians(t["frame_angle_deg"])
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    if t["mirror"]:
        rot = rot @ np.diag([1.0, -1.0])
    return res.registration.apply(r.land_mm @ rot.T + np.array(t["frame_shift_mm"]))


def accuracy(seeds: int, folder: str) -> None:
    print("1. 9 x 9 over 110 mm, noise 0.02 mm (goals: area <= 0.030, field <= 0.080 mm RMS, CV/noise <= 1.3)")
    print(f"{'seed':>4} {'mirror':>6} {'before':>8} {'area':>7} {'field':>7} {'CV/noise':>8} {'runtime':>8}")
    rows = []
    for seed in range(seeds):
        o = GridRenderOptions(mirror=bool(seed % 2))
        r = render_grid(seed, o)
        res = _run(r, folder, o.lens_mm)
        half_area = o.fill * o.lens_mm / 2
        _, before = correction_residual(r.machine, lambda w: w, half_area, half_area, 1.0)
        _, area = correction_residual(r.machine, res.model.command, half_area, half_area, 1.0)
        _, field = correction_residual(r.machine, res.model.command, o.lens_mm / 2, o.lens_mm / 2, 1.0)
        ratio = res.summary["cv_rmse_mm"] / (np.sqrt(2) * o.noise_mm)
        rows.append((_rms(area), _rms(field), ratio))
        print(f"{seed:4d} {str(o.mirror):>6} {_rms(before):8.4f} {_rms(area):7.4f} {_rms(field):7.4f} {ratio:8.3f} "
              f"{res.summary['runtime_s']:7.3f}s")
    a = np.array(rows)
    print(f"worst: area {a[:, 0].max():.4f} mm, field {a[:, 1].max():.4f} mm, CV/noise {a[:, 2].max():.3f}; "
          f"median: {np.median(a[:, 0]):.4f}, {np.median(a[:, 1]):.4f}, {np.median(a[:, 2]):.3f}")


CASES = [(7, 50, 0.01), (9, 110, 0.02), (9, 110, 0.05), (11, 160, 0.03), (11, 110, 0.1), (15, 220, 0.05),
         (21, 300, 0.1), (21, 300, 0.02), (7, 300, 0.05)]


def comparison(folder: str, seeds: int = 2) -> None:
    print("\n2. physical+rbf vs rbf alone, 5-fold CV, same folds (goal: >= 10 % better on every case)")
    print(f"{'grid':>7} {'lens':>5} {'noise':>5} {'seed':>4} | {'vs measured: phys':>17} {'rbf':>7} {'better':>7} | "
          f"{'vs truth: phys':>14} {'rbf':>7} {'better':>7} | {'field phys':>10} {'field rbf':>9}")
    worst_meas, worst_truth = np.inf, np.inf
    for n, lens, noise in CASES:
        for seed in range(seeds):
            o = GridRenderOptions(rows=n, cols=n, lens_mm=lens, noise_mm=noise, mirror=bool(seed % 2))
            r = render_grid(100 + seed, o)
            res = _run(r, folder, lens)
            clean = _clean_registered(r, res)
            land = np.column_stack([res.fiducials["x_meas_mm"], res.fiducials["y_meas_mm"]])
            e = res.choice.cv_errors_mm
            m = {k: _rms(e[k]) for k in ("physical+rbf", "rbf")}
            t = {k: _rms(e[k] + land - clean) for k in ("physical+rbf", "rbf")}
            bm = 100 * (1 - m["physical+rbf"] / m["rbf"])
            bt = 100 * (1 - t["physical+rbf"] / t["rbf"])
            worst_meas, worst_truth = min(worst_meas, bm), min(worst_truth, bt)
            res_rbf = _run(r, folder, lens, model="rbf")
            fld = [_rms(correction_residual(r.machine, x.model.command, lens / 2, lens / 2, lens / 50)[1])
                   for x in (res, res_rbf)]
            print(f"{n:3d}x{n:<3d} {lens:5.0f} {noise:5.2f} {seed:4d} | {m['physical+rbf']:17.4f} {m['rbf']:7.4f} "
                  f"{bm:6.1f}% | {t['physical+rbf']:14.4f} {t['rbf']:7.4f} {bt:6.1f}% | {fld[0]:10.4f} {fld[1]:9.4f}")
    print(f"smallest improvement: {worst_meas:.1f} % against the measurements, {worst_truth:.1f} % against the "
          "noise-free landings")


#: the same two commands through a parser that registers only their modules (what lazy registration would cost)
LEAN_CLI = ("import argparse, sys\n"
            "from markcal.pipeline import cli_export, cli_grid\n"
            "from markcal.pipeline.cli import main\n"
            "ap = argparse.ArgumentParser(); sub = ap.add_subparsers(dest='command', required=True)\n"
            "rs = sub.add_parser('render').add_subparsers()\n"
            "cli_grid.register(sub, rs); cli_export.register(sub, rs)\n"
            "import markcal.pipeline.cli as c; c.build_parser = lambda: ap\n"
            "sys.exit(main(sys.argv[1:]))\n")


def speed(folder: str, repeats: int) -> None:
    print("\n3. 81 marks -> .cor as commands (median of %d; goal <= 1 s together)" % repeats)
    r = render_grid(0, GridRenderOptions(n_missing=0))
    path = os.path.join(folder, "speed.csv")
    write_csv(path, {"x_cmd_mm": r.cmd_mm[:, 0], "y_cmd_mm": r.cmd_mm[:, 1],
                     "x_meas_mm": r.meas_mm[:, 0], "y_meas_mm": r.meas_mm[:, 1]})
    exe = [sys.executable, "-m", "markcal.pipeline.cli"]
    out = os.path.join(folder, "speed_out")
    cor = os.path.join(folder, "speed.cor")
    for label, extra in (("with report.html", []), ("--no-report", ["--no-report"])):
        tg, te = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            subprocess.run(exe + ["grid", path, "--out", out, "--quiet", "--lens-mm", "110", *extra], check=True,
                           stdout=subprocess.DEVNULL)
            t1 = time.perf_counter()
            subprocess.run(exe + ["export", "cor", out, "--lens-mm", "110", "--out", cor, "--quiet"], check=True,
                           stdout=subprocess.DEVNULL)
            t2 = time.perf_counter()
            tg.append(t1 - t0)
            te.append(t2 - t1)
        tot = np.array(tg) + np.array(te)
        print(f"{label:17s}: grid {np.median(tg):.3f} s + export cor {np.median(te):.3f} s = {np.median(tot):.3f} s")
    lean = [sys.executable, "-c", LEAN_CLI]
    tl = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(lean + ["grid", path, "--out", out, "--quiet", "--lens-mm", "110", "--no-report"], check=True,
                       stdout=subprocess.DEVNULL)
        subprocess.run(lean + ["export", "cor", out, "--lens-mm", "110", "--out", cor, "--quiet"], check=True,
                       stdout=subprocess.DEVNULL)
        tl.append(time.perf_counter() - t0)
    print(f"--no-report through a parser holding only grid and export: {np.median(tl):.3f} s together")
    th = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(exe + ["--help"], check=True, capture_output=True)
        th.append(time.perf_counter() - t0)
    print(f"(python start-up and the CLI's imports alone, `markcal --help`: {np.median(th):.3f} s)")
    from markcal.pipeline.flows.export import export_table
    from markcal.reports.files import atomic_write_bytes
    from markcal.reports.grid_outputs import write_grid_outputs
    for label, rep in (("with report.html", True), ("--no-report", False)):
        tw = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = run_grid(path, GridOptions(lens_mm=110.0))
            write_grid_outputs(res, out, report=rep)
            atomic_write_bytes(cor, export_table("cor", out, lens_mm=110.0)[0])
            tw.append(time.perf_counter() - t0)
        print(f"in one process, {label:17s}: read, fit, CV, write, export .cor {np.median(tw):.3f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--skip-speed", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        accuracy(args.seeds, folder)
        comparison(folder)
        if not args.skip_speed:
            speed(folder, args.repeats)


if __name__ == "__main__":
    main()
