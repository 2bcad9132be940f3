"""Batch runner: a folder of inputs -> one output folder per input + an index.

The core of ``markcal batch``. Every flow's descriptor (in
:mod:`markcal.pipeline.registry`) says how to recognise an input, how to run
the flow and write its outputs exactly as the single-file command does, which
key figures to report and the default pass/fail tolerances.

Workers (local processes or Dask) receive a *job*: a small dict of paths and
settings, and return a small *record* dict (see :func:`run_job`). Nothing here
imports dask; the local pool sets the thread caps in the environment before it
spawns its workers, so the libraries the flows load are limited.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

from markcal.pipeline.config import read_batch_config as read_config_file
from markcal.pipeline.flows.descriptor import file_ext
from markcal.pipeline.registry import all_flows, get_flow, run_and_write
from markcal.stages.errors import MarkcalError, one_line
from markcal.stages.verdict import FAIL, PASS

#: file names written in OUT_DIR itself (not per-input folders)
INDEX_FILES = ("index.html", "summary.csv", "summary.json")

#: record columns common to every flow, in summary.csv order
BASE_COLUMNS = ("name", "group", "flow", "status", "reason", "failed_checks", "checks", "input", "spec",
                "out_dir", "report", "input_mtime", "data_time", "runtime_s", "reused")


# ------------------------------------------------------------------ configuration

def read_batch_config(path) -> dict:
    """Read batch.toml: ``[<flow>]`` option defaults and ``[<flow>.tolerance]`` limits.

    Returns flow name -> {"options": dict, "tolerances": dict}: options with defaults filled in, and
    batch.toml's limits, which override each input's default limits (the flow's, or a scan's per purpose).
    Unknown flows, options and tolerance keys are refused (typos must not pass), and every flow's
    options are checked by its ``validate_options`` (whether or not the folder holds inputs of that flow).
    """
    flows = all_flows()
    # the jobs carry batch.toml's limits only: each input's defaults depend on its summary (a scan's purpose)
    cfg = read_config_file(path, {n: f.descriptor.options for n, f in flows.items()}, {})
    for n, f in flows.items():          # every flow, inputs or not: a bad value stops the batch before any work
        try:
            f.descriptor.check_options(cfg[n]["options"])
        except MarkcalError as exc:
            raise MarkcalError(f"[{n}] {exc.message}", path or "batch defaults") from None
    return cfg


# ------------------------------------------------------------------ discovery

@dataclass
class Discovery:
    """What :func:`discover` found: jobs to run and files nothing claimed."""

    jobs: list
    ignored: list


def _is_spec_or_aux(path) -> bool:
    return file_ext(path) in (".toml", ".json", ".md", ".html", ".log") or os.path.basename(path).startswith(".")


def discover(input_dir, out_dir, config: dict) -> Discovery:
    """Walk ``input_dir`` and make one job per recognised input (sorted by path).

    A folder claimed by a folder flow (a session) is one input and is not
    descended into. Other files are claimed by the first file flow that
    recognises them; spec files (.toml), JSON and hidden files are not inputs
    (unless a flow claims them); anything else is listed as ignored.
    """
    input_dir = os.path.abspath(input_dir)
    out_abs = os.path.abspath(out_dir)
    if not os.path.isdir(input_dir):
        raise MarkcalError("input folder does not exist", input_dir)
    if os.path.realpath(out_abs) == os.path.realpath(input_dir):
        raise MarkcalError("--out is the input folder: outputs would land among the inputs; choose another folder",
                           out_dir)
    jobs, ignored = [], []
    flows = [f.descriptor for f in all_flows().values()]
    folder_flows = [d for d in flows if d.folder]
    file_flows = [d for d in flows if not d.folder]
    for root, dirs, files in os.walk(input_dir):
        dirs.sort()
        keep = []
        for d in dirs:
            full = os.path.join(root, d)
            if d.startswith(".") or os.path.abspath(full) == out_abs:
                continue
            entry = next((e for e in folder_flows if e.claims(full)), None)
            if entry is not None:
                jobs.append(_job(entry, full, input_dir, out_abs, config))
            else:
                keep.append(d)
        dirs[:] = keep
        for f in sorted(files):
            full = os.path.join(root, f)
            if not os.path.isfile(full):            # FIFO, socket, device, dangling link: never read
                ignored.append(os.path.relpath(full, input_dir) + " (not a regular file)")
                continue
            entry = next((e for e in file_flows if e.claims(full)), None)
            if entry is not None:
                jobs.append(_job(entry, full, input_dir, out_abs, config))
            elif not _is_spec_or_aux(full):
                ignored.append(os.path.relpath(full, input_dir))
    jobs.sort(key=lambda j: j["input"])
    _unique_names(jobs, out_abs)
    return Discovery(jobs, ignored)


def _job(entry, path, input_dir, out_abs, config) -> dict:
    rel = os.path.relpath(path, input_dir)
    name = rel if entry.folder else os.path.splitext(rel)[0]
    name = name.replace(os.sep, "/")
    spec = entry.find_spec(path)
    return {"name": name, "rel": rel.replace(os.sep, "/"), "flow": entry.name, "input": os.path.abspath(path),
            "spec": spec, "group": name.split("/")[0] if "/" in name else "",
            "options": dict(config[entry.name]["options"]), "tolerances": dict(config[entry.name]["tolerances"]),
            "out_dir": ""}


def _unique_names(jobs, out_abs) -> None:
    """Give every job its own output folder: ``plate7.ply`` and ``plate7.npy`` -> ``plate7_ply``,
    ``plate7_npy``; a name still taken after that (by another input's name) gets ``_2``, ``_3``, ..."""
    seen = {}
    for j in jobs:
        seen.setdefault(j["name"], []).append(j)
    for name, js in seen.items():
        if len(js) > 1 or name in INDEX_FILES:
            for j in js:
                j["name"] = j["rel"].replace(".", "_")
    taken = set()
    for j in jobs:
        base, k = j["name"], 1
        while j["name"].lower() in taken:       # case-insensitive: file systems that fold case
            k += 1
            j["name"] = f"{base}_{k}"
        taken.add(j["name"].lower())
        j["out_dir"] = os.path.join(out_abs, *j["name"].split("/"))


# ------------------------------------------------------------------ resume

def input_mtime(job, with_spec: bool = True) -> float:
    """Newest modification time of the input (every file of a session folder) and its spec."""
    p = job["input"]
    times = []
    if os.path.isdir(p):
        for root, _, files in os.walk(p):
            times += [os.path.getmtime(os.path.join(root, f)) for f in files]
        times.append(os.path.getmtime(p))
    elif os.path.exists(p):
        times.append(os.path.getmtime(p))
    if with_spec and job.get("spec") and os.path.exists(job["spec"]):
        times.append(os.path.getmtime(job["spec"]))
    return max(times) if times else 0.0


def is_done(job) -> bool:
    """True when the job's outputs are complete (summary.json, written last) and newer than its input."""
    s = os.path.join(job["out_dir"], "summary.json")
    try:
        return os.path.getmtime(s) >= input_mtime(job)
    except OSError:
        return False


# ------------------------------------------------------------------ records and pass/fail

def make_record(job, summary: dict | None, reason: str = "", runtime_s: float = float("nan"),
                reused: bool = False) -> dict:
    """The small result record of one input (a row of summary.csv).

    Its status, checks and failed checks are the verdict :func:`~markcal.pipeline.registry.judge`
    wrote into the summary (the report's), not evaluated again.
    """
    entry = get_flow(job["flow"]).descriptor
    if summary is None:
        status, checks, failed = "error", "", ""
    else:
        status = {PASS: "pass", FAIL: "fail"}.get(summary.get("verdict"), "done")
        checks, failed = summary.get("checks") or "", summary.get("failed_checks") or ""
    report = os.path.join(job["out_dir"], "report.html")
    rec = {"name": job["name"], "group": job["group"], "flow": job["flow"], "status": status,
           "reason": reason, "failed_checks": failed, "checks": checks, "input": job["input"],
           "spec": job.get("spec") or "", "out_dir": job["out_dir"],
           "report": report if summary is not None and os.path.exists(report) else "",
           "input_mtime": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(input_mtime(job, with_spec=False))),
           "data_time": (summary or {}).get("data_time") or "",
           "runtime_s": runtime_s, "reused": reused}
    for k in (entry.key_names if entry else ()):
        v = None if summary is None else summary.get(k)
        rec[k] = v if isinstance(v, (int, float, str)) or v is None else str(v)
    return rec


