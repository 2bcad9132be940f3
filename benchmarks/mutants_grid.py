"""Mutants of the grid stages (issue 21 for issue 14's ``markcal grid``), run with ``benchmarks/mutants.py``'s harness.

``MUTANTS_GRID`` holds plausible bugs in ``stages/grid_input.py``, ``stages/galvo_fit.py`` and
``stages/grid_smooth.py``, one dict each: ``name``, ``kind`` (the harness's kinds), ``file``, ``old``
(text that occurs exactly once), ``new`` and ``tests`` (pytest arguments of the fast grid tests).
``python benchmarks/mutants.py --areas -k grid`` runs each in a fresh pytest process with the mutated module
swapped in at import (the source tree is never written) and prints killed / survived.

Not listed, as equivalent: dropping ``- lam * w`` from the spline's affine fit
(``lstsq(p, y - k @ w - lam * w)``): the weights satisfy ``P' w = 0``, so ``lam * w`` has no
component in the span of ``P`` and the least-squares affine part is the same (it survived, as it must).

Measured (2-core machine shared with other sessions, load 12-15): the baseline passes in 23 s; every
mutant is killed, each in 4-16 s, 50-100 s in all (10 of 10). Against the grid tests as they were before (the whole
file, slow tests included) 7 of 10 were killed: the BJJCZ i/j swap and the coupling and decentring
swaps survived; the tests that now kill them are ``test_bjjcz_line_and_layout_detection`` (row and
column of every line) and ``test_physical_model_holds_the_true_galvo``; the CV leak, the hull and the
prior weight were caught before only by the slow CLI tests and now also by fast hand-computed ones.
"""


FAST = ["tests/test_grid.py", "-k", "not grid_to_cor and not grid_job"]

MUTANTS_GRID = [
    {"name": "grid-bjjcz-ij-swap", "kind": "axis-swap", "file": "stages/grid_input.py",
     "old": 'ij.append([int(_number(tok[3], "j", i + 1)), int(_number(tok[2], "i", i + 1))])',
     "new": 'ij.append([int(_number(tok[2], "i", i + 1)), int(_number(tok[3], "j", i + 1))])', "tests": FAST},
    {"name": "grid-bjjcz-centre-off-by-one", "kind": "off-by-half-pixel", "file": "stages/grid_input.py",
     "old": "BJJCZ_CENTRE_UNITS = 0x8000", "new": "BJJCZ_CENTRE_UNITS = 0x7FFF", "tests": FAST},
    {"name": "galvo-fit-coupling-axis-swap", "kind": "axis-swap", "file": "stages/galvo_fit.py",
     "old": "ty = 2.0 * ((1.0 + gy) * ay + zy + cyx * ax)", "new": "ty = 2.0 * ((1.0 + gy) * ay + zy + cyx * ay)",
     "tests": FAST},
    {"name": "galvo-fit-decentring-swap", "kind": "axis-swap", "file": "stages/galvo_fit.py",
     "old": "x + k3 * r2 * u + p1 * (r2 + 2 * u * u) + 2 * p2 * u * v",
     "new": "x + k3 * r2 * u + p2 * (r2 + 2 * u * u) + 2 * p1 * u * v", "tests": FAST},
    {"name": "galvo-fit-prior-weight", "kind": "unit-factor", "file": "stages/galvo_fit.py",
     "old": "w_prior = 1e-2", "new": "w_prior = 1e2", "tests": FAST},
    {"name": "galvo-fit-cv-leak", "kind": "dropped-term", "file": "stages/galvo_fit.py",
     "old": "m = fit_model(kind, cmd[tr], land[tr], d0_mm, e0_mm, start)",
     "new": "m = fit_model(kind, cmd, land, d0_mm, e0_mm, start)", "tests": FAST},
    {"name": "galvo-fit-hull-min", "kind": "sign", "file": "stages/galvo_fit.py",
     "old": "return np.maximum(d.max(axis=1), 0.0)", "new": "return np.maximum(d.min(axis=1), 0.0)", "tests": FAST},
    {"name": "grid-smooth-loo-unscaled", "kind": "dropped-term", "file": "stages/grid_smooth.py",
     "old": "e = w / (zv2 @ g)[:, None]", "new": "e = w", "tests": FAST},
    {"name": "grid-smooth-smoothing-dropped", "kind": "dropped-term", "file": "stages/grid_smooth.py",
     "old": "g = 1.0 / (s + lam)", "new": "g = 1.0 / (s + 1e-12)", "tests": FAST},
    {"name": "grid-smooth-kernel-factor", "kind": "unit-factor", "file": "stages/grid_smooth.py",
     "old": "return 0.5 * r2 * np.log(r2)", "new": "return r2 * np.log(r2)", "tests": FAST},
]

