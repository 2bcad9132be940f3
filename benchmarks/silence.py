"""Benchmark: the longest stretch every markcal command stays silent on stderr (issue 16: at most 2 s).

Runs each command of the chosen size set as a child process in a temporary folder (the render
commands first, so the later commands have their inputs), stamps every stderr line on arrival and
prints, per command: wall and CPU time (user + system of the child), the number of stderr lines,
the longest gap (start -> first line, between lines, last line -> exit), the CPU time the child
used in it, and the line that ends it; then the largest CPU time used between two lines (read from
/proc at each line: what the gap would be on an idle core, for one-threaded work; the CPU of worker
processes is not counted). On a loaded machine the wall gaps grow with the load; the CPU gaps do not.

    python benchmarks/silence.py [--size small|demo|both] [--limit 2.0] [--keep]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

#: (size, command line after ``markcal``); run in order in one folder
COMMANDS = (
    ("small", "render scan --rows 7 --cols 7 --seed 7 --out plate"),
    ("small", "scan plate/cloud.ply --plate plate/plate.toml --out cal"),
    ("small", "export cor cal --lens-mm 70 --out lens.cor"),
    ("small", "inspect lens.cor --out lens_check"),
    ("small", "render grid --seed 3 --out measured"),
    ("small", "grid measured/measured.csv --out gridcal"),
    ("small", "render afm --single --seed 2 --out afm"),
    ("small", "indents afm/heights.ibw --load-mN 50 --out imprint"),
    ("small", "render selfcal --n 7 --k 8 --seed 5 --out session"),
    ("small", "selfcal session --out stage"),
    ("small", "export a3200 stage --out stage.cal"),
    ("small", "render path --kind text --out text"),
    ("small", "path text/job.json --out ordered"),
    ("small", "render servo --seed 3 --out log"),
    ("small", "servo --trace log/trace.csv --out drive"),
    ("small", "render pmcal --seed 1 --out pm"),
    ("small", "pmcal pm --out pm_out"),
    ("small", "render batch --seed 7 --scans 2 --sessions 1 --traces 2 --broken 0 --out inputs"),
    ("small", "batch inputs --out results --workers 2"),
    ("demo", "render scan --seed 7 --out plate19"),
    ("demo", "scan plate19/cloud.ply --plate plate19/plate.toml --out cal19"),
    ("demo", "render selfcal --seed 5 --out session11"),
    ("demo", "selfcal session11 --out stage11"),
    ("demo", "render afm --seed 7 --out afm7"),
    ("demo", "indents afm7/heights.tif --array afm7/array.toml --out afm7_out"),
    ("demo", "render om --seed 7 --out om7"),
    ("demo", "indents om7/image.tif --array om7/array.toml --out om7_out"),
    ("demo", "render path --kind grid --out pgrid"),
    ("demo", "path pgrid/job.json --out pgrid_order"),
    ("demo", "servo --out servo_sim"),
    ("demo", "render grid --seed 1 --out gdemo"),
    ("demo", "grid gdemo/measured.csv --out gcal --lens-mm 110"),
)


def run_one(argv: list, cwd: str) -> dict:
    """Run one command; stderr lines stamped on arrival. Returns wall, cpu, status, lines, longest gap."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "markcal.pipeline.cli", *argv], cwd=cwd, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True, bufsize=1)
    stamps = []
    for line in p.stderr:
        stamps.append((time.perf_counter() - t0, _cpu_s(p.pid), line.rstrip("\n")))
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    cpu = ru.ru_utime + ru.ru_stime
    p.returncode = os.waitstatus_to_exitcode(status)
    edges = [(0.0, 0.0, "(start)")] + stamps + [(wall, cpu, "(exit)")]
    gaps = [(b[0] - a[0], b[1] - a[1], b[2]) for a, b in zip(edges, edges[1:])]
    gap, cpu_gap, after = max(gaps, key=lambda g: g[0])
    return {"wall": wall, "cpu": cpu, "status": p.returncode, "lines": len(stamps), "gap": gap,
            "cpu_gap": max(g[1] for g in gaps), "gap_cpu": cpu_gap, "ends_with": after,
            "tail": [s for _, _, s in stamps[-3:]]}


def _cpu_s(pid: int) -> float:
    """CPU time (user + system, s) the process has used so far, from /proc (0 where there is none)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=["small", "demo", "both"], default="small")
    ap.add_argument("--limit", type=float, default=2.0, help="longest allowed silence (s)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args()
    sizes = ("small", "demo") if args.size == "both" else (args.size,)
    tmp = tempfile.mkdtemp(prefix="markcal-silence-")
    env_cpus = os.cpu_count()
    print(f"{'command':<64} {'wall s':>6} {'CPU s':>5} {'exit':>4} {'lines':>5} {'gap s':>5} {'(CPU)':>5} "
          f"{'max CPU gap':>11}  line ending the longest gap")
    over = []
    loads = []
    try:
        for size, line in COMMANDS:
            if size not in sizes:
                continue
            loads.append(os.getloadavg()[0])
            r = run_one(line.split(), tmp)
            flag = " <-- over" if r["gap"] > args.limit else ""
            print(f"{line[:64]:<64} {r['wall']:6.1f} {r['cpu']:5.1f} {r['status']:4d} {r['lines']:5d} "
                  f"{r['gap']:5.2f} {r['gap_cpu']:5.2f} {r['cpu_gap']:11.2f}  {r['ends_with'][:50]}{flag}", flush=True)
            if r["status"] not in (0, 4):
                print(f"    failed: {' | '.join(r['tail'])}")
            if r["gap"] > args.limit:
                over.append((line, r["gap"]))
    finally:
        if args.keep:
            print(f"(outputs kept in {tmp})")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average 1 min during the runs: {min(loads):.1f}-{max(loads):.1f} ({env_cpus} cores); "
          f"{len(over)} command(s) silent for more than {args.limit:g} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
