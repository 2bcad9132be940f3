"""Hand-computed reference values for small measurement formulas.

Every expected number here was worked out by hand from the definition quoted next to it (the
arithmetic is in the comments), not by calling the code under test: paper 001 eq. 9 on a pure
rotation field and the O/R split, paper 000 eq. 10 (both readings) on four samples and eq. 11 on a
known error, and the servo MAE/STD of a known error signal.
"""
import numpy as np
import pytest

from markcal.stages.drift import compensate, in_force, paper_filter, reduction_rate, sample_reduction_rate
from markcal.stages.selfcal import SelfcalSetup, linear_terms, tie_rows
from markcal.stages.servo_sim import step_metrics, tracking_metrics


# --- paper 001 eq. 9 and the linear terms -----------------------------------------------------

def _field(setup, fx, fy):
    M = setup.half
    m, n = np.meshgrid(np.arange(-M, M + 1), np.arange(-M, M + 1), indexing="ij")
    x, y = m * setup.pitch_mm, n * setup.pitch_mm
    return fx(x, y), fy(x, y)


def _tie_values(setup, gx, gy):
    g = np.column_stack([gx.ravel(), gy.ravel()])
    return {line: sum(w * g[s, c] for s, c, w in terms) for line, terms in tie_rows(setup)}


def test_eq9_on_a_pure_rotation_field():
    # G = ω × p with ω = 2.5 mrad: Gx = -ω·y, Gy = ω·x (µm for x, y in mm). The mean angle
    # deviation (x·Gy - y·Gx)/(x² + y²) = ω at every site, so each half-axis line reads 2.5 mrad.
    setup = SelfcalSetup(n=7, pitch_mm=5.0, k=8)
    gx, gy = _field(setup, lambda x, y: -2.5 * y, lambda x, y: 2.5 * x)
    vals = _tie_values(setup, gx, gy)
    assert sorted(vals) == [0, 2, 4, 6]                      # lines 0, K/4, K/2, 3K/4
    for line, v in vals.items():
        assert v == pytest.approx(2.5, abs=1e-12), line


def test_eq9_sees_each_half_axis_alone():
    # a field that turns only the +X half axis: Gy = 0.004 µm·x on sites with x > 0, y = 0
    # (each of the 3 sites at x = 5, 10, 15 mm reads Gy/x = 0.004 mrad); other lines read 0.
    setup = SelfcalSetup(n=7, pitch_mm=5.0, k=8)
    gx, gy = _field(setup, lambda x, y: 0 * x, lambda x, y: np.where((x > 0) & (y == 0), 0.004 * x, 0.0))
    vals = _tie_values(setup, gx, gy)
    assert vals[0] == pytest.approx(0.004, abs=1e-15)
    assert vals[2] == 0 and vals[4] == 0 and vals[6] == 0
    # -Y half axis: Gx = 0.006 µm on sites (0, -j): mean of -y·Gx / y² = 0.006 / |y| over y = -5, -10, -15
    # = 0.006 · (1/5 + 1/10 + 1/15) / 3 = 0.006 · 0.366667 / 3 = 0.000733333 mrad
    gx, gy = _field(setup, lambda x, y: np.where((x == 0) & (y < 0), 0.006, 0.0), lambda x, y: 0 * x)
    assert _tie_values(setup, gx, gy)[6] == pytest.approx(0.000733333333333, abs=1e-12)


def test_linear_terms_split_o_and_r():
    # Gx = R·x + O·y, Gy = O·x - R·y with O = 3 µrad, R = -2 ppm (µm = 1e-3 · µrad · mm), plus a pure
    # rotation (not part of O or R) and a bump at the centre: O, R come back exactly, F holds the rest.
    setup = SelfcalSetup(n=5, pitch_mm=10.0, k=4)
    gx, gy = _field(setup, lambda x, y: 1e-3 * (-2 * x + 3 * y) - 0.01 * y,
                    lambda x, y: 1e-3 * (3 * x + 2 * y) + 0.01 * x)
    o, r, fx, fy = linear_terms(setup, gx, gy)
    assert o == pytest.approx(3.0, abs=1e-9) and r == pytest.approx(-2.0, abs=1e-9)
    gx0, gy0 = _field(setup, lambda x, y: -0.01 * y, lambda x, y: 0.01 * x)
    assert np.abs(fx - gx0).max() < 1e-12 and np.abs(fy - gy0).max() < 1e-12


# --- paper 000 eqs. 10-11 ---------------------------------------------------------------------

M4 = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 0.5], [1.0, -2.0, 0.5], [2.0, 0.0, 1.0]])


