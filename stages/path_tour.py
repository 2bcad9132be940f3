"""Tour construction and local search for marking jobs (numba kernels).

Model. Every stroke s has two *endpoint cities*, ``2s`` (its first vertex) and
``2s + 1`` (its last vertex; a contour's entry vertex for both, a point's
vertex for both). A tour is a cyclic array of the 2n cities in which the two
cities of a stroke always sit side by side: the edge between them is the
stroke itself (marked, fixed), every other edge is a *jump* (laser off).
Reversing a run of whole strokes reverses their direction too, so plain
2-opt on this array chooses the direction of open strokes for free. Moves
only ever cut jump edges.

Local search: 2-opt and Or-opt (segments of 1-3 strokes, either way round)
with neighbour lists and don't-look bits (a queue of active cities), then an
iterated local search: segment-swap kicks (the double bridge of Chained
Lin-Kernighan, kept local) each repaired by the same local search and kept
only if the tour got shorter. Closed contours are re-entered at their best
vertex between rounds. The number of kicks is fixed by the options, never by
a clock, so a seed gives the same tour on any machine.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import permutations, product

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .path_job import CONTOUR, POLYLINE, Job, Timing, Tour, endpoints, tour_cost, tour_points

__all__ = ["LocalSearchOptions", "nearest_neighbour_tour", "raster_tour", "best_entries", "local_search",
           "population_arrays", "population_points", "population_cost"]

_EPS = 1e-10


@dataclass(frozen=True)
class LocalSearchOptions:
    """Settings of :func:`local_search`.

    ``kicks_per_stroke`` x n kicks (at least ``min_kicks``, at most ``max_kicks``) of the iterated
    local search; each swaps two runs of 1..``max_kick_strokes`` strokes.
    """

    neighbours: int = 10
    kicks_per_stroke: float = 50.0
    min_kicks: int = 20_000
    max_kicks: int = 200_000
    max_kick_strokes: int = 30
    entry_rounds: int = 3
    seed: int = 0


# ----------------------------------------------------------------------------- numba kernels

@njit(cache=True)
def _c(xy, i, j, a, b):
    dx = xy[i, 0] - xy[j, 0]
    dy = xy[i, 1] - xy[j, 1]
    d = math.sqrt(dx * dx + dy * dy)
    return a * d + (b if d > 0.0 else 0.0)


@njit(cache=True)
def _jn(tour, pos, n, c):
    """Jump neighbour of city c and the direction (+1: it follows c, -1: it precedes c)."""
    s = tour[(pos[c] + 1) % n]
    if s == (c ^ 1):
        return tour[(pos[c] - 1 + n) % n], -1
    return s, 1


@njit(cache=True)
def _reverse(tour, pos, n, i, j):
    """Reverse the cyclic run of positions i..j (or, equivalently, its complement)."""
    L = (j - i + n) % n + 1
    if 2 * L > n:
        i, j = (j + 1) % n, (i - 1 + n) % n
        L = n - L
    for _ in range(L // 2):
        ci = tour[i]
        cj = tour[j]
        tour[i] = cj
        pos[cj] = i
        tour[j] = ci
        pos[ci] = j
        i = (i + 1) % n
        j = (j - 1 + n) % n


@njit(cache=True)
def _move2(tour, pos, n, a, b, c, d):
    """2-opt: drop (a,b), (c,d) (b after a, d after c, same way round), add (a,c), (b,d)."""
    if tour[(pos[a] + 1) % n] == b:
        _reverse(tour, pos, n, pos[b], pos[c])
    else:
        _reverse(tour, pos, n, pos[c], pos[b])


@njit(cache=True)
def _or_move(tour, pos, n, i, L, j, first, buf):
    """Move the run of L cities at positions i.. to between positions j and j+1.

    ``first`` is the run's end city that must sit next to the city at j.
    """
    for t in range(L):
        buf[t] = tour[(i + t) % n]
    if buf[0] != first:
        for t in range(L // 2):
            x = buf[t]
            buf[t] = buf[L - 1 - t]
            buf[L - 1 - t] = x
    mf = (j - (i + L) + 1 + 2 * n) % n
    mb = n - L - mf
    if mf <= mb:
        for k in range(mf):
            c = tour[(i + L + k) % n]
            tour[(i + k) % n] = c
            pos[c] = (i + k) % n
        start = (i + mf) % n
    else:
        for k in range(mb):
            src = (i - 1 - k + 2 * n) % n
            dst = (src + L) % n
            c = tour[src]
            tour[dst] = c
            pos[c] = dst
        start = (i - mb + n) % n
    for t in range(L):
        p = (start + t) % n
        tour[p] = buf[t]
        pos[buf[t]] = p


@njit(cache=True)
def _push(q, inq, state, c):
    if not inq[c]:
        n = q.shape[0]
        q[(state[0] + state[1]) % n] = c
        state[1] += 1
        inq[c] = True


@njit(cache=True)
def _try_2opt(xy, tour, pos, n, neigh, a, b, t1, touched):
    t2, dr = _jn(tour, pos, n, t1)
    d12 = _c(xy, t1, t2, a, b)
    best = _EPS
    b3 = -1
    b4 = -1
    for k in range(neigh.shape[1]):
        t3 = neigh[t1, k]
        d13 = _c(xy, t1, t3, a, b)
        if d13 >= d12 - _EPS:
            break
        if dr == 1:
            t4 = tour[(pos[t3] + 1) % n]
        else:
            t4 = tour[(pos[t3] - 1 + n) % n]
        if t4 == (t3 ^ 1) or t3 == t2 or t4 == t1:
            continue
        g = d12 + _c(xy, t3, t4, a, b) - d13 - _c(xy, t2, t4, a, b)
        if g > best:
            best = g
            b3 = t3
            b4 = t4
    if b3 < 0:
        return 0.0
    _move2(tour, pos, n, t1, t2, b3, b4)
    touched[0] = t1
    touched[1] = t2
    touched[2] = b3
    touched[3] = b4
    return best


@njit(cache=True)
def _try_oropt(xy, tour, pos, n, neigh, a, b, t1, touched, buf, max_seg):
    t2, dr = _jn(tour, pos, n, t1)
    p = t1
    s1 = t2
    for k in range(1, max_seg + 1):
        L = 2 * k
        if L >= n - 4:
            break
        s2 = tour[(pos[s1] + dr * (L - 1) + 2 * n) % n]
        nx = tour[(pos[s1] + dr * L + 2 * n) % n]
        g1 = _c(xy, p, s1, a, b) + _c(xy, s2, nx, a, b) - _c(xy, p, nx, a, b)
        if g1 <= _EPS:
            continue
        best = _EPS
        bc = -1
        bcn = -1
        be = -1
        for side in range(2):
            e = s1 if side == 0 else s2
            o = s2 if side == 0 else s1
            for j in range(neigh.shape[1]):
                c = neigh[e, j]
                dec = _c(xy, e, c, a, b)
                if dec >= g1 - _EPS:
                    break
                if ((pos[c] - pos[s1]) * dr + 2 * n) % n < L:
                    continue
                cn, _ = _jn(tour, pos, n, c)
                if ((pos[cn] - pos[s1]) * dr + 2 * n) % n < L:
                    continue
                g = g1 - dec - _c(xy, o, cn, a, b) + _c(xy, c, cn, a, b)
                if g > best:
                    best = g
                    bc = c
                    bcn = cn
                    be = e
        if bc >= 0:
            i0 = pos[s1] if dr == 1 else pos[s2]
            if tour[(pos[bc] + 1) % n] == bcn:
                left = bc
                first = be
            else:
                left = bcn
                first = s2 if be == s1 else s1
            _or_move(tour, pos, n, i0, L, pos[left], first, buf)
            touched[0] = p
            touched[1] = nx
            touched[2] = s1
            touched[3] = s2
            touched[4] = bc
            touched[5] = bcn
            return best
    return 0.0


@njit(cache=True)
def _run_queue(xy, tour, pos, neigh, a, b, q, inq, state, max_seg):
    """Process the don't-look-bit queue until empty; return the total gain."""
    n = tour.shape[0]
    touched = np.empty(6, np.int64)
    buf = np.empty(2 * max_seg + 2, np.int64)
    gain = 0.0
    while state[1] > 0:
        t1 = q[state[0]]
        state[0] = (state[0] + 1) % n
        state[1] -= 1
        inq[t1] = False
        g = _try_2opt(xy, tour, pos, n, neigh, a, b, t1, touched)
        m = 4
        if g <= 0.0:
            g = _try_oropt(xy, tour, pos, n, neigh, a, b, t1, touched, buf, max_seg)
            m = 6
        if g > 0.0:
            gain += g
            for t in range(m):
                c = touched[t]
                _push(q, inq, state, c)
                _push(q, inq, state, c ^ 1)
    return gain


