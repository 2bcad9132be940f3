"""No exit 0 with a non-finite or out-of-range number in any output file (issue 17): every output of a small
batch (with a non-UTF-8 input name) and of extreme-but-legal inputs is scanned (NaN/inf, beyond ±1e15, and
empty cells or nulls outside the documented allow-list, ``hostile_run.ALLOWED_EMPTY``)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from hostile_run import assert_refused, run, scan_outputs
from markcal.pipeline.cli import main


def _trace(path, scale=1.0):
    t = np.arange(400) * 1e-3
    ref = np.where(t > 0.05, 5.0 * scale, 0.0)
    pos = ref * (1 - np.exp(-np.maximum(t - 0.05, 0) / 0.01))
    with open(path, "w") as fh:
        fh.write("t_s,ref_mm,pos_mm\n" + "".join(f"{a:.6f},{b:.9g},{c:.9g}\n" for a, b, c in zip(t, ref, pos)))


def test_batch_with_a_non_utf8_name_writes_its_index_and_finite_outputs(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    _trace(d / "a.csv")
    _trace(os.path.join(os.fsencode(d), b"tr\xe9ce.csv"))
    (d / "job.json").write_text(json.dumps({"strokes": [{"kind": "point", "xy_mm": [float(x), float(x % 4)]}
                                                        for x in range(12)]}))
    assert main(["render", "selfcal", "--n", "5", "--k", "8", "--out", str(d / "sc"), "--quiet"]) == 0
    out = tmp_path / "out"
    o = run(["batch", str(d), "--out", str(out), "--workers", "1", "--quiet"], tmp_path)
    assert o.code in (0, 4), o.err[-10:]
    assert (out / "index.html").exists()
    done = [n for n in os.listdir(out) if (out / n / "summary.json").exists()]
    assert len(done) == 4, os.listdir(out)
    assert scan_outputs(out) == []


@pytest.mark.parametrize("case", ["drift_far", "path_far", "servo_far"])
def test_extreme_but_legal_inputs_give_finite_outputs(tmp_path, case):
    out = tmp_path / "o"
    if case == "drift_far":
        p = tmp_path / "drift.csv"
        t = np.arange(20.0) * 30
        p.write_text("t_min,dx_um,dy_um,dz_um\n" + "".join(f"{a:g},{9e6 * np.sin(a):.6g},{-9e6:g},1e-9\n"
                                                             for a in t))
        argv = ["drift", str(p), "--out", str(out), "--noise-um", "1e4", "--quiet"]
    elif case == "path_far":
        p = tmp_path / "job.csv"
        p.write_text("x_mm,y_mm\n" + "".join(f"{9999.0 * np.cos(k):.4f},{-9999.0 * np.sin(k):.4f}\n"
                                             for k in range(30)))
        argv = ["path", str(p), "--out", str(out), "--quiet"]
    else:
        p = tmp_path / "t.csv"
        _trace(p, scale=1999.0)                              # a 10 m move
        argv = ["servo", "--trace", str(p), "--out", str(out), "--quiet"]
    o = run(argv, tmp_path)
    if o.code == 1:                                          # refused is fine, in one line with nothing written
        assert_refused(o)
        assert not out.exists() or os.listdir(out) == []
        return
    assert o.code in (0, 4), o.err[-10:]
    assert scan_outputs(out) == []


def test_exported_cor_has_no_int32_minimum(tmp_path):
    assert main(["render", "grid", "--seed", "4", "--out", str(tmp_path / "m"), "--quiet"]) == 0
    assert main(["grid", str(tmp_path / "m" / "measured.csv"), "--out", str(tmp_path / "cal"), "--quiet",
                 "--no-report"]) in (0, 4)
    o = run(["export", "cor", str(tmp_path / "cal"), "--lens-mm", "110", "--out", str(tmp_path / "t.cor"),
             "--quiet", "--no-report"], tmp_path)
    assert o.code == 0, o.err
    e = np.frombuffer((tmp_path / "t.cor").read_bytes(), "<i4", count=2 * 65 * 65, offset=36)
    assert np.abs(e).max() <= 0x7FFF and e.min() > -2 ** 31
