"""Benchmark: the scan flow on a full-size (~5 M point) plate, and RBF training + selection.

Prints medians over several runs. Usage: python benchmarks/bench_scan.py [--runs N] [--seed S]
"""
import argparse
import os
import platform
import statistics
import tempfile
import time

import numpy as np

from markcal.fixtures.scan_plate import ScanOptions as RenderOptions, render_scan
from markcal.pipeline.flows.scan import MSE_GOALS_MM2, SPREADS_PER_PITCH, run_scan
from markcal.reports.files import write_ply
from markcal.reports.scan_outputs import write_scan_outputs
from markcal.stages import rbf
from markcal.stages.plate import PlateSpec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    spec = PlateSpec(orientation_mark=(0, 1))     # site 0,1 unmarked: the flow refuses a plate of unknown orientation
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}")
    r = render_scan(args.seed, spec, RenderOptions(n_contaminated=1))
    tmp = tempfile.mkdtemp(prefix="markcal-bench-")
    cloud = os.path.join(tmp, "cloud.ply")
    write_ply(cloud, r.xyz_mm, r.intensity)
    print(f"cloud: {len(r.xyz_mm):,} points, {os.path.getsize(cloud) / 1e6:.0f} MB PLY")
    flow, outputs, rbf_s, res = [], [], [], None
    for i in range(args.runs):
        t = time.perf_counter()
        res = run_scan(cloud, spec)
        flow.append(time.perf_counter() - t)
        t = time.perf_counter()
        write_scan_outputs(res, os.path.join(tmp, f"out{i}"))
        outputs.append(time.perf_counter() - t)
        p = np.column_stack([res.fiducials["x_meas_mm"], res.fiducials["y_meas_mm"]])
        d = np.column_stack([res.fiducials["dx_mm"], res.fiducials["dy_mm"]])
        t = time.perf_counter()
        sel = rbf.select(p, d, np.array(SPREADS_PER_PITCH) * spec.pitch_mm, MSE_GOALS_MM2, 5, 0, 200)
        rbf.train(p, d, sel.spread_mm, sel.mse_goal_mm2, 200)
        rbf_s.append(time.perf_counter() - t)
    med = statistics.median
    print(f"scan flow (read PLY -> model, tables in memory): median {med(flow):.2f} s "
          f"(min {min(flow):.2f}, max {max(flow):.2f}) over {args.runs} runs; goal <= 10 s")
    print(f"writing outputs incl. report.html: median {med(outputs):.2f} s")
    print(f"flow + outputs: median {med([a + b for a, b in zip(flow, outputs)]):.2f} s")
    print(f"RBF selection (5-fold CV, {len(SPREADS_PER_PITCH)} spreads x {len(MSE_GOALS_MM2)} goals) + training: "
          f"median {med(rbf_s):.2f} s; goal <= 1 s")
    print(f"detected {res.summary['n_detected']}/{res.summary['n_expected']}, neurons {res.summary['n_neurons']}")


if __name__ == "__main__":
    main()
