"""Compare two output trees (e.g. the demo batch before and after a refactor) up to paths and run times.

    python benchmarks/compare_outputs.py OLD_DIR NEW_DIR

Identical files pass. Otherwise: the new tree's own path is replaced by the old one's; JSON is
compared without run-time keys (``runtime*``, ``*_training_s``, ``wall_s``, ``date_utc``); other
text is compared line by line with decimal numbers masked, and lines that still differ are printed.
Exit status 1 when any file differs beyond that (or is missing).
"""
from __future__ import annotations

import json
import os
import re
import sys

NUMBER = re.compile(r"\d+\.\d+")
RUNTIME_KEY = re.compile(r"runtime|_training_s$|^wall_s$|^date_utc$|^command$")


def _strip(o):
    if isinstance(o, dict):
        return {k: _strip(v) for k, v in o.items() if not RUNTIME_KEY.search(k)}
    if isinstance(o, list):
        return [_strip(v) for v in o]
    return o


def compare(old: str, new: str) -> int:
    bad = 0
    for root, _, files in os.walk(old):
        for f in sorted(files):
            pa = os.path.join(root, f)
            pb = os.path.join(new, os.path.relpath(pa, old))
            if not os.path.exists(pb):
                print(f"missing in {new}: {os.path.relpath(pa, old)}")
                bad += 1
                continue
            a = open(pa, "rb").read()
            b = open(pb, "rb").read().replace(os.path.abspath(new).encode(), os.path.abspath(old).encode())
            if a == b:
                continue
            try:
                ta, tb = a.decode(), b.decode()
            except UnicodeDecodeError:
                print(f"binary files differ: {pa}")
                bad += 1
                continue
            if f.endswith(".json"):
                try:
                    if _strip(json.loads(ta)) == _strip(json.loads(tb)):
                        continue
                except ValueError:
                    pass
            la, lb = ta.splitlines(), tb.splitlines()
            diff = [(x, y) for x, y in zip(la, lb) if NUMBER.sub("#", x) != NUMBER.sub("#", y)]
            if len(la) != len(lb) or diff:
                bad += 1
                print(f"{os.path.relpath(pa, old)}: {len(diff)} lines differ beyond numbers"
                      + ("" if len(la) == len(lb) else f", {len(la)} vs {len(lb)} lines"))
                for x, y in diff[:3]:
                    print(f"  - {x[:200]}\n  + {y[:200]}")
    print(f"{bad} files differ beyond paths and run times")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(compare(sys.argv[1], sys.argv[2]))
