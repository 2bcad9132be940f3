"""Plate-frame coordinates (stages/plane.py) of known points on a known plane."""
import numpy as np
import pytest

from markcal.stages.plane import Plane, _basis, from_plane, to_plane


def _plane(normal, origin):
    n, e_u, e_v = _basis(np.asarray(normal, float))
    return Plane(origin_mm=np.asarray(origin, float), normal=n, e_u=e_u, e_v=e_v, rms_mm=0.0,
                 inlier_fraction=1.0, threshold_mm=0.1)


def test_plate_frame_of_known_points():
    # a plate tilted 30 deg about the scanner's y axis, seen from above (normal along -z)
    t = np.radians(30)
    plane = _plane([np.sin(t), 0.0, -np.cos(t)], [10.0, 20.0, 5.0])
    assert plane.normal == pytest.approx([-np.sin(t), 0.0, np.cos(t)], abs=1e-12)   # n_z > 0: unmirrored
    assert plane.e_u == pytest.approx([np.cos(t), 0.0, np.sin(t)], abs=1e-12)       # scanner x on the plate
    assert plane.e_v == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)
    pts = np.array([[10.0, 20.0, 5.0],                                               # the origin
                    [10.0 + 4 * np.cos(t), 23.0, 5.0 + 4 * np.sin(t)],               # u = 4, v = 3
                    [10.0 - 2 * np.sin(t), 20.0, 5.0 + 2 * np.cos(t)]])              # 2 mm above
    uvh = to_plane(pts, plane)
    np.testing.assert_allclose(uvh, [[0, 0, 0], [4, 3, 0], [0, 0, 2]], atol=1e-12)
    np.testing.assert_allclose(from_plane(uvh[:2, :2], plane), pts[:2], atol=1e-12)


def test_plate_frame_of_many_points_matches_the_rotation():
    rng = np.random.default_rng(3)
    plane = _plane([0.1, -0.2, 1.0], [1.0, 2.0, 3.0])
    xyz = rng.uniform(-100, 100, (1000, 3))
    expect = np.array([[(p - plane.origin_mm) @ e for e in (plane.e_u, plane.e_v, plane.normal)] for p in xyz])
    np.testing.assert_allclose(to_plane(xyz, plane), expect, rtol=0, atol=1e-11)
