"""The one dedupe (stages.detect.dedupe) used by the scan and indents flows, against brute force."""
from __future__ import annotations

import numpy as np

from markcal.stages import detect


def _greedy(xy, score, r):
    """Brute force: best first (ties: earlier), keep a point unless a kept one is within max(r_i, r_j)."""
    keep = []
    for i in sorted(range(len(xy)), key=lambda i: -score[i]):
        if all(np.hypot(*(xy[i] - xy[k])) > max(r[i], r[k]) for k in keep):
            keep.append(i)
    return sorted(keep)


def test_dedupe_matches_brute_force_scalar_and_per_point():
    rng = np.random.default_rng(4)
    for _ in range(100):
        n = int(rng.integers(1, 50))
        xy = rng.uniform(0, 20, (n, 2))
        score = rng.integers(0, 4, n).astype(float)           # ties on purpose
        radii = rng.uniform(0.3, 3.0, n)
        assert detect.dedupe(xy, score, radii).tolist() == _greedy(xy, score, radii)
        assert detect.dedupe(xy, score, 1.2).tolist() == _greedy(xy, score, np.full(n, 1.2))


def test_dedupe_keeps_the_better_of_two_close_points():
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [5.0, 0.0]])
    assert detect.dedupe(xy, [1.0, 2.0, 0.0], 1.0).tolist() == [1, 2]
    assert detect.dedupe(np.zeros((0, 2)), [], 1.0).tolist() == []
