"""Trajectory files: KITTI (12 numbers per line), TUM (stamp tx ty tz qx qy qz qw), KITTI calib."""

from __future__ import annotations

import re
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


def _numpy_reason(exc: ValueError) -> str:
    """np.loadtxt's error without its advice to the programmer ("use `usecols` ..."), rows
    counted from 1 as lines are."""
    text = str(exc).split(";")[0].strip()
    m = re.search(r"columns changed from (\d+) to (\d+) at row (\d+)", text)
    if m:  # (this row is counted from 1)
        return f"line {m.group(3)} has {m.group(2)} numbers, the lines before {m.group(1)}"
    m = re.search(r"could not convert string (.*) to float64 at row (\d+), column (\d+)", text)
    if m:  # (this row from 0)
        return f"line {int(m.group(2)) + 1}, value {m.group(3)}: {m.group(1)} is not a number"
    return text


RIGID_TOL = 1e-3  # |R R^T - I| or |q| - 1: files write 6-9 digits; KITTI's are rigid to 1e-7


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """(K, 4, 4) poses from a KITTI pose file (row-major 3x4 per line)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "pose file does not exist")
    try:
        data = _loadtxt(p, ndmin=2)
    except ValueError as exc:
        raise InputError(p, f"not a KITTI pose file ({_numpy_reason(exc)})") from None
    if data.size == 0:
        raise InputError(p, "pose file is empty")
    if data.shape[1] != 12:
        raise InputError(p, f"expected 12 numbers per line, found {data.shape[1]}")
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if len(bad):
        raise InputError(p, f"pose {bad[0] + 1}: NaN or infinite values")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :4] = data.reshape(-1, 3, 4)
    R = poses[:, :3, :3]
    off = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((off > RIGID_TOL) | (np.linalg.det(R) < 0))
    if len(bad):
        raise InputError(p, f"pose {bad[0] + 1}: not a rigid motion (its 3x3 rotation is not "
                            f"orthonormal with determinant +1)")
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
        raise InputError(p, f"not a TUM pose file ({_numpy_reason(exc)})") from None
    if data.size == 0 or data.shape[1] != 8:
        raise InputError(p, "expected 8 numbers per line (stamp tx ty tz qx qy qz qw)")
    norm = np.linalg.norm(data[:, 4:8], axis=1)
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1) | (np.abs(norm - 1) > RIGID_TOL))
    if len(bad):
        raise InputError(p, f"pose {bad[0] + 1}: NaN or infinite values, or a quaternion whose "
                            f"norm is not 1 ({norm[bad[0]]:.6g})")
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
    """Tr (velodyne -> cam0) as 4x4 from a KITTI calib.txt; a rigid transform (its rotation
    orthonormal to 1e-3: KITTI's are to 1e-7), else the ground truth would be bent silently."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "calib file does not exist")
    for n, line in enumerate(text_lines(p, "calib file"), 1):
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            try:
                nums = np.array(values.split(), dtype=float)
            except ValueError:
                raise InputError(p, f"line {n}: Tr: not 12 numbers "
                                    f"({values.strip()[:60]!r})") from None
            if nums.size != 12:
                raise InputError(p, f"line {n}: Tr must have 12 numbers, found {nums.size}")
            T = np.eye(4)
            T[:3, :4] = nums.reshape(3, 4)
            R = T[:3, :3]
            if not np.isfinite(nums).all():
                raise InputError(p, f"line {n}: Tr has NaN or infinite values")
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
                raise InputError(p, f"line {n}: Tr is not a rigid transform (its 3x3 rotation "
                                    "is not orthonormal with determinant +1)")
            return T
    raise InputError(p, "no 'Tr:' line (velodyne -> cam0 calibration)")


def camera_to_lidar_poses(poses_cam: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """KITTI cam0 ground truth to lidar frame: T_world_lidar(i) = inv(Tr) @ P_i @ Tr."""
    return np.linalg.inv(Tr) @ poses_cam @ Tr


def read_times(path: str | Path) -> np.ndarray:
    """One stamp (s) per line (blank lines and '#' comments skipped), strictly increasing and
    finite: a stamp out of order is refused with its line number (taken silently, a stamp that
    goes back or repeats doubled the ATE of the sample drive)."""
    p = Path(path)
    stamps: list[float] = []
    prev_line = 0
    for n, line in enumerate(text_lines(p, "times file"), 1):
        fields = line.partition("#")[0].split()
        if not fields:
            continue
        if len(fields) != 1:
            raise InputError(p, f"line {n}: expected one stamp per line, found {len(fields)} "
                                f"columns")
        try:
            stamp = float(fields[0])
        except ValueError:
            raise InputError(p, f"line {n}: not a number ({fields[0][:40]!r})") from None
        check_stamp(p, n, stamp, prev_line, stamps[-1] if stamps else None)
        stamps.append(stamp)
        prev_line = n
    return np.array(stamps, dtype=np.float64)


def check_stamp(path: Path, line: int, stamp_s: float, prev_line: int,
                prev_s: float | None) -> None:
    """Refuse a scan stamp (s) that is not finite or not after the previous one (line numbers
    1-based)."""
    if not np.isfinite(stamp_s):
        raise InputError(path, f"line {line}: stamp {stamp_s} is not a finite number")
    if prev_s is not None and not stamp_s > prev_s:
        now, before = f"{stamp_s:.6f}", f"{prev_s:.6f}"
        if now == before and stamp_s != prev_s:  # apart by less than a microsecond
            now, before = repr(stamp_s), repr(prev_s)
        raise InputError(path, f"line {line}: stamp {now} s is not after line {prev_line}'s "
                               f"{before} s (stamps must increase)")


def text_lines(p: Path, what: str) -> list[str]:
    """The lines of a text file; a missing, unreadable or non-UTF-8 file is one InputError."""
    try:
        return p.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(p, f"{what} does not exist") from None
    except UnicodeDecodeError as exc:
        raise InputError(p, f"not a text file (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise InputError(p, f"cannot read {what} ({exc.strerror or exc})") from None


def read_kitti_raw_timestamps(path: Path) -> np.ndarray:
    """KITTI raw timestamps.txt ('2011-09-26 13:02:25.964389445' per line) -> seconds since the
    UNIX epoch, the clock taken as UTC (the fraction is kept to the nanosecond); they must
    increase strictly."""
    from datetime import datetime, timezone

    stamps: list[float] = []
    prev_line = 0
    for n, line in enumerate(text_lines(path, "timestamps file"), 1):
        if not line.strip():
            continue
        whole, _, frac = line.strip().partition(".")
        try:
            if frac and not frac.isdigit():
                raise ValueError(frac)
            t = datetime.strptime(whole, "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc)
            stamp = t.timestamp() + (float("0." + frac) if frac else 0.0)
        except ValueError:
            raise InputError(path, f"line {n}: not a 'YYYY-MM-DD HH:MM:SS.fraction' stamp "
                                   f"({line.strip()[:40]!r})") from None
        check_stamp(path, n, stamp, prev_line, stamps[-1] if stamps else None)
        stamps.append(stamp)
        prev_line = n
    return np.array(stamps, dtype=np.float64)
