"""Numba kernels that build tours and candidate lists for :mod:`markcal.stages.path_tour`.

Candidates: the k alpha-nearest cities of each city (Helsgaun 2000, LKH): alpha(i, j) is how
much longer than the minimum spanning tree the cheapest spanning tree holding edge (i, j) is,
i.e. ``c(i, j)`` minus the longest edge on the tree path from i to j. Unlike nearest
neighbours it keeps the edges that join clusters. Fixed edges (a stroke's two endpoint
cities ``2s``, ``2s + 1``) count 0 in the tree.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .path_tour_moves import _c


@njit(cache=True)
def alpha_candidates(xy, a, b, k):
    """The k alpha-nearest cities of every city (ties by cost), shape (N, k); O(N^2) time, O(N k) memory.

    The minimum spanning tree (Prim, dense) counts each fixed edge (2s, 2s+1) as 0; a city's own
    partner is never its candidate.
    """
    N = xy.shape[0]
    k = min(k, N - 2)
    inf = 1e300
    key = np.full(N, inf)
    dad = np.full(N, -1, np.int64)
    intree = np.zeros(N, np.bool_)
    order = np.empty(N, np.int64)
    key[0] = 0.0
    for it in range(N):
        u = -1
        bk = inf
        for v in range(N):
            if not intree[v] and (u < 0 or key[v] < bk):
                u = v
                bk = key[v]
        intree[u] = True
        order[it] = u
        for v in range(N):
            if not intree[v]:
                w = 0.0 if v == (u ^ 1) else _c(xy, u, v, a, b)
                if w < key[v]:
                    key[v] = w
                    dad[v] = u
    key[order[0]] = 0.0
    beta = np.empty(N)
    mark = np.full(N, -1, np.int64)
    cand = np.empty((N, k), np.int64)
    ca = np.empty(k)
    cc = np.empty(k)
    for i in range(N):
        beta[i] = -inf
        mark[i] = i
        u = i
        while dad[u] >= 0:
            p = dad[u]
            beta[p] = max(beta[u], key[u])
            mark[p] = i
            u = p
        cnt = 0
        for t in range(N):
            j = order[t]
            if mark[j] != i:
                beta[j] = max(beta[dad[j]], key[j])
            if j == i or j == (i ^ 1):
                continue
            cij = _c(xy, i, j, a, b)
            al = cij - beta[j]
            if cnt == k and (al > ca[k - 1] or (al == ca[k - 1] and cij >= cc[k - 1])):
                continue
            p = cnt if cnt < k else k - 1
            while p > 0 and (ca[p - 1] > al or (ca[p - 1] == al and cc[p - 1] > cij)):
                ca[p] = ca[p - 1]
                cc[p] = cc[p - 1]
                cand[i, p] = cand[i, p - 1]
                p -= 1
            ca[p] = al
            cc[p] = cij
            cand[i, p] = j
            if cnt < k:
                cnt += 1
    return cand


@njit(cache=True)
def nearest_neighbour_picks(cand_in, cand_out, owner, n_strokes, start):
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
