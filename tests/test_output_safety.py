"""Nothing lost, nothing mixed (issue 17, output safety): --out checks, stale files, locks, unique batch names."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from markcal.fixtures.servo_trace import TraceOptions, render_servo_trace, save_servo_trace
from markcal.pipeline import batch
from markcal.pipeline.cli import main
from markcal.reports.files import LOCK_NAME


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("sc") / "s"
    assert main(["render", "selfcal", "--n", "7", "--k", "8", "--out", str(d), "--quiet"]) == 0
    return d


def _one_line(capsys, needle):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error:") and needle in err[0], err


def test_out_is_the_input_folder(session, capsys):
    before = sorted(os.listdir(session))
    assert main(["selfcal", str(session), "--out", str(session), "--quiet"]) == 1
    _one_line(capsys, "folder holding it")
    assert sorted(os.listdir(session)) == before


def test_out_holding_the_input_file(tmp_path, capsys):
    trace = tmp_path / "t.csv"
    save_servo_trace(trace, render_servo_trace(1, TraceOptions(kind="step")))
    assert main(["servo", "--trace", str(trace), "--out", str(tmp_path), "--quiet"]) == 1
    _one_line(capsys, "folder holding it")
    assert not (tmp_path / "summary.json").exists()


def test_rerun_removes_what_the_earlier_run_wrote(session, tmp_path):
    out = tmp_path / "o"
    assert main(["selfcal", str(session), "--out", str(out), "--quiet"]) == 0
    assert (out / "report.html").exists()
    (out / "mine.txt").write_text("a user's file")
    assert main(["selfcal", str(session), "--out", str(out), "--quiet", "--no-report"]) == 0
    assert not (out / "report.html").exists()              # no stale report beside the new summary
    assert (out / "mine.txt").exists()                     # files markcal did not write stay
    s = json.loads((out / "summary.json").read_text())
    assert "report.html" not in s["outputs"] and "stage_error.csv" in s["outputs"]
    assert not (out / LOCK_NAME).exists()


def test_lock_of_a_live_run_refuses_a_stale_one_does_not(session, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / LOCK_NAME).write_text("1")                      # process 1 is always alive
    assert main(["selfcal", str(session), "--out", str(out), "--quiet"]) == 1
    _one_line(capsys, "another markcal run")
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()                                               # a process that is gone
    (out / LOCK_NAME).write_text(str(p.pid))
    assert main(["selfcal", str(session), "--out", str(out), "--quiet"]) == 0
    assert not (out / LOCK_NAME).exists()


def test_batch_names_unique_after_renaming(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    r = render_servo_trace(2, TraceOptions(kind="step"))
    save_servo_trace(d / "p.csv", r)
    save_servo_trace(d / "p_csv.csv", r)
    (d / "p.json").write_text(json.dumps({"strokes": [{"kind": "point", "xy_mm": [float(x), 0.0]}
                                                      for x in np.arange(5.0)]}))
    found = batch.discover(str(d), str(tmp_path / "out"), batch.read_batch_config(None))
    dirs = [j["out_dir"] for j in found.jobs]
    assert len(found.jobs) == 3 and len(set(dirs)) == 3, dirs


def test_batch_out_is_the_input_folder(tmp_path, capsys):
    d = tmp_path / "in"
    d.mkdir()
    save_servo_trace(d / "t.csv", render_servo_trace(3, TraceOptions(kind="step")))
    assert main(["batch", str(d), "--out", str(d), "--quiet"]) == 1
    _one_line(capsys, "is the input folder")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_batch_skips_a_fifo(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    save_servo_trace(d / "t.csv", render_servo_trace(3, TraceOptions(kind="step")))
    os.mkfifo(d / "pipe.csv")                              # reading it would hang
    found = batch.discover(str(d), str(tmp_path / "out"), batch.read_batch_config(None))
    assert [os.path.basename(j["input"]) for j in found.jobs] == ["t.csv"]
    assert found.ignored == ["pipe.csv (not a regular file)"]


def test_out_folder_probed_once_per_input_and_a_failed_batch_job_leaves_no_summary(tmp_path, monkeypatch):
    """The writability probe runs once per input, before any work (single commands and batch jobs); a batch
    job still removes its old summary before the run, so a run that fails leaves none vouching."""
    from markcal.reports import files
    probes, probe = [], files.check_writable
    monkeypatch.setattr(files, "check_writable", lambda *a, **k: probes.append(a[0]) or probe(*a, **k))
    d = tmp_path / "in"
    d.mkdir()
    save_servo_trace(d / "t.csv", render_servo_trace(2, TraceOptions(kind="step")))
    (d / "p.json").write_text(json.dumps({"strokes": [{"kind": "point", "xy_mm": [float(x), 0.0]}
                                                      for x in np.arange(5.0)]}))
    assert main(["servo", "--trace", str(d / "t.csv"), "--out", str(tmp_path / "s"), "--quiet", "--no-report"]) == 0
    assert main(["path", str(d / "p.json"), "--out", str(tmp_path / "p"), "--quiet", "--no-report"]) == 0
    assert len(probes) == 2, probes
    probes.clear()
    found = batch.discover(str(d), str(tmp_path / "out"), batch.read_batch_config(None))
    recs = [batch.run_job(j) for j in found.jobs]
    assert all(r["status"] != "error" for r in recs) and len(probes) == 2, (recs, probes)
    job = next(j for j in found.jobs if j["flow"] == "servo")
    assert os.path.exists(os.path.join(job["out_dir"], "summary.json"))
    (d / "t.csv").write_text("t_s,ref_mm,pos_mm\n0,0,0\n")
    assert batch.run_job(job)["status"] == "error"
    assert not os.path.exists(os.path.join(job["out_dir"], "summary.json"))


@pytest.mark.parametrize("argv", [["indents", "/nonexistent.tif"], ["servo", "/nonexistent.toml"]])
def test_commands_writing_without_run_and_write_check_out_before_any_work(argv, capsys):
    """``indents`` and the servo simulation probe --out before reading their input, as every flow command."""
    assert main([*argv, "--out", "/proc/markcal-no-such/o", "--quiet"]) == 1
    _one_line(capsys, "/proc/markcal-no-such/o: cannot write here")


def test_batch_record_takes_the_judged_verdict(tmp_path):
    """A batch record's status and checks are the verdict judge wrote (the report's); a reused record keeps
    it when batch.toml's limits change (they apply with --force, docs/batch.md)."""
    d = tmp_path / "in"
    d.mkdir()
    save_servo_trace(d / "t.csv", render_servo_trace(2, TraceOptions(kind="step")))
    job = batch.discover(str(d), str(tmp_path / "out"), batch.read_batch_config(None)).jobs[0]
    job["tolerances"] = {"max_mae_um": 0.0}                 # out of tolerance
    rec = batch.run_job(job)
    s = json.loads(open(os.path.join(job["out_dir"], "summary.json")).read())
    assert (rec["status"], rec["checks"], rec["failed_checks"]) == ("fail", s["checks"], s["failed_checks"])
    assert "mae_um <= 0" in s["checks"]
    job["tolerances"] = {}                                  # loosened in batch.toml, no --force
    again = batch.reuse_record(job)
    assert (again["status"], again["checks"]) == ("fail", s["checks"]) and again["reused"]
