"""Benchmark: the whole ``markcal scan`` command on a full-size (~5.4 M point) PLY, this code beside an older commit.

Renders one plate (seed 7, one contaminated mark), then runs ``python -m markcal.pipeline.cli scan
cloud.ply --plate plate.toml --out DIR --quiet`` (report included) in child processes, alternating
the reference commit (``git archive`` into a temporary folder, imported through PYTHONPATH) and this
working tree, and prints medians of wall and CPU time (user + system of the child) side by side,
with the load average. The RBF selection (5-fold CV over the scan flow's spreads and goals) is
timed the same way, in children, on the fiducials of the first run: the first call in a fresh
process (numba kernels loaded from their cache) and the median of 3 repeats in that process; and so
is the output side (the flow's writer: tables, model.json, report.html, imports included, after an
untimed flow). The output trees of both
codes are compared with benchmarks/compare_outputs.py.

    python benchmarks/bench_scan.py [--runs 3] [--ref 5f2c370] [--cloud PLY --plate TOML]

Both trees are byte-compiled first (``compileall``), as an installed package is: this machine sets
PYTHONDONTWRITEBYTECODE, so without it every run would compile markcal's modules again (about 0.06 s).

This code draws the report's figures in a drawing process started before the flow, when a core is
free (``reports/drawing.py``); ``MARKCAL_REPORT_FORK=0 python benchmarks/bench_scan.py`` times it without.
"""
from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

RBF_SNIPPET = r"""
import sys, time, numpy as np
from markcal.pipeline.flows.scan import MSE_GOALS_MM2, SPREADS_PER_PITCH
from markcal.reports.files import read_csv
from markcal.stages import rbf
from markcal.stages.plate import PlateSpec
f = read_csv(sys.argv[1])
p = np.column_stack([f["x_meas_mm"], f["y_meas_mm"]]); d = np.column_stack([f["dx_mm"], f["dy_mm"]])
spreads = np.array(SPREADS_PER_PITCH) * PlateSpec().pitch_mm
runs = []
for _ in range(4):                 # the first in a fresh process (compiled kernels loaded), then 3 warm
    c, w = time.process_time(), time.perf_counter()
    sel = rbf.select(p, d, spreads, MSE_GOALS_MM2, 5, 0, 200)
    m = rbf.train(p, d, sel.spread_mm, sel.mse_goal_mm2, 200)
    runs.append((time.perf_counter() - w, time.process_time() - c))
warm = sorted(runs[1:])[1]
print(runs[0][0], runs[0][1], warm[0], warm[1], sel.spread_mm, sel.mse_goal_mm2, m.n_neurons, sel.cv_rmse_mm)
"""

#: the output side alone: the flow runs untimed, then its writer (tables, model, report.html with its imports)
OUTPUT_SNIPPET = r"""
import resource, sys, time
from markcal.pipeline.registry import get_flow
def cpu():   # this process and its reaped children (figures drawn in a forked child count too)
    return sum(getattr(resource.getrusage(who), k) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
               for k in ("ru_utime", "ru_stime"))
flow = get_flow("scan")
try:                # this code: the drawing process starts before the flow, as in the command
    from markcal.reports.drawing import start_drawing_process, stop_drawing_process
except ImportError:  # older code: none
    start_drawing_process = stop_drawing_process = lambda *a: None
start_drawing_process(getattr(flow, "drawing", ()))
res = flow.descriptor.run(sys.argv[1], sys.argv[2], dict(flow.descriptor.options), None)
c, w = cpu(), time.perf_counter()
flow.write(res, sys.argv[3], report=True)
t = time.perf_counter() - w
stop_drawing_process()       # reaped: its CPU time counts
print(t, cpu() - c)
"""


