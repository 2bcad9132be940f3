"""The paper's real-coded GA for the PM machine's static calibration (paper 000 §3.1, eq. 9).

Settings as in the paper: population 60, 100 generations, Pc = 0.9, Pm = 0.05,
tournament selection with elitism, a fixed seed. A chromosome holds the nine
direction cosines of the stage's axis triad (projected to a right-handed
orthonormal triad Q before every fitness evaluation: x normalised, y
orthogonalised and normalised, z = x × y) and the three non-orthogonality
angles γ, so the calibrated axes are A = Q·N(γ). Everything that follows from
the triad in closed form is solved for each individual (variable projection):
the scale errors, straightness and offset by linear least squares on the axis
trajectories, R and T of eq. 4 by least squares (Kabsch, as the paper estimates
them), and the plane a, b, c by least squares (eq. 6). Every individual's
fitness is the full F of eq. 9, and the whole population is evaluated in one
vectorised call. (``GAOptions(pose_genes=True)`` puts the PM -> OM rotation
vector in the chromosome instead of solving it; it converges worse in 100
generations: tested during development, not the default.)

Operators (the paper names only the selection): simulated binary crossover
(η = 15) applied to a pair with probability Pc, Michalewicz non-uniform
mutation applied to each gene with probability Pm, binary tournaments, the 2
best individuals copied unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from markcal.stages.pm_fit import (SessionData, _k_matrix_batch, _tip_pm_batch, coarse_start, residual_parts_m,
                                   terms_from_parts, theta_from_model)
from markcal.stages.pm_model import STRAIGHTNESS_REF_UM, K_PAIRS, PMModel, gram_schmidt, rotvec_to_matrix, shear_matrix

__all__ = ["GAOptions", "GAResult", "run_ga", "decode"]


@dataclass(frozen=True)
class GAOptions:
    """GA settings (paper defaults) and search half-widths (rad) around the datum start."""
    population: int = 60
    generations: int = 100
    pc: float = 0.9
    pm: float = 0.05
    tournament: int = 2
    elite: int = 2
    eta_c: float = 15.0
    mutation_b: float = 2.0
    seed: int = 0
    cos_half: float = 2e-3
    gamma_half: float = 2e-3
    rot_half: float = 2e-3
    pose_genes: bool = False


@dataclass(frozen=True)
class GAResult:
    """Best θ (27 values, see ``pm_fit``), its E terms, per-generation best and mean F, evaluations."""
    theta: np.ndarray
    terms: dict
    best_f: np.ndarray
    mean_f: np.ndarray
    n_evals: int


def _linear_solve(a, d: SessionData, r):
    """Closed-form ε, K, o (axes), T (pose) and plane for P triads ``a`` and rotations ``r``."""
    p_n = a.shape[0]
    c, u2 = d.c_axes, (d.c_axes / STRAIGHTNESS_REF_UM) ** 2
    n = len(c)
    cols = np.zeros((p_n, n, 3, 12))
    cols[..., 0:3] = (a[:, None, :, :] * (c[None, :, None, :] / STRAIGHTNESS_REF_UM))  # ε·L
    for idx, (i, j) in enumerate(K_PAIRS):
        cols[:, :, i, 3 + idx] = u2[None, :, j]
    for i in range(3):
        cols[:, :, i, 9 + i] = 1.0
    dm = cols.reshape(p_n, 3 * n, 12)
    y = (d.p_axes[None] - np.matmul(c, a.transpose(0, 2, 1))).reshape(p_n, 3 * n)
    sol = np.linalg.solve(np.matmul(dm.transpose(0, 2, 1), dm), np.matmul(dm.transpose(0, 2, 1), y[..., None]))[..., 0]
    eps, k, o = sol[:, 0:3] / STRAIGHTNESS_REF_UM, sol[:, 3:9], sol[:, 9:12]
    m_mat = a * (1.0 + eps[:, None, :])
    km = _k_matrix_batch(k)
    pp = _tip_pm_batch(m_mat, km, o, d.c_pose)
    if r is None:  # eq. 4 by least squares (batched Kabsch), as the paper estimates R and T
        h = np.matmul((pp - pp.mean(1, keepdims=True)).transpose(0, 2, 1), d.x_om - d.x_om.mean(0))
        u, _, vt = np.linalg.svd(h)
        sgn = np.sign(np.linalg.det(u @ vt))
        dd = np.ones((p_n, 3))
        dd[:, 2] = sgn
        r = np.matmul(vt.transpose(0, 2, 1) * dd[:, None, :], u.transpose(0, 2, 1))
    rp = np.matmul(pp, r.transpose(0, 2, 1))
    t = np.mean(d.x_om[None] - rp, axis=1)
    xq = np.matmul(_tip_pm_batch(m_mat, km, o, d.c_probe), r.transpose(0, 2, 1)) + t[:, None, :]
    g = np.stack([xq[..., 0], xq[..., 1], np.ones(xq.shape[:2])], -1)
    plane = np.linalg.solve(np.matmul(g.transpose(0, 2, 1), g), np.matmul(g.transpose(0, 2, 1), xq[..., 2:3]))[..., 0]
    return eps, k, o, r, t, plane


def decode(genes: np.ndarray, center: np.ndarray, half: np.ndarray, d: SessionData):
    """Normalised genes (P, 15) in [-1, 1] -> model arrays (A, ε, K, o, R, T, plane)."""
    x = center + half * genes
    a = gram_schmidt(x[:, 0:9]) @ shear_matrix(x[:, 9:12])
    r = rotvec_to_matrix(x[:, 12:15]) if x.shape[1] > 12 else None
    eps, k, o, r, t, plane = _linear_solve(a, d, r)
    return a, eps, k, o, r, t, plane


def _fitness(genes, center, half, d):
    parts = decode(genes, center, half, d)
    return terms_from_parts(*residual_parts_m(*parts, d), d)


def run_ga(d: SessionData, opts: GAOptions = GAOptions()) -> GAResult:
    """Run the GA on a session; deterministic for a given ``opts.seed``."""
    rng = np.random.default_rng(opts.seed)
    th0 = coarse_start(d)
    center = np.concatenate([np.eye(3).ravel(), np.zeros(3)])
    half = np.concatenate([np.full(9, opts.cos_half), np.full(3, opts.gamma_half)])
    if opts.pose_genes:
        center = np.concatenate([center, th0[18:21]])
        half = np.concatenate([half, np.full(3, opts.rot_half)])
    n_pop, n_gene = opts.population, len(center)
    pop = rng.uniform(-1, 1, (n_pop, n_gene))
    pop[0] = 0.0  # the datum start is one of the initial individuals
    f = _fitness(pop, center, half, d)["F"]
    best_f, mean_f = [float(f.min())], [float(f.mean())]
    n_eval = n_pop
    for gen in range(1, opts.generations):
        order = np.argsort(f)
        elite = pop[order[:opts.elite]]
        n_child = n_pop - opts.elite
        cand = rng.integers(0, n_pop, (n_child + (n_child % 2), opts.tournament))
        parents = pop[cand[np.arange(len(cand)), np.argmin(f[cand], axis=1)]]
        p1, p2 = parents[0::2], parents[1::2]
        # simulated binary crossover
        u = rng.random(p1.shape)
        beta = np.where(u <= 0.5, (2 * u) ** (1 / (opts.eta_c + 1)), (1 / (2 * (1 - u))) ** (1 / (opts.eta_c + 1)))
        do = rng.random(len(p1))[:, None] < opts.pc
        c1 = np.where(do, 0.5 * ((1 + beta) * p1 + (1 - beta) * p2), p1)
        c2 = np.where(do, 0.5 * ((1 - beta) * p1 + (1 + beta) * p2), p2)
        kids = np.vstack([c1, c2])[:n_child]
        # non-uniform mutation
        mut = rng.random(kids.shape) < opts.pm
        shrink = 1 - rng.random(kids.shape) ** ((1 - gen / opts.generations) ** opts.mutation_b)
        up = rng.random(kids.shape) < 0.5
        step = np.where(up, (1 - kids) * shrink, -(kids + 1) * shrink)
        kids = np.clip(np.where(mut, kids + step, kids), -1, 1)
        pop = np.vstack([elite, kids])
        f = np.concatenate([f[order[:opts.elite]], _fitness(kids, center, half, d)["F"]])
        n_eval += len(kids)
        best_f.append(float(f.min()))
        mean_f.append(float(f.mean()))
    best = pop[[int(np.argmin(f))]]
    a, eps, k, o, r, t, plane = decode(best, center, half, d)
    model = PMModel(a[0], eps[0], k[0], o[0], r[0], t[0], plane[0])
    th = theta_from_model(model)
    terms = {key: float(v[0]) for key, v in terms_from_parts(*residual_parts_m(a, eps, k, o, r, t, plane, d), d).items()}
    return GAResult(th, terms, np.array(best_f), np.array(mean_f), n_eval)
