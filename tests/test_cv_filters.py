"""stages/cv_filters against the scipy.ndimage calls they stand in for."""
import numpy as np
import pytest
from scipy import ndimage

from markcal.stages.cv_filters import binary_dilate, dilate_square, gaussian, grey_close, max_line, min_line


@pytest.mark.parametrize("shape", [(5, 7), (9, 9), (10, 40), (257, 311), (512, 512)])
@pytest.mark.parametrize("sigma", [0.7, 1.0, 2.5, 6.0])
@pytest.mark.parametrize("mode", ["reflect", "nearest"])
def test_gaussian_is_scipys_gaussian_filter(shape, sigma, mode):
    # heights with a trend and a step (borders matter), float64: equal to rounding (1e-13 of the values)
    rng = np.random.default_rng(shape[0] * 1000 + shape[1] + int(10 * sigma))
    z = rng.normal(size=shape).cumsum(axis=0) + 50.0 * (np.arange(shape[1]) > shape[1] // 3)
    want = ndimage.gaussian_filter(z, sigma, mode=mode)
    got = gaussian(z, sigma, mode)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.max(np.abs(got - want)) <= 1e-13 * np.max(np.abs(want))


def test_gaussian_float32_views_and_other_dtypes():
    rng = np.random.default_rng(3)
    z = rng.normal(size=(300, 400)).cumsum(axis=1)
    view = z[::2, 1::3]                                         # not contiguous
    assert np.max(np.abs(gaussian(view, 1.0) - ndimage.gaussian_filter(view, 1.0))) <= 1e-12
    z32 = z.astype(np.float32)
    got = gaussian(z32, 1.0)
    assert got.dtype == np.float32
    assert np.max(np.abs(got - ndimage.gaussian_filter(z32, 1.0))) <= 1e-5 * np.max(np.abs(z32))
    ints = (z * 10).astype(np.int32)                            # scipy's own rounding for integers
    assert np.array_equal(gaussian(ints, 1.0), ndimage.gaussian_filter(ints, 1.0))


@pytest.mark.parametrize("shape", [(4, 5), (13, 40), (257, 311)])
@pytest.mark.parametrize("share", [0.03, 0.5])
def test_binary_morphology_is_scipys(shape, share):
    """Exactly scipy's result, borders included (outside the map counts as 0, or as ``cval``)."""
    m = np.random.default_rng(shape[0] + int(100 * share)).random(shape) < share
    u = m.view(np.uint8)
    for size in (3, 6, 7, 9):
        assert np.array_equal(dilate_square(m, size), ndimage.maximum_filter(m, size=size, mode="constant"))
        for axis in (0, 1):
            assert np.array_equal(max_line(m, size, axis),
                                  ndimage.maximum_filter1d(u, size, axis=axis, mode="constant", cval=0))
            for cval in (0, 1):
                assert np.array_equal(min_line(m, size, axis, cval),
                                      ndimage.minimum_filter1d(u, size, axis=axis, mode="constant", cval=cval))
    for iterations in (1, 3, 12):
        assert np.array_equal(binary_dilate(m, iterations), ndimage.binary_dilation(m, iterations=iterations))


@pytest.mark.parametrize("shape", [(6, 6), (40, 13), (257, 311)])
def test_grey_closing_is_scipys(shape):
    z = np.random.default_rng(shape[1]).normal(size=shape).cumsum(axis=0)
    for r in (1.5, 3.0, 4.5):
        ri = int(np.ceil(r))
        yy, xx = np.mgrid[-ri:ri + 1, -ri:ri + 1]
        disc = yy ** 2 + xx ** 2 <= r ** 2 + 1e-9
        for mode in ("reflect", "nearest"):
            assert np.array_equal(grey_close(z, disc, mode), ndimage.grey_closing(z, footprint=disc, mode=mode))
    assert np.array_equal(grey_close(z, np.ones((9, 9), bool)), ndimage.grey_closing(z, size=9))
