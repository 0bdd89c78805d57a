"""Sensor pcaps (issue 30, items 2 and 3): an Ouster pcap + metadata through ouster-sdk and a
Velodyne pcap through velodyne-decoder. CI installs the pcap extra and ouster-sdk (tools/dev.sh
test); without the packages these tests skip.

Two kinds of input:
- pcaps written at test time (run in CI, seconds): a simulated OS1-64 walk with its IMU, written
  as Ouster packets by ouster-sdk itself, and simulated VLP-16 sweeps written by the VLP-16
  packet encoder in tests/pcap_writers.py; both checked against the simulated truth.
- two small public captures (marker `public_captures`): ouster-sdk's OS-1-128 and VeloView's
  HDL-32E. They are fetched data, which the repository may not hold and CI's ../shared lacks:
  these tests skip wherever ../shared/data/pcaps is absent, even under
  LIDAR_SLAM_REQUIRE_SHARED=1. To run them, put the folder there or point LIDAR_SLAM_PCAPS at
  it (docs/design.md, "Sensor pcaps", names the source repositories and commits)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from lidar_slam.errors import InputError


def _capture(folder: Path, *parts: str) -> Path:
    path = folder.joinpath(*parts)
    if not path.is_file():  # the folder is there but not this file: a broken copy, said
        pytest.fail(f"{path} missing from the public captures folder {folder}")
    return path


@pytest.fixture
def ouster(public_captures) -> Path:
    """ouster-sdk's OS-1-128 capture: 3 frames, 30 IMU packets, its metadata beside it."""
    return _capture(public_captures, "ouster", "OS-1-128_v2.3.0_1024x10_lb_n3.pcap")


@pytest.fixture
def velodyne(public_captures) -> Path:
    """VeloView's HDL-32E capture: 18 sweeps and position packets with two NMEA fixes."""
    return _capture(public_captures, "velodyne", "monterey-first-100-packets.pcap")


def _needs(module: str) -> None:
    pytest.importorskip(module, reason=f"{module} not installed (bash tools/dev.sh test does)")


def _run(data: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(data), "--out",
                           str(out), *args], capture_output=True, text=True, timeout=300)


def _one_line_error(proc: subprocess.CompletedProcess, path: Path, text: str) -> None:
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln.lower()]
    assert len(errors) == 1 and str(path) in errors[0] and text in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr


# --- pcaps written at test time (CI) -------------------------------------------------------

SIM_SECONDS = 3.0  # 30 OS1-64 sweeps (1.0 s of IMU is needed before it is used)
IMU_LEVER_M = (0.006253, -0.011775, 0.007645)  # the IMU in the sensor frame, as an OS-1's
VLP16_SECONDS = 2.0  # 20 VLP-16 sweeps
VLP16_HOUR_S = 1_700_002_800.0  # the capture's top of the hour (UTC); sweeps start 1200 s past


@dataclass(frozen=True)
class SimPcap:
    """A pcap written from a simulation, and its truth: poses_world_lidar (n, 4, 4) at the
    scans' stamps, in the first scan's lidar frame."""

    pcap: Path
    seq: Path | None
    truth: np.ndarray
    capture: object = None  # pcap_writers.Vlp16Capture for the Velodyne one


@pytest.fixture(scope="module")
def sim_ouster(tmp_path_factory) -> SimPcap:
    """3 s of `simulate --motion handheld --world indoor --seed 0 --imu` (OS1-64, BMI088 IMU at
    200 Hz, 1.5 cm off the lidar) written by ouster-sdk as an Ouster pcap (tests/pcap_writers.py):
    30 frames of 64 lidar packets and 601 legacy IMU packets, ~25 MB, written in ~2 s."""
    _needs("ouster.sdk")
    from pcap_writers import write_ouster_pcap

    from lidar_slam.io.trajectory import read_kitti_poses
    from lidar_slam.sim.imu_gnss import ImuOptions
    from lidar_slam.sim.motions import simulate_handheld

    root = tmp_path_factory.mktemp("sim_ouster")
    T_lidar_imu = np.eye(4)
    T_lidar_imu[:3, 3] = IMU_LEVER_M
    simulate_handheld(root / "seq", "indoor", 0, SIM_SECONDS,
                      imu=ImuOptions(T_lidar_imu=T_lidar_imu))
    pcap = write_ouster_pcap(root / "seq", root / "os1.pcap",
                             imu_to_sensor_mm=tuple(1000 * v for v in IMU_LEVER_M))
    return SimPcap(pcap, root / "seq", read_kitti_poses(root / "seq" / "poses.txt"))


