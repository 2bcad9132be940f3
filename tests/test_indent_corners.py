"""The valley's kink fits (stages/indent_corners._kink_fits): all candidates at once, as each alone."""
import numpy as np

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
