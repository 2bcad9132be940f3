"""Numba kernels of the marking-order local search (see :mod:`markcal.stages.path_tour`).

Cities: stroke s has the endpoint cities ``2s`` and ``2s + 1`` that always sit side by side in
the tour array (the stroke itself, a fixed edge); every other edge is a jump. Moves only ever
cut jump edges.

- Candidates (:mod:`markcal.stages.path_tour_cand`): alpha-nearest cities.
- Moves: 2-opt; Or-opt (runs of 1-3 strokes, either way round); a variable-depth
  Lin-Kernighan step made of sequential 2-opt flips (breadth 5, 3, then 1, depth
  ``max_depth``), the best prefix of the chain kept; don't-look bits as a queue.
- Kicks: a double bridge (two neighbouring runs of strokes swapped, either reversed) whose
  three cuts are each the longest of a few random jumps, so that on clustered jobs it mostly
  reorders whole clusters (on a 3000-point clustered board this took the gap to fast-tsp from
  1.0-3.0 % to 0.1-0.3 % over three seeds; cuts at random, or at candidate neighbours of one
  city, did worse), plus a shuffle of a few neighbouring strokes elsewhere (order and
  directions), repaired by the local search and kept unless the tour got longer.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_EPS = 1e-10


@njit(cache=True)
def _c(xy, i, j, a, b):
    dx = xy[i, 0] - xy[j, 0]
    dy = xy[i, 1] - xy[j, 1]
    d = math.sqrt(dx * dx + dy * dy)
    return a * d + (b if d > 0.0 else 0.0)


@njit(cache=True)
def _succ(tour, pos, n, c):
    """The city after c in the tour array."""
    p = pos[c] + 1
    return tour[0 if p == n else p]


@njit(cache=True)
def _pred(tour, pos, n, c):
    """The city before c in the tour array."""
    p = pos[c]
    return tour[n - 1 if p == 0 else p - 1]


@njit(cache=True)
def _jn(tour, pos, n, c):
    """Jump neighbour of city c and the direction (+1: it follows c, -1: it precedes c)."""
    s = _succ(tour, pos, n, c)
    if s == (c ^ 1):
        return _pred(tour, pos, n, c), -1
    return s, 1


@njit(cache=True)
def _reverse(tour, pos, n, i, j):
    """Reverse the cyclic run of positions i..j (or, equivalently, its complement).

    Calling it twice with the same (i, j) restores the tour.
    """
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
        i += 1
        if i == n:
            i = 0
        j -= 1
        if j < 0:
            j = n - 1


@njit(cache=True)
def _move2(tour, pos, n, a, b, c, d):
    """2-opt: drop (a,b), (c,d) (b after a, d after c, same way round), add (a,c), (b,d)."""
    if _succ(tour, pos, n, a) == b:
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
        src = (i + L) % n
        dst = i % n
        for k in range(mf):
            c = tour[src]
            tour[dst] = c
            pos[c] = dst
            src += 1
            if src == n:
                src = 0
            dst += 1
            if dst == n:
                dst = 0
        start = (i + mf) % n
    else:
        src = (i - 1 + n) % n
        dst = (src + L) % n
        for k in range(mb):
            c = tour[src]
            tour[dst] = c
            pos[c] = dst
            src -= 1
            if src < 0:
                src = n - 1
            dst -= 1
            if dst < 0:
                dst = n - 1
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
            continue
        if dr == 1:
            t4 = _succ(tour, pos, n, t3)
        else:
            t4 = _pred(tour, pos, n, t3)
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
                    continue
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
            if _succ(tour, pos, n, bc) == bcn:
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
def _lk_flip(tour, pos, n, t1, t2, t4, flips, k):
    """Flip so that (t1, t2) and (t4, t3) become (t1, t4) and (t2, t3); log the reversal as flip k."""
    if _succ(tour, pos, n, t1) == t2:
        i = pos[t2]
        j = pos[t4]
    else:
        i = pos[t4]
        j = pos[t2]
    _reverse(tour, pos, n, i, j)
    flips[k, 0] = i
    flips[k, 1] = j


@njit(cache=True)
def _lk_alternatives(xy, tour, pos, n, neigh, a, b, t1, t2, G, depth, breadth, alt, alt_g, chain):
    """Up to ``breadth`` next steps (t3, t4) from t2 that keep the partial gain positive, best first."""
    fwd = _succ(tour, pos, n, t1) == t2
    cnt = 0
    for k in range(neigh.shape[1]):
        t3 = neigh[t2, k]
        g1 = G - _c(xy, t2, t3, a, b)
        if g1 <= _EPS or t3 == t1:
            continue
        if fwd:
            t4 = _pred(tour, pos, n, t3)
        else:
            t4 = _succ(tour, pos, n, t3)
        if t4 == (t3 ^ 1) or t4 == t2 or t3 == _succ(tour, pos, n, t2) or t3 == _pred(tour, pos, n, t2):
            continue
        bad = False
        for m in range(depth):                 # never remove an edge this chain added
            u = chain[m, 0]
            v = chain[m, 1]
            if (u == t3 and v == t4) or (u == t4 and v == t3):
                bad = True
                break
        if bad:
            continue
        g = g1 + _c(xy, t3, t4, a, b)
        # insert into the sorted (descending g) list of at most `breadth`
        if cnt == breadth and g <= alt_g[depth, cnt - 1]:
            continue
        p = cnt if cnt < breadth else breadth - 1
        while p > 0 and alt_g[depth, p - 1] < g:
            alt_g[depth, p] = alt_g[depth, p - 1]
            alt[depth, p, 0] = alt[depth, p - 1, 0]
            alt[depth, p, 1] = alt[depth, p - 1, 1]
            p -= 1
        alt_g[depth, p] = g
        alt[depth, p, 0] = t3
        alt[depth, p, 1] = t4
        if cnt < breadth:
            cnt += 1
    return cnt


@njit(cache=True)
def _try_lk(xy, tour, pos, n, neigh, a, b, t1, ws, touched, max_depth, br1, br2):
    """Variable-depth LK step from t1 (sequential 2-opt flips); returns the gain kept and fills touched.

    ``ws``: work arrays (alt, alt_g, chain, flips, cnt, idx, t2s, gains) from :func:`lk_work`.
    """
    alt, alt_g, chain, flips, cnt, idx, t2s, gains = ws
    t2, _ = _jn(tour, pos, n, t1)
    t2s[0] = t2
    gains[0] = _c(xy, t1, t2, a, b)
    depth = 0
    cnt[0] = _lk_alternatives(xy, tour, pos, n, neigh, a, b, t1, t2, gains[0], 0, br1, alt, alt_g, chain)
    idx[0] = 0
    nf = 0
    best = _EPS
    bestf = 0
    while True:
        if idx[depth] < cnt[depth] and nf == depth:
            k = idx[depth]
            idx[depth] += 1
            t2 = t2s[depth]
            t3 = alt[depth, k, 0]
            t4 = alt[depth, k, 1]
            g = alt_g[depth, k]
            close = g - _c(xy, t4, t1, a, b)
            deeper = False
            if depth + 1 < max_depth:           # can the chain go on from t4 at all?
                for m in range(neigh.shape[1]):
                    if g - _c(xy, t4, neigh[t4, m], a, b) > _EPS:
                        deeper = True
                        break
            if close <= best and not deeper:
                continue                         # a dead end: no need to flip
            _lk_flip(tour, pos, n, t1, t2, t4, flips, nf)
            nf += 1
            chain[depth, 0] = t2
            chain[depth, 1] = t3
            if close > best:
                best = close
                bestf = nf
            if deeper:
                depth += 1
                t2s[depth] = t4
                gains[depth] = g
                br = br2 if depth == 1 else 1
                cnt[depth] = _lk_alternatives(xy, tour, pos, n, neigh, a, b, t1, t4, g, depth, br, alt, alt_g,
                                              chain)
                idx[depth] = 0
            continue
        # the chain ends here
        if best > _EPS:
            while nf > bestf:
                nf -= 1
                _reverse(tour, pos, n, flips[nf, 0], flips[nf, 1])
            m = 0
            touched[m] = t1
            m += 1
            for d in range(bestf):
                touched[m] = t2s[d]
                touched[m + 1] = alt[d, idx[d] - 1, 0]
                touched[m + 2] = alt[d, idx[d] - 1, 1]
                m += 3
            touched[m] = -1
            return best
        if nf > depth:                         # deepest step: undo it, try the next alternative
            nf -= 1
            _reverse(tour, pos, n, flips[nf, 0], flips[nf, 1])
            continue
        if depth == 0:
            return 0.0
        depth -= 1
        nf -= 1
        _reverse(tour, pos, n, flips[nf, 0], flips[nf, 1])


def lk_work(max_depth: int):
    """Work arrays of :func:`_try_lk`."""
    d = max_depth + 1
    return (np.zeros((d, 5, 2), np.int64), np.zeros((d, 5)), np.zeros((d, 2), np.int64),
            np.zeros((d, 2), np.int64), np.zeros(d, np.int64), np.zeros(d, np.int64), np.zeros(d, np.int64),
            np.zeros(d))


@njit(cache=True)
def _run_queue(xy, tour, pos, neigh, a, b, q, inq, state, max_seg, ws, max_depth, br1, br2):
    """Process the don't-look-bit queue until empty; return the total gain."""
    n = tour.shape[0]
    touched = np.empty(3 * max_depth + 8, np.int64)
    buf = np.empty(2 * max_seg + 2, np.int64)
    gain = 0.0
    while state[1] > 0:
        t1 = q[state[0]]
        state[0] = (state[0] + 1) % n
        state[1] -= 1
        inq[t1] = False
        touched[6] = -1
        m = 4
        g = _try_2opt(xy, tour, pos, n, neigh, a, b, t1, touched)
        if g <= 0.0:
            m = 6
            g = _try_oropt(xy, tour, pos, n, neigh, a, b, t1, touched, buf, max_seg)
        if g <= 0.0 and max_depth > 1:
            m = touched.shape[0]
            g = _try_lk(xy, tour, pos, n, neigh, a, b, t1, ws, touched, max_depth, br1, br2)
        if g > 0.0:
            gain += g
            for t in range(m):
                c = touched[t]
                if c < 0:
                    break
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
def _long_cut(xy, tour, n, a, b, k):
    """The longest of k random jump edges, as the position x of its first city."""
    best = -1.0
    bx = 0
    for _ in range(k):
        x = np.random.randint(n)
        if not _is_cut(tour, n, x):
            x = (x + 1) % n
        d = _c(xy, tour[x], tour[(x + 1) % n], a, b)
        if d > best:
            best = d
            bx = x
    return bx


