"""The valley's kink fits (stages/indent_corners._kink_fits): all candidates at once, as each alone."""
import numpy as np
import pytest

from markcal.stages.indent_corners import _kink_fits


def test_kink_fits_match_each_windows_least_squares_and_find_the_kink():
    """A valley's bottom profile rising 40 nm/px to a kink at 30 px, then 2 nm/px (a crack's floor), with 1 nm
    noise, sampled every 0.5 px: every candidate's coefficients and mean squared residual equal those of its own
    window's least-squares fit (to 1e-6), and the best of those rising steeply and then flat sits at the kink
    within a sample, with the two slopes within 1 nm/px."""
    rng = np.random.default_rng(3)
    s = np.arange(0.0, 60.0, 0.5)
    z = -1200.0 + 40.0 * np.minimum(s - 30.0, 0.0) + 2.0 * np.maximum(s - 30.0, 0.0) + rng.normal(0, 1.0, s.size)
    cand, ks, msr = _kink_fits(s, z, 12.0)
    for c, k, m in zip(cand, ks, msr):
        use = np.abs(s - s[c]) <= 12.0
        d = s[use] - s[c]
        a = np.column_stack([np.ones_like(d), np.minimum(d, 0.0), np.maximum(d, 0.0)])
        ref, *_ = np.linalg.lstsq(a, z[use], rcond=None)
        assert np.allclose(k, ref, rtol=1e-6, atol=1e-6)
        assert np.isclose(m, np.mean((a @ ref - z[use]) ** 2), rtol=1e-6, atol=1e-9)
    steep_then_flat = (ks[:, 1] > 10.0) & (ks[:, 2] < ks[:, 1] / 3.0)      # as _valley_kink selects
    b = int(np.flatnonzero(steep_then_flat)[np.argmin(msr[steep_then_flat])])
    assert abs(s[cand[b]] - 30.0) <= 0.5
    assert abs(ks[b, 1] - 40.0) <= 1.0 and abs(ks[b, 2] - 2.0) <= 1.0


def _diamond_pit(level_nm, a_px=40.0, depth_nm=1000.0, n=128):
    """A sharp square pyramid (diagonals along the axes, half-diagonal ``a_px`` where it meets 0) in a surface at
    ``level_nm`` (below 0: the map's zero above the surface, as pile-up's tails or a bow left in put it)."""
    rr, cc = np.mgrid[0:n, 0:n].astype(float)
    c = (n - 1) / 2
    pyr = -depth_nm + depth_nm / a_px * (np.abs(rr - c) + np.abs(cc - c))
    return np.minimum(pyr, level_nm), c


@pytest.mark.parametrize("level_nm", [-20.0, -40.0])
def test_corner_on_the_surface_beyond_it(level_nm):
    """The surface 20-40 nm under the map's zero: the valley meets it a (1 + level / depth) from the floor (0.8-1.6 px
    short of where it would meet 0). With the local level the corner is within 0.1 px of that; at 0 it lies
    beyond by more than half the difference; a surface above 0 (a rim) is not taken."""
    from markcal.stages.indent_corners import corner_on_ray
    from scipy import ndimage
    z, c = _diamond_pit(level_nm)
    zc = ndimage.spline_filter(z, order=3, mode="nearest")
    slope = 1000.0 / 40.0
    true_px = 40.0 * (1 + level_nm / 1000.0)
    coarse = np.array([c, c + true_px + 1.0])
    got, _ = corner_on_ray(zc, np.array([c, c]), coarse, slope, 0.1, z, local_level=True)
    assert abs(got[1] - c - true_px) <= 0.1 and abs(got[0] - c) <= 0.1
    at0, _ = corner_on_ray(zc, np.array([c, c]), coarse, slope, 0.1, z, local_level=False)
    assert at0[1] - c - true_px >= 0.5 * (40.0 - true_px)
    rim, _ = _diamond_pit(0.0)
    rim = np.where(rim >= 0.0, 15.0, rim)                               # a rim 15 nm up all round
    zc_rim = ndimage.spline_filter(rim, order=3, mode="nearest")
    on_rim, _ = corner_on_ray(zc_rim, np.array([c, c]), np.array([c, c + 41.0]), slope, 0.1, rim, local_level=True)
    plain, _ = corner_on_ray(zc_rim, np.array([c, c]), np.array([c, c + 41.0]), slope, 0.1, rim, local_level=False)
    assert np.allclose(on_rim, plain)
