"""NCLT (Carlevaris-Bianco et al., IJRR 2016): velodyne_sync scans, the ground truth, the MS25
IMU and the consumer GPS, as the dataset's download unpacks them:

    DATE/velodyne_sync/<utime>.bin   8 bytes a point: uint16 x, y, z (little-endian), uint8
                                     intensity, uint8 laser; metres = value * 0.005 - 100
                                     (the NCLT site's read_vel_sync.py, convert() / '<HHHBB')
    DATE/ms25.csv                    utime, mag xyz, accel xyz (m/s^2), rot_r, rot_p, rot_h
                                     (rad/s) (the site's ms25_to_rosbag.py)
    DATE/gps.csv                     utime, mode, num_sats, lat, lng (rad), alt, track, speed
                                     (the site's read_gps.py reads lat/lng in radians)
    groundtruth_DATE.csv             utime, x, y, z, roll, pitch, yaw (rad): T_world_body, in
                                     DATE/, beside it, or in ../ground_truth/ (kiss-icp's place)

utime is microseconds. Frames: the site's project_vel_to_cam.py projects the velodyne_sync
points with T_cam_body alone ("hits_body"): they are already in the body frame (x forward, y
right, z down), so x_body_vel is not applied again. This reader turns them z-up, as kiss-icp's
loader does: lidar frame L = body rotated 180 deg about x (F = diag(1, -1, -1)), points F p,
and T_world_lidar = F @ T_world_body @ F (world z up too). T_world_body from the ground truth
row: R = Rz(yaw) Ry(pitch) Rx(roll), the site's ssc_to_homo.

No per-point times (velodyne_sync has none). IMU: read, but the dataset's files give no MS25
mounting: used only with imu.T_lidar_imu in the config (in the z-up lidar frame above; ETH's
nclt_tools, python/sensor_extrinsics.py get_T_B_I, puts it at (-0.11, -0.18, -0.71) m in the body
frame, axes aligned: in this lidar frame [-0.11, 0.18, 0.71, 180, 0, 0], docs/datasets.md). GPS:
fixes with mode >= 2 (0 and 1 are no fix: nclt_tools python/sensordata_to_rosbag.py write_gps);
gps.csv has no accuracy, so CONSUMER_GPS_SIGMA_* below (1-sigma, m) are used.
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
    rigid,
    rpy_zyx,
    stamped_files,
)
from lidar_slam.io.imu_gnss import gnss_from_rows, imu_from_rows
from lidar_slam.io.pointcloud import CloudData

KIND = "nclt"
SCALE_M, OFFSET_M = 0.005, -100.0  # read_vel_sync.py convert()
POINT = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # body (z down) -> this reader's z-up lidar frame
# A consumer receiver's horizontal / vertical 1-sigma (m): gps.csv states no accuracy. Loose on
# purpose: the back-end's Huber loss and chi-square gate handle what is worse.
CONSUMER_GPS_SIGMA_H_M, CONSUMER_GPS_SIGMA_V_M = 5.0, 10.0


def detect(path: Path) -> Path | None:
    """The session folder when path holds velodyne_sync/, else None."""
    return path if (path / "velodyne_sync").is_dir() else None


def ground_truth_file(root: Path) -> Path | None:
    name = f"groundtruth_{root.name}.csv"
    for cand in (root / name, root / "groundtruth.csv", root.parent / name,
                 root.parent / "ground_truth" / name):
        if cand.is_file():
            return cand
    return None


def body_to_lidar(T_world_body: np.ndarray) -> np.ndarray:
    """NCLT ground truth (T_world_body, z down) to this reader's z-up T_world_lidar."""
    return FLIP @ T_world_body @ FLIP


def read_ground_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps s, T_world_body (N, 4, 4)) of groundtruth_DATE.csv; rows with NaN dropped (the
    files start with some)."""
    rows = load_rows(path, 7, "NCLT ground truth: utime, x, y, z, roll, pitch, yaw")
    rows = rows[np.isfinite(rows[:, :7]).all(axis=1)]
    poses = np.array([rigid(rpy_zyx(*r[4:7]), r[1:4]) for r in rows]).reshape(-1, 4, 4)
    return rows[:, 0] * 1e-6, poses


def read_velodyne_sync(path: Path) -> CloudData:
    """One velodyne_sync file, points in the z-up lidar frame (F p_body)."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc
    if size % POINT.itemsize:
        raise InputError(path, f"{size} bytes is not a multiple of 8 (NCLT velodyne_sync: "
                               "uint16 x, y, z, uint8 intensity, laser)")
    hits = np.fromfile(path, dtype=POINT)
    xyz = np.stack([hits["x"], hits["y"], hits["z"]], axis=1) * SCALE_M + OFFSET_M
    xyz[:, 1:] *= -1.0  # F p: y and z flipped
    return CloudData(xyz, None, hits["i"].astype(np.float32))


def _carried(root: Path) -> Carried:
    why = []
    imu = gnss = None
    imu_file, gps_file = root / "ms25.csv", root / "gps.csv"
    if imu_file.is_file():
        r = load_rows(imu_file, 10, "NCLT ms25.csv: utime, mag xyz, accel xyz, rot rph")
        imu = imu_from_rows(imu_file, np.c_[r[:, 0] * 1e-6, r[:, 7:10], r[:, 4:7]])
        why.append(("imu", f"{imu_file}: NCLT publishes no MS25-to-lidar mounting; set "
                           "imu.T_lidar_imu (z-up lidar frame, docs/datasets.md) to use it"))
    else:
        why.append(("imu", f"no {imu_file}"))
    if gps_file.is_file():
        r = load_rows(gps_file, 6, "NCLT gps.csv: utime, mode, num_sats, lat, lng, alt, ...")
        r = r[r[:, 1] >= 2]  # mode 2 (2D) or 3 (3D fix)
        n = len(r)
        gnss = gnss_from_rows(gps_file, np.c_[r[:, 0] * 1e-6, np.degrees(r[:, 3:5]), r[:, 5],
                                              np.full(n, CONSUMER_GPS_SIGMA_H_M),
                                              np.full(n, CONSUMER_GPS_SIGMA_V_M)])
    else:
        why.append(("gnss", f"no {gps_file}"))
    return Carried(imu=imu, gnss=gnss, T_lidar_imu=None, why_not=tuple(why))


def open_sequence(root: Path) -> DatasetSource:
    """An NCLT session folder (see the module docstring)."""
    files, stamps = stamped_files(root / "velodyne_sync", ".bin", lambda s: int(s) * 1e-6,
                                  "NCLT velodyne_sync/<utime>.bin")
    gt = None
    gt_file = ground_truth_file(root)
    if gt_file is not None:
        gt_stamps, T_world_body = read_ground_truth(gt_file)
        gt = poses_at(gt_stamps, body_to_lidar(T_world_body), stamps)
    return DatasetSource(KIND, root.name, files, stamps, lambda p, _s: read_velodyne_sync(p),
                         gt, _carried(root))
