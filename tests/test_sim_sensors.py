"""The simulator's sensors (spinning XT32 and OS0-128, a non-repetitive Mid-360 with a time per
point), its stamp conventions (sweep start or end) and an IMU on a clock of its own."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error
from scipy.spatial.transform import Rotation

from lidar_slam.config import load_config
from lidar_slam.io.imu_gnss import read_imu_csv
from lidar_slam.io.sources import KittiSource
from lidar_slam.sim import (
    ALBEDO,
    CLASSES,
    OVERLAY_FILE,
    SENSORS,
    NonRepetitiveModel,
    PoseInterpolator,
    SimScan,
    build_world,
    get_sensor,
    place_on_terrain,
    simulate_scan,
    simulate_sequence,
)
from lidar_slam.sim.imu_gnss import ImuOptions

SMALL = dataclasses.replace(SENSORS["vlp16"], n_azimuth=360)


def straight(n: int, speed_mps: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (10 Hz) and T_world_lidar along +x, turning 20 deg/s, 1.8 m over the ground."""
    stamps = np.arange(n) / 10.0
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", np.radians(20.0) * stamps[:, None]).as_matrix()
    poses[:, :3, 3] = np.c_[speed_mps * stamps, np.zeros(n), np.full(n, 1.8)]
    return stamps, poses


@pytest.fixture(scope="module")
def street():
    """A street world (built for a 120 m sensor, as reach) and the sensor's poses in it."""
    stamps, poses = straight(3)
    world = build_world(poses, "hdl64", seed=5)
    placed = place_on_terrain(poses, world.terrain, 1.8)
    return world, stamps, PoseInterpolator(stamps, placed)


def elevation_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def one_scan(street, sensor, frame: int = 0, seed: int = 0) -> SimScan:
    world, stamps, at = street
    return simulate_scan(world, get_sensor(sensor), at, stamps[1], np.random.default_rng(0),
                         frame, seed)


# ----------------------------------------------------------------------------------------------
# Sensors


def test_sensor_xt32_has_32_beams_a_degree_apart_and_2000_columns(street):
    xt = SENSORS["xt32"]
    assert np.allclose(sorted(xt.elevations_deg), np.arange(-16.0, 16.0))
    sweep = xt.sweep()
    assert sweep.directions.shape == (2000, 32, 3) and len(sweep.times_s) == 2000
    scan = one_scan(street, "xt32")
    assert 30_000 < len(scan.points) <= 64_000
    el = elevation_deg(scan.points)  # nominal directions: only the noise moves them
    assert el.min() > -16.01 and el.max() < 15.01
    assert 0.0 <= scan.times_s.min() and scan.times_s.max() < xt.period_s
    assert len(np.unique(scan.times_s)) <= 2000  # a column shares its time
    r = np.linalg.norm(scan.points, axis=1)
    assert r.max() < 120.0 + 3 * xt.range_noise_m


def test_sensor_os0_128_sees_45_degrees_up_and_down_to_50_m(street):
    os0 = SENSORS["os0-128"]
    assert len(os0.elevations_deg) == 128 and os0.n_azimuth == 1024
    assert max(os0.elevations_deg) == 45.0 and min(os0.elevations_deg) == -45.0
    scan = one_scan(street, "os0-128")
    el = elevation_deg(scan.points)
    assert el.min() > -45.01 and el.max() < 45.01
    assert el.min() < -40.0 and el.max() > 30.0  # the ground below, facades above
    r = np.linalg.norm(scan.points, axis=1)
    assert r.max() < 50.0 + 3 * os0.range_noise_m and r.min() > 0.3 - 3 * os0.range_noise_m
    assert 0.0 <= scan.times_s.min() and scan.times_s.max() < os0.period_s


def test_sensor_mid360_fires_each_point_at_its_own_time_over_the_fov(street):
    mid = SENSORS["mid360"]
    assert isinstance(mid, NonRepetitiveModel) and mid.points_per_sweep == 20_000
    sweep = mid.sweep(7, seed=3)
    assert sweep.directions.shape == (20_000, 1, 3)
    assert np.all(np.diff(sweep.times_s) > 0) and sweep.times_s[0] == 0.0
    assert sweep.times_s[-1] == pytest.approx(mid.period_s - 1.0 / mid.points_per_s)
    d = sweep.directions[:, 0]
    el = elevation_deg(d)
    assert el.min() > -7.001 and el.max() < 52.001
    assert el.min() < -6.5 and el.max() > 51.5
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    assert np.all(np.histogram(az, 72, (-180.0, 180.0))[0] > 0.8 * 20_000 / 72)  # all around
    # No rings: elevations take thousands of values (a 64-beam lidar: 64).
    assert len(np.unique(np.round(el, 2))) > 3000
    scan = one_scan(street, mid, frame=7, seed=3)
    assert 5_000 < len(scan.points) < 20_000
    assert len(np.unique(scan.times_s)) == len(scan.points)
    r = np.linalg.norm(scan.points, axis=1)
    assert r.max() < 40.0 + 3 * mid.range_noise_m


