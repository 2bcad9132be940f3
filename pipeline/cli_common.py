"""What every flow command shares on the command line: tolerances, traceability, help layout, exit status."""
from __future__ import annotations

import argparse
import re
import sys

#: ANSI escape sequences (colour codes) a library may put in a message
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
#: control characters and bidirectional overrides (a file name holding U+202E turns the line around)
_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def error_line(text: str) -> None:
    """``markcal: error: TEXT`` as one line: no ANSI colour codes, no line breaks, no unprintable bytes."""
    text = _UNSAFE.sub(lambda m: f"\\u{ord(m.group()):04x}", " ".join(ANSI.sub("", text).split()))
    print(f"markcal: error: {text}".encode("utf-8", "backslashreplace").decode("utf-8"), file=sys.stderr)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default (except None / False, whose meaning the help text states)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or action.default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """An argument parser whose help shows the defaults."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        """A bad command line is bad input: one line on stderr, exit status 1 (not argparse's usage block)."""
        error_line(f"{self.prog}: {message} (see {self.prog} --help)")
        raise SystemExit(1)

    def add_argument(self, *args, **kwargs):
        """As argparse's; ``--out`` also answers to ``-o``; an option with a default but no help shows its default."""
        if args == ("--out",):
            args = ("-o", "--out")
        d = kwargs.get("default")
        if not kwargs.get("help") and not (d is None or d is False or d is argparse.SUPPRESS) \
                and args and args[0].startswith("-"):
            kwargs["help"] = "default: %(default)s"
        return super().add_argument(*args, **kwargs)


class _ScaledStore(argparse.Action):
    """Store ``value * factor`` (an old spelling in other units than the current option)."""

    def __init__(self, option_strings, dest, factor=1.0, **kwargs):
        self.factor = factor
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values * self.factor)


def add_alias(p, old: str, new: str, factor: float = 1.0, type=float, dest: str | None = None) -> None:
    """Accept ``old`` as a hidden spelling of option ``new`` (not listed in ``--help``).

    ``factor`` converts a value given in the old option's unit to the new option's unit
    (e.g. ``--noise-nm`` 5 is ``--noise-um`` 0.005: factor 1e-3).
    """
    dest = dest or new.lstrip("-").replace("-", "_")
    if factor == 1.0:
        p.add_argument(old, dest=dest, type=type, default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    else:
        p.add_argument(old, dest=dest, type=type, default=argparse.SUPPRESS, help=argparse.SUPPRESS,
                       action=_ScaledStore, factor=factor)


def add_run_options(p) -> None:
    """``--tol KEY<=VALUE`` (repeatable) and the traceability fields of a flow command."""
    p.add_argument("--tol", action="append", default=[], metavar="KEY<=VALUE",
                   help="pass/fail limit on a summary figure, e.g. rms_mm<=0.05 (repeatable; overrides the "
                        "flow's default limits; exit status 4 when out of tolerance)")
    add_context_options(p)


#: traceability fields a user may give on any command that writes a report
CONTEXT_FIELDS = ("machine", "lens", "operator", "note")


def add_context_options(p) -> None:
    """``--machine``, ``--lens``, ``--operator``, ``--note``: recorded in summary.json and the report."""
    for k in CONTEXT_FIELDS:
        p.add_argument(f"--{k}", metavar="TEXT", help=f"{k} recorded in summary.json and the report")


def context_of(args) -> dict:
    """The traceability fields given on the command line (None when absent)."""
    return {k: getattr(args, k, None) for k in CONTEXT_FIELDS}


def run_options(args) -> dict:
    """``tolerances`` and ``context`` keyword arguments of ``run_and_write`` from parsed arguments."""
    from markcal.stages.verdict import parse_tolerance
    tolerances = dict(parse_tolerance(t) for t in getattr(args, "tol", []) or [])
    return {"tolerances": tolerances, "context": context_of(args)}


class LazyChoices:
    """``choices`` for an option whose allowed values live in a heavy module: loaded on first use.

    ``markcal --help`` and the other commands then never import that module.
    """

    def __init__(self, load):
        self._load, self._values = load, None

    def _get(self) -> list:
        if self._values is None:
            self._values = list(self._load())
        return self._values

    def __contains__(self, value) -> bool:
        return value in self._get()

    def __iter__(self):
        return iter(self._get())

    def __len__(self) -> int:
        return len(self._get())


def _attr(module: str, name: str):
    import importlib
    return getattr(importlib.import_module(module), name)


def choices_from(module: str, name: str, extra=()) -> LazyChoices:
    """Lazy choices: ``module.name`` (an iterable of names) followed by ``extra``."""
    return LazyChoices(lambda: [*_attr(module, name), *extra])
