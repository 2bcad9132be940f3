"""Drawing a report's figures in other processes, so that they take a free core.

Two ways, both on Linux/macOS only (``os.fork``) and only when a core is free (:func:`_fork_helps`):

- :func:`parts_in_two` forks a child when the figures are due; it draws half of them while this
  process draws the other half. Each process imports matplotlib then (about 0.3 s).
- :func:`start_drawing_processes` forks drawing processes before a flow runs: they import matplotlib
  and the report's module while the flow computes, then wait. :func:`draw_groups` sends them the
  figures (module-level functions and picklable arguments) when they are due. The flow's registration
  says whether it wants them (``registry.register(..., drawing=...)``).

A drawing process that fails, dies or takes longer than :data:`FORK_TIMEOUT_S` is killed and its
figures are drawn here, so an error comes out here, as it would without it.
"""
from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import time
from functools import partial

from markcal.reports.html import figure_progress

__all__ = ["parts_in_two", "start_drawing_processes", "stop_drawing_processes", "draw_groups", "draw_groups_later",
           "FORK_ENV"]

#: environment variable: "0" keeps every figure in this process; by default a report draws half of its
#: figures in a forked process when a core is free (the 5.4 M-point scan: 3.8 s instead of 4.2 s wall at
#: load 1.9 on 2 cores; it costs 0.15-0.4 s CPU more, so it is skipped when no core is free)
FORK_ENV = "MARKCAL_REPORT_FORK"
#: seconds the parent waits for the child's figures before drawing them itself
FORK_TIMEOUT_S = 120.0


def parts_in_two(here, there) -> tuple:
    """Evaluate two lists of report parts (callables returning HTML): ``there`` in a forked child
    process while this one does ``here``, when that can help; else both here, one after the other.

    The child only draws and sends its strings back through a pipe, then ends (``os._exit``); the parent
    always reaps it. A child that fails, sends nothing or takes longer than :data:`FORK_TIMEOUT_S`
    is killed and its parts are drawn here, so an error comes out here, as it would without the
    child. Not with ``MARKCAL_REPORT_FORK=0``, one core, a busy machine
    (as many runnable tasks as cores, :func:`_busy_cores`) or other Python threads running.
    """
    if not _fork_helps():
        return [f() for f in here], [f() for f in there]
    import pickle
    import select
    import signal
    import gc
    r, w = os.pipe()
    gc.freeze()                  # the collector leaves the objects both processes share alone: fewer page copies
    try:
        pid = os.fork()
    except OSError:              # no memory or process slot for a child: all here
        gc.unfreeze()
        os.close(r)
        os.close(w)
        return [f() for f in here], [f() for f in there]
    if pid == 0:                                          # the child: draw, send, end
        code = 0
        try:
            os.close(r)
            figure_progress(None)
            data = pickle.dumps([f() for f in there])
            with os.fdopen(w, "wb") as fh:
                fh.write(data)
        except BaseException:                             # noqa: BLE001 - the parent redraws; nothing printed
            code = 1
        finally:
            os._exit(code)
    gc.unfreeze()
    os.close(w)
    theirs = None
    try:
        mine = [f() for f in here]
        chunks, deadline = [], time.monotonic() + FORK_TIMEOUT_S
        while time.monotonic() < deadline:
            if select.select([r], [], [], max(deadline - time.monotonic(), 0.0))[0]:
                chunk = os.read(r, 1 << 20)
                if not chunk:
                    break
                chunks.append(chunk)
        else:
            os.kill(pid, signal.SIGKILL)
            chunks = []
        _, status = os.waitpid(pid, 0)
        pid = 0
        if chunks and os.waitstatus_to_exitcode(status) == 0:
            theirs = pickle.loads(b"".join(chunks))
    finally:
        os.close(r)
        if pid:                                           # this process failed while the child ran
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    if theirs is None:
        theirs = [f() for f in there]
    return mine, theirs


def _fork_helps() -> bool:
    import threading
    cores = os.cpu_count() or 1
    return (hasattr(os, "fork") and cores > 1 and os.environ.get(FORK_ENV, "1") != "0"
            and threading.active_count() == 1 and _busy_cores() < cores)


