"""IMU and GNSS input (issue 22, item 1): imu.csv / gnss.csv beside the scans, sensor_msgs/Imu
and NavSatFix bag topics, the imu:/gnss: config sections, and every kind of bad sample."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from lidar_slam.config import load_config
from lidar_slam.errors import ConfigError, InputError
from lidar_slam.io.imu_gnss import read_gnss_csv, read_imu_csv
from lidar_slam.io.inertial_input import StreamsBesideScans
from lidar_slam.io.rosbag import read_gnss_topic, read_imu_topic

REPO = Path(__file__).resolve().parents[1]
IMU_HEADER = "stamp_s,wx,wy,wz,ax,ay,az\n"
GNSS_HEADER = "stamp_s,lat_deg,lon_deg,alt_m,sigma_h_m,sigma_v_m\n"
ROS2 = get_typestore(Stores.ROS2_HUMBLE)


def _imu_rows(n: int = 100, rate_hz: float = 200.0, t0: float = 0.0) -> np.ndarray:
    t = t0 + np.arange(n) / rate_hz
    return np.c_[t, 0.01 * np.ones(n), np.zeros(n), 0.5 * np.ones(n), np.zeros((n, 2)),
                 9.81 * np.ones(n)]


def _gnss_rows(n: int = 10, t0: float = 0.0) -> np.ndarray:
    t = t0 + np.arange(n, dtype=float)
    return np.c_[t, 49.0 + 1e-5 * np.arange(n), 8.4 * np.ones(n), 115.0 * np.ones(n),
                 np.ones(n), 2 * np.ones(n)]


class _Folder(StreamsBesideScans):
    """The IMU / GNSS half of a folder input (FolderSource's base) over csv files alone."""

    def __init__(self, path: Path, stamps: np.ndarray):
        self.path, self.stamps = path, stamps


def load_inertial(folder: Path, stamps: np.ndarray, **options):
    return _Folder(folder, stamps).inertial(**options)


def _write(path: Path, header: str, rows) -> Path:
    body = "".join(",".join(f"{v!r}" if isinstance(v, float) else str(v) for v in row) + "\n"
                   for row in rows)
    path.write_text(header + body)
    return path


def test_imu_csv_is_read_in_si_units_in_the_imu_frame(tmp_path):
    rows = _imu_rows()
    imu = read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows.tolist()))
    assert len(imu) == 100
    np.testing.assert_array_equal(imu.stamp_s, rows[:, 0])
    np.testing.assert_array_equal(imu.gyro_radps, rows[:, 1:4])
    np.testing.assert_array_equal(imu.accel_mps2, rows[:, 4:7])
    assert imu.dropped == {"invalid": 0, "duplicate_stamp": 0, "out_of_order": 0, "gaps": 0}


def test_non_finite_imu_samples_are_dropped_with_a_counted_warning(tmp_path, caplog):
    rows = _imu_rows().tolist()
    rows[10][4] = "nan"
    rows[20][1] = "inf"
    rows[30][0] = "nan"
    imu = read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows))
    assert len(imu) == 97 and imu.dropped["invalid"] == 3
    assert np.isfinite(imu.accel_mps2).all() and np.isfinite(imu.gyro_radps).all()
    assert "dropped 3 of 100 IMU samples (3 non-finite, 0 duplicate" in caplog.text
    assert "imu.csv" in caplog.text


