"""Images of a marked plate through ``markcal scan``: time, peak memory and centre error against truth.

Renders flatbed images of the paper's 190 mm plate (19 x 19) with an independent renderer
(fixtures/plate_image.py), writes them as files, runs the whole command (``python -m
markcal.pipeline.cli scan IMAGE --plate plate.toml``, report included) in a child process
and reads its peak RSS. Issue 22 goals at 1200 dpi: centre error <= 0.1 px RMS, <= 10 s,
<= 4 GiB.

    python benchmarks/bench_scan_image.py [DPI ...]     (default 1200; repeats: 3)
    python benchmarks/bench_scan_image.py --variants [--rows N] [DPI ...]
        once per image variant (8-bit TIFF, JPEG q90, 16-bit, RGB, paper, 300 dust specks), error table;
        --rows N: an N x N plate (the same pitch) instead of 19 x 19, for 2400 dpi on a loaded machine
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.plate_image import ImageOptions, render_plate_image, save_plate_image
from markcal.reports.files import read_csv
from markcal.stages.plate import PlateSpec


def run_once(path, plate, out):
    """One whole command in a child; returns (wall s, CPU s of the child, its peak RSS GiB)."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "markcal.pipeline.cli", "scan", path, "--plate", plate,
                          "--out", out, "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    err = p.stderr.read()
    if os.waitstatus_to_exitcode(status) not in (0, 4):          # 4: out of tolerance, outputs written
        raise SystemExit(err)
    return wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 2 ** 20          # this child's own peak (KiB)


VARIANTS = {  # name -> (ImageOptions keywords, file format)
    "8-bit TIFF": ({}, "tif"),
    "JPEG q90": ({"jpeg_quality": 90}, "png"),
    "16-bit": ({"bits": 16}, "tif"),
    "RGB": ({"rgb": True}, "tif"),
    "paper": ({"material": "paper"}, "tif"),
    "dust x5": ({"n_dust": 300, "n_hairs": 20}, "tif"),
}


def main(dpis, repeats=3, fmt="tif", variants=None, rows=19):
    spec = PlateSpec(rows=rows, cols=rows, orientation_mark=(0, 1))     # site 0,1 unmarked: the flow refuses a plate of unknown orientation
    for dpi, name, kw, fmt in [(d, n, kw, f) for d in dpis for n, (kw, f) in (variants or {"": ({}, fmt)}).items()]:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            r = render_plate_image(1, spec, ImageOptions(dpi=dpi, **kw))
            paths = save_plate_image(tmp, r, fmt=fmt)
            t_render = time.perf_counter() - t0
            walls, cpus, loads = [], [], []
            for k in range(repeats):
                loads.append(os.getloadavg()[0])
                wall, cpu, rss = run_once(paths["image"], paths["plate.toml"], os.path.join(tmp, f"out{k}"))
                walls.append(wall)
                cpus.append(cpu)
            f = read_csv(os.path.join(tmp, "out0", "fiducials.csv"))
            with open(os.path.join(tmp, "out0", "summary.json")) as fh:
                s = json.load(fh)
            ids = f["id"].astype(int)
            px = r.pixel_mm
            col = f["x_scanner_mm"] / px - 0.5
            row = f["y_scanner_mm"] / px - 0.5
            tc = np.array(r.truth["fiducials"]["col_px"])[ids]
            tr = np.array(r.truth["fiducials"]["row_px"])[ids]
            e = np.hypot(col - tc, row - tr)
            print(f"{name:10s} {dpi:5.0f} dpi {r.pixels.shape[1]} x {r.pixels.shape[0]} px ({fmt}, rendered in {t_render:.1f} s): "
                  f"{s['n_detected']}/{s['n_expected']} marks, centre error RMS {np.sqrt(np.mean(e ** 2)):.4f} px "
                  f"(max {e.max():.3f} px) = {np.sqrt(np.mean(e ** 2)) * px * 1000:.2f} um; whole command median "
                  f"{np.median(walls):.1f} s (of {repeats}: {', '.join(f'{w:.1f}' for w in walls)}), "
                  f"CPU median {np.median(cpus):.1f} s, peak RSS {rss:.2f} GiB; flow runtime_s {s['runtime_s']:.1f}; "
                  f"load average {min(loads):.1f}-{max(loads):.1f} on {os.cpu_count()} cores", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    n_rows = 19
    if "--rows" in args:
        i = args.index("--rows")
        n_rows = int(args[i + 1])
        del args[i:i + 2]
    if "--variants" in args:
        args.remove("--variants")
        main([float(a) for a in args] or [1200.0], repeats=1, variants=VARIANTS, rows=n_rows)
    else:
        main([float(a) for a in args] or [1200.0])
