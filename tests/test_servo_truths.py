"""Servo measurements against truths computed by hand or from closed forms, not by the code under test.

* MAE, STD, gain and phase lag of a sine tracked with a known gain, lag and offset (closed forms);
* settling time, overshoot, rise time and steady-state error of a hand-made move;
* the simulated loop's steady sine error against the continuous loop's transfer function
  (feed-forward + PID + plant, evaluated by hand, no simulation);
* the reading's unit conversions against hand arithmetic.
"""
import math

import numpy as np
import pytest

from markcal.stages.servo_log import find_moves, move_metrics, sine_metrics
from markcal.stages.servo_reading import DEFAULT_READING, Reading, baseline_rows, reading_params
from markcal.stages.servo_sim import tracking_metrics


def _tracked_sine(f_hz=2.0, amp_mm=1.0, gain=0.98, lag_deg=5.0, offset_um=0.0, periods=4, ts=1e-4):
    t = np.arange(int(round(periods / f_hz / ts))) * ts
    w = 2 * np.pi * f_hz
    ref = amp_mm * np.sin(w * t)
    pos = gain * amp_mm * np.sin(w * t - np.radians(lag_deg)) - offset_um * 1e-3
    return t, ref, pos


def _sine_error_truth(amp_mm, gain, lag_deg, offset_um=0.0):
    """MAE and STD (µm) of A sin(x) - g A sin(x - phi) + c over whole periods.

    The error is a sine of amplitude E = A sqrt(1 + g^2 - 2 g cos phi) plus c: STD = E / sqrt(2);
    with c = 0, MAE = 2 E / pi; with |c| < E, MAE = (2/pi) (c asin(c/E) + sqrt(E^2 - c^2)).
    """
    e = amp_mm * 1e3 * math.sqrt(1 + gain ** 2 - 2 * gain * math.cos(math.radians(lag_deg)))
    c = abs(offset_um)
    mae = 2 / math.pi * (c * math.asin(c / e) + math.sqrt(e * e - c * c))
    return mae, e / math.sqrt(2)


@pytest.mark.parametrize("gain,lag_deg,offset_um", [(0.98, 5.0, 0.0), (1.0, 1.0, 0.0), (0.9, 20.0, 30.0)])
def test_sine_metrics_closed_forms(gain, lag_deg, offset_um):
    t, ref, pos = _tracked_sine(gain=gain, lag_deg=lag_deg, offset_um=offset_um)
    mae, std = _sine_error_truth(1.0, gain, lag_deg, offset_um)
    sm = sine_metrics(t, ref, pos)
    # limits: about 2x the worst seen on these signals (sampling of 5,000 points per period: < 1e-6)
    assert abs(sm.mae_um / mae - 1) < 2e-6 and abs(sm.std_um / std - 1) < 2e-6
    assert abs(sm.phase_lag_deg - lag_deg) < 1e-6
    assert abs(sm.phase_lag_s - lag_deg / 360.0 / 2.0) < 1e-8
    assert abs(sm.gain - gain) < 1e-8
    assert abs(sm.frequency_hz - 2.0) < 1e-7
    m2, s2 = tracking_metrics(ref - pos)
    assert abs(m2 / mae - 1) < 2e-6 and abs(s2 / std - 1) < 2e-6


def test_tracking_metrics_by_hand():
    # error (µm) 3, -1, 2, 0: MAE 1.5; mean 1, deviations 2, -2, 1, -1: STD sqrt(10/4)
    mae, std = tracking_metrics(np.array([3e-3, -1e-3, 2e-3, 0.0]))
    assert mae == pytest.approx(1.5, abs=1e-12) and std == pytest.approx(math.sqrt(2.5), abs=1e-12)


def test_hand_made_move():
    """A 2 mm move: ramp 0..0.1 s, then 30 µm past the target decaying in steps of known size."""
    ts = 1e-3
    t = np.arange(400) * ts
    ref = np.clip((t - 0.05) / 0.1, 0, 1) * 2.0             # ramp from 0.05 s to 0.15 s
    ref[t >= 0.15] = 2.0
    pos = ref.copy()
    dev_um = np.zeros_like(t)
    after = t >= 0.15
    k = np.arange(after.sum())
    # hold +30 µm for 20 samples, -12 µm for 20, +4 µm for 20, then +0.5 µm (inside a 1 µm band)
    dev_um[after] = np.select([k < 20, k < 40, k < 60], [30.0, -12.0, 4.0], 0.5)
    pos = pos + dev_um * 1e-3
    pos[(t > 0.05) & (t < 0.15)] -= 0.05                      # lags by 50 µm while the reference moves
    mv = find_moves(ref)
    assert len(mv.lo) == 1
    cols = move_metrics(t, ref, pos, mv, band_um=1.0)
    # last sample outside the band: k = 59 -> settled at k = 60 -> 60 ms after the end of the ramp
    assert cols["settling_time_s"][0] == pytest.approx(0.060, abs=1e-12)
    assert cols["overshoot_um"][0] == pytest.approx(30.0, abs=1e-9)
    assert cols["overshoot_pct"][0] == pytest.approx(1.5, abs=1e-9)
    # the last 20 % of the hold: 0.5 µm past the target -> steady-state error (target - pos) = -0.5 µm
    assert cols["steady_state_error_um"][0] == pytest.approx(-0.5, abs=1e-9)
    assert cols["stroke_mm"][0] == pytest.approx(2.0, abs=1e-12)
    # with a 5 µm band the +4 µm stretch is inside: settled after the -12 µm stretch (k = 40)
    assert move_metrics(t, ref, pos, mv, band_um=5.0)["settling_time_s"][0] == pytest.approx(0.040, abs=1e-12)
    # 10 %..90 % of the stroke: pos = 20 (t - 0.05) - 0.05 mm on the ramp reaches 0.2 mm at t = 0.0625 s and
    # 1.8 mm at t = 0.1425 s (linear, so the interpolation between samples is exact): rise 80 ms
    assert cols["rise_time_s"][0] == pytest.approx(0.080, abs=1e-9)


