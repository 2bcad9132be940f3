"""The scanline polygon fill of the single-imprint pile-up mask against an independent point-in-polygon test."""
import numpy as np
from matplotlib.path import Path

from markcal.stages.indent_geometry import inside_polygon


def _truth(rows, cols, shape):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    pts = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    return Path(np.column_stack([cols, rows])).contains_points(pts).reshape(shape)


def test_star_shaped_boundaries_match_an_independent_test():
    rng = np.random.default_rng(3)
    shape = (96, 120)
    for _ in range(40):
        n = int(rng.integers(3, 900))
        t = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = rng.uniform(8, 50) * (1 + 0.35 * np.sin(int(rng.integers(1, 6)) * t + rng.uniform(0, 6)))
        rows = rng.uniform(-10, 100) + rad * np.sin(t)
        cols = rng.uniform(-10, 130) + rad * np.cos(t)
        got = inside_polygon(rows, cols, shape)
        want = _truth(rows, cols, shape)
        # pixel centres within 1e-6 px of an edge may go either way; none should at random vertices
        assert np.array_equal(got, want)


def test_a_known_square():
    rows = np.array([1.5, 1.5, 5.5, 5.5])
    cols = np.array([2.5, 7.5, 7.5, 2.5])
    got = inside_polygon(rows, cols, (8, 10))
    want = np.zeros((8, 10), bool)
    want[2:6, 3:8] = True
    assert np.array_equal(got, want)
