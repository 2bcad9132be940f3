"""Measured drive logs: reading CSV/TSV/whitespace logs, cutting them into moves, per-move metrics.

A drive log is a table with one row per controller sample: a time column, a
reference (target/demand) column and a measured position column, in any order
among other columns, with or without a header. :func:`read_log` turns it into
``t_s``, ``ref_mm``, ``pos_mm`` (units converted here, nowhere else) and
refuses bad logs with the line that is wrong. :func:`find_moves` cuts a log at
the reference's steps; :func:`move_metrics` and :func:`sine_metrics` measure.
Time s, positions mm, errors µm.
"""
from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass

import numpy as np

from markcal.stages.errors import MarkcalError
from markcal.stages.limits import check_file_ends, check_values, max_abs_for
from markcal.stages.servo_cases import dominant_frequency_hz
from markcal.stages.servo_sim import step_metrics

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
POS_UNITS = ("mm", "um", "counts")
#: a time step larger than this many median steps is a gap (samples missing)
MAX_GAP_SAMPLES = 10
#: a run of at least this many equal reference samples is a hold (between moves)
MIN_HOLD_SAMPLES = 10
COMMENT_CHARS = ("#", "%", ";", "//")


@dataclass(frozen=True)
class LogLayout:
    """How a log file is laid out: where its data start, its separator and header."""

    sep: str                  # "," "\t" ";" or "ws" (runs of blanks)
    header: tuple             # column names ((): no header row)
    first_data_line: int      # 1-based line number of the first data row
    n_fields: int             # fields on the first data (or header) line
    decimal: str = "."        # "," in semicolon-separated logs written with decimal commas


@dataclass(frozen=True)
class DriveLog:
    """A drive log in markcal's units, with where its rows came from."""

    t_s: np.ndarray
    ref_mm: np.ndarray
    pos_mm: np.ndarray
    columns: tuple            # (time, ref, pos) column names as found (or "#<index>")
    first_data_line: int


#: header names (lower case, units stripped) that say a column's role when the defaults are absent
ROLE_NAMES = {
    "time": ("t", "time", "timestamp", "t_s", "time_s", "zeit", "sample_time"),
    # in order of preference: the demand (profiled) position is what the loop follows; a target is its end point
    "reference": ("ref", "reference", "demand", "demand_pos", "pos_demand", "ref_pos", "x_ref", "xd", "desired",
                  "setpoint", "set_point", "command", "cmd", "pos_cmd", "position_cmd", "target", "target_pos"),
    "position": ("pos", "position", "actual", "act", "feedback", "fbk", "measured", "encoder", "enc",
                 "actual_pos", "pos_act", "position_actual", "x", "x_act", "pos_mm", "act_pos"),
}
_UNIT_SUFFIX = {"ms": "ms", "us": "us", "µs": "us", "s": "s", "mm": "mm", "um": "um", "µm": "um",
                "counts": "counts", "cnt": "counts", "inc": "counts"}


def _name_and_unit(header_field: str) -> tuple:
    """``"Time [ms]"`` / ``"time_ms"`` / ``"pos(um)"`` -> (``"time"``, ``"ms"``); unit None when absent."""
    h = header_field.strip().lower().replace(" ", "_")
    for open_, close in (("[", "]"), ("(", ")")):
        if h.endswith(close) and open_ in h:
            base, unit = h[:-1].rsplit(open_, 1)
            return base.strip("_"), _UNIT_SUFFIX.get(unit.strip("_"))
    if "_" in h:
        base, unit = h.rsplit("_", 1)
        if unit in _UNIT_SUFFIX:
            return base, _UNIT_SUFFIX[unit]
    return h, None


def guess_columns(header) -> dict:
    """The time, reference and position columns of a header by their names, with the units the names carry.

    Returns ``{role: (column name, unit or None)}``. Names are tried in the order
    of :data:`ROLE_NAMES` (a "demand" column wins over a "target" one); a name
    that two columns carry (two "actual" columns) is ambiguous and skipped. Used
    when a log lacks the default ``t_s``/``ref_mm``/``pos_mm`` columns.
    """
    parsed = [(h, *_name_and_unit(h)) for h in header]
    found = {}
    for role, names in ROLE_NAMES.items():
        for name in names:
            hits = [(h, unit) for h, base, unit in parsed if base == name or h.strip().lower() == name]
            if len(hits) == 1 and all(hits[0][0] != f[0] for f in found.values()):
                found[role] = hits[0]
                break
    return found


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _split(line: str, sep: str) -> list:
    if sep == "ws":
        return line.split()
    return [c.strip() for c in next(csv.reader(io.StringIO(line), delimiter=sep))]


