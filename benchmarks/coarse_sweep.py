"""Coarse scans: 7 x 7 plates at a given point spacing (seeds 5-10, height z, NPY round trip) through the
scan flow; marks found against the marks on the plate, and the centre error against the renderer's truth.

    python benchmarks/coarse_sweep.py [SPACING_MM ...]      (default 0.2)
"""
from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.scan_plate import ScanOptions, render_scan
from markcal.pipeline.flows.scan import run_scan
from markcal.stages.errors import MarkcalError
from markcal.stages.plate import DEFAULT_ORIENTATION_MARK, PlateSpec

SPEC = PlateSpec(rows=7, cols=7, orientation_mark=DEFAULT_ORIENTATION_MARK)
SEEDS = range(5, 11)


def main(spacings):
    print(f"load: {os.getloadavg()}")
    for sp in spacings:
        found = marks = 0
        errs = []
        t0, c0 = time.perf_counter(), time.process_time()
        for seed in SEEDS:
            r = render_scan(seed, SPEC, ScanOptions(spacing_mm=sp, z_convention="height"))
            with tempfile.TemporaryDirectory() as d:
                path = os.path.join(d, "cloud.npy")
                np.save(path, np.column_stack([r.xyz_mm, r.intensity]))
                try:
                    res = run_scan(path, SPEC)
                except MarkcalError as exc:
                    print(f"  {sp:.2f} mm seed {seed}: refused: {exc}")
                    marks += len(SPEC.marked_ids)
                    continue
            t = r.truth["fiducials"]
            ids = res.fiducials["id"]
            e = np.hypot(res.fiducials["x_scanner_mm"] - np.array(t["x_scanner_mm"])[ids],
                         res.fiducials["y_scanner_mm"] - np.array(t["y_scanner_mm"])[ids])
            errs.append(e)
            n_vis = len(SPEC.marked_ids) - len(r.truth.get("hidden_ids", []))
            found, marks = found + len(ids), marks + n_vis
            print(f"  {sp:.2f} mm seed {seed}: {len(ids)} of {n_vis}, centre error RMS {np.sqrt(np.mean(e ** 2)):.4f} "
                  f"max {e.max():.4f} mm", flush=True)
        e = np.concatenate(errs) if errs else np.array([np.nan])
        print(f"{sp:.2f} mm: {found} of {marks} marks found, centre error RMS {np.sqrt(np.mean(e ** 2)):.4f} mm, "
              f"max {np.max(e):.4f} mm; {time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU")


if __name__ == "__main__":
    main([float(a) for a in sys.argv[1:]] or [0.2])