@pytest.fixture(scope="module")
def sim_vlp16(tmp_path_factory) -> SimPcap:
    """2 s of a handheld walk (indoor, seed 0) seen by a VLP-16 at 600 rpm, encoded packet by
    packet (tests/pcap_writers.py) into a pcap: 1507 data packets, 20 sweeps, ~1.9 MB."""
    _needs("velodyne_decoder")
    from pcap_writers import write_vlp16_pcap

    from lidar_slam.sim.handheld import build_site
    from lidar_slam.sim.motions import make_motion
    from lidar_slam.sim.sensor import get_sensor

    site = build_site("indoor", 0, get_sensor("vlp16"))
    motion = make_motion("handheld", site, 0, VLP16_SECONDS)
    root = tmp_path_factory.mktemp("sim_vlp16")
    capture = write_vlp16_pcap(root / "vlp16.pcap", site.world, motion.trajectory,
                               VLP16_SECONDS, hour_s=VLP16_HOUR_S)
    from lidar_slam.io.sources import open_source

    stamps = open_source(capture.path).stamps  # the truth at the stamps the reader gives
    T = motion.trajectory(stamps - VLP16_HOUR_S - 1200.0)
    return SimPcap(capture.path, None, np.linalg.inv(T[0]) @ T, capture)


def test_ouster_sim_pcap_run_matches_the_simulated_truth(sim_ouster, tmp_path):
    """`run` on the pcap does what it does on the simulated folder itself (ATE 0.0126 m there,
    0.0130 m here: only the mm ranges differ), IMU packets included."""
    from lidar_slam.eval.metrics import ate
    from lidar_slam.io.trajectory import read_kitti_poses

    out = tmp_path / "run"
    proc = _run(sim_ouster.pcap, out, "--no-loops")
    assert proc.returncode == 0, proc.stderr[-2000:]
    est = read_kitti_poses(out / "poses_kitti.txt")
    assert len(est) == 30
    assert ate(est, sim_ouster.truth).rmse_m < 0.02  # 0.0130 m measured
    assert ate(est, sim_ouster.truth, align=False).max_m < 0.08  # 0.050 m measured
    summary = json.loads((out / "summary.json").read_text())
    assert summary["input_kind"] == "ouster_pcap" and summary["deskew"] == "on"
    imu = summary["imu"]
    assert imu["used"] and imu["samples"] == 601 and imu["rate_hz"] == pytest.approx(200)
    assert imu["T_lidar_imu_from"] == "the input's own calibration (ouster_pcap)"
    assert imu["factors"] > 0
    assert summary["imu_frontend"]["initialisations"] == 1
    import yaml

    T = np.array(yaml.safe_load((out / "config.yaml").read_text())["imu"]["T_lidar_imu"])
    assert np.allclose(T.reshape(4, 4)[:3, 3], IMU_LEVER_M)  # mm in the metadata, m here


def test_ouster_sim_pcap_reads_back_the_simulated_points_times_and_imu(sim_ouster):
    from scipy.spatial import cKDTree

    from lidar_slam.io.sources import open_source

    seq = sim_ouster.seq
    source = open_source(sim_ouster.pcap)
    assert len(source) == 30 and not source.input_notes
    # the pcap_writers clock: 1000 s + the simulated sweep starts
    assert np.allclose(source.stamps, 1000.0 + np.loadtxt(seq / "times.txt"), atol=1e-9)
    for scan in source.scans(0, 30):
        if scan.index not in (0, 29):
            continue
        cloud = np.fromfile(seq / "velodyne" / f"{scan.index:06d}.bin", np.float32)
        cloud = cloud.reshape(-1, 4)[:, :3].astype(np.float64)
        times = np.fromfile(seq / "velodyne_times" / f"{scan.index:06d}.bin", np.float32)
        assert len(scan.points) == len(cloud)
        dist, nearest = cKDTree(cloud).query(scan.points)
        assert dist.max() < 0.5e-3 + 1e-6  # ranges in whole mm, directions exact
        assert np.abs(scan.point_times - times[nearest]).max() < 1e-6  # column stamps
    imu = source.sensor_streams.imu
    rows = np.loadtxt(seq / "imu.csv", delimiter=",", skiprows=1)
    assert len(imu) == len(rows)
    assert np.allclose(imu.stamp_s, 1000.0 + rows[:, 0], atol=1e-9)
    # the packets hold float32 g and deg/s: back in m/s^2 and rad/s to float32 precision
    assert np.allclose(imu.gyro_radps, rows[:, 1:4], rtol=1e-6, atol=1e-6)
    assert np.allclose(imu.accel_mps2, rows[:, 4:7], rtol=1e-6, atol=1e-5)


