"""Speed and accuracy of the pmcal and drift flows on sessions the tests never see (seeds 1000+).

Run: .venv/bin/python benchmarks/bench_pmcal.py [--sessions N] [--repeats R]
Prints medians; timings are wall-clock and noisy on a shared machine.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import statistics
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.pm_session import render_pm_session, session_data
from markcal.pipeline.cli import main as cli_main
from markcal.pipeline.flows.pmcal import run_pmcal
from markcal.reports.pmcal_outputs import write_pmcal_outputs
from markcal.stages.drift import compensate, in_force, reduction_rate
from markcal.stages.pm_ga import run_ga


def _render(seed: int, out: str) -> None:
    with contextlib.redirect_stdout(io.StringIO()):
        cli_main(["render", "pmcal", "--seed", str(seed), "--out", out, "--quiet"])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sessions", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    d = session_data(render_pm_session(1000))
    ts = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        run_ga(d)
        ts.append(time.perf_counter() - t0)
    print(f"GA 60 x 100: median {statistics.median(ts):.3f} s (min {min(ts):.3f}) over {args.repeats} runs; goal <= 1 s")

    with tempfile.TemporaryDirectory() as tmp:
        sess = os.path.join(tmp, "s")
        _render(1001, sess)
        tf, tr = [], []
        for i in range(args.repeats):
            t0 = time.perf_counter()
            res = run_pmcal(sess)
            write_pmcal_outputs(res, os.path.join(tmp, f"o{i}"), report=False)
            tf.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            write_pmcal_outputs(res, os.path.join(tmp, f"r{i}"), report=True)
            tr.append(time.perf_counter() - t0)
        print(f"pmcal flow (read, GA + 2 x LSQ, truth check, files without report): median {statistics.median(tf):.3f} s; "
              f"report.html adds median {statistics.median(tr):.3f} s; goal (whole flow) <= 3 s")

        rows = {m: [] for m in ("ga", "lsq", "ga+lsq")}
        for k in range(args.sessions):
            sess = os.path.join(tmp, f"a{k}")
            _render(2000 + k, sess)
            res = run_pmcal(sess)
            for m, f in res.fits.items():
                rows[m].append(f.truth_errors)
    print(f"\naccuracy over {args.sessions} unseen sessions (seeds 2000+), 100 random targets each, noise 10 nm "
          "(probe 2 nm):")
    keys = [("landing_rms_um", "landing RMS µm", 0.05), ("landing_max_um", "landing max µm", 0.10),
            ("depth_err_max_um", "|depth err| max µm", 0.005), ("err_nonorth_xy_urad", "non-orth xy µrad", 2),
            ("err_nonorth_xz_urad", "non-orth xz µrad", 2), ("err_nonorth_yz_urad", "non-orth yz µrad", 2),
            ("err_scale_x_ppm", "scale x ppm", 5), ("err_scale_y_ppm", "scale y ppm", 5),
            ("err_scale_z_ppm", "scale z ppm", 5), ("err_pose_rot_urad", "pose rotation µrad", 10),
            ("err_plane_tilt_x_urad", "plane tilt x µrad", 2), ("err_plane_tilt_y_urad", "plane tilt y µrad", 2)]
    print(f"{'quantity (worst |value| over sessions; median)':<48}" + "".join(f"{m:>22}" for m in rows) + "    goal")
    for key, label, goal in keys:
        cells = []
        for m in rows:
            v = np.abs([r[key] for r in rows[m]])
            cells.append(f"{v.max():10.4g} ({np.median(v):8.3g})")
        print(f"{label:<48}" + "".join(f"{c:>22}" for c in cells) + f"    <= {goal}")

    print("\ndrift: η (%) against the true drift at 1-min resolution, 30 unseen records each (seeds 3000+), "
          "median [min] per axis; Δhold = median η minus hold-last's median η (goal for the default on wander: >= -0.1)")
    t_s = np.arange(0, 241, 10)
    for kind in ("thermal", "wander"):
        recs = []
        for seed in range(3000, 3030):
            s = render_pm_session(seed, drift_kind=kind)
            recs.append((np.column_stack([s.drift[k] for k in ("dx_um", "dy_um", "dz_um")]), s))
        med = {}
        for meth in ("hold", "paper", "paper-literal", "trend", "kalman"):
            etas = [reduction_rate(s.drift_true_um, in_force(t_s, compensate(t_s, m, meth), s.drift_true_t_min))[2]
                    for m, s in recs]
            e = np.array(etas)
            med[meth], mn = np.median(e, 0), e.min(0)
            dh = med[meth] - med["hold"]
            print(f"  {kind:<8} {meth:<14} " + "  ".join(f"{a} {med[meth][i]:5.1f} [{mn[i]:5.1f}]" for i, a in enumerate("xyz"))
                  + f"   mean {e.mean():5.1f}   Δhold " + " ".join(f"{v:+5.2f}" for v in dh))
    return 0


if __name__ == "__main__":
    sys.exit(main())
