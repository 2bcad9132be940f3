"""The drift flow: online drift compensation from a reference-array record (paper 000 eqs. 10-11).

Reads ``drift.csv`` (``t_min,dx_um,dy_um,dz_um``), runs every compensation
method, and returns the chosen one's compensation plus the reduction rate η per
axis for all methods: at the samples (the error at t_{k+1} is m_{k+1} − C_k),
and, when the true drift at fine resolution is given (``drift_true.csv`` from the
renderer), between the samples too.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from markcal.pipeline.tables import check_increasing, read_table
from markcal.stages.drift import METHODS, compensate, in_force, reduction_rate, sample_reduction_rate
from markcal.stages.errors import MarkcalError

__all__ = ["DriftResult", "read_drift", "run_drift", "DEFAULT_METHOD"]

DEFAULT_METHOD = "kalman"
#: the largest noise of one drift sample accepted (µm): beyond it the filters' variances overflow
NOISE_MAX_UM = 1e4


@dataclass(frozen=True)
class DriftResult:
    """Drift flow output; ``comp_um`` maps method -> (K, 3) compensation; ``eta`` method -> dict of η arrays."""
    source: str
    method: str
    t_min: np.ndarray
    meas_um: np.ndarray
    comp_um: dict
    eta: dict
    true_t_min: np.ndarray | None
    true_um: np.ndarray | None
    summary: dict


def read_drift(path) -> tuple:
    """drift.csv -> (t_min (K,), meas_um (K, 3)); times must increase, ≥ 3 samples."""
    t = read_table(path, ("t_min", "dx_um", "dy_um", "dz_um"))
    tm = t["t_min"]
    check_increasing(tm, "t_min", path)
    if len(tm) < 3:
        raise MarkcalError(f"{len(tm)} samples: need at least 3", path)
    return tm, np.column_stack([t["dx_um"], t["dy_um"], t["dz_um"]])


def run_drift(path, method: str = DEFAULT_METHOD, truth_path=None, noise_um: float = 0.005,
              alpha: float = 0.8) -> DriftResult:
    """Compensate a drift record with every method; ``method`` is the chosen (written) one."""
    if method not in METHODS:
        raise MarkcalError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    if not (0 < alpha < 1):
        raise MarkcalError(f"--alpha must be in (0, 1) (got {alpha})")
    if not 0 < noise_um <= NOISE_MAX_UM:
        raise MarkcalError(f"--noise-um must be positive and at most {NOISE_MAX_UM:g} µm (got {noise_um})")
    t, m = read_drift(path)
    tt = tu = None
    if truth_path is not None:
        tt, tu = read_drift(truth_path)
        sel = (tt >= t[0]) & (tt <= t[-1])
        tt, tu = tt[sel], tu[sel]
        if len(tt) < 2:
            raise MarkcalError("the true drift does not cover the record's time span", truth_path)
    comp, eta = {}, {}
    for name in METHODS:
        c = compensate(t, m, name, alpha=alpha, noise_um=noise_um)
        comp[name] = c
        pre, post, e = sample_reduction_rate(m, c)
        eta[name] = {"pre_samples_um": pre, "post_samples_um": post, "eta_samples_pct": e}
        if tt is not None:
            pre, post, e = reduction_rate(tu, in_force(t, c, tt))
            eta[name].update({"pre_true_um": pre, "post_true_um": post, "eta_true_pct": e})
    s = {"method": method, "n_samples": len(t), "t_start_min": float(t[0]), "t_end_min": float(t[-1]),
         "alpha": alpha, "noise_um": noise_um, "truth": tt is not None}
    for ax, a in enumerate("xyz"):
        s[f"max_drift_{a}_um"] = float(np.max(np.abs(m[:, ax])))
    for name in METHODS:
        key = name.replace("-", "_")
        for ax, a in enumerate("xyz"):
            s[f"eta_samples_{a}_pct_{key}"] = float(eta[name]["eta_samples_pct"][ax])
            if tt is not None:
                s[f"eta_true_{a}_pct_{key}"] = float(eta[name]["eta_true_pct"][ax])
    for ax, a in enumerate("xyz"):
        src = "true" if tt is not None else "samples"
        s[f"pre_{a}_um"] = float(eta[method][f"pre_{src}_um"][ax])
        s[f"post_{a}_um"] = float(eta[method][f"post_{src}_um"][ax])
        s[f"eta_{a}_pct"] = float(eta[method][f"eta_{src}_pct"][ax])
    return DriftResult(os.path.abspath(path), method, t, m, comp, eta, tt, tu, s)
