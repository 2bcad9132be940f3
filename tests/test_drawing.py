"""Drawing a report's figures in other processes (reports/drawing.py): a child forked when the figures
are due (parts_in_two), drawing processes started before the flow (draw_groups), and when they are used."""
from __future__ import annotations

import os
import time

import pytest

from markcal.reports import drawing


def _reaped(pid: int) -> bool:
    """The child ``pid`` is gone and was waited for (no zombie left)."""
    try:
        os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        return True
    return False


@pytest.fixture
def forking(monkeypatch):
    """parts_in_two forks whatever the load; the pids of its children are recorded."""
    monkeypatch.setattr(drawing, "_fork_helps", lambda: True)
    children, real_fork = [], os.fork

    def fork():
        pid = real_fork()
        if pid:
            children.append(pid)
        return pid
    monkeypatch.setattr(os, "fork", fork)
    return children


def _all_reaped(children) -> bool:
    return len(children) == 1 and all(_reaped(p) for p in children)


def test_parts_in_two_draws_the_second_half_in_a_child(forking):
    me = str(os.getpid())
    mine, theirs = drawing.parts_in_two([lambda: "a", lambda: str(os.getpid())], [lambda: str(os.getpid()), lambda: "z"])
    assert mine == ["a", me]
    assert theirs == [str(forking[0]), "z"]                       # drawn by the child
    assert _all_reaped(forking)


def test_parts_in_two_redraws_what_the_child_failed(forking):
    parent = os.getpid()
    _, theirs = drawing.parts_in_two([lambda: "a"], [lambda: "redone here" if os.getpid() == parent else 1 / 0])
    assert theirs == ["redone here"] and _all_reaped(forking)


def test_parts_in_two_kills_a_slow_child(forking, monkeypatch):
    parent = os.getpid()
    monkeypatch.setattr(drawing, "FORK_TIMEOUT_S", 0.5)
    t0 = time.perf_counter()
    _, theirs = drawing.parts_in_two([lambda: "a"], [lambda: "here" if os.getpid() == parent else time.sleep(60)])
    assert theirs == ["here"] and time.perf_counter() - t0 < 20 and _all_reaped(forking)


def test_parts_in_two_error_here_ends_the_child(forking):
    t0 = time.perf_counter()
    with pytest.raises(ZeroDivisionError, match="division by zero"):
        drawing.parts_in_two([lambda: 1 / 0], [lambda: time.sleep(60)])
    assert time.perf_counter() - t0 < 20 and _all_reaped(forking)


def test_scan_report_is_the_same_drawn_in_two_processes(small_result, forking, monkeypatch):
    from markcal.reports.scan_report import scan_report_html
    monkeypatch.setattr(drawing, "_fork_helps", lambda: False)
    alone = scan_report_html(small_result)
    monkeypatch.setattr(drawing, "_fork_helps", lambda: True)
    assert scan_report_html(small_result) == alone and _all_reaped(forking)


def test_no_fork_when_turned_off_or_loaded(monkeypatch):
    busy = [1.0]
    monkeypatch.setattr(drawing, "_busy_cores", lambda: busy[0])
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    import threading
    monkeypatch.setattr(threading, "active_count", lambda: 1)      # pytest-xdist's worker runs threads
    monkeypatch.setenv(drawing.FORK_ENV, "0")
    assert not drawing._fork_helps()                                   # turned off
    monkeypatch.delenv(drawing.FORK_ENV, raising=False)
    assert drawing._fork_helps()                                       # the default, with a free core
    busy[0] = 2.0
    assert not drawing._fork_helps()                                   # no core is free


def test_busy_cores_counts_the_runnable_tasks_now(monkeypatch, tmp_path):
    import builtins
    real_open = builtins.open
    loadavg = tmp_path / "loadavg"
    loadavg.write_text("2.95 3.01 2.50 1/113 19021\n")            # a minute of load, but only this task runs now
    monkeypatch.setattr(builtins, "open", lambda f, *a, **k: real_open(loadavg if f == "/proc/loadavg" else f, *a, **k))
    monkeypatch.setattr(drawing, "_own_running_threads", lambda: 1)
    assert drawing._busy_cores() == 1.0
    monkeypatch.setattr(drawing, "_own_running_threads", lambda: 2)     # a BLAS worker of this process still spins
    loadavg.write_text("0.10 0.20 0.30 2/113 19021\n")
    assert drawing._busy_cores() == 1.0                               # it is not other work
    monkeypatch.setattr(drawing, "_own_running_threads", lambda: 1)
    loadavg.write_text("0.10 0.20 0.30 3/113 19021\n")
    assert drawing._busy_cores() == 3.0
    loadavg.write_text("garbled\n")                                  # unreadable: the 1-minute load
    monkeypatch.setattr(os, "getloadavg", lambda: (1.5, 0.0, 0.0))
    assert drawing._busy_cores() == 1.5


def test_own_running_threads_sees_the_calling_thread():
    assert drawing._own_running_threads() >= 1                         # this thread runs while it reads /proc


# ----------------------------------------------------------------------------- drawing processes

def _pid_and(x):
    """A part drawn in a drawing process: which process drew it, and its argument."""
    return f"{os.getpid()}:{x}"


def _fail_in_a_drawer(parent):
    if os.getpid() != parent:
        raise ValueError("drawer fails")
    return "here"


def _fail_but_in(*pids):
    if os.getpid() not in pids:
        raise ValueError("fails in this process")
    return f"{os.getpid()}:ok"


def _sleep_in_a_drawer(parent):
    if os.getpid() != parent:
        time.sleep(60)
    return "here"


