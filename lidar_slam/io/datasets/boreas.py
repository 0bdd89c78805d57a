"""Boreas (Burnett et al., IJRR 2023), a sequence folder as pyboreas documents it
(github.com/utiasASRL/pyboreas, DATA_REFERENCE.md "Data Organization", "File Formats"):

    boreas-YYYY-MM-DD-HH-MM/lidar/<stamp_us>.bin          float32 x, y, z, intensity, laser,
                                                          t per point (pyboreas utils.load_lidar)
    boreas-YYYY-MM-DD-HH-MM/applanix/lidar_poses.csv      header, then t (us), x, y, z, vx, vy,
                                                          vz, r, p, y, wz, wy, wx
    boreas-YYYY-MM-DD-HH-MM/calib/T_applanix_lidar.txt    4x4 (not needed for the lidar poses)

Stamps: the file name, microseconds since 1970 UTC, is the temporal middle of the sweep; each
point's t is seconds after that stamp (load_lidar adds the file's time to it)
(DATA_REFERENCE.md "Timestamps"), so the times are about -0.05..+0.05 s.

Ground truth: lidar_poses.csv is already the lidar's pose in ENU_ref at each scan's stamp:
T_enu_lidar = [C | (x, y, z)], C = yawPitchRollToRot(y, p, r) = roll(r) @ pitch(p) @ yaw(y) with
pyboreas's frame-rotation matrices (pyboreas/utils/utils.py: roll, pitch, yaw, yawPitchRollToRot,
get_transform). Rebuilt here with the same matrices, not a textbook Euler convention.

The Applanix imu.csv is extracted from the post-processed solution (DATA_REFERENCE.md "Applanix
Data") and imu_raw.csv is in an IMU body frame whose mounting is not given: neither is read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.datasets.common import (
    Carried,
    DatasetSource,
    load_rows,
    poses_at,
    stamped_files,
)
from lidar_slam.io.point_times import relative_seconds
from lidar_slam.io.pointcloud import CloudData

KIND = "boreas"
FIELDS = 6  # x, y, z, intensity, laser, t
MAX_ABS_POINT_TIME_S = 1.0  # a point's t about the sweep's middle: +-0.05 s at 10 Hz


def detect(path: Path) -> Path | None:
    """The sequence folder when path holds lidar/ and applanix/ (or calib/), else None."""
    if (path / "lidar").is_dir() and ((path / "applanix").is_dir() or (path / "calib").is_dir()):
        return path
    return None


def _roll(r: float) -> np.ndarray:  # pyboreas utils.roll
    c, s = np.cos(r), np.sin(r)
    return np.array([[1.0, 0, 0], [0, c, s], [0, -s, c]])


def _pitch(p: float) -> np.ndarray:  # pyboreas utils.pitch
    c, s = np.cos(p), np.sin(p)
    return np.array([[c, 0, -s], [0, 1.0, 0], [s, 0, c]])


def _yaw(y: float) -> np.ndarray:  # pyboreas utils.yaw
    c, s = np.cos(y), np.sin(y)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])


def pose_from_row(row: np.ndarray) -> np.ndarray:
    """T_enu_sensor of one <sensor>_poses.csv row (pyboreas get_transform)."""
    T = np.eye(4)
    T[:3, :3] = _roll(row[7]) @ _pitch(row[8]) @ _yaw(row[9])
    T[:3, 3] = row[1:4]
    return T


def read_lidar_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps s, T_enu_lidar (N, 4, 4)) of applanix/lidar_poses.csv."""
    rows = load_rows(path, 13, "Boreas lidar_poses.csv: t, x, y, z, vx, vy, vz, r, p, y, wz, wy, "
                               "wx", skip_header=True)
    poses = np.array([pose_from_row(r) for r in rows]).reshape(-1, 4, 4)
    return rows[:, 0] * 1e-6, poses


def read_lidar(path: Path, stamp_s: float) -> CloudData:
    """One Boreas lidar .bin (six float32 a point); times in s after the file's stamp."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc
    if size % (4 * FIELDS):
        raise InputError(path, f"{size} bytes is not a multiple of 24 (Boreas lidar: float32 x, "
                               "y, z, intensity, laser, t)")
    data = np.fromfile(path, dtype=np.float32).reshape(-1, FIELDS)
    with np.errstate(invalid="ignore"):  # a NaN time is a point without one (point_times)
        wrong = np.abs(data[:, 5]) > MAX_ABS_POINT_TIME_S
    if wrong.any():  # four float32 a point (KITTI's) whose count happens to divide by 6
        raise InputError(path, f"{int(wrong.sum())} of {len(data)} points have a time beyond "
                               f"+-{MAX_ABS_POINT_TIME_S:g} s of the stamp: not Boreas's six "
                               f"float32 a point (x, y, z, intensity, laser, t)?")
    return CloudData(data[:, :3].astype(np.float64),
                     relative_seconds(data[:, 5], round(stamp_s * 1e9)), data[:, 3].copy())


def open_sequence(root: Path) -> DatasetSource:
    """A Boreas sequence folder (see the module docstring)."""
    files, stamps = stamped_files(root / "lidar", ".bin", lambda s: int(s) * 1e-6,
                                  "Boreas lidar/<stamp_us>.bin")
    gt = None
    pose_file = root / "applanix" / "lidar_poses.csv"
    if pose_file.is_file():
        gt_stamps, T_enu_lidar = read_lidar_poses(pose_file)
        gt = poses_at(gt_stamps, T_enu_lidar, stamps)
    why = (("imu", "Boreas's imu.csv is post-processed and imu_raw.csv's mounting is not "
                   "given: not read"), ("gnss", "Boreas ships no raw GNSS fixes"))
    return DatasetSource(KIND, root.name, files, stamps, read_lidar, gt,
                         Carried(why_not=why))