def _loop_error_ratio(reading, f_hz):
    """|E/R| of the continuous loop: E = (1 - Kf s Gn) / (1 + C Gn) R, C = Kp + Kd s + Ki/s (by hand)."""
    p, g = reading_params(reading)
    s = 2j * math.pi * f_hz
    gn = p.b0 / (s * s + p.a1 * s + p.a0)
    c = g.kp + g.kd * s + (0.0 if math.isinf(g.ki) else 1.0 / g.ki) / s
    return abs((1 - g.kf * s * gn) / (1 + c * gn))


@pytest.mark.parametrize("f_hz", [0.5, 2.0])
def test_simulated_sine_error_matches_the_transfer_function(f_hz):
    """Steady state (last of 3 periods): the simulated MAE/STD are those of a sine of amplitude A |E/R|."""
    rd = Reading(**{**DEFAULT_READING.__dict__, "sine_window": "last"})
    rows = baseline_rows(rd, strokes_mm=(), freqs_hz=(f_hz,))
    mae, std = rows["t2"][f_hz]
    e_um = 10.0 * 1e3 * _loop_error_ratio(rd, f_hz)
    # measured: 2.4e-6 (0.5 Hz) and 1.5e-5 (2 Hz: sampling and the zero-order hold); limit 3e-5
    assert abs(std / (e_um / math.sqrt(2)) - 1) < 3e-5
    assert abs(mae / (2 * e_um / math.pi) - 1) < 3e-5


def test_reading_units_by_hand():
    # 468.33 and no a0; gains as printed in mm; (1/Ki) -> integral gain 1/0.422
    p, g = reading_params(DEFAULT_READING)
    assert p.b0 == pytest.approx(468.33, rel=1e-12) and p.a0 == 0.0 and p.a1 == 18.85
    assert g.kp == pytest.approx(85.572) and g.ki == pytest.approx(0.422) and g.kf == pytest.approx(5.5e-5)
    # PID on µm: every gain per mm x 1000; Ki as a gain: divisor 1 / (0.422 * 1000)
    p2, g2 = reading_params(Reading(ctrl_unit="um", integral="gain"))
    assert g2.kp == pytest.approx(85572.0) and g2.kd == pytest.approx(193.0)
    assert 1.0 / g2.ki == pytest.approx(422.0)
    # per-sample PID at Ts = 0.1 ms: integral gain / Ts, derivative gain x Ts
    _, g3 = reading_params(Reading(pid_form="sample"))
    assert 1.0 / g3.ki == pytest.approx(1.0 / 0.422 / 1e-4) and g3.kd == pytest.approx(0.193e-4)
    _, g4 = reading_params(Reading(feedforward="none"))
    assert g4.kf == 0.0


def test_reading_option_and_config_key(tmp_path, capsys):
    import json

    from markcal.pipeline.cli import main
    cfg = tmp_path / "small.toml"
    cfg.write_text('[step]\nstrokes_mm = [10.0]\n[sine]\namplitudes_mm = [5.0]\nfrequencies_hz = [2.0]\n'
                   '[model]\nreading = "sat20"\n')
    assert main(["servo", str(cfg), "--out", str(tmp_path / "a"), "--no-report", "--quiet"]) == 0
    s = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert s["reading"] == "sat20" and s["reading_u_max_v"] == 20.0 and s["reading_b0_scale"] == 0.1
    # the option wins over the config key; "printed" reads b0 = 4683.3 with a0
    assert main(["servo", str(cfg), "--reading", "printed", "--out", str(tmp_path / "b"), "--no-report",
                 "--quiet"]) == 0
    s = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert s["reading"] == "printed" and s["reading_b0_scale"] == 1.0 and s["reading_plant"] == "a0"
    capsys.readouterr()
    assert main(["servo", "--reading", "nonsense", "--out", str(tmp_path / "c"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--reading 'nonsense' unknown (one of best, printed" in err[0]
    assert not (tmp_path / "c" / "summary.json").exists()
    cfg.write_text('[model]\nreading = "nonsense"\n')
    assert main(["servo", str(cfg), "--out", str(tmp_path / "d"), "--quiet"]) == 1
    assert "must be one of best, printed" in capsys.readouterr().err
