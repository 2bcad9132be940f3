"""Drive logs (issue 15 parts 3-4): reading layouts and units, moves against the analytic truth, sine phase lag, bad logs."""
import json

import numpy as np
import pytest

from markcal.fixtures.servo_log import LogOptions, render_servo_log, save_servo_log, step_response
from markcal.pipeline.cli import main
from markcal.pipeline.registry import get_flow
from markcal.reports.files import read_csv


def _flags(read: dict) -> list:
    out = []
    for k, v in read.items():
        out += [f"--{k.replace('_', '-')}", f"{v:g}" if isinstance(v, float) else str(v)]
    return out


def _run(tmp_path, opts, seed=1, extra=(), name="log"):
    r = render_servo_log(seed, opts)
    ext = {"csv": "csv", "tsv": "tsv", "ws": "txt"}[opts.layout]
    p = tmp_path / f"{name}.{ext}"
    read = save_servo_log(p, r)
    out = tmp_path / f"{name}_out"
    rc = main(["servo", "--trace", str(p), *_flags(read), "--out", str(out), "--quiet", "--no-report", *extra])
    assert rc in (0, 4)
    return r, out


def test_renderer_truth_is_the_textbook_second_order_response():
    # an isolated step: overshoot exp(-zeta pi / sqrt(1 - zeta^2)), peak at pi / wd (independent of the flow)
    z, fn = 0.3, 50.0
    wn = 2 * np.pi * fn
    wd = wn * np.sqrt(1 - z * z)
    assert abs(step_response(np.pi / wd, wn, z) - 1 - np.exp(-z * np.pi / np.sqrt(1 - z * z))) < 1e-12
    assert abs(step_response(0.0, wn, z)) < 1e-15 and abs(step_response(1.0, wn, z) - 1) < 1e-12
    for zz in (1.0, 1.5):                                    # critically and over-damped: monotone, no overshoot
        y = step_response(np.linspace(0, 0.2, 2001), wn, zz)
        assert np.all(np.diff(y) >= -1e-15) and y.max() <= 1.0
    r = render_servo_log(3, LogOptions(zeta=z, fn_hz=fn, noise_nm=0, jitter=0, n_moves=2))
    for m in r.truth["moves"]:
        assert abs(m["overshoot_pct"] / 100 - np.exp(-z * np.pi / np.sqrt(1 - z * z))) < 1e-6
    assert np.array_equal(r.pos_mm, render_servo_log(3, LogOptions(zeta=z, fn_hz=fn, noise_nm=0, jitter=0,
                                                                   n_moves=2)).pos_mm)


CASES = [
    # kind, layout, time unit, position unit, zeta, dc gain
    ("square", "csv", "s", "mm", 0.4, 1.0),
    ("steps", "tsv", "ms", "counts", 0.25, 0.999),
    ("steps", "ws", "us", "um", 0.7, 1.0),
    ("square", "tsv", "ms", "um", 1.3, 1.0),
]


