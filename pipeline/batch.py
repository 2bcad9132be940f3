"""Batch runner: a folder of inputs -> one output folder per input + an index.

The core of ``markcal batch``. A small registry (:data:`FLOWS`, one
:class:`FlowEntry` per flow) says how to recognise an input, how to run the
flow and write its outputs exactly as the single-file command does, which key
figures to report and the default pass/fail tolerances. Adding a flow to the
batch is one :func:`register_flow` call.

Workers (local processes or Dask) receive a *job*: a small dict of paths and
settings, and return a small *record* dict (see :func:`run_job`). Nothing here
imports dask; heavy modules (numpy, the flows) are imported inside functions so
a spawned worker can limit its threads before they load.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable

from markcal.pipeline.config import load_toml
from markcal.reports.files import start_outputs
from markcal.stages.errors import MarkcalError

#: file names written in OUT_DIR itself (not per-input folders)
INDEX_FILES = ("index.html", "summary.csv", "summary.json")

#: record columns common to every flow, in summary.csv order
BASE_COLUMNS = ("name", "group", "flow", "status", "reason", "failed_checks", "checks", "input", "spec",
                "out_dir", "report", "input_mtime", "runtime_s", "reused")


@dataclass(frozen=True)
class FlowEntry:
    """How the batch runs one flow.

    Attributes
    ----------
    name : str
        Flow name (the single command's name).
    folder : bool
        True when an input is a folder (a session), False for a file.
    claims : callable
        ``claims(path) -> bool``: is this file (or folder) an input of the flow.
    find_spec : callable or None
        ``find_spec(path) -> str | None``: the companion spec file of an input.
    run : callable
        ``run(job) -> dict``: run the flow on ``job["input"]``, write the same
        files as the single command into ``job["out_dir"]`` (summary.json last)
        and return the summary dict.
    key_figures : tuple of str
        Summary keys shown in the index and summary.csv.
    tolerances : dict
        Default pass/fail limits: ``max_<key>`` / ``min_<key>`` -> number.
    options : dict
        Default flow options (the single command's option names, ``_`` for ``-``).
    trends : tuple of (key, label)
        Key figures plotted across inputs in the index.
    needs_spec : bool
        True when an input without a spec file cannot be processed.
    cost : float
        Rough relative run time per input; the longest jobs are started first
        so the workers finish together.
    """

    name: str
    folder: bool
    claims: Callable
    run: Callable
    key_figures: tuple
    find_spec: Callable | None = None
    tolerances: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    trends: tuple = ()
    needs_spec: bool = False
    cost: float = 1.0


#: the registry, in recognition order
FLOWS: dict = {}


def register_flow(entry: FlowEntry) -> None:
    """Add (or replace) a flow in the batch registry."""
    FLOWS[entry.name] = entry


# ------------------------------------------------------------------ helpers for recognising inputs

def _ext(path) -> str:
    return os.path.splitext(os.fspath(path))[1].lower()


def _csv_header(path) -> list:
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


# ------------------------------------------------------------------ the built-in flows

def _scan_claims(path) -> bool:
    e = _ext(path)
    if e in (".ply", ".pcd", ".xyz", ".npy"):
        return True
    if e in (".csv", ".txt"):
        h = _csv_header(path)
        return not ({"t_s", "ref_mm", "pos_mm"} & set(h)) and (len(h) >= 3 or not any(c.isalpha() for c in "".join(h)))
    return False


def _run_scan(job) -> dict:
    from markcal.pipeline.config import read_plate_spec
    from markcal.pipeline.flows.scan import ScanOptions, run_scan
    from markcal.reports.scan_outputs import write_scan_outputs

    o = job["options"]
    spec = read_plate_spec(job["spec"])
    res = run_scan(job["input"], spec, ScanOptions(seed=int(o["seed"]), validation=bool(o["validation"])))
    write_scan_outputs(res, job["out_dir"], report=not o["no_report"])
    return res.summary


def _selfcal_claims(path) -> bool:
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, "setup.toml")) and (
        os.path.isfile(os.path.join(path, "grid_views.csv")) or os.path.isfile(os.path.join(path, "angle_views.csv")))


def _run_selfcal(job) -> dict:
    from markcal.pipeline.flows.selfcal import run_selfcal
    from markcal.reports.selfcal_outputs import write_selfcal_outputs

    res = run_selfcal(job["input"])
    write_selfcal_outputs(res, job["out_dir"], report=not job["options"]["no_report"])
    return res.summary


def _servo_claims(path) -> bool:
    return _ext(path) == ".csv" and {"t_s", "ref_mm", "pos_mm"} <= set(_csv_header(path))


def _run_servo(job) -> dict:
    from markcal.pipeline.flows.servo import run_servo_trace
    from markcal.reports.servo_outputs import write_servo_outputs

    o = job["options"]
    band = float(o["settle_band_um"])
    if not band > 0:
        raise MarkcalError(f"settle_band_um must be positive (got {band})")
    res = run_servo_trace(job["input"], band_um=band)
    write_servo_outputs(res, job["out_dir"], report=not o["no_report"])
    return res.summary


register_flow(FlowEntry(
    name="selfcal", folder=True, claims=_selfcal_claims, run=_run_selfcal,
    key_figures=("n", "gx_rms_um", "gy_rms_um", "predicted_sd_gxy_um", "nonorthogonality_urad",
                 "scale_difference_ppm", "residual_rms_xy_um"),
    tolerances={"max_residual_rms_xy_um": 0.1},
    options={"no_report": False},
    trends=(("gx_rms_um", "stage error RMS Gx, µm"),)))
register_flow(FlowEntry(
    name="servo", folder=False, claims=_servo_claims, run=_run_servo,
    key_figures=("trace_kind", "mae_um", "std_um", "settling_time_s", "overshoot_um"),
    tolerances={"max_overshoot_um": 6.0},
    options={"settle_band_um": 1.0, "no_report": False},
    trends=(("mae_um", "servo mean absolute tracking error, µm"),), cost=0.5))
register_flow(FlowEntry(
    name="scan", folder=False, claims=_scan_claims, run=_run_scan,
    find_spec=lambda p: spec_beside(p, "plate.toml"), needs_spec=True,
    key_figures=("kind", "n_detected", "n_expected", "rms_mm", "max_mm", "cv_rmse_mm"),
    tolerances={"max_rms_mm": 0.05},
    options={"seed": 0, "validation": False, "no_report": False},
    trends=(("rms_mm", "scan deviation RMS, mm"),), cost=4.0))


#: flows registered lazily (their modules are imported only when a batch runs):
#: name -> builder returning a FlowEntry; see :func:`load_optional_flows`
OPTIONAL_FLOWS: dict = {}


def _indents_entry() -> FlowEntry:
    def claims(path):
        return _ext(path) in (".tif", ".tiff", ".gsf", ".gwy", ".ibw")

    def run(job):
        from markcal.pipeline.flows.indents import IndentsOptions, read_array_spec, run_indents
        from markcal.reports.indent_outputs import write_indent_outputs
        o = job["options"]
        spec = read_array_spec(job["spec"]) if job.get("spec") else None
        res = run_indents([job["input"]], spec, IndentsOptions(kind=o["kind"] or None,
                                                               pixel_size_um=o["pixel_size_um"] or None))
        if res.failed:
            raise MarkcalError(res.failed[0][1], res.failed[0][0])
        write_indent_outputs(res, job["out_dir"], report=not o["no_report"])
        return res.summary

    return FlowEntry(name="indents", folder=False, claims=claims, run=run,
                     find_spec=lambda p: spec_beside(p, "array.toml"),
                     key_figures=("n_imprints", "mean_diameter_um", "n_out_of_tolerance", "n_low_hd"),
                     tolerances={"max_n_out_of_tolerance": 0, "max_n_low_hd": 0},
                     options={"kind": "", "pixel_size_um": 0.0, "no_report": False},
                     trends=(("mean_diameter_um", "mean imprint diameter, µm"),), cost=8.0)


def _path_entry() -> FlowEntry:
    def claims(path):
        if _ext(path) == ".csv":             # a point job: x_mm,y_mm[,...] without z
            h = _csv_header(path)
            return h[:2] == ["x_mm", "y_mm"] and "z_mm" not in h
        if _ext(path) != ".json" or os.path.getsize(path) > 50_000_000:
            return False
        import json
        try:
            with open(path, encoding="utf-8") as fh:
                d = json.load(fh)
        except (OSError, ValueError):
            return False
        return isinstance(d, dict) and "strokes" in d

    def run(job):
        from markcal.pipeline.flows.path import PathOptions, run_path
        from markcal.reports.path_outputs import write_path_outputs
        o = job["options"]
        res = run_path(job["input"], PathOptions(method=o["method"], seed=int(o["seed"])))
        write_path_outputs(res, job["out_dir"], report=not o["no_report"])
        return res.summary

    return FlowEntry(name="path", folder=False, claims=claims, run=run,
                     key_figures=("jump_length_mm", "length_reduction_vs_input_pct", "time_s"),
                     options={"method": "ga+ls", "seed": 0, "no_report": False},
                     trends=(("length_reduction_vs_input_pct", "jump length reduction vs input order, %"),),
                     cost=2.0)


def _pmcal_entry() -> FlowEntry:
    from markcal.pipeline.flows.pmcal import SESSION_FILES

    def claims(path):
        return os.path.isdir(path) and sum(os.path.isfile(os.path.join(path, f)) for f in SESSION_FILES[:3]) >= 2

    def run(job):
        from markcal.pipeline.flows.pmcal import run_pmcal
        from markcal.reports.pmcal_outputs import write_pmcal_outputs
        o = job["options"]
        res = run_pmcal(job["input"], method=o["method"], seed=int(o["seed"]))
        write_pmcal_outputs(res, job["out_dir"], report=not o["no_report"])
        return res.summary

    return FlowEntry(name="pmcal", folder=True, claims=claims, run=run,
                     key_figures=("F", "axes_rms_um", "pose_rms_um", "nonorth_xy_urad", "nonorth_xz_urad",
                                  "nonorth_yz_urad", "landing_rms_um"),
                     options={"method": "ga+lsq", "seed": 0, "no_report": False},
                     trends=(("pose_rms_um", "pmcal pose residual RMS, µm"),), cost=8.0)


OPTIONAL_FLOWS["indents"] = _indents_entry
OPTIONAL_FLOWS["path"] = _path_entry
OPTIONAL_FLOWS["pmcal"] = _pmcal_entry


def load_optional_flows() -> list:
    """Register the lazily imported flows; return their names.

    An import error is not swallowed: a broken flow must not vanish from a batch silently.
    """
    added = []
    for name, build in OPTIONAL_FLOWS.items():
        if name not in FLOWS:
            register_flow(build())
            added.append(name)
    return added


# ------------------------------------------------------------------ configuration

def read_batch_config(path) -> dict:
    """Read batch.toml: ``[<flow>]`` option defaults and ``[<flow>.tolerance]`` limits.

    Returns flow name -> {"options": dict, "tolerances": dict}, defaults filled in.
    Unknown flows, options and tolerance keys are refused (typos must not pass).
    """
    cfg = {n: {"options": dict(e.options), "tolerances": dict(e.tolerances)} for n, e in FLOWS.items()}
    if path is None:
        return cfg
    path = os.fspath(path)
    d = load_toml(path, "batch config")
    for flow, sec in d.items():
        if flow not in FLOWS or not isinstance(sec, dict):
            raise MarkcalError(f"unknown flow [{flow}] (known: {', '.join(FLOWS)})", path)
        for k, v in sec.items():
            if k == "tolerance":
                if not isinstance(v, dict):
                    raise MarkcalError(f"[{flow}.tolerance] must be a table", path)
                for tk, tv in v.items():
                    if not (tk.startswith("max_") or tk.startswith("min_")) or len(tk) < 5:
                        raise MarkcalError(f"tolerance '{tk}' in [{flow}.tolerance] must be max_<key> or min_<key>",
                                           path)
                    if isinstance(tv, bool) or not isinstance(tv, (int, float)):
                        raise MarkcalError(f"tolerance '{tk}' in [{flow}.tolerance] must be a number", path)
                    cfg[flow]["tolerances"][tk] = float(tv)
            elif k in cfg[flow]["options"]:
                default = FLOWS[flow].options[k]
                if type(v) is not type(default) and not (isinstance(default, float) and isinstance(v, int)
                                                         and not isinstance(v, bool)):
                    raise MarkcalError(f"option '{k}' in [{flow}] must be {type(default).__name__}", path)
                cfg[flow]["options"][k] = type(default)(v)
            else:
                raise MarkcalError(f"unknown option '{k}' in [{flow}] (known: {', '.join(FLOWS[flow].options)}, "
                                   "tolerance)", path)
    return cfg


# ------------------------------------------------------------------ discovery

@dataclass
class Discovery:
    """What :func:`discover` found: jobs to run and files nothing claimed."""

    jobs: list
    ignored: list


def _is_spec_or_aux(path) -> bool:
    return _ext(path) in (".toml", ".json", ".md", ".html", ".log") or os.path.basename(path).startswith(".")


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
    jobs, ignored = [], []
    folder_flows = [e for e in FLOWS.values() if e.folder]
    file_flows = [e for e in FLOWS.values() if not e.folder]
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
            entry = next((e for e in file_flows if e.claims(full)), None)
            if entry is not None:
                jobs.append(_job(entry, full, input_dir, out_abs, config))
            elif not _is_spec_or_aux(full):
                ignored.append(os.path.relpath(full, input_dir))
    jobs.sort(key=lambda j: j["input"])
    _unique_names(jobs, out_abs)
    return Discovery(jobs, ignored)


def _job(entry: FlowEntry, path, input_dir, out_abs, config) -> dict:
    rel = os.path.relpath(path, input_dir)
    name = rel if entry.folder else os.path.splitext(rel)[0]
    name = name.replace(os.sep, "/")
    spec = entry.find_spec(path) if entry.find_spec else None
    return {"name": name, "rel": rel.replace(os.sep, "/"), "flow": entry.name, "input": os.path.abspath(path),
            "spec": spec, "group": name.split("/")[0] if "/" in name else "",
            "options": dict(config[entry.name]["options"]), "tolerances": dict(config[entry.name]["tolerances"]),
            "out_dir": ""}


def _unique_names(jobs, out_abs) -> None:
    seen = {}
    for j in jobs:
        seen.setdefault(j["name"], []).append(j)
    for name, js in seen.items():
        if len(js) > 1 or name in INDEX_FILES:
            for j in js:            # plate7.ply and plate7.npy -> plate7_ply, plate7_npy
                j["name"] = j["rel"].replace(".", "_")
    for j in jobs:
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

def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def evaluate(summary: dict, tolerances: dict) -> tuple:
    """Check a summary against ``max_<key>``/``min_<key>`` limits.

    A key the summary does not have fails ("missing": catches typos in
    batch.toml); a key whose value is null/NaN is not applicable and passes.

    Returns
    -------
    checks : str
        The limits applied, e.g. ``"rms_mm <= 0.05"``.
    failed : str
        The violated ones with the value, ``"; "``-joined ("" when all hold).
    """
    checks, failed = [], []
    for tk in sorted(tolerances):
        lim = tolerances[tk]
        key, op = tk[4:], ("<=" if tk.startswith("max_") else ">=")
        checks.append(f"{key} {op} {lim:g}")
        if key not in summary:
            failed.append(f"{key} missing")
            continue
        v = summary[key]
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            continue                    # not applicable to this input (e.g. overshoot of a tracking trace)
        if not _finite(v):
            failed.append(f"{key} not a number")
        elif (op == "<=" and v > lim) or (op == ">=" and v < lim):
            failed.append(f"{key} {v:.4g} {'>' if op == '<=' else '<'} {lim:g}")
    return "; ".join(checks), "; ".join(failed)


def make_record(job, summary: dict | None, reason: str = "", runtime_s: float = float("nan"),
                reused: bool = False) -> dict:
    """The small result record of one input (a row of summary.csv)."""
    entry = FLOWS.get(job["flow"])
    checks, failed = evaluate(summary, job["tolerances"]) if summary is not None else ("", "")
    if summary is None:
        status = "error"
    elif not job["tolerances"]:
        status = "done"
    else:
        status = "fail" if failed else "pass"
    report = os.path.join(job["out_dir"], "report.html")
    rec = {"name": job["name"], "group": job["group"], "flow": job["flow"], "status": status,
           "reason": reason, "failed_checks": failed, "checks": checks, "input": job["input"],
           "spec": job.get("spec") or "", "out_dir": job["out_dir"],
           "report": report if summary is not None and os.path.exists(report) else "",
           "input_mtime": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(input_mtime(job, with_spec=False))),
           "runtime_s": runtime_s, "reused": reused}
    for k in (entry.key_figures if entry else ()):
        v = None if summary is None else summary.get(k)
        rec[k] = v if isinstance(v, (int, float, str)) or v is None else str(v)
    return rec


def one_line(exc: BaseException) -> str:
    """A one-line reason for an exception (MarkcalError text as is, else its type and message)."""
    if isinstance(exc, MarkcalError):
        text = str(exc)
    else:
        text = f"internal error: {type(exc).__name__}: {exc}"
    text = " ".join(text.split())
    return text[:400] + ("…" if len(text) > 400 else "")


def run_job(job: dict) -> dict:
    """Run one job (in a worker): the flow, its outputs, then the record. Never raises.

    The old summary.json is removed first so that a run killed half way never
    leaves a folder that counts as done.
    """
    t0 = time.perf_counter()
    try:
        if job["flow"] not in FLOWS:
            load_optional_flows()
        entry = FLOWS[job["flow"]]
        if entry.needs_spec and not job.get("spec"):
            raise MarkcalError(f"no spec file: expected {os.path.splitext(os.path.basename(job['input']))[0]}.toml "
                               f"or the folder's default spec beside the input", job["input"])
        start_outputs(job["out_dir"])     # a failure now must not leave an old summary vouching
        summary = entry.run(job)
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
    for name, e in FLOWS.items():
        if name in flows_present:
            cols += [k for k in e.key_figures if k not in cols]
    return cols


# ------------------------------------------------------------------ the whole batch

def _expected_cost(job) -> float:
    """Rough run time of a job: the flow's cost times the input's size relative to 10 MB (at least 1)."""
    p = job["input"]
    try:
        size = (sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(p) for f in fs)
                if os.path.isdir(p) else os.path.getsize(p))
    except OSError:
        size = 0
    return FLOWS[job["flow"]].cost * max(1.0, size / 10e6)


@dataclass
class BatchResult:
    """Records of every input (discovery order) plus counts."""

    records: list
    ignored: list
    n_run: int
    n_reused: int
    wall_s: float

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
    load_optional_flows()
    config = read_batch_config(config_path)
    if workers < 1:
        raise MarkcalError(f"--workers must be at least 1 (got {workers})")
    found = discover(input_dir, out_dir, config)
    if not found.jobs:
        raise MarkcalError(f"no inputs found (known flows: {', '.join(FLOWS)}; "
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
    return BatchResult(ordered, found.ignored, len(todo), n_reused, time.perf_counter() - t0)
