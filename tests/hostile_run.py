"""Run one ``markcal`` command as a hostile user would, in a forked child under resource limits (issue 17).

The child is forked from the test process (markcal already imported: no 2 s start-up per case), gets an
address-space limit of its current size + ``AS_HEADROOM`` (about 1.5 GiB), a CPU limit and a wall alarm
(a hang is killed, not waited for), runs ``main(argv)`` with stderr and stdout in files and exits with its
status. The parent reads the exit status and the child's own CPU time and peak RSS (``os.wait4``).
"""
from __future__ import annotations

import math
import os
import resource
import signal
import sys
from dataclasses import dataclass

#: extra address space the child may map beyond what it holds at the fork
AS_HEADROOM = 3 * 2 ** 29           # 1.5 GiB
#: CPU seconds before the kernel kills a child (a hang); the goal is 5 s
CPU_KILL_S = 30
#: wall seconds before the alarm kills a child blocked on I/O (a FIFO)
WALL_KILL_S = 60


@dataclass(frozen=True)
class Outcome:
    """Exit code (negative: killed by that signal), stderr lines, stdout, child CPU s, peak RSS growth (bytes)."""
    code: int
    err: list
    out: str
    cpu_s: float
    rss_growth_b: int


def _status_b(key: str) -> int:
    """A size line of /proc/self/status (``VmSize``, ``VmRSS``) in bytes."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return 0


def run(argv, tmp_path, env=None) -> Outcome:
    """Run ``markcal argv`` in a forked, limited child; return what happened."""
    from markcal.pipeline.cli import main

    errf, outf = os.path.join(tmp_path, ".hostile_err"), os.path.join(tmp_path, ".hostile_out")
    sys.stdout.flush()
    sys.stderr.flush()
    rss0 = _status_b("VmRSS")
    pid = os.fork()
    if pid == 0:                                   # child
        code = 70
        try:
            limit = _status_b("VmSize") + AS_HEADROOM
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            resource.setrlimit(resource.RLIMIT_CPU, (CPU_KILL_S, CPU_KILL_S + 5))
            signal.alarm(WALL_KILL_S)
            fd_e = os.open(errf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            fd_o = os.open(outf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            os.dup2(fd_e, 2)
            os.dup2(fd_o, 1)
            sys.stderr = os.fdopen(2, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
            sys.stdout = os.fdopen(1, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
            for k, v in (env or {}).items():
                os.environ[k] = v
            try:
                code = main([os.fsdecode(a) if isinstance(a, bytes) else str(a) for a in argv])
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 2
            except BaseException:                  # a bug: show it in the test's failure message
                import traceback
                traceback.print_exc()
                code = 99
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(code if isinstance(code, int) else 70)
    _, status, ru = os.wait4(pid, 0)
    code = os.waitstatus_to_exitcode(status)
    with open(errf, encoding="utf-8", errors="replace") as fh:
        err = [line for line in fh.read().splitlines() if line.strip()]
    with open(outf, encoding="utf-8", errors="replace") as fh:
        out = fh.read()
    os.remove(errf)
    os.remove(outf)
    return Outcome(code, err, out, ru.ru_utime + ru.ru_stime, max(0, ru.ru_maxrss * 1024 - rss0))


def listing(folder) -> dict:
    """Every file under ``folder`` -> (size, mtime_ns), to tell that nothing was written or changed."""
    out = {}
    for root, _, files in os.walk(folder):
        for f in files:
            if f.startswith(".hostile_"):
                continue
            p = os.path.join(root, f)
            st = os.lstat(p)
            out[os.path.relpath(p, folder)] = (st.st_size, st.st_mtime_ns)
    return out


def assert_refused(o: Outcome, *needles, max_cpu_s: float = 5.0, max_rss_growth_b: int = 2 ** 30) -> None:
    """One line ``markcal: error: …`` holding every needle, exit 1, within the CPU and memory goals."""
    assert o.code == 1, (o.code, o.err[-15:])
    assert len(o.err) == 1, o.err[-15:]
    line = o.err[0]
    assert line.startswith("markcal: error: "), line
    assert "\x1b[" not in line, line
    for n in needles:
        assert n in line, (n, line)
    assert o.cpu_s < max_cpu_s, f"{o.cpu_s:.1f} CPU s: {line}"
    assert o.rss_growth_b < max_rss_growth_b, f"{o.rss_growth_b / 2 ** 20:.0f} MiB: {line}"


def finite_text(text: str) -> bool:
    """True when no nan/inf token (or a controller's int32 minimum) appears in a text output."""
    import re
    return not re.search(r"(?i)(?<![a-z])(nan|-?inf(inity)?)(?![a-z])|-2147483648", text)


def huge(x: float) -> bool:
    return not math.isfinite(x) or abs(x) > 1e12
