"""Work split over threads, for compiled kernels that release the GIL."""
from __future__ import annotations

import os
import threading
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
    # called from one of the pool's own threads (nested work): here, so the pool cannot deadlock
    workers = 1 if threading.current_thread().name.startswith(_PREFIX) else thread_count(len(items))
    if workers > 1:
        list(_pool(workers).map(fn, items))
    else:
        for item in items:
            fn(item)


_POOLS: dict = {}
_PREFIX = "markcal-pool"


def _pool(workers: int) -> ThreadPoolExecutor:
    """The process's pool, kept for its life (a fresh pool costs about 0.2 ms, which counts in solvers
    that split every iteration); a forked child makes its own."""
    pool, size = _POOLS.get(os.getpid(), (None, 0))
    if size < workers:
        _POOLS.clear()
        pool, size = _POOLS[os.getpid()] = ThreadPoolExecutor(workers, thread_name_prefix=_PREFIX), workers
    return pool
