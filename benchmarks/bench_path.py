"""Path flow benchmark: tour quality against LKH (elkai) and TSPLIB pr1002, and speed.

Prints medians. LKH (through ``elkai``, the ``bench`` extra) is only the
yardstick: its licence is academic, so it is not markcal's engine. Seeds here
(1000+) are not used by any test.

    .venv/bin/python benchmarks/bench_path.py [--quick]
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from markcal.fixtures.path_jobs import paper_points, random_points, text_job
from markcal.stages.path_ga import GAOptions, run_ga
from markcal.stages.path_job import Timing, input_tour, make_job, tour_cost
from markcal.stages.path_tour import LocalSearchOptions, local_search, nearest_neighbour_tour, raster_tour

TM = Timing()
HERE = os.path.dirname(os.path.abspath(__file__))
PR1002_OPT = 259045


def lkh_length(p, runs=1):
    """Closed-tour length of LKH's tour (elkai), float distances (coordinates scaled for its integer costs)."""
    import elkai
    s = 1000.0 / max(float(np.ptp(p)), 1e-9) * 100
    order = elkai.Coordinates2D({i: (float(x * s), float(y * s)) for i, (x, y) in enumerate(p)}).solve_tsp(runs=runs)
    o = np.array(order[:-1] if order[0] == order[-1] else order)
    return float(np.hypot(*(p[np.roll(o, -1)] - p[o]).T).sum())


def read_tsp(path):
    rows = open(path).read().split("NODE_COORD_SECTION")[1].split("EOF")[0].split()
    return np.array(rows, float).reshape(-1, 3)[:, 1:]


def tsplib_length(p, order):
    d = np.hypot(*(p[np.roll(order, -1)] - p[order]).T)
    return int(np.floor(d + 0.5).sum())        # EUC_2D: nint of each edge


def solve(job, opts=None):
    t0 = time.perf_counter()
    nn = nearest_neighbour_tour(job)
    t = local_search(job, nn, TM, opts)
    return t, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer instances")
    args = ap.parse_args()
    seeds = [1000, 1001] if args.quick else [1000, 1001, 1002, 1003, 1004]
    print("path benchmark (2-core shared machine: timings are noisy)")
    warm = random_points(1, 50)
    local_search(warm, nearest_neighbour_tour(warm), TM)
    run_ga(warm, TM, GAOptions(generations=5))

    # 1,000 random points: gap to LKH, runtime
    gaps, times, gaps_ls0, gaps_nn = [], [], [], []
    for s in seeds:
        job = random_points(s, 1000)
        p = np.array([st.xy_mm[0] for st in job.strokes])
        ref = lkh_length(p)
        ts = []
        for _ in range(3):
            t, dt = solve(job)
            ts.append(dt)
        t0, _ = solve(job, LocalSearchOptions(kicks_per_stroke=0))
        gaps.append(100 * (tour_cost(job, t, TM) / ref - 1))
        gaps_ls0.append(100 * (tour_cost(job, t0, TM) / ref - 1))
        gaps_nn.append(100 * (tour_cost(job, nearest_neighbour_tour(job), TM) / ref - 1))
        times.append(statistics.median(ts))
        print(f"  random 1000 seed {s}: LKH {ref:.1f} mm, markcal ls {tour_cost(job, t, TM):.1f} mm "
              f"(gap {gaps[-1]:.2f} %, {times[-1]:.2f} s), 2-opt+Or-opt only gap {gaps_ls0[-1]:.2f} %, "
              f"NN gap {gaps_nn[-1]:.1f} %")
    print(f"random 1000 points: gap to LKH median {statistics.median(gaps):.2f} % (max {max(gaps):.2f} %), "
          f"runtime median {statistics.median(times):.2f} s (max {max(times):.2f} s); "
          f"without kicks {statistics.median(gaps_ls0):.2f} %; nearest neighbour {statistics.median(gaps_nn):.1f} %")

    # TSPLIB pr1002
    p = read_tsp(os.path.join(HERE, "pr1002.tsp"))
    job = make_job(("point", q) for q in p)
    ts, lens = [], []
    for _ in range(3):
        t, dt = solve(job)
        ts.append(dt)
        lens.append(tsplib_length(p, t.order))
    print(f"pr1002 (optimum {PR1002_OPT}): markcal ls {lens[0]} (gap {100 * (lens[0] / PR1002_OPT - 1):.2f} %), "
          f"runtime median {statistics.median(ts):.2f} s")

    # 70-100 points: gap to LKH
    small = []
    for s in seeds:
        for job in (paper_points(s, 70), random_points(s, 100)):
            p = np.array([st.xy_mm[0] for st in job.strokes])
            ref = lkh_length(p, runs=5)
            t, _ = solve(job)
            small.append(100 * (tour_cost(job, t, TM) / ref - 1))
    print(f"70 and 100 points ({len(small)} jobs): gap to LKH median {statistics.median(small):.3f} %, "
          f"max {max(small):.3f} %")

    # the paper's GA on its kind of job (70 points) and on 1,000 points
    ga_gaps, gals_gaps, ga_t, ga_red = [], [], [], []
    for s in seeds:
        job = paper_points(s, 70)
        p = np.array([st.xy_mm[0] for st in job.strokes])
        ref = lkh_length(p, runs=5)
        r = run_ga(job, TM, GAOptions(seed=s))
        better = local_search(job, r.tour, TM)
        ga_gaps.append(100 * (r.cost / ref - 1))
        gals_gaps.append(100 * (tour_cost(job, better, TM) / ref - 1))
        ga_red.append(100 * (1 - r.cost / tour_cost(job, raster_tour(job), TM)))
        ga_t.append(r.runtime_s)
    print(f"paper GA, 70 points, 3000 generations x 100: gap to LKH median {statistics.median(ga_gaps):.1f} % "
          f"(max {max(ga_gaps):.1f} %), {statistics.median(ga_red):.1f} % shorter than raster, "
          f"{statistics.median(ga_t):.2f} s; GA + local search gap median {statistics.median(gals_gaps):.3f} %")
    job = text_job(0)
    r = run_ga(job, TM, GAOptions(seed=0))
    better = local_search(job, r.tour, TM)
    base = tour_cost(job, input_tour(job), TM)
    print(f"text job ({job.n} strokes): input order {base:.1f} mm, paper GA {r.cost:.1f} mm "
          f"({100 * (1 - r.cost / base):.1f} % shorter; paper: 28 %), GA + local search "
          f"{tour_cost(job, better, TM):.1f} mm ({100 * (1 - tour_cost(job, better, TM) / base):.1f} % shorter)")
    job = random_points(seeds[0], 1000)
    p = np.array([st.xy_mm[0] for st in job.strokes])
    ref = lkh_length(p)
    r = run_ga(job, TM, GAOptions(seed=0))
    print(f"paper GA, 1000 points, 3000 generations x 100: {r.cost:.1f} mm, gap to LKH "
          f"{100 * (r.cost / ref - 1):.1f} %, {r.runtime_s:.1f} s")


if __name__ == "__main__":
    main()