#: samples of the runnable count, 1 ms apart, that :func:`_busy_cores` takes
BUSY_SAMPLES = 5


def _busy_cores() -> float:
    """Cores busy now: this process plus the runnable tasks of other processes (Linux ``/proc``), else the
    1-minute load.

    The 1-minute load remembers the last minute (a command run right after another sees its load);
    the runnable count says whether a core is free at this moment (the fewest of :data:`BUSY_SAMPLES`).
    This process's own threads are not counted: a BLAS or OpenCV worker still spinning after its last
    call is no other work.
    """
    try:
        seen = []
        for _ in range(BUSY_SAMPLES):          # the fewest seen: a kernel thread waking for a moment is no load
            with open("/proc/loadavg", encoding="ascii") as fh:
                running = float(fh.read().split()[3].split("/")[0])
            seen.append(running - max(_own_running_threads(), 1) + 1)
            time.sleep(0.001)
        return min(seen)
    except (OSError, IndexError, ValueError):
        return os.getloadavg()[0]


def _own_running_threads() -> int:
    """This process's threads that are runnable now (``/proc/self/task/*/stat`` state R)."""
    own = 0
    for tid in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{tid}/stat", encoding="ascii", errors="replace") as fh:
            stat = fh.read()
        own += stat[stat.rindex(")") + 2:][:1] == "R"
    return own


# ----------------------------------------------------------------------------- drawing processes

#: the drawing processes of this command: (pid, job pipe's write end, result pipe's read end)
_DRAWERS: list = []


def start_drawing_processes(n: int, modules: tuple = ()) -> int:
    """Fork ``n`` drawing processes now, when forking helps (:func:`_fork_helps`); none when some run.

    Each imports matplotlib and ``modules`` (the report's module), draws one tiny figure (fonts) and
    waits for :func:`draw_groups`. Call before the flow, from a process with no other threads.
    Returns how many run; :func:`stop_drawing_processes` ends them.
    """
    if _DRAWERS or n <= 0 or not _fork_helps():
        return len(_DRAWERS)
    import gc
    gc.freeze()                                   # the collector leaves the objects both processes share alone
    try:
        for _ in range(n):
            if not _fork_drawer(modules):
                break
    finally:
        gc.unfreeze()
    return len(_DRAWERS)


def _fork_drawer(modules: tuple) -> bool:
    """Fork one drawing process; False when the system has no process or memory for it."""
    jobs_r, jobs_w = os.pipe()
    results_r, results_w = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        for fd in (jobs_r, jobs_w, results_r, results_w):
            os.close(fd)
        return False
    if pid == 0:
        os.close(jobs_w)
        os.close(results_r)
        for _pid, w, r in _DRAWERS:              # the siblings' ends: their EOF must not wait for this one
            os.close(w)
            os.close(r)
        _serve(jobs_r, results_w, modules)       # never returns
    os.close(jobs_r)
    os.close(results_w)
    os.set_blocking(jobs_w, False)               # a stuck drawer must not block the sender past its deadline
    _DRAWERS.append((pid, jobs_w, results_r))
    return True


def stop_drawing_processes() -> None:
    """End the drawing processes (their job pipe closes; they exit) and reap them."""
    while _DRAWERS:
        pid, w, r = _DRAWERS.pop()
        _end(pid, w, r, kill=False)


def _end(pid: int, w: int, r: int, kill: bool) -> None:
    for fd in (w, r):
        os.close(fd)
    if kill:
        os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 5.0
    while os.waitpid(pid, os.WNOHANG)[0] == 0:   # an idle drawer exits at once on the closed pipe
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return
        time.sleep(0.002)


