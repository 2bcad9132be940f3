"""Path flow benchmark: markcal's local search side by side with LKH (elkai), fast-tsp and pyvrp.

Same instances, same run: the TSPLIB boards in ``../shared/realdata/tsp`` (proven optima) and
``benchmarks/pr1002.tsp``, plus clustered instances rendered here (Gaussian clusters and
drilling boards, ``markcal.fixtures.tsp_boards``) whose yardstick is LKH
(elkai, one run). Every tour is scored as TSPLIB EUC_2D (edges rounded to integers;
rendered instances are scaled to a 20,000-unit board first). fast-tsp and pyvrp get markcal's
time goal for the search, ``1 s + n / 500 s``. Then the whole command
(``markcal path job.csv --method ls --no-report --kicks-per-stroke 5``) is timed against its goal ``2 s + n / 500 s``,
and the paper's GA is compared on its kind of job. Prints medians; the competitors come from
the ``bench`` extra (LKH's licence is academic: it is only the yardstick, never markcal's engine).

    .venv/bin/python benchmarks/bench_path.py [--quick] [--skip-cli] [--skip-ga]
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from markcal.fixtures.path_jobs import paper_points, text_job
from markcal.fixtures.tsp_boards import clustered_points, drill_board, read_tsplib, tsplib_length
from markcal.stages.path_ga import GAOptions, run_ga
from markcal.stages.path_job import Timing, input_tour, make_job, tour_cost
from markcal.stages.path_tour import LocalSearchOptions, local_search, nearest_neighbour_tour, raster_tour

TM = Timing()
HERE = Path(__file__).resolve().parent
OPTIMA = {"pcb442": 50778, "d493": 35002, "rat783": 8806, "pr1002": 259045, "u1060": 224094, "pcb1173": 56892}


def realdata() -> Path | None:
    for p in (os.environ.get("MARKCAL_REALDATA"), HERE.parent / ".." / "shared" / "realdata",
              "/work/shared/realdata"):
        if p and (Path(p) / "tsp").is_dir():
            return Path(p)
    return None


def nint_matrix(p):
    d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
    return np.floor(d + 0.5).astype(np.int64)


def run_markcal(p):
    t0 = time.perf_counter()
    job = make_job(("point", q) for q in p)
    t = local_search(job, nearest_neighbour_tour(job), TM)
    return t.order, time.perf_counter() - t0


def run_elkai(p, runs):
    import elkai
    t0 = time.perf_counter()
    order = elkai.DistanceMatrix(nint_matrix(p).tolist()).solve_tsp(runs=runs)
    o = np.array(order[:-1] if len(order) > len(p) else order)
    return o, time.perf_counter() - t0


def run_fast_tsp(p, seconds):
    import fast_tsp
    m = nint_matrix(p).tolist()
    t0 = time.perf_counter()
    o = fast_tsp.find_tour(m, duration_seconds=seconds)
    return np.array(o), time.perf_counter() - t0


def run_pyvrp(p, seconds):
    from pyvrp import Model
    from pyvrp.stop import MaxRuntime
    d = nint_matrix(p)
    m = Model()
    locs = [m.add_location(x=float(x), y=float(y)) for x, y in p]
    m.add_depot(locs[0])
    for loc in locs[1:]:
        m.add_client(loc)
    m.add_vehicle_type(num_available=1)
    for i, a in enumerate(locs):
        for j, b in enumerate(locs):
            if i != j:
                m.add_edge(a, b, distance=int(d[i, j]))
    t0 = time.perf_counter()
    res = m.solve(stop=MaxRuntime(seconds), display=False, seed=0)
    visits = [a.idx + 1 for a in res.best.routes()[0].schedule() if a.is_client()]   # client k: location k+1
    return np.array([0] + visits), time.perf_counter() - t0


def instances(quick):
    out = []
    rd = realdata()
    if rd is not None:
        names = ["pcb442", "d493", "pr1002"] if quick else list(OPTIMA)
        out += [(n, read_tsplib(rd / "tsp" / f"{n}.tsp"), OPTIMA[n], "optimum") for n in names]
    else:
        print("realdata not found: TSPLIB boards skipped (set MARKCAL_REALDATA)")
    out.append(("pr1002 (benchmarks/)", read_tsplib(HERE / "pr1002.tsp"), OPTIMA["pr1002"], "optimum"))
    rendered = [("clusters 800 s1000", clustered_points(1000, 800, clusters=10)),
                ("board 1200 s1001", drill_board(1001, 1200))]
    if not quick:
        rendered += [("clusters 1500 s1002", clustered_points(1002, 1500, clusters=20, spread=0.01)),
                     ("board 2500 s1003", drill_board(1003, 2500)),
                     ("clusters 3000 s1004", clustered_points(1004, 3000, clusters=30, spread=0.008))]
    for name, p in rendered:
        p = (p - p.min(axis=0)) * (20_000.0 / float(np.ptp(p)))      # fast-tsp: costs < 65,536
        out.append((name, p, None, "LKH"))
    return out


def compare(quick):
    names = ("markcal", "fast-tsp", "pyvrp", "LKH")
    gaps = {k: [] for k in names}
    secs = {k: [] for k in names}
    print(f"{'instance':24s} {'n':>5s} {'reference':>14s} " + " ".join(f"{k:>16s}" for k in names))
    for name, p, opt, kind in instances(quick):
        n = len(p)
        budget = 1.0 + n / 500.0
        res = {"markcal": run_markcal(p), "LKH": run_elkai(p, runs=1)}
        for k, f in (("fast-tsp", run_fast_tsp), ("pyvrp", run_pyvrp)):
            if k == "pyvrp" and n > 1500:                  # its model takes n^2 edges one call at a time
                continue
            try:
                res[k] = f(p, budget)
            except Exception as e:                         # a competitor failing is reported, not fatal
                print(f"  {k} failed on {name}: {e}")
        lengths = {k: tsplib_length(p, o) for k, (o, _) in res.items() if sorted(o.tolist()) == list(range(n))}
        ref = opt if opt is not None else lengths["LKH"]
        row = []
        for k in names:
            if k in lengths:
                g = 100.0 * (lengths[k] / ref - 1.0)
                gaps[k].append(g)
                secs[k].append(res[k][1])
                row.append(f"{g:7.2f}% {res[k][1]:6.2f}s")
            else:
                row.append(f"{'-':>16s}")
        print(f"{name:24s} {n:5d} {ref:>8d} {kind[:5]:>5s} " + " ".join(f"{c:>16s}" for c in row), flush=True)
    print("median gap % / max gap % / median s:")
    for k in names:
        if gaps[k]:
            print(f"  {k:9s} {statistics.median(gaps[k]):6.2f} {max(gaps[k]):6.2f} {statistics.median(secs[k]):6.2f}")
    g = gaps["markcal"]
    print(f"goal median <= 0.5 %: {statistics.median(g):.2f} %; every instance <= 1 %: max {max(g):.2f} %")


def cli_timing(quick):
    """Whole command ``markcal path job.csv --method ls --no-report`` against 2 s + n/500 s."""
    exe = Path(sys.executable).with_name("markcal")
    rd = realdata()
    cases = [("random 400", np.random.default_rng(1005).random((400, 2)) * 100)]
    if rd is not None:
        cases += [(n, read_tsplib(rd / "tsp" / f"{n}.tsp")) for n in (["pr1002"] if quick else ["pcb442", "pcb1173"])]
    cases.append(("clusters 3000", clustered_points(1004, 3000, clusters=30, spread=0.008)))
    kicks = str(LocalSearchOptions().kicks_per_stroke)       # the CLI's own default may differ
    print(f"whole command (median of 3, --kicks-per-stroke {kicks}), goal 2 s + n/500 s:")
    with tempfile.TemporaryDirectory() as tmp:
        for name, p in cases:
            csv = Path(tmp) / "job.csv"
            csv.write_text("x_mm,y_mm\n" + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in p))
            ts, cpu = [], []
            for r in range(3):
                t0 = time.perf_counter()
                c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                subprocess.run([str(exe), "path", str(csv), "--out", str(Path(tmp) / f"o{r}"), "--method", "ls",
                                "--no-report", "--quiet", "--kicks-per-stroke", kicks], check=True,
                               stdout=subprocess.DEVNULL)
                ts.append(time.perf_counter() - t0)
                c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu.append(c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime)
            goal = 2.0 + len(p) / 500.0
            print(f"  {name:16s} n={len(p):5d}: {statistics.median(ts):.2f} s wall, {statistics.median(cpu):.2f} s CPU "
                  f"(goal {goal:.2f} s; load average {os.getloadavg()[0]:.1f})")


def paper_ga(quick):
    seeds = [1000, 1001] if quick else [1000, 1001, 1002, 1003, 1004]
    gaps, gals, ts = [], [], []
    for s in seeds:
        job = paper_points(s, 70)
        p = np.array([st.xy_mm[0] for st in job.strokes]) * 1000.0      # µm: integer costs for LKH
        o, _ = run_elkai(p, runs=5)
        ref = float(np.hypot(*(p[np.roll(o, -1)] - p[o]).T).sum()) / 1000.0
        r = run_ga(job, TM, GAOptions(seed=s))
        better = local_search(job, r.tour, TM)
        gaps.append(100 * (r.cost / ref - 1))
        gals.append(100 * (tour_cost(job, better, TM) / ref - 1))
        ts.append(r.runtime_s)
    print(f"paper GA, 70 points, 3000 generations x 100: gap to LKH median {statistics.median(gaps):.1f} % "
          f"(max {max(gaps):.1f} %), {statistics.median(ts):.2f} s; GA + local search {statistics.median(gals):.3f} %")
    job = text_job(0)
    r = run_ga(job, TM, GAOptions(seed=0))
    better = local_search(job, r.tour, TM)
    base = tour_cost(job, input_tour(job), TM)
    print(f"text job ({job.n} strokes): input order {base:.1f} mm, raster {tour_cost(job, raster_tour(job), TM):.1f} mm, "
          f"paper GA {r.cost:.1f} mm ({100 * (1 - r.cost / base):.1f} % shorter; paper: 28 %), "
          f"GA + local search {tour_cost(job, better, TM):.1f} mm")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer instances")
    ap.add_argument("--skip-cli", action="store_true", help="no whole-command timing")
    ap.add_argument("--skip-ga", action="store_true", help="no paper GA comparison")
    args = ap.parse_args()
    print("path benchmark (2-core shared machine: timings are noisy)")
    warm = make_job(("point", q) for q in np.random.default_rng(0).random((50, 2)))
    local_search(warm, nearest_neighbour_tour(warm), TM)
    if not args.skip_cli:
        cli_timing(args.quick)
    compare(args.quick)
    if not args.skip_ga:
        paper_ga(args.quick)


if __name__ == "__main__":
    main()
