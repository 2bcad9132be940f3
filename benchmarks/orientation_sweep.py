"""Orientation at any angle: rendered plates at random angles (and exactly 45, 90, 135 deg), with and
without a mirror, through the scan flow in each way of deciding the orientation: the plate spec's
orientation mark (what `markcal render scan` writes by default), no mark and no hint (the default must
refuse), and no mark with a rotation hint 30 deg off the true angle (mirrored plates with ``--mirror yes``;
the hint is the direction of the plate's rows, its x axis, in the scan frame: for the renderer's mirror,
which negates the scanner x, that is 180 deg minus the rendered angle).

Truth: the renderer's true fiducial positions (its own galvo and pose, not the flow's model). A plate
counts as right when every detected fiducial sits within 0.1 mm of the true position of its id, wrong
when any does not, refused when the flow stops with a message. Prints one line per plate and a table.

    python benchmarks/orientation_sweep.py [N]      (default 54 plates, 7 x 7)

Prints the load average and the CPU time with the wall time (the machine is shared).
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np

from markcal.fixtures.scan_plate import ScanOptions, render_scan
from markcal.pipeline.flows.scan import ScanOptions as FlowOptions
from markcal.pipeline.flows.scan import _run
from markcal.stages.errors import MarkcalError
from markcal.stages.io import PointCloud
from markcal.stages.plate import PlateSpec

MARKED = PlateSpec(rows=7, cols=7, orientation_mark=(0, 1))
PLAIN = PlateSpec(rows=7, cols=7)
MODES = {  # name -> (spec the flow is given, flow options); "hint" options get the plate's angle + 30 deg
    "orientation mark": (MARKED, {"mirror": "auto"}),
    "no mark, no hint": (PLAIN, {"mirror": "auto"}),
    "hint 30 deg off": (PLAIN, {"hint": 30.0}),
}


def row_direction_deg(angle_deg: float, mirrored: bool) -> float:
    """Direction of the plate's x axis in the scan frame (what ``--rotation-hint-deg`` gives)."""
    return (180.0 - angle_deg) if mirrored else angle_deg


def outcome(render, spec, opts):
    cloud = PointCloud(render.xyz_mm, render.intensity)
    try:
        res = _run(cloud, "sweep", spec, FlowOptions(**opts), lambda m: None, time.perf_counter())
    except MarkcalError as exc:
        return "refused", None, str(exc)
    t = render.truth["fiducials"]
    ids = res.fiducials["id"]
    err = np.hypot(res.fiducials["x_scanner_mm"] - np.array(t["x_scanner_mm"])[ids],
                   res.fiducials["y_scanner_mm"] - np.array(t["y_scanner_mm"])[ids])
    return ("right" if err.max() < 0.1 else "wrong"), res.summary.get("orientation_margin"), ""


def main(n=54):
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    rng = np.random.default_rng(2026)
    angles = [45.0, 90.0, 135.0, -90.0, 180.0, -45.0] + list(rng.uniform(-180, 180, max(n - 6, 0)))
    counts = {m: {"right": 0, "wrong": 0, "refused": 0} for m in MODES}
    margins = []
    for i, ang in enumerate(angles[:n]):
        mirror = bool(i % 2)
        r = render_scan(500 + i, MARKED, ScanOptions(rotation_deg=float(ang), mirror=mirror))
        line = [f"plate {i:2d} {ang:7.1f} deg{' mirrored' if mirror else '         '}"]
        for mode, (spec, opts) in MODES.items():
            if "hint" in opts:
                opts = {"rotation_hint_deg": row_direction_deg(float(ang), mirror) + opts["hint"],
                        "mirror": "yes" if mirror else "no"}
            o, margin, msg = outcome(r, spec, opts)
            counts[mode][o] += 1
            if mode == "orientation mark" and margin is not None:
                margins.append(margin)
            line.append(f"{mode}: {o}" + (f" ({msg[:60]}...)" if o == "refused" and mode != "no mark, no hint" else ""))
        print(" | ".join(line), flush=True)
    print("\nmode                  right  wrong  refused  (of", n, "plates)")
    for mode, c in counts.items():
        print(f"{mode:20s} {c['right']:6d} {c['wrong']:6d} {c['refused']:8d}")
    print(f"wall {time.perf_counter() - t0:.0f} s, CPU {time.process_time() - c0:.0f} s, load average "
          f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end, {os.cpu_count()} cores")
    m = np.array(margins)
    print(f"galvo-model margin (best other orientation / chosen, residual RMS): median {np.median(m):.3f}, "
          f"min {m.min():.3f}, max {m.max():.3f}; decides alone only at >= 2")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 54)