def test_paper_filter_text_reading_four_samples():
    # C_k = (1 - α)·m_k + α·C_{k-1}, α = 0.8, C_{-1} = 0. Column x: 0; 0.2; 0.2 + 0.16 = 0.36;
    # 0.4 + 0.288 = 0.688. Column y: 0; -0.4; -0.4 - 0.32 = -0.72; 0 - 0.576 = -0.576.
    # Column z: 0; 0.1; 0.1 + 0.08 = 0.18; 0.2 + 0.144 = 0.344.
    c = compensate(np.array([0.0, 10, 20, 30]), M4, "paper")
    assert np.allclose(c, [[0, 0, 0], [0.2, -0.4, 0.1], [0.36, -0.72, 0.18], [0.688, -0.576, 0.344]],
                       atol=1e-12, rtol=0)


def test_paper_filter_printed_reading_four_samples():
    # C_k = α·m_k + (1 - α)·C_{k-1}: x: 0; 0.8; 0.8 + 0.16 = 0.96; 1.6 + 0.192 = 1.792
    c = compensate(np.array([0.0, 10, 20, 30]), M4, "paper-literal")
    assert np.allclose(c[:, 0], [0.0, 0.8, 0.96, 1.792], atol=1e-12, rtol=0)
    # a static offset C_GA is added to every sample
    assert np.allclose(paper_filter(M4, 0.8, c_ga_um=0.5)[:, 0], [0.5, 1.3, 1.46, 2.292], atol=1e-12, rtol=0)


def test_hold_last_is_the_measurement():
    assert np.array_equal(compensate(np.array([0.0, 10, 20, 30]), M4, "hold"), M4)


def test_reduction_rate_on_a_known_error():
    # x: drift 1, -3, 2, -2 (mean |e| = 2); residual after C = 0.5, -1, 0.5, -1 (mean 0.75): η = 62.5 %
    # y: drift 4 everywhere, C = 5: residual -1 (mean 1), η = 75 %
    # z: drift -2, 2, -2, 2, C = 0: η = 0
    d = np.array([[1.0, 4, -2], [-3, 4, 2], [2, 4, -2], [-2, 4, 2]])
    c = np.array([[0.5, 5, 0], [-2, 5, 0], [1.5, 5, 0], [-1, 5, 0]])
    pre, post, eta = reduction_rate(d, c)
    assert np.allclose(pre, [2.0, 4.0, 2.0]) and np.allclose(post, [0.75, 1.0, 2.0])
    assert np.allclose(eta, [62.5, 75.0, 0.0], atol=1e-12)


def test_sample_reduction_rate_uses_the_previous_compensation():
    # the error at t_{k+1} is m_{k+1} - C_k: m = 0, 2, 4, 6 with hold-last C = m gives residuals 2, 2, 2
    # against pre 2, 4, 6 (mean 4): η = (4 - 2)/4 = 50 %
    m = np.column_stack([[0.0, 2, 4, 6]] * 3)
    _, post, eta = sample_reduction_rate(m, m.copy())
    assert np.allclose(post, 2.0) and np.allclose(eta, 50.0)


