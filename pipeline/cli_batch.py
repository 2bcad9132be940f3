"""``markcal batch`` and ``markcal render batch``."""
from __future__ import annotations

import os
import sys
import threading
import time

#: seconds without a line before the batch says it is still working; then twice as long each time, up to
#: ``HEARTBEAT_MAX_S`` (a long batch logged to a file gets a line every 30 s, not every 2 s)
HEARTBEAT_S = 1.5
HEARTBEAT_MAX_S = 30.0


class BatchProgress:
    """Files done / failed / left, rate and ETA: a bar on a terminal, log lines otherwise."""

    def __init__(self, stream=None, quiet: bool = False, tty: bool | None = None):
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = self.stream.isatty() if tty is None else tty
        self.t0 = time.perf_counter()
        self.total = self.todo = self.reused = 0
        self._bar_shown = False
        self._lock = threading.Lock()
        self._last = self.t0                  # when the last line was printed
        self._gap = HEARTBEAT_S
        self._running = 0
        self._stop = threading.Event()
        self._beat = None

    def _line(self, msg: str, beat: bool = False) -> None:
        if self.quiet:
            return
        with self._lock:
            if self._bar_shown:
                self.stream.write("\r\033[K")
                self._bar_shown = False
            print(f"[{time.perf_counter() - self.t0:7.1f} s] {msg}", file=self.stream, flush=True)
            self._last = time.perf_counter()
            self._gap = min(2 * self._gap, HEARTBEAT_MAX_S) if beat else HEARTBEAT_S

    def _heartbeat(self) -> None:
        """While inputs run (or the index is written): a line when none came for a while."""
        while not self._stop.wait(0.25):
            if time.perf_counter() - self._last >= self._gap:
                left = self._running
                self._line(f"working: {left} input{'s' if left != 1 else ''} left, "
                           f"{time.perf_counter() - self._last:.0f} s since the last line" if left else
                           "writing the batch index", beat=True)

    def start(self, total, todo, reused, ignored) -> None:
        self.total, self.todo, self.reused = total, todo, reused
        self._running = todo
        self.t_work = time.perf_counter()
        if not self.quiet and self._beat is None:
            self._beat = threading.Thread(target=self._heartbeat, name="markcal-batch-heartbeat", daemon=True)
            self._beat.start()
        self._line(f"{total} inputs: {todo} to process, {reused} already done (outputs up to date)"
                   + (f"; {len(ignored)} files not recognised: {', '.join(ignored[:5])}"
                      + (" ..." if len(ignored) > 5 else "") if ignored else ""))

    def update(self, rec, done, failed, left) -> None:
        self._running = left
        if self.quiet:
            return
        ran = done - self.reused
        el = time.perf_counter() - self.t_work
        rate = ran / el if el > 0 else 0.0
        eta = left / rate if rate > 0 else float("nan")
        eta_s = time.strftime("%H:%M:%S", time.gmtime(eta)) if eta == eta else "--:--:--"
        if rec["status"] == "error":
            self._line(f"FAILED {rec['name']} ({rec['flow']}): {rec['reason']}")
        elif not self.tty:
            extra = f": {rec['failed_checks']}" if rec["failed_checks"] else ""
            self._line(f"{done}/{self.total} {rec['status']:5s} {rec['name']} ({rec['flow']}, "
                       f"{rec['runtime_s']:.1f} s){extra}")
        if self.tty:
            w = 30
            k = int(round(w * done / max(self.total, 1)))
            self.stream.write(f"\r\033[K[{'#' * k}{'.' * (w - k)}] {done}/{self.total} done, {failed} failed, "
                              f"{left} left, {rate:.2f}/s, ETA {eta_s}")
            self.stream.flush()
            self._bar_shown = True
            self._last = time.perf_counter()
        elif left == 0 or done % 10 == 0:
            self._line(f"progress: {done} done, {failed} failed, {left} left, {rate:.2f} inputs/s, ETA {eta_s}")

    def finish(self, msg: str) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join()
        if self._bar_shown and not self.quiet:
            self.stream.write("\n")
            self._bar_shown = False
        self._line(msg)


def cmd_batch(args) -> int:
    from markcal.pipeline.batch import run_batch
    from markcal.reports.batch_index import write_batch_index

    prog = BatchProgress(quiet=args.quiet)
    res = run_batch(args.input_dir, args.out, config_path=args.config, workers=args.workers,
                    scheduler=args.scheduler, force=args.force, progress=prog.update, on_start=prog.start)
    paths = write_batch_index(res, args.out)
    prog.finish(f"{len(res.records)} inputs: {res.count('pass')} pass, {res.count('fail')} out of tolerance, "
                f"{res.count('done')} done (no tolerance), {res.count('error')} failed to process; "
                f"{res.n_run} run, {res.n_reused} reused, {res.wall_s:.1f} s")
    for r in res.records:
        if r["status"] == "error":
            print(f"markcal: failed: {r['name']} ({r['flow']}): {r['reason']}", file=sys.stderr)
    print(os.path.abspath(paths["index.html"]))
    return res.exit_code


def cmd_render_batch(args) -> int:
    from markcal.fixtures.batch_mix import MixOptions, render_batch_mix
    from markcal.pipeline.progress import progress

    say = progress(args.quiet)
    opts = MixOptions(n_scan=args.scans, n_selfcal=args.sessions, n_servo=args.traces, n_broken=args.broken,
                      n_afm=args.maps, n_om=args.micrographs)
    say(f"rendering a mixed batch: {args.scans} plates, {args.sessions} selfcal sessions, {args.traces} traces, "
        f"{args.maps} AFM maps, {args.micrographs} micrographs, {args.broken} broken, seed {args.seed}")
    render_batch_mix(args.out, args.seed, opts, say=say)
    print(os.path.abspath(args.out))
    return 0


def register(sub, render_sub) -> None:
    """Add ``batch`` to the top-level commands and ``batch`` to ``render``."""
    b = sub.add_parser("batch", help="run the right flow on every input in a folder; write an index report")
    b.add_argument("input_dir", help="folder of inputs (clouds + plate.toml, selfcal session folders, servo traces, ...)")
    b.add_argument("--out", required=True, help="output folder: one sub-folder per input + index.html")
    b.add_argument("--config", help="batch.toml: per-flow options and pass/fail tolerances")
    b.add_argument("--workers", type=int, default=max(1, os.cpu_count() or 1),
                   help="local worker processes (default: the number of cores)")
    b.add_argument("--scheduler", help="Dask scheduler address (tcp://host:port): run on that cluster")
    b.add_argument("--force", action="store_true", help="redo inputs whose outputs are already up to date")
    b.add_argument("--quiet", action="store_true", help="no progress on stderr")
    b.set_defaults(func=cmd_batch)

    r = render_sub.add_parser("batch", help="a small mixed batch of inputs (plates, sessions, traces, broken files)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", required=True)
    r.add_argument("--scans", type=int, default=3, help="scan plates")
    r.add_argument("--sessions", type=int, default=2, help="selfcal session folders")
    r.add_argument("--traces", type=int, default=3, help="servo encoder traces")
    r.add_argument("--maps", type=int, default=0, help="AFM height maps of indentation arrays (float TIFF)")
    r.add_argument("--micrographs", type=int, default=0, help="OM micrographs of indentation arrays (integer TIFF)")
    r.add_argument("--broken", type=int, default=1, help="broken inputs")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=cmd_render_batch)