def _reference_tree(ref: str, tmp: str) -> str:
    """``git archive`` of ``ref`` laid out as an importable ``markcal`` namespace; returns its PYTHONPATH."""
    src = os.path.join(tmp, "ref_src")
    os.makedirs(src)
    archive = subprocess.run(["git", "-C", REPO, "archive", ref], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", src], input=archive, check=True)
    pkg = os.path.join(tmp, "ref", "markcal")
    os.makedirs(pkg)
    for d in ("pipeline", "stages", "fixtures", "reports"):
        os.symlink(os.path.join(src, d), os.path.join(pkg, d))
    return os.path.join(tmp, "ref")


def _run(args, pythonpath, ok=(0,)):
    """Run a child Python; returns (wall s, cpu s, stdout). Exit codes in ``ok`` are success."""
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    t = time.perf_counter()
    p = subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=env, cwd=tempfile.gettempdir())
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t
    out, err = p.stdout.read(), p.stderr.read()
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode not in ok:
        raise SystemExit(f"child failed ({pythonpath or 'this tree'}): {err[-2000:]}")
    return wall, ru.ru_utime + ru.ru_stime, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--ref", default="5f2c370", help="reference commit (default: the code before issue 22's speed work)")
    ap.add_argument("--cloud", help="an existing PLY (default: render one)")
    ap.add_argument("--plate", help="its plate.toml")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}")
    tmp = tempfile.mkdtemp(prefix="markcal-bench-scan-")
    try:
        ref_path = _reference_tree(args.ref, tmp)
    except (subprocess.CalledProcessError, OSError) as exc:       # not a git checkout, or no such commit
        print(f"reference {args.ref} not available ({exc}); timing this tree alone")
        ref_path = None
    if args.cloud:
        cloud, plate = args.cloud, args.plate
    else:
        from markcal.fixtures.scan_plate import ScanOptions as RenderOptions, render_scan, save_scan
        from markcal.stages.plate import PlateSpec
        # site 0,1 unmarked: without an orientation mark the flow refuses a plate of unknown orientation
        r = render_scan(args.seed, PlateSpec(orientation_mark=(0, 1)), RenderOptions(n_contaminated=1))
        paths = save_scan(os.path.join(tmp, "plate"), r, formats=("ply",), truth=False)
        cloud, plate = paths["ply"], paths["plate.toml"]
    print(f"cloud: {os.path.getsize(cloud) / 1e6:.0f} MB PLY ({cloud})")
    # this tree is copied too, so edits made while the benchmark runs do not leak into it
    here = os.path.join(tmp, "here", "markcal")
    for d in ("pipeline", "stages", "fixtures", "reports"):
        shutil.copytree(os.path.join(REPO, d), os.path.join(here, d), ignore=shutil.ignore_patterns("__pycache__"))
    codes = {f"ref {args.ref}": ref_path, "this tree": os.path.dirname(here)}
    # as installed: byte-compiled (pip does it; this machine's Python does not); compileall does not follow the
    # reference tree's symbolic links, but its sources lie under tmp too
    subprocess.run([sys.executable, "-m", "compileall", "-q", tmp], check=True, stdout=subprocess.DEVNULL)
    if ref_path is None:
        del codes[f"ref {args.ref}"]
    # the copy of this tree has no numba cache yet: one untimed run compiles its kernels (as the first run
    # after an install does), so the timed runs load them from the cache as every later run does
    wall, cpu, _ = _run(["-m", "markcal.pipeline.cli", "scan", cloud, "--plate", plate, "--out",
                         os.path.join(tmp, "out_compile"), "--quiet"], os.path.dirname(here), ok=(0, 4))
    print(f"first run of this tree (compiles the numba kernels into its cache): wall {wall:.1f} s, CPU {cpu:.1f} s")
    times = {k: [] for k in codes}
    rbf_times = {k: [] for k in codes}
    out_times = {k: [] for k in codes}
    rbf_warm = {k: [] for k in codes}          # the same call repeated in the same process (median of 3)
    loads = []
    for i in range(args.runs):
        for name, path in codes.items():
            out = os.path.join(tmp, f"out_{name.split()[0]}{i}")
            loads.append(os.getloadavg()[0])
            wall, cpu, _ = _run(["-m", "markcal.pipeline.cli", "scan", cloud, "--plate", plate, "--out", out,
                                 "--quiet"], path, ok=(0, 4))      # 4: out of tolerance, outputs written
            times[name].append((wall, cpu))
            fid = os.path.join(tmp, f"out_{list(codes)[0].split()[0]}0", "fiducials.csv")
            _, _, line = _run(["-c", RBF_SNIPPET, fid], path)
            w, c, ww, wc, *sel = line.split()
            rbf_times[name].append((float(w), float(c), sel))
            rbf_warm[name].append((float(ww), float(wc)))
            _, _, line = _run(["-c", OUTPUT_SNIPPET, cloud, plate, out + "_w"], path)
            out_times[name].append(tuple(float(v) for v in line.split()))
            print(f"run {i + 1} {name:>14}: output side (tables + report.html, imports included) wall "
                  f"{out_times[name][-1][0]:5.2f} s, CPU {out_times[name][-1][1]:5.2f} s", flush=True)
            print(f"run {i + 1} {name:>14}: whole command wall {wall:6.1f} s, CPU {cpu:6.1f} s; "
                  f"RBF selection + training wall {float(w):5.2f} s, CPU {float(c):5.2f} s "
                  f"(warm {float(ww):5.2f} s, CPU {float(wc):5.2f} s; spread {sel[0]} mm, goal {sel[1]} mm2, "
                  f"{sel[2]} neurons, CV RMSE {float(sel[3]) * 1000:.3f} um); load {loads[-1]:.1f}", flush=True)
    med = statistics.median
    print(f"\nload average 1 min during the runs: {min(loads):.1f}-{max(loads):.1f} ({os.cpu_count()} cores)")
    if len(codes) == 1:
        for label, t in (("whole command", times), ("RBF selection + training", rbf_times),
                         ("RBF, warm (same process)", rbf_warm), ("output side", out_times)):
            print(f"{label:>25}: wall median {med([x[0] for x in t['this tree']]):6.2f} s, "
                  f"CPU median {med([x[1] for x in t['this tree']]):6.2f} s")
        return
    ref, new = list(codes)
    for label, t in (("whole command", times), ("RBF selection + training", rbf_times),
                     ("RBF, warm (same process)", rbf_warm), ("output side", out_times)):
        for k, name in ((0, "wall"), (1, "CPU")):
            a, b = med([x[k] for x in t[ref]]), med([x[k] for x in t[new]])
            print(f"{label:>25} {name:>4}: {ref} median {a:6.2f} s | this tree {b:6.2f} s | ratio {a / b:4.2f}x")
    print("goals: whole command >= 3x, RBF selection >= 5x (issue 22)")
    cmp = subprocess.run([sys.executable, os.path.join(HERE, "compare_outputs.py"),
                          os.path.join(tmp, "out_ref0"), os.path.join(tmp, "out_this0")],
                         capture_output=True, text=True)
    print(f"outputs (ref vs this tree, compare_outputs.py): {'same' if cmp.returncode == 0 else 'DIFFER'}")
    if cmp.returncode:
        print(cmp.stdout[-3000:])
    print(f"(outputs kept in {tmp})")


if __name__ == "__main__":
    main()