@njit(cache=True)
def _segment_kick(xy, tour, pos, n, saved, a, b, max_kick_strokes, ends, tournament):
    """Swap two neighbouring runs of strokes (either reversed); return the cost change.

    ``tournament`` k > 0: the three cuts are each the longest of k random jumps (on clustered
    jobs these are the jumps between clusters, so the kick reorders clusters), the two shorter
    runs between them are swapped. 0: runs of 1..max_kick_strokes strokes from a random cut.
    """
    nstroke = n // 2
    if tournament > 0:
        p0 = _long_cut(xy, tour, n, a, b, tournament)
        p1 = _long_cut(xy, tour, n, a, b, tournament)
        p2 = _long_cut(xy, tour, n, a, b, tournament)
        p0, p1, p2 = min(p0, p1, p2), p0 + p1 + p2 - min(p0, p1, p2) - max(p0, p1, p2), max(p0, p1, p2)
        s0 = p1 - p0
        s1 = p2 - p1
        s2 = n - (p2 - p0)                  # the two shorter runs are swapped, the longest stays
        if min(s0, s1, s2) < 2:
            return 1e300
        if s2 >= s0 and s2 >= s1:
            x1, l1, l2 = p0, s0 // 2, s1 // 2
        elif s0 >= s1:
            x1, l1, l2 = p1, s1 // 2, s2 // 2
        else:
            x1, l1, l2 = p2, s2 // 2, s0 // 2
    else:
        lim = max(1, min(max_kick_strokes, (nstroke - 2) // 2))
        x1 = np.random.randint(n)
        if not _is_cut(tour, n, x1):
            x1 = (x1 + 1) % n
        l1 = 1 + np.random.randint(lim)
        l2 = 1 + np.random.randint(lim)
    if 2 * (l1 + l2) >= n - 2:
        return 1e300
    x2 = (x1 + 2 * l1) % n
    x3 = (x2 + 2 * l2) % n
    A = tour[x1]
    B0 = tour[(x1 + 1) % n]
    B1 = tour[x2]
    C0 = tour[(x2 + 1) % n]
    C1 = tour[x3]
    D = tour[(x3 + 1) % n]
    kind = np.random.randint(3)
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
    ends[0] = A
    ends[1] = B0
    ends[2] = B1
    ends[3] = C0
    ends[4] = C1
    ends[5] = D
    ends[6] = -1
    return delta


@njit(cache=True)
def _shuffle_kick(xy, tour, pos, n, a, b, w, q, inq, state):
    """Shuffle a window of w neighbouring strokes (random order and directions); queue its cities.

    Returns the cost change.
    """
    x = np.random.randint(n)
    if not _is_cut(tour, n, x):
        x = (x + 1) % n
    before = 0.0
    for k in range(w + 1):
        before += _c(xy, tour[(x + 2 * k) % n], tour[(x + 2 * k + 1) % n], a, b)
    for k in range(w - 1, 0, -1):                   # Fisher-Yates on the strokes of the window
        j = np.random.randint(k + 1)
        pk = (x + 1 + 2 * k) % n
        pj = (x + 1 + 2 * j) % n
        for t in range(2):
            u = tour[(pk + t) % n]
            v = tour[(pj + t) % n]
            tour[(pk + t) % n] = v
            tour[(pj + t) % n] = u
    for k in range(w):
        p0 = (x + 1 + 2 * k) % n
        p1 = (p0 + 1) % n
        if np.random.random() < 0.5:
            u = tour[p0]
            tour[p0] = tour[p1]
            tour[p1] = u
        pos[tour[p0]] = p0
        pos[tour[p1]] = p1
    after = 0.0
    for k in range(w + 1):
        after += _c(xy, tour[(x + 2 * k) % n], tour[(x + 2 * k + 1) % n], a, b)
    for k in range(2 * w + 2):
        _push(q, inq, state, tour[(x + k) % n])
    return after - before


@njit(cache=True)
def optimise(xy, tour, neigh, a, b, n_kicks, seed, max_kick_strokes, shuffle_strokes, max_seg, ws, max_depth, br1,
             br2, tournament):
    """Local search to a local optimum, then ``n_kicks`` kicks each repaired by the local search.

    A kick swaps two neighbouring runs of strokes (a double bridge) and shuffles
    ``shuffle_strokes`` strokes elsewhere; it is kept when the repaired tour is not longer.
    Returns the kicks kept.
    """
    np.random.seed(seed)
    n = tour.shape[0]
    pos = np.empty(n, np.int64)
    for k in range(n):
        pos[tour[k]] = k
    q = np.empty(n, np.int64)
    inq = np.zeros(n, np.bool_)
    state = np.zeros(2, np.int64)
    for k in range(n):
        _push(q, inq, state, tour[k])
    _run_queue(xy, tour, pos, neigh, a, b, q, inq, state, max_seg, ws, max_depth, br1, br2)
    saved = tour.copy()
    ends = np.empty(8, np.int64)
    accepted = 0
    for it in range(n_kicks):
        for k in range(n):
            saved[k] = tour[k]
        delta = _segment_kick(xy, tour, pos, n, saved, a, b, max_kick_strokes, ends, tournament)
        if delta > 1e299:
            continue
        for m in range(8):
            if ends[m] < 0:
                break
            _push(q, inq, state, ends[m])
        w = min(shuffle_strokes, n // 2 - 2)
        if w >= 2:
            delta += _shuffle_kick(xy, tour, pos, n, a, b, w, q, inq, state)
        delta -= _run_queue(xy, tour, pos, neigh, a, b, q, inq, state, max_seg, ws, max_depth, br1, br2)
        if delta > _EPS:
            for k in range(n):
                c = saved[k]
                tour[k] = c
                pos[c] = k
        else:
            accepted += 1
    return accepted
