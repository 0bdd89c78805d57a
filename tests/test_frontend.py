"""Front-end stages: range crop, deskew, voxel downsample."""

import numpy as np
from scipy.spatial.transform import Rotation

from lidar_slam.frontend.crop import range_mask
from lidar_slam.frontend.deskew import deskew
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import interpolate, inverse, make_pose, transform_points


def test_range_mask_keeps_only_points_inside_the_band():
    pts = np.array([[0.5, 0, 0], [3, 0, 0], [0, 0, 99], [0, 120, 0]], float)
    assert range_mask(pts, 1.0, 100.0).tolist() == [False, True, True, False]


def test_deskew_recovers_points_captured_during_constant_velocity_motion():
    rng = np.random.default_rng(0)
    world = rng.uniform(-30, 30, (2000, 3))
    period = 0.1
    T_prev_curr = make_pose(Rotation.from_euler("xyz", [1, -2, 8], degrees=True).as_matrix(),
                            [1.2, 0.3, -0.05])
    times = rng.uniform(0, period, len(world))
    # Each point is seen from the pose the sensor has at its capture time (stamp = identity).
    captured = np.array([
        transform_points(inverse(interpolate(np.eye(4), T_prev_curr, t / period)), p[None])[0]
        for p, t in zip(world, times)])
    assert np.abs(captured - world).max() > 0.5  # the distortion is real
    fixed = deskew(captured, times, T_prev_curr, period)
    np.testing.assert_allclose(fixed, world, atol=1e-9)


def test_deskew_is_identity_without_motion_and_at_the_stamp():
    pts = np.random.default_rng(1).normal(size=(100, 3))
    np.testing.assert_allclose(deskew(pts, np.full(100, 0.05), np.eye(4), 0.1), pts)
    moving = make_pose(np.eye(3), [1.0, 0, 0])
    np.testing.assert_allclose(deskew(pts, np.zeros(100), moving, 0.1), pts)


def test_voxel_downsample_averages_points_and_intensity_per_voxel():
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2]])
    out, inten = voxel_downsample(pts, 1.0, np.array([1.0, 3.0, 5.0]))
    order = np.argsort(out[:, 0])
    np.testing.assert_allclose(out[order], [[0.2, 0.2, 0.2], [1.5, 0.2, 0.2]])
    np.testing.assert_allclose(inten[order], [2.0, 5.0])


def test_voxel_downsample_leaves_one_point_per_occupied_voxel():
    pts = np.random.default_rng(2).uniform(0, 10, (50000, 3))
    out, _ = voxel_downsample(pts, 1.0)
    assert len(out) == 1000


def test_first_point_reduction_keeps_one_input_point_per_voxel():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 10, (20000, 3))
    inten = rng.uniform(0, 1, 20000)
    out, out_i = voxel_downsample(pts, 1.0, inten, reduce="first")
    assert len(out) == 1000
    assert len(np.unique(np.floor(out), axis=0)) == 1000  # one per voxel
    rows = {tuple(p): i for i, p in enumerate(pts)}
    idx = [rows[tuple(p)] for p in out]  # every kept point is an input point ...
    np.testing.assert_array_equal(out_i, inten[idx])  # ... with its own intensity