@pytest.mark.parametrize("kind,layout,tu,pu,zeta,k", CASES)
def test_moves_against_truth(tmp_path, kind, layout, tu, pu, zeta, k):
    opts = LogOptions(kind=kind, layout=layout, time_unit=tu, pos_unit=pu, zeta=zeta, dc_gain=k, n_moves=6,
                      hold_s=0.25 if zeta > 1 else 0.15, noise_nm=5.0, jitter=0.2, band_um=5.0)
    r, out = _run(tmp_path, opts, extra=["--settle-band-um", "5"])
    m = read_csv(out / "moves.csv")
    truth = r.truth["moves"]
    dt = r.truth["max_step_s"]                              # one sample of this (jittered) log
    res_um = 10e-3 if pu == "counts" else 1e-3
    assert len(m["move"]) == len(truth) == 6
    for i, t in enumerate(truth):
        assert abs(m["stroke_mm"][i] - t["stroke_mm"]) < 1e-9
        assert abs(m["t_end_s"][i] - t["t_step_s"]) < 1e-12
        # settling time and rise time within one sample
        assert abs(m["settling_time_s"][i] - t["settling_time_s"]) <= dt, (i, m["settling_time_s"][i], t)
        assert abs(m["rise_time_s"][i] - t["rise_time_s"]) <= dt
        # overshoot within 1 % (of itself; an over-damped move has none: within noise and resolution)
        if t["overshoot_um"] > 1.0:
            assert abs(m["overshoot_um"][i] / t["overshoot_um"] - 1) < 0.01, (i, m["overshoot_um"][i], t)
        else:
            assert m["overshoot_um"][i] <= t["overshoot_um"] + 4 * 5e-3 + res_um
        # steady-state error: the static gain's (1 - K) x target, within noise / sqrt(n) and the resolution
        assert abs(m["steady_state_error_um"][i] - t["steady_state_error_um"]) < 0.01 + res_um
    s = json.loads((out / "summary.json").read_text())
    assert s["trace_kind"] == "move" and s["n_moves"] == 6 and s["n_settled"] == 6
    ts = [t["settling_time_s"] for t in truth]
    assert abs(s["settling_time_median_s"] - np.median(ts)) <= dt
    assert abs(s["settling_time_s"] - max(ts)) <= dt
    assert abs(s["overshoot_um"] - max(t["overshoot_um"] for t in truth)) <= max(0.01 * max(t["overshoot_um"] for t in truth), 0.03)


def test_band_in_percent_of_stroke(tmp_path):
    opts = LogOptions(kind="steps", n_moves=5, zeta=0.5, band_um=1.0, noise_nm=2.0)
    r = render_servo_log(4, opts)
    p = tmp_path / "log.csv"
    read = save_servo_log(p, r)
    out = tmp_path / "o"
    assert main(["servo", "--trace", str(p), *_flags(read), "--settle-band-pct", "0.5", "--out", str(out), "--quiet",
                 "--no-report"]) in (0, 4)
    m = read_csv(out / "moves.csv")
    # each move's band is 0.5 % of its own stroke; check the settling against the truth rendered with that band
    for i, stroke in enumerate(m["stroke_mm"]):
        assert abs(m["settle_band_um"][i] - abs(stroke) * 5.0) < 1e-9
        ri = render_servo_log(4, LogOptions(**{**r.truth["options"], "band_um": abs(stroke) * 5.0}))
        assert abs(m["settling_time_s"][i] - ri.truth["moves"][i]["settling_time_s"]) <= ri.truth["max_step_s"]


@pytest.mark.parametrize("layout,tu,pu", [("csv", "s", "mm"), ("tsv", "ms", "counts"), ("ws", "us", "um")])
def test_sine_against_truth(tmp_path, layout, tu, pu):
    opts = LogOptions(kind="sine", layout=layout, time_unit=tu, pos_unit=pu, amplitude_mm=2.0, frequency_hz=5.0,
                      periods=4, fn_hz=40.0, zeta=0.5, noise_nm=5.0, jitter=0.2)
    r, out = _run(tmp_path, opts)
    s = json.loads((out / "summary.json").read_text())
    t = r.truth["sine"]
    assert s["trace_kind"] == "tracking"
    assert abs(s["frequency_hz"] / t["frequency_hz"] - 1) < 1e-4
    assert abs(s["phase_lag_deg"] - t["phase_lag_deg"]) < 0.02          # truth 14.6 deg here
    assert abs(s["phase_lag_s"] - t["phase_lag_s"]) < 0.02 / 360 / 5.0
    assert abs(s["gain"] - t["gain"]) < 1e-4
    # MAE / STD over whole periods within 1 % (the error's amplitude is ~0.5 mm; noise 5 nm)
    assert abs(s["mae_um"] / t["mae_um"] - 1) < 0.01
    assert abs(s["std_um"] / t["std_um"] - 1) < 0.01


