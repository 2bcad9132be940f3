"""Selfcal flow: speed (N = 21, K = 72) and accuracy on sessions the tests never use.

Run: .venv/bin/python benchmarks/bench_selfcal.py [--runs 7] [--seeds 20]
"""
import argparse
import contextlib
import io
import os
import platform
import tempfile
import time

import numpy as np

from markcal.fixtures.selfcal_stage import SelfcalOptions, render_selfcal
from markcal.pipeline.cli import main
from markcal.stages.selfcal import solve_selfcal


def sweep(opts, seeds):
    sx, st, ratio = [], [], []
    for seed in seeds:
        r = render_selfcal(seed, opts)
        sol = solve_selfcal(r.setup, r.grid, r.angle)
        N = opts.n
        ex = np.asarray(r.truth["gx_um"]).reshape(N, N) - sol.gx_um
        ey = np.asarray(r.truth["gy_um"]).reshape(N, N) - sol.gy_um
        et = np.asarray(r.truth["gtheta_deg"]) - sol.gtheta_deg
        sx += [ex.std(ddof=1), ey.std(ddof=1)]
        st.append(et.std(ddof=1))
        bound = np.sqrt(np.mean(np.r_[sol.predicted_sd_gx_um.ravel(), sol.predicted_sd_gy_um.ravel()] ** 2))
        ratio.append(np.sqrt(np.mean([ex.var(ddof=1), ey.var(ddof=1)])) / bound)
    return np.array(sx), np.array(st), np.array(ratio)


def main_():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--seeds", type=int, default=20)
    a = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    big = render_selfcal(1000, SelfcalOptions(n=21, pitch_mm=5.0, k=72))
    solve_selfcal(big.setup, big.grid, big.angle)          # warm-up
    for bound in (False, True):
        ts = []
        for _ in range(a.runs):
            t = time.perf_counter()
            solve_selfcal(big.setup, big.grid, big.angle, bound=bound)
            ts.append(time.perf_counter() - t)
        print(f"solve N=21, K=72{' + covariance bound' if bound else ''}: median {np.median(ts) * 1e3:.0f} ms "
              f"(min {min(ts) * 1e3:.0f}, max {max(ts) * 1e3:.0f}; {a.runs} runs; goal <= 500 ms)")
    with tempfile.TemporaryDirectory() as d:
        with contextlib.redirect_stdout(io.StringIO()):
            main(["render", "selfcal", "--seed", "1000", "--n", "21", "--pitch-mm", "5", "--k", "72",
                  "--out", f"{d}/s", "--quiet"])
        tc = []
        for _ in range(3):
            t = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                main(["selfcal", f"{d}/s", "--out", f"{d}/o", "--quiet"])
            tc.append(time.perf_counter() - t)
        print(f"whole command N=21 (read, solve, tables, report): median {np.median(tc):.2f} s")
    seeds = range(1000, 1000 + a.seeds)
    for label, opts in (("11x11, K=24, noise 0.02 um / 0.001 deg", SelfcalOptions()),
                        ("11x11, K=24, noise 0.002 um / 0.0001 deg",
                         SelfcalOptions(noise_xy_um=0.002, noise_theta_deg=0.0001)),
                        ("21x21 @ 5 mm, K=72, noise 0.02 um / 0.001 deg", SelfcalOptions(n=21, pitch_mm=5.0, k=72)),
                        ("11x11, noise-free", SelfcalOptions(noise_xy_um=0.0, noise_theta_deg=0.0))):
        sx, st, ratio = sweep(opts, seeds)
        over = f", above the noise level {np.sum(sx > opts.noise_xy_um)}/{len(sx)}" if opts.noise_xy_um else ""
        print(f"{label} ({len(seeds)} seeds): std E_Gxy median {np.median(sx):.3g} um, max {sx.max():.3g}{over}; "
              f"std E_Gtheta median {np.median(st):.3g} deg, max {st.max():.3g}"
              + (f"; error / LSQ bound median {np.median(ratio):.3f}" if opts.noise_xy_um else ""))


if __name__ == "__main__":
    main_()