def test_imu_samples_no_imu_could_read_are_dropped_as_invalid(tmp_path, caplog):
    """A spike of 1e6 m/s^2 (or rad/s) on one row took the odometry 41 km away and the final
    solve to "internal error"; beyond 1e4 in any unit it is a glitch, dropped and counted."""
    rows = _imu_rows().tolist()
    rows[40][4] = 1e6
    rows[60][2] = -1e30
    imu = read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows))
    assert len(imu) == 98 and imu.dropped["invalid"] == 2
    assert "dropped 2 of 100 IMU samples (2 beyond 10000 rad/s or 10000 m/s^2" in caplog.text
    # 16 g is a real accelerometer's range: kept in a stream that moves (a legged robot's
    # impacts: jumps of a few m/s^2 from sample to sample are common there); 300 m/s^2 alone in
    # a quiet stream is a glitch (50x the jumps 99 % of samples make, and past 150 m/s^2)
    shaken = _imu_rows()
    shaken[:, 4:7] += np.random.default_rng(0).normal(0.0, 1.5, (len(shaken), 3))
    shaken[40, 4] = 156.0
    assert len(read_imu_csv(_write(tmp_path / "imu2.csv", IMU_HEADER, shaken.tolist()))) == 100
    rows = _imu_rows().tolist()
    rows[40][4] = 300.0  # past a consumer IMU's +-16 g, alone in a quiet stream
    quiet = read_imu_csv(_write(tmp_path / "imu3.csv", IMU_HEADER, rows))
    assert len(quiet) == 99 and "1 glitches (50x further from their neighbours" in caplog.text
    rows[40][4] = 60.0  # a 6 g foot strike after standing still: kept
    assert len(read_imu_csv(_write(tmp_path / "imu4.csv", IMU_HEADER, rows))) == 100


def test_duplicated_imu_stamps_are_dropped_and_counted(tmp_path, caplog):
    rows = _imu_rows()
    rows = np.insert(rows, 50, rows[50], axis=0)  # a repeated sample
    imu = read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows.tolist()))
    assert len(imu) == 100 and imu.dropped["duplicate_stamp"] == 1
    assert (np.diff(imu.stamp_s) > 0).all()
    assert "1 duplicate stamps" in caplog.text


def test_out_of_order_imu_samples_are_dropped_and_counted(tmp_path, caplog):
    rows = _imu_rows()
    rows[[40, 41]] = rows[[41, 40]]  # two samples swapped: the second one steps back
    imu = read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows.tolist()))
    assert len(imu) == 99 and imu.dropped["out_of_order"] == 1
    assert (np.diff(imu.stamp_s) > 0).all()
    assert "1 out of order" in caplog.text


def test_missing_imu_samples_are_counted_as_gaps(tmp_path, caplog):
    rows = np.delete(_imu_rows(), np.s_[30:60], axis=0)  # 0.15 s without a sample
    imu = read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows.tolist()))
    assert imu.dropped["gaps"] == 1
    assert "1 gaps longer than 5 sample periods" in caplog.text and "0.155 s" in caplog.text


@pytest.mark.parametrize("text,needle", [
    ("", "empty file"),
    ("t,wx,wy,wz,ax,ay,az\n0,0,0,0,0,0,9.8\n", "header is 't,wx,wy,wz,ax,ay,az'"),
    (IMU_HEADER + "0,0,0,0,0,0,9.8\n0.005,0,0,x,0,0,9.8\n", "line 3: not a number ('x')"),
    (IMU_HEADER + "0,0,0,0,0,0,9.8\n0.005,0,0,0,0,9.8\n", "line 3: 6 columns, expected 7"),
    (IMU_HEADER, "0 usable IMU samples of 0"),
    (IMU_HEADER + "0,0,0,0,0,0,9.8\nnan,0,0,0,0,0,9.8\n", "1 usable IMU samples of 2"),
    (IMU_HEADER + "0,0,0,0,0,0,9.8\n0,0,0,0,0,0,9.8\n", "1 duplicate stamps"),
])
def test_an_imu_file_that_cannot_be_used_is_one_error_naming_it(tmp_path, text, needle):
    path = tmp_path / "imu.csv"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_imu_csv(path)
    message = str(err.value)
    assert message.startswith(str(path)) and needle in message and "\n" not in message, message


def test_an_imu_file_without_gravity_is_refused(tmp_path):
    rows = _imu_rows()
    rows[:, 4:7] *= 0.0
    with pytest.raises(InputError, match=re.escape("median specific force 0 m/s^2 (expected "
                                                   "about 9.81")):
        read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows.tolist()))


