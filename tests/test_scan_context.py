"""Loop detection stage: Scan Context descriptor, yaw alignment and ring-key retrieval, on the real
indoor Ouster sequence (reference poses: line k of poses.txt is file 100 + k)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_slam.config import ScanContextConfig
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import inverse, transform_points, yaw_matrix, yaw_rad
from lidar_slam.io.pointcloud import read_cloud
from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.loop.scan_context import ScanContextIndex, column_distances, describe
from lidar_slam.registration import level_ground

INDOOR = dict(max_radius_m=30.0)  # the value recommended for this indoor data


def keyframe_cloud(root: Path, frame: int) -> np.ndarray:
    """A keyframe cloud as the pipeline builds it: range <= 60 m, 0.5 m voxels, sensor frame."""
    pts = read_cloud(root / "scans" / f"{frame:06d}.bin").points
    return voxel_downsample(pts[np.linalg.norm(pts, axis=1) <= 60.0], 0.5)[0]


def wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def test_column_distance_is_zero_for_itself_and_one_without_common_columns():
    grid = np.random.default_rng(0).uniform(0.5, 3.0, (20, 60))
    assert column_distances(grid, grid, np.array([0]))[0] == pytest.approx(0.0, abs=1e-12)
    shifted = np.roll(grid, -7, axis=1)  # match column j + 7 == query column j
    d = column_distances(grid, np.roll(grid, 7, axis=1), np.arange(60))
    assert int(np.argmin(d)) == 7 and d[7] == pytest.approx(0.0, abs=1e-12)
    assert column_distances(grid, shifted, np.array([7]))[0] > 0.01
    half = grid.copy()
    half[:, 30:] = 0.0
    other = grid.copy()
    other[:, :30] = 0.0
    assert column_distances(half, other, np.array([0]))[0] == 1.0


@pytest.mark.shared_data
@pytest.mark.parametrize("yaw_deg", [0.0, 37.0, 90.0, -120.0, 178.0])
def test_rotated_cloud_matches_itself_with_the_yaw_of_T_match_query(ouster_loop, yaw_deg):
    """The query is the match cloud seen from a frame turned by yaw: T_match_query = Rz(yaw), so
    p_query = inv(Rz(yaw)) p_match. The index must report that yaw (sign included)."""
    cfg = ScanContextConfig(**INDOOR, exclude_recent_m=1.0)
    match = keyframe_cloud(ouster_loop, 110)
    T_match_query = yaw_matrix(np.radians(yaw_deg))
    query = transform_points(inverse(T_match_query), match)
    index = ScanContextIndex(cfg)
    index.add(0, match, path_m=0.0)
    res = index.query(5, query, path_m=5.0)
    assert res.best_match == 0
    sector_deg = 360.0 / cfg.sectors
    # Whole-sector turns give back the same bins; others re-bin points near sector borders.
    on_grid = abs(yaw_deg / sector_deg - round(yaw_deg / sector_deg)) < 1e-9
    assert res.best_distance < (0.01 if on_grid else 0.1)
    assert abs(wrap_deg(np.degrees(res.best_yaw_rad) - yaw_deg)) <= sector_deg / 2 + 1e-6
    # The same yaw through the candidate and the levelled initial guess for ICP.
    (cand,) = res.candidates
    assert cand.query == 5 and cand.match == 0
    T0 = index.initial_guess(cand)
    assert abs(wrap_deg(np.degrees(yaw_rad(T0)) - yaw_deg)) <= sector_deg / 2 + 1e-6


@pytest.mark.shared_data
def test_ground_levelling_recovers_the_reference_gravity_of_a_tilted_handheld_scan(ouster_loop):
    poses = read_kitti_poses(ouster_loop / "poses.txt")
    for frame in (100, 114, 120, 175):  # tilt 5-21 deg in the reference poses
        ground = level_ground(keyframe_cloud(ouster_loop, frame))
        up_in_sensor = poses[frame - 100][:3, :3].T @ np.array([0.0, 0.0, 1.0])
        fitted_up = ground.R_level_sensor.T @ np.array([0.0, 0.0, 1.0])
        angle = np.degrees(np.arccos(np.clip(up_in_sensor @ fitted_up, -1, 1)))
        assert angle < 5.0, (frame, angle)
        assert 1.3 < ground.height_m < 2.2


@pytest.mark.shared_data
def test_last_scans_retrieve_an_early_scan_of_the_same_place(ouster_loop):
    """Files 168-176 revisit 106-115 (2.3-4 m away, heading ~80-100 deg different)."""
    poses = read_kitti_poses(ouster_loop / "poses.txt")
    cfg = ScanContextConfig(**INDOOR, exclude_recent_m=20.0)
    index = ScanContextIndex(cfg)
    for frame in range(100, 141):
        index.add(frame, keyframe_cloud(ouster_loop, frame), path_m=float(frame))
    for frame in range(168, 177):
        res = index.query(frame, keyframe_cloud(ouster_loop, frame), path_m=float(frame))
        assert res.candidates, (frame, res.best_distance)
        best = res.candidates[0]
        assert best.score == pytest.approx(res.best_distance)
        assert all(a.score <= b.score for a, b in zip(res.candidates, res.candidates[1:]))
        gap = np.linalg.norm(poses[frame - 100][:3, 3] - poses[best.match - 100][:3, 3])
        assert gap < 5.0, (frame, best.match, gap)


@pytest.mark.shared_data
def test_recent_keyframes_are_never_candidates_and_grids_on_disk_match_ram(ouster_loop, tmp_path):
    clouds = {f: keyframe_cloud(ouster_loop, f) for f in range(100, 124)}
    cfg = ScanContextConfig(**INDOOR, exclude_recent_m=5.0, threshold=1.0)
    disk = ScanContextIndex(cfg, tmp_path / "grids.bin")
    ram = ScanContextIndex(cfg)
    for f, pts in clouds.items():
        a, b = disk.query(f, pts, float(f)), ram.query(f, pts, float(f))
        assert all(c.match <= f - 5 for c in a.candidates)
        assert [(c.match, c.score) for c in a.candidates] == [(c.match, c.score)
                                                               for c in b.candidates]
        if f < 105:
            assert a.best_match is None and not a.candidates
        # keep= drops neighbours before their grids are compared: the same candidates as
        # filtering the result afterwards.
        even = ram.query(f, pts, float(f), keep=lambda m: m % 2 == 0)
        assert [(c.match, c.score) for c in even.candidates] == [
            (c.match, c.score) for c in b.candidates if c.match % 2 == 0]
        disk.add(f, pts, float(f))
        ram.add(f, pts, float(f))
    with pytest.raises(ValueError):
        disk.add(110, clouds[110], 110.0)
    disk.close()


def test_descriptor_bins_hold_the_highest_point_above_ground():
    cfg = ScanContextConfig(rings=4, sectors=8, max_radius_m=8.0, sensor_height_m=2.0,
                            level_to_ground=False)
    pts = np.array([[1.0, 0.1, -1.0], [1.5, 0.2, 0.5], [5.0, 0.1, -3.0], [-3.0, -0.1, 1.0]])
    grid = describe(pts, cfg).grid
    # x>0, y>0 small: azimuth just above 0 -> sector 4 of 8 (azimuth + pi); ring = r / 2 m.
    assert grid[0, 4] == pytest.approx(2.5)  # max(1.0, 2.5): the higher point wins
    assert grid[2, 4] == 0.0  # below the ground: clipped at 0
    assert grid[1, 0] == pytest.approx(3.0)  # azimuth just above -pi -> sector 0, r = 3 m
    assert np.count_nonzero(grid) == 2


def test_recent_means_little_path_and_little_time():
    """A keyframe is skipped while the sensor is within exclude_recent_m of path of it and
    exclude_recent_s of time: standing in a room for a minute makes old keyframes candidates."""
    cfg = ScanContextConfig(**INDOOR, exclude_recent_m=10.0, exclude_recent_s=30.0)
    index = ScanContextIndex(cfg)
    rng = np.random.default_rng(0)
    for k in range(5):  # 1 m and 1 s apart
        index.add(k, rng.uniform(-10, 10, (500, 3)), path_m=float(k), stamp_s=float(k))
    assert index.n_eligible(path_m=5.0, stamp_s=5.0) == 0
    assert index.n_eligible(path_m=12.5, stamp_s=5.0) == 3  # path 0, 1, 2 are 10 m back
    assert index.n_eligible(path_m=5.0, stamp_s=32.0) == 3  # stamps 0, 1, 2 are 30 s back
    assert index.n_eligible(path_m=5.0) == 0  # no stamp: path alone


def test_a_candidate_is_verified_only_where_the_odometry_could_have_drifted_to(tmp_path):
    """loop.max_gap_m + loop.max_drift x path between the keyframes: a square 50 m loop
    (200 m of path) closes 4 m off; a keyframe 45 m away after 60 m of path cannot be the same
    place (kiss-icp would have drifted 75 %)."""
    from lidar_slam.config import SlamConfig
    from lidar_slam.geometry import make_pose
    from lidar_slam.loop.detector import LoopDetector
    from lidar_slam.map.keyframes import KeyframeStore

    store = KeyframeStore(tmp_path / "kf")
    corners = [(0, 0), (50, 0), (50, 50), (0, 50), (0, 4)]
    xy = [np.array(corners[0], float)]
    for a, b in zip(corners, corners[1:]):
        a, b = np.array(a, float), np.array(b, float)
        n = int(np.ceil(np.linalg.norm(b - a) / 2.0))
        xy += [a + (b - a) * (i / n) for i in range(1, n + 1)]
    for k, p in enumerate(xy):
        store.add(k, make_pose(np.eye(3), [p[0], p[1], 0.0]), np.zeros((1, 3)), None, 0.1 * k)
    det = LoopDetector(SlamConfig(), store)
    last = len(xy) - 1
    assert det.plausible(last, 0)  # 4 m apart after 196 m: 20 + 19.6 m allowed
    k45 = next(k for k, p in enumerate(xy) if p[1] >= 45)  # (50, 45): 95 m of path
    assert not det.plausible(k45, 0)  # 67 m apart after 95 m: 29.5 m allowed
    k_far = len(xy) - 3  # (0, 8), ~8 m from keyframe 0 by the odometry
    assert det.plausible(k_far, 0)
    strict = LoopDetector(SlamConfig(loop={"max_gap_m": 2.0, "max_drift": 0.0}), store)
    assert not strict.plausible(last, 0)
    det.index.close()
    strict.index.close()