def test_in_force_between_samples():
    # samples at 0, 10, 20 min: at 5 min C_0 holds, at 10 min C_1, at 25 min C_2, before 0 nothing
    c = np.array([[1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    f = in_force(np.array([0.0, 10, 20]), c, np.array([-1.0, 5, 10, 19.9, 25]))
    assert np.array_equal(f[:, 0], [0.0, 1.0, 2.0, 2.0, 3.0])


# --- servo MAE / STD ----------------------------------------------------------------------------

def test_tracking_metrics_of_a_known_error():
    # error 1, -1, 3, -3 µm (given in mm): MAE = (1 + 1 + 3 + 3)/4 = 2 µm; mean 0, so
    # STD (population) = √((1 + 1 + 9 + 9)/4) = √5 = 2.2360680 µm
    mae, std = tracking_metrics(np.array([1e-3, -1e-3, 3e-3, -3e-3]))
    assert mae == pytest.approx(2.0, abs=1e-12) and std == pytest.approx(5 ** 0.5, abs=1e-12)
    # an offset error 2, 2, 2, 4 µm: MAE 2.5, mean 2.5, STD = √((0.25·3 + 2.25)/4) = √0.75 = 0.8660254
    mae, std = tracking_metrics(np.array([2e-3, 2e-3, 2e-3, 4e-3]))
    assert mae == pytest.approx(2.5, abs=1e-12) and std == pytest.approx(0.75 ** 0.5, abs=1e-12)


def test_step_metrics_of_a_known_move():
    # reference 0 -> 1 mm reached at t = 0.2 s; the stage overshoots by 3 µm at 0.3 s, is 2 µm short at
    # 0.4 s and within 1 µm from 0.5 s: settling 0.5 - 0.2 = 0.3 s, overshoot 3 µm.
    t = np.arange(0.0, 0.8, 0.1)
    ref = np.array([0.0, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    pos = np.array([0.0, 0.4, 0.99, 1.003, 0.998, 1.0005, 0.9998, 1.0])
    m = step_metrics(t, ref, pos, t_end_s=0.2, band_um=1.0)
    assert m.settling_time_s == pytest.approx(0.3, abs=1e-12)
    assert m.overshoot_um == pytest.approx(3.0, abs=1e-9)
    # e = ref - pos in µm: 0, 100, 10, -3, 2, -0.5, 0.2, 0 -> MAE = 115.7/8 = 14.4625 µm
    assert m.mae_um == pytest.approx(14.4625, abs=1e-9)
    e = np.array([0, 100, 10, -3, 2, -0.5, 0.2, 0])
    assert m.std_um == pytest.approx(np.sqrt(np.mean((e - e.mean()) ** 2)), abs=1e-9)


# --- the circumscribed circle of an imprint ------------------------------------------------------

def test_circle_fit_is_the_geometric_least_squares_circle():
    """stages.indent_geometry.circle_fit against scipy's least_squares on the geometric distances
    (an independent solver of the same definition) on noisy points of a 100° arc, where the algebraic
    (Kasa) circle is visibly different; and exact on four points of a known circle."""
    from scipy.optimize import least_squares
    from markcal.stages.indent_geometry import circle_fit
    rng = np.random.default_rng(2)
    ang = np.radians(np.linspace(10, 110, 7))
    p = np.column_stack([1.0 + 3.0 * np.cos(ang), -2.0 + 3.0 * np.sin(ang)]) + rng.normal(0, 0.05, (7, 2))
    ref = least_squares(lambda q: np.hypot(p[:, 0] - q[0], p[:, 1] - q[1]) - q[2], [0.0, 0.0, 1.0],
                        xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    got = np.array(circle_fit(p))
    assert np.abs(got - ref).max() < 1e-7
    kasa, *_ = np.linalg.lstsq(np.column_stack([2 * p, np.ones(7)]), (p ** 2).sum(1), rcond=None)
    assert np.hypot(*(kasa[:2] - ref[:2])) > 1e-3          # the case tells the two circles apart
    # four corners at 0°, 80°, 200°, 290° of the circle centred (0.5, 0.25), radius 2: exact
    a = np.radians([0, 80, 200, 290])
    cx, cy, r = circle_fit(np.column_stack([0.5 + 2 * np.cos(a), 0.25 + 2 * np.sin(a)]))
    assert (cx, cy, r) == pytest.approx((0.5, 0.25, 2.0), abs=1e-12)


# --- paper 004 Table 1 statistics ----------------------------------------------------------------

def test_deviation_stats_by_hand():
    """Max and RMS of ux, uy, |δ| inside a centred square (paper 004 Table 1). Points (mm) and deviations:
    (0, 0): (3, 4) -> |δ| 5;  (25, -25): (0, -1) -> 1, on the border of the 50 mm square (kept);
    (30, 0): (6, 8) -> 10, outside it. Over all: max_x 6, max_y 8, max 10, rms_x = √(45/3) = 3.873,
    rms_y = √(81/3) = 5.196, rms = √(126/3) = 6.481. Inside ±25 mm: rms_x = √(9/2) = 2.121,
    rms_y = √(17/2) = 2.915, rms = √(26/2) = 3.606, max 5."""
    from markcal.stages.deviation import deviation_stats
    xy = np.array([[0.0, 0.0], [25.0, -25.0], [30.0, 0.0]])
    d = np.array([[3.0, 4.0], [0.0, -1.0], [6.0, 8.0]])
    a = deviation_stats(xy, d)
    assert a["n"] == 3 and (a["max_x_mm"], a["max_y_mm"], a["max_mm"]) == (6.0, 8.0, 10.0)
    assert (a["rms_x_mm"], a["rms_y_mm"], a["rms_mm"]) == pytest.approx((15 ** 0.5, 27 ** 0.5, 42 ** 0.5), abs=1e-12)
    b = deviation_stats(xy, d, half_width_mm=25.0)
    assert b["n"] == 2 and b["max_mm"] == 5.0
    assert (b["rms_x_mm"], b["rms_y_mm"], b["rms_mm"]) == pytest.approx((4.5 ** 0.5, 8.5 ** 0.5, 13 ** 0.5), abs=1e-12)