def sniff_layout(path) -> LogLayout:
    """Find the separator, the header and the first data line of a log (reads its first lines).

    Leading blank lines and comment lines (``#``, ``%``, ``;``, ``//``) are skipped.
    The separator is a tab, a semicolon or a comma when the first line holds one
    (in that order), otherwise runs of blanks; decimal commas are recognised in
    tab-, semicolon- and blank-separated logs whose first data line has commas and no
    points. The first line is a header when one of its fields is not a number.
    """
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isfile(path):
        raise MarkcalError("not a regular file (a folder, FIFO or device)", path)
    try:
        with open(path, encoding="utf-8-sig", errors="strict", newline="") as fh:
            lineno = 0
            for raw in fh:
                lineno += 1
                line = raw.strip()
                if line and not line.startswith(COMMENT_CHARS):
                    break
                if lineno > 10000:
                    raise MarkcalError("no data in the first 10,000 lines (only blank or comment lines)", path)
            else:
                raise MarkcalError("empty log (no data lines)", path)
            data = line if _is_number(line.replace(",", ".").split()[0].split(";")[0].split("\t")[0]) \
                else fh.readline().strip()            # the first data line (after a header)
    except FileNotFoundError:
        raise MarkcalError("no such file", path) from None
    except UnicodeDecodeError:
        raise MarkcalError("not a text log (cannot decode as UTF-8)", path) from None
    except OSError as exc:
        raise MarkcalError(f"cannot read ({exc.strerror or exc})", path) from None
    sep = "\t" if "\t" in line else ";" if ";" in line else "," if "," in line else "ws"
    # "0,5;1,25": semicolons between fields, decimal commas inside them
    decimal = "," if sep in (";", "\t", "ws") and "," in data and "." not in data else "."
    fields = _split(line, sep)
    num = (lambda f: _is_number(f.replace(",", "."))) if decimal == "," else _is_number
    if all(num(f) for f in fields):
        return LogLayout(sep, (), lineno, len(fields), decimal)
    return LogLayout(sep, tuple(fields), lineno + 1, len(fields), decimal)


def _column_index(spec, layout: LogLayout, role: str, path) -> int:
    """Index of a column given by name (exact, then case-insensitive) or 0-based index."""
    s = str(spec).strip()
    if s.isdigit():
        i = int(s)
        if i >= layout.n_fields:
            raise MarkcalError(f"{role} column index {i} is out of range: the log has {layout.n_fields} columns "
                               f"(0-based indices 0..{layout.n_fields - 1})", path)
        return i
    if s in layout.header:
        return layout.header.index(s)
    low = [h.lower() for h in layout.header]
    if s.lower() in low:
        return low.index(s.lower())
    if not layout.header:
        raise MarkcalError(f"missing column(s) {s} ({role}): the log has no header row; give the column as a "
                           f"0-based index (0..{layout.n_fields - 1})", path)
    raise MarkcalError(f"missing column(s) {s} ({role}; header: {','.join(layout.header)})", path)


def _first_bad(raw, col: np.ndarray):
    """Index and text of the first cell of a parsed column that is not a finite number."""
    bad = np.flatnonzero(~np.isfinite(col))
    if raw is None or not len(bad):
        return (int(bad[0]) if len(bad) else None), None
    return int(bad[0]), raw[int(bad[0])]


def check_log_units(time_unit: str, pos_unit: str, counts_per_mm: float) -> None:
    """Refuse an unknown time or position unit, or counts without a positive finite counts per mm."""
    if time_unit not in TIME_UNITS:
        raise MarkcalError(f"time unit must be one of {', '.join(TIME_UNITS)} (got {time_unit!r})")
    if pos_unit not in POS_UNITS:
        raise MarkcalError(f"position unit must be one of {', '.join(POS_UNITS)} (got {pos_unit!r})")
    if pos_unit == "counts" and not (counts_per_mm > 0 and np.isfinite(counts_per_mm)):
        raise MarkcalError(f"positions in counts need a positive counts per mm (got {counts_per_mm:g})")