def test_default_csv_claimed_and_batch_options(tmp_path):
    flow = get_flow("servo")
    r = render_servo_log(2, LogOptions(n_moves=2))
    p = tmp_path / "log.csv"
    save_servo_log(p, r)
    assert p.read_text().startswith("t_s,ref_mm,pos_mm\n") and flow.descriptor.claims(p)
    from markcal.fixtures.servo_trace import render_servo_trace, save_servo_trace
    assert flow.descriptor.claims(save_servo_trace(tmp_path / "trace.csv", render_servo_trace(1)))
    o = LogOptions(n_moves=2, layout="tsv", time_unit="ms")
    rt = render_servo_log(2, o)
    tsv = tmp_path / "drive.tsv"
    read = save_servo_log(tsv, rt)
    assert flow.descriptor.claims(tsv)            # time / target / demand / actual: found by name
    # the options batch.toml can set are the descriptor's (typed like its defaults)
    d = flow.descriptor.options
    assert {k: type(v) for k, v in read.items()} == {k: type(d[k]) for k in read}
    from markcal.pipeline.registry import run_and_write
    res, paths = run_and_write("servo", str(tsv), str(tmp_path / "b"), options={**read, "settle_band_um": 5.0})
    assert res.summary["n_moves"] == 2
    assert abs(res.summary["settling_time_s"] - max(m["settling_time_s"] for m in rt.truth["moves"])) \
        <= rt.truth["max_step_s"]


def test_batch_claims_logs_with_their_own_headers(tmp_path):
    """A drive log named otherwise (time_ms, demand, actual; a "Time [ms]" header) is claimed by the
    batch and measured right with no options; batch.toml's [servo] options read the rest."""
    from markcal.pipeline.cli import main as cli
    import csv as _csv
    inp = tmp_path / "in"
    inp.mkdir()
    r = render_servo_log(3, LogOptions(n_moves=3, time_unit="ms", jitter=0.0))
    t_ms, ref, pos = r.t_s * 1e3, r.ref_mm, r.pos_mm
    with open(inp / "axis_x.csv", "w", newline="") as fh:          # unit in the name: no option needed
        w = _csv.writer(fh)
        w.writerow(["sample", "time_ms", "target", "demand", "actual"])
        w.writerows([i, f"{a:.4f}", f"{b:.6f}", f"{b:.6f}", f"{c:.6f}"] for i, (a, b, c) in enumerate(zip(t_ms, ref, pos)))
    with open(inp / "axis_y.tsv", "w", newline="") as fh:          # units in brackets, positions in µm
        fh.write("Time [ms]\tSetpoint [um]\tPosition [um]\n")
        fh.writelines(f"{a:.4f}\t{b * 1e3:.3f}\t{c * 1e3:.3f}\n" for a, b, c in zip(t_ms, ref, pos))
    with open(inp / "notes.csv", "w") as fh:                       # a table that is not a drive log
        fh.write("name,value,comment\na,1,x\n")
    (tmp_path / "batch.toml").write_text('[servo]\nsettle_band_um = 5.0\n')
    out = tmp_path / "out"
    assert cli(["batch", str(inp), "--out", str(out), "--config", str(tmp_path / "batch.toml"), "--workers", "1",
                "--quiet"]) in (0, 3)
    rows = {row["name"]: row for row in _csv.DictReader(open(out / "summary.csv")) if row["flow"] == "servo"}
    assert set(rows) == {"axis_x", "axis_y"}                       # notes.csv is not taken for a drive log
    truth = max(m["settling_time_s"] for m in r.truth["moves"])
    for name in rows:
        s = json.load(open(out / name / "summary.json"))
        assert s["n_moves"] == 3 and s["time_unit"] == "ms"
        assert abs(s["settling_time_s"] - truth) <= r.truth["max_step_s"], (name, s["settling_time_s"], truth)
    assert json.load(open(out / "axis_x" / "summary.json"))["ref_col"] == "demand"
    assert json.load(open(out / "axis_y" / "summary.json"))["pos_unit"] == "um"