def run_job(job: dict) -> dict:
    """Run one job (in a worker): the flow, its outputs, then the record. Never raises.

    The old summary.json is removed first so that a run killed half way never
    leaves a folder that counts as done.
    """
    t0 = time.perf_counter()
    try:
        flow = get_flow(job["flow"])
        if flow.descriptor.needs_spec and not job.get("spec"):
            raise MarkcalError(f"no spec file: expected {os.path.splitext(os.path.basename(job['input']))[0]}.toml "
                               f"or the folder's default spec beside the input", job["input"])
        index = os.path.join(os.path.dirname(job["out_dir"].rstrip(os.sep)), *[".."] * job["name"].count("/"),
                             "index.html")
        result, _ = run_and_write(job["flow"], job["input"], job["out_dir"], spec_path=job.get("spec"),
                                  options=job["options"], tolerances=job["tolerances"],
                                  context={"batch_index": os.path.relpath(index, job["out_dir"])},
                                  clear_first=True)     # a failure now must not leave an old summary vouching
        summary = result.summary
        return make_record(job, summary, runtime_s=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001  failure isolation: every error becomes a one-line reason
        return make_record(job, None, reason=one_line(exc), runtime_s=time.perf_counter() - t0)
    except BaseException as exc:  # SystemExit from a library
        if isinstance(exc, KeyboardInterrupt):
            raise
        return make_record(job, None, reason=one_line(exc), runtime_s=time.perf_counter() - t0)


def reuse_record(job) -> dict | None:
    """The record of a finished job from its summary.json (None if unreadable)."""
    import json
    try:
        with open(os.path.join(job["out_dir"], "summary.json"), encoding="utf-8") as fh:
            summary = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict):
        return None
    return make_record(job, summary, runtime_s=float("nan"), reused=True)