def read_log(path, time_col="t_s", ref_col="ref_mm", pos_col="pos_mm", time_unit="s", pos_unit="mm",
             counts_per_mm: float = 0.0, layout: LogLayout | None = None) -> DriveLog:
    """Read a drive log into time (s), reference and position (mm).

    Parameters
    ----------
    path : path
        CSV, TSV, semicolon- or whitespace-separated text, with or without a header row.
    time_col, ref_col, pos_col : str or int
        Column names or 0-based indices.
    time_unit : {"s", "ms", "us"}
        Unit of the time column.
    pos_unit : {"mm", "um", "counts"}
        Unit of the reference and position columns.
    counts_per_mm : float
        Encoder counts per mm (required when ``pos_unit == "counts"``).
    layout : LogLayout, optional
        The log's :func:`sniff_layout`, when the caller has read it already.

    Raises
    ------
    MarkcalError
        Unreadable file, a missing column, a cell that is not a finite number,
        fewer than 20 rows; the message names the line.
    """
    import pandas as pd

    path = os.fspath(path)
    check_log_units(time_unit, pos_unit, counts_per_mm)
    lay = layout or sniff_layout(path)
    check_file_ends(path)
    roles = (("time", time_col), ("reference", ref_col), ("position", pos_col))
    idx = [_column_index(spec, lay, role, path) for role, spec in roles]
    names = tuple(lay.header[i] if lay.header else f"#{i}" for i in idx)
    uniq = sorted(set(idx))
    kw = dict(sep=r"\s+" if lay.sep == "ws" else lay.sep, header=None, skiprows=lay.first_data_line - 1,
              usecols=uniq, skip_blank_lines=False, engine="c", comment=None, na_filter=True,
              keep_default_na=False, na_values=[""], encoding="utf-8-sig", decimal=lay.decimal)
    try:
        df = pd.read_csv(path, **kw)
    except pd.errors.EmptyDataError:
        raise MarkcalError("no data rows", path) from None
    except (pd.errors.ParserError, ValueError, UnicodeDecodeError) as exc:
        raise MarkcalError(f"cannot parse the log ({' '.join(str(exc).split())})", path) from None
    # blank lines at the end are not data
    n = len(df)
    while n and df.iloc[n - 1].isna().all():
        n -= 1
    df = df.iloc[:n]
    if n < 20:
        raise MarkcalError(f"log has {n} data rows; need at least 20", path)
    cols = {}
    for (role, _), i, name in zip(roles, idx, names):
        s = df[i]
        raw = None
        if not pd.api.types.is_numeric_dtype(s.dtype):
            raw = s.to_numpy(dtype=object)
            v = pd.to_numeric(s, errors="coerce").to_numpy(dtype=float)
        else:
            v = s.to_numpy(dtype=float)
        k, cell = _first_bad(raw, v)
        if k is not None:
            line = lay.first_data_line + k
            if df.iloc[k].isna().all():
                raise MarkcalError(f"line {line} is blank (a data line is missing)", path)
            if cell is None and np.isnan(v[k]):
                cell = ""
            what = f"{cell!r} is not a number" if cell is not None else f"{v[k]} is not a finite number"
            raise MarkcalError(f"line {line}: {name} = {what}", path)
        cols[role] = v
    scale = 1.0 if pos_unit == "mm" else 1e-3 if pos_unit == "um" else 1.0 / counts_per_mm
    for (role, _), name, unit, f in zip(roles, names, ("_s", "_mm", "_mm"),
                                        (TIME_UNITS[time_unit], scale, scale)):
        check_values(cols[role] * f, f"{name} (in{unit.replace('_', ' ')})", path, lay.first_data_line,
                     limit=max_abs_for(unit))
    return DriveLog(t_s=cols["time"] * TIME_UNITS[time_unit], ref_mm=cols["reference"] * scale,
                    pos_mm=cols["position"] * scale, columns=names, first_data_line=lay.first_data_line)


#: the shortest median sample step accepted, s (no drive log is sampled faster than 1 GHz)
MIN_STEP_S = 1e-9


def check_log(log: DriveLog, path=None) -> float:
    """Refuse time out of order or repeated, gaps over 10 samples, a reference that never moves.

    Returns the median sample step, s.
    """
    t, first = log.t_s, log.first_data_line
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if len(bad):
        i = int(bad[0])
        what = "repeats the time" if dt[i] == 0 else "goes back in time"
        raise MarkcalError(f"out of time order: line {first + i + 1} {what}: {log.columns[0]} = {t[i + 1]:.9g} s "
                           f"after {t[i]:.9g} s on line {first + i} (times must increase)", path)
    med = float(np.median(dt))
    if med < MIN_STEP_S:
        raise MarkcalError(f"median sample step {med:.3g} s is below {MIN_STEP_S:g} s (a 1 GHz log): is the time "
                           "unit right (--time-unit)?", path)
    gaps = np.flatnonzero(dt > MAX_GAP_SAMPLES * med)
    if len(gaps):
        i = int(gaps[0])
        raise MarkcalError(f"gap in the trace at line {first + i + 1}: step {dt[i]:.6g} s = {dt[i] / med:.1f} "
                           f"samples after line {first + i} (median step {med:.6g} s; more than "
                           f"{MAX_GAP_SAMPLES} samples missing)", path)
    if np.ptp(log.ref_mm) == 0:
        raise MarkcalError(f"the reference ({log.columns[1]}) never moves: {log.ref_mm[0]:g} mm on every line "
                           f"(lines {first}-{first + len(t) - 1}); is --ref-col the right column?", path)
    return med


