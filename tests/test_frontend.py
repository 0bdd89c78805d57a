"""Front-end stages: range crop, deskew, voxel downsample."""

import numpy as np
import pytest
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


def test_a_scan_is_deskewed_once_by_the_motion_it_was_taken_in():
    """The pipeline's path (Deskewer, every point): a sweep of a static scene taken while moving
    at constant velocity comes out as the scene seen from the sensor at the sweep's middle, the
    expected points computed here from the motion alone. Deskewing twice (as kiss-icp would
    if it were given the times too) leaves them off by the whole correction again."""
    from lidar_slam.config import DataConfig
    from lidar_slam.frontend.deskew import Deskewer
    from lidar_slam.frontend.odometry import VoxelSelector
    from lidar_slam.types import Scan

    rng = np.random.default_rng(3)
    world = rng.uniform(-30, 30, (1500, 3))
    period = 0.1
    T_prev_curr = make_pose(Rotation.from_euler("xyz", [0.5, -1, 10], degrees=True).as_matrix(),
                            [1.5, 0.2, 0.0])
    times = np.sort(rng.uniform(0, period, len(world)))
    ref = 0.5 * (times[0] + times[-1])
    # world: the scene in the sensor's frame at the sweep's middle; each point seen from the
    # pose the sensor has at its capture time, moving at constant velocity through ref
    captured = np.array([
        transform_points(inverse(interpolate(np.eye(4), T_prev_curr, (t - ref) / period)),
                         p[None])[0] for p, t in zip(world, times)])
    expected = world
    deskewer = Deskewer(DataConfig(deskew_all_points=True), 0.5, VoxelSelector())
    deskewer(Scan(0, 0.0, captured[:10], times[:10]), np.eye(4))  # the previous scan: period
    out = deskewer(Scan(1, period, captured, times), T_prev_curr)
    assert out.ref_s == pytest.approx(ref)
    assert np.abs(captured - expected).max() > 0.5  # the distortion is real
    np.testing.assert_allclose(out.points, expected, atol=1e-9)


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