def test_gnss_csv_drops_invalid_fixes_and_keeps_the_rest(tmp_path, caplog):
    rows = _gnss_rows().tolist()
    rows[2][1] = 91.0  # latitude out of range
    rows[3][4] = 0.0  # a sigma that is not positive
    rows[4][3] = "nan"
    rows.insert(6, rows[6])  # a duplicate fix
    gnss = read_gnss_csv(_write(tmp_path / "gnss.csv", GNSS_HEADER, rows))
    assert len(gnss) == 7
    assert gnss.dropped == {"invalid": 3, "duplicate_stamp": 1, "out_of_order": 0}
    assert (gnss.sigma_h_m == 1).all() and (gnss.sigma_v_m == 2).all()
    np.testing.assert_allclose(gnss.lat_deg[0], 49.0)
    assert ("dropped 4 of 11 GNSS fixes (1 non-finite, 1 latitude or longitude out of range, "
            "1 sigma_h_m or sigma_v_m not positive, 1 duplicate stamps" in caplog.text)


def test_gnss_csv_whose_sigmas_are_all_zero_is_refused_naming_the_sigmas(tmp_path):
    """It said "0 usable GNSS fixes of 10 (... 10 non-finite or invalid ...)": which column?"""
    rows = _gnss_rows().tolist()
    for row in rows:
        row[4] = 0.0
    with pytest.raises(InputError, match="10 sigma_h_m or sigma_v_m not positive"):
        read_gnss_csv(_write(tmp_path / "gnss.csv", GNSS_HEADER, rows))


def test_streams_on_another_clock_than_the_scans_are_refused_unless_offset(tmp_path):
    _write(tmp_path / "imu.csv", IMU_HEADER, _imu_rows(t0=1.6e9).tolist())
    scans = np.arange(5) * 0.1
    with pytest.raises(InputError, match="do not overlap the scans' 0..0.4 s.*time_offset_s"):
        load_inertial(tmp_path, scans, imu_enabled=True, gnss_enabled=True)
    got = load_inertial(tmp_path, scans, imu_enabled=True, gnss_enabled=True,
                        imu_offset_s=-1.6e9)
    assert got.imu is not None and abs(got.imu.stamp_s[0]) < 1e-6
    assert got.summary["imu"]["time_offset_s"] == -1.6e9
    assert got.summary["gnss"] == {"used": False, "reason": "no gnss.csv beside the scans"}


def test_imu_covering_part_of_the_scans_warns(tmp_path, caplog):
    _write(tmp_path / "imu.csv", IMU_HEADER, _imu_rows(n=200).tolist())  # 0..0.995 s
    load_inertial(tmp_path, np.arange(50) * 0.1, imu_enabled=True, gnss_enabled=False)
    assert "cover only part of the scans' 0..4.9 s" in caplog.text


def test_the_summary_says_what_was_read_and_what_was_switched_off(tmp_path):
    (tmp_path / "scans").mkdir()
    rows = _imu_rows(n=401)
    rows[7][3] = np.nan
    _write(tmp_path / "scans" / "imu.csv", IMU_HEADER, rows.tolist())
    _write(tmp_path / "gnss.csv", GNSS_HEADER, _gnss_rows(3).tolist())
    got = load_inertial(tmp_path, np.arange(21) * 0.1, imu_enabled=True,
                        gnss_enabled=False)
    assert got.gnss is None
    assert got.summary["gnss"]["reason"] == "off (--no-gnss or gnss.enabled: false)"
    imu = got.summary["imu"]
    assert imu["used"] and imu["source"] == str(tmp_path / "scans" / "imu.csv")
    assert imu["samples"] == 400 and imu["rate_hz"] == pytest.approx(200, rel=0.01)
    assert imu["dropped"]["invalid"] == 1


def test_imu_and_gnss_config_sections_check_the_extrinsics():
    cfg = load_config(None, {"imu": {"T_lidar_imu": [1, 2, 3, 0, 0, 90]},
                             "gnss": {"lever_arm_m": [0, 0, 1.5], "time_offset_s": 0.2}})
    T = cfg.imu.T_lidar_imu_matrix()
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    matrix = load_config(None, {"imu": {"T_lidar_imu": T.ravel().tolist()}})
    np.testing.assert_allclose(matrix.imu.T_lidar_imu_matrix(), T)
    for bad, needle in [({"imu": {"T_lidar_imu": [1, 2]}}, "6 numbers"),
                        ({"imu": {"T_lidar_imu": [2.0] + [0.0] * 15}}, "not a rigid transform"),
                        ({"gnss": {"lever_arm_m": [1.0]}}, "3 numbers"),
                        ({"imu": {"time_offset_s": float("nan")}}, "imu.time_offset_s"),
                        ({"imu": {"T_lidar_imu": [0, 0, 0, 0, 0, 1e300]}}, "within -360..360")]:
        with pytest.raises(ConfigError, match=needle):
            load_config(None, bad)


