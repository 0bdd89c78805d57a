"""The sensor_msgs/Imu and NavSatFix messages of a bag as IMU samples and GNSS fixes (header
stamps), cleaned as imu.csv / gnss.csv are (lidar_slam.io.imu_gnss)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.imu_gnss import GnssFixes, ImuSamples, gnss_from_rows, imu_from_rows
from lidar_slam.io.rosbag.bag import open_bag, topic_messages
from lidar_slam.io.rosbag.pointcloud2 import header_stamp_ns
from lidar_slam.io.rosbag.reader import BAG_ERRORS, LEAKS, problem
from lidar_slam.io.rosbag.topics import pick_typed_topic

log = logging.getLogger(__name__)


IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"


def _typed_rows(path: Path, topic: str | None, msgtype: str, flag: str, row: Any
                ) -> tuple[str | None, np.ndarray]:
    """The picked topic and row(message) of each of its messages as an (N, k) array (None and
    an empty array when there is no such topic); messages are not kept (an hour of IMU at
    200 Hz is 720k of them)."""
    with open_bag(path) as bag:
        picked = pick_typed_topic(path, bag.topics(), topic, msgtype, flag)
        if picked is None:
            return None, np.empty((0, 0))
        rows = []
        for position, deserialize in enumerate(topic_messages(bag, picked)):
            try:
                msg = deserialize()
            except (*BAG_ERRORS, *LEAKS) as exc:
                raise InputError(path, f"{picked} message {position} cannot be deserialized "
                                       f"({problem(exc)})") from exc
            rows.append(row(msg))
    return picked, np.array(rows, dtype=np.float64)


def _imu_row(m: Any) -> tuple[float, ...]:
    return (header_stamp_ns(m) * 1e-9, m.angular_velocity.x, m.angular_velocity.y,
            m.angular_velocity.z, m.linear_acceleration.x, m.linear_acceleration.y,
            m.linear_acceleration.z)


def _fix_row(m: Any) -> tuple[float, ...]:
    """stamp, lat, lon, alt, sigma_h, sigma_v, status, covariance type."""
    cov = m.position_covariance
    return (header_stamp_ns(m) * 1e-9, m.latitude, m.longitude, m.altitude,
            max(cov[0], cov[4]), cov[8], m.status.status, m.position_covariance_type)


def read_imu_topic(path: Path, topic: str | None = None) -> tuple[ImuSamples | None, str | None]:
    """The sensor_msgs/Imu samples of a bag (header stamps), cleaned as imu.csv; or None and why
    not (no Imu topic)."""
    picked, rows = _typed_rows(path, topic, IMU, "--imu-topic", _imu_row)
    if picked is None:
        return None, "no sensor_msgs/Imu topic in the bag"
    return imu_from_rows(f"{path}:{picked}", rows.reshape(-1, 7)), None


def read_gnss_topic(path: Path, topic: str | None = None
                    ) -> tuple[GnssFixes | None, str | None]:
    """The sensor_msgs/NavSatFix fixes of a bag (header stamps), cleaned as gnss.csv; fixes
    with status NO_FIX (< 0) or an unknown covariance (type 0) are dropped and counted. sigma_h
    is the larger of the east and north sigmas of the covariance's diagonal."""
    picked, rows = _typed_rows(path, topic, NAVSATFIX, "--gnss-topic", _fix_row)
    if picked is None:
        return None, "no sensor_msgs/NavSatFix topic in the bag"
    rows = rows.reshape(-1, 8)
    no_fix = rows[:, 6] < 0
    unknown_cov = ~no_fix & (rows[:, 7] == 0)
    with np.errstate(invalid="ignore"):
        rows[:, 4:6] = np.sqrt(rows[:, 4:6])  # variances (m^2) to sigmas; negative: NaN
    fixes = rows[:, :6].copy()
    fixes[no_fix | unknown_cov] = np.nan  # dropped (and counted as invalid) by gnss_from_rows
    if no_fix.any() or unknown_cov.any():
        log.warning("%s:%s: %d fixes without a fix (status < 0) and %d with an unknown "
                    "covariance are not used", path, picked, no_fix.sum(), unknown_cov.sum())
    return gnss_from_rows(f"{path}:{picked}", fixes,
                          {"no_fix": int(no_fix.sum()),
                           "unknown_covariance": int(unknown_cov.sum())}), None