def _fails_everywhere():
    raise ValueError("fails here too")


@pytest.fixture
def drawer(monkeypatch):
    """The drawing process, started whatever the load (without the warm-up's imports); stopped after."""
    monkeypatch.setattr(drawing, "_fork_helps", lambda: True)
    monkeypatch.setattr(drawing, "_warm_up", lambda modules: None)
    assert drawing.start_drawing_process()
    pid = drawing._DRAWER[0][0]
    yield pid
    drawing.stop_drawing_process()
    assert not drawing._DRAWER and _reaped(pid)                   # ended and waited for: no zombie


def test_the_drawing_process_draws_the_groups_side_by_side(drawer):
    assert drawer != os.getpid()
    first, second = drawing.draw_groups([[(_pid_and, ("a",)), (_pid_and, ("b",))], [(_pid_and, ("c",))]])
    assert [v.split(":")[1] for v in first + second] == ["a", "b", "c"]       # in order
    assert {v.split(":")[0] for v in first} == {str(drawer)}                   # the first group in it
    helper = second[0].split(":")[0]
    assert helper not in (str(drawer), str(os.getpid()))                       # the second in a fork of it
    again = drawing.draw_groups([[(_pid_and, ("d",))], [(_pid_and, ("e",))]])  # it serves until stopped
    assert [g[0].split(":")[1] for g in again] == ["d", "e"] and drawing._DRAWER[0][0] == drawer
    assert drawing.draw_groups([[(_pid_and, ("f",))]]) == [[f"{drawer}:f"]]    # one group: drawn there


def test_a_group_that_fails_in_the_drawing_process_is_drawn_here(drawer):
    parent = os.getpid()
    out = drawing.draw_groups([[(_fail_in_a_drawer, (parent,))], [(_pid_and, ("x",))]])
    assert out[0] == ["here"] and out[1][0] == f"{parent}:x"                   # both drawn here
    out = drawing.draw_groups([[(_pid_and, ("y",))], [(_fail_but_in, (parent, drawer))]])
    assert out == [[f"{drawer}:y"], [f"{drawer}:ok"]]                          # its fork failed: it redrew
    with pytest.raises(ValueError, match="fails here too"):                    # the error comes out here
        drawing.draw_groups([[(_fails_everywhere, ())], [(_pid_and, ("z",))]])
    assert drawing._DRAWER                                                     # still serving


def test_a_stuck_drawing_process_is_killed_and_the_groups_drawn_here(drawer, monkeypatch):
    monkeypatch.setattr(drawing, "FORK_TIMEOUT_S", 0.5)
    t0 = time.perf_counter()
    out = drawing.draw_groups([[(_sleep_in_a_drawer, (os.getpid(),))], [(_pid_and, ("z",))]])
    assert out[0] == ["here"] and time.perf_counter() - t0 < 20
    assert not drawing._DRAWER and _reaped(drawer)                             # killed, reaped, not used again


def test_without_the_drawing_process_two_groups_fork_as_before(forking):
    assert not drawing._DRAWER
    first, second = drawing.draw_groups([[(_pid_and, ("a",))], [(_pid_and, ("b",))]])
    assert first == [f"{os.getpid()}:a"] and second == [f"{forking[0]}:b"] and _all_reaped(forking)


def test_scan_report_is_the_same_drawn_by_the_drawing_process(small_result, monkeypatch):
    from markcal.reports.scan_report import scan_report_html
    monkeypatch.setattr(drawing, "_fork_helps", lambda: False)
    alone = scan_report_html(small_result)
    monkeypatch.setattr(drawing, "_fork_helps", lambda: True)
    assert drawing.start_drawing_process(("markcal.reports.scan_report",))
    try:
        drawn = scan_report_html(small_result)
        assert drawing._DRAWER                                                 # it did not fail
    finally:
        drawing.stop_drawing_process()
    assert drawn == alone


def test_the_scan_command_stops_its_drawing_process(small_files, tmp_path, monkeypatch):
    from markcal.pipeline.registry import run_and_write
    monkeypatch.setattr(drawing, "_fork_helps", lambda: True)
    started = []
    real = drawing.start_drawing_process
    monkeypatch.setattr(drawing, "start_drawing_process", lambda modules: started.append(modules) or real(modules))
    import markcal.pipeline.registry as registry
    monkeypatch.setattr(registry, "start_drawing_process", drawing.start_drawing_process)
    _, paths = run_and_write("scan", small_files[0], tmp_path / "out", spec_path=small_files[1])
    assert started == [("markcal.reports.scan_report",)] and not drawing._DRAWER
    assert os.path.getsize(paths["report.html"]) > 100_000
    _, paths = run_and_write("scan", small_files[0], tmp_path / "out2", spec_path=small_files[1],
                             options={"no_report": True})
    assert len(started) == 1 and "report.html" not in paths                   # no report: no drawing process


def test_a_failing_flow_stops_its_drawing_process(small_files, tmp_path, forking, monkeypatch):
    from markcal.pipeline.registry import run_and_write
    from markcal.stages.errors import MarkcalError
    monkeypatch.setattr(drawing, "_warm_up", lambda modules: None)
    bad = tmp_path / "cut.ply"
    bad.write_bytes(open(small_files[0], "rb").read()[:5000])                  # a truncated cloud
    with pytest.raises(MarkcalError, match="truncated"):
        run_and_write("scan", str(bad), tmp_path / "out", spec_path=small_files[1])
    assert not drawing._DRAWER and _all_reaped(forking)                        # started, then ended and reaped
    assert not (tmp_path / "out" / "summary.json").exists()
