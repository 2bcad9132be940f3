"""Paper 004 eqs. 1-5 (stages/galvo.py) against values worked out by hand at off-axis points.

Each reference value below was computed on paper (and checked with a pocket calculator) from the
equations as printed in paper 004 §2.3, d = 490 mm, e = 22 mm; the tolerance is rounding only.
Off-axis points are used on purpose: on an axis the lever term e + √(d² + x²) and the slant path
d / cos θx reduce to constants and a dropped or mis-signed term goes unnoticed.
"""
import numpy as np
import pytest

from markcal.fixtures.gls import TrueGalvo
from markcal.stages import galvo

D_MM, E_MM = 490.0, 22.0


@pytest.mark.parametrize("x_mm,y_mm,alpha_x,alpha_y,dfr_mm", [
    # x = 60, y = -45: αx = ½ atan(60/490) = ½ · 0.1218424 = 0.0609212;
    # lever = 22 + √(490² + 60²) = 22 + 493.6598 = 515.6598; αy = ½ atan(-45/515.6598) = -0.0435232;
    # Δf = √(515.6598² + 45²) - (22 + 490) = 517.6196 - 512 = 5.6196
    (60.0, -45.0, 0.060921218509958595, -0.043523158546153705, 5.619581626378931),
    # x = -80, y = 70: lever = 22 + √(240100 + 6400) = 518.4939; αy = ½ atan(70/518.4939) = 0.0670983;
    # Δf = √(518.4939² + 70²) - 512 = 523.1916 - 512 = 11.1916
    (-80.0, 70.0, -0.08091871561921146, 0.06709830897657049, 11.19160657799091),
])
def test_inverse_matches_hand_values(x_mm, y_mm, alpha_x, alpha_y, dfr_mm):
    ax, ay, dfr = galvo.inverse(x_mm, y_mm, D_MM, E_MM)
    assert float(ax) == pytest.approx(alpha_x, abs=1e-12)      # rad
    assert float(ay) == pytest.approx(alpha_y, abs=1e-12)      # rad
    assert float(dfr) == pytest.approx(dfr_mm, abs=1e-9)       # mm


def test_inverse_with_target_height():
    # z_s = 5 mm: d - z = 485; αx = ½ atan(60/485); lever = 22 + √(485² + 60²) = 510.6973;
    # Δf = √(510.6973² + 45²) - (22 + 485) = 512.6760 - 507 = 5.6760
    ax, ay, dfr = galvo.inverse(60.0, -45.0, D_MM, E_MM, z_mm=5.0)
    assert float(ax) == pytest.approx(0.06154297984750289, abs=1e-12)
    assert float(ay) == pytest.approx(-0.04394391824964852, abs=1e-12)
    assert float(dfr) == pytest.approx(5.675997978130113, abs=1e-9)


@pytest.mark.parametrize("theta_x,theta_y,x_mm,y_mm", [
    # θx = 0.12: x = 490 tan 0.12 = 490 · 0.1205793 = 59.0839; y = (22 + 490/cos 0.12) tan(-0.08)
    # = (22 + 493.5607) · (-0.0801710) = -41.3322
    (0.12, -0.08, 59.0838752335396, -41.332156326245126),
    # θx = -0.15: x = 490 tan(-0.15) = -74.0563; y = (22 + 495.5879) · tan 0.1 = 51.9297
    (-0.15, 0.10, -74.05625684856459, 51.92968013409315),
])
def test_forward_matches_hand_values(theta_x, theta_y, x_mm, y_mm):
    x, y = galvo.forward(theta_x, theta_y, D_MM, E_MM)
    assert float(x) == pytest.approx(x_mm, abs=1e-9)
    assert float(y) == pytest.approx(y_mm, abs=1e-9)


def test_forward_undoes_inverse_off_axis():
    xs, ys = np.meshgrid(np.linspace(-90, 90, 7), np.linspace(-70, 70, 5))
    ax, ay, _ = galvo.inverse(xs, ys, D_MM, E_MM, z_mm=3.0)
    x, y = galvo.forward(2 * ax, 2 * ay, D_MM, E_MM, z_mm=3.0)
    assert np.abs(x - xs).max() < 1e-9 and np.abs(y - ys).max() < 1e-9     # mm


def test_true_machine_with_nominal_parameters_lands_on_target():
    # the fixture's own physics (fixtures/gls.py, not stages/galvo.py): an ideal machine lands where commanded
    ideal = TrueGalvo(d_mm=D_MM, e_mm=E_MM, gain_x=1.0, gain_y=1.0, zero_x_rad=0.0, zero_y_rad=0.0,
                      coupling_yx=0.0, lens_k3_per_mm2=0.0, lens_p1_per_mm=0.0, lens_p2_per_mm=0.0)
    cmd = np.array([[60.0, -45.0], [-80.0, 70.0], [0.0, 0.0]])
    assert np.abs(ideal.land(cmd) - cmd).max() < 1e-9
    # a longer true d throws the beam further by d_true/d_nominal in x (x = d tan θx)
    longer = TrueGalvo(d_mm=D_MM + 4.9, e_mm=E_MM, gain_x=1.0, gain_y=1.0, zero_x_rad=0.0, zero_y_rad=0.0,
                       coupling_yx=0.0, lens_k3_per_mm2=0.0, lens_p1_per_mm=0.0, lens_p2_per_mm=0.0)
    assert longer.land(cmd)[0, 0] == pytest.approx(60.0 * 1.01, abs=1e-9)