def _serve(jobs_r: int, results_w: int, modules: tuple) -> None:
    """A drawing process: warm up, then draw each group of figures it is sent, until the pipe closes."""
    code = 0
    try:
        figure_progress(None)
        _idle_priority(True)                      # the flow's own work comes first while it runs
        _warm_up(modules)
        _idle_priority(False)
        while True:
            msg = _receive(jobs_r, None)
            if msg is None:
                break
            try:
                out = (True, [fn(*args) for fn, args in pickle.loads(msg)])
            except Exception:                     # noqa: BLE001 - the parent draws them and shows the error
                out = (False, None)
            _send(results_w, pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL), None)
    except BaseException:                         # noqa: BLE001 - the parent redraws; nothing printed
        code = 1
    finally:
        os._exit(code)


def _idle_priority(idle: bool) -> None:
    """Run only on otherwise idle cores (``SCHED_IDLE``), or normally again where that is allowed."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE if idle else os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):             # not Linux, or not allowed (unprivileged: it stays idle)
        pass


def _warm_up(modules: tuple) -> None:
    import importlib

    from markcal.reports.html import new_figure, png_bytes
    for m in modules:
        importlib.import_module(m)
    fig = new_figure(1.0, 1.0)                    # loads the font and the PNG writer
    fig.add_subplot(111).set_title("0.1 mm")
    png_bytes(fig)


def draw_groups(groups: list) -> list:
    """Draw groups of report parts; each part is ``(function, args)`` returning HTML.

    With as many drawing processes as groups (:func:`start_drawing_processes`), each group is drawn in
    one of them, side by side. Else two groups go through :func:`parts_in_two`, and any other number is
    drawn here. A group whose process fails or exceeds :data:`FORK_TIMEOUT_S` is drawn here.
    """
    return draw_groups_later(groups)()


def draw_groups_later(groups: list):
    """:func:`draw_groups` in two steps: the groups go to the drawing processes now, and the returned
    function (call it once) collects them, so this process can do other work meanwhile."""
    if len(_DRAWERS) < len(groups):
        def here():
            if len(groups) == 2:
                return list(parts_in_two(*[[partial(fn, *args) for fn, args in g] for g in groups]))
            return [_draw_here(g) for g in groups]
        return here
    deadline = time.monotonic() + FORK_TIMEOUT_S
    drawers = _DRAWERS[:len(groups)]
    sent = [_send(w, pickle.dumps(g, protocol=pickle.HIGHEST_PROTOCOL), deadline)
            for g, (_pid, w, _r) in zip(groups, drawers)]

    def collect():
        out = []
        for g, ok, (pid, w, r) in zip(groups, sent, drawers):
            msg = _receive(r, deadline) if ok else None
            done, drawn = pickle.loads(msg) if msg is not None else (False, None)
            if msg is None:                       # dead, stuck or cut off: it is not used again
                _DRAWERS.remove((pid, w, r))
                _end(pid, w, r, kill=True)
            out.append(drawn if done else _draw_here(g))
        return out
    return collect


def _draw_here(group: list) -> list:
    return [fn(*args) for fn, args in group]


_HEADER = struct.Struct("<Q")


def _send(fd: int, data: bytes, deadline: float | None) -> bool:
    """Write a length-prefixed message; False when the reader is gone or the deadline passes."""
    view = memoryview(_HEADER.pack(len(data)) + data)
    try:
        while view:
            if deadline is not None and not select.select([], [fd], [], max(deadline - time.monotonic(), 0))[1]:
                return False
            try:
                view = view[os.write(fd, view[:1 << 16]):]
            except BlockingIOError:               # the pipe is full: wait for the reader again
                continue
    except OSError:                               # broken pipe: the reader died
        return False
    return True


def _receive(fd: int, deadline: float | None) -> bytes | None:
    """Read one length-prefixed message; None at end of file, on a short message or past the deadline."""
    head = _read_exactly(fd, _HEADER.size, deadline)
    if head is None:
        return None
    return _read_exactly(fd, _HEADER.unpack(head)[0], deadline)


def _read_exactly(fd: int, n: int, deadline: float | None) -> bytes | None:
    chunks, left = [], n
    while left:
        if deadline is not None and not select.select([fd], [], [], max(deadline - time.monotonic(), 0))[0]:
            return None
        chunk = os.read(fd, min(left, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)
