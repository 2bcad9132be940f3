"""Plausible bugs in the path flow's local search, for the mutation harness (issue 21).

Each entry: ``name``, ``file`` (relative to the repository), ``old`` text (occurs once), ``new``
text, ``tests`` (pytest arguments that must fail with the edit applied). Checked by hand in a
scratch copy of the repository (each edit applied, the tests run, 150 s limit):

- killed by a failing test: candidates-truncated, alpha-beta-dropped, kick-kept-when-longer,
  entry-keeps-worse (by test_best_entries_moves_a_contour_entry_to_the_near_corner, added after
  it first survived);
- killed by the time limit only (the search never ends: a "gain" that lengthens the tour is
  found again and again): 2opt-gain-sign, oropt-gain-sign, lk-close-sign;
- survives: oropt-single-strokes-only (2-opt and the LK step make the same repairs on these tests).

A harness that swaps a module in at import should give numba a fresh cache folder
(``NUMBA_CACHE_DIR``): these kernels are ``cache=True``.
"""

_T = ["tests/test_path_tour.py", "tests/test_path.py", "-k", "not cli and not bad_input"]

MUTANTS_PATH = [
    {"name": "path-2opt-gain-sign", "file": "stages/path_tour_moves.py",
     "old": "g = d12 + _c(xy, t3, t4, a, b) - d13 - _c(xy, t2, t4, a, b)",
     "new": "g = d12 - _c(xy, t3, t4, a, b) - d13 + _c(xy, t2, t4, a, b)", "tests": _T},
    {"name": "path-oropt-gain-sign", "file": "stages/path_tour_moves.py",
     "old": "g = g1 - dec - _c(xy, o, cn, a, b) + _c(xy, c, cn, a, b)",
     "new": "g = g1 - dec + _c(xy, o, cn, a, b) - _c(xy, c, cn, a, b)", "tests": _T},
    {"name": "path-oropt-single-strokes-only", "file": "stages/path_tour_moves.py",
     "old": "for k in range(1, max_seg + 1):", "new": "for k in range(1, 1):", "tests": _T},
    {"name": "path-candidates-truncated", "file": "stages/path_tour_cand.py",
     "old": "k = min(k, N - 2)", "new": "k = min(k, N - 2, 4)", "tests": _T},
    {"name": "path-alpha-beta-dropped", "file": "stages/path_tour_cand.py",
     "old": "beta[j] = max(beta[dad[j]], key[j])", "new": "beta[j] = key[j]", "tests": _T},
    {"name": "path-lk-close-sign", "file": "stages/path_tour_moves.py",
     "old": "close = g - _c(xy, t4, t1, a, b)", "new": "close = g + _c(xy, t4, t1, a, b)", "tests": _T},
    {"name": "path-kick-kept-when-longer", "file": "stages/path_tour_moves.py",
     "old": "        if delta > _EPS:\n            for k in range(n):",
     "new": "        if delta < -_EPS:\n            for k in range(n):", "tests": _T},
    {"name": "path-entry-keeps-worse", "file": "stages/path_tour.py",
     "old": "if cost[j] < cost[entry[k]] - 1e-12:", "new": "if cost[j] > cost[entry[k]] + 1e-12:", "tests": _T},
]