def test_guess_columns_by_name():
    from markcal.stages.servo_log import guess_columns
    g = guess_columns(("sample", "Time [ms]", "target", "demand", "actual", "current_A"))
    assert g == {"time": ("Time [ms]", "ms"), "reference": ("demand", None), "position": ("actual", None)}
    assert guess_columns(("t_us", "setpoint", "pos(um)")) == {"time": ("t_us", "us"), "reference": ("setpoint", None),
                                                             "position": ("pos(um)", "um")}
    # two position columns of the same name: ambiguous, not guessed
    assert "position" not in guess_columns(("time", "target", "actual", "Actual"))
    assert guess_columns(("name", "value", "comment")) == {}


def test_trace_reads_the_header_once(tmp_path, monkeypatch):
    """A log whose columns are found by name (time_ms, demand, actual): its header is sniffed once, and the
    units the names carry reach the summary."""
    from markcal.pipeline.flows import servo as servo_flow
    from markcal.stages import servo_log
    r = render_servo_log(3, LogOptions(n_moves=2, time_unit="ms", jitter=0.0))
    p = tmp_path / "axis.csv"
    with open(p, "w") as fh:
        fh.write("time_ms,demand,actual\n")
        fh.writelines(f"{a * 1e3:.4f},{b:.6f},{c:.6f}\n" for a, b, c in zip(r.t_s, r.ref_mm, r.pos_mm))
    calls, sniff = [], servo_log.sniff_layout
    counting = lambda path: calls.append(path) or sniff(path)                  # noqa: E731
    monkeypatch.setattr(servo_log, "sniff_layout", counting)
    monkeypatch.setattr(servo_flow, "sniff_layout", counting)
    res = servo_flow.run_servo_trace(p)
    assert len(calls) == 1
    s = res.summary
    assert (s["time_col"], s["ref_col"], s["pos_col"], s["time_unit"], s["n_moves"]) == \
        ("time_ms", "demand", "actual", "ms", 2)


def test_columns_by_index_and_case(tmp_path, capsys):
    r = render_servo_log(5, LogOptions(n_moves=2, layout="tsv"))
    p = tmp_path / "d.tsv"
    save_servo_log(p, r)
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["servo", "--trace", str(p), "--time-col", "TIME", "--ref-col", "Target", "--pos-col", "actual",
                 "--out", str(a), "--quiet", "--no-report"]) in (0, 4)
    assert main(["servo", "--trace", str(p), "--time-col", "0", "--ref-col", "1", "--pos-col", "3",
                 "--out", str(b), "--quiet", "--no-report"]) in (0, 4)
    assert (a / "moves.csv").read_bytes() == (b / "moves.csv").read_bytes()
    # the demand column (one sample late) is a different reference: every step is one sample later
    c = tmp_path / "c"
    assert main(["servo", "--trace", str(p), "--time-col", "0", "--ref-col", "demand", "--pos-col", "3",
                 "--out", str(c), "--quiet", "--no-report"]) in (0, 4)
    ma, mc = read_csv(a / "moves.csv"), read_csv(c / "moves.csv")
    assert np.all(mc["t_end_s"] > ma["t_end_s"])


def test_semicolon_decimal_comma_crlf_bom(tmp_path):
    r = render_servo_log(8, LogOptions(n_moves=3, noise_nm=2.0))
    p = tmp_path / "log.csv"
    save_servo_log(p, r)
    out_a = tmp_path / "a"
    assert main(["servo", "--trace", str(p), "--settle-band-um", "5", "--out", str(out_a), "--quiet",
                 "--no-report"]) in (0, 4)
    text = p.read_text().replace(",", ";").replace(".", ",").replace("\n", "\r\n")
    q = tmp_path / "eu.csv"
    q.write_bytes(b"\xef\xbb\xbf" + b"# exported by a drive tool\r\n" + text.encode())
    out_b = tmp_path / "b"
    assert main(["servo", "--trace", str(q), "--settle-band-um", "5", "--out", str(out_b), "--quiet",
                 "--no-report"]) in (0, 4)
    assert (out_a / "moves.csv").read_bytes() == (out_b / "moves.csv").read_bytes()


# ------------------------------------------------------------------ bad logs