@dataclass(frozen=True)
class Moves:
    """Moves of a log, as sample indices.

    ``lo[k]``: last sample before move k (reference at its start value);
    ``end[k]``: first sample with the reference at its final value (end of the
    reference's move); ``hi[k]``: last sample of the hold after it.
    """

    lo: np.ndarray
    end: np.ndarray
    hi: np.ndarray
    hold_fraction: float      # share of the samples in holds
    dropped_tail: bool        # the log ends while the reference moves (that move is not measured)


def find_moves(ref_mm: np.ndarray, min_hold: int = MIN_HOLD_SAMPLES) -> Moves:
    """Cut a reference into moves at its steps: a move runs from one hold to the next.

    A hold is a run of at least ``min_hold`` equal reference samples; a move is
    what lies between two holds (or between the start of the log and the first
    hold). Moves whose start and end values are equal are skipped.
    """
    n = len(ref_mm)
    change = np.flatnonzero(np.diff(ref_mm) != 0)          # ref[i+1] != ref[i]
    starts = np.concatenate(([0], change + 1))              # first sample of each constant run
    stops = np.concatenate((change, [n - 1]))               # last sample of each constant run
    hold = (stops - starts + 1) >= min_hold
    hs, he = starts[hold], stops[hold]
    lo, end, hi = [], [], []
    if len(hs) and hs[0] > 0:                               # the log starts moving
        lo.append(0), end.append(hs[0]), hi.append(he[0])
    for j in range(len(hs) - 1):
        lo.append(he[j]), end.append(hs[j + 1]), hi.append(he[j + 1])
    lo, end, hi = (np.asarray(x, dtype=np.int64) for x in (lo, end, hi))
    keep = ref_mm[end] != ref_mm[lo]
    return Moves(lo[keep], end[keep], hi[keep], float(np.sum(he - hs + 1)) / n if n else 0.0,
                 bool(len(he) and he[-1] < n - 1))


MOVE_COLUMNS = ("move", "t_start_s", "t_end_s", "start_mm", "stroke_mm", "rise_time_s", "settling_time_s",
                "overshoot_um", "overshoot_pct", "steady_state_error_um", "settle_band_um", "mae_um", "std_um")


def _crossing_time(t, y, level, k0):
    """First time from sample ``k0`` on where ``y`` reaches ``level`` (linear between samples), or NaN."""
    above = np.flatnonzero(y[k0:] >= level)
    if not len(above):
        return float("nan")
    k = k0 + int(above[0])
    if k == 0 or y[k] == y[k - 1] or k == k0:
        return float(t[k])
    f = (level - y[k - 1]) / (y[k] - y[k - 1])
    return float(t[k - 1] + f * (t[k] - t[k - 1]))


def move_metrics(t_s, ref_mm, pos_mm, moves: Moves, band_um: float | None = None,
                 band_pct: float | None = None, ss_fraction: float = 0.2) -> dict:
    """Per-move metrics as columns (see ``MOVE_COLUMNS``).

    Parameters
    ----------
    t_s, ref_mm, pos_mm : (n,) arrays
        Time (s), reference and measured position (mm).
    moves : Moves
        From :func:`find_moves`.
    band_um, band_pct : float
        Settling band half width in µm, or in % of each move's stroke (one of them).
    ss_fraction : float
        Steady-state error: mean of reference − position over this last share of the hold.

    Notes
    -----
    Rise time: 10 % to 90 % of the stroke, from the start of the move. Settling time:
    from the end of the reference's move until the position stays within the band of
    the target. Overshoot: largest excursion past the target in the move's direction.
    """
    cols = {c: np.full(len(moves.lo), np.nan) for c in MOVE_COLUMNS}
    for k, (lo, end, hi) in enumerate(zip(moves.lo, moves.end, moves.hi)):
        w = slice(lo, hi + 1)
        t, r, p = t_s[w], ref_mm[w], pos_mm[w]
        start, target = r[0], r[-1]
        stroke = target - start
        band = band_um if band_pct is None else abs(stroke) * 1e3 * band_pct / 100.0
        m = step_metrics(t, r, p, float(t_s[end]), band)
        y = (p - start) / stroke                              # normalised response, 0 -> 1
        t10, t90 = _crossing_time(t, y, 0.1, 1), _crossing_time(t, y, 0.9, 1)
        n_ss = max(1, int(ss_fraction * (hi - end + 1)))
        cols["move"][k] = k + 1
        cols["t_start_s"][k] = t_s[lo + 1]
        cols["t_end_s"][k] = t_s[end]
        cols["start_mm"][k] = start
        cols["stroke_mm"][k] = stroke
        cols["rise_time_s"][k] = t90 - t10
        cols["settling_time_s"][k] = m.settling_time_s
        cols["overshoot_um"][k] = m.overshoot_um
        cols["overshoot_pct"][k] = m.overshoot_um / (abs(stroke) * 1e3) * 100.0
        cols["steady_state_error_um"][k] = float(np.mean(target - p[-n_ss:])) * 1e3
        cols["settle_band_um"][k] = band
        cols["mae_um"][k] = m.mae_um
        cols["std_um"][k] = m.std_um
    return cols


