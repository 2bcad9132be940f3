"""The flows markcal knows: each flow's descriptor paired with the writer of its files.

Adding a flow: its module in ``pipeline/flows/`` (exporting ``FLOW``), its
stages, its writer in ``reports/``, and one ``register`` line here. The order
of registration is the order in which inputs are recognised and in which the
batch index lists the flows.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

from markcal.pipeline.flows.descriptor import FlowDescriptor
from markcal.stages.errors import MarkcalError


@dataclass(frozen=True)
class Flow:
    """A registered flow: what it is (descriptor) and how its result becomes files (writer)."""

    descriptor: FlowDescriptor
    write: Callable          # write(result, out_dir, report=True) -> {name: path}, summary.json last

    @property
    def name(self) -> str:
        return self.descriptor.name


#: name -> (flow module exporting FLOW, "module:function" of its writer), in recognition order.
#: Modules are imported when first asked for, so a single command loads only its own flow.
REGISTERED: dict = {}
_LOADED: dict = {}


def register(name: str, flow_module: str, writer: str) -> None:
    """Add (or replace) a flow: its module (exporting ``FLOW``) and its writer ``"module:function"``."""
    REGISTERED[name] = (flow_module, writer)
    _LOADED.pop(name, None)


register("selfcal", "markcal.pipeline.flows.selfcal", "markcal.reports.selfcal_outputs:write_selfcal_outputs")
register("servo", "markcal.pipeline.flows.servo", "markcal.reports.servo_outputs:write_servo_outputs")
register("grid", "markcal.pipeline.flows.grid", "markcal.reports.grid_outputs:write_grid_outputs")
register("scan", "markcal.pipeline.flows.scan", "markcal.reports.scan_outputs:write_scan_outputs")
register("indents", "markcal.pipeline.flows.indents", "markcal.reports.indents_outputs:write_indents_outputs")
register("path", "markcal.pipeline.flows.path", "markcal.reports.path_outputs:write_path_outputs")
register("pmcal", "markcal.pipeline.flows.pmcal", "markcal.reports.pmcal_outputs:write_pmcal_outputs")


def get_flow(name: str) -> Flow:
    """The registered flow ``name`` (imports its modules on first use)."""
    if name not in _LOADED:
        flow_module, writer = REGISTERED[name]
        wmod, wfun = writer.split(":")
        descriptor = importlib.import_module(flow_module).FLOW
        if descriptor.name != name:
            raise ValueError(f"{flow_module}.FLOW is named {descriptor.name!r}, registered as {name!r}")
        _LOADED[name] = Flow(descriptor, getattr(importlib.import_module(wmod), wfun))
    return _LOADED[name]


def all_flows() -> dict:
    """Every registered flow, name -> :class:`Flow`, in recognition order (imports them all)."""
    return {name: get_flow(name) for name in REGISTERED}


def run_and_write(name: str, input_path, out_dir, spec_path=None, options: dict | None = None,
                  progress=None) -> tuple:
    """Run flow ``name`` on one input and write its files, as the single command and the batch do.

    Parameters
    ----------
    name : str
        Registered flow name.
    input_path, out_dir : path
        The input file (or session folder) and the output folder.
    spec_path : path, optional
        The spec file (required when the flow ``needs_spec``).
    options : dict, optional
        Option values; missing ones take the descriptor's defaults; unknown ones are refused.
    progress : callable, optional
        ``progress(msg)`` for progress lines.

    Returns
    -------
    result, paths
        The flow's result object and output name -> path (summary.json written last).
    """
    flow = get_flow(name)
    d = flow.descriptor
    opts = dict(d.options)
    for k, v in (options or {}).items():
        if k not in opts:
            raise MarkcalError(f"unknown option '{k}' of the {name} flow (known: {', '.join(opts)})")
        opts[k] = v
    if d.needs_spec and not spec_path:
        raise MarkcalError("no spec file: expected <stem>.toml or the folder's default spec beside the input",
                           input_path)
    result = d.run(input_path, spec_path, opts, progress)
    if progress:
        progress("writing tables and report")
    paths = flow.write(result, out_dir, report=not opts.get("no_report", False))
    return result, paths