def test_sensor_mid360_pattern_moves_on_every_frame_and_repeats_for_the_seed():
    mid = SENSORS["mid360"]
    a, again = mid.sweep(4, seed=1), mid.sweep(4, seed=1)
    assert a.directions.tobytes() == again.directions.tobytes()
    for other in (mid.sweep(5, seed=1), mid.sweep(4, seed=2)):
        # Not the same directions, nor the same ones in another order: the nearest neighbour
        # of a point of one frame is rarely the point itself.
        assert not np.allclose(other.directions, a.directions)
        assert np.median(np.linalg.norm(other.directions - a.directions, axis=-1)) > 0.005
    # Over ten frames the pattern fills the FOV far more densely than one.
    cells = [np.unique(_cell(mid.sweep(k, 0).directions[:, 0])) for k in range(10)]
    assert len(np.unique(np.concatenate(cells))) > 3 * len(cells[0])


def _cell(d: np.ndarray) -> np.ndarray:
    """A 0.25 x 0.25 deg cell index per direction (N, 3)."""
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0])) + 180.0
    el = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0))) + 90.0
    return (az // 0.25).astype(np.int64) * 1000 + (el // 0.25).astype(np.int64)


def _scan_before_sweeps(world, sensor, poses_at, stamp_s, rng) -> SimScan:
    """simulate_scan as it was before sensors gave their own sweeps (commit 58ac8a9)."""
    tau = sensor.column_times_s()
    T = poses_at(stamp_s + tau)
    d_loc = sensor.directions()
    d_true = sensor.directions(sensor.elevation_error_deg) if sensor.elevation_error_deg else d_loc
    d_world = np.einsum("aij,abj->abi", T[:, :3, :3], d_true).reshape(-1, 3)
    n_b = d_loc.shape[1]
    o_world = np.repeat(T[:, :3, 3], n_b, axis=0)
    hit = world.cast(o_world, d_world)
    r = hit["t_hit"].astype(np.float64)
    cos_inc = np.abs(np.sum(hit["normal"] * d_world, axis=1))
    u = rng.random(len(r))
    noise = np.clip(rng.normal(0.0, sensor.range_noise_m, len(r)), -3 * sensor.range_noise_m,
                    3 * sensor.range_noise_m)
    p_drop = sensor.dropout + 0.6 * np.clip(1.0 - cos_inc / 0.12, 0.0, 1.0)
    ok = np.isfinite(r) & (r >= sensor.min_range_m) & (r <= sensor.max_range_m) & (u >= p_drop)
    rn = r[ok] + noise[ok]
    points = d_loc.reshape(-1, 3)[ok] * rn[:, None]
    albedo = np.array([ALBEDO[c] for c in CLASSES])[hit["class"][ok]]
    texture = 0.8 + 0.4 * ((hit["prim"][ok].astype(np.int64) * 2654435761) % 1000) / 1000.0
    intensity = np.clip(albedo * texture * (0.35 + 0.65 * cos_inc[ok]) * np.exp(-rn / 400.0),
                        0.0, 1.0)
    return SimScan(points, intensity, np.repeat(tau, n_b)[ok])


@pytest.mark.parametrize("name", ["hdl64", "os1-64"])
def test_spinning_sensors_cast_the_same_bytes_as_before_sweeps(street, name):
    world, stamps, at = street
    sensor = SENSORS[name]
    new = simulate_scan(world, sensor, at, stamps[1], np.random.default_rng([3, 1, 1]), 1, 3)
    old = _scan_before_sweeps(world, sensor, at, stamps[1], np.random.default_rng([3, 1, 1]))
    for field in ("points", "intensity", "times_s"):
        assert getattr(new, field).tobytes() == getattr(old, field).tobytes(), field


# ----------------------------------------------------------------------------------------------
# Stamps at the sweep's end


def test_stamp_end_stamps_and_poses_the_sweep_end_with_negative_point_times(tmp_path):
    stamps, poses = straight(3)
    start = simulate_sequence(poses, stamps, tmp_path / "start", SMALL, seed=2)
    end = simulate_sequence(poses, stamps, tmp_path / "end", SMALL, seed=2, stamp="end")
    period = SMALL.period_s
    np.testing.assert_allclose(np.loadtxt(tmp_path / "end" / "times.txt"), stamps + period)
    for k in range(3):
        name = f"{k:06d}.bin"
        # The same sweeps: the same points, their times relative to the later stamp.
        assert ((tmp_path / "start" / "velodyne" / name).read_bytes()
                == (tmp_path / "end" / "velodyne" / name).read_bytes())
        t_start = np.fromfile(tmp_path / "start" / "velodyne_times" / name, np.float32)
        t_end = np.fromfile(tmp_path / "end" / "velodyne_times" / name, np.float32)
        np.testing.assert_allclose(t_end, t_start - period, atol=1e-7)
        assert -period <= t_end.min() < -0.99 * period
        assert -1.01 * period / SMALL.n_azimuth < t_end.max() < 0.0  # the last column: ~0
    # The poses are the truth at the sweep's end: 20 deg/s turns 2 deg over a sweep.
    at = PoseInterpolator(stamps, start.poses_world_lidar)
    np.testing.assert_allclose(end.poses_world_lidar, at(stamps + period), atol=1e-9)
    turn = Rotation.from_matrix(start.poses_world_lidar[:, :3, :3]).inv() * Rotation.from_matrix(
        end.poses_world_lidar[:, :3, :3])
    np.testing.assert_allclose(np.degrees(turn.magnitude()), 2.0, atol=0.05)
    assert "is the END of the sweep" in (tmp_path / "end" / "README.txt").read_text()
    # Read back as a run reads it: negative times relative to the stamp, kept as they are.
    scan = next(KittiSource(tmp_path / "end").scans(1, 1))
    assert scan.stamp_s == pytest.approx(0.2)
    assert scan.point_times.max() < 0.0 and scan.point_times.min() >= -period - 1e-6


# ----------------------------------------------------------------------------------------------
# An IMU on its own clock


def test_imu_time_offset_shifts_imu_csv_and_the_overlay_puts_it_back(tmp_path):
    stamps, poses = straight(4)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [90.0, 0.0, 0.0], degrees=True).as_matrix()
    T[:3, 3] = [0.05, 0.02, -0.03]
    runs = {}
    for name, offset in (("same", 0.0), ("late", 0.02)):
        out = tmp_path / name
        simulate_sequence(poses, stamps, out, SMALL, seed=1, n_scans=3,
                          imu=ImuOptions(T_lidar_imu=T, time_offset_s=offset))
        runs[name] = np.loadtxt(out / "imu.csv", delimiter=",", skiprows=1)
    truth = np.loadtxt(tmp_path / "late" / "imu_truth.csv", delimiter=",", skiprows=1)
    # The same samples, stamped 0.02 s earlier on the IMU's clock; the truth on the lidar's.
    np.testing.assert_array_equal(runs["late"][:, 1:], runs["same"][:, 1:])
    np.testing.assert_allclose(runs["late"][:, 0], runs["same"][:, 0] - 0.02, atol=1e-9)
    np.testing.assert_allclose(truth[:, 0], runs["same"][:, 0], atol=1e-9)
    cfg = load_config(tmp_path / "late" / OVERLAY_FILE)
    assert cfg.imu.time_offset_s == 0.02
    assert cfg.imu.T_lidar_imu == [0.05, 0.02, -0.03, 0.0, 0.0, 90.0]
    np.testing.assert_allclose(cfg.imu.T_lidar_imu_matrix(), T, atol=1e-9)
    back = read_imu_csv(tmp_path / "late" / "imu.csv").shifted(cfg.imu.time_offset_s)
    np.testing.assert_allclose(back.stamp_s, truth[:, 0], atol=1e-9)
    assert "0.02 s behind the lidar's" in (tmp_path / "late" / "README.txt").read_text()
    same = load_config(tmp_path / "same" / OVERLAY_FILE)
    assert same.imu.time_offset_s == 0.0


