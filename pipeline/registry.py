"""The flows markcal knows: each flow's descriptor paired with the writer of its files.

Adding a flow: its module in ``pipeline/flows/`` (exporting ``FLOW``), its
stages, its writer in ``reports/``, and one ``register`` line here. The order
of registration is the order in which inputs are recognised and in which the
batch index lists the flows.
"""
from __future__ import annotations

import functools
import importlib
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

from markcal.pipeline.flows.descriptor import FlowDescriptor
from markcal.reports.drawing import start_drawing_process, stop_drawing_process
from markcal.reports.files import check_out_dir, start_outputs
from markcal.stages.errors import MarkcalError
from markcal.stages.verdict import FAIL, evaluate


@dataclass(frozen=True)
class Flow:
    """A registered flow: what it is (descriptor) and how its result becomes files (writer)."""

    descriptor: FlowDescriptor
    write: Callable          # write(result, out_dir, report=True) -> {name: path}, summary.json last
    drawing: tuple = ()      # report modules its drawing process imports while the flow runs (none: no process)

    @property
    def name(self) -> str:
        return self.descriptor.name


#: name -> (flow module exporting FLOW, "module:function" of its writer, drawing modules), in recognition order.
#: Modules are imported when first asked for, so a single command loads only its own flow.
REGISTERED: dict = {}
_LOADED: dict = {}


def register(name: str, flow_module: str, writer: str, drawing: tuple = ()) -> None:
    """Add (or replace) a flow: its module (exporting ``FLOW``) and its writer ``"module:function"``.

    ``drawing``: the report modules of a writer that draws through ``reports.drawing.draw_groups``;
    its drawing process starts before the flow runs and imports them meanwhile.
    """
    REGISTERED[name] = (flow_module, writer, tuple(drawing))
    _LOADED.pop(name, None)


register("selfcal", "markcal.pipeline.flows.selfcal", "markcal.reports.selfcal_outputs:write_selfcal_outputs")
register("servo", "markcal.pipeline.flows.servo", "markcal.reports.servo_outputs:write_servo_outputs")
register("grid", "markcal.pipeline.flows.grid", "markcal.reports.grid_outputs:write_grid_outputs")
register("scan", "markcal.pipeline.flows.scan", "markcal.reports.scan_outputs:write_scan_outputs",
         drawing=("markcal.reports.scan_report",))
register("indents", "markcal.pipeline.flows.indents", "markcal.reports.indents_outputs:write_indents_outputs")
register("path", "markcal.pipeline.flows.path", "markcal.reports.path_outputs:write_path_outputs")
register("pmcal", "markcal.pipeline.flows.pmcal", "markcal.reports.pmcal_outputs:write_pmcal_outputs")


def get_flow(name: str) -> Flow:
    """The registered flow ``name`` (imports its modules on first use)."""
    if name not in _LOADED:
        flow_module, writer, drawing = REGISTERED[name]
        wmod, wfun = writer.split(":")
        descriptor = importlib.import_module(flow_module).FLOW
        if descriptor.name != name:
            raise ValueError(f"{flow_module}.FLOW is named {descriptor.name!r}, registered as {name!r}")
        _LOADED[name] = Flow(descriptor, getattr(importlib.import_module(wmod), wfun), drawing)
    return _LOADED[name]


def all_flows() -> dict:
    """Every registered flow, name -> :class:`Flow`, in recognition order (imports them all)."""
    return {name: get_flow(name) for name in REGISTERED}


@functools.cache
def markcal_version() -> str:
    """The installed markcal version ("unknown" when run from a source tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("markcal")
    except PackageNotFoundError:
        return "unknown"


def sha256_of(path) -> str:
    """SHA-256 of a file, or of a folder's files (``relative path\0digest`` lines, sorted)."""
    import hashlib
    import os

    def file_digest(p):
        h = hashlib.sha256()
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()
    if not os.path.isdir(path):
        return file_digest(path)
    h = hashlib.sha256()
    for root, dirs, files in sorted(os.walk(path)):
        dirs.sort()
        for f in sorted(files):
            p = os.path.join(root, f)
            h.update(f"{os.path.relpath(p, path)}\0{file_digest(p)}\n".encode())
    return h.hexdigest()


def data_time(path) -> str | None:
    """The measurement's own timestamp, ISO ``YYYY-MM-DDTHH:MM:SS`` (instrument local time), when the file
    carries one: a TIFF's FEI/Thermo ``[User] Date``/``Time`` or its ``DateTime`` tag (306); else None."""
    import datetime
    import os
    if os.path.isdir(path) or os.path.splitext(os.fspath(path))[1].lower() not in (".tif", ".tiff"):
        return None
    try:
        import tifffile
        with tifffile.TiffFile(path) as tif:
            user = (tif.fei_metadata or {}).get("User", {}) if tif.is_fei else {}
            page = tif.pages.first
            tag = page.tags.get(306)
            for text, fmt in ((f"{user.get('Date', '')} {user.get('Time', '')}", "%m/%d/%Y %I:%M:%S %p"),
                              (str(tag.value).strip() if tag is not None else "", "%Y:%m:%d %H:%M:%S")):
                try:
                    return datetime.datetime.strptime(text.strip(), fmt).strftime("%Y-%m-%dT%H:%M:%S")
                except ValueError:
                    continue
    except Exception:  # noqa: BLE001  a timestamp is optional: an unreadable header just has none
        return None
    return None


