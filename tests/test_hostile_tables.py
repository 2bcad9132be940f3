"""Hostile CSV/JSON inputs of pmcal, drift, path and servo (issue 17): one line naming the file, exit 1,
nothing written, under 5 CPU s and 1 GiB, each run in a limited child (tests/hostile_run.py)."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from hostile_run import assert_refused, listing, run, scan_outputs
from markcal.pipeline.cli import main


@pytest.fixture(scope="module")
def pm_session(tmp_path_factory):
    d = tmp_path_factory.mktemp("pm") / "s"
    assert main(["render", "pmcal", "--seed", "1", "--pose-grid", "4", "--out", str(d), "--quiet"]) == 0
    return d


@pytest.fixture(scope="module")
def drift_csv(tmp_path_factory):
    p = tmp_path_factory.mktemp("dr") / "drift.csv"
    t = np.arange(12.0) * 5
    p.write_text("t_min,dx_um,dy_um,dz_um\n" + "".join(f"{a:g},{0.01 * a:g},{-0.02 * a:g},0.001\n" for a in t))
    return p


def _copy(src, tmp_path):
    dst = tmp_path / "s"
    shutil.copytree(src, dst)
    return dst


def _set_cell(path, line: int, col: int, value: str) -> None:
    lines = path.read_text().splitlines()
    cells = lines[line - 1].split(",")
    cells[col] = value
    lines[line - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


def _refused_nothing_written(argv, tmp_path, out, *needles):
    before = listing(tmp_path)
    o = run(argv, tmp_path)
    assert_refused(o, *needles)
    assert not os.path.exists(out) or not os.listdir(out), os.listdir(out)
    after = listing(tmp_path)
    assert after == before, set(after) ^ set(before)
    return o


# ----------------------------------------------------------------------------- pmcal

@pytest.mark.parametrize("name,line,col,value,needle", [
    ("axes.csv", 3, 1, "1e308", "line 3"),
    ("axes.csv", 2, 4, "-1e300", "line 2"),
    ("pose.csv", 4, 1, "1e308", "line 4"),
    ("probe.csv", 2, 2, "inf", "line 2"),
    ("probe.csv", 3, 2, "nan", "line 3"),
    ("drift.csv", 2, 1, "1e308", "line 2"),
])
def test_pmcal_huge_or_nonfinite_cell(pm_session, tmp_path, name, line, col, value, needle):
    s = _copy(pm_session, tmp_path)
    _set_cell(s / name, line, col, value)
    _refused_nothing_written(["pmcal", str(s), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             name, needle)


def test_pmcal_csv_cut_inside_last_row(pm_session, tmp_path):
    s = _copy(pm_session, tmp_path)
    text = (s / "axes.csv").read_text()
    (s / "axes.csv").write_text(text[:-4])                  # the last value shortened, no final newline
    _refused_nothing_written(["pmcal", str(s), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "axes.csv", "truncated")


def test_pmcal_row_with_extra_fields(pm_session, tmp_path):
    s = _copy(pm_session, tmp_path)
    lines = (s / "pose.csv").read_text().splitlines()
    lines[3] += ",7"
    (s / "pose.csv").write_text("\n".join(lines) + "\n")
    _refused_nothing_written(["pmcal", str(s), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "pose.csv", "line 4")


def test_pmcal_command_depth_huge(pm_session, tmp_path):
    targets = tmp_path / "t.csv"
    targets.write_text("x_um,y_um\n0,0\n100,50\n")
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"not": "a calibration"}))
    o = run(["pmcal", "command", str(cal), str(targets), "--depth-um", "1e300", "--out", str(tmp_path / "c.csv")],
            tmp_path)
    assert_refused(o, "--depth-um")
    assert not (tmp_path / "c.csv").exists()


# ----------------------------------------------------------------------------- drift

@pytest.mark.parametrize("value", ["1e308", "-1e300", "inf", "nan", ""])
def test_drift_bad_cell(drift_csv, tmp_path, value):
    p = tmp_path / "drift.csv"
    shutil.copy(drift_csv, p)
    _set_cell(p, 5, 2, value)
    _refused_nothing_written(["drift", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "drift.csv", "line 5")


@pytest.mark.parametrize("noise", ["1e300", "inf", "nan", "0", "-1"])
def test_drift_noise_out_of_range(drift_csv, tmp_path, noise):
    _refused_nothing_written(["drift", str(drift_csv), "--out", str(tmp_path / "o"), "--noise-um", noise, "--quiet"],
                             tmp_path, tmp_path / "o", "--noise-um")


def test_drift_readonly_out(drift_csv, tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o500)
    try:
        o = run(["drift", str(drift_csv), "--out", str(out), "--quiet"], tmp_path)
        assert_refused(o, str(out))
        assert os.listdir(out) == []
    finally:
        out.chmod(0o700)


# ----------------------------------------------------------------------------- path

def _job(tmp_path, doc, name="job.json", raw=None, encoding="utf-8"):
    p = tmp_path / name
    if raw is not None:
        p.write_bytes(raw)
    else:
        p.write_text(json.dumps(doc) if not isinstance(doc, str) else doc, encoding=encoding)
    return p


GOOD = {"strokes": [{"kind": "point", "xy_mm": [float(x), float(x % 3)]} for x in range(6)]}


@pytest.mark.parametrize("case,needle", [
    ("latin1", "UTF-8"),
    ("utf16", "UTF-8"),
    ("garbage", "JSON"),
    ("deep", "nest"),
    ("coord_1e300", "1e+300"),
    ("coord_str", "stroke 1"),
    ("coord_true", "stroke 1"),
    ("coord_nan_token", "JSON"),
])
def test_path_hostile_json(tmp_path, case, needle):
    doc = json.loads(json.dumps(GOOD))
    raw = None
    if case == "latin1":
        raw = json.dumps({**doc, "name": "café"}, ensure_ascii=False).encode("latin-1")
    elif case == "utf16":
        raw = json.dumps(doc).encode("utf-16")
    elif case == "garbage":
        raw = bytes(range(256)) * 4
    elif case == "deep":
        raw = b"[" * 100_000 + b"]" * 100_000
    elif case == "coord_1e300":
        doc["strokes"][2]["xy_mm"] = [1e300, 0.0]
    elif case == "coord_str":
        doc["strokes"][1]["xy_mm"] = ["12.8", 0.0]
    elif case == "coord_true":
        doc["strokes"][1]["xy_mm"] = [True, 0.0]
    elif case == "coord_nan_token":
        raw = json.dumps(doc).replace("2.0", "NaN", 1).encode()
    p = _job(tmp_path, None if raw is not None else doc, raw=raw)
    _refused_nothing_written(["path", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "job.json", needle)


@pytest.mark.parametrize("body,needle", [
    ("0,0\n1,1\n1e308,2\n3,3\n", "row 4"),
    ("0,0\n1,1\n2,2\n3,3", "truncated"),                   # cut inside its last row: no final newline
    ("0,0\n1,1,5\n2,2\n", "row 3"),
])
def test_path_hostile_csv(tmp_path, body, needle):
    p = tmp_path / "job.csv"
    p.write_text("x_mm,y_mm\n" + body)
    _refused_nothing_written(["path", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "job.csv", needle)


# ----------------------------------------------------------------------------- servo trace

def _trace(tmp_path, rows=200, name="t.csv"):
    p = tmp_path / name
    t = np.arange(rows) * 1e-3
    ref = np.where(t > 0.02, 5.0, 0.0)
    pos = ref * (1 - np.exp(-np.maximum(t - 0.02, 0) / 0.01))
    p.write_text("t_s,ref_mm,pos_mm\n" + "".join(f"{a:.6f},{b:.6f},{c:.6f}\n" for a, b, c in zip(t, ref, pos)))
    return p


@pytest.mark.parametrize("value", ["1e308", "inf", "nan"])
def test_servo_trace_bad_cell(tmp_path, value):
    p = _trace(tmp_path)
    _set_cell(p, 50, 2, value)
    _refused_nothing_written(["servo", "--trace", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path,
                             tmp_path / "o", "t.csv", "50")


def test_servo_trace_unreadable(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root reads unreadable files")
    p = _trace(tmp_path)
    p.chmod(0)
    _refused_nothing_written(["servo", "--trace", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path,
                             tmp_path / "o", "t.csv")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_servo_trace_fifo(tmp_path):
    p = tmp_path / "pipe.csv"
    os.mkfifo(p)
    o = run(["servo", "--trace", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path)
    assert_refused(o, "pipe.csv", "regular file")
    assert not (tmp_path / "o").exists()


def test_servo_trace_non_utf8_name(tmp_path):
    src = _trace(tmp_path)
    name = os.path.join(os.fsencode(tmp_path), b"tr\xe9ce.csv")
    os.rename(src, name)
    out = tmp_path / "o"
    o = run(["servo", "--trace", name, "--out", str(out), "--quiet"], tmp_path)
    # either refused in one line with nothing written, or run through with every output written
    if o.code == 1:
        assert_refused(o)
        assert not out.exists() or os.listdir(out) == []
    else:
        assert o.code in (0, 4), o.err
        s = json.loads((out / "summary.json").read_text())
        assert all((out / f).exists() for f in s["outputs"])
        assert scan_outputs(out) == []


@pytest.mark.parametrize("kind", ["component", "path"])
def test_overlong_paths(tmp_path, kind):
    p = _trace(tmp_path)
    if kind == "component":
        out = tmp_path / ("x" * 256)
    else:
        out = tmp_path.joinpath(*(["y" * 200] * 22))          # > 4096 characters
    _refused_nothing_written(["servo", "--trace", str(p), "--out", str(out), "--quiet"], tmp_path, out)
    if kind == "component":
        long_in = str(tmp_path / ("z" * 256 + ".csv"))
    else:
        long_in = str(tmp_path.joinpath(*(["w" * 200] * 22), "t.csv"))
    _refused_nothing_written(["servo", "--trace", long_in, "--out", str(tmp_path / "o"), "--quiet"], tmp_path,
                             tmp_path / "o")


def test_drift_out_holding_its_input(drift_csv, tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(drift_csv, d / "drift.csv")
    _refused_nothing_written(["drift", str(d / "drift.csv"), "--out", str(d), "--quiet"], tmp_path, d / "nothing",
                             "folder holding it")


def test_drift_out_is_a_file(drift_csv, tmp_path):
    f = tmp_path / "f.txt"
    f.write_text("keep")
    _refused_nothing_written(["drift", str(drift_csv), "--out", str(f), "--quiet"], tmp_path, tmp_path / "nothing",
                             "existing file")
    assert f.read_text() == "keep"


def test_pmcal_command_out_is_a_folder(pm_session, tmp_path):
    targets = tmp_path / "t.csv"
    targets.write_text("x_um,y_um\n0,0\n100,50\n")
    (tmp_path / "c").mkdir()
    o = run(["pmcal", "command", str(pm_session / "truth.json"), str(targets), "--depth-um", "1",
             "--out", str(tmp_path / "c")], tmp_path)
    assert_refused(o, "folder")
    assert os.listdir(tmp_path / "c") == []


@pytest.mark.parametrize("opt,value", [("--jump-speed-mm-s", "inf"), ("--jump-speed-mm-s", "nan"),
                                       ("--settle-us", "inf"), ("--dwell-us", "-1")])
def test_path_timing_options(tmp_path, opt, value):
    p = _job(tmp_path, GOOD)
    o = run(["path", str(p), "--out", str(tmp_path / "o"), "--metric", "time", opt, value, "--quiet"], tmp_path)
    assert_refused(o)
    assert not (tmp_path / "o").exists() or os.listdir(tmp_path / "o") == []


def test_drift_out_cannot_be_made(drift_csv, tmp_path):
    f = tmp_path / "f.txt"
    f.write_text("keep")
    o = run(["drift", str(drift_csv), "--out", str(f / "sub"), "--quiet"], tmp_path)
    assert_refused(o, "f.txt")
    assert f.read_text() == "keep"


@pytest.fixture(scope="module")
def grid_csv(tmp_path_factory):
    d = tmp_path_factory.mktemp("gr")
    assert main(["render", "grid", "--seed", "3", "--out", str(d / "m"), "--quiet"]) == 0
    return d / "m" / "measured.csv"


@pytest.mark.parametrize("case,needle", [("huge", "line 4"), ("cut", "truncated"), ("nan", "line 4")])
def test_grid_hostile_cells(grid_csv, tmp_path, case, needle):
    lines = grid_csv.read_text().splitlines()
    if case == "cut":
        text = "\n".join(lines)[:-2]
    else:
        c = lines[3].split(",")
        c[-1] = "1e308" if case == "huge" else "nan"
        lines[3] = ",".join(c)
        text = "\n".join(lines) + "\n"
    p = tmp_path / "g.csv"
    p.write_text(text)
    _refused_nothing_written(["grid", str(p), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "g.csv", needle)


@pytest.mark.parametrize("value", ["1e308", "inf", "nan"])
def test_selfcal_hostile_cell(tmp_path_factory, tmp_path, value):
    src = tmp_path_factory.getbasetemp() / "selfcal_src"
    if not src.exists():
        assert main(["render", "selfcal", "--n", "5", "--k", "8", "--out", str(src), "--quiet"]) == 0
    s = _copy(src, tmp_path)
    header = (s / "grid_views.csv").read_text().splitlines()[0].split(",")
    _set_cell(s / "grid_views.csv", 3, header.index("vx_um"), value)
    _refused_nothing_written(["selfcal", str(s), "--out", str(tmp_path / "o"), "--quiet"], tmp_path, tmp_path / "o",
                             "grid_views.csv", "line 3")
