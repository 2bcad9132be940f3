"""The ``markcal`` command line: one sub-command module per command family."""
from __future__ import annotations

import argparse
import importlib
import sys

from markcal.stages.errors import MarkcalError

#: modules that add their own sub-commands, in the order of the pipeline: each has
#: ``register(sub, render_sub)`` taking the top-level and the ``render`` sub-parser collections.
COMMAND_MODULES: tuple = (
    "markcal.pipeline.cli_scan",
    "markcal.pipeline.cli_indents",
    "markcal.pipeline.cli_selfcal",
    "markcal.pipeline.cli_pmcal",
    "markcal.pipeline.cli_path",
    "markcal.pipeline.cli_servo",
    "markcal.pipeline.cli_grid",
    "markcal.pipeline.cli_export",
    "markcal.pipeline.cli_batch",
)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="markcal", description="Measure marked plates; write correction tables and reports.")
    sub = ap.add_subparsers(dest="command", required=True)
    rd = sub.add_parser("render", help="render synthetic instrument data with ground truth")
    rsub = rd.add_subparsers(dest="what", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub, rsub)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except MarkcalError as exc:
        print(f"markcal: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("markcal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
