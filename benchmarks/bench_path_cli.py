"""Time the whole command ``markcal path job.csv --out d --no-report`` (goal: <= 2 s + n/500 s).

Usage: python benchmarks/bench_path_cli.py [n ...] [--repeats R]
Prints, per job size, the median wall time of R runs (a fresh process each, as a user runs it).
"""
import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

from markcal.fixtures.path_jobs import random_points
from markcal.reports.files import write_csv


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("n", nargs="*", type=int, default=[200, 1000, 3000])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    print(f"{'n':>6} {'median s':>9} {'goal s':>7}  verdict")
    with tempfile.TemporaryDirectory() as d:
        for n in a.n:
            job = random_points(0, n)
            f = os.path.join(d, f"job{n}.csv")
            write_csv(f, {"x_mm": [s.xy_mm[0, 0] for s in job.strokes], "y_mm": [s.xy_mm[0, 1] for s in job.strokes]})
            ts = []
            for r in range(a.repeats):
                t = time.perf_counter()
                subprocess.run([sys.executable, "-m", "markcal.pipeline.cli", "path", f, "--out",
                                os.path.join(d, f"o{n}_{r}"), "--no-report", "--quiet"], check=True,
                               stdout=subprocess.DEVNULL)
                ts.append(time.perf_counter() - t)
            med = statistics.median(ts)
            goal = 2 + n / 500
            print(f"{n:>6} {med:>9.2f} {goal:>7.2f}  {'ok' if med <= goal else 'MISSED'}", flush=True)


if __name__ == "__main__":
    main()
