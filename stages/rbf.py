"""Gaussian RBF network trained by orthogonal least squares (Chen, Cowan & Grant 1991).

Forward selection of centres from the training inputs, a bias term, and the
two hyper-parameters of MATLAB's ``newrb``: the spread and the MSE goal. The
kernel is paper 004 eq. (7), phi = exp(-|u - c|^2 / (2 sigma^2)), sigma =
spread; the output is eq. (8), g = sum_j w_j phi_j + b. Lengths in mm; the MSE
is the mean over points and outputs of the squared error (mm^2), as newrb's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .errors import MarkcalError
from .threads import map_on_threads


@dataclass(frozen=True)
class RBFModel:
    """A trained network. ``centres_mm`` (m, 2), ``weights_mm`` (m, k), ``bias_mm`` (k,)."""

    centres_mm: np.ndarray
    weights_mm: np.ndarray
    bias_mm: np.ndarray
    spread_mm: float

    @property
    def n_neurons(self) -> int:
        return len(self.centres_mm)

    def __call__(self, xy_mm: np.ndarray) -> np.ndarray:
        """Evaluate at positions (n, 2) mm; returns (n, k) mm."""
        return evaluate(self, xy_mm)

    def to_dict(self) -> dict:
        return {
            "format": "markcal-rbf-1",
            "kernel": "gaussian: phi_j = exp(-((x - cx_j)^2 + (y - cy_j)^2) / (2 * spread_mm^2))",
            "output": "[dx, dy] = sum_j phi_j * [wx_j, wy_j] + [bx, by]",
            "units": "mm",
            "spread_mm": float(self.spread_mm),
            "n_neurons": self.n_neurons,
            "centres_mm": np.asarray(self.centres_mm).tolist(),
            "weights_mm": np.asarray(self.weights_mm).tolist(),
            "bias_mm": np.asarray(self.bias_mm).tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "RBFModel":
        try:
            c = np.asarray(d["centres_mm"], float).reshape(-1, 2)
            w = np.asarray(d["weights_mm"], float).reshape(len(c), -1)
            b = np.asarray(d["bias_mm"], float).ravel()
            s = float(d["spread_mm"])
        except (KeyError, TypeError, ValueError) as exc:
            raise MarkcalError(f"not a markcal RBF model: {exc}") from None
        if len(b) != w.shape[1] or not 1e-6 <= s <= 1e6:
            raise MarkcalError(f"not a markcal RBF model: inconsistent sizes or spread (spread_mm = {s:g}; "
                               "1e-6 to 1e6 mm)")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
            raise MarkcalError("not a markcal RBF model: non-finite centres, weights or bias")
        return cls(c, w, b, s)


def evaluate(model: RBFModel, xy_mm: np.ndarray, block: int = 65536) -> np.ndarray:
    """Network output at positions (n, 2) mm, in blocks to bound memory."""
    xy = np.atleast_2d(np.asarray(xy_mm, float))
    out = np.empty((len(xy), model.weights_mm.shape[1]))
    k = -0.5 / model.spread_mm ** 2
    for s in range(0, len(xy), block):
        d2 = _sqdist(xy[s:s + block], model.centres_mm)
        out[s:s + block] = np.exp(k * d2) @ model.weights_mm + model.bias_mm
    return out


def _sqdist(a, b):
    return np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T, 0.0)


def _design(x, centres, spread):
    return np.exp(-0.5 * _sqdist(x, centres) / spread ** 2)


#: smallest deflated/original squared norm of a candidate column the OLS selection may still choose
NUMERICAL_RANK_FLOOR = 1e-6


def ols_select(x_mm, y_mm, spread_mm, max_neurons, mse_goal=0.0, x_val_mm=None):
    """Forward OLS selection; the training MSE (and validation predictions) after each step.

    Returns
    -------
    order : list of int
        Indices of the training points chosen as centres, in selection order.
    mse : ndarray, shape (len(order) + 1,)
        Training MSE with the bias only, then after each added centre.
    val_pred : ndarray, shape (len(order) + 1, n_val, k) or None
        Predictions at ``x_val_mm`` for each prefix.
    """
    x = np.asarray(x_mm, float)
    xv = None if x_val_mm is None else np.asarray(x_val_mm, float)
    return _ols_on_design(_design(x, x, spread_mm), y_mm, max_neurons, mse_goal,
                          None if xv is None else _design(xv, x, spread_mm))


def _ols_on_design(P, y_mm, max_neurons, mse_goal=0.0, Pv=None):
    """:func:`ols_select` on a design matrix ``P`` (n, n) of the training points (and ``Pv`` (n_val, n))."""
    y = np.asarray(y_mm, float).reshape(len(P), -1)
    n, k = y.shape
    col_mean = P.mean(axis=0)
    PT = np.ascontiguousarray((P - col_mean).T)          # row i: candidate column i, orthogonal to the bias
    E = y - y.mean(axis=0)
    val = Pv is not None
    PvT = np.ascontiguousarray((Pv - col_mean).T) if val else np.zeros((n, 0))
    steps = min(int(max_neurons), n)
    order, mse, pred = _ols_kernel(PT, np.ascontiguousarray(E.T), PvT, y.mean(axis=0), steps, float(mse_goal),
                                   NUMERICAL_RANK_FLOOR)
    m = len(order)
    return order.tolist(), mse[:m + 1], (pred[:m + 1].transpose(0, 2, 1).copy() if val else None)


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _ols_kernel(PT, ET, PvT, y_mean, steps, mse_goal, floor):  # pragma: no cover - compiled
    """Modified Gram-Schmidt forward selection, in place on the candidate rows ``PT`` (n, n).

    Each step takes the candidate of largest error reduction among those whose
    deflated squared norm is above ``floor`` of the original (a candidate that
    is, to 1e-3 of its length, a combination of the chosen ones is numerically
    dependent: choosing it lets rounding decide; a 1e-14 mm change of the input
    moved the cross-validated choice from 47.5 mm / 1e-6 to 68.6 mm / 1e-5 at
    1e-10), then deflates every remaining candidate (and its validation row in
    ``PvT``) by the chosen one. ``ET`` (k, n) is the centred target, transposed.
    """
    n = PT.shape[0]
    k = ET.shape[0]
    nv = PvT.shape[1]
    norms = np.empty(n)
    num = np.zeros((n, k))
    for i in range(n):
        s = 0.0
        for r in range(n):
            s += PT[i, r] * PT[i, r]
        norms[i] = s
        for c in range(k):
            t = 0.0
            for r in range(n):
                t += PT[i, r] * ET[c, r]
            num[i, c] = t
    norms0 = norms.copy()
    avail = np.ones(n, np.bool_)
    order = np.empty(steps, np.int64)
    mse = np.empty(steps + 1)
    pred = np.empty((steps + 1, k, nv))
    for c in range(k):
        for q in range(nv):
            pred[0, c, q] = y_mean[c]
    tot = 0.0
    for c in range(k):
        for r in range(n):
            tot += ET[c, r] * ET[c, r]
    mse[0] = tot / (n * k)
    pj = np.empty(n)
    pvj = np.empty(nv)
    g = np.empty(k)
    m = 0
    while m < steps and mse[m] > mse_goal:
        j = -1
        best = -1.0
        for i in range(n):
            if avail[i] and norms[i] > floor * norms0[i]:
                e = 0.0
                for c in range(k):
                    e += num[i, c] * num[i, c]
                e /= norms[i]
                if e > best:
                    best = e
                    j = i
        if j < 0:
            break
        nj = norms[j]
        pj[:] = PT[j]
        pvj[:] = PvT[j]
        for c in range(k):
            g[c] = num[j, c] / nj
        tot = 0.0
        for c in range(k):
            for r in range(n):
                ET[c, r] -= pj[r] * g[c]
                tot += ET[c, r] * ET[c, r]
        for c in range(k):
            for q in range(nv):
                pred[m + 1, c, q] = pred[m, c, q] + pvj[q] * g[c]
        avail[j] = False
        for i in range(n):
            if not avail[i]:
                continue
            row = PT[i]
            s = 0.0
            for r in range(n):
                s += pj[r] * row[r]
            coef = s / nj
            if k == 2:                      # the scan flow's (dx, dy): deflate and project in one pass
                t0 = 0.0
                t1 = 0.0
                for r in range(n):
                    v = row[r] - pj[r] * coef
                    row[r] = v
                    t0 += v * ET[0, r]
                    t1 += v * ET[1, r]
                num[i, 0] = t0
                num[i, 1] = t1
            else:
                for r in range(n):
                    row[r] -= pj[r] * coef
                for c in range(k):
                    t = 0.0
                    for r in range(n):
                        t += row[r] * ET[c, r]
                    num[i, c] = t
            vrow = PvT[i]
            for q in range(nv):
                vrow[q] -= pvj[q] * coef
            norms[i] = max(norms[i] - coef * coef * nj, 0.0)
        order[m] = j
        m += 1
        mse[m] = tot / (n * k)
    return order[:m], mse, pred


def train(x_mm, y_mm, spread_mm: float, mse_goal: float, max_neurons: int | None = None) -> RBFModel:
    """Train a network: OLS forward selection until the MSE goal, then least-squares weights.

    Parameters
    ----------
    x_mm : ndarray, shape (n, 2)
        Inputs (positions, mm).
    y_mm : ndarray, shape (n, k)
        Targets (mm).
    """
    x = np.asarray(x_mm, float)
    y = np.asarray(y_mm, float).reshape(len(x), -1)
    order, _, _ = ols_select(x, y, spread_mm, max_neurons or len(x), mse_goal)
    return _weights(x, y, x[order], spread_mm)


def _weights(x, y, centres, spread):
    from threadpoolctl import threadpool_limits
    a = np.column_stack([_design(x, centres, spread), np.ones(len(x))])
    with threadpool_limits(1):          # a few hundred rows: threaded BLAS only spins (60 ms instead of 1)
        sol, *_ = np.linalg.lstsq(a, y, rcond=None)
    return RBFModel(centres_mm=centres.copy(), weights_mm=sol[:-1], bias_mm=sol[-1], spread_mm=float(spread))


@dataclass(frozen=True)
class Selection:
    """Result of the cross-validated grid search."""

    spread_mm: float
    mse_goal_mm2: float
    cv_rmse_mm: float
    cv_rmse_std_mm: float
    table: np.ndarray          # (n_spreads, n_goals) mean CV RMSE, mm
    spreads_mm: np.ndarray
    goals_mm2: np.ndarray


def select(x_mm, y_mm, spreads_mm, goals_mm2, folds: int = 5, seed: int = 0,
           max_neurons: int | None = None) -> Selection:
    """Choose spread and MSE goal by k-fold cross-validation over a grid.

    One OLS run per (spread, fold) serves every goal: a looser goal stops the
    same forward selection earlier. The CV RMSE is the RMS of the Euclidean
    prediction error on the held-out points (mm).
    """
    x = np.asarray(x_mm, float)
    y = np.asarray(y_mm, float).reshape(len(x), -1)
    n = len(x)
    if n < 2 * folds:
        raise MarkcalError(f"{n} points are too few for {folds}-fold cross-validation")
    spreads = np.asarray(spreads_mm, float)
    goals = np.asarray(goals_mm2, float)
    fold_of = np.random.default_rng(seed).permutation(n) % folds
    cap = max_neurons or n
    sq = np.zeros((len(spreads), len(goals), folds))
    parts = [(np.flatnonzero(fold_of != f), np.flatnonzero(fold_of == f)) for f in range(folds)]

    def one_spread(i):
        full = _design(x, x, spreads[i])        # one Gaussian design per spread, sliced per fold
        for f, (tr, va) in enumerate(parts):
            _, mse, pred = _ols_on_design(full[np.ix_(tr, tr)], y[tr], cap, goals.min(), full[np.ix_(va, tr)])
            for g, goal in enumerate(goals):
                m = int(np.argmax(mse <= goal)) if np.any(mse <= goal) else len(mse) - 1
                e = pred[m] - y[va]
                sq[i, g, f] = np.sqrt(np.mean((e * e).sum(axis=1)))

    map_on_threads(one_spread, range(len(spreads)))     # the compiled selection releases the GIL
    mean = sq.mean(axis=2)
    i, g = np.unravel_index(int(np.argmin(mean)), mean.shape)
    return Selection(spread_mm=float(spreads[i]), mse_goal_mm2=float(goals[g]),
                     cv_rmse_mm=float(mean[i, g]), cv_rmse_std_mm=float(sq[i, g].std(ddof=1)),
                     table=mean, spreads_mm=spreads, goals_mm2=goals)
