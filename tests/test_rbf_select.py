"""OLS forward selection (stages/rbf.py): each chosen centre is the largest error reduction.

The compiled selection (modified Gram-Schmidt, stages/rbf._ols_kernel) must choose what the
textbook algorithm chooses: checked against brute force.
"""
import numpy as np
import pytest

from markcal.stages import rbf


def _data(n, seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-40, 40, (n, 2))
    y = np.column_stack([0.02 * np.sin(x[:, 0] / 15), 0.01 * np.cos(x[:, 1] / 11) * x[:, 0] / 40])
    return x, y + rng.normal(0, 0.001, y.shape)


def _design(x, c, spread):
    d2 = ((x[:, None] - c[None]) ** 2).sum(2)
    return np.column_stack([np.exp(-0.5 * d2 / spread ** 2), np.ones(len(x))])


def _brute_force(x, y, spread, steps):
    """Greedy by refitting every candidate: the centre whose addition lowers the LS error most."""
    chosen = []
    for _ in range(steps):
        best, best_sse = None, np.inf
        for j in range(len(x)):
            if j in chosen:
                continue
            a = _design(x, x[chosen + [j]], spread)
            sol, *_ = np.linalg.lstsq(a, y, rcond=None)
            sse = ((a @ sol - y) ** 2).sum()
            if sse < best_sse:
                best, best_sse = j, sse
        chosen.append(best)
    return chosen


def test_each_chosen_centre_is_the_largest_error_reduction():
    x, y = _data(40, 3)
    order, mse, _ = rbf.ols_select(x, y, 12.0, 8)
    assert order == _brute_force(x, y, 12.0, 8)
    a = _design(x, x[order], 12.0)
    sol, *_ = np.linalg.lstsq(a, y, rcond=None)
    assert mse[-1] == pytest.approx(np.mean((a @ sol - y) ** 2), rel=1e-9)


def test_selection_stops_at_the_goal_and_the_cap():
    x, y = _data(60, 5)
    order, mse, _ = rbf.ols_select(x, y, 12.0, 60, mse_goal=2e-5)
    assert mse[-1] <= 2e-5 < mse[-2]
    order, mse, _ = rbf.ols_select(x, y, 12.0, 7)
    assert len(order) == 7 and len(mse) == 8


def test_wide_kernel_on_a_plate_grid_stays_orthogonal():
    # the 19 x 19 plate at 10.56 mm pitch with the 68.6 mm spread the scan flow chooses: the design is
    # close to singular (a classical Gram-Schmidt lost orthogonality here and ran to 200 neurons); the
    # training MSE after every step must be the least-squares MSE of the centres chosen so far (measured:
    # 20 centres, relative differences up to 5e-14; a lost orthogonality shows as 1e-5 and more)
    g = (np.arange(19) - 9) * 10.56
    x = np.column_stack([np.repeat(g, 19), np.tile(g, 19)])
    rng = np.random.default_rng(7)
    y = np.column_stack([0.3 * np.sin(x[:, 0] / 60) * np.cos(x[:, 1] / 80), 1e-5 * x[:, 0] * x[:, 1] / 10])
    y = y + rng.normal(0, 0.001, y.shape)
    order, mse, _ = rbf.ols_select(x, y, 68.6, 200, mse_goal=1e-6)
    assert 10 <= len(order) <= 40 and mse[-1] <= 1e-6 < mse[-2]
    for m in (5, len(order) // 2, len(order)):
        a = _design(x, x[order[:m]], 68.6)
        sol, *_ = np.linalg.lstsq(a, y, rcond=None)
        assert mse[m] == pytest.approx(np.mean((a @ sol - y) ** 2), rel=1e-10)