def test_a_config_mounting_wins_over_the_metadata(sim_ouster, tmp_path):
    from lidar_slam.config import load_config
    from lidar_slam.io.sources import open_source
    from lidar_slam.run.runner import _mounting_from_input

    overlay = tmp_path / "imu.yaml"
    overlay.write_text("imu:\n  T_lidar_imu: [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]\n")
    source = open_source(sim_ouster.pcap)
    given, where = _mounting_from_input(load_config(overlay), source, None)
    assert given.imu.T_lidar_imu == [0.1, 0, 0, 0, 0, 0] and where == ""
    mounted, where = _mounting_from_input(load_config(), source, None)
    assert np.allclose(mounted.imu.T_lidar_imu_matrix()[:3, 3], IMU_LEVER_M)
    assert where == "ouster_pcap"


def test_ouster_metadata_is_found_beside_or_given_or_one_line(sim_ouster, tmp_path):
    from lidar_slam.io.sources import open_source

    alone = tmp_path / "rec.pcap"
    alone.symlink_to(sim_ouster.pcap)
    with pytest.raises(InputError, match=r"rec\.pcap: no sensor metadata: expected rec\.json"):
        open_source(alone)
    assert len(open_source(alone, meta=sim_ouster.pcap.with_suffix(".json"))) == 30
    _one_line_error(_run(alone, tmp_path / "out"), alone, "no sensor metadata")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match=r"bad\.json: not Ouster sensor metadata"):
        open_source(alone, meta=bad)


