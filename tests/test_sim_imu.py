"""The simulator's IMU and GNSS: measured along the same smooth trajectory that places the points,
so gtsam's preintegration of the noise-free IMU carries one scan pose to the next."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_slam.io.trajectory import camera_to_lidar_poses, read_kitti_calib_tr, read_kitti_poses
from lidar_slam.sim import SENSORS, simulate_sequence
from lidar_slam.sim.imu_gnss import (
    BMI088,
    NOISELESS,
    GnssOptions,
    ImuOptions,
    SmoothTrajectory,
    enu_to_wgs84,
    simulate_imu,
)

SMALL = dataclasses.replace(SENSORS["vlp16"], n_azimuth=360)


def winding(n: int, rate_hz: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and T_world_lidar of a car that speeds up, weaves and climbs (lidar 1.8 m up)."""
    t = np.arange(n) / rate_hz
    x = 8.0 * t + 0.8 * t**2
    y = 3.0 * np.sin(0.8 * t)
    z = 1.8 + 0.05 * x
    yaw = np.arctan2(np.gradient(y, t), np.gradient(x, t))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("zyx", np.c_[yaw, -0.05 + 0 * t, 0.02 * np.sin(t)]
                                           ).as_matrix()
    poses[:, :3, 3] = np.c_[x, y, z]
    return t, poses


def T_lidar_imu() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [180.0, 0.0, 90.0], degrees=True).as_matrix()
    T[:3, 3] = [0.3, -0.1, -0.25]
    return T


