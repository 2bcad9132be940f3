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

from .errors import MarkcalError


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
    y = np.asarray(y_mm, float).reshape(len(x), -1)
    n, k = y.shape
    P = _design(x, x, spread_mm)
    col_mean = P.mean(axis=0)
    P -= col_mean                      # orthogonal to the bias column
    E = y - y.mean(axis=0)
    norms = (P * P).sum(axis=0)
    norms0 = norms.copy()
    avail = np.ones(n, bool)
    order = []
    mse = [float((E * E).mean())]
    pred = None
    if x_val_mm is not None:
        Pv = _design(np.asarray(x_val_mm, float), x, spread_mm)
        Pv -= col_mean
        pred = [np.broadcast_to(y.mean(axis=0), (len(Pv), k)).copy()]
    for _ in range(min(max_neurons, n)):
        if mse[-1] <= mse_goal:
            break
        # a candidate whose column is, to 1e-3 of its length, a combination of the chosen ones is
        # numerically dependent: choosing it lets rounding decide (a 1e-14 mm change of the input
        # moved the cross-validated choice from 47.5 mm / 1e-6 to 68.6 mm / 1e-5 at 1e-10 here)
        good = avail & (norms > NUMERICAL_RANK_FLOOR * norms0)
        if not good.any():
            break
        num = P.T @ E                       # (n, k)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            err = np.where(good, (num * num).sum(axis=1) / np.where(good, norms, 1.0), -1.0)
        j = int(np.argmax(err))
        pj = P[:, j].copy()
        nj = norms[j]
        g = num[j] / nj
        E = E - np.outer(pj, g)
        coef = (pj @ P) / nj
        if pred is not None:
            pvj = Pv[:, j].copy()
            pred.append(pred[-1] + np.outer(pvj, g))
            Pv -= np.outer(pvj, coef)
        P -= np.outer(pj, coef)
        norms = np.maximum(norms - coef * coef * nj, 0.0)
        avail[j] = False
        order.append(j)
        mse.append(float((E * E).mean()))
    return order, np.array(mse), (None if pred is None else np.array(pred))


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
    a = np.column_stack([_design(x, centres, spread), np.ones(len(x))])
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
    for i, s in enumerate(spreads):
        for f in range(folds):
            tr, va = fold_of != f, fold_of == f
            _, mse, pred = ols_select(x[tr], y[tr], s, cap, goals.min(), x[va])
            for g, goal in enumerate(goals):
                m = int(np.argmax(mse <= goal)) if np.any(mse <= goal) else len(mse) - 1
                e = pred[m] - y[va]
                sq[i, g, f] = np.sqrt(np.mean((e * e).sum(axis=1)))
    mean = sq.mean(axis=2)
    i, g = np.unravel_index(int(np.argmin(mean)), mean.shape)
    return Selection(spread_mm=float(spreads[i]), mse_goal_mm2=float(goals[g]),
                     cv_rmse_mm=float(mean[i, g]), cv_rmse_std_mm=float(sq[i, g].std(ddof=1)),
                     table=mean, spreads_mm=spreads, goals_mm2=goals)
