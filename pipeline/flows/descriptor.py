"""What every flow module declares about itself: one :class:`FlowDescriptor`.

The CLI and the batch runner use it to recognise inputs, fill in options, run
the flow, show its key figures with units, apply tolerances and plot trends.
A flow module exports ``FLOW``; the writer of its files lives in ``reports/``
and is paired with it by one line in :mod:`markcal.pipeline.registry`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Callable

from markcal.stages.errors import MarkcalError


@dataclass(frozen=True)
class Figure:
    """A key figure of a flow's summary: summary key, label and unit."""

    key: str
    label: str
    unit: str = ""

    @property
    def caption(self) -> str:
        """``label, unit`` (as plot axes show it)."""
        return f"{self.label}, {self.unit}" if self.unit else self.label


@dataclass(frozen=True)
class FlowDescriptor:
    """How a flow is recognised, configured, run and judged.

    Attributes
    ----------
    name : str
        The command's name (``markcal NAME``).
    help : str
        One line for ``--help`` and the docs.
    claims : callable
        ``claims(path) -> bool``: is this file (folder when ``folder``) an input.
    run : callable
        ``run(input_path, spec_path, options, progress) -> result``; the result
        has a ``summary`` dict. ``options`` holds every key of :attr:`options`.
    folder : bool
        An input is a folder (a session) rather than a file.
    spec_name : str, optional
        Default spec file in the input's folder; ``<stem>.toml`` beside the input wins.
    needs_spec : bool
        An input without a spec cannot be processed.
    options : dict
        Option name (CLI spelling with ``_``) -> default value (its type is the option's type).
    key_figures : tuple of Figure
        Summary keys shown in the batch index and summary.csv, with labels and units.
    tolerances : dict
        Default pass/fail limits, ``max_<key>`` / ``min_<key>`` -> number.
    tolerances_by_kind : dict
        Defaults that replace :attr:`tolerances` for a summary whose ``kind`` is a key here
        (a scan's validation plate is judged on other figures than a calibration plate).
    trends : tuple of str
        Key figures plotted across inputs in the batch index (the first is the "main figure").
    cost : float
        Rough relative run time per input (the batch starts the longest first).
    validate_options : callable, optional
        ``validate_options(options) -> None``: raises a MarkcalError naming the option
        when a value is bad (the flow's own option parsing; ``options`` holds every key).
        The batch calls it on every flow's batch.toml section before any work.
    """

    name: str
    help: str
    claims: Callable
    run: Callable
    folder: bool = False
    spec_name: str | None = None
    needs_spec: bool = False
    options: dict = field(default_factory=dict)
    key_figures: tuple = ()
    tolerances: dict = field(default_factory=dict)
    tolerances_by_kind: dict = field(default_factory=dict)
    trends: tuple = ()
    cost: float = 1.0
    validate_options: Callable | None = None

    def find_spec(self, path):
        """The input's spec file: ``<stem>.toml`` beside it, else :attr:`spec_name` in its folder, else None."""
        return spec_beside(path, self.spec_name) if self.spec_name else None

    def default_tolerances(self, summary: dict) -> dict:
        """The default limits for this summary: :attr:`tolerances_by_kind` of its ``kind``, else :attr:`tolerances`."""
        return dict(self.tolerances_by_kind.get(summary.get("kind"), self.tolerances))

    def check_options(self, options: dict) -> dict:
        """``options`` over the defaults, refusing unknown names and bad values; returns the full dict."""
        opts = dict(self.options)
        for k, v in options.items():
            if k not in opts:
                raise MarkcalError(f"unknown option '{k}' of the {self.name} flow (known: {', '.join(opts)})")
            opts[k] = v
        seed = opts.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 32:
            raise MarkcalError(f"seed must be a whole number from 0 to 2**32 - 1 (got {seed!r})")
        if self.validate_options is not None:
            self.validate_options(opts)
        return opts

    @property
    def key_names(self) -> tuple:
        return tuple(f.key for f in self.key_figures)

    def figure(self, key: str) -> Figure:
        """The key figure ``key`` (a bare one when it is not declared)."""
        return next((f for f in self.key_figures if f.key == key), Figure(key, key))


# ------------------------------------------------------------------ helpers for recognising inputs

def file_ext(path) -> str:
    """Lower-case extension with the dot (``.csv``)."""
    return os.path.splitext(os.fspath(path))[1].lower()


def csv_header(path) -> list:
    """The first line of a CSV file as lower-case stripped names ([] when unreadable)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            line = fh.readline()
    except OSError:
        return []
    return [h.strip().lower() for h in line.strip().split(",")]


def spec_beside(path, default_name: str):
    """``<stem>.toml`` beside ``path`` if it exists, else ``default_name`` in its folder, else None."""
    path = os.fspath(path)
    own = os.path.splitext(path)[0] + ".toml"
    if os.path.isfile(own):
        return own
    common = os.path.join(os.path.dirname(path), default_name)
    return common if os.path.isfile(common) else None
