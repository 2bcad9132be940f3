"""Servo flow timings and the headline reductions.

Goals: a 2 s move at 10 kHz simulates in <= 0.2 s; a 1,000,000-line drive log in <= 3 s as a whole command
(``markcal servo --trace``: start-up, reading, moves, report and files).

Run: .venv/bin/python benchmarks/bench_servo.py [--log-only] (medians of several runs; first call compiles
numba). The log timing prints wall-clock and CPU seconds (user + system of the command) and the load
average, since on a shared machine the wall clock also counts waiting for a core.
"""
from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

from markcal.pipeline.flows.servo import ServoConfig, run_servo
from markcal.stages.servo_control import PIDGains, RepetitiveParams
from markcal.stages.servo_plant import PlantParams, discretise
from markcal.stages.servo_profile import s_curve, sinusoid
from markcal.stages.servo_sim import BASELINE, CCA_STEP, CCA_TRACK, simulate, step_metrics


def median_time(fn, n=7):
    fn()                                   # warm-up (numba compile / cache load)
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), min(ts), max(ts)


def bench_log(n_lines=1_000_000, repeats=5):
    """Whole-command time of ``markcal servo --trace`` on a rendered 1,000,000-line TSV drive log."""
    from markcal.fixtures.servo_log import LogOptions, render_servo_log, save_servo_log
    markcal = os.path.join(os.path.dirname(sys.executable), "markcal")
    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "drive.tsv")
        opts = LogOptions(kind="square", layout="tsv", time_unit="ms", pos_unit="counts", n_lines=n_lines)
        read = save_servo_log(log, render_servo_log(0, opts))
        flags = []
        for k, v in read.items():
            flags += [f"--{k.replace('_', '-')}", f"{v:g}" if isinstance(v, float) else str(v)]
        def timed(cmd):
            walls, cpus = [], []
            for i in range(repeats + 1):
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                subprocess.run([c.replace("{i}", str(i)) for c in cmd], check=False, stdout=subprocess.DEVNULL)
                wall = time.perf_counter() - t0
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                if i:                              # the first run warms the file cache and numba's cache
                    walls.append(wall)
                    cpus.append((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime))
            return walls, cpus
        walls, cpus = timed([markcal, "servo", "--trace", log, *flags, "--settle-band-um", "5", "--out",
                             os.path.join(d, "o{i}"), "--quiet"])
        w0, c0 = timed([markcal, "servo", "--help"])
        size = os.path.getsize(log) / 1e6
    print(f"start-up alone (markcal servo --help): wall median {statistics.median(w0):.2f} s, CPU median "
          f"{statistics.median(c0):.2f} s")
    print(f"drive log {n_lines:,} lines ({size:.0f} MB TSV, ms, counts), whole command with report: wall median "
          f"{statistics.median(walls):.2f} s (min {min(walls):.2f}, max {max(walls):.2f}), CPU median "
          f"{statistics.median(cpus):.2f} s; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
          f"  goal <= 3 s")


def main():
    bench_log()
    if "--log-only" in sys.argv:
        return
    dp, g = discretise(PlantParams()), PIDGains()
    prof = s_curve(10.0, dwell_s=2.0 - 0.12)            # 10 mm move, 2 s record at 10 kHz
    n = len(prof.t_s)

    def move(ctrl):
        r = simulate(dp, g, prof, ctrl)
        step_metrics(prof.t_s, r.ref_mm, r.pos_mm, prof.t_end_s)

    for name, ctrl in (("baseline", BASELINE), ("cca (TD + scheduled PID)", CCA_STEP)):
        med, lo, hi = median_time(lambda: move(ctrl))
        print(f"2 s move ({n:,} samples), {name}: median {med * 1e3:.2f} ms (min {lo * 1e3:.2f}, max {hi * 1e3:.2f})"
              f"  goal <= 200 ms")
    sine = sinusoid(10.0, 1.0, 2)
    med, lo, hi = median_time(lambda: simulate(dp, g, sine, CCA_TRACK, RepetitiveParams(m=7), 1.0))
    print(f"2 s sine with repetitive control ({len(sine.t_s):,} samples): median {med * 1e3:.2f} ms")
    med, lo, hi = median_time(lambda: run_servo(ServoConfig()), n=3)
    print(f"whole default flow (3 moves + 10 sinusoids, 2 controllers, eq. 24 + auto m): median {med:.2f} s")
    for label, cfg in (("paper defaults (reconstructed plant a0 = 61.68)", ServoConfig()),
                       ("variant a0 = 0 (no stiffness term)", ServoConfig(plant=PlantParams(a0=0.0)))):
        s = run_servo(cfg).summary
        print(f"{label}: m = {s['rc_m']}, overshoot {s['step_baseline_overshoot_um']:.2f} -> "
              f"{s['step_cca_overshoot_um']:.2f} um ({s['overshoot_reduction_pct']:.1f} %), settling "
              f"{s['step_baseline_settling_time_s']} -> {s['step_cca_settling_time_s']} s "
              f"({s['settling_reduction_pct']:.1f} %), STD 0.1 Hz {s['std_baseline_0p1hz_um']:.3f} -> "
              f"{s['std_cca_0p1hz_um']:.4f} um ({s['std_reduction_0p1hz_pct']:.1f} %), 2 Hz "
              f"{s['std_baseline_2hz_um']:.3f} -> {s['std_cca_2hz_um']:.3f} um ({s['std_reduction_2hz_pct']:.1f} %)")


if __name__ == "__main__":
    main()
