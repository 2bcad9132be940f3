"""Work split over threads, for compiled kernels that release the GIL."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numba

__all__ = ["thread_count", "map_on_threads"]


def thread_count(n_items: int) -> int:
    """Threads for ``n_items`` pieces of work: numba's thread count (1 in batch workers), at most one per piece."""
    return min(n_items, max(1, int(numba.config.NUMBA_NUM_THREADS)))


def map_on_threads(fn, items) -> None:
    """Call ``fn(item)`` for every item, on :func:`thread_count` threads (here when that is one).

    ``fn`` should spend its time in code that releases the GIL (``nogil`` numba kernels); an
    exception in any call is raised here.
    """
    items = list(items)
    workers = thread_count(len(items))
    if workers > 1:
        list(_pool(workers).map(fn, items))
    else:
        for item in items:
            fn(item)


_POOLS: dict = {}


def _pool(workers: int) -> ThreadPoolExecutor:
    """One pool per thread count, kept for the life of the process (a fresh pool costs about 0.2 ms,
    which counts in solvers that split every iteration); a forked child makes its own."""
    key = (os.getpid(), workers)
    pool = _POOLS.get(key)
    if pool is None:
        _POOLS.clear()
        pool = _POOLS[key] = ThreadPoolExecutor(workers, thread_name_prefix="markcal")
    return pool