def _lines(n=200):
    t = np.arange(n) * 1e-3
    ref = np.where((np.arange(n) // 50) % 2 == 1, 1.0, 0.0)
    return ["t_s,ref_mm,pos_mm"] + [f"{a:.6f},{b:.6f},{b * 0.99:.6f}" for a, b in zip(t, ref)]


def _bad(kind):
    lines = _lines()
    args = []
    if kind == "back":
        lines[101] = "0.090000" + lines[101][8:]
        needle = "out of time order: line 102 goes back in time"
    elif kind == "repeat":
        lines[120] = lines[119].split(",")[0] + "," + ",".join(lines[120].split(",")[1:])
        needle = "out of time order: line 121 repeats the time"
    elif kind == "gap":
        del lines[60:71]                                     # 11 samples missing: a step of 12
        needle = "gap in the trace at line 61: step 0.012 s = 12.0 samples after line 60"
    elif kind == "missing":
        lines = [",".join(x.split(",")[:2]) for x in lines]
        needle = "missing column(s) pos_mm (position"
    elif kind == "text":
        lines[77] = lines[77].rsplit(",", 1)[0] + ",n/a"
        needle = "line 78: pos_mm = 'n/a' is not a number"
    elif kind == "flat":
        lines = ["t_s,ref_mm,pos_mm"] + [f"{i * 1e-3:.6f},2.5,2.5" for i in range(100)]
        needle = "the reference (ref_mm) never moves: 2.5 mm on every line (lines 2-101)"
    elif kind == "index":
        args = ["--pos-col", "7"]
        needle = "position column index 7 is out of range: the log has 3 columns"
    elif kind == "blank":
        lines[50] = ""
        needle = "line 51 is blank"
    elif kind == "counts":
        args = ["--pos-unit", "counts"]
        needle = "positions in counts need a positive counts per mm"
    return "\n".join(lines) + "\n", needle, args


@pytest.mark.parametrize("kind", ["back", "repeat", "gap", "missing", "text", "flat", "index", "blank",
                                  "counts"])
def test_bad_logs_refused(tmp_path, capsys, kind):
    text, needle, args = _bad(kind)
    p = tmp_path / "bad.csv"
    p.write_text(text)
    out = tmp_path / "o"
    assert main(["servo", "--trace", str(p), *args, "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: "), err
    assert needle in err[0], err
    if kind not in ("counts",):
        assert str(p) in err[0]
    assert not (out / "summary.json").exists()


def test_small_gap_accepted(tmp_path):
    lines = _lines()
    del lines[60:68]                                         # 8 samples missing: accepted (not more than 10)
    p = tmp_path / "ok.csv"
    p.write_text("\n".join(lines) + "\n")
    assert main(["servo", "--trace", str(p), "--out", str(tmp_path / "o"), "--quiet", "--no-report"]) in (0, 4)


def test_log_options_refused_without_trace(tmp_path, capsys):
    assert main(["servo", "--time-col", "t", "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "--time-col: only with --trace LOG" in capsys.readouterr().err


def test_report_shows_every_move_overlaid(tmp_path):
    r = render_servo_log(6, LogOptions(kind="steps", n_moves=4, layout="ws", time_unit="us"))
    p = tmp_path / "log.txt"
    read = save_servo_log(p, r)
    out = tmp_path / "o"
    assert main(["servo", "--trace", str(p), *_flags(read), "--out", str(out), "--quiet"]) in (0, 4)
    html = (out / "report.html").read_text()
    assert html.count("<img") == 2 and 'alt="moves overlaid"' in html and "Statistics over the moves" in html
    assert html.count("<tr>") >= 4 + 5 and "src=\"http" not in html
    assert json.loads((out / "summary.json").read_text())["outputs"] == sorted(
        ["metrics.csv", "moves.csv", "traces.csv", "report.html"])
    m = read_csv(out / "metrics.csv")
    assert list(m["case"]) == ["trace"] * 4 and np.allclose(m["amplitude_mm"], np.abs([t["stroke_mm"] for t in r.truth["moves"]]))
