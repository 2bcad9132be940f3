"""Where the batch's jobs run: a local process pool, or a Dask distributed cluster.

Both take plain job dicts (paths and small settings) and hand back the small
record dicts the job function returns. The Dask executor is used only when a
scheduler address is given; ``dask`` is imported there and nowhere else.
"""
from __future__ import annotations

import os

from markcal.stages.errors import MarkcalError, one_line

#: environment variables that cap the thread pools of BLAS, OpenMP (Open3D), numba
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "NUMBA_NUM_THREADS")

#: a job whose worker process dies this many times is recorded as failed
MAX_CRASHES = 2


def limit_threads() -> None:
    """Worker initializer: one thread per worker for BLAS, OpenMP, OpenCV, Open3D, numba.

    The environment variables take effect for libraries loaded after this call
    (a spawned worker loads them lazily, when its first job runs); OpenCV and
    already-loaded BLAS libraries are limited directly.
    """
    for v in THREAD_VARS:
        os.environ[v] = "1"
    try:
        import cv2
        cv2.setNumThreads(1)
    except ImportError:
        pass
    try:                                      # BLAS already loaded (e.g. numpy imported by __main__)
        from threadpoolctl import threadpool_limits
        threadpool_limits(1)
    except ImportError:
        pass
    # Open3D has no Python knob for its thread count: it uses OpenMP (OMP_NUM_THREADS above).


class LocalExecutor:
    """A process pool (spawn start method, one thread per worker).

    A job whose worker process dies (segfault, out of memory) is retried alone
    in a fresh pool; after :data:`MAX_CRASHES` deaths it is recorded as failed,
    and the other jobs go on.
    """

    def __init__(self, workers: int = 1):
        self.workers = int(workers)
        self._saved_env = {}

    def __enter__(self):
        # a spawned child inherits the parent's environment at start: set the caps
        # there too so libraries imported while the child boots are limited as well
        for v in THREAD_VARS:
            self._saved_env[v] = os.environ.get(v)
            os.environ[v] = "1"
        return self

    def __exit__(self, *exc):
        for v, old in self._saved_env.items():
            if old is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = old
        return False

    def map_unordered(self, fn, jobs, collect, on_crash) -> None:
        """Run ``fn(job)`` for every job; call ``collect(record)`` as each finishes.

        At most ``workers`` jobs are in flight, so when a worker process dies
        only those are suspects: they are retried one at a time in a fresh pool
        while the rest wait; a job that kills its worker :data:`MAX_CRASHES`
        times on its own is recorded with ``on_crash(job, reason) -> record``.
        """
        import multiprocessing as mp
        from collections import deque
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool


        queue, suspects = deque(jobs), deque()
        crashes = {}
        ctx = mp.get_context("spawn")
        while queue or suspects:
            pool = ProcessPoolExecutor(max_workers=min(self.workers, len(queue) + len(suspects)), mp_context=ctx,
                                       initializer=limit_threads)
            inflight, broken = {}, []
            try:
                while queue or suspects or inflight:
                    if not broken:
                        if suspects:                  # isolate: one suspect alone in the pool
                            if not inflight:
                                j = suspects.popleft()
                                inflight[pool.submit(fn, j)] = (j, True)
                        else:
                            while queue and len(inflight) < self.workers:
                                j = queue.popleft()
                                inflight[pool.submit(fn, j)] = (j, False)
                    if not inflight:
                        break
                    finished, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
                    for f in finished:
                        job, alone = inflight.pop(f)
                        try:
                            rec = f.result()
                        except BrokenProcessPool:
                            broken.append((job, alone))
                            continue
                        except Exception as exc:  # noqa: BLE001  e.g. a result that does not unpickle
                            rec = on_crash(job, one_line(exc))
                        collect(rec)
                    if broken and not inflight:
                        break
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                for p in list((getattr(pool, "_processes", None) or {}).values()):
                    if p.is_alive():
                        p.terminate()
                raise
            pool.shutdown(wait=not broken)
            for job, alone in broken:
                if alone:
                    crashes[job["name"]] = crashes.get(job["name"], 0) + 1
                    if crashes[job["name"]] >= MAX_CRASHES:
                        collect(on_crash(job, f"worker process died while processing this input "
                                              f"({crashes[job['name']]} times)"))
                        continue
                suspects.append(job)


class DaskExecutor:
    """Jobs on a Dask distributed cluster (``dask[distributed]``, an optional extra).

    The cluster's workers must have markcal installed. Each worker's threads are
    limited once (:func:`limit_threads`); give workers one thread each
    (``dask worker --nthreads 1``) for the same per-core behaviour as the pool.
    """

    def __init__(self, address: str):
        self.address = address
        self.client = None

    def __enter__(self):
        try:
            from dask.distributed import Client
        except ImportError:
            raise MarkcalError("--scheduler needs dask[distributed]: pip install 'markcal[dask]'") from None
        try:
            self.client = Client(self.address, timeout="10s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise MarkcalError(f"cannot connect to the Dask scheduler at {self.address} ({exc})") from None
        self.client.run(limit_threads)
        return self

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        return False

    def map_unordered(self, fn, jobs, collect, on_crash) -> None:
        """As :meth:`LocalExecutor.map_unordered`, on the cluster."""
        from dask.distributed import as_completed

        futs = self.client.map(fn, jobs, pure=False, key=[f"markcal-{i}-{j['name']}" for i, j in enumerate(jobs)])
        byf = {f.key: j for f, j in zip(futs, jobs)}
        try:
            for f in as_completed(futs):
                try:
                    rec = f.result()
                except Exception as exc:  # noqa: BLE001  worker lost, result not deserialisable
                    rec = on_crash(byf[f.key], one_line(exc))
                collect(rec)
        except BaseException:
            self.client.cancel(futs)
            raise


def make_executor(workers: int = 1, scheduler: str | None = None):
    """The Dask executor when ``scheduler`` is given, else a local pool of ``workers`` processes."""
    if scheduler:
        return DaskExecutor(scheduler)
    return LocalExecutor(workers)
