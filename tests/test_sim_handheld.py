"""`simulate --motion handheld`: a walk with quick looks, flicks and shakes within 180 deg/s and
10 m/s^2, never closer than 0.5 m to a surface, whose IMU is measured on the trajectory that
places the points."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_one_line_error
from test_sim_imu import pose_error, preintegrate

from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.sim import SENSORS
from lidar_slam.sim.handheld import (
    CLEARANCE_M,
    MAX_ACCEL_MPS2,
    MAX_RATE_DPS,
    build_site,
    clearance_m,
    handheld_motion,
)
from lidar_slam.sim.imu_gnss import NOISELESS, ImuOptions
from lidar_slam.sim.motions import simulate_handheld

# Fewer columns than an OS1-64 (1024) keeps the scans cheap; the motion is the same.
SMALL_OS1 = dataclasses.replace(SENSORS["os1-64"], n_azimuth=256)


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_handheld_motion_reaches_but_never_passes_180_deg_s_and_10_m_s2(kind):
    kinds = set()
    for seed in (0, 1):
        site = build_site(kind, seed, SMALL_OS1)
        m = handheld_motion(site.path, site.ground, seed, 25.0)
        st = m.stats
        assert 0.85 * MAX_RATE_DPS < st.max_rate_dps <= MAX_RATE_DPS, st
        assert 0.4 * MAX_ACCEL_MPS2 < st.max_accel_mps2 <= MAX_ACCEL_MPS2, st
        # A walk: about 1-1.6 m/s on average once set off (1 s standing, 1 s speeding up).
        assert 1.0 < st.distance_m / (25.0 - 1.5) < 1.7, st
        kinds |= {b.kind for b in m.bursts}
        assert st.n_bursts >= 6
        # Steps: the height bobs at 1.8-2 Hz while walking.
        t = np.arange(5.0, 25.0, 0.01)
        z = m.trajectory(t)[:, 2, 3]
        if kind == "indoor":  # flat floor: the bob is all there is
            spectrum = np.abs(np.fft.rfft(z - z.mean()))
            f = np.fft.rfftfreq(len(z), 0.01)
            assert 1.7 < f[np.argmax(spectrum[1:]) + 1] < 2.1
    assert kinds == {"look", "flick", "shake", "jolt"}


def test_handheld_walk_keeps_half_a_metre_from_every_surface_and_comes_back():
    for kind in ("indoor", "outdoor"):
        for seed in (0, 1, 2):  # the benchmark's seeds
            site = build_site(kind, seed, SMALL_OS1)
            m = handheld_motion(site.path, site.ground, seed, 65.0)
            assert clearance_m(site.world, m.trajectory, 0.0, 65.0).min() >= CLEARANCE_M
            assert m.stats.laps > 1.0  # a loop: places are seen again


def test_handheld_imu_preintegrates_from_one_scan_pose_to_the_next_through_bursts(tmp_path):
    T_li = np.eye(4)
    T_li[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T_li[:3, 3] = [0.02, -0.03, -0.05]
    # 1 kHz: trapezoidal preintegration at 200 Hz is itself ~6 mdeg off over 0.1 s of a shake.
    s, st = simulate_handheld(tmp_path, "indoor", 3, 3.0, SMALL_OS1,
                              imu=ImuOptions(rate_hz=1000.0, noise=NOISELESS, T_lidar_imu=T_li))
    assert s.n_scans == 30
    T_world_seq = np.eye(4)
    T_world_seq[:3] = np.loadtxt(tmp_path / "T_world_seq.txt").reshape(3, 4)
    T_world_imu = T_world_seq @ read_kitti_poses(tmp_path / "poses.txt") @ T_li
    imu = np.loadtxt(tmp_path / "imu.csv", delimiter=",", skiprows=1)
    truth = np.loadtxt(tmp_path / "imu_truth.csv", delimiter=",", skiprows=1)
    rate = np.linalg.norm(truth[:, 1:4], axis=1)
    worst, fastest = (0.0, 0.0), 0.0
    for k in range(29):
        i, j = np.searchsorted(imu[:, 0], s.stamps_s[[k, k + 1]] - 1e-6)
        fastest = max(fastest, float(rate[i:j + 1].max()))
        T_pred = preintegrate(T_world_imu[k], truth[i, 13:16], imu[i:j + 1, 0],
                              imu[i:j + 1, 1:4], imu[i:j + 1, 4:7])
        dt_m, dr_deg = pose_error(T_pred, T_world_imu[k + 1])
        worst = (max(worst[0], dt_m), max(worst[1], dr_deg))
    assert np.degrees(fastest) > 90.0  # the check covers a burst, not a stroll
    assert worst[0] < 1e-3 and worst[1] < 1e-3, worst  # within a mm and a mdeg over 0.1 s


def test_handheld_same_seed_same_bytes(tmp_path):
    runs = {}
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        simulate_handheld(tmp_path / name, "outdoor", seed, 0.5, SMALL_OS1,
                          imu=ImuOptions(), gnss=None)
        runs[name] = {p.relative_to(tmp_path / name): p.read_bytes()
                      for p in sorted((tmp_path / name).rglob("*")) if p.is_file()}
    assert runs["a"] == runs["b"] and len(runs["a"]) == 2 * 5 + 9  # with lidar_slam.yaml
    assert runs["a"][next(k for k in runs["a"] if k.name == "imu.csv")] != \
        runs["c"][next(k for k in runs["c"] if k.name == "imu.csv")]


def lidar_slam(*args):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("args, needle", [
    (["simulate", "--motion", "handheld", "--world", "indoor", "--gnss"], "--gnss needs"),
    (["simulate", "poses.txt", "--motion", "handheld"], "POSES"),
    (["simulate", "--world", "outdoor"], "--motion handheld"),
    (["simulate"], "POSES"),
])
def test_simulate_handheld_bad_flag_combinations_are_one_line(tmp_path, args, needle):
    assert_one_line_error(lidar_slam(*args, "--out", tmp_path / "o"), needle)
    assert not (tmp_path / "o").exists()


def test_simulate_handheld_cli_writes_a_kitti_sequence_with_imu_and_gnss(tmp_path):
    pytest.importorskip("pyproj")
    out = tmp_path / "hh"
    proc = lidar_slam("simulate", "--motion", "handheld", "--world", "outdoor", "--duration-s",
                      "0.5", "--imu", "--gnss", "--gnss-rate", "10", "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "handheld outdoor" in proc.stdout and "max rate" in proc.stdout
    assert len(list((out / "velodyne").glob("*.bin"))) == 5
    for name in ("poses.txt", "times.txt", "calib.txt", "imu.csv", "imu_truth.csv", "gnss.csv",
                 "gnss_truth.csv", "T_world_seq.txt", "bursts.csv"):
        assert (out / name).is_file(), name
    np.testing.assert_allclose(np.loadtxt(out / "times.txt"), [0.0, 0.1, 0.2, 0.3, 0.4])
    assert "handheld walk (outdoor, seed 0)" in (out / "README.txt").read_text()
    assert "sensor os1-64" in (out / "README.txt").read_text()  # the handheld default
