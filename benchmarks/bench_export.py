"""Correction tables: fidelity of a .cor to the scan flow's correction, and write/read times.

Run: .venv/bin/python benchmarks/bench_export.py  (renders and scans one 19 x 19 plate first)
"""
import contextlib
import io
import tempfile
import time

import numpy as np

from markcal.pipeline.cli import main
from markcal.pipeline.flows.export import export_table, load_scan_source
from markcal.stages import table_formats as fmt


def run():
    with tempfile.TemporaryDirectory() as d, contextlib.redirect_stdout(io.StringIO()):
        main(["render", "scan", "--seed", "1001", "--out", f"{d}/p", "--formats", "npy", "--quiet"])
        main(["scan", f"{d}/p/cloud.npy", "--plate", f"{d}/p/plate.toml", "--out", f"{d}/c", "--quiet", "--no-report"])
        src = load_scan_source(f"{d}/c")
        rng = np.random.default_rng(0)
        x0, x1, y0, y1 = src.region_mm
        xy = np.column_stack([rng.uniform(x0, x1, 20000), rng.uniform(y0, y1, 20000)])
        want = src.offset_mm(xy)
        rows = []
        for lens in (195.0, 220.0, 260.0):
            t = time.perf_counter()
            data, facts = export_table("cor", f"{d}/c", lens_mm=lens)
            t_w = time.perf_counter() - t
            t = time.perf_counter()
            table, upm = fmt.decode_cor(data)
            t_r = time.perf_counter() - t
            err = np.abs(table.offset(xy) - want).max() * upm
            rows.append((lens, upm, facts["max_entry_units"], err, facts["extrapolated_nodes"], t_w, t_r))
    print(f"plate seed 1001 (19 x 19 fiducials over {x1 - x0:.0f} mm), 20,000 random points on the plate")
    print("lens_mm  units/mm  max|entry|  max |bilinear(.cor) - model| (units)  extrapolated nodes  write s  read s")
    for r in rows:
        print(f"{r[0]:7.0f}  {r[1]:8.1f}  {r[2]:10.0f}  {r[3]:38.3f}  {r[4]:18d}  {r[5]:7.3f}  {r[6]:6.4f}")


if __name__ == "__main__":
    run()
