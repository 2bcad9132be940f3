"""Correction tables: fidelity of a .cor to the scan flow's correction, and write/read times.

Run: .venv/bin/python benchmarks/bench_export.py  (renders and scans one 19 x 19 plate first)
     .venv/bin/python benchmarks/bench_export.py --structure   (only the structural check and the note, on the
     real EZCAD tables in ../shared/realdata/galvo_tables/)
"""
import contextlib
import io
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from markcal.pipeline.cli import main
from markcal.pipeline.flows.export import export_table, inspect_bytes, load_scan_source
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


def _median_s(fn, repeats=15):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def structure():
    """Structural check (inspect_bytes) and the note's HTML on the real tables: median of 15 runs."""
    from markcal.reports.table_report import table_report_html
    root = Path(os.environ.get("MARKCAL_REALDATA", Path(__file__).resolve().parents[1].parent / "shared" / "realdata"))
    if not (root / "galvo_tables").is_dir():
        root = Path("/work/shared/realdata")
    print("table       layout found  evidence  inspect_bytes ms  note HTML ms")
    for name in ("50mm.cor", "250mm.cor"):
        data = (root / "galvo_tables" / name).read_bytes()
        t = inspect_bytes(data, name)
        t_read = _median_s(lambda: inspect_bytes(data, name))
        t_html = _median_s(lambda: table_report_html(t), repeats=5)
        print(f"{name:10s}  {t.structure.first_along:12s}  {t.structure.evidence:+8.2f}  {t_read * 1e3:16.2f}  "
              f"{t_html * 1e3:12.0f}")


if __name__ == "__main__":
    structure() if "--structure" in sys.argv else run()