def move_statistics(cols: dict, keys=("rise_time_s", "settling_time_s", "overshoot_um", "overshoot_pct",
                                      "steady_state_error_um")) -> dict:
    """Mean, STD, median, min, max and count of finite values over the moves, flat ``<key>_<stat>`` names.

    Keys ending in a unit keep it at the end (``settling_time_mean_s``).
    """
    out = {}
    for key in keys:
        v = np.asarray(cols[key], float)
        v = v[np.isfinite(v)]
        base, unit = key.rsplit("_", 1)
        for stat, fn in (("mean", np.mean), ("std", np.std), ("median", np.median), ("min", np.min),
                         ("max", np.max)):
            out[f"{base}_{stat}_{unit}"] = float(fn(v)) if len(v) else float("nan")
        out[f"{base}_n"] = int(len(v))
    return out


@dataclass(frozen=True)
class SineMetrics:
    """Tracking of a sinusoidal reference over whole periods."""

    frequency_hz: float
    amplitude_mm: float       # of the reference
    gain: float               # position amplitude / reference amplitude
    phase_lag_deg: float      # position behind reference (> 0: lags)
    phase_lag_s: float
    mae_um: float
    std_um: float
    window: slice             # the whole periods evaluated


def _fit_sine(t, x, f):
    a = np.column_stack((np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t)))
    c, res, *_ = np.linalg.lstsq(a, x, rcond=None)
    return c, float(res[0]) if len(res) else float(np.sum((a @ c - x) ** 2))


def sine_metrics(t_s, ref_mm, pos_mm) -> SineMetrics:
    """Frequency, amplitude, gain, phase lag, MAE and STD of a sinusoidal tracking log.

    The frequency is the FFT peak of the reference refined by least squares
    (a sine fitted to the reference); gain and phase from sines fitted to the
    reference and the position at that frequency; MAE and STD of reference −
    position over the whole periods from the start of the log.
    """
    from scipy.optimize import minimize_scalar

    f0 = dominant_frequency_hz(t_s, ref_mm)
    dur = float(t_s[-1] - t_s[0])
    dec = max(1, len(t_s) // 200_000)
    td, rd = t_s[::dec] - t_s[0], ref_mm[::dec]
    span = 2.0 / dur
    f = minimize_scalar(lambda ff: _fit_sine(td, rd, ff)[1], bounds=(max(f0 - span, 0.5 * f0), f0 + span),
                        method="bounded", options={"xatol": 1e-7 * f0}).x
    k = int(np.floor(dur * f + 1e-9))
    if k >= 1:
        win = slice(0, int(np.searchsorted(t_s, t_s[0] + k / f, side="left")))
    else:
        win = slice(None)
    t = t_s[win] - t_s[0]
    cr, _ = _fit_sine(t, ref_mm[win], f)
    cp, _ = _fit_sine(t, pos_mm[win], f)
    ar, ap = np.hypot(cr[0], cr[1]), np.hypot(cp[0], cp[1])
    lag = np.degrees(np.arctan2(cr[1], cr[0]) - np.arctan2(cp[1], cp[0]))
    lag = float((lag + 180.0) % 360.0 - 180.0)
    e_um = (ref_mm[win] - pos_mm[win]) * 1e3
    return SineMetrics(float(f), float(ar), float(ap / ar), lag, lag / 360.0 / f, float(np.mean(np.abs(e_um))),
                       float(np.std(e_um)), win)
