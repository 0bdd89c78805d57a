"""Trajectory files: KITTI (12 numbers per line), TUM (stamp tx ty tz qx qy qz qw), KITTI calib."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.geometry import matrix_from_quat, quat_from_matrix
from lidar_slam.io.atomic import atomic_path


def _loadtxt(path: Path, **kwargs) -> np.ndarray:
    """np.loadtxt without its "input contained no data" warning: an empty file is reported as one
    error line by the caller, not a warning plus an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(path, **kwargs)


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """(K, 4, 4) poses from a KITTI pose file (row-major 3x4 per line)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "pose file does not exist")
    try:
        data = _loadtxt(p, ndmin=2)
    except ValueError as exc:
        raise InputError(p, f"not a KITTI pose file ({exc})") from exc
    if data.size == 0:
        raise InputError(p, "pose file is empty")
    if data.shape[1] != 12:
        raise InputError(p, f"expected 12 numbers per line, found {data.shape[1]}")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :4] = data.reshape(-1, 3, 4)
    return poses


def write_kitti_poses(path: str | Path, poses: np.ndarray) -> None:
    """Write (K, 4, 4) poses in KITTI format (atomically)."""
    rows = np.asarray(poses)[:, :3, :4].reshape(-1, 12)
    with atomic_path(path) as tmp:
        np.savetxt(tmp, rows, fmt="%.9e")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (K,), poses (K, 4, 4)) from a TUM file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "pose file does not exist")
    try:
        data = _loadtxt(p, ndmin=2, comments="#")
    except ValueError as exc:
        raise InputError(p, f"not a TUM pose file ({exc})") from exc
    if data.size == 0 or data.shape[1] != 8:
        raise InputError(p, "expected 8 numbers per line (stamp tx ty tz qx qy qz qw)")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = matrix_from_quat(data[:, 4:8])
    poses[:, :3, 3] = data[:, 1:4]
    return data[:, 0], poses


def write_tum(path: str | Path, stamps_s: np.ndarray, poses: np.ndarray) -> None:
    """Write poses with stamps in TUM format (atomically)."""
    poses = np.asarray(poses)
    q = quat_from_matrix(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    data = np.c_[np.asarray(stamps_s, float), poses[:, :3, 3], q]
    with atomic_path(path) as tmp:
        np.savetxt(tmp, data, fmt="%.9f")


def read_kitti_calib_tr(path: str | Path) -> np.ndarray:
    """Tr (velodyne -> cam0) as 4x4 from a KITTI calib.txt."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "calib file does not exist")
    for line in p.read_text().splitlines():
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            try:
                nums = np.array(values.split(), dtype=float)
            except ValueError:
                raise InputError(p, f"Tr: not 12 numbers ({values.strip()[:60]})") from None
            if nums.size != 12:
                raise InputError(p, "Tr must have 12 numbers")
            T = np.eye(4)
            T[:3, :4] = nums.reshape(3, 4)
            return T
    raise InputError(p, "no 'Tr:' line (velodyne -> cam0 calibration)")


def camera_to_lidar_poses(poses_cam: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """KITTI cam0 ground truth to lidar frame: T_world_lidar(i) = inv(Tr) @ P_i @ Tr."""
    return np.linalg.inv(Tr) @ poses_cam @ Tr


def read_times(path: str | Path) -> np.ndarray:
    """One stamp (s) per line."""
    p = Path(path)
    try:
        return np.atleast_1d(_loadtxt(p, ndmin=1))
    except (ValueError, OSError) as exc:
        raise InputError(p, f"unreadable times file ({exc})") from exc