def columns(records) -> list:
    """summary.csv columns: the common ones, then each flow's key figures in registry order."""
    cols = list(BASE_COLUMNS)
    flows_present = {r["flow"] for r in records}
    for name, f in all_flows().items():
        if name in flows_present:
            cols += [k for k in f.descriptor.key_names if k not in cols]
    return cols


# ------------------------------------------------------------------ the whole batch

def _tolerance_keys(record) -> list:
    """``max_<key>``-style names of the limits a record was checked against (from its ``checks``)."""
    out = []
    for c in (record.get("checks") or "").split("; "):
        parts = c.split(" ")
        if len(parts) == 3:
            out.append(("max_" if parts[1] == "<=" else "min_") + parts[0])
    return out


def _expected_cost(job) -> float:
    """Rough run time of a job: the flow's cost times the input's size relative to 10 MB (at least 1)."""
    p = job["input"]
    try:
        size = (sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(p) for f in fs)
                if os.path.isdir(p) else os.path.getsize(p))
    except OSError:
        size = 0
    return get_flow(job["flow"]).descriptor.cost * max(1.0, size / 10e6)


@dataclass(frozen=True)
class FlowColumns:
    """What the index shows of one flow: its key figures (summary keys and their captions with units)
    and the trends plotted (summary key, axis caption): the toleranced figures first."""

    key_figures: tuple
    trends: tuple
    captions: tuple = ()


@dataclass
class BatchResult:
    """Records of every input (discovery order), counts, and what the index shows per flow."""

    records: list
    ignored: list
    n_run: int
    n_reused: int
    wall_s: float
    columns: list = field(default_factory=list)
    flows: dict = field(default_factory=dict)

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.records)

    @property
    def exit_code(self) -> int:
        """0 when every input was processed, 3 when some failed to process."""
        return 3 if self.count("error") else 0


def run_batch(input_dir, out_dir, config_path=None, workers: int = 1, scheduler: str | None = None,
              force: bool = False, progress=None, on_start=None) -> BatchResult:
    """Discover, skip finished inputs, run the rest on an executor, collect the records.

    Parameters
    ----------
    input_dir, out_dir : path
        Folder of inputs; folder for the outputs (one sub-folder per input).
    config_path : path, optional
        batch.toml with per-flow options and tolerances.
    workers : int
        Local worker processes (ignored with ``scheduler``).
    scheduler : str, optional
        Dask scheduler address: run on that cluster instead of locally.
    force : bool
        Redo inputs whose outputs are complete and up to date.
    progress : callable, optional
        ``progress(record, done, failed, left)`` after each input.
    on_start : callable, optional
        ``on_start(n_total, n_todo, n_reused, ignored)`` before the work starts.

    Raises
    ------
    MarkcalError
        The batch itself cannot run (no such folder, bad config, no inputs,
        scheduler unreachable).
    """
    from markcal.pipeline.executors import make_executor

    t0 = time.perf_counter()
    config = read_batch_config(config_path)
    if workers < 1:
        raise MarkcalError(f"--workers must be at least 1 (got {workers})")
    found = discover(input_dir, out_dir, config)
    if not found.jobs:
        raise MarkcalError(f"no inputs found (known flows: {', '.join(all_flows())}; "
                           f"{len(found.ignored)} files not recognised)", os.path.abspath(input_dir))
    os.makedirs(out_dir, exist_ok=True)
    records = {}
    todo = []
    for j in found.jobs:
        rec = None if force or not is_done(j) else reuse_record(j)
        if rec is None:
            todo.append(j)
        else:
            records[j["name"]] = rec
    n_reused = len(records)
    todo.sort(key=_expected_cost, reverse=True)       # longest first: the workers finish together
    if on_start:
        on_start(len(found.jobs), len(todo), n_reused, found.ignored)
    counts = {"done": n_reused, "failed": sum(r["status"] == "error" for r in records.values())}
    if todo:
        def collect(rec):
            records[rec["name"]] = rec
            counts["done"] += 1
            counts["failed"] += rec["status"] == "error"
            if progress:
                progress(rec, counts["done"], counts["failed"], len(found.jobs) - counts["done"])
        with make_executor(workers=workers, scheduler=scheduler) as ex:
            ex.map_unordered(run_job, todo, collect, on_crash=lambda job, why: make_record(job, None, reason=why))
    ordered = [records[j["name"]] for j in found.jobs]
    present = {r["flow"] for r in ordered}
    shown = {}
    for n, f in all_flows().items():
        if n in present:
            d = f.descriptor
            limited = [tk[4:] for r in ordered if r["flow"] == n for tk in _tolerance_keys(r)]
            trend_keys = list(dict.fromkeys([*limited, *d.trends]))
            shown[n] = FlowColumns(d.key_names, tuple((k, d.figure(k).caption) for k in trend_keys),
                                   tuple(d.figure(k).caption for k in d.key_names))
    return BatchResult(ordered, found.ignored, len(todo), n_reused, time.perf_counter() - t0,
                       columns(ordered), shown)