def _header(stamp_ns: int):
    time = ROS2.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                     nanosec=stamp_ns % 10**9)
    return ROS2.types["std_msgs/msg/Header"](stamp=time, frame_id="imu")


def _imu_msg(stamp_ns: int, w: float):
    v3 = ROS2.types["geometry_msgs/msg/Vector3"]
    quat = ROS2.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    return ROS2.types["sensor_msgs/msg/Imu"](
        header=_header(stamp_ns), orientation=quat, orientation_covariance=np.zeros(9),
        angular_velocity=v3(x=0.0, y=0.0, z=w), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(x=0.0, y=0.0, z=9.81), linear_acceleration_covariance=np.zeros(9))


def _fix_msg(stamp_ns: int, status: int, cov_type: int):
    st = ROS2.types["sensor_msgs/msg/NavSatStatus"](status=status, service=1)
    return ROS2.types["sensor_msgs/msg/NavSatFix"](
        header=_header(stamp_ns), status=st, latitude=49.0, longitude=8.4, altitude=115.0,
        position_covariance=np.diag([4.0, 1.0, 9.0]).ravel(), position_covariance_type=cov_type)


def _bag(path: Path, topics: dict[str, tuple[str, list]]) -> Path:
    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, (msgtype, msgs) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=ROS2)
            for k, msg in enumerate(msgs):
                writer.write(conn, 10**9 + k, ROS2.serialize_cdr(msg, msgtype))
    return path


def test_imu_and_navsatfix_topics_are_auto_picked_and_cleaned(tmp_path, caplog):
    t0 = 1_700_000_000 * 10**9
    imu_msgs = [_imu_msg(t0 + k * 5_000_000, 0.1 * k) for k in range(20)]
    imu_msgs.insert(5, imu_msgs[5])  # a duplicated message
    fixes = [_fix_msg(t0 + k * 10**9, 0, 2) for k in range(5)]
    fixes[1] = _fix_msg(t0 + 10**9, -1, 2)  # no fix
    fixes[2] = _fix_msg(t0 + 2 * 10**9, 0, 0)  # unknown covariance
    path = _bag(tmp_path / "b", {"/imu": ("sensor_msgs/msg/Imu", imu_msgs),
                                 "/fix": ("sensor_msgs/msg/NavSatFix", fixes)})
    imu, why = read_imu_topic(path)
    assert why is None and len(imu) == 20 and imu.dropped["duplicate_stamp"] == 1
    assert imu.source == f"{path}:/imu"
    np.testing.assert_allclose(imu.gyro_radps[:, 2], 0.1 * np.arange(20))
    np.testing.assert_allclose(imu.stamp_s - imu.stamp_s[0], np.arange(20) * 0.005, atol=1e-6)
    gnss, why = read_gnss_topic(path)
    assert why is None and len(gnss) == 3
    assert gnss.dropped["no_fix"] == 1 and gnss.dropped["unknown_covariance"] == 1
    np.testing.assert_allclose(gnss.sigma_h_m, 2.0)
    np.testing.assert_allclose(gnss.sigma_v_m, 3.0)
    assert "1 fixes without a fix (status < 0) and 1 with an unknown covariance" in caplog.text


def test_bag_topics_of_imu_and_gnss_are_chosen_or_refused_by_name(tmp_path):
    t0 = 1_700_000_000 * 10**9
    msgs = [_imu_msg(t0 + k * 5_000_000, 0.0) for k in range(4)]
    path = _bag(tmp_path / "b", {"/imu_a": ("sensor_msgs/msg/Imu", msgs),
                                 "/imu_b": ("sensor_msgs/msg/Imu", msgs[:3])})
    with pytest.raises(InputError, match="2 sensor_msgs/Imu topics .*pass --imu-topic.*--no-imu"):
        read_imu_topic(path)
    assert len(read_imu_topic(path, "/imu_b")[0]) == 3
    with pytest.raises(InputError, match="no topic /nope"):
        read_imu_topic(path, "/nope")
    with pytest.raises(InputError, match="topic /imu_a is sensor_msgs/msg/Imu, not "
                                         "sensor_msgs/NavSatFix"):
        read_gnss_topic(path, "/imu_a")
    assert read_gnss_topic(path) == (None, "no sensor_msgs/NavSatFix topic in the bag")


