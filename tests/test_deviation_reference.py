"""Deviation statistics and the correction-grid nodes against values worked by hand."""
import numpy as np

from markcal.stages.deviation import deviation_stats, grid_nodes


def test_max_is_of_the_magnitude_whatever_the_sign():
    xy = np.zeros((3, 2))
    d = np.array([[-0.30, 0.01], [0.10, -0.20], [0.05, 0.02]])
    s = deviation_stats(xy, d)
    assert s["max_x_mm"] == 0.30 and s["max_y_mm"] == 0.20
    assert np.isclose(s["max_mm"], np.hypot(0.30, 0.01))
    assert np.isclose(s["rms_x_mm"], np.sqrt((0.09 + 0.01 + 0.0025) / 3))


def test_grid_nodes_reach_the_field_edge():
    # half widths 10.5 x 3 mm at 1 mm: x needs 11 steps each side to reach 10.5, y exactly 3
    n = grid_nodes(10.5, 3.0, 1.0)
    xs, ys = np.unique(n[:, 0]), np.unique(n[:, 1])
    assert np.array_equal(xs, np.arange(-11, 12, dtype=float))
    assert np.array_equal(ys, np.arange(-3, 4, dtype=float))
    assert len(n) == 23 * 7 and np.array_equal(n[:23, 1], np.full(23, -3.0))    # row-major, y outer