def input_digests(input_path, spec_path=None) -> dict:
    """``input_sha256`` (``; ``-joined for several inputs) and ``spec_sha256`` (when a spec is given)."""
    paths = input_path if isinstance(input_path, (list, tuple)) else [input_path]
    out = {"input_sha256": "; ".join(sha256_of(p) for p in paths)}
    if spec_path:
        out["spec_sha256"] = sha256_of(spec_path)
    return out


def provenance(input_path, spec_path=None, context: dict | None = None, digests: dict | None = None) -> dict:
    """Summary keys that make a result traceable: version, UTC date, command, inputs and their SHA-256,
    the data's own timestamp (``data_time``) when the file has one, and the user's ``machine``, ``lens``,
    ``operator``, ``note`` when given. ``digests``: :func:`input_digests`, when already computed."""
    import datetime
    import os
    import sys
    paths = input_path if isinstance(input_path, (list, tuple)) else [input_path]
    out = {"markcal_version": markcal_version(),
           "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": " ".join(["markcal", *sys.argv[1:]]) if os.path.basename(sys.argv[0]) == "markcal"
           else " ".join(sys.argv),
           "input": "; ".join(os.path.abspath(p) for p in paths)}
    digests = digests if digests is not None else input_digests(input_path, spec_path)
    out["input_sha256"] = digests["input_sha256"]
    stamps = [t for t in (data_time(p) for p in paths) if t]
    if stamps:
        out["data_time"] = min(stamps)
    if spec_path:
        out.update(spec=os.path.abspath(spec_path), spec_sha256=digests["spec_sha256"])
    for k, v in (context or {}).items():
        if v:
            out[k] = str(v)
    return out


def check_tolerance_keys(name: str, summary: dict, tolerances: dict, path=None) -> None:
    """Refuse a limit on a key the flow does not produce (a typo must not pass as "missing")."""
    unknown = sorted(k for k in tolerances if k[4:] not in summary)
    if unknown:
        numeric = sorted(k for k, v in summary.items() if isinstance(v, (int, float)) and not isinstance(v, bool))
        raise MarkcalError(f"tolerance on {', '.join(k[4:] for k in unknown)}: the {name} flow produces no such "
                           f"figure (numeric figures: {', '.join(numeric)})", path)


def judge(name: str, summary: dict, input_path, spec_path=None, tolerances: dict | None = None,
          context: dict | None = None, digests: dict | None = None) -> None:
    """Add the verdict (the flow's default limits overridden by ``tolerances``) and the provenance to ``summary``.

    ``input_path`` may be a list (several files pooled in one result); ``digests`` as :func:`provenance`.
    """
    check_tolerance_keys(name, summary, tolerances or {}, input_path if not isinstance(input_path, list) else None)
    d = get_flow(name).descriptor
    limits = {**d.default_tolerances(summary), **(tolerances or {})}
    v = evaluate(summary, limits)
    labels = "; ".join(d.figure(k[4:]).caption for k in limits)
    summary.update(verdict=v.status, checks=v.checks, check_labels=labels, failed_checks=v.failed,
                   **provenance(input_path, spec_path, context, digests))


def run_and_write(name: str, input_path, out_dir, spec_path=None, options: dict | None = None,
                  progress=None, tolerances: dict | None = None, context: dict | None = None,
                  clear_first: bool = False) -> tuple:
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
    tolerances : dict, optional
        ``max_<key>``/``min_<key>`` limits over the descriptor's defaults; the verdict
        (``verdict``, ``checks``, ``failed_checks``) goes into the summary and the report.
    context : dict, optional
        ``machine``, ``lens``, ``operator``, ``note``: recorded in the summary and the report.
    clear_first : bool
        Remove what an earlier run wrote in ``out_dir`` before the run (the batch: a run that
        fails then leaves no old summary vouching for the input), not only when writing.

    Returns
    -------
    result, paths
        The flow's result object and output name -> path (summary.json written last).
    """
    flow = get_flow(name)
    d = flow.descriptor
    opts = d.check_options(options or {})
    if d.needs_spec and not spec_path:
        raise MarkcalError("no spec file: expected <stem>.toml or the folder's default spec beside the input",
                           input_path)
    inputs = [p for p in (input_path, spec_path) if p]
    check_out_dir(out_dir, inputs)     # once, before any work
    if clear_first:
        start_outputs(out_dir)
    report = not opts.get("no_report", False)
    if report and flow.drawing:       # the report's drawing process imports matplotlib while the flow computes
        start_drawing_process(flow.drawing)       # (started before any thread is)
    try:
        # the checksums (hashlib and file reads release the interpreter lock) are computed while the flow
        # runs, when every input is a plain file or folder (a pipe or device is left to the flow, which refuses it)
        if all(os.path.isfile(p) or os.path.isdir(p) for p in inputs):
            with ThreadPoolExecutor(1, thread_name_prefix="markcal-sha256") as pool:
                pool.submit(markcal_version)      # for the provenance: its metadata lookup is done there too
                digests = pool.submit(input_digests, input_path, spec_path)
                result = d.run(input_path, spec_path, opts, progress)
                digests = digests.result()
        else:
            result, digests = d.run(input_path, spec_path, opts, progress), None
        judge(name, result.summary, input_path, spec_path, tolerances, context, digests)
        if progress:
            progress("writing tables and report")
        paths = flow.write(result, out_dir, report=report)
    finally:
        stop_drawing_process()
    return result, paths


def exit_status(summary: dict) -> int:
    """A single command's exit status: 4 when it ran but is out of tolerance, else 0."""
    return 4 if summary.get("verdict") == FAIL else 0
