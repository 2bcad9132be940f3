"""Every output of the demo batch is scanned (issue 17): ``make demo``'s ``render batch`` + ``batch``, on a smaller
render (one plate, one session, three traces, one AFM map, one micrograph, one broken file), holds no NaN/inf, no
number beyond ±1e15, and no empty cell or JSON null the docs do not allow (``hostile_run.ALLOWED_EMPTY``)."""
from __future__ import annotations

import json

from hostile_run import ALLOWED_EMPTY, scan_outputs
from markcal.pipeline.cli import main


def test_demo_batch_outputs_are_finite_and_filled(tmp_path):
    inputs, out = tmp_path / "inputs", tmp_path / "batch"
    assert main(["render", "batch", "--seed", "7", "--out", str(inputs), "--scans", "1", "--sessions", "1",
                 "--traces", "3", "--maps", "1", "--micrographs", "1", "--broken", "1", "--quiet"]) == 0
    assert main(["batch", str(inputs), "--out", str(out), "--workers", "2", "--quiet"]) == 3     # the broken file
    index = json.loads((out / "summary.json").read_text())
    status = {r["name"]: r["status"] for r in index["rows"]}
    assert [n for n, s in status.items() if s == "error"] == ["broken/bad1_truncated"], status
    assert {r["flow"] for r in index["rows"]} == {"scan", "selfcal", "servo", "indents"}
    done = [n for n in status if (out / n / "summary.json").exists()]
    assert len(done) == len(status) - 1
    assert scan_outputs(out) == []


def test_the_scan_catches_what_it_is_meant_to(tmp_path):
    """The scanner itself: a NaN token, a huge number, an undocumented empty cell and null are each reported."""
    d = tmp_path / "r"
    d.mkdir()
    (d / "moves.csv").write_text("x_mm,settling_time_s\n1.0,\n,2.0\n")    # settling may be empty, x_mm not
    (d / "summary.json").write_text(json.dumps({"rms_mm": None, "settling_time_s": None}))
    (d / "c.txt").write_text("value nan\n")
    (d / "e.csv").write_text("y_mm\n3e16\n")
    bad = scan_outputs(d)
    assert len(bad) == 4, bad
    assert any("moves.csv: empty x_mm" in b for b in bad) and any("null at rms_mm" in b for b in bad)
    assert not any("settling_time_s" in b for b in bad)
    assert all(len(entry) == 3 and entry[2] for entry in ALLOWED_EMPTY)          # every allowance cites its doc
