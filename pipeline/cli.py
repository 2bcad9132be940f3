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
    from markcal.pipeline.cli_common import Parser
    from markcal.pipeline.registry import markcal_version

    ap = Parser(prog="markcal", description="Measure marked plates; write correction tables and reports. "
                                            "Exit status: 0 done, 1 bad input, 4 ran but out of tolerance "
                                            "(batch: 3 some inputs failed).")
    ap.add_argument("--version", action="version", version=f"markcal {markcal_version()}")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=Parser)
    rd = sub.add_parser("render", help="render synthetic instrument data with ground truth")
    rsub = rd.add_subparsers(dest="what", required=True, parser_class=Parser)
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
    except OSError as exc:              # a folder that cannot be written, a full disk: one line, no traceback
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"markcal: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print("markcal: error: out of memory: the input is larger than this machine can hold", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
