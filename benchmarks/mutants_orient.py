"""Mutants of the scan flow's orientation and registration stages (issue 21 for issue 22's area).

Each entry of ``MUTANTS_ORIENT`` is one fixed text edit a reviewer would plant in
``stages/orientation.py`` or ``stages/register.py``; ``tests`` names the pytest selection (a list of pytest arguments)
that must kill it. Runs through the harness of ``benchmarks/mutants.py`` (the mutated module is
swapped in at import; the source tree is never written):

    python benchmarks/mutants.py --areas [--jobs 2] [-k NAME] [--no-baseline]

Measured (2 jobs, load 15-18 on 2 cores): 8 of 8 killed; the baseline took 431 s and the mutants
75-360 s each. ``orient-angle-diff-not-wrapped`` survived the first run and is killed since a hint
across the 180 deg wrap was added to tests/test_orientation.py.
"""


ORIENT_TESTS = ["tests/test_orientation.py", "tests/test_geometry.py", "-k",
               "(orientation or hint or upright or ambiguous or galvo_model_alone or rigid or index_grid) "
               "and not closes_the_loop"]

MUTANTS_ORIENT = [
    {"name": "orient-mark-filter-inverted", "file": "stages/orientation.py",
     "old": "pool = [c for c in pool if not np.any(c.ids == mark_id)]",
     "new": "pool = [c for c in pool if np.any(c.ids == mark_id)]", "tests": ORIENT_TESTS},
    {"name": "orient-margin-never-refuses", "file": "stages/orientation.py",
     "old": "        if m_pool < min_margin:", "new": "        if m_pool < 1.0:", "tests": ORIENT_TESTS},
    {"name": "orient-hint-window-wide", "file": "stages/orientation.py",
     "old": "HINT_WINDOW_DEG = 44.0", "new": "HINT_WINDOW_DEG = 60.0", "tests": ORIENT_TESTS},
    {"name": "orient-angle-diff-not-wrapped", "file": "stages/orientation.py",
     "old": "return float(abs((a - b + 180.0) % 360.0 - 180.0))", "new": "return float(abs(a - b))",
     "tests": ORIENT_TESTS},
    {"name": "orient-rotation-sign", "file": "stages/orientation.py",
     "old": "rot = np.degrees(np.arctan2(tf.rotation[0, 1], tf.rotation[0, 0]))",
     "new": "rot = np.degrees(np.arctan2(-tf.rotation[0, 1], tf.rotation[0, 0]))", "tests": ORIENT_TESTS},
    {"name": "orient-mirror-fit-proper", "file": "stages/orientation.py",
     "old": "tf = rigid_fit(uv[on], q, allow_reflection=mirrored)",
     "new": "tf = rigid_fit(uv[on], q, allow_reflection=False)", "tests": ORIENT_TESTS},
    {"name": "register-lattice-2fold", "file": "stages/register.py",
     "old": "theta = np.angle(np.sum(np.exp(4j * ang))) / 4",
     "new": "theta = np.angle(np.sum(np.exp(2j * ang))) / 2", "tests": ORIENT_TESTS},
    {"name": "register-kabsch-no-reflection", "file": "stages/register.py",
     "old": "if not allow_reflection and np.linalg.det(vt.T @ u.T) < 0:",
     "new": "if np.linalg.det(vt.T @ u.T) < 0:", "tests": ORIENT_TESTS},
]

