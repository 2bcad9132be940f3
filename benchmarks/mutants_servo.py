"""Plausible bugs planted in the servo stages, and whether the servo tests catch each (issue 21).

Each entry of ``MUTANTS_SERVO`` is one text edit of a servo stage: ``name``, ``file``, ``old``
(occurs exactly once), ``new`` and ``tests`` (the pytest arguments that must fail). The edits run
through the harness of ``benchmarks/mutants.py``: the mutated module is swapped in at import in a
fresh pytest process, the source tree is never written.

Run: .venv/bin/python benchmarks/mutants.py --areas [--jobs 2] [-k NAME] [--list]
"""


TRUTHS = ["tests/test_servo_truths.py"]

LOGS = ["tests/test_servo_truths.py", "tests/test_servo_log.py", "-k",
        "truths or moves_against_truth or sine_against_truth"]

#: the composite controller's Table 2 rows (issue 15, third pass)
CCA_SINE = ["tests/test_servo.py", "-k", "paper_defaults or learned_period or previous_window"]

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
    {"name": "servo-cca-window-one-period-early", "kind": "off-by-one", "file": "pipeline/flows/servo.py",
     "old": "n = int(round(n_cca / freq / ts)) + 1", "new": "n = int(round((n_cca - 1) / freq / ts)) + 1",
     "tests": CCA_SINE},
    {"name": "servo-rc-lead-as-lag", "kind": "sign", "file": "stages/servo_sim.py",
     "old": "j = k - rc_D + rc_m", "new": "j = k - rc_D - rc_m", "tests": CCA_SINE},
]
