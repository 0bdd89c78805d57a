"""KITTI-360 (Liao et al., TPAMI 2022), one drive as the dataset unpacks it (the devkit
github.com/autonomousvision/kitti360Scripts reads the same paths):

    ROOT/data_3d_raw/DRIVE/velodyne_points/data/<frame:010d>.bin   float32 x, y, z, reflectance
    ROOT/data_3d_raw/DRIVE/velodyne_points/timestamps.txt          date-times, as KITTI raw
    ROOT/data_poses/DRIVE/poses.txt                                frame + 12 numbers: row-major
                                                                   3x4 T_world_pose (IMU/GPS)
    ROOT/calibration/calib_cam_to_pose.txt                         'image_00: ' + 12: T_pose_cam0
    ROOT/calibration/calib_cam_to_velo.txt                         12 numbers: T_velo_cam0

DRIVE is e.g. 2013_05_28_drive_0000_sync; point this reader at ROOT/data_3d_raw/DRIVE (or its
velodyne_points/). poses.txt holds only some frames (the devkit keys them by frame,
viewer/kitti360Viewer3DRaw.py loadPoses); the others get a pose interpolated in time between
their neighbours with poses, and none outside them.

Ground truth: T_world_velo = T_world_pose @ T_pose_velo with T_pose_velo = T_pose_cam0 @
inv(T_velo_cam0), the devkit's TrVeloToPose (viewer/kitti360Viewer3DRaw.py loadExtrinsics:
"TrCamToPose['image_00'] @ np.linalg.inv(TrCam0ToVelo)"; devkits/accumuLaser/src/
accumulation.cpp: "Tr_velo_pose = Tr_cam_pose[0] * Tr_cam_velo.inverse()").

No per-point times (the files have none), no IMU or GNSS read (the OXTS data are not).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.datasets.common import Carried, DatasetSource, load_rows, poses_at, require
from lidar_slam.io.pointcloud import read_bin
from lidar_slam.io.trajectory import read_kitti_raw_timestamps, text_lines

KIND = "kitti360"


def detect(path: Path) -> Path | None:
    """The drive's data_3d_raw folder when path is it or its velodyne_points/, else None."""
    drive = path.parent if path.name == "velodyne_points" else path
    if drive.parent.name == "data_3d_raw" and (drive / "velodyne_points" / "data").is_dir():
        return drive
    return None


def _rigid_rows(path: Path, values: list[str], what: str) -> np.ndarray:
    try:
        nums = np.array(values, dtype=np.float64)
    except ValueError:
        raise InputError(path, f"{what}: not 12 numbers") from None
    if nums.size != 12 or not np.isfinite(nums).all():
        raise InputError(path, f"{what}: expected 12 finite numbers, found {nums.size}")
    T = np.eye(4)
    T[:3, :4] = nums.reshape(3, 4)
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise InputError(path, f"{what}: not a rigid transform")
    return T


def read_cam_to_pose(path: Path) -> np.ndarray:
    """T_pose_cam0, the image_00 line of calib_cam_to_pose.txt."""
    for line in text_lines(path, "KITTI-360 calib_cam_to_pose.txt"):
        key, _, values = line.partition(":")
        if key.strip() == "image_00":
            return _rigid_rows(path, values.split(), "image_00")
    raise InputError(path, "no 'image_00:' line (camera 0 -> pose)")


def read_cam_to_velo(path: Path) -> np.ndarray:
    """T_velo_cam0 from calib_cam_to_velo.txt (12 numbers)."""
    words = " ".join(text_lines(path, "KITTI-360 calib_cam_to_velo.txt")).split()
    return _rigid_rows(path, words, "cam0 -> velo")


def pose_to_velo(T_world_pose: np.ndarray, T_pose_cam0: np.ndarray,
                 T_velo_cam0: np.ndarray) -> np.ndarray:
    """KITTI-360 poses.txt (T_world_pose) to T_world_velo."""
    return T_world_pose @ T_pose_cam0 @ np.linalg.inv(T_velo_cam0)


def read_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(frame numbers, T_world_pose (N, 4, 4)) of data_poses/DRIVE/poses.txt."""
    rows = load_rows(path, 13, "KITTI-360 poses.txt: frame + 12 numbers", delimiter=None)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows[:, 1:13].reshape(-1, 3, 4)
    return rows[:, 0].astype(np.int64), poses


def open_sequence(drive: Path) -> DatasetSource:
    """A KITTI-360 drive (see the module docstring)."""
    velo = drive / "velodyne_points"
    files = sorted((velo / "data").glob("*.bin"))
    if not files:
        raise InputError(velo / "data", "no .bin scans found (KITTI-360 <frame>.bin)")
    try:
        frames = np.array([int(p.stem) for p in files], dtype=np.int64)
    except ValueError:
        raise InputError(velo / "data", "a scan file name is not a frame number") from None
    stamps_all = read_kitti_raw_timestamps(require(velo / "timestamps.txt",
                                                   "KITTI-360 velodyne timestamps"))
    if frames.max() >= len(stamps_all):
        raise InputError(velo / "timestamps.txt", f"has {len(stamps_all)} stamps, the scans "
                                                  f"reach frame {int(frames.max())}")
    stamps = stamps_all[frames]
    root = drive.parent.parent
    gt = None
    pose_file = root / "data_poses" / drive.name / "poses.txt"
    if pose_file.is_file():
        calib = root / "calibration"
        T_pose_cam0 = read_cam_to_pose(require(calib / "calib_cam_to_pose.txt",
                                               "KITTI-360 calibration, needed for the poses"))
        T_velo_cam0 = read_cam_to_velo(require(calib / "calib_cam_to_velo.txt",
                                               "KITTI-360 calibration, needed for the poses"))
        pose_frames, T_world_pose = read_poses(pose_file)
        if pose_frames.size and pose_frames.max() >= len(stamps_all):
            raise InputError(pose_file, f"frame {int(pose_frames.max())} has no stamp in "
                                        f"{velo / 'timestamps.txt'}")
        gt = poses_at(stamps_all[pose_frames], pose_to_velo(T_world_pose, T_pose_cam0,
                                                            T_velo_cam0), stamps)
    why = (("imu", "KITTI-360's OXTS data are not read"),
           ("gnss", "KITTI-360's OXTS data are not read"))
    return DatasetSource(KIND, drive.name, files, stamps, lambda p, _s: read_bin(p), gt,
                         Carried(why_not=why))
