"""Newer College 2020 (Ramezani et al., IROS 2020; OS1-64 + its IMU), a sequence folder as the
dataset's raw_format download unpacks it:

    SEQ/raw_format/ouster_scan/cloud_<sec>_<nsec>.pcd   Ouster clouds with fields x y z intensity
                                                       t (uint32 ns after the stamp) reflectivity
                                                       ring noise range
    SEQ/raw_format/ouster_imu/data.csv                 one header line, then counter, sec, nsec,
                                                       gyro xyz (rad/s), accel xyz (m/s^2)
    SEQ/ground_truth/registered_poses.csv              '#sec,nsec,x,y,z,qx,qy,qz,qw': T_world_base

(ouster_zip_files/ouster_scan/ under raw_format is accepted too.) File names and the csv column
orders are those kiss-icp (kiss_icp/datasets/ncd.py) and steam_icp
(steam_icp/src/datasets/newer_college.cpp: NCPoint, the ouster_imu/data.csv loop, loadGTPoses)
read.

Frames (steam_icp newer_college.cpp, NewerCollegeSequence constructor): T_base_imu = Rz(-45 deg),
t = (-0.0882, -0.0377, 0.0217) m; T_imu_lidar = Rz(180 deg), t = (-0.006253, 0.011775,
0.028535) m, the OS1's own imu_to_sensor (6.253, -11.775, 7.645) mm and lidar_to_sensor (Rz(180
deg), z 36.18 mm) combined. Their product T_base_lidar = Rz(135 deg), t = (-0.084, -0.025,
0.050) m is kiss-icp's T_CL (ncd.py load_gt_poses). T_world_lidar = T_world_base @
T_base_lidar; the IMU's mounting T_lidar_imu = inv(T_imu_lidar).

Per-point times: the t field (ns after the scan stamp, the file name), converted by
lidar_slam.io.point_times like every other reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.geometry import inverse, matrix_from_quat
from lidar_slam.io.datasets.common import (
    Carried,
    DatasetSource,
    load_rows,
    poses_at,
    rigid,
    rot_z,
    stamped_files,
)
from lidar_slam.io.imu_gnss import imu_from_rows
from lidar_slam.io.pointcloud import read_cloud

KIND = "newer_college"
T_BASE_IMU = rigid(rot_z(np.radians(-45.0)), [-0.08815464364571213, -0.03774772105123108,
                                               0.021653])
T_IMU_LIDAR = rigid(rot_z(np.pi), [-0.006253, 0.011775, 0.028535])
T_BASE_LIDAR = T_BASE_IMU @ T_IMU_LIDAR
T_LIDAR_IMU = inverse(T_IMU_LIDAR)


def _scan_dir(root: Path) -> Path | None:
    for cand in (root / "raw_format" / "ouster_scan",
                 root / "raw_format" / "ouster_zip_files" / "ouster_scan"):
        if cand.is_dir():
            return cand
    return None


def detect(path: Path) -> Path | None:
    """The sequence folder when path holds raw_format/.../ouster_scan/, else None."""
    return path if _scan_dir(path) is not None else None


def cloud_stamp_s(stem: str) -> float:
    """cloud_<sec>_<nsec> -> seconds."""
    kind, sec, nsec = stem.split("_")
    if kind != "cloud" or not sec.isdigit() or not nsec.isdigit():
        raise ValueError(f"{stem!r} is not cloud_<sec>_<nsec>")
    return int(sec) + int(nsec) * 1e-9


def base_to_lidar(T_world_base: np.ndarray) -> np.ndarray:
    """Newer College ground truth (T_world_base) to T_world_lidar."""
    return T_world_base @ T_BASE_LIDAR


def read_registered_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps s, T_world_base (N, 4, 4)) of registered_poses.csv."""
    rows = load_rows(path, 9, "Newer College registered_poses.csv: sec,nsec,x,y,z,qx,qy,qz,qw")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = matrix_from_quat(rows[:, 5:9]) if len(rows) else np.zeros((0, 3, 3))
    poses[:, :3, 3] = rows[:, 2:5]
    return rows[:, 0] + rows[:, 1] * 1e-9, poses


def _carried(root: Path) -> Carried:
    imu_file = root / "raw_format" / "ouster_imu" / "data.csv"
    if not imu_file.is_file():
        return Carried(why_not=(("imu", f"no {imu_file}"), ("gnss", "Newer College has none")))
    r = load_rows(imu_file, 9, "Newer College ouster_imu/data.csv: counter, sec, nsec, gyro "
                               "xyz, accel xyz", skip_header=True)
    imu = imu_from_rows(imu_file, np.c_[r[:, 1] + r[:, 2] * 1e-9, r[:, 3:6], r[:, 6:9]])
    return Carried(imu=imu, T_lidar_imu=T_LIDAR_IMU, why_not=(("gnss", "Newer College has none"),))


def open_sequence(root: Path) -> DatasetSource:
    """A Newer College 2020 sequence folder (see the module docstring)."""
    folder = _scan_dir(root)
    if folder is None:
        raise InputError(root / "raw_format" / "ouster_scan", "missing (Newer College scans)")
    files, stamps = stamped_files(folder, ".pcd", cloud_stamp_s,
                                  "Newer College cloud_<sec>_<nsec>.pcd")
    gt = None
    gt_file = root / "ground_truth" / "registered_poses.csv"
    if gt_file.is_file():
        gt_stamps, T_world_base = read_registered_poses(gt_file)
        gt = poses_at(gt_stamps, base_to_lidar(T_world_base), stamps)
    return DatasetSource(KIND, root.name, files, stamps,
                         lambda p, s: read_cloud(p, round(s * 1e9)), gt, _carried(root))
