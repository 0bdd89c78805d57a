"""The lidar simulator: reproducible, true per-column motion distortion, one terrain, KITTI
layout."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_times,
)
from lidar_slam.o3d import o3d
from lidar_slam.sim import (
    CLASSES,
    SENSORS,
    PoseInterpolator,
    WorldParams,
    build_world,
    load_kitti_truth,
    place_on_terrain,
    simulate_scan,
    simulate_sequence,
)

REPO = Path(__file__).resolve().parents[1]
SMALL = dataclasses.replace(SENSORS["vlp16"], n_azimuth=360)
EXACT = dataclasses.replace(SMALL, range_noise_m=0.0, dropout=0.0)


def straight(n: int, speed_mps: float = 10.0, rate_hz: float = 10.0, yaw_rate_dps: float = 0.0,
             slope: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and T_world_lidar along +x (optionally turning), the sensor 1.8 m over the ground."""
    stamps = np.arange(n) / rate_hz
    poses = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.radians(yaw_rate_dps) * stamps
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    x = speed_mps * stamps
    poses[:, :3, 3] = np.c_[x, np.zeros(n), slope * x + 1.8]
    return stamps, poses


def surface_distance_m(world, points_world: np.ndarray) -> np.ndarray:
    """Distance (m) of world points to the nearest simulated surface."""
    q = o3d.core.Tensor((points_world - world.origin).astype(np.float32))
    return world.scene.compute_distance(q).numpy()


def to_world(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]


def test_simulate_same_seed_same_bytes(tmp_path):
    stamps, poses = straight(4)
    a = simulate_sequence(poses, stamps, tmp_path / "a", SMALL, seed=3)
    simulate_sequence(poses, stamps, tmp_path / "b", SMALL, seed=3)
    simulate_sequence(poses, stamps, tmp_path / "c", SMALL, seed=4)
    assert a.n_scans == 4 and a.points_per_scan > 3000
    for name in ("velodyne/000003.bin", "velodyne_times/000003.bin", "poses.txt", "times.txt"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert ((tmp_path / "a" / "velodyne/000003.bin").read_bytes()
            != (tmp_path / "c" / "velodyne/000003.bin").read_bytes())


def test_simulate_point_times_span_the_sweep(tmp_path):
    stamps, poses = straight(2)
    simulate_sequence(poses, stamps, tmp_path, SMALL, seed=0)
    pts = np.fromfile(tmp_path / "velodyne/000001.bin", np.float32).reshape(-1, 4)
    t = np.fromfile(tmp_path / "velodyne_times/000001.bin", np.float32)
    assert len(t) == len(pts)
    period = SMALL.period_s
    assert t.min() == 0.0 and period * 0.99 < t.max() < period
    assert np.all(np.diff(t) >= 0)  # written in capture order
    # The head starts facing backwards and turns clockwise: azimuth falls with time.
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) % 360.0
    first, mid = az[t < 0.1 * period], az[np.abs(t - 0.5 * period) < 0.05 * period]
    assert np.median(np.abs(first - 180.0)) < 40.0
    assert np.median(np.minimum(mid, 360.0 - mid)) < 30.0  # facing forwards half a sweep later
    assert np.all((pts[:, 3] >= 0) & (pts[:, 3] <= 1))


def test_simulate_motion_distortion_matches_the_motion():
    stamps, poses = straight(8, speed_mps=12.0, yaw_rate_dps=45.0)
    world = build_world(poses, EXACT, seed=1)
    sim = place_on_terrain(poses, world.terrain, EXACT.mount_height_m)
    moving = PoseInterpolator(stamps, sim)
    stamp = stamps[3]
    static = PoseInterpolator(stamps[3:4], sim[3:4])
    rng = np.random.default_rng(0)
    scan = simulate_scan(world, EXACT, moving, stamp, rng)
    still = simulate_scan(world, EXACT, static, stamp, rng)
    late = scan.times_s > 0.5 * EXACT.period_s
    above = scan.points[:, 2] > -1.0  # not ground: the ground hides horizontal shifts
    # Placed with each column's own pose, every point lies on a surface ...
    d_true = surface_distance_m(world, to_world(moving(stamp + scan.times_s), scan.points))
    assert np.median(d_true) < 0.005
    # ... placed with the stamp pose only, late points are off by about the motion since the stamp.
    T_stamp = np.broadcast_to(sim[3], (len(scan.points), 4, 4))
    d_naive = surface_distance_m(world, to_world(T_stamp, scan.points))
    assert np.median(d_naive[late & above]) > 0.2
    assert np.median(d_naive[~late & above]) < np.median(d_naive[late & above])
    # A sensor that does not move needs no correction.
    T_still = np.broadcast_to(sim[3], (len(still.points), 4, 4))
    assert np.median(surface_distance_m(world, to_world(T_still, still.points))) < 0.005