def preintegrate(T_world_imu: np.ndarray, v_world: np.ndarray, stamps: np.ndarray,
                 gyro: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """gtsam's prediction of T_world_imu at stamps[-1] from the samples (trapezoidal: the mean
    of each pair of samples over its interval), gravity 9.81 along -z."""
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.setGyroscopeCovariance(np.eye(3) * 1e-8)
    params.setAccelerometerCovariance(np.eye(3) * 1e-8)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
    for i in range(len(stamps) - 1):
        pim.integrateMeasurement(0.5 * (accel[i] + accel[i + 1]), 0.5 * (gyro[i] + gyro[i + 1]),
                                 stamps[i + 1] - stamps[i])
    state = gtsam.NavState(gtsam.Pose3(T_world_imu), v_world)
    return pim.predict(state, gtsam.imuBias.ConstantBias()).pose().matrix()


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) between two poses."""
    d = np.linalg.inv(T_a) @ T_b
    return (float(np.linalg.norm(d[:3, 3])),
            float(np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude())))


def test_simulate_imu_preintegrates_from_one_written_scan_pose_to_the_next(tmp_path):
    stamps, poses = winding(8)
    T_li = T_lidar_imu()
    s = simulate_sequence(poses, stamps, tmp_path, SMALL, seed=1, n_scans=6,
                          imu=ImuOptions(rate_hz=200.0, noise=NOISELESS, T_lidar_imu=T_li))
    assert s.n_imu == 6 * 20 + 1  # to the end of the last sweep
    Tr = read_kitti_calib_tr(tmp_path / "calib.txt")
    T_seq_lidar = camera_to_lidar_poses(read_kitti_poses(tmp_path / "poses.txt"), Tr)
    T_world_seq = np.eye(4)
    T_world_seq[:3] = np.loadtxt(tmp_path / "T_world_seq.txt").reshape(3, 4)
    T_world_imu = T_world_seq @ T_seq_lidar @ T_li
    imu = np.loadtxt(tmp_path / "imu.csv", delimiter=",", skiprows=1)
    truth = np.loadtxt(tmp_path / "imu_truth.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(imu[:, 1:7], truth[:, 1:7], atol=1e-7)  # noise-free: = truth
    worst = (0.0, 0.0)
    for k in range(5):
        i, j = np.searchsorted(imu[:, 0], s.stamps_s[[k, k + 1]] - 1e-6)
        assert np.allclose(imu[[i, j], 0], s.stamps_s[[k, k + 1]], atol=1e-6)
        T_pred = preintegrate(T_world_imu[k], truth[i, 13:16], imu[i:j + 1, 0],
                              imu[i:j + 1, 1:4], imu[i:j + 1, 4:7])
        dt_m, dr_deg = pose_error(T_pred, T_world_imu[k + 1])
        worst = (max(worst[0], dt_m), max(worst[1], dr_deg))
    assert worst[0] < 1e-3 and worst[1] < 1e-3, worst  # within a mm and a mdeg over 0.1 s


def test_simulate_imu_at_rest_measures_gravity_up_and_no_rotation():
    stamps = np.arange(5) * 0.1
    poses = np.tile(np.eye(4), (5, 1, 1))
    traj = SmoothTrajectory(stamps, poses)
    imu = simulate_imu(traj, 0.0, 0.4, ImuOptions(noise=NOISELESS), np.random.default_rng(0))
    np.testing.assert_allclose(imu.accel, np.tile([0.0, 0.0, 9.81], (len(imu.accel), 1)),
                               atol=1e-9)
    np.testing.assert_allclose(imu.gyro, 0.0, atol=1e-12)


def test_simulate_imu_noise_has_the_bmi088_white_noise_and_a_slow_bias():
    stamps = np.arange(101) * 0.1
    traj = SmoothTrajectory(stamps, np.tile(np.eye(4), (101, 1, 1)))
    imu = simulate_imu(traj, 0.0, 10.0, ImuOptions(rate_hz=200.0), np.random.default_rng(5))
    white_g = np.diff(imu.gyro - imu.gyro_bias, axis=0).std() / np.sqrt(2)
    white_a = np.diff(imu.accel - imu.accel_bias - imu.accel_true, axis=0).std() / np.sqrt(2)
    assert white_g == pytest.approx(BMI088.gyro_noise_density * np.sqrt(200.0), rel=0.05)
    assert white_a == pytest.approx(BMI088.accel_noise_density * np.sqrt(200.0), rel=0.05)
    # The measurements carry the bias: their mean error is the bias's mean, to the white noise's
    # share (n = 2001 samples), and the bias is there (BMI088 start spread 0.1 deg/s, 5 mg).
    n = len(imu.stamps_s)
    for meas, true, bias, white in ((imu.gyro, 0.0, imu.gyro_bias, white_g),
                                    (imu.accel, imu.accel_true, imu.accel_bias, white_a)):
        np.testing.assert_allclose((meas - true).mean(0), bias.mean(0),
                                   atol=5 * white / np.sqrt(n))
    assert np.linalg.norm(imu.gyro_bias[0]) > 0.2 * BMI088.gyro_bias_sigma
    assert np.linalg.norm(imu.accel_bias[0]) > 0.2 * BMI088.accel_bias_sigma
    # The bias wanders slowly: over 10 s far less than its initial spread allows.
    drift = np.abs(imu.gyro_bias[-1] - imu.gyro_bias[0])
    assert np.all(drift < 10 * BMI088.gyro_bias_random_walk * np.sqrt(10.0))


def test_simulate_without_imu_or_gnss_writes_no_inertial_files(tmp_path):
    stamps, poses = winding(3)
    simulate_sequence(poses, stamps, tmp_path, SMALL, seed=0)
    for name in ("imu.csv", "imu_truth.csv", "gnss.csv", "gnss_truth.csv", "T_world_seq.txt"):
        assert not (tmp_path / name).exists()


def test_simulate_gnss_fixes_are_the_antenna_on_wgs84_with_flagged_jumps(tmp_path):
    pytest.importorskip("pyproj")
    stamps, poses = winding(101)  # 10 s: 11 fixes at 1 Hz
    opts = GnssOptions(rate_hz=1.0, dropout=0.2, jump_fraction=0.3, lever_arm_m=(0.1, 0.0, 0.5))
    s = simulate_sequence(poses, stamps, tmp_path, SMALL, seed=2, n_scans=100, gnss=opts)
    truth = np.loadtxt(tmp_path / "gnss_truth.csv", delimiter=",", skiprows=1)
    fixes = np.loadtxt(tmp_path / "gnss.csv", delimiter=",", skiprows=1)
    assert (tmp_path / "gnss.csv").read_text().splitlines()[0] == \
        "stamp_s,lat_deg,lon_deg,alt_m,sigma_h_m,sigma_v_m"
    np.testing.assert_allclose(truth[:, 0], np.arange(11.0))
    kept = truth[:, 7] == 0
    assert s.n_gnss == len(fixes) == kept.sum() and 0 < len(fixes) < 11
    np.testing.assert_allclose(fixes[:, 0], truth[kept, 0])
    # The truth is the antenna: the lever arm turned with the lidar, on top of the lidar.
    T_world_seq = np.eye(4)
    T_world_seq[:3] = np.loadtxt(tmp_path / "T_world_seq.txt").reshape(3, 4)
    T_seq_lidar = camera_to_lidar_poses(read_kitti_poses(tmp_path / "poses.txt"), np.eye(4))
    T = T_world_seq @ T_seq_lidar[::10]
    np.testing.assert_allclose(truth[:10, 1:4], T[:, :3, 3] + T[:, :3, :3] @ [0.1, 0.0, 0.5],
                               atol=1e-6)
    # WGS84 at the datum: 1 m north is 1/111.2 km of latitude there, 1 m up is 1 m of height.
    lat0, lon0, h0 = opts.datum
    d = enu_to_wgs84(np.array([[0.0, 0.0, 0.0], [0.0, 1000.0, 0.0], [0.0, 0.0, 10.0]]),
                     opts.datum)
    np.testing.assert_allclose(d[0], [lat0, lon0, h0], atol=1e-9)
    assert (d[1, 0] - lat0) * 111_200.0 == pytest.approx(1000.0, rel=2e-3)
    assert d[2, 2] - h0 == pytest.approx(10.0, abs=1e-6)
    # Fixes are off the truth by the noise, or by a flagged jump of 20-50 m.
    lat = np.radians(truth[kept, 4])
    north = (fixes[:, 1] - truth[kept, 4]) * 111_200.0
    east = (fixes[:, 2] - truth[kept, 5]) * 111_200.0 * np.cos(lat)
    off = np.hypot(north, east)
    jump = truth[kept, 8]
    assert np.all(off[jump == 0] < 5 * opts.sigma_h_m * np.sqrt(2))
    assert np.all((jump[jump > 0] >= 20) & (jump[jump > 0] <= 50))
    np.testing.assert_allclose(off[jump > 0], jump[jump > 0], atol=5 * opts.sigma_h_m * 1.5)
    assert (jump > 0).any()


def test_simulate_cli_writes_imu_and_gnss_and_overwrite_removes_them(tmp_path):
    pytest.importorskip("pyproj")
    root = Path(__file__).resolve().parents[1] / "sample_scans"
    out = tmp_path / "sim"
    base = [sys.executable, "-m", "lidar_slam.cli", "simulate", str(root / "poses.txt"),
            "--calib", str(root / "calib.txt"), "--out", str(out), "--n-scans", "3",
            "--sensor", "vlp16"]
    bad = subprocess.run([*base, "--imu", "--imu-extrinsic", "0,0,0,90"], capture_output=True,
                         text=True, timeout=300)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr
    assert bad.stderr.strip().splitlines()[-1].startswith("lidar-slam: error: --imu-extrinsic")
    proc = subprocess.run([*base, "--imu", "--imu-rate", "100", "--gnss", "--gnss-rate", "10",
                           "--imu-extrinsic", "0.1,0,-0.2,0,0,90"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "IMU samples" in proc.stdout and "GNSS fixes" in proc.stdout
    imu = (out / "imu.csv").read_text().splitlines()
    assert imu[0] == "stamp_s,wx,wy,wz,ax,ay,az" and len(imu) == 1 + 31  # 0.3 s at 100 Hz
    assert (out / "gnss.csv").is_file()
    assert "T_lidar_imu (row-major 3x4): 0 -1 0 0.1 1 0 0 0 0 0 1 -0.2" in \
        (out / "README.txt").read_text()
    # Re-simulated without them into the same folder: no stale IMU or GNSS left behind.
    again = subprocess.run([*base, "--overwrite"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert not any((out / n).exists() for n in ("imu.csv", "imu_truth.csv", "gnss.csv",
                                                "gnss_truth.csv", "T_world_seq.txt"))