def lidar_slam(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_simulate_cli_mid360_handheld_stamped_at_the_end_with_a_late_imu(tmp_path):
    out = tmp_path / "hh"
    proc = lidar_slam("simulate", "--motion", "handheld", "--duration-s", "0.5", "--sensor",
                      "mid360", "--stamp", "end", "--imu", "--imu-time-offset", "0.01",
                      "--imu-extrinsic", "0.05,0.02,-0.03,0,0,90", "--out", out)
    assert proc.returncode == 0, proc.stderr
    np.testing.assert_allclose(np.loadtxt(out / "times.txt"), [0.1, 0.2, 0.3, 0.4, 0.5])
    t = np.fromfile(out / "velodyne_times" / "000002.bin", np.float32)
    assert len(t) > 5_000 and -0.1 <= t.min() and t.max() < 0.0
    assert np.loadtxt(out / "imu.csv", delimiter=",", skiprows=1)[0, 0] == pytest.approx(-0.01)
    cfg = load_config(out / OVERLAY_FILE)
    assert cfg.imu.time_offset_s == 0.01 and cfg.imu.T_lidar_imu[5] == 90.0
    assert "sensor mid360: non-repetitive" in (out / "README.txt").read_text()
    assert_one_line_error(lidar_slam("simulate", "--motion", "handheld", "--imu-time-offset",
                                     "0.01", "--out", tmp_path / "o"), "--imu-time-offset")
    assert not Path(tmp_path / "o").exists()