def _sample_copy(tmp_path: Path) -> Path:
    data = tmp_path / "seq"
    shutil.copytree(REPO / "sample_scans", data)
    return data


def _run(*args):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_run_reports_the_imu_and_gnss_it_read_in_summary_json(tmp_path):
    data = _sample_copy(tmp_path)
    stamps = np.loadtxt(data / "times.txt")
    n = int((stamps[-1] - stamps[0]) * 200) + 1
    _write(data / "imu.csv", IMU_HEADER, _imu_rows(n, t0=stamps[0]).tolist())
    _write(data / "gnss.csv", GNSS_HEADER, _gnss_rows(int(stamps[-1]) + 1, stamps[0]).tolist())
    # Three scans cannot calibrate an IMU (tests/test_imu_calibration.py): the config gives it.
    given = tmp_path / "imu.yaml"
    given.write_text("imu: {T_lidar_imu: [0, 0, 0, 0, 0, 0], time_offset_s: 0.0}\n")
    proc = _run(data, "--out", tmp_path / "o", "--n-scans", "3", "--no-loops", "--config", given)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    # read (samples, rate), but three scans are too short for either end to use it: said so
    assert summary["imu"]["used"] is False and "need 1.0 s" in summary["imu"]["reason"]
    assert summary["imu"]["samples"] == n
    # no IMU factor in the final solve: the deskew's white term is in the covariances
    assert summary["covariance_deskew_white"] is not None
    assert summary["imu"]["rate_hz"] == pytest.approx(200, rel=1e-3)
    assert summary["gnss"]["source"] == str(data / "gnss.csv")
    # three scans span 3 fixes, fewer than the alignment needs: read, not used, and said why
    # (the log's "GNSS not used" and summary.json agree)
    assert not summary["gnss"]["used"] and not summary["gnss"]["geo_referenced"]
    assert "usable fixes" in summary["gnss"]["reason"] and "GNSS not used" in proc.stderr
    proc = _run(data, "--out", tmp_path / "o2", "--n-scans", "3", "--no-loops", "--no-imu",
                "--no-gnss", "--imu-topic", "/imu")
    assert proc.returncode == 0, proc.stderr
    assert "--imu-topic /imu ignored" in proc.stderr
    summary = json.loads((tmp_path / "o2" / "summary.json").read_text())
    assert summary["imu"] == {"used": False, "reason": "off (--no-imu or imu.enabled: false)"}
    assert not summary["gnss"]["used"]


def test_run_with_an_unusable_imu_file_is_one_line_and_exit_2(tmp_path):
    data = _sample_copy(tmp_path)
    (data / "imu.csv").write_text("time,gx,gy,gz,ax,ay,az\n0,0,0,0,0,0,9.8\n")
    proc = _run(data, "--out", tmp_path / "o", "--n-scans", "3", "--no-loops")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(data / "imu.csv") in lines[0] and "header" in lines[0], lines
    assert not (tmp_path / "o").exists()
    # --no-imu reads around it
    assert _run(data, "--out", tmp_path / "o", "--n-scans", "3", "--no-loops",
                "--no-imu").returncode == 0


def test_imu_warnings_name_the_file(tmp_path, caplog):
    caplog.set_level(logging.WARNING)
    rows = _imu_rows().tolist()
    rows[3][0] = rows[2][0]
    read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows))
    assert str(tmp_path / "imu.csv") in caplog.text


