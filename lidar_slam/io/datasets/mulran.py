"""MulRan (Kim et al., ICRA 2020): the Ouster OS1-64 scans, global_pose.csv, and the consumer
IMU and GPS, in the layout the official file player reads (github.com/irapkaist/
file_player_mulran, src/ROSThread.cpp):

    SEQ/global_pose.csv                    stamp_ns, 12 numbers: row-major 3x4 T_world_base
    SEQ/sensor_data/Ouster/<stamp_ns>.bin  float32 x, y, z, intensity per point (ROSThread.cpp
                                           OusterThread: 4 floats a point, ring = k % 64)
    SEQ/sensor_data/xsens_imu.csv          stamp_ns, q xyzw, euler xyz, gyro xyz (rad/s),
                                           accel xyz (m/s^2), mag xyz (ROSThread.cpp, 17 values)
    SEQ/sensor_data/gps.csv                stamp_ns, lat, lon, alt, 9 covariance values (m^2)

(kiss-icp's loader also takes SEQ/Ouster/*.bin; both are accepted.)

Ground truth: global_pose.csv is the vehicle base frame; T_world_lidar = T_world_base @
T_base_lidar, T_base_lidar = (1.7042, -0.021, 1.8047) m, roll-pitch-yaw (0.0001, 0.0003,
179.6654) deg, R = Rz Ry Rx: calib_base2ouster.txt as quoted in kiss-icp
(kiss_icp/datasets/mulran.py, _get_calibration). kiss-icp applies it as T @ P @ inv(T); the
pose of the lidar is P @ T (the two differ by the sign of the 1.8 m lever arm's z).

Per-point times: the files have none; a full 64 x 1024 scan (65,536 points, column by column,
as the player's ring = k % 64 says) gets column / 1024 of the sweep (the median stamp spacing),
as kiss-icp's loader does, i.e. stamps taken as the sweep's start. Other point counts: none.

IMU / GPS: read (the GPS's 1-sigma from its covariance diagonal), but MulRan publishes no IMU
or antenna mounting (the numbers some tools use are the Complex Urban dataset's): the IMU is
used only with imu.T_lidar_imu given in the config, the GPS with gnss.lever_arm_m (default 0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.datasets.common import (
    Carried,
    DatasetSource,
    check_scan_period,
    load_rows,
    poses_at,
    rigid,
    rpy_zyx,
)
from lidar_slam.io.imu_gnss import gnss_from_rows, imu_from_rows
from lidar_slam.io.pointcloud import CloudData, read_bin

KIND = "mulran"
OUSTER_H, OUSTER_W = 64, 1024
T_BASE_LIDAR = rigid(rpy_zyx(*np.radians([0.0001, 0.0003, 179.6654])), [1.7042, -0.021, 1.8047])


def detect(path: Path) -> Path | None:
    """The sequence folder when path is one, or its sensor_data/, else None. kiss-icp's bare
    Ouster/ folder counts only beside global_pose.csv (a folder named Ouster alone says little)."""
    root = path.parent if path.name == "sensor_data" else path
    if (root / "sensor_data" / "Ouster").is_dir():
        return root
    if (root / "Ouster").is_dir() and (root / "global_pose.csv").is_file():
        return root
    return None


def _ouster_dir(root: Path) -> Path:
    nested = root / "sensor_data" / "Ouster"
    return nested if nested.is_dir() else root / "Ouster"


def base_to_lidar(T_world_base: np.ndarray) -> np.ndarray:
    """MulRan ground truth (T_world_base) to T_world_lidar."""
    return T_world_base @ T_BASE_LIDAR


def read_global_pose(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps s, T_world_base (N, 4, 4)) of global_pose.csv."""
    rows = load_rows(path, 13, "MulRan global_pose.csv: stamp_ns + 12 numbers")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows[:, 1:13].reshape(-1, 3, 4)
    return rows[:, 0] * 1e-9, poses


def _read(path: Path, sweep_s: float) -> CloudData:
    cloud = read_bin(path)
    if len(cloud.points) != OUSTER_H * OUSTER_W:
        return cloud
    column = np.arange(OUSTER_H * OUSTER_W) // OUSTER_H
    return CloudData(cloud.points, column * (sweep_s / OUSTER_W), cloud.intensity)


def _carried(root: Path) -> Carried:
    data = root / "sensor_data"
    why = []
    imu = gnss = None
    imu_file, gps_file = data / "xsens_imu.csv", data / "gps.csv"
    if imu_file.is_file():
        rows = load_rows(imu_file, 17, "MulRan xsens_imu.csv: 17 columns")
        imu = imu_from_rows(imu_file, np.c_[rows[:, 0] * 1e-9, rows[:, 8:11], rows[:, 11:14]])
        why.append(("imu", f"{imu_file}: MulRan publishes no IMU-to-lidar mounting; set "
                           "imu.T_lidar_imu to use it"))
    else:
        why.append(("imu", f"no {imu_file}"))
    if gps_file.is_file():
        rows = load_rows(gps_file, 13, "MulRan gps.csv: stamp_ns, lat, lon, alt, 9 covariances")
        with np.errstate(invalid="ignore"):
            sig_h = np.sqrt(np.maximum(rows[:, 4], rows[:, 8]))
            sig_v = np.sqrt(rows[:, 12])
        gnss = gnss_from_rows(gps_file, np.c_[rows[:, 0] * 1e-9, rows[:, 1:4], sig_h, sig_v])
    else:
        why.append(("gnss", f"no {gps_file}"))
    return Carried(imu=imu, gnss=gnss, T_lidar_imu=None, why_not=tuple(why))


def open_sequence(root: Path) -> DatasetSource:
    """A MulRan sequence folder (see the module docstring)."""
    folder = _ouster_dir(root)
    files = sorted((p for p in folder.glob("*.bin")), key=lambda p: p.stem)
    if not files:
        raise InputError(folder, "no .bin scans found (MulRan Ouster/<stamp_ns>.bin)")
    try:
        ns = np.array([int(p.stem) for p in files], dtype=np.int64)
    except ValueError:
        raise InputError(folder, "a scan file name is not a stamp in ns (MulRan "
                                 "Ouster/<stamp_ns>.bin)") from None
    order = np.argsort(ns)
    files, stamps = [files[i] for i in order], ns[order] * 1e-9
    check_scan_period(folder, stamps, "MulRan Ouster/<stamp_ns>.bin")
    sweep_s = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.1
    gt = None
    pose_file = root / "global_pose.csv"
    if pose_file.is_file():
        gt_stamps, T_world_base = read_global_pose(pose_file)
        gt = poses_at(gt_stamps, base_to_lidar(T_world_base), stamps)
    return DatasetSource(KIND, root.name, files, stamps, lambda p, _s: _read(p, sweep_s), gt,
                         _carried(root))
