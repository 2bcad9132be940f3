"""``quantile.median_filter``: the values of ``scipy.ndimage.median_filter(mode="nearest")``, exactly."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from markcal.stages.quantile import median_filter


@pytest.mark.parametrize("seed", range(6))
def test_median_filter_equals_ndimage_exactly(seed):
    rng = np.random.default_rng(seed)
    for size in (1, 3, 5, 15, 21):
        for shape in ((1, 1), (3, 40), (57, 9), (64, 64)):
            a = rng.normal(size=shape) * 10
            if seed % 2:
                a = np.round(a)                           # many ties
            assert np.array_equal(median_filter(a, size), ndimage.median_filter(a, size=size, mode="nearest"))


def test_median_filter_of_a_constant_and_of_a_step():
    assert np.array_equal(median_filter(np.full((9, 11), 2.5), 5), np.full((9, 11), 2.5))
    step = np.zeros((20, 20))
    step[:, 10:] = 1.0
    got = median_filter(step, 5)
    assert np.array_equal(got[:, :10], np.zeros((20, 10))) and np.array_equal(got[:, 10:], np.ones((20, 10)))


def test_median_filter_refuses_an_even_size():
    with pytest.raises(ValueError, match="odd"):
        median_filter(np.zeros((5, 5)), 4)
