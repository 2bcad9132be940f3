"""Verdicts, tolerances and traceability shared by every flow command (issue 16, items 1, 3, 7)."""
from __future__ import annotations

import hashlib
import json
import os
import stat

import pytest

from markcal.pipeline.cli import main
from markcal.stages.errors import MarkcalError
from markcal.stages.verdict import evaluate, parse_tolerance


def test_evaluate_against_hand_made_summaries():
    s = {"rms_mm": 0.04, "max_mm": 0.2, "n": 25, "nan_mm": float("nan")}
    assert evaluate(s, {}).status == "no tolerance"
    v = evaluate(s, {"max_rms_mm": 0.05, "min_n": 20})
    assert (v.status, v.failed) == ("pass", "")
    v = evaluate(s, {"max_rms_mm": 0.03, "max_max_mm": 0.5})
    assert v.status == "fail" and v.failed == "rms_mm 0.04 > 0.03"
    assert evaluate(s, {"max_nan_mm": 1.0, "max_rms_mm": 0.05}).status == "pass"   # NaN: not applicable, skipped
    assert evaluate(s, {"max_nan_mm": 1.0}).status == "no tolerance"                # nothing was checked
    assert evaluate(s, {"max_other": 1.0}).failed == "other missing"


@pytest.mark.parametrize("text,want", [("rms_mm<=0.05", ("max_rms_mm", 0.05)), (" n >= 3 ", ("min_n", 3.0)),
                                       ("depth_nm<=1e3", ("max_depth_nm", 1000.0))])
def test_parse_tolerance(text, want):
    assert parse_tolerance(text) == want


@pytest.mark.parametrize("text", ["rms_mm<0.05", "rms_mm<=", "<=3", "rms_mm<=abc", "rms_mm<=inf"])
def test_parse_tolerance_refuses(text):
    with pytest.raises(MarkcalError, match="expected KEY<=VALUE|the limit must be finite"):
        parse_tolerance(text)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("sc") / "s"
    assert main(["render", "selfcal", "--n", "7", "--k", "8", "--out", str(d), "--quiet"]) == 0
    return d


def _sha(folder) -> str:
    h = hashlib.sha256()
    for root, dirs, files in sorted(os.walk(folder)):
        dirs.sort()
        for f in sorted(files):
            p = os.path.join(root, f)
            h.update(f"{os.path.relpath(p, folder)}\0{hashlib.sha256(open(p, 'rb').read()).hexdigest()}\n".encode())
    return h.hexdigest()


def test_out_of_tolerance_exits_4_and_says_so(session, tmp_path, capsys):
    out = tmp_path / "o"
    rc = main(["selfcal", str(session), "--out", str(out), "--quiet", "--tol", "residual_rms_xy_um<=0.0001",
               "--machine", "stage 3", "--operator", "ann"])
    assert rc == 4
    s = json.loads((out / "summary.json").read_text())
    assert s["verdict"] == "fail" and s["failed_checks"].startswith("residual_rms_xy_um ")
    assert s["machine"] == "stage 3" and s["operator"] == "ann" and s["markcal_version"]
    assert s["input_sha256"] == _sha(session)                 # an independent digest of the session folder
    html = (out / "report.html").read_text()
    head = html[:html.index("<h2")]                            # the first screen, before any section
    assert 'id="verdict"' in head and ">FAIL<" in head and "residual RMS" in head
    mode = stat.S_IMODE(os.stat(out / "summary.json").st_mode)
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask                              # not mkstemp's 0600


def test_within_tolerance_exits_0(session, tmp_path):
    out = tmp_path / "o"
    assert main(["selfcal", str(session), "--out", str(out), "--quiet", "--tol", "gx_rms_um<=10"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["verdict"] == "pass" and "gx_rms_um <= 10" in s["checks"]
    assert "max_residual_rms_xy_um" not in s["checks"] and "residual_rms_xy_um <= 0.1" in s["checks"]  # default kept


@pytest.mark.parametrize("args,needle", [(["--tol", "bogus_um<=1"], "produces no such figure"),
                                         (["--tol", "rms"], "expected KEY<=VALUE")])
def test_bad_tolerances_refused(session, tmp_path, capsys, args, needle):
    out = tmp_path / "o"
    assert main(["selfcal", str(session), "--out", str(out), "--quiet", *args]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error:") and needle in err[0]
    assert not (out / "summary.json").exists()


def test_out_that_is_a_file_is_one_line(session, tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("keep me")
    assert main(["selfcal", str(session), "--out", str(f), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "existing file" in err[0] and f.read_text() == "keep me"


def test_version(capsys):
    with pytest.raises(SystemExit, match="^0$") as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("markcal ")


def test_out_has_a_short_form(session, tmp_path):
    assert main(["selfcal", str(session), "-o", str(tmp_path / "o"), "--quiet"]) == 0
    assert (tmp_path / "o" / "summary.json").exists()


def test_help_shows_defaults(capsys):
    with pytest.raises(SystemExit, match="^0$"):
        main(["render", "grid", "--help"])
    out = capsys.readouterr().out
    assert "--rows ROWS" in out and "default: 9" in out and "-o OUT, --out OUT" in out


def test_no_applicable_limit_is_no_tolerance_not_pass():
    s = {"overshoot_um": None, "mae_um": 0.3}                 # a tracking trace has no moves to overshoot
    v = evaluate(s, {"max_overshoot_um": 6.0})
    assert (v.status, v.checks, v.failed) == ("no tolerance", "overshoot_um <= 6", "")
    assert evaluate(s, {"max_overshoot_um": 6.0, "max_mae_um": 0.2}).status == "fail"
    assert evaluate(s, {"max_mae_um": 0.5, "max_overshoot_um": 6.0}).checks == "mae_um <= 0.5; overshoot_um <= 6"


def test_servo_simulation_report_opens_with_no_tolerance_and_says_why(tmp_path):
    # every report's first screen carries a verdict (issue 16); the simulation is compared with the paper
    from markcal.reports.html import verdict_banner
    out = tmp_path / "sim"
    cfg = tmp_path / "servo.toml"
    cfg.write_text("[step]\nstrokes_mm = [10.0]\n[sine]\namplitudes_mm = [10.0]\nfrequencies_hz = [2.0]\n")
    assert main(["servo", str(cfg), "--out", str(out), "--quiet"]) == 0
    s = json.load(open(out / "summary.json"))
    assert s["verdict"] == "no tolerance" and "compared with the paper" in s["verdict_note"]
    html = (out / "report.html").read_text()
    assert 'id="verdict"><span class="big">NO TOLERANCE</span>' in html and "not judged against a tolerance" in html
    banner = verdict_banner({"verdict": "no tolerance", "verdict_note": "x < y"})
    assert "x &lt; y" in banner and "--tol" not in banner