def _cloud(stamp_ns: int, seed: int):
    """A PointCloud2 of 3000 float32 x, y, z points on the walls of a 40 m box."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-20, 20, (3000, 3)).astype(np.float32)
    pts[np.arange(3000), rng.integers(0, 2, 3000)] = rng.choice([-20, 20], 3000)
    field = ROS2.types["sensor_msgs/msg/PointField"]
    fields = [field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    return ROS2.types["sensor_msgs/msg/PointCloud2"](
        header=_header(stamp_ns), height=1, width=3000, fields=fields, is_bigendian=False,
        point_step=12, row_step=36000, data=np.frombuffer(pts.tobytes(), np.uint8),
        is_dense=True)


def test_run_on_a_bag_names_the_imu_topic_it_read(tmp_path):
    t0 = 1_700_000_000 * 10**9
    imu = [_imu_msg(t0 + k * 5_000_000, 0.0) for k in range(80)]
    path = _bag(tmp_path / "b", {
        "/points": ("sensor_msgs/msg/PointCloud2", [_cloud(t0 + k * 10**8, 0) for k in range(3)]),
        "/imu_a": ("sensor_msgs/msg/Imu", imu), "/imu_b": ("sensor_msgs/msg/Imu", imu)})
    proc = _run(path, "--out", tmp_path / "o", "--no-loops")
    assert proc.returncode == 2 and "pass --imu-topic" in proc.stderr, proc.stderr
    proc = _run(path, "--out", tmp_path / "o", "--no-loops", "--imu-topic", "/imu_b")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["imu"]["source"] == f"{path}:/imu_b" and summary["imu"]["samples"] == 80
    assert summary["gnss"] == {"used": False, "reason": "no sensor_msgs/NavSatFix topic in the bag"}


def test_a_bag_imu_on_another_clock_is_refused_when_named_and_left_out_when_picked(tmp_path):
    """With the clock offset given (here wrong: 0), a named IMU that does not overlap the
    scans stops the run in one line, and a picked one is left out; not given, the offset is
    to be found from the data (lidar_slam.imu_calibration), which three scans cannot do:
    lidar-only, one line."""
    t0 = 1_700_000_000 * 10**9
    imu = [_imu_msg(k * 5_000_000, 0.0) for k in range(1, 80)]  # stamps from boot, not epoch
    path = _bag(tmp_path / "b", {
        "/points": ("sensor_msgs/msg/PointCloud2", [_cloud(t0 + k * 10**8, 0) for k in range(3)]),
        "/imu": ("sensor_msgs/msg/Imu", imu)})
    auto = _run(path, "--out", tmp_path / "auto", "--no-loops", "--imu-topic", "/imu")
    assert auto.returncode == 0, auto.stderr
    assert f"{path}:/imu: IMU not used: its clock offset and mounting cannot be found" \
        in auto.stderr
    zero = tmp_path / "zero.yaml"
    zero.write_text("imu: {time_offset_s: 0.0, T_lidar_imu: [0, 0, 0, 0, 0, 0]}\n")
    proc = _run(path, "--out", tmp_path / "o", "--no-loops", "--imu-topic", "/imu", "--config",
                zero)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert f"{path}:/imu: IMU stamps 0.005..0.395 s do not overlap the scans'" in line, line
    assert not (tmp_path / "o").exists()
    proc = _run(path, "--out", tmp_path / "o", "--no-loops", "--config", zero)
    assert proc.returncode == 0, proc.stderr
    assert f"{path}:/imu: not used: IMU stamps 0.005..0.395 s" in proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert not summary["imu"]["used"] and "do not overlap" in summary["imu"]["reason"]


def test_the_ouster_bags_own_imu_on_the_sensor_clock_does_not_stop_a_lidar_run(rosbags_dir,
                                                                              tmp_path):
    """The shared Ouster recording stamps its clouds with the epoch and its sensor_msgs/Imu
    with the sensor's clock (~1622 s): picked by itself, that IMU is brought over by the
    streams' starts, its mounting from the bag's /tf_static, but one cloud cannot find its clock
    offset: left out with one warning saying so."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((rosbags_dir / "ouster_os1_64_points_ros1_profile.mcap").read_bytes()[:2**21])
    proc = _run(cut, "--out", tmp_path / "o", "--no-loops")
    assert proc.returncode == 0, proc.stderr
    assert f"{cut}:/os1_cloud_node/imu: IMU not used: its clock offset cannot be found from " \
        "the data: 1 scans registered" in proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["imu"]["used"] is False and summary["frames"] == 1


