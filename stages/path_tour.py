"""Tour construction and local search for marking jobs (numba kernels).

Model. Every stroke s has two *endpoint cities*, ``2s`` (its first vertex) and
``2s + 1`` (its last vertex; a contour's entry vertex for both, a point's
vertex for both). A tour is a cyclic array of the 2n cities in which the two
cities of a stroke always sit side by side: the edge between them is the
stroke itself (marked, fixed), every other edge is a *jump* (laser off).
Reversing a run of whole strokes reverses their direction too, so plain
2-opt on this array chooses the direction of open strokes for free. Moves
only ever cut jump edges.

Local search (kernels in :mod:`markcal.stages.path_tour_moves`): candidate
neighbours by alpha-nearness on a minimum spanning tree (as in LKH: they join
clusters, which nearest neighbours do not), 2-opt, Or-opt (runs of 1-3
strokes, either way round) and a variable-depth Lin-Kernighan step, with
don't-look bits (a queue of active cities); then an iterated local search:
double-bridge kicks (two neighbouring runs of strokes swapped, as in Chained
Lin-Kernighan, cut at long jumps) each repaired by the same local search and
kept unless the tour got longer.
Closed contours are re-entered at their best vertex between rounds. The
number of kicks is fixed by the options, never by a clock, so a seed gives
the same tour on any machine.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations, product

import numpy as np

from .limits import check_values
from .path_job import CONTOUR, POLYLINE, Job, Timing, Tour, endpoints, tour_cost, tour_points
from .path_tour_cand import alpha_candidates, nearest_neighbour_picks
from .path_tour_moves import lk_work, optimise

__all__ = ["LocalSearchOptions", "nearest_neighbour_tour", "raster_tour", "best_entries", "local_search",
           "population_arrays", "population_points", "population_cost"]

@dataclass(frozen=True)
class LocalSearchOptions:
    """Settings of :func:`local_search`.

    ``neighbours`` candidate cities per city (each stroke has two: a point job's 10 are its 5
    alpha-nearest points), alpha-nearness up to ``alpha_max_cities`` cities (O(N^2) time), nearest
    cities above. ``lk_depth``: the longest Lin-Kernighan chain (1: 2-opt and Or-opt only).
    ``kicks_per_stroke`` x n kicks (at least ``min_kicks``, at most ``max_kicks``) of the iterated
    local search; each swaps two neighbouring runs of strokes cut at jumps that are each the
    longest of ``kick_tournament`` random jumps (0: runs of 1..``max_kick_strokes`` strokes from a
    random cut, capped at half the tour) and shuffles ``shuffle_strokes`` neighbouring strokes
    elsewhere (order and directions; 0: no shuffle). ``lk_breadth``: alternatives tried at the
    first two levels of a chain.
    """

    neighbours: int = 10
    alpha_max_cities: int = 16_000
    lk_depth: int = 10
    lk_breadth: tuple = (5, 3)
    kicks_per_stroke: float = 5.0
    min_kicks: int = 2_000
    max_kicks: int = 10_000
    max_kick_strokes: int = 1_000_000
    shuffle_strokes: int = 8
    kick_tournament: int = 4
    entry_rounds: int = 3
    seed: int = 0


# ----------------------------------------------------------------------------- conversions

def _cities(job: Job, tour: Tour) -> tuple:
    """City coordinates (2n, 2) and the city tour for a stroke tour (contours at their entries)."""
    a, b = endpoints(job)
    xy = np.empty((2 * job.n, 2))
    xy[0::2] = a
    xy[1::2] = b
    kinds = job.kinds
    for s, e in zip(tour.order, tour.entry):
        if kinds[s] == CONTOUR:
            xy[2 * s] = xy[2 * s + 1] = job.strokes[s].xy_mm[e]
    c = np.empty(2 * job.n, np.int64)
    c[0::2] = 2 * tour.order + tour.reverse
    c[1::2] = 2 * tour.order + 1 - tour.reverse
    return xy, c


def _from_cities(job: Job, cities: np.ndarray, entry_of: dict) -> Tour:
    off = 0 if cities[1] == (cities[0] ^ 1) else 1
    c = np.roll(cities, -off)
    first = c[0::2]
    order = first // 2
    reverse = (first % 2 == 1) & (job.kinds[order] == POLYLINE)
    entry = np.array([entry_of.get(int(s), 0) for s in order], np.int64)
    return Tour(order.astype(np.int64), reverse, entry)


def _neighbours(xy: np.ndarray, k: int) -> np.ndarray:
    """k nearest cities of each city, nearest first, without itself and its partner (large jobs)."""
    from scipy.spatial import cKDTree        # imported here: ~0.4 s of every command's start otherwise
    n = len(xy)
    kk = min(k + 2, n)
    _, idx = cKDTree(xy).query(xy, k=kk)
    idx = np.asarray(idx, np.int64).reshape(n, kk)
    own = np.arange(n)[:, None]
    keep = (idx != own) & (idx != (own ^ 1))
    out = np.empty((n, min(k, n - 2)), np.int64)
    for i in range(n):
        row = idx[i][keep[i]]
        out[i] = row[:out.shape[1]]
    return out


# ----------------------------------------------------------------------------- public

def nearest_neighbour_tour(job: Job, start: int = 0) -> Tour:
    """Nearest-neighbour order from the first stroke as given.

    From where the laser is, mark the unmarked stroke with the nearest entry:
    either end of an open stroke (which fixes its direction), any vertex of a
    contour, a point.
    """
    a, b = endpoints(job)
    kinds = job.kinds
    cin, cout, own, vtx, rev = [], [], [], [], []
    for s, st in enumerate(job.strokes):
        if kinds[s] == CONTOUR:
            p = st.xy_mm
            cin.append(p)
            cout.append(p)
            own += [s] * len(p)
            vtx += list(range(len(p)))
            rev += [False] * len(p)
        else:
            cin.append(a[s:s + 1])
            cout.append(b[s:s + 1])
            own.append(s)
            vtx.append(0)
            rev.append(False)
            if kinds[s] == POLYLINE:
                cin.append(b[s:s + 1])
                cout.append(a[s:s + 1])
                own.append(s)
                vtx.append(0)
                rev.append(True)
    cin = np.ascontiguousarray(np.vstack(cin), float)
    cout = np.ascontiguousarray(np.vstack(cout), float)
    own = np.array(own, np.int64)
    first = int(np.flatnonzero(own == start)[0])
    picks = nearest_neighbour_picks(cin, cout, own, job.n, first)
    vtx = np.array(vtx, np.int64)
    rev = np.array(rev, bool)
    return Tour(own[picks], rev[picks], vtx[picks])


def raster_tour(job: Job) -> Tour:
    """Raster (serpentine) order of the strokes' bounding-box centres, input directions kept.

    Rows: the centres' y values split where the gap between neighbouring
    values exceeds half the largest gap (the rows of a grid, the lines of a
    text); when that gives one row or more than 2 sqrt(n) rows,
    ``round(sqrt(n / 3))`` equal strips instead. Top row first, x alternating
    left-right and right-left; contours entered at their first vertex.
    """
    n = job.n
    c = np.array([(s.xy_mm.min(axis=0) + s.xy_mm.max(axis=0)) / 2 for s in job.strokes]).reshape(-1, 2)
    y = c[:, 1]
    ys = np.sort(y)
    gaps = np.diff(ys)
    row = np.zeros(n, int)
    if n > 1 and gaps.max() > 0:
        cuts = ys[1:][gaps > 0.5 * gaps.max()]
        row = np.searchsorted(cuts, y, side="right")
        if not 2 <= len(cuts) + 1 <= 2 * np.sqrt(n):
            k = max(1, int(round(np.sqrt(n / 3.0))))
            span = max(float(np.ptp(y)), 1e-12)
            row = np.minimum(((y - y.min()) / span * k).astype(int), k - 1)
    row = row.max() - row                      # top row first
    xkey = np.where(row % 2 == 0, c[:, 0], -c[:, 0])
    order = np.lexsort((xkey, row)).astype(np.int64)
    return Tour(order, np.zeros(n, bool), np.zeros(n, np.int64))


def best_entries(job: Job, tour: Tour, timing: Timing, rounds: int = 3) -> Tour:
    """Enter every closed contour at the vertex that makes its two jumps cheapest.

    Sweeps the tour ``rounds`` times (a contour's neighbour may be a contour).
    """
    kinds = job.kinds[tour.order]
    cpos = np.flatnonzero(kinds == CONTOUR)
    if len(cpos) == 0:
        return tour
    a_, b_ = timing.cost_coefficients
    entry = tour.entry.copy()
    n = job.n
    for _ in range(rounds):
        changed = False
        t = Tour(tour.order, tour.reverse, entry)
        ein, eout = tour_points(job, t)
        for k in cpos:
            v = job.strokes[tour.order[k]].xy_mm
            prev = eout[(k - 1) % n]
            nxt = ein[(k + 1) % n]
            d1 = np.hypot(*(v - prev).T)
            d2 = np.hypot(*(v - nxt).T)
            cost = a_ * (d1 + d2) + b_ * ((d1 > 0).astype(float) + (d2 > 0))
            j = int(np.argmin(cost))
            if cost[j] < cost[entry[k]] - 1e-12:
                entry[k] = j
                ein[k] = eout[k] = v[j]
                changed = True
        if not changed:
            break
    return Tour(tour.order, tour.reverse, entry)


def _exhaustive(job: Job, timing: Timing) -> Tour:
    """Best tour of a job with at most 3 strokes (orders x directions x contour entries)."""
    n = job.n
    kinds = job.kinds
    best, bt = np.inf, None
    for perm in permutations(range(1, n)):
        order = np.array((0,) + perm, np.int64)
        for rev in product((False, True), repeat=n):
            rev = np.array(rev) & (kinds[order] == POLYLINE)
            t = best_entries(job, Tour(order, rev, np.zeros(n, np.int64)), timing, rounds=4)
            c = tour_cost(job, t, timing)
            if c < best - 1e-12:
                best, bt = c, t
    return bt


def n_kicks_for(n_strokes: int, opt: LocalSearchOptions) -> int:
    """Kicks of the iterated local search for a job of ``n_strokes`` (0 when kicks_per_stroke is 0)."""
    if opt.kicks_per_stroke <= 0:
        return 0
    return int(min(opt.max_kicks, max(opt.min_kicks, round(opt.kicks_per_stroke * n_strokes))))


def local_search(job: Job, tour: Tour, timing: Timing, options: LocalSearchOptions | None = None) -> Tour:
    """Improve a tour: 2-opt, Or-opt, Lin-Kernighan steps, iterated kicks, contour entries.

    Parameters
    ----------
    job : Job
        Strokes in mm.
    tour : Tour
        Start tour (e.g. nearest neighbour or the GA's best).
    timing : Timing
        The jump cost (distance or time).
    options : LocalSearchOptions, optional

    Returns
    -------
    Tour
        Never costlier than ``best_entries(job, tour)``.
    """
    opt = options or LocalSearchOptions()
    if job.n:                                     # the move loops assume finite coordinates
        check_values(np.concatenate([np.asarray(s.xy_mm, float).reshape(-1, 2) for s in job.strokes]), "xy_mm",
                     limit=np.inf)
    if job.n <= 3:
        return _exhaustive(job, timing)
    a_, b_ = timing.cost_coefficients
    rng = np.random.default_rng([opt.seed, 8])
    start = best_entries(job, tour, timing, rounds=opt.entry_rounds)
    cur = start
    n_kicks = n_kicks_for(job.n, opt)
    rounds = max(1, opt.entry_rounds) if (job.kinds == CONTOUR).any() else 1
    for r in range(rounds):
        xy, cities = _cities(job, cur)
        if len(xy) <= opt.alpha_max_cities:
            neigh = alpha_candidates(np.ascontiguousarray(xy), a_, b_, opt.neighbours)
        else:
            neigh = _neighbours(xy, opt.neighbours)
        cities = cities.copy()
        depth = max(1, opt.lk_depth)
        optimise(np.ascontiguousarray(xy), cities, neigh, a_, b_, n_kicks // rounds, int(rng.integers(2**31)),
                 opt.max_kick_strokes, opt.shuffle_strokes, 3, lk_work(depth), depth, *opt.lk_breadth,
                 opt.kick_tournament)
        entry_of = {int(s): int(e) for s, e in zip(cur.order, cur.entry)}
        new = best_entries(job, _from_cities(job, cities, entry_of), timing, rounds=opt.entry_rounds)
        if tour_cost(job, new, timing) <= tour_cost(job, cur, timing) + 1e-12:
            cur = new
    return cur


def population_arrays(job: Job) -> dict:
    """Arrays the vectorised population cost needs (see :func:`population_cost`)."""
    a, b = endpoints(job)
    ids, v, cnt = job.contour_vertices()
    slot = np.zeros(job.n, np.int64)
    slot[ids] = np.arange(len(ids))
    centroid = a.copy()
    for k, i in enumerate(ids):
        centroid[i] = v[k, :cnt[k]].mean(axis=0)
    cities = np.empty((2 * job.n, 2))
    cities[0::2] = a
    cities[1::2] = b
    return {"start": a, "end": b, "cities_x": cities[:, 0].copy(), "cities_y": cities[:, 1].copy(),
            "n_contours": len(ids), "is_contour": job.kinds == CONTOUR, "contour_slot": slot,
            "contour_vertices": v, "centroid": centroid}


def _population_xy(genes: np.ndarray, arrays: dict, timing: Timing) -> tuple:
    """x and y of the entry and exit points (each (m, n), mm) and contour entries (m, n)."""
    idx = np.abs(genes) - 1
    city = 2 * idx + (genes < 0)
    cx, cy = arrays["cities_x"], arrays["cities_y"]
    xi, yi = cx[city], cy[city]
    city ^= 1
    xo, yo = cx[city], cy[city]
    entry = np.zeros(genes.shape, np.int64)
    isc = arrays["is_contour"][idx]
    if arrays["n_contours"]:
        r, k = np.nonzero(isc)
        n = genes.shape[1]
        kp, kn = (k - 1) % n, (k + 1) % n
        cen = arrays["centroid"]
        ip, inx = isc[r, kp], isc[r, kn]
        px = np.where(ip, cen[idx[r, kp], 0], xo[r, kp])
        py = np.where(ip, cen[idx[r, kp], 1], yo[r, kp])
        nx = np.where(inx, cen[idx[r, kn], 0], xi[r, kn])
        ny = np.where(inx, cen[idx[r, kn], 1], yi[r, kn])
        v = arrays["contour_vertices"][arrays["contour_slot"][idx[r, k]]]        # (k, V, 2)
        a_, b_ = timing.cost_coefficients
        d1 = np.hypot(v[..., 0] - px[:, None], v[..., 1] - py[:, None])
        d2 = np.hypot(v[..., 0] - nx[:, None], v[..., 1] - ny[:, None])
        c = d1 + d2 if b_ == 0.0 else a_ * (d1 + d2) + b_ * ((d1 > 0).astype(float) + (d2 > 0))
        j = np.argmin(c, axis=1)
        pick = v[np.arange(len(j)), j]
        xi[r, k] = xo[r, k] = pick[:, 0]
        yi[r, k] = yo[r, k] = pick[:, 1]
        entry[r, k] = j
    return xi, yi, xo, yo, entry


def population_points(genes: np.ndarray, arrays: dict, timing: Timing) -> tuple:
    """Entry and exit points (m, n, 2) mm and contour entry vertices (m, n) of signed-gene tours.

    Each contour is entered at its best vertex for its neighbours' exit and
    entry points (a neighbouring contour counts by its centroid).
    """
    xi, yi, xo, yo, entry = _population_xy(genes, arrays, timing)
    return np.stack([xi, yi], axis=-1), np.stack([xo, yo], axis=-1), entry


def population_cost(genes: np.ndarray, arrays: dict, timing: Timing) -> np.ndarray:
    """Jump cost (mm or s) of every individual of a GA population, shape (m,).

    Vectorised over individuals and positions: no Python loop over strokes.

    Parameters
    ----------
    genes : ndarray of int, shape (m, n)
        Signed genes ``±(stroke + 1)``; negative runs an open stroke backwards.
    arrays : dict
        From :func:`population_arrays`.
    timing : Timing
    """
    xi, yi, xo, yo, _ = _population_xy(genes, arrays, timing)
    dx = np.empty(genes.shape)
    dy = np.empty(genes.shape)
    np.subtract(xi[:, 1:], xo[:, :-1], out=dx[:, :-1])
    np.subtract(yi[:, 1:], yo[:, :-1], out=dy[:, :-1])
    np.subtract(xi[:, 0], xo[:, -1], out=dx[:, -1])
    np.subtract(yi[:, 0], yo[:, -1], out=dy[:, -1])
    d = np.hypot(dx, dy)
    a_, b_ = timing.cost_coefficients
    if b_ == 0.0:
        return a_ * d.sum(axis=1)
    return (a_ * d + b_ * (d > 0)).sum(axis=1)
