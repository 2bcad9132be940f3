"""Progress lines on stderr for the single commands."""
from __future__ import annotations

import sys
import time


def progress(quiet: bool):
    """A ``say(msg)`` function printing ``[  12.3 s] msg`` on stderr (nothing when ``quiet``)."""
    t0 = time.perf_counter()

    def say(msg: str) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)
    return say