def test_the_terminal_summary_shows_the_fixes_used_rejected_and_unused_and_units_read():
    """A run's table said gnss used=True and nothing of the fixes it left out (multipath jumps,
    fixes outside the scans): their counts are shown, as is a unit converted on reading."""
    from lidar_slam.cli.common import summary_table

    table = summary_table({"gnss": {"used": True, "source": "gnss.csv", "fixes_used": 40,
                                    "fixes_rejected": 2, "fixes_unused": 5, "dropped": {}},
                           "imu": {"used": True, "read_as": {"stamps": "ns"}, "samples": 10}})
    assert "fixes_used=40, fixes_rejected=2, fixes_unused=5" in table
    assert "read_as={'stamps': 'ns'}" in table


def _tf(parent: str, child: str, xyz, quat):
    v3 = ROS2.types["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2])
    q = ROS2.types["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3])
    header = dataclasses.replace(_header(0), frame_id=parent)
    return ROS2.types["geometry_msgs/msg/TransformStamped"](
        header=header, child_frame_id=child,
        transform=ROS2.types["geometry_msgs/msg/Transform"](translation=v3, rotation=q))


@pytest.mark.parametrize("imu_tfs,expect", [
    ([("base", "imu", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))], "ok"),
    ([("base", "imu", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 0.0))], "is not a rigid transform"),
    ([("base", "imu", (np.nan, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))], "is not a rigid transform"),
    ([("base", "imu", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
      ("base", "imu", (0.0, 5.0, 0.0), (0.0, 0.0, 0.0, 1.0))], "two different transforms")])
def test_a_bags_tf_static_gives_the_mounting_or_says_what_it_left_out(tmp_path, caplog,
                                                                      imu_tfs, expect):
    """A zero or NaN quaternion in /tf_static ran into "internal error" (a NaN mounting); a
    frame given two transforms took the last one silently (a review): both left out, said."""
    from lidar_slam.io.rosbag.tf import imu_mounting

    t0 = 1_700_000_000 * 10**9
    cloud = _cloud(t0, 0)
    cloud = dataclasses.replace(cloud, header=dataclasses.replace(cloud.header, frame_id="lidar"))
    lidar_tf = _tf("base", "lidar", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0))  # turned 180 about z
    msgs = [ROS2.types["tf2_msgs/msg/TFMessage"](transforms=[lidar_tf, *[_tf(*a) for a in t]])
            for t in [imu_tfs[:1], imu_tfs[1:]] if t]
    path = _bag(tmp_path / "b", {"/points": ("sensor_msgs/msg/PointCloud2", [cloud]),
                                 "/imu": ("sensor_msgs/msg/Imu", [_imu_msg(t0, 0.0)]),
                                 "/tf_static": ("tf2_msgs/msg/TFMessage", msgs)})
    T, why = imu_mounting(path, "/points", None)
    if expect == "ok":
        assert why == "/tf_static imu -> lidar"
        np.testing.assert_allclose(T[:3, 3], [1.0, -1.0, 0.0], atol=1e-12)  # Rz(180) (-1, 1, 0)
        np.testing.assert_allclose(T[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    else:
        assert T is None and expect in why and "left out" in why
        assert "mounting is not taken from /tf_static" in caplog.text


@pytest.mark.parametrize("scale,every_s,scans_s,unit", [(1e3, 1.0, 20.0, "ms"),
                                                         (1e3, 0.1, 20.0, "ms"),
                                                         (1.0, 60.0, 600.0, None),
                                                         (1.0, 1.0, 20.0, None)])
def test_gnss_stamps_counted_from_zero_in_ms_are_told_by_the_scans_clock(tmp_path, caplog,
                                                                         scale, every_s,
                                                                         scans_s, unit):
    """In ms from 0 at 1 Hz they look like a fix every 1000 s, which size and spacing cannot
    tell from a sparse receiver in s: the GNSS was dropped ("1 usable fixes"). Read so that
    the most fixes fall within the scans' span; a fix a minute in s stays s."""
    n = int(scans_s / every_s) + 1
    rows = _gnss_rows(n)
    rows[:, 0] = np.round(np.arange(n) * every_s * scale, 6)
    _write(tmp_path / "gnss.csv", GNSS_HEADER, rows.tolist())
    got = load_inertial(tmp_path, np.arange(int(scans_s * 10) + 1) * 0.1, imu_enabled=False,
                        gnss_enabled=True)
    np.testing.assert_allclose(got.gnss.stamp_s, np.arange(n) * every_s, atol=1e-9)
    if unit is None:
        assert "read_as" not in got.summary["gnss"] and "stamps read as" not in caplog.text
    else:
        assert got.summary["gnss"]["read_as"] == {"stamps": unit}
        assert caplog.text.count("stamps read as ms") == 1


def test_empty_csv_fields_are_missing_values_dropped_as_nan_is(tmp_path, caplog):
    """An empty field stopped the run ("not a number ('')") where nan was dropped."""
    rows = [",".join(str(v) for v in r) for r in _gnss_rows(10)]
    rows[3] = "3.0,,,,1,2"
    (tmp_path / "gnss.csv").write_text(GNSS_HEADER + "\n".join(rows) + "\n")
    assert len(read_gnss_csv(tmp_path / "gnss.csv")) == 9
    assert "dropped 1 of 10 GNSS fixes (1 non-finite" in caplog.text
    bad = rows[:]
    bad[5] = "5.0,north,8.4,115,1,2"  # a word is still named, not an empty field before it
    (tmp_path / "g2.csv").write_text(GNSS_HEADER + "\n".join(bad) + "\n")
    with pytest.raises(InputError, match=r"line 7: not a number \('north'\)"):
        read_gnss_csv(tmp_path / "g2.csv")


def test_swapped_rate_and_acceleration_columns_are_named(tmp_path):
    rows = _imu_rows()
    rows[:, 1:7] = rows[:, [4, 5, 6, 1, 2, 3]]
    with pytest.raises(InputError, match="wx,wy,wz and ax,ay,az swapped"):
        read_imu_csv(_write(tmp_path / "imu.csv", IMU_HEADER, rows.tolist()))


def test_gnss_in_epoch_seconds_with_scans_from_zero_is_another_clock(tmp_path):
    """They were taken for ns counted from 0 (1.76 s): refused as another clock instead."""
    rows = _gnss_rows(10, t0=1_764_950_400.0)
    _write(tmp_path / "gnss.csv", GNSS_HEADER, rows.tolist())
    with pytest.raises(InputError, match="do not overlap the scans"):
        load_inertial(tmp_path, np.arange(100) * 0.1, imu_enabled=False, gnss_enabled=True)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 300), cols=st.integers(0, 3), half=st.integers(0, 40),
       quantile=st.floats(0.0, 0.999), seed=st.integers(0, 2**31 - 1),
       ties=st.booleans())
