"""markcal batch: discovery, failure isolation, exit codes, resume, --force, atomic outputs, Dask."""
import io
import json
import os
import shutil
import time

import pytest

from markcal.fixtures.batch_mix import MixOptions, render_batch_mix
from markcal.pipeline import batch
from markcal.pipeline.cli import main
from markcal.pipeline.cli_batch import BatchProgress
from markcal.stages.errors import MarkcalError

MIX = MixOptions(n_scan=1, n_selfcal=1, n_servo=2, n_broken=5, scan_rows=5)


@pytest.fixture(scope="module")
def mix(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("mix") / "in")
    truth = render_batch_mix(d, seed=3, options=MIX)
    return d, truth


@pytest.fixture(scope="module")
def ran(mix, tmp_path_factory):
    d, truth = mix
    out = str(tmp_path_factory.mktemp("out") / "out")
    rc = main(["batch", d, "--out", out, "--workers", "2", "--quiet"])
    return out, rc


def _traces_only(mix, tmp_path):
    """A fast sub-batch: the two servo traces and the broken trace."""
    d = str(tmp_path / "in")
    shutil.copytree(os.path.join(mix[0], "servo"), os.path.join(d, "servo"))
    os.makedirs(os.path.join(d, "broken"))
    shutil.copy2(os.path.join(mix[0], "broken", "bad2_trace.csv"), os.path.join(d, "broken"))
    return d


def test_discovery_and_specs(mix, tmp_path):
    d, truth = mix
    cfg = batch.read_batch_config(None)
    found = batch.discover(d, str(tmp_path / "out"), cfg)
    got = {j["input"]: j for j in found.jobs}
    assert set(got) == {os.path.abspath(t["input"]) for t in truth}
    for t in truth:
        assert got[os.path.abspath(t["input"])]["flow"] == t["flow"], t
    plate = next(j for j in found.jobs if j["name"] == "machine_A/plate01")
    assert plate["spec"] == os.path.join(d, "machine_A", "plate.toml")
    bad = next(j for j in found.jobs if j["name"] == "broken/bad1_truncated")
    assert bad["spec"].endswith("bad1_truncated.toml")          # <stem>.toml wins over plate.toml
    assert next(j for j in found.jobs if j["name"] == "broken/nospec5/cloud")["spec"] is None
    assert found.ignored == []                                  # truth.json, .toml are not inputs


def test_discovery_of_the_other_flows(tmp_path):
    """indents, path, pmcal inputs are recognised by their flows' descriptors (no run here)."""
    d = tmp_path / "in"
    (d / "afm").mkdir(parents=True)
    (d / "afm" / "m1.tif").write_bytes(b"II*\0")
    (d / "afm" / "array.toml").write_text("")
    (d / "afm" / "m2.gsf").write_bytes(b"Gwyddion")
    (d / "afm" / "m2.toml").write_text("")
    (d / "jobs").mkdir()
    (d / "jobs" / "job.csv").write_text("x_mm,y_mm\n0,0\n")
    (d / "jobs" / "job2.json").write_text('{"strokes": []}')
    (d / "pm").mkdir()
    for f in ("axes.csv", "pose.csv", "probe.csv"):
        (d / "pm" / f).write_text("a\n")
    (d / "notes.docx").write_bytes(b"x")
    found = batch.discover(str(d), str(tmp_path / "out"), batch.read_batch_config(None))
    got = {j["name"]: (j["flow"], j["spec"] and os.path.basename(j["spec"])) for j in found.jobs}
    want = {"afm/m1": ("indents", "array.toml"), "afm/m2": ("indents", "m2.toml"), "jobs/job": ("path", None),
            "jobs/job2": ("path", None), "pm": ("pmcal", None)}
    assert got == want
    assert found.ignored == ["notes.docx"]