def test_simulate_written_poses_round_trip(tmp_path):
    stamps, poses = straight(6, speed_mps=8.0, yaw_rate_dps=20.0, slope=0.04)
    Tr = np.eye(4)
    Tr[:3, :3] = Rotation.from_euler("zyx", [-90.0, 0.5, -90.0], degrees=True).as_matrix()
    Tr[:3, 3] = [0.27, -0.08, -0.06]
    s = simulate_sequence(poses, stamps, tmp_path, SMALL, seed=2, start=1, n_scans=4,
                          Tr_cam_lidar=Tr)
    Tr_read = read_kitti_calib_tr(tmp_path / "calib.txt")
    np.testing.assert_allclose(Tr_read, Tr, atol=1e-12)
    T_seq_lidar = camera_to_lidar_poses(read_kitti_poses(tmp_path / "poses.txt"), Tr_read)
    np.testing.assert_allclose(T_seq_lidar, np.linalg.inv(s.T_world_seq) @ s.poses_world_lidar,
                               atol=1e-7)
    np.testing.assert_allclose(T_seq_lidar[0], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(read_times(tmp_path / "times.txt"), stamps[1:5], atol=1e-6)
    # The poses written are the ones simulated: scans placed with them land on the world.
    world = build_world(poses, SMALL, seed=2)
    interp = PoseInterpolator(read_times(tmp_path / "times.txt"), s.T_world_seq @ T_seq_lidar)
    for k in (0, 3):
        pts = np.fromfile(tmp_path / f"velodyne/{k:06d}.bin", np.float32).reshape(-1, 4)[:, :3]
        t = np.fromfile(tmp_path / f"velodyne_times/{k:06d}.bin", np.float32)
        d = surface_distance_m(world, to_world(interp(s.stamps_s[k] + t), pts))
        assert np.median(d) < 0.02 and np.quantile(d, 0.9) < 0.05


def test_simulate_terrain_is_one_surface_when_passes_disagree():
    # Two passes along the same street whose heights disagree by 2 m (as a drifting truth).
    s1, p1 = straight(40, speed_mps=15.0)
    p2 = p1.copy()
    p2[:, 1, 3] += 0.4
    p2[:, 2, 3] += 2.0
    stamps = np.r_[s1, s1 + 10.0]
    poses = np.r_[p1, p2]
    world = build_world(poses, SMALL, seed=0)
    sim = place_on_terrain(poses, world.terrain, SMALL.mount_height_m)
    z1, z2 = sim[10:30, 2, 3], sim[50:70, 2, 3]
    assert np.max(np.abs(z1 - z2)) < 0.02
    assert 2.4 < np.mean(z1) < 3.4  # between the passes' 1.8 m and 3.8 m
    # The sensor rides on the one ground: straight down it finds the ground at mount height.
    down = np.tile([0.0, 0.0, -1.0], (40, 1))
    hit = world.cast(sim[10:70:1, :3, 3][np.r_[0:20, 40:60]], down)
    np.testing.assert_allclose(hit["t_hit"], SMALL.mount_height_m, atol=0.02)
    assert set(hit["class"]) == {0}  # ground
    assert len(stamps) == len(sim)


def test_simulate_terrain_follows_a_slope():
    stamps, poses = straight(60, speed_mps=10.0, slope=0.05)
    world = build_world(poses, SMALL, seed=0)
    sim = place_on_terrain(poses, world.terrain, SMALL.mount_height_m)
    mid = slice(15, 45)
    np.testing.assert_allclose(sim[mid, 2, 3], poses[mid, 2, 3], atol=0.05)
    pitch = np.degrees(np.arcsin(sim[mid, 2, 0]))  # x axis climbs with the road
    np.testing.assert_allclose(pitch, np.degrees(np.arctan(0.05)), atol=0.3)
    np.testing.assert_allclose(np.linalg.det(sim[:, :3, :3]), 1.0, atol=1e-9)


def test_simulate_street_of_buildings_only_keeps_the_same_facades():
    stamps, poses = straight(60, speed_mps=10.0)
    full = build_world(poses, SMALL, seed=3)
    bare = build_world(poses, SMALL, seed=3, params=WorldParams(objects=False))
    assert {c for c, n in bare.n_objects.items() if n} == {"facade"}
    assert bare.n_objects["facade"] == full.n_objects["facade"] > 0
    assert sum(n for c, n in full.n_objects.items() if c != "facade") > 0
    # Rays that hit a facade in the full world hit it at the same range in the bare one.
    sim = place_on_terrain(poses, full.terrain, SMALL.mount_height_m)
    az = np.radians(np.arange(0, 360, 2.0))
    dirs = np.c_[np.cos(az), np.sin(az), np.zeros_like(az)]
    origins = np.repeat(sim[::10, :3, 3], len(az), axis=0)
    d = np.tile(dirs, (len(sim[::10]), 1))
    a, b = full.cast(origins, d), bare.cast(origins, d)
    facade = a["class"] == CLASSES.index("facade")
    assert facade.sum() > 50
    np.testing.assert_allclose(a["t_hit"][facade], b["t_hit"][facade], atol=1e-4)
    assert set(np.unique(b["class"][np.isfinite(b["t_hit"])])) <= {CLASSES.index("ground"),
                                                                   CLASSES.index("facade")}


def test_simulate_sensor_models():
    hdl, vlp, os1 = SENSORS["hdl64"], SENSORS["vlp16"], SENSORS["os1-64"]
    assert len(hdl.elevations_deg) == 64 and max(hdl.elevations_deg) == 2.0
    assert min(hdl.elevations_deg) == pytest.approx(-24.8)
    assert len(vlp.elevations_deg) == 16 and max(vlp.elevations_deg) == 15.0
    assert len(os1.elevations_deg) == 64 and os1.n_azimuth == 1024
    assert max(os1.elevations_deg) == pytest.approx(16.6)
    d = vlp.directions()
    assert d.shape == (vlp.n_azimuth, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)


def test_simulate_sample_scans_match_their_tool():
    root = REPO / "sample_scans"
    stamps = read_times(root / "times.txt")
    poses = camera_to_lidar_poses(read_kitti_poses(root / "poses.txt"),
                                  read_kitti_calib_tr(root / "calib.txt"))
    assert 40 <= len(stamps) == len(poses) == len(list((root / "velodyne").glob("*.bin")))
    # A loop: the last scan comes back within 5 m of one of the first 20, heading the same way.
    d = np.linalg.norm(poses[:20, :2, 3] - poses[-1, :2, 3], axis=1)
    j = int(np.argmin(d))
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    assert d[j] < 5.0 and abs(np.angle(np.exp(1j * (yaw[-1] - yaw[j])))) < np.radians(30)
    assert np.max(np.linalg.norm(poses[:, :2, 3] - poses[0, :2, 3], axis=1)) > 20.0
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    assert size < 6e6


def test_simulate_loads_kitti_truth(kitti_gt):
    gt = load_kitti_truth(kitti_gt, 7)
    assert gt.poses_world_lidar.shape == (1101, 4, 4) and len(gt.stamps_s) == 1101
    np.testing.assert_allclose(gt.poses_world_lidar[0], np.eye(4), atol=1e-6)
    # Lidar frame: x forward, so the heading follows the direction of travel.
    step = gt.poses_world_lidar[60, :3, 3] - gt.poses_world_lidar[40, :3, 3]
    assert step @ gt.poses_world_lidar[50, :3, 0] > 0.95 * np.linalg.norm(step)


def test_simulate_elevation_error_biases_points_like_kittis_lasers():
    # The lasers point elevation_error_deg higher than the nominal elevations the points are
    # computed with: ground returns then come back farther away and too low, as on real KITTI.
    import dataclasses

    from lidar_slam.sim import SENSORS

    assert SENSORS["hdl64"].elevation_error_deg == pytest.approx(0.2)
    stamps, poses = straight(3, speed_mps=0.0)
    base = dataclasses.replace(SENSORS["vlp16"], n_azimuth=360, range_noise_m=0.0, dropout=0.0)
    world = build_world(poses, base, seed=3)
    sim = place_on_terrain(poses, world.terrain, base.mount_height_m)
    at = PoseInterpolator(stamps, sim)
    exact = simulate_scan(world, base, at, stamps[0], np.random.default_rng(0))
    tilted = simulate_scan(world, dataclasses.replace(base, elevation_error_deg=0.5), at,
                           stamps[0], np.random.default_rng(0))
    def ground(s):
        return s.points[(s.points[:, 2] < -1.0) & (np.hypot(*s.points[:, :2].T) < 15)]

    assert np.median(ground(tilted)[:, 2]) < np.median(ground(exact)[:, 2]) - 0.02


def test_simulate_says_when_the_trajectory_ends_before_n_scans(tmp_path, caplog):
    """--start 1099 --n-scans 5 on a 1101-pose trajectory gave 2 scans without a word."""
    stamps, poses = straight(6, speed_mps=8.0)
    s = simulate_sequence(poses, stamps, tmp_path, SMALL, seed=2, start=4, n_scans=5)
    assert len(s.stamps_s) == 2
    assert "simulating 2 scans, not the 5 asked for: the trajectory has 6 poses" in caplog.text
