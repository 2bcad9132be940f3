"""The shared thread pool of :mod:`markcal.stages.threads`."""
import os
import threading

import pytest

from markcal.stages import threads


@pytest.fixture
def two_threads(monkeypatch):
    monkeypatch.setattr(threads, "thread_count", lambda n: min(n, 2))


def test_every_item_is_done_once_on_the_pool(two_threads):
    seen, names = [], set()

    def work(i):
        seen.append(i)
        names.add(threading.current_thread().name)

    threads.map_on_threads(work, range(10))
    assert sorted(seen) == list(range(10))
    assert all(n.startswith("markcal-pool") for n in names)
    threads.map_on_threads(work, range(3))
    assert len(threads._POOLS) == 1                      # the same pool, not a new one per call


def test_nested_calls_run_in_the_calling_thread_and_do_not_deadlock(two_threads):
    out = []

    def outer(i):
        caller = threading.current_thread().name
        threads.map_on_threads(lambda j: out.append((i, j, threading.current_thread().name == caller)), range(4))

    threads.map_on_threads(outer, range(4))
    assert sorted((i, j) for i, j, _ in out) == [(i, j) for i in range(4) for j in range(4)]
    assert all(same for _i, _j, same in out)


def test_an_error_in_one_item_is_raised_here(two_threads):
    def work(i):
        if i == 3:
            raise ValueError("item 3")

    with pytest.raises(ValueError, match="item 3"):
        threads.map_on_threads(work, range(6))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_makes_its_own_pool(two_threads):
    threads.map_on_threads(lambda i: None, range(4))
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:                                          # child: the parent's pool threads do not exist here
        try:
            done = []
            threads.map_on_threads(done.append, range(6))
            os.write(w, b"ok" if sorted(done) == list(range(6)) else b"bad")
        finally:
            os._exit(0)
    os.close(w)
    os.waitpid(pid, 0)
    assert os.read(r, 2) == b"ok"
