"""Plausible bugs planted in the servo stages, and whether the servo tests catch each (issue 21).

Each entry of ``MUTANTS_SERVO`` is one text edit of a servo stage: ``name``, ``file``, ``old``
(occurs exactly once), ``new`` and ``tests`` (the pytest arguments that must fail). The edits run
through the harness of ``benchmarks/mutants.py``: the mutated module is swapped in at import in a
fresh pytest process, the source tree is never written.

Run: .venv/bin/python benchmarks/mutants_servo.py [--jobs 2] [-k NAME] [--list]
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mutants as harness  # noqa: E402  (benchmarks/mutants.py: the plugin and the runner)

TRUTHS = ["tests/test_servo_truths.py"]
LOGS = ["tests/test_servo_truths.py", "tests/test_servo_log.py", "-k",
        "truths or moves_against_truth or sine_against_truth"]

MUTANTS_SERVO = [
    {"name": "servo-std-as-rms", "kind": "dropped-term", "file": "stages/servo_sim.py",
     "old": "return float(np.mean(np.abs(e_um))), float(np.std(e_um))",
     "new": "return float(np.mean(np.abs(e_um))), float(np.sqrt(np.mean(e_um ** 2)))", "tests": TRUTHS},
    {"name": "servo-phase-lag-sign", "kind": "sign", "file": "stages/servo_log.py",
     "old": "lag = np.degrees(np.arctan2(cr[1], cr[0]) - np.arctan2(cp[1], cp[0]))",
     "new": "lag = np.degrees(np.arctan2(cp[1], cp[0]) - np.arctan2(cr[1], cr[0]))", "tests": TRUTHS},
    {"name": "servo-overshoot-direction", "kind": "sign", "file": "stages/servo_sim.py",
     "old": "over = float(max(0.0, np.max(sgn * dev_um)))", "new": "over = float(max(0.0, np.max(dev_um)))",
     "tests": LOGS},
    {"name": "servo-settling-one-sample-early", "kind": "off-by-one", "file": "stages/servo_sim.py",
     "old": "settle = float(t_s[outside[-1] + 1] - t_end_s)", "new": "settle = float(t_s[outside[-1]] - t_end_s)",
     "tests": TRUTHS},
    {"name": "servo-integral-without-ts", "kind": "unit-factor", "file": "stages/servo_sim.py",
     "old": "integ += e * ts", "new": "integ += e", "tests": TRUTHS},
    {"name": "servo-plant-damping-sign", "kind": "sign", "file": "stages/servo_plant.py",
     "old": "Ac = np.array([[0.0, 1.0], [-p.a0, -p.a1]])", "new": "Ac = np.array([[0.0, 1.0], [-p.a0, p.a1]])",
     "tests": TRUTHS},
    {"name": "servo-microseconds-as-ms", "kind": "unit-factor", "file": "stages/servo_log.py",
     "old": '"us": 1e-6}', "new": '"us": 1e-3}', "tests": LOGS},
    {"name": "servo-rise-to-95pct", "kind": "unit-factor", "file": "stages/servo_log.py",
     "old": "_crossing_time(t, y, 0.9, 1)", "new": "_crossing_time(t, y, 0.95, 1)", "tests": TRUTHS},
]


def _mutant(d: dict, count: int = 1) -> harness.Mutant:
    key = "servo:" + " ".join(d["tests"])
    harness.TESTS[key] = d["tests"]
    return harness.Mutant(d["name"], d["kind"], d["file"], d["old"], d["new"], key, count=count)


def _run(m, py, work, timeout):
    """One mutant in a worker process with its own numba cache: numba keys its on-disk cache by the
    source file, not the mutated text, so a shared cache could hand one mutant another's machine code."""
    os.environ["NUMBA_CACHE_DIR"] = os.path.join(work, "numba-" + m.id)
    return harness.run_mutant(m, py, work, timeout)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-k", default="", help="only mutants whose name contains this")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=600.0)
    a = ap.parse_args(argv)
    chosen = [_mutant(d) for d in MUTANTS_SERVO if a.k in d["name"]]
    for m in chosen:
        harness.mutated_source(m)            # every edit applies exactly once and compiles
    if a.list:
        for m in chosen:
            print(f"{m.id:34s} {m.kind:14s} {m.file}")
        return 0
    py = sys.executable
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work, cf.ProcessPoolExecutor(max(1, a.jobs)) as pool:
        # the unmutated tests must pass through the same plugin, or a "kill" means nothing
        nulls = {m.tests: harness.Mutant(f"null-{i}", "none", m.file, "", "", m.tests, count=0)
                 for i, m in enumerate(chosen)}
        args = lambda ms: ([m for m in ms], [py] * len(ms), [work] * len(ms), [a.timeout] * len(ms))  # noqa: E731
        for m, status, dt, tail in pool.map(_run, *args(list(nulls.values()))):
            print(f"baseline {harness.TESTS[m.tests]}: {status} ({dt:.0f} s)", flush=True)
            if status != "SURVIVED":
                raise SystemExit(f"baseline fails without a mutant: {tail}")
        results = list(pool.map(_run, *args(chosen)))
    for m, status, dt, tail in results:
        print(f"{status:9s} {m.id:34s} {m.kind:14s} {dt:6.1f} s  {tail}")
    killed = sum(r[1] == "killed" for r in results)
    print(f"servo mutants: {len(results)}, killed {killed}, survived {len(results) - killed} "
          f"({time.perf_counter() - t0:.0f} s wall)")
    return 0 if killed == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
