"""The ``markcal`` command line: one sub-command module per command family."""
from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import sys
import warnings

from markcal.pipeline.cli_common import ANSI, error_line
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


#: the module that registers each top-level command other than ``render`` (whose kinds come from every module)
COMMAND_OWNERS: dict = {"scan": "markcal.pipeline.cli_scan", "indents": "markcal.pipeline.cli_indents",
                        "selfcal": "markcal.pipeline.cli_selfcal", "pmcal": "markcal.pipeline.cli_pmcal",
                        "path": "markcal.pipeline.cli_path", "servo": "markcal.pipeline.cli_servo",
                        "grid": "markcal.pipeline.cli_grid", "export": "markcal.pipeline.cli_export",
                        "inspect": "markcal.pipeline.cli_export", "batch": "markcal.pipeline.cli_batch",
                        "drift": "markcal.pipeline.cli_pmcal"}


class _Version(argparse.Action):
    """``--version``: the installed version, looked up only when asked for (the lookup takes ~15 ms)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show markcal's version and exit"):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from markcal.pipeline.registry import markcal_version
        print(f"markcal {markcal_version()}")
        parser.exit()


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The ``markcal`` parser. Given the command line, only the module of its command is imported when the
    command is known (a command starts faster); otherwise, and for ``render`` and help, every module is."""
    from markcal.pipeline.cli_common import Parser

    ap = Parser(prog="markcal", description="Measure marked plates; write correction tables and reports. "
                                            "Exit status: 0 done, 1 bad input, 4 ran but out of tolerance "
                                            "(batch: 3 some inputs failed).")
    ap.add_argument("--version", action=_Version)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=Parser)
    rd = sub.add_parser("render", help="render synthetic instrument data with ground truth")
    rsub = rd.add_subparsers(dest="what", required=True, parser_class=Parser)
    only = COMMAND_OWNERS.get(argv[0]) if argv else None
    for name in (only,) if only else COMMAND_MODULES:
        importlib.import_module(name).register(sub, rsub)
    return ap


def _numba_cache() -> None:
    """numba caches compiled kernels beside the package; when that is read-only, use the user's cache."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if "NUMBA_CACHE_DIR" not in os.environ and not os.access(here, os.W_OK):
        os.environ["NUMBA_CACHE_DIR"] = os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "markcal", "numba")


def _report_warnings(caught, quiet: bool) -> None:
    """Library warnings (numpy, tifffile, …) once, as one line each kind, unless --quiet."""
    if quiet or not caught:
        return
    kinds = {}
    for w in caught:
        kinds.setdefault((w.category.__name__, str(w.message).splitlines()[0][:160]), 0)
        kinds[(w.category.__name__, str(w.message).splitlines()[0][:160])] += 1
    for (cat, msg), n in list(kinds.items())[:5]:
        print(f"markcal: warning: {cat}: {msg}" + (f" ({n} times)" if n > 1 else ""), file=sys.stderr)


class _LogRecords(logging.Handler):
    """Collects library log records (tifffile, igor2, …) so they are reported like warnings, once, not raw."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.records = []

    def emit(self, record):
        self.records.append(record)


def main(argv=None) -> int:
    _numba_cache()
    args = build_parser(sys.argv[1:] if argv is None else argv).parse_args(argv)
    logs = _LogRecords()
    root = logging.getLogger()
    root.addHandler(logs)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for developer_only in (DeprecationWarning, PendingDeprecationWarning, FutureWarning):
            warnings.simplefilter("ignore", developer_only)
        try:
            return _run(args)
        finally:
            root.removeHandler(logs)
            caught = list(caught) + [warnings.WarningMessage(ANSI.sub("", r.getMessage()), UserWarning,
                                                             r.pathname, r.lineno) for r in logs.records]
            _report_warnings(caught, bool(getattr(args, "quiet", False)))


def _run(args) -> int:
    from markcal.reports.files import abort_unfinished_outputs
    ok = False
    try:
        code = args.func(args)
        ok = True
        return code
    except MarkcalError as exc:
        error_line(str(exc))
        return 1
    except KeyboardInterrupt:
        print("markcal: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:              # a folder that cannot be written, a full disk: one line, no traceback
        where = f"{os.fsdecode(exc.filename)}: " if getattr(exc, "filename", None) else ""
        error_line(f"{where}{exc.strerror or exc}")
        return 1
    except UnicodeError as exc:         # a name or text no codec can hold
        error_line(f"text that cannot be encoded or decoded ({exc})")
        return 1
    except MemoryError:
        error_line("out of memory: the input is larger than this machine can hold")
        return 1
    except Exception:                   # a bug: keep the traceback, say so
        print("markcal: internal error (a bug, not your input's fault as far as markcal knows): please report it "
              "with the command line and the traceback below", file=sys.stderr)
        raise
    finally:
        if not ok:
            abort_unfinished_outputs()


#: youngest-generation threshold of the collector in a command's own process (Python's default is 700)
GC_YOUNG_THRESHOLD = 20_000


def entry() -> None:
    """The ``markcal`` command: :func:`main` in a process of its own, which ends with it.

    The cyclic garbage collector is tuned for a short process. The imports leave about 175,000 objects
    (numba, scipy, matplotlib) that every full collection walks; with the default thresholds a scan
    spends about 0.25 s CPU in collections while it runs, and the interpreter's shutdown walks them all
    again (about 0.35 s). Here young collections are rarer, and the survivors are frozen at the end
    (``gc.freeze``), so shutdown does not walk them. Reference counting frees memory as before; only
    cyclic garbage waits a little longer. :func:`main` itself, as tests and other programs call it,
    leaves the collector as it is.
    """
    gc.set_threshold(GC_YOUNG_THRESHOLD, *gc.get_threshold()[1:])
    code = main()
    sys.stdout.flush()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    entry()