@njit(cache=True)
def _tour_cost(xy, tour, a, b):
    n = tour.shape[0]
    s = 0.0
    for k in range(n):
        i = tour[k]
        j = tour[(k + 1) % n]
        if j != (i ^ 1):
            s += _c(xy, i, j, a, b)
    return s


@njit(cache=True)
def _is_cut(tour, n, x):
    return tour[(x + 1) % n] != (tour[x % n] ^ 1)


@njit(cache=True)
def _optimise(xy, tour, neigh, a, b, kick_r, max_seg):
    """2-opt + Or-opt to a local optimum, then one local-search repair per kick.

    ``kick_r`` (k, 5): uniform numbers in [0, 1) for the start and the two run lengths, the
    longest run (strokes), and one more choosing plain swap / first run reversed / second reversed.
    """
    n = tour.shape[0]
    pos = np.empty(n, np.int64)
    for k in range(n):
        pos[tour[k]] = k
    q = np.empty(n, np.int64)
    inq = np.zeros(n, np.bool_)
    state = np.zeros(2, np.int64)
    for k in range(n):
        _push(q, inq, state, tour[k])
    _run_queue(xy, tour, pos, neigh, a, b, q, inq, state, max_seg)
    nstroke = n // 2
    saved = tour.copy()
    accepted = 0
    for it in range(kick_r.shape[0]):
        r0 = kick_r[it, 0]
        r1 = kick_r[it, 1]
        r2 = kick_r[it, 2]
        lim = max(1, min(int(kick_r[it, 3]), (nstroke - 2) // 2))
        x1 = int(r0 * n) % n
        if not _is_cut(tour, n, x1):
            x1 = (x1 + 1) % n
        l1 = 1 + int(r1 * lim)
        l2 = 1 + int(r2 * lim)
        if 2 * (l1 + l2) >= n - 2:
            continue
        x2 = (x1 + 2 * l1) % n
        x3 = (x2 + 2 * l2) % n
        A = tour[x1]
        B0 = tour[(x1 + 1) % n]
        B1 = tour[x2]
        C0 = tour[(x2 + 1) % n]
        C1 = tour[x3]
        D = tour[(x3 + 1) % n]
        for k in range(n):
            saved[k] = tour[k]
        # rewrite positions x1+1 .. x3 as C then B, either of them possibly reversed
        kind = int(kick_r[it, 4] * 3.0)
        rc = kind == 1
        rb = kind == 2
        cf, cl = (C1, C0) if rc else (C0, C1)
        bf, bl = (B1, B0) if rb else (B0, B1)
        delta = (_c(xy, A, cf, a, b) + _c(xy, cl, bf, a, b) + _c(xy, bl, D, a, b)
                 - _c(xy, A, B0, a, b) - _c(xy, B1, C0, a, b) - _c(xy, C1, D, a, b))
        p = (x1 + 1) % n
        for t in range(2 * l2):
            c = saved[(x3 - t + n) % n] if rc else saved[(x2 + 1 + t) % n]
            tour[p] = c
            pos[c] = p
            p = (p + 1) % n
        for t in range(2 * l1):
            c = saved[(x2 - t + n) % n] if rb else saved[(x1 + 1 + t) % n]
            tour[p] = c
            pos[c] = p
            p = (p + 1) % n
        for c in (A, B0, B1, C0, C1, D):
            _push(q, inq, state, c)
        delta -= _run_queue(xy, tour, pos, neigh, a, b, q, inq, state, max_seg)
        if delta >= -_EPS:
            for k in range(n):
                c = saved[k]
                tour[k] = c
                pos[c] = k
        else:
            accepted += 1
    return accepted


@njit(cache=True)
def _nearest_neighbour(cand_in, cand_out, owner, n_strokes, start):
    """Greedy order: from the current exit, the nearest entry candidate of an unmarked stroke."""
    m = cand_in.shape[0]
    used = np.zeros(n_strokes, np.bool_)
    picks = np.empty(n_strokes, np.int64)
    cur = start
    picks[0] = cur
    used[owner[cur]] = True
    for k in range(1, n_strokes):
        x = cand_out[cur, 0]
        y = cand_out[cur, 1]
        best = 1e300
        bi = -1
        for j in range(m):
            if used[owner[j]]:
                continue
            dx = cand_in[j, 0] - x
            dy = cand_in[j, 1] - y
            d = dx * dx + dy * dy
            if d < best:
                best = d
                bi = j
        picks[k] = bi
        used[owner[bi]] = True
        cur = bi
    return picks


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
    """k nearest cities of each city, nearest first, without itself and its partner."""
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
    picks = _nearest_neighbour(cin, cout, own, job.n, first)
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
    """Improve a tour: 2-opt, Or-opt, iterated kicks, contour entries.

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
        neigh = _neighbours(xy, opt.neighbours)
        kicks = n_kicks // rounds
        r = rng.random((kicks, 4))
        kr = np.column_stack([r[:, :3], np.full(kicks, float(opt.max_kick_strokes)), r[:, 3]])
        cities = cities.copy()
        _optimise(np.ascontiguousarray(xy), cities, neigh, a_, b_, np.ascontiguousarray(kr), 3)
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
