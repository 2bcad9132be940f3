"""Mutants of the scan flow's orientation and registration stages (issue 21 for issue 22's area).

Each entry of ``MUTANTS_ORIENT`` is one fixed text edit a reviewer would plant in
``stages/orientation.py`` or ``stages/register.py``; ``tests`` names the pytest selection (in ``TESTS``)
that must kill it. Runs through the harness of ``benchmarks/mutants.py`` (the mutated module is
swapped in at import; the source tree is never written):

    python benchmarks/mutants_orient.py [--jobs 2] [-k NAME] [--no-baseline]

Measured (2 jobs, load 15-18 on 2 cores): 8 of 8 killed; the baseline took 431 s and the mutants
75-360 s each. ``orient-angle-diff-not-wrapped`` survived the first run and is killed since a hint
across the 180 deg wrap was added to tests/test_orientation.py.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mutants as harness  # noqa: E402  (benchmarks/mutants.py)

TESTS = {
    "orient": ["tests/test_orientation.py", "tests/test_geometry.py", "-k",
               "(orientation or hint or upright or ambiguous or galvo_model_alone or rigid or index_grid) "
               "and not closes_the_loop"],
}

MUTANTS_ORIENT = [
    {"name": "orient-mark-filter-inverted", "file": "stages/orientation.py",
     "old": "pool = [c for c in pool if not np.any(c.ids == mark_id)]",
     "new": "pool = [c for c in pool if np.any(c.ids == mark_id)]", "tests": "orient"},
    {"name": "orient-margin-never-refuses", "file": "stages/orientation.py",
     "old": "        if m_pool < min_margin:", "new": "        if m_pool < 1.0:", "tests": "orient"},
    {"name": "orient-hint-window-wide", "file": "stages/orientation.py",
     "old": "HINT_WINDOW_DEG = 44.0", "new": "HINT_WINDOW_DEG = 60.0", "tests": "orient"},
    {"name": "orient-angle-diff-not-wrapped", "file": "stages/orientation.py",
     "old": "return float(abs((a - b + 180.0) % 360.0 - 180.0))", "new": "return float(abs(a - b))",
     "tests": "orient"},
    {"name": "orient-rotation-sign", "file": "stages/orientation.py",
     "old": "rot = np.degrees(np.arctan2(tf.rotation[0, 1], tf.rotation[0, 0]))",
     "new": "rot = np.degrees(np.arctan2(-tf.rotation[0, 1], tf.rotation[0, 0]))", "tests": "orient"},
    {"name": "orient-mirror-fit-proper", "file": "stages/orientation.py",
     "old": "tf = rigid_fit(uv[on], q, allow_reflection=mirrored)",
     "new": "tf = rigid_fit(uv[on], q, allow_reflection=False)", "tests": "orient"},
    {"name": "register-lattice-2fold", "file": "stages/register.py",
     "old": "theta = np.angle(np.sum(np.exp(4j * ang))) / 4",
     "new": "theta = np.angle(np.sum(np.exp(2j * ang))) / 2", "tests": "orient"},
    {"name": "register-kabsch-no-reflection", "file": "stages/register.py",
     "old": "if not allow_reflection and np.linalg.det(vt.T @ u.T) < 0:",
     "new": "if np.linalg.det(vt.T @ u.T) < 0:", "tests": "orient"},
]


def _mutant(d: dict) -> harness.Mutant:
    return harness.Mutant(d["name"], "orient", d["file"], d["old"], d["new"], d["tests"])


def _baseline(timeout_s: float) -> None:
    """The selection must pass with the unchanged modules loaded through the harness (a null mutant)."""
    print("baseline: the selection passes without a mutant ...", flush=True)
    with tempfile.TemporaryDirectory() as work:
        null = harness.Mutant("null-orient", "none", "stages/orientation.py", "", "", "orient", count=0)
        _, status, dt, tail = harness.run_mutant(null, sys.executable, work, timeout_s)
        print(f"baseline {dt:6.1f} s  {tail}", flush=True)
        if status != "SURVIVED":
            raise SystemExit(f"baseline: the tests fail without a mutant ({status}): {tail}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-k", default="", help="only mutants whose name contains this")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of the selection")
    args = ap.parse_args(argv)
    harness.TESTS.update(TESTS)
    chosen = [_mutant(d) for d in MUTANTS_ORIENT if args.k in d["name"]]
    for m in chosen:
        harness.mutated_source(m)            # every edit applies and compiles before anything runs
    if not args.no_baseline:
        _baseline(args.timeout)
    t0 = time.perf_counter()
    killed = 0
    with tempfile.TemporaryDirectory() as work, cf.ThreadPoolExecutor(max(1, args.jobs)) as pool:
        futs = [pool.submit(harness.run_mutant, m, sys.executable, work, args.timeout) for m in chosen]
        for f in cf.as_completed(futs):
            m, status, dt, tail = f.result()
            killed += status == "killed"
            print(f"{status:9s} {m.id:32s} {dt:6.1f} s  {tail}", flush=True)
    print(f"{killed} of {len(chosen)} killed in {time.perf_counter() - t0:.0f} s")
    return 0 if killed == len(chosen) else 1


if __name__ == "__main__":
    sys.exit(main())
