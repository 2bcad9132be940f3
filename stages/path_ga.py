"""The paper's genetic algorithm for the laser travelling path (paper 002, Wang, Yu & Zhang).

Path representation with signed genes: gene ``±(s + 1)`` marks stroke s, a
negative sign runs an open stroke from its last vertex to its first; a closed
contour is entered at its best vertex. Initial population random; fitness
``1 / tour cost`` (paper eq. 3), evaluated for the whole population at once;
roulette-wheel selection (eq. 4); order crossover (OX) with probability CP =
0.8 giving two children per couple; simple inversion mutation with
probability MP = 0.01 per child (the run between two random positions is
reversed, which also turns its open strokes round); the best individual is
carried over (elitism 1). Every random draw comes from one seeded generator.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit

from .path_job import POLYLINE, Job, Timing, Tour
from .path_tour import population_arrays, population_cost, population_points

__all__ = ["GAOptions", "GAResult", "run_ga", "order_crossover", "genes_to_tour"]


@dataclass(frozen=True)
class GAOptions:
    """GA settings; CP and MP as in the paper (section "Setting the parameters")."""

    population: int = 100
    generations: int = 3000
    crossover_p: float = 0.8
    mutation_p: float = 0.01
    elitism: int = 10
    mutation_per: str = "gene"
    seed: int = 0


@dataclass(frozen=True, eq=False)
class GAResult:
    """Best tour found, its cost, and the convergence curve (best cost after each generation)."""

    tour: Tour
    cost: float
    curve: np.ndarray           # (generations + 1,) best cost, mm or s; [0] = initial population
    mean_curve: np.ndarray      # (generations + 1,) population mean cost
    evaluations: int
    runtime_s: float


@njit(cache=True)
def _ox(p1, p2, c1, c2, child, seen):
    """Order crossover OX1: p1[c1..c2] kept in place, the rest in p2's order from c2 + 1."""
    n = p1.shape[0]
    seen[:] = False
    for k in range(c1, c2 + 1):
        child[k] = p1[k]
        seen[abs(p1[k]) - 1] = True
    w = (c2 + 1) % n
    for t in range(n):
        g = p2[(c2 + 1 + t) % n]
        if not seen[abs(g) - 1]:
            child[w] = g
            seen[abs(g) - 1] = True
            w = (w + 1) % n


@njit(cache=True)
def _breed(parents, cross, cuts, mutate, mcuts, out):
    """Children of consecutive parent couples: OX when ``cross``, then inversion when ``mutate``."""
    m, n = parents.shape
    seen = np.zeros(n, np.bool_)
    for k in range(m // 2):
        a = parents[2 * k]
        b = parents[2 * k + 1]
        if cross[k]:
            _ox(a, b, cuts[k, 0], cuts[k, 1], out[2 * k], seen)
            _ox(b, a, cuts[k, 0], cuts[k, 1], out[2 * k + 1], seen)
        else:
            out[2 * k] = a
            out[2 * k + 1] = b
    if m % 2:
        out[m - 1] = parents[m - 1]
    for r in range(m):
        if mutate[r]:
            i = mcuts[r, 0]
            j = mcuts[r, 1]
            while i < j:
                x = out[r, i]
                out[r, i] = -out[r, j]
                out[r, j] = -x
                i += 1
                j -= 1
            if i == j:
                out[r, i] = -out[r, i]


def order_crossover(p1: np.ndarray, p2: np.ndarray, c1: int, c2: int) -> np.ndarray:
    """One OX child of signed-gene parents (cut positions c1 <= c2, inclusive)."""
    child = np.empty_like(p1)
    _ox(np.asarray(p1, np.int64), np.asarray(p2, np.int64), int(c1), int(c2), child,
        np.zeros(len(p1), np.bool_))
    return child


def genes_to_tour(genes: np.ndarray, job: Job, arrays: dict, timing: Timing) -> Tour:
    """The tour a chromosome stands for (contour entries as the fitness chose them)."""
    g = np.asarray(genes, np.int64)[None, :]
    _, _, entry = population_points(g, arrays, timing)
    order = np.abs(g[0]) - 1
    reverse = (g[0] < 0) & (job.kinds[order] == POLYLINE)
    return Tour(order, reverse, entry[0])


def run_ga(job: Job, timing: Timing, options: GAOptions | None = None, progress=None) -> GAResult:
    """Run the paper's GA on a job.

    Parameters
    ----------
    job : Job
        Strokes (mm).
    timing : Timing
        Jump cost: distance (mm) or time (s).
    options : GAOptions, optional
    progress : callable, optional
        Called as ``progress(generation, best_cost)`` every 100 generations.

    Returns
    -------
    GAResult
    """
    opt = options or GAOptions()
    t0 = time.perf_counter()
    rng = np.random.default_rng([opt.seed, 2])
    n, m = job.n, max(2, int(opt.population))
    arrays = population_arrays(job)
    signable = job.kinds == POLYLINE
    pop = np.empty((m, n), np.int64)
    for r in range(m):
        perm = rng.permutation(n) + 1
        sign = np.where(signable[perm - 1] & (rng.random(n) < 0.5), -1, 1)
        pop[r] = perm * sign
    cost = population_cost(pop, arrays, timing)
    evals = m
    curve = [float(cost.min())]
    mean_curve = [float(cost.mean())]
    children = np.empty_like(pop)
    for gen in range(opt.generations):
        fit = 1.0 / np.maximum(cost, 1e-300)
        cum = np.cumsum(fit / fit.sum())
        sel = np.minimum(np.searchsorted(cum, rng.random(m), side="right"), m - 1)
        parents = pop[sel]
        cross = rng.random(m // 2) < opt.crossover_p
        cuts = np.sort(rng.integers(0, n, size=(m // 2, 2)), axis=1)
        if opt.mutation_per == "gene":
            mutate = rng.random(m) < 1.0 - (1.0 - opt.mutation_p) ** n
        else:
            mutate = rng.random(m) < opt.mutation_p
        mcuts = np.sort(rng.integers(0, n, size=(m, 2)), axis=1)
        _breed(parents, cross, cuts, mutate, mcuts, children)
        ccost = population_cost(children, arrays, timing)
        evals += m
        if opt.elitism > 0:
            keep = np.argsort(cost, kind="stable")[:opt.elitism]
            worst = np.argsort(-ccost, kind="stable")[:opt.elitism]
            children[worst] = pop[keep]
            ccost[worst] = cost[keep]
        pop, children = children, pop
        cost = ccost
        curve.append(float(cost.min()))
        mean_curve.append(float(cost.mean()))
        if progress is not None and (gen + 1) % 100 == 0:
            progress(gen + 1, curve[-1])
    best = int(np.argmin(cost))
    tour = genes_to_tour(pop[best], job, arrays, timing)
    return GAResult(tour, float(cost[best]), np.array(curve), np.array(mean_curve), evals,
                    time.perf_counter() - t0)