def test_failure_isolation_and_exit_3(mix, ran):
    d, truth = mix
    out, rc = ran
    assert rc == 3
    s = json.load(open(os.path.join(out, "summary.json")))
    rows = {r["input"]: r for r in s["rows"]}
    assert len(rows) == len(truth) and s["n_error"] == MIX.n_broken
    for t in truth:
        r = rows[os.path.abspath(t["input"])]
        if t["expect"] == "error":
            assert r["status"] == "error" and "\n" not in r["reason"] and r["reason"], r
            assert os.path.basename(t["input"]) in r["reason"]     # the reason names the file
        else:
            assert r["status"] != "error", r
            assert os.path.exists(os.path.join(r["out_dir"], "summary.json"))
            assert os.path.exists(r["report"])
        if t["expect"] in ("pass", "fail"):
            assert r["status"] == t["expect"], r
    csv_lines = open(os.path.join(out, "summary.csv")).read().splitlines()
    assert len(csv_lines) == len(truth) + 1 and csv_lines[0].startswith("name,group,flow,status,reason")
    html = open(os.path.join(out, "index.html")).read()
    assert 'id="summary"' in html and "http://" not in html and "https://" not in html


def test_outputs_as_single_command(mix, ran, tmp_path):
    d, _ = mix
    out, _ = ran
    trace = os.path.join(d, "servo", "trace01.csv")
    assert main(["servo", "--trace", trace, "--out", str(tmp_path / "single"), "--quiet"]) == 0
    for f in ("metrics.csv", "traces.csv"):
        assert open(tmp_path / "single" / f, "rb").read() == open(os.path.join(out, "servo", "trace01", f), "rb").read()
    a = json.load(open(tmp_path / "single" / "summary.json"))
    b = json.load(open(os.path.join(out, "servo", "trace01", "summary.json")))
    for k in ("runtime_s", "date_utc", "command"):          # when and how it ran: the rest is identical
        a.pop(k), b.pop(k)
    assert b.pop("batch_index") == "../../index.html"        # the batch's report links back to its index
    assert a == b


def test_resume_force_and_kill_safety(mix, tmp_path):
    d = _traces_only(mix, tmp_path)
    out = str(tmp_path / "out")
    assert main(["batch", d, "--out", out, "--workers", "1", "--quiet"]) == 3
    s = json.load(open(os.path.join(out, "summary.json")))
    assert (s["n_run"], s["n_reused"], s["n_error"]) == (3, 0, 1)
    # re-run: the two good traces are reused, only the broken one is retried
    assert main(["batch", d, "--out", out, "--workers", "1", "--quiet"]) == 3
    s = json.load(open(os.path.join(out, "summary.json")))
    assert (s["n_run"], s["n_reused"]) == (1, 2)
    # what a kill leaves: a folder whose summary.json (written last) is absent, a temp .part file,
    # and an input newer than its outputs; both must be redone, and the other one reused
    t1 = os.path.join(out, "servo", "trace01")
    os.unlink(os.path.join(t1, "summary.json"))
    open(os.path.join(t1, ".metrics.csv.x.part"), "w").write("half")
    later = time.time() + 5
    os.utime(os.path.join(d, "servo", "trace02.csv"), (later, later))
    assert main(["batch", d, "--out", out, "--workers", "1", "--quiet"]) == 3
    s = json.load(open(os.path.join(out, "summary.json")))
    assert (s["n_run"], s["n_reused"]) == (3, 0)
    assert all(r["status"] != "error" for r in s["rows"] if "servo/" in r["name"])
    # --force redoes everything
    assert main(["batch", d, "--out", out, "--workers", "1", "--quiet", "--force"]) == 3
    assert json.load(open(os.path.join(out, "summary.json")))["n_run"] == 3


