"""Drawing a report's figures in other processes, so that they take a free core.

Two ways, both on Linux/macOS only (``os.fork``) and only when a core is free (:func:`_fork_helps`):

- :func:`parts_in_two` forks a child when the figures are due; it draws half of them while this
  process draws the other half. Each process imports matplotlib then (about 0.3 s).
- :func:`start_drawing_process` forks a drawing process before a flow runs: it imports matplotlib and
  the report's module while the flow computes, then waits. :func:`draw_groups`
  sends it the figures (module-level functions and picklable arguments) when they are due; it draws
  one group and a fork of itself, matplotlib already imported, the others. The flow's registration
  says whether it wants one (``registry.register(..., drawing=...)``).

A process that fails, dies or takes longer than :data:`FORK_TIMEOUT_S` is killed and its figures are
drawn here, so an error comes out here, as it would without it.
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

__all__ = ["parts_in_two", "start_drawing_process", "stop_drawing_process", "draw_groups", "draw_groups_later", "FORK_ENV"]

#: environment variable: "0" keeps every figure in this process (no drawing process, no fork); by default
#: a report's figures are drawn in other processes when a core is free (it costs CPU time: skipped when
#: no core is free)
FORK_ENV = "MARKCAL_REPORT_FORK"
#: seconds this process waits for the figures of another before drawing them itself
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
    return _in_two(here, there)


def _in_two(here, there) -> tuple:
    """:func:`parts_in_two` without asking whether forking helps."""
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
        code = 1
        try:
            os.close(r)
            figure_progress(None)
            code = 0 if _send(w, pickle.dumps([f() for f in there]), None) else 1
        except BaseException:                             # noqa: BLE001 - the parent redraws; nothing printed
            pass
        finally:
            os._exit(code)
    gc.unfreeze()
    os.close(w)
    msg = None
    try:
        mine = [f() for f in here]
        msg = _receive(r, time.monotonic() + FORK_TIMEOUT_S)
        if msg is None:                                   # failed, or stuck past the deadline
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        pid = 0
    finally:
        os.close(r)
        if pid:                                           # this process failed while the child ran
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    return mine, (pickle.loads(msg) if msg is not None else [f() for f in there])


def _draw_split(groups: list, in_two) -> list:
    """The first group drawn here, the others by ``in_two``'s child (:func:`parts_in_two` or :func:`_in_two`)."""
    if len(groups) < 2:
        return [_draw_here(g) for g in groups]
    first, rest = in_two([partial(_draw_here, groups[0])], [partial(_draw_here, g) for g in groups[1:]])
    return first + rest


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


# ----------------------------------------------------------------------------- the drawing process

#: the drawing process of this command, as [(pid, job pipe's write end, result pipe's read end)] or []
_DRAWER: list = []


def start_drawing_process(modules: tuple = ()) -> bool:
    """Fork the drawing process now, when forking helps (:func:`_fork_helps`) and none runs.

    It imports matplotlib and ``modules`` (the report's module) and draws one tiny figure (fonts) while
    the flow runs, then waits for :func:`draw_groups`. It runs at normal priority: at idle priority
    (``SCHED_IDLE``) the flow was no faster in A/B runs, and an unprivileged process could not have
    left it to draw. Call before the flow, from a process with no other threads. Returns whether it
    runs; :func:`stop_drawing_process` ends it.
    """
    if _DRAWER or not _fork_helps():
        return bool(_DRAWER)
    import gc
    jobs_r, jobs_w = os.pipe()
    results_r, results_w = os.pipe()
    gc.freeze()                                   # the collector leaves the objects both processes share alone
    try:
        pid = os.fork()
    except OSError:                               # no memory or process slot: no drawing process
        gc.unfreeze()
        for fd in (jobs_r, jobs_w, results_r, results_w):
            os.close(fd)
        return False
    if pid == 0:
        os.close(jobs_w)
        os.close(results_r)
        _serve(jobs_r, results_w, modules)        # never returns
    gc.unfreeze()
    os.close(jobs_r)
    os.close(results_w)
    os.set_blocking(jobs_w, False)               # a stuck drawer must not block the sender past its deadline
    _DRAWER.append((pid, jobs_w, results_r))
    return True


def stop_drawing_process() -> None:
    """End the drawing process (its job pipe closes; it exits) and reap it."""
    if _DRAWER:
        _end(*_DRAWER.pop(), kill=False)


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
    """The drawing process: warm up, then draw the groups of figures it is sent, until the pipe closes.

    The first group is drawn here and the others in a fork of this process (:func:`_in_two`), which has
    matplotlib imported already: one import serves both cores.
    """
    code = 0
    try:
        figure_progress(None)
        _warm_up(modules)
        while True:
            msg = _receive(jobs_r, None)
            if msg is None:
                break
            try:
                out = (True, _draw_split(pickle.loads(msg), _in_two))
            except Exception:                     # noqa: BLE001 - the caller draws them and shows the error
                out = (False, None)
            _send(results_w, pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL), None)
    except BaseException:                         # noqa: BLE001 - the caller redraws; nothing printed
        code = 1
    finally:
        os._exit(code)


def _warm_up(modules: tuple) -> None:
    import importlib

    from markcal.reports.html import new_figure, png_bytes
    for m in modules:
        importlib.import_module(m)
    fig = new_figure(2.0, 1.5)                    # loads the font and the PNG writer
    fig.subplots_adjust(left=0.3, right=0.9, bottom=0.3, top=0.8)      # all inside: drawn once, as in png_bytes
    fig.add_subplot(111).set_title("0.1 mm")
    png_bytes(fig)


def draw_groups(groups: list) -> list:
    """Draw groups of report parts; each part is ``(function, args)`` returning HTML.

    With the drawing process (:func:`start_drawing_process`), the groups are drawn there, its first
    group beside the others (:func:`_serve`); else here, the first group beside the others when
    :func:`parts_in_two` forks. What the drawing process fails to draw, or does not send within
    :data:`FORK_TIMEOUT_S`, is drawn here (a stuck process is killed).
    """
    return draw_groups_later(groups)()


def draw_groups_later(groups: list):
    """:func:`draw_groups` in two steps: the groups go to the drawing process now, and the returned
    function (call it once) collects them, so this process can do other work meanwhile."""
    def here():
        return _draw_split(groups, parts_in_two)

    if not _DRAWER:
        return here
    pid, w, r = _DRAWER[0]
    deadline = time.monotonic() + FORK_TIMEOUT_S
    sent = _send(w, pickle.dumps(groups, protocol=pickle.HIGHEST_PROTOCOL), deadline)

    def collect():
        msg = _receive(r, deadline) if sent else None
        if msg is None:                           # dead, stuck or cut off: it is not used again
            _DRAWER.clear()
            _end(pid, w, r, kill=True)
            return here()
        done, drawn = pickle.loads(msg)
        return drawn if done else [_draw_here(g) for g in groups]
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
