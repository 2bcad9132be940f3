"""The flows markcal knows: each flow's descriptor paired with the writer of its files.

Adding a flow: its module in ``pipeline/flows/`` (exporting ``FLOW``), its
stages, its writer in ``reports/``, and one ``register`` line here. The order
of registration is the order in which inputs are recognised and in which the
batch index lists the flows.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from markcal.pipeline.flows import indents, path, pmcal, scan, selfcal, servo
from markcal.pipeline.flows.descriptor import FlowDescriptor
from markcal.reports.indent_outputs import write_indent_outputs
from markcal.reports.path_outputs import write_path_outputs
from markcal.reports.pmcal_outputs import write_pmcal_outputs
from markcal.reports.scan_outputs import write_scan_outputs
from markcal.reports.selfcal_outputs import write_selfcal_outputs
from markcal.reports.servo_outputs import write_servo_outputs
from markcal.stages.errors import MarkcalError


@dataclass(frozen=True)
class Flow:
    """A registered flow: what it is (descriptor) and how its result becomes files (writer)."""

    descriptor: FlowDescriptor
    write: Callable          # write(result, out_dir, report=True) -> {name: path}, summary.json last

    @property
    def name(self) -> str:
        return self.descriptor.name


#: name -> Flow, in recognition order
FLOWS: dict = {}


def register(descriptor: FlowDescriptor, write: Callable) -> None:
    """Add (or replace) a flow."""
    FLOWS[descriptor.name] = Flow(descriptor, write)


register(selfcal.FLOW, write_selfcal_outputs)
register(servo.FLOW, write_servo_outputs)
register(scan.FLOW, write_scan_outputs)
register(indents.FLOW, write_indent_outputs)
register(path.FLOW, write_path_outputs)
register(pmcal.FLOW, write_pmcal_outputs)


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
    flow = FLOWS[name]
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
