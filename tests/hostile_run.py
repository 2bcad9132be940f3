"""Run one ``markcal`` command as a hostile user would, in a forked child under resource limits (issue 17).

The child is forked from the test process (markcal already imported: no 2 s start-up per case), gets an
address-space limit of its current size + ``AS_HEADROOM`` (about 1.5 GiB), a CPU limit and a wall alarm
(a hang is killed, not waited for), runs ``main(argv)`` with stderr and stdout in files and exits with its
status. The parent reads the exit status and the child's own CPU time and peak RSS (``os.wait4``).
"""
from __future__ import annotations

import math
import os
import re
import resource
import signal
import sys
from dataclasses import dataclass

#: extra address space the child may map beyond what it holds at the fork
AS_HEADROOM = 3 * 2 ** 29           # 1.5 GiB
#: CPU seconds before the kernel kills a child (a hang); the goal is 5 s
CPU_KILL_S = 30
#: wall seconds before the alarm kills a child blocked on I/O (a FIFO)
WALL_KILL_S = 60


@dataclass(frozen=True)
class Outcome:
    """Exit code (negative: killed by that signal), stderr lines, stdout, child CPU s, peak RSS growth (bytes)."""
    code: int
    err: list
    out: str
    cpu_s: float
    rss_growth_b: int


