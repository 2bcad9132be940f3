"""Plane, projection, galvo kinematics, registration and grid indexing against known truth."""
import numpy as np
import pytest

from markcal.stages import galvo
from markcal.stages.errors import MarkcalError
from markcal.stages.plane import fit_plane, from_plane, to_plane
from markcal.stages.project import project
from markcal.stages.register import index_grid, rigid_fit, robust_rigid_fit


def _tilted_plane_cloud(rng, normal, n=200_000):
    normal = normal / np.linalg.norm(normal)
    a = np.cross(normal, [0, 1, 0]); a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-100, 100, (n, 2))
    xyz = uv[:, :1] * a + uv[:, 1:] * b + [3.0, -2.0, 50.0] + rng.normal(0, 0.01, (n, 1)) * normal
    # a frame 2 mm above around the edges, and wild spurious points
    frame = np.any(np.abs(uv) > 85, axis=1)
    xyz[frame] += 2.0 * normal
    wild = rng.random(n) < 0.002
    xyz[wild, 2] += rng.uniform(-30, 30, wild.sum())
    return xyz


@pytest.mark.parametrize("sign", [1, -1])
def test_plane_fit_ignores_frame_and_outliers(sign):
    rng = np.random.default_rng(0)
    true_n = np.array([np.sin(np.radians(2.5)), 0.3 * np.sin(np.radians(2.5)), 1.0]) * sign
    xyz = _tilted_plane_cloud(rng, true_n)
    plane = fit_plane(xyz)
    true_n = true_n / np.linalg.norm(true_n) * sign
    angle = np.degrees(np.arccos(abs(plane.normal @ true_n)))
    assert angle < 0.005                      # normal within 0.005 deg
    assert plane.normal[2] > 0                # side that keeps x, y unmirrored
    assert abs(plane.rms_mm - 0.01) < 0.002   # the z noise, not the frame
    assert np.linalg.det(plane.rotation) == pytest.approx(1.0)


def test_plane_fit_rejects_a_cloud_without_plane():
    rng = np.random.default_rng(1)
    with pytest.raises(MarkcalError, match="no plane"):
        fit_plane(rng.uniform(-100, 100, (50_000, 3)))


def test_projection_round_trip_and_raster():
    rng = np.random.default_rng(2)
    xyz = _tilted_plane_cloud(rng, np.array([0.02, -0.03, 1.0]), 100_000)
    plane = fit_plane(xyz)
    uvh = to_plane(xyz, plane)
    back = from_plane(uvh[:, :2], plane) + uvh[:, 2:3] * plane.normal
    assert np.abs(back - xyz).max() < 1e-9
    inten = rng.random(len(xyz))
    r = project(xyz, inten, plane, 0.5)
    # raster cells hold the mean in-plane position of their points: inside the cell
    cr = r.to_pixel(np.column_stack([r.u_mm[r.valid], r.v_mm[r.valid]]))
    rows, cols = np.nonzero(r.valid)
    assert np.all(np.abs(cr[:, 0] - cols) <= 0.5 + 1e-9)
    assert np.all(np.abs(cr[:, 1] - rows) <= 0.5 + 1e-9)


def test_galvo_inverse_inverts_forward():
    x, y = np.meshgrid(np.linspace(-95, 95, 21), np.linspace(-95, 95, 21))
    ax, ay, dfr = galvo.inverse(x, y, 490.0, 22.0)
    xf, yf = galvo.forward(2 * ax, 2 * ay, 490.0, 22.0)
    assert np.abs(xf - x).max() < 1e-9 and np.abs(yf - y).max() < 1e-9
    # on-axis: paper eq. (3) is arctan(x / d) / 2 and the focus shift is zero at the centre
    assert ax[10, 20] == pytest.approx(0.5 * np.arctan(95 / 490.0))
    assert dfr[10, 10] == pytest.approx(0.0, abs=1e-12)
    assert np.all(dfr >= -1e-12)


def test_rigid_fit_recovers_transform_and_skips_bad_pairs():
    rng = np.random.default_rng(3)
    src = rng.uniform(-90, 90, (200, 2))
    a = np.radians(11.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    dst = src @ rot.T + [4.0, -7.0]
    dst[:3] += 10.0                           # three mis-indexed pairs
    tf, used = robust_rigid_fit(src, dst, outlier_mm=3.0)
    assert tf.angle_deg == pytest.approx(11.0, abs=1e-9)
    assert np.allclose(tf.translation_mm, [4.0, -7.0], atol=1e-9)
    assert not used[:3].any() and used[3:].all()
    mirrored = rigid_fit(src * [1, -1], src @ rot.T, allow_reflection=True)
    assert mirrored.reflection


@pytest.mark.parametrize("rot_deg", [-15.0, -4.0, 0.0, 9.5, 15.0])
def test_index_grid_with_rotation_distortion_and_missing(rot_deg):
    rng = np.random.default_rng(4)
    pitch = 10.0
    r, c = np.divmod(np.arange(19 * 19), 19)
    xy = np.column_stack([(c - 9) * pitch, (r - 9) * pitch])
    xy = xy + 1.5 * np.column_stack([(xy[:, 0] / 95) ** 3, (xy[:, 1] / 95) * (xy[:, 0] / 95) ** 2])
    a = np.radians(rot_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    uv = xy @ rot.T + [123.4, -56.7]
    keep = np.ones(len(uv), bool)
    keep[rng.choice(len(uv), 3, replace=False)] = False
    order = rng.permutation(np.flatnonzero(keep))
    gi = index_grid(uv[order], 19, 19, pitch)
    assert np.array_equal(gi.row, r[order]) and np.array_equal(gi.col, c[order])
    assert gi.rotation_deg == pytest.approx(rot_deg, abs=0.5)


def test_index_grid_rejects_wrong_pitch():
    r, c = np.divmod(np.arange(49), 7)
    uv = np.column_stack([c * 10.0, r * 10.0])
    with pytest.raises(MarkcalError, match="pitch"):
        index_grid(uv, 7, 7, 12.0)