def test_a_cut_pcap_is_warned_and_counted_and_a_cut_header_is_one_line(sim_ouster, tmp_path,
                                                                        caplog):
    from lidar_slam.io.sources import open_source

    data = sim_ouster.pcap.read_bytes()
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(data[:len(data) // 2])  # mid-packet, in frame 14 or 15
    shutil.copy(sim_ouster.pcap.with_suffix(".json"), cut.with_suffix(".json"))
    source = open_source(cut)
    assert 13 <= len(source) <= 15 and source.input_notes["cut_bytes_missing"] > 0
    assert any("last packet is cut" in r.getMessage() for r in caplog.records)
    head = tmp_path / "head.pcap"
    head.write_bytes(data[:10])
    shutil.copy(sim_ouster.pcap.with_suffix(".json"), head.with_suffix(".json"))
    _one_line_error(_run(head, tmp_path / "out"), head, "not a readable pcap")


def test_velodyne_sim_pcap_decodes_to_the_simulated_returns(sim_vlp16):
    """Every simulated return comes back, at its firing time, where it was simulated: within
    the packet's 2 mm distance unit and velodyne-decoder's 0.01 deg azimuths (each laser's
    azimuth interpolated between block azimuths and rounded to 0.01 deg)."""
    from lidar_slam.io.sources import open_source

    capture = sim_vlp16.capture
    source = open_source(sim_vlp16.pcap)
    # the decoder cuts whole packets: a sweep of 76 packets of 1.327 ms lasts 0.10086 s
    assert len(source) == 20 and np.allclose(np.diff(source.stamps)[:-1], 0.1, atol=1.4e-3)
    points, times = [], []
    for scan in source.scans():
        # stamped at the sweep's last packet: times back one sweep, and within that packet
        assert -0.102 < scan.point_times.min() and scan.point_times.max() < 0.0014
        points.append(scan.points)
        times.append(scan.stamp_s + scan.point_times)
    points, times = np.concatenate(points), np.concatenate(times)
    assert len(points) == len(capture.points) and np.isfinite(points).all()
    order = np.argsort(times, kind="stable")  # firing times are unique, 2.304 us apart
    points, times = points[order], times[order]
    assert np.abs(times - capture.times_s).max() < 1e-6
    r = np.linalg.norm(capture.points, axis=1)
    err = np.linalg.norm(points - capture.points, axis=1)
    assert np.all(err < 1.1e-3 + r * np.tan(np.radians(0.0102)))  # 3.5 mm max measured
    assert np.median(err) < 1e-3  # 0.6 mm measured


def test_velodyne_sim_pcap_run_writes_poses(sim_vlp16, tmp_path):
    """A VLP-16's 16 rings indoors, no IMU, a handheld walk's quick turns: the poses follow
    the truth to a few cm (0.045 m RMSE, 0.107 m max, 1.35 deg, over 0.74 m walked)."""
    from scipy.spatial.transform import Rotation

    from lidar_slam.eval.metrics import ate
    from lidar_slam.io.trajectory import read_kitti_poses

    out = tmp_path / "run"
    proc = _run(sim_vlp16.pcap, out, "--no-loops")
    assert proc.returncode == 0, proc.stderr[-2000:]
    est = read_kitti_poses(out / "poses_kitti.txt")
    assert len(est) == 20
    assert ate(est, sim_vlp16.truth, align=False).max_m < 0.2
    wrong = Rotation.from_matrix((np.linalg.inv(sim_vlp16.truth) @ est)[:, :3, :3])
    assert np.degrees(wrong.magnitude()).max() < 3.0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["input_kind"] == "velodyne_pcap" and summary["deskew"] == "on"
    assert not summary["gnss"]["used"] and "no position packets" in summary["gnss"]["reason"]


# --- Ouster: a public capture ------------------------------------------------------------


@pytest.mark.public_captures
def test_ouster_pcap_run_writes_poses_and_says_what_its_imu_did(ouster, tmp_path):
    _needs("ouster.sdk")
    out = tmp_path / "run"
    proc = _run(ouster, out, "--no-loops")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(np.loadtxt(out / "poses_kitti.txt", ndmin=2)) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["input_kind"] == "ouster_pcap" and summary["deskew"] == "on"
    imu = summary["imu"]
    # The 30 IMU packets are read and handed to the run, with the sensor's own mounting ...
    assert imu["used"] and imu["samples"] == 30 and imu["rate_hz"] == pytest.approx(100, rel=0.01)
    assert imu["T_lidar_imu_from"] == "the input's own calibration (ouster_pcap)"
    # ... but 0.3 s is too short for the IMU to be initialised: the summary says so.
    assert imu["factors"] == 0 and "need 1.0 s" in imu["reason"]
    assert summary["imu_frontend"]["initialisations"] == 0
    assert not summary["gnss"]["used"]
    # The effective config carries the metadata's imu_to_sensor_transform, mm -> m.
    import yaml

    cfg = yaml.safe_load((out / "config.yaml").read_text())
    T = np.array(cfg["imu"]["T_lidar_imu"]).reshape(4, 4)
    meta = json.loads(ouster.with_suffix(".json").read_text())
    T_meta = np.array(meta["imu_to_sensor_transform"]).reshape(4, 4)  # the legacy layout
    assert np.allclose(T[:3, :3], T_meta[:3, :3]) and np.allclose(T[:3, 3], T_meta[:3, 3] / 1000)


@pytest.mark.public_captures
def test_ouster_scans_have_column_times_from_the_sweep_start(ouster):
    _needs("ouster.sdk")
    from lidar_slam.io.sources import open_source

    source = open_source(ouster)
    assert len(source) == 3 and np.all(np.diff(source.stamps) > 0.09)
    for scan in source.scans():
        assert scan.stamp_s == source.stamps[scan.index]
        assert len(scan.points) > 100_000 and np.isfinite(scan.points).all()
        # stamp = the earliest valid column: times in [0, one 10 Hz sweep]
        assert scan.point_times.min() == 0.0 and 0.099 < scan.point_times.max() < 0.1
        assert scan.intensity is not None and len(scan.intensity) == len(scan.points)
    # a slice reads the same scans
    (second,) = list(source.scans(1, 1))
    assert second.index == 1 and second.stamp_s == source.stamps[1]


@pytest.mark.public_captures
def test_ouster_imu_units_against_the_raw_packet_bytes(ouster):
    """The legacy IMU packet holds accel in g and gyro in deg/s (Ouster's packet format: three
    u64 stamps, then six float32); ouster-sdk's accel()/gyro() scale them, the reader keeps that."""
    _needs("ouster.sdk")
    from ouster.sdk import core
    from ouster.sdk.pcap import PcapPacketSource

    from lidar_slam.io.sources import open_source

    imu = open_source(ouster).sensor_streams.imu
    info = core.SensorInfo(ouster.with_suffix(".json").read_text())
    raw = [np.asarray(p.buf).tobytes() for _, p in PcapPacketSource(str(ouster),
                                                                     sensor_info=[info])
           if isinstance(p, core.ImuPacket)]
    assert len(raw) == len(imu) == 30
    stamps = np.array([np.frombuffer(b[:24], "<u8") for b in raw])  # sys, accel, gyro ts (ns)
    values = np.array([np.frombuffer(b[24:48], "<f4") for b in raw], dtype=np.float64)
    accel_g, gyro_dps = values[:, :3], values[:, 3:]
    assert 0.9 < np.median(np.linalg.norm(accel_g, axis=1)) < 1.2  # the packets are in g
    assert np.allclose(imu.accel_mps2, accel_g * 9.80665, rtol=1e-6, atol=1e-5)
    assert np.allclose(imu.gyro_radps, np.radians(gyro_dps), rtol=1e-6, atol=1e-7)
    assert np.array_equal(np.round(imu.stamp_s * 1e9).astype(np.int64), stamps[:, 2])
    # on the lidar's clock: within the scans' span
    source = open_source(ouster)
    assert source.stamps[0] < imu.stamp_s[0] < imu.stamp_s[-1] < source.stamps[-1] + 0.2


def test_without_the_extra_the_line_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ouster.sdk", None)  # import ouster.sdk -> ImportError
    monkeypatch.setitem(sys.modules, "velodyne_decoder", None)
    from lidar_slam.io import ouster_pcap, velodyne_pcap

    with pytest.raises(InputError, match=r"x\.pcap: .*pip install 'lidar-slam\[pcap\]'"):
        ouster_pcap._sdk(tmp_path / "x.pcap")
    with pytest.raises(InputError, match=r"x\.pcap: .*pip install 'lidar-slam\[pcap\]'"):
        velodyne_pcap._vd(tmp_path / "x.pcap")


# --- Velodyne: a public capture ----------------------------------------------------------


@pytest.mark.public_captures
def test_velodyne_pcap_run_writes_poses_and_reports_its_gnss(velodyne, tmp_path):
    _needs("velodyne_decoder")
    out = tmp_path / "run"
    proc = _run(velodyne, out, "--no-loops")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(np.loadtxt(out / "poses_kitti.txt", ndmin=2)) == 18
    summary = json.loads((out / "summary.json").read_text())
    assert summary["input_kind"] == "velodyne_pcap" and summary["deskew"] == "on"
    assert not summary["imu"]["used"]
    # The capture's two NMEA fixes (22:06:32 and :33 UTC) precede its first sweep on the
    # sensor's clock (PPS not locked): left out, and said why.
    gnss = summary["gnss"]
    assert not gnss["used"] and "NMEA" in gnss["reason"] and "do not overlap" in gnss["reason"]
    assert "PPS not locked" in gnss["reason"]


@pytest.mark.public_captures
def test_velodyne_sweeps_and_nmea_fixes(velodyne):
    _needs("velodyne_decoder")
    from lidar_slam.io.sources import open_source

    source = open_source(velodyne)
    assert len(source) == 18 and np.all(np.diff(source.stamps) > 0.04)
    for scan in source.scans(0, 3):
        # stamped at the sweep's last packet: times up to one HDL-32E sweep (~0.085 s) before it
        assert -0.09 < scan.point_times.min() < -0.08 and 0 <= scan.point_times.max() < 0.001
        assert len(scan.points) > 40_000 and np.isfinite(scan.points).all()
    gnss = source.sensor_streams.gnss
    # $GPRMC,220632,A,3707.8324,N,12139.2864,W,...,111212: 37 deg 7.8324', -(121 deg 39.2864')
    assert len(gnss) == 2
    assert np.allclose(gnss.lat_deg, 37 + 7.8324 / 60) and np.allclose(gnss.lon_deg,
                                                                      -(121 + 39.2864 / 60))
    first = datetime(2012, 12, 11, 22, 6, 32, tzinfo=timezone.utc).timestamp()
    assert np.array_equal(gnss.stamp_s, [first, first + 1])
    assert np.all(gnss.sigma_v_m > 1e3)  # RMC carries no altitude


def test_a_pcap_that_is_neither_is_one_line(tmp_path):
    _needs("velodyne_decoder")
    from lidar_slam.io.sources import open_source

    junk = tmp_path / "junk.pcap"
    junk.write_bytes(b"not a pcap at all, not even its header")
    with pytest.raises(InputError, match=r"junk\.pcap: not a readable pcap"):
        open_source(junk)
