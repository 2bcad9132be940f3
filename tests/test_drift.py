"""drift flow: the paper's filter, the better estimator, causality, η, files and bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from markcal.fixtures.pm_session import render_drift
from markcal.pipeline.cli import main
from markcal.reports.files import read_csv, write_csv
from markcal.stages.drift import METHODS, compensate, in_force, reduction_rate

T_S = np.arange(0, 241, 10)


def _eta(seed, kind, method):
    rng = np.random.default_rng([seed, 77])
    d = render_drift(rng, 240, kind)
    m = d[T_S] + rng.normal(0, 0.005, (len(T_S), 3))
    m = m - m[0]
    c = compensate(T_S, m, method)
    return reduction_rate(d, in_force(T_S, c, np.arange(241)))[2]


@pytest.fixture(scope="module")
def etas():
    out = {}
    for kind in ("thermal", "wander"):
        for meth in ("paper", "kalman", "hold"):
            out[kind, meth] = np.array([_eta(s, kind, meth) for s in range(10)])
    return out


def test_paper_filter_reproduces_table2(etas):
    """Paper Table 2: η 76 % (X/Y), 78 % (Z) on a slow monotonic drift.

    Measured medians over seeds 0-9: 75.1 / 74.9 / 76.1 %; the printed reading of eq. 10 gives
    93.5 / 94.3 / 94.9 %, so the band (71-80 %) tells the two readings apart."""
    med = np.median(etas["thermal", "paper"], axis=0)
    assert np.all((med > 71) & (med < 80)), med


def test_better_estimator_reaches_90(etas):
    med = np.median(etas["thermal", "kalman"], axis=0)
    # measured medians 94.5 / 94.9 / 95.4 % (residual 5.5 % at worst; the limit allows ~1.45x that, 8 %)
    assert np.all(med >= 92), med
    assert np.all(med > np.median(etas["thermal", "paper"], axis=0) + 10)


def test_better_estimator_does_not_lose_to_hold_on_wander(etas):
    """Issue 4: the default must not lose to holding the last sample on a wandering drift.

    10 records only (test speed): per-axis medians within 0.5 point, the mean over records and
    axes at least hold's (the 0.1-point goal is checked on 30 + 200 records in the benchmark).
    """
    k, h = np.median(etas["wander", "kalman"], axis=0), np.median(etas["wander", "hold"], axis=0)
    assert np.all(k >= h - 0.5), (k, h)
    assert np.mean(etas["wander", "kalman"]) >= np.mean(etas["wander", "hold"])


def test_better_estimator_beats_hold_on_thermal(etas):
    """On the slow thermal approach the trend members must pay off against hold-last."""
    k, h = etas["thermal", "kalman"], etas["thermal", "hold"]
    assert np.all(np.median(k, axis=0) > np.median(h, axis=0)), (np.median(k, axis=0), np.median(h, axis=0))


def test_bank_is_deterministic_and_tracks_a_ramp():
    """Same input, same output bit for bit; a noise-free linear ramp ends up predicted to mid-interval."""
    rng = np.random.default_rng(3)
    m = np.cumsum(rng.normal(0, 0.01, (25, 3)), axis=0)
    assert np.array_equal(compensate(T_S, m, "kalman"), compensate(T_S, m, "kalman"))
    ramp = np.outer(T_S * 0.002, [1.0, -1.0, 0.5])  # 0.002 µm/min, 0.02 µm per sample
    c = compensate(T_S, ramp, "kalman")
    mid = np.outer((T_S + 5) * 0.002, [1.0, -1.0, 0.5])
    assert np.all(np.abs(c[-5:] - mid[-5:]) < np.abs(ramp[-5:] - mid[-5:]))  # closer than hold-last


def test_trend_filter_predicts_a_ramp_to_mid_interval():
    """The constant-velocity filter on a noise-free ramp: C_k is the level at t_k + Δt/2 (measured: exact)."""
    ramp = np.outer(T_S * 0.002, [1.0, -1.0, 0.5])
    mid = np.outer((T_S + 5) * 0.002, [1.0, -1.0, 0.5])
    c = compensate(T_S, ramp, "trend")
    assert np.abs(c[-5:] - mid[-5:]).max() < 1e-6


@pytest.mark.parametrize("method", list(METHODS))
def test_causal(method):
    """C_k must not change when samples after t_k change."""
    rng = np.random.default_rng(1)
    m = np.cumsum(rng.normal(0, 0.01, (25, 3)), axis=0)
    m2 = m.copy()
    m2[15:] += rng.normal(0, 0.5, (10, 3))
    c, c2 = compensate(T_S, m, method), compensate(T_S, m2, method)
    assert np.array_equal(c[:15], c2[:15])
    assert not np.array_equal(c[15:], c2[15:])


def test_in_force_holds_between_samples():
    c = np.arange(75, dtype=float).reshape(25, 3)
    f = in_force(T_S, c, np.array([-1.0, 0.0, 9.0, 10.0, 239.0, 240.0]))
    assert np.array_equal(f[:, 0], [0.0, 0.0, 0.0, 3.0, 69.0, 72.0])


def test_cli_files(tmp_path):
    s = tmp_path / "s"
    assert main(["render", "pmcal", "--seed", "21", "--out", str(s), "--quiet"]) == 0
    out = tmp_path / "d"
    assert main(["drift", str(s / "drift.csv"), "--truth", str(s / "drift_true.csv"), "--out", str(out), "--quiet"]) == 0
    c = read_csv(out / "compensation.csv")
    assert list(c) == ["t_min", "cx_um", "cy_um", "cz_um"] and len(c["t_min"]) == 25
    summ = json.load(open(out / "summary.json"))
    assert summ["method"] == "kalman" and summ["truth"] is True
    for a in "xyz":
        assert summ[f"eta_{a}_pct"] == pytest.approx(summ[f"eta_true_{a}_pct_kalman"])
    # the file holds the stage's compensation (a consistency check of the writer, not a truth: the
    # truths are the η bands above and the hand values in test_reference_values.py)
    d = read_csv(s / "drift.csv")
    m = np.column_stack([d["dx_um"], d["dy_um"], d["dz_um"]])
    assert np.allclose(np.column_stack([c["cx_um"], c["cy_um"], c["cz_um"]]), compensate(d["t_min"], m, "kalman"))
    out2 = tmp_path / "p"
    assert main(["drift", str(s / "drift.csv"), "--method", "paper", "--out", str(out2), "--no-report", "--quiet"]) == 0
    assert json.load(open(out2 / "summary.json"))["truth"] is False
    # the paper method's file against eq. 10 (text reading) written out here: C_k = 0.2·m_k + 0.8·C_{k-1}
    c2 = read_csv(out2 / "compensation.csv")
    want, prev = np.zeros_like(m), np.zeros(3)
    for k in range(len(m)):
        prev = 0.2 * m[k] + 0.8 * prev
        want[k] = prev
    assert np.allclose(np.column_stack([c2["cx_um"], c2["cy_um"], c2["cz_um"]]), want, atol=1e-9, rtol=0)


def test_bad_drift(tmp_path, capsys):
    p = tmp_path / "drift.csv"
    write_csv(p, {"t_min": [0.0, 10.0, 5.0, 30.0], "dx_um": [0, 1, 2, 3], "dy_um": [0, 0, 0, 0], "dz_um": [0, 0, 0, 0]})
    assert main(["drift", str(p), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "drift.csv" in err[0] and "time order" in err[0] and "line 4" in err[0]
    write_csv(p, {"t_min": [0.0, 10.0], "dx_um": [0, 1], "dy_um": [0, 0], "dz_um": [0, 0]})
    assert main(["drift", str(p), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "at least 3" in capsys.readouterr().err