def test_running_rank_equals_scipys_rank_filter(n, cols, half, quantile, seed, ties):
    """The glitch filter's running median and percentile (NumPy, to spare every IMU run
    scipy.ndimage's ~0.2 s import) are scipy.ndimage's, ends, ties and windows wider than the
    data included, across block boundaries too."""
    from scipy.ndimage import rank_filter

    from lidar_slam.io import imu_gnss

    rng = np.random.default_rng(seed)
    shape = (n,) if cols == 0 else (n, cols)
    x = rng.normal(size=shape)
    if ties:
        x = np.round(x)
    size = 2 * half + 1
    rank = int(size * quantile)
    footprint = (size,) if cols == 0 else (size, 1)
    want = rank_filter(x, rank, size=footprint, mode="nearest")
    got = imu_gnss.running_rank(x, size, rank)
    assert np.array_equal(got, want)
    at = np.flatnonzero(rng.random(n) < 0.3)  # some rows only, in order
    assert np.array_equal(imu_gnss.running_rank(x, size, rank, at=at), want[at])
    old, imu_gnss.RANK_BLOCK = imu_gnss.RANK_BLOCK, 7  # several blocks
    try:
        assert np.array_equal(imu_gnss.running_rank(x, size, rank), want)
    finally:
        imu_gnss.RANK_BLOCK = old