def test_exit_0_and_bad_batch(mix, tmp_path, capsys):
    d = str(tmp_path / "in")
    shutil.copytree(os.path.join(mix[0], "servo"), d)
    cfg = tmp_path / "batch.toml"
    cfg.write_text("[servo]\nsettle_band_um = 2.0\n[servo.tolerance]\nmax_mae_um = 0.01\n")
    assert main(["batch", d, "--out", str(tmp_path / "o"), "--workers", "1", "--quiet", "--config", str(cfg)]) == 0
    s = json.load(open(tmp_path / "o" / "summary.json"))
    assert s["n_error"] == 0 and s["n_fail"] == 2                # every trace MAE > 0.01 µm
    assert all("mae_um" in r["failed_checks"] for r in s["rows"])
    capsys.readouterr()
    cfg.write_text("[servo]\nsettle_band = 2.0\n")
    assert main(["batch", d, "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error:") and "settle_band" in err[0]
    assert main(["batch", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 1
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["batch", str(empty), "--out", str(tmp_path / "o2")]) == 1
    assert "no inputs found" in capsys.readouterr().err
    with pytest.raises(MarkcalError, match="missing.toml: no such batch config"):
        batch.read_batch_config(str(tmp_path / "missing.toml"))


def test_progress_bar_and_log_lines():
    rec = {"name": "a", "flow": "servo", "status": "pass", "failed_checks": "", "runtime_s": 1.0, "reason": ""}
    for tty in (True, False):
        buf = io.StringIO()
        p = BatchProgress(buf, tty=tty)
        p.start(2, 2, 0, [])
        p.update(rec, 1, 0, 1)
        p.update(dict(rec, status="error", reason="bad file"), 2, 1, 0)
        p.finish("end")
        text = buf.getvalue()
        assert "FAILED a (servo): bad file" in text
        if tty:
            assert "\r" in text and "ETA" in text and "1 failed" in text
        else:
            assert "\r" not in text and "1/2 pass" in text


def test_progress_heartbeat_while_inputs_run(monkeypatch):
    # a batch whose inputs each take long must not go silent (issue 16): a line when none came for a while,
    # the wait doubling each time; none after finish()
    import markcal.pipeline.cli_batch as cb
    monkeypatch.setattr(cb, "HEARTBEAT_S", 0.1)
    buf = io.StringIO()
    p = BatchProgress(buf, tty=False)
    p.start(3, 3, 0, [])
    time.sleep(0.9)                              # beats after about 0.1, 0.3 and 0.7 s
    p.finish("end")
    beats = [ln for ln in buf.getvalue().splitlines() if "working: 3 inputs left" in ln]
    assert 2 <= len(beats) <= 4
    n = len(buf.getvalue())
    time.sleep(0.3)
    assert len(buf.getvalue()) == n and buf.getvalue().rstrip().endswith("end")
    quiet = io.StringIO()
    q = BatchProgress(quiet, quiet=True, tty=False)
    q.start(1, 1, 0, [])
    time.sleep(0.3)
    q.finish("end")
    assert quiet.getvalue() == ""


def test_dask_local_cluster_same_records(mix, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    d = _traces_only(mix, tmp_path)
    assert main(["batch", d, "--out", str(tmp_path / "pool"), "--workers", "2", "--quiet"]) == 3
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        assert main(["batch", d, "--out", str(tmp_path / "dask"), "--quiet",
                     "--scheduler", cluster.scheduler_address]) == 3

    def rows(o):
        s = json.load(open(tmp_path / o / "summary.json"))
        return [{k: v for k, v in r.items() if k not in ("runtime_s", "out_dir", "report")} for r in s["rows"]]
    assert rows("pool") == rows("dask")
    for f in ("metrics.csv", "traces.csv"):
        assert (open(tmp_path / "pool" / "servo" / "trace02" / f, "rb").read()
                == open(tmp_path / "dask" / "servo" / "trace02" / f, "rb").read())


def test_worker_crash_is_isolated(tmp_path, monkeypatch):
    """A job that kills its worker process is recorded as failed; the jobs beside it still finish."""
    from markcal.pipeline.executors import LocalExecutor
    (tmp_path / "crashy_jobs.py").write_text(
        "import os\ndef fn(job):\n    if job['name'].startswith('crash'):\n        os._exit(7)\n"
        "    return {'name': job['name'], 'ok': True}\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import crashy_jobs
    got = []
    jobs = [{"name": n} for n in ("a", "crash1", "b", "c", "crash2", "d")]
    with LocalExecutor(2) as ex:
        ex.map_unordered(crashy_jobs.fn, jobs, got.append,
                         on_crash=lambda j, why: {"name": j["name"], "error": why})
    by = {r["name"]: r for r in got}
    assert len(got) == 6 and all(by[n].get("ok") for n in "abcd")
    assert "worker process died" in by["crash1"]["error"] and "worker process died" in by["crash2"]["error"]
