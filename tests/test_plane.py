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


def test_projection_cells_hold_the_mean_plate_position_and_intensity_of_their_points():
    # points on a tilted plane, a cell of 0.5 mm: each cell's u, v and intensity are the means of the
    # points that fall in it (computed here with the plate frame of to_plane), points off the plane dropped
    from markcal.stages.project import project
    rng = np.random.default_rng(5)
    plane = _plane([0.2, -0.1, 1.0], [3.0, -4.0, 10.0])
    uv = rng.uniform(-20, 20, (20000, 2))
    h = np.where(np.arange(20000) < 19000, rng.normal(0, 0.002, 20000), 1.0)      # 1000 points 1 mm above
    xyz = plane.origin_mm + uv[:, :1] * plane.e_u + uv[:, 1:] * plane.e_v + h[:, None] * plane.normal
    inten = rng.uniform(0, 100, 20000)
    r = project(xyz, inten, plane, pixel_mm=0.5, max_height_mm=0.05)
    on = np.abs(h) < 0.05
    uvh = to_plane(xyz[on], plane)
    col = np.floor((uvh[:, 0] - r.u0_mm) / 0.5).astype(int)
    row = np.floor((uvh[:, 1] - r.v0_mm) / 0.5).astype(int)
    inside = (col >= 0) & (col < r.valid.shape[1]) & (row >= 0) & (row < r.valid.shape[0])
    flat = row[inside] * r.valid.shape[1] + col[inside]
    n = np.bincount(flat, minlength=r.valid.size)
    np.testing.assert_array_equal(r.valid.ravel(), n > 0)
    full = n > 0
    for got, vals in ((r.u_mm, uvh[inside, 0]), (r.v_mm, uvh[inside, 1]), (r.intensity, inten[on][inside])):
        want = np.bincount(flat, vals, r.valid.size)[full] / n[full]
        np.testing.assert_allclose(got.ravel()[full], want, rtol=0, atol=1e-4)    # intensity is float32
    assert abs(r.u0_mm + 20) < 0.6 and abs(r.v0_mm + 20) < 0.6     # the raster starts at the points' edge


def test_float32_cloud_is_read_exactly_and_projects_as_its_float64_copy(tmp_path):
    # a float32 PLY stays float32 (lossless, half the memory); the plane fit and the projection give the
    # same plane and raster as on a float64 copy of the same values
    from markcal.reports.files import write_ply
    from markcal.stages.io import read_cloud
    from markcal.stages.plane import fit_plane
    from markcal.stages.project import project
    rng = np.random.default_rng(11)
    plane = _plane([0.05, -0.03, 1.0], [1.0, 2.0, 30.0])
    uv = rng.uniform(-40, 40, (300_000, 2))                        # above the percentiles' sorting threshold
    xyz = plane.origin_mm + uv[:, :1] * plane.e_u + uv[:, 1:] * plane.e_v + rng.normal(0, 0.003, (300_000, 1)) * plane.normal
    inten = rng.uniform(0, 1, 300_000)
    write_ply(tmp_path / "c.ply", xyz.astype(np.float32), inten.astype(np.float32))
    cloud = read_cloud(tmp_path / "c.ply")
    assert cloud.xyz_mm.dtype == np.float32 and cloud.intensity.dtype == np.float32
    np.testing.assert_array_equal(cloud.xyz_mm, xyz.astype(np.float32))
    p32, p64 = fit_plane(cloud.xyz_mm), fit_plane(cloud.xyz_mm.astype(np.float64))
    np.testing.assert_array_equal(p32.normal, p64.normal)
    np.testing.assert_array_equal(p32.origin_mm, p64.origin_mm)
    r32 = project(cloud.xyz_mm, cloud.intensity, p32, pixel_mm=0.5)
    r64 = project(cloud.xyz_mm.astype(np.float64), cloud.intensity.astype(np.float64), p64, pixel_mm=0.5)
    assert (r32.u0_mm, r32.v0_mm) == (r64.u0_mm, r64.v0_mm)
    for a, b in ((r32.intensity, r64.intensity), (r32.u_mm, r64.u_mm), (r32.v_mm, r64.v_mm), (r32.valid, r64.valid)):
        np.testing.assert_array_equal(a, b)
    assert abs(p32.normal @ plane.normal) > 1 - 1e-8                 # and the plane is the true one
