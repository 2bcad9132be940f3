"""Progress lines on stderr for the single commands."""
from __future__ import annotations

import sys
import time


def progress(quiet: bool):
    """A ``say(msg)`` function printing ``[  12.3 s] msg`` on stderr (nothing when ``quiet``).

    It also receives the report writers' ``report: N figures drawn`` lines of this thread
    (:func:`markcal.reports.html.figure_progress`), so no command stays silent while its report
    is drawn.
    """
    from markcal.reports.html import figure_progress
    t0 = time.perf_counter()

    def say(msg: str) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)
    figure_progress(None if quiet else say)
    return say