def _status_b(key: str) -> int:
    """A size line of /proc/self/status (``VmSize``, ``VmRSS``) in bytes."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return 0


def run(argv, tmp_path, env=None) -> Outcome:
    """Run ``markcal argv`` in a forked, limited child; return what happened."""
    from markcal.pipeline.cli import main

    errf, outf = os.path.join(tmp_path, ".hostile_err"), os.path.join(tmp_path, ".hostile_out")
    sys.stdout.flush()
    sys.stderr.flush()
    rss0 = _status_b("VmRSS")
    pid = os.fork()
    if pid == 0:                                   # child
        code = 70
        try:
            limit = _status_b("VmSize") + AS_HEADROOM
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            resource.setrlimit(resource.RLIMIT_CPU, (CPU_KILL_S, CPU_KILL_S + 5))
            signal.alarm(WALL_KILL_S)
            fd_e = os.open(errf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            fd_o = os.open(outf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            os.dup2(fd_e, 2)
            os.dup2(fd_o, 1)
            sys.stderr = os.fdopen(2, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
            sys.stdout = os.fdopen(1, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
            for k, v in (env or {}).items():
                os.environ[k] = v
            try:
                code = main([os.fsdecode(a) if isinstance(a, bytes) else str(a) for a in argv])
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 2
            except BaseException:                  # a bug: show it in the test's failure message
                import traceback
                traceback.print_exc()
                code = 99
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(code if isinstance(code, int) else 70)
    _, status, ru = os.wait4(pid, 0)
    code = os.waitstatus_to_exitcode(status)
    with open(errf, encoding="utf-8", errors="replace") as fh:
        err = [line for line in fh.read().splitlines() if line.strip()]
    with open(outf, encoding="utf-8", errors="replace") as fh:
        out = fh.read()
    os.remove(errf)
    os.remove(outf)
    return Outcome(code, err, out, ru.ru_utime + ru.ru_stime, max(0, ru.ru_maxrss * 1024 - rss0))


def listing(folder) -> dict:
    """Every file under ``folder`` -> (size, mtime_ns), to tell that nothing was written or changed."""
    out = {}
    for root, _, files in os.walk(folder):
        for f in files:
            if f.startswith(".hostile_"):
                continue
            p = os.path.join(root, f)
            st = os.lstat(p)
            out[os.path.relpath(p, folder)] = (st.st_size, st.st_mtime_ns)
    return out


def assert_refused(o: Outcome, *needles, max_cpu_s: float = 5.0, max_rss_growth_b: int = 2 ** 30) -> None:
    """One line ``markcal: error: …`` holding every needle, exit 1, within the CPU and memory goals."""
    assert o.code == 1, (o.code, o.err[-15:])
    assert len(o.err) == 1, o.err[-15:]
    line = o.err[0]
    assert line.startswith("markcal: error: "), line
    assert "\x1b[" not in line, line
    for n in needles:
        assert n in line, (n, line)
    assert o.cpu_s < max_cpu_s, f"{o.cpu_s:.1f} CPU s: {line}"
    assert o.rss_growth_b < max_rss_growth_b, f"{o.rss_growth_b / 2 ** 20:.0f} MiB: {line}"


def finite_text(text: str) -> bool:
    """True when no nan/inf token (or a controller's int32 minimum) appears in a text output."""
    import re
    return not re.search(r"(?i)(?<![a-z])(nan|-?inf(inity)?)(?![a-z])|-2147483648", text)


def huge(x: float) -> bool:
    return not math.isfinite(x) or abs(x) > 1e12


# ----------------------------------------------------------------------------- scanning outputs

#: a number token in a text output, and the tokens that must never appear
NUMBER = re.compile(rb"(?<![\w.])-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)(?![\w.])")
NONFINITE = re.compile(rb"(?i)(?<![a-z_])(nan|-?inf(inity)?)(?![a-z_])")

#: where an output may hold an empty CSV cell or a JSON null (markcal writes NaN as both), with the doc that
#: says so: (file name pattern, column or key pattern, reference)
ALLOWED_EMPTY = (
    (r"^summary\.(csv|json)$", r"^(reason|failed_checks|checks|check_labels|spec|report|group)$",
     "docs/batch.md 'Outputs in OUT_DIR': reason (for errors), failed_checks/checks (limits applied), "
     "spec and report ('' if none), group ('' at the top)"),
    (r"^summary\.(csv|json)$", r"^runtime_s$", "docs/batch.md: runtime_s empty when reused"),
    (r"^summary\.(csv|json)$", r"^data_time$", "docs/batch.md: data_time \"\" when the file carries no timestamp"),
    (r"^summary\.(csv|json)$", r"^(n_low_hd|n_out_of_tolerance)$",
     "docs/indents.md summary.json: n_low_hd null without depths (micrographs), n_out_of_tolerance null "
     "without an array spec (no verdict on an inferred nominal)"),
    (r"^summary\.(csv|json)$", r"^(optics_resolution_um|n_near_resolution|optics_from|held_rim|held_rim_w|held_crease)$",
     "docs/indents.md summary.json: null for AFM maps and single-imprint micrographs (no fitted PSF)"),
    (r"^summary\.(csv|json)$", r"^(corner_level_nm|corner_level_weight)$",
     "docs/indents.md summary.json: corner_level_nm and corner_level_weight null when the map was not levelled to the "
     "surface beyond the corners"),
    (r"^summary\.(csv|json)$", r"^scan_lag_px$",
     "docs/indents.md summary.json: scan_lag_px null without the other scan direction, or where the two did not match"),
    (r"^summary\.(csv|json)$", r"^imprint_shift_px$",
     "docs/indents.md summary.json: imprint_shift_px null unless an array's retrace was not measured whole"),
    (r"^(summary\.(csv|json)|metrics\.csv|moves\.csv)$", r"^(settling_time_s|rise_time_s)$",
     "docs/servo.md summary.json and moves.csv: settling empty when a move never settles"),
    (r"^summary\.json$", r"^(settling_time|rise_time)_\w+$", "docs/servo.md: statistics over the settled moves"),
    (r"^(summary\.(csv|json)|metrics\.csv|traces\.csv)$",
     r"^(frequency_hz|phase_lag_deg|phase_lag_s|gain|overshoot_um|overshoot_pct|settle_band_um|settle_band_pct)$",
     "docs/servo.md metrics.csv/traces.csv: 'Empty = not applicable' (frequency for sines only); docs/batch.md: a "
     "null key (e.g. the overshoot of a tracking trace) is not applicable; settle_band_um or _pct, the other NaN"),
    (r"^summary\.json$", r"^(n_neurons|spread_mm|mse_goal_mm2|predicted_residual_\w*)$",
     "docs/scan.md summary.json: null for the galvo models"),
    (r"^(indents|sizes)\.csv$", r"^(row|col|dx_um|dy_um|depth_nm|hd_ratio|pileup_nm|pileup_volume_um3|apex_depth_nm|"
                                 r"area_um2|edge_bow|chipped_area_um2|hv|mean_hd|sd_hd|mean_depth_nm)$",
     "docs/indents.md indents.csv: row/col/dx/dy empty without a spec; heights (depth, H/D, pile-up, apex depth, "
     "area, edge bow, chipped area) empty for OM; area NaN when cut; hv empty without a load"),
    (r"^summary\.json$", r"^(mean_depth_nm|mean_hd|mean_pileup_nm|mean_apex_depth_nm|mean_area_um2|noise_nm|tilt_deg|"
                          r"mean_hv|load_mN)$",
     "docs/indents.md summary.json: the height figures are empty for OM; hv and the load without a load"),
)


def _allowed_empty(fname: str, key: str) -> bool:
    return any(re.search(f, fname) and re.search(k, key) for f, k, _ in ALLOWED_EMPTY)


def _row_allows(row: dict, key: str, key_columns: dict | None) -> bool:
    """A batch index row may leave empty the key figures of other flows, and its own when it failed to process
    (docs/batch.md: "then the key figures of the flows present"; status ``error``)."""
    if key_columns is None or "flow" not in row:
        return False
    all_keys = set().union(*key_columns.values())
    own = set(key_columns.get(row["flow"], ()))
    return key in all_keys and (key not in own or row.get("status") == "error")


def _json_nulls(obj, prefix="", parent=None):
    """(key, path, the dict holding it) of every null in a parsed JSON document."""
    if obj is None:
        yield prefix.rsplit(".", 1)[-1], prefix, parent
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _json_nulls(v, f"{prefix}.{k}" if prefix else str(k), obj)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _json_nulls(v, f"{prefix}[{i}]", parent)


def scan_outputs(folder, key_columns: dict | None = None) -> list:
    """Every problem in the text outputs under ``folder``: nan/inf tokens, numbers beyond ±1e15, and empty CSV
    cells or JSON nulls where :data:`ALLOWED_EMPTY` does not allow them.

    ``key_columns`` (flow -> its key-figure columns; default: every registered flow's) lets a row of the batch
    index (summary.csv, summary.json ``rows``) leave other flows' key figures empty, and its own when it failed.
    """
    import csv
    import io
    import json
    if key_columns is None:
        from markcal.pipeline.registry import all_flows
        key_columns = {n: f.descriptor.key_names for n, f in all_flows().items()}
    bad = []
    for root, _, files in os.walk(folder):
        for f in files:
            if not f.endswith((".csv", ".json", ".txt", ".cal")):
                continue
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                data = fh.read()
            if f.endswith(".json"):
                try:
                    doc = json.loads(data, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
                except ValueError as exc:
                    bad.append(f"{p}: {exc}")
                    doc = None
                bad += [f"{p}: null at {where}" for key, where, holder in _json_nulls(doc)
                        if not _allowed_empty(f, key) and not _row_allows(holder or {}, key, key_columns)]
            if f.endswith(".csv"):
                rows = list(csv.reader(io.StringIO(data.decode("utf-8", "replace"))))
                head = rows[0] if rows else []
                for r in rows[1:]:
                    row = dict(zip(head, r))
                    for k, v in row.items():
                        if v == "" and not _allowed_empty(f, k) and not _row_allows(row, k, key_columns):
                            msg = f"{p}: empty {k}"
                            if msg not in bad:
                                bad.append(msg)
            m = NONFINITE.search(data)
            if m:
                bad.append(f"{p}: {m.group(0)!r}")
            for tok in NUMBER.findall(data):
                if abs(float(tok)) > 1e15:
                    bad.append(f"{p}: {tok!r}")
                    break
    return bad


def grid_result(folder, seed: int = 3):
    """A grid flow result folder (render a measured grid, run ``markcal grid`` on it): a source for export."""
    from markcal.pipeline.cli import main
    folder = os.fspath(folder)
    assert main(["render", "grid", "--seed", str(seed), "--out", os.path.join(folder, "m"), "--quiet"]) == 0
    assert main(["grid", os.path.join(folder, "m", "measured.csv"), "--out", os.path.join(folder, "cal"), "--quiet",
                 "--no-report"]) in (0, 4)
    return os.path.join(folder, "cal")
