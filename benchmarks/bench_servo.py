"""Servo flow timings (goal: a 2 s move at 10 kHz simulates in <= 0.2 s) and the headline reductions.

Run: .venv/bin/python benchmarks/bench_servo.py  (medians of several runs; first call compiles numba).
"""
from __future__ import annotations

import statistics
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


def main():
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
