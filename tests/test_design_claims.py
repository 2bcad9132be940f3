"""Design claims of the README as tests, on the stages directly.

* The scan correction learns the inverse of the machine (trained on the measured landings P with
  targets Q - P, command K = t + f(t)); the README says this cuts the loop residual about 3x against
  the paper's eq. 9 (trained on the nominal Q, K = Q + δ̂(Q)). Checked on true machines drawn by
  ``fixtures/gls.py`` (its own physics, not ``stages/galvo.py``).
* OLS forward selection (Chen, Cowan & Grant 1991) adds, at each step, the centre with the largest
  reduction of the training error: checked against a brute-force search on a small set.
"""
import numpy as np
import pytest

from markcal.fixtures.gls import correction_residual, sample_true_galvo
from markcal.stages import rbf

#: one network setting for both trainings (3 pitches; MSE goal at the 2 µm landing noise, 4e-6 mm²): the
#: claim is about what the network is trained on, so the cross-validated search is left out (speed)
SPREAD_MM, GOAL_MM2 = 30.0, 4e-6


def _plate(seed, noise_mm=0.002):
    """Nominal fiducials Q (19 x 19 at 10 mm) marked on a true machine: landings P (GLS frame, mm)."""
    rng = np.random.default_rng([seed, 21])
    machine = sample_true_galvo(rng)
    g = np.arange(-90.0, 90.1, 10.0)
    q = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    p = machine.land(q) + rng.normal(0, noise_mm, q.shape)
    return machine, q, p


def _fit(x, y):
    return rbf.train(x, y, SPREAD_MM, GOAL_MM2)


def _loop_rms(machine, command):
    _, res = correction_residual(machine, command, 80.0, 80.0, step_mm=4.0)
    return float(np.sqrt(np.mean((res ** 2).sum(axis=1))))


@pytest.mark.parametrize("seed", [1, 2])
def test_inverse_map_beats_eq9_on_the_true_machine(seed):
    machine, q, p = _plate(seed)
    inverse = _fit(p, q - p)                         # where a mark lands -> the command that put it there
    eq9 = _fit(q, q - p)                             # the paper: deviation predicted at the wanted position
    rms_inv = _loop_rms(machine, lambda t: t + inverse(t))
    rms_eq9 = _loop_rms(machine, lambda t: t + eq9(t))
    rms_none = _loop_rms(machine, lambda t: t)
    assert rms_none > 0.3                            # the uncorrected field is off by a fraction of a mm
    # measured (seeds 1, 2): inverse 0.0021 / 0.0015 mm, eq. 9 0.0078 / 0.0067 mm (3.7x, 4.5x; the README
    # says ~3x over 10 plates); the limits ask for 2x and ~1.9x the worst inverse residual
    assert rms_inv < 0.5 * rms_eq9, (rms_inv, rms_eq9)
    assert rms_inv < 0.004, rms_inv


def _brute_force_order(x, y, spread, steps):
    """Greedy forward selection by refitting: at each step add the candidate whose least-squares fit
    (bias + chosen centres + candidate) leaves the smallest training SSE."""
    phi = np.exp(-((x[:, None, :] - x[None, :, :]) ** 2).sum(-1) / (2 * spread ** 2))
    chosen, sse = [], []
    for _ in range(steps):
        best = None
        for j in range(len(x)):
            if j in chosen:
                continue
            a = np.column_stack([phi[:, chosen + [j]], np.ones(len(x))])
            coef, *_ = np.linalg.lstsq(a, y, rcond=None)
            e = float(((a @ coef - y) ** 2).sum())
            if best is None or e < best[1]:
                best = (j, e)
        chosen.append(best[0])
        sse.append(best[1])
    return chosen, np.array(sse)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_ols_picks_the_centre_with_the_largest_error_reduction(seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-50, 50, (14, 2))
    # two outputs of different size and a point-to-point scatter: the selection rule, not the fit, decides
    y = np.column_stack([np.sin(x[:, 0] / 17) + 0.3 * np.cos(x[:, 1] / 9), 0.2 * np.tanh(x[:, 1] / 20)])
    y = y + rng.normal(0, 0.05, y.shape)
    order, mse, _ = rbf.ols_select(x, y, 25.0, 6)
    want, sse = _brute_force_order(x, y, 25.0, 6)
    assert order == want
    assert np.allclose(mse[1:], sse / y.size, rtol=1e-8, atol=1e-14)   # MSE over points and outputs
    assert mse[0] == pytest.approx(((y - y.mean(axis=0)) ** 2).mean(), rel=1e-12)
