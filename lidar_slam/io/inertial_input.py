"""The IMU and GNSS of one input, from a folder's csv files or a bag's topics, checked against
the scan stamps, with what summary.json says of them (issue 22, item 1)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.io.datasets.common import Carried
from lidar_slam.io.imu_gnss import (
    GNSS_FILE,
    IMU_FILE,
    GnssFixes,
    ImuSamples,
    check_overlap,
    find_beside,
    overlap_problem,
    read_gnss_csv,
    read_imu_csv,
    stream_info,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InertialInput:
    """The IMU samples and GNSS fixes of a run (None when not used), on the scans' clock (the
    config's time offsets applied), and what summary.json says of each ("imu", "gnss")."""

    imu: ImuSamples | None
    gnss: GnssFixes | None
    summary: dict


def _folder_stream(data: Path, name: str, reader, what: str):
    """The stream in `name` beside the scans of a folder input, or (None, why not)."""
    path = find_beside(data, name) if data.is_dir() else None
    if path is None:
        return None, f"no {name} beside the scans"
    return reader(path), None


def _carried_stream(carried: Carried, what: str, imu_mount_given: bool):
    """A dataset's stream, or (None, why not): an IMU whose mounting neither the dataset nor the
    config gives is not used (a wrong mounting makes the trajectory worse than none)."""
    stream = carried.imu if what == "imu" else carried.gnss
    if stream is None:
        return None, carried.reason(what)
    if what == "imu" and carried.T_lidar_imu is None and not imu_mount_given:
        log.warning("%s", carried.reason("imu"))
        return None, carried.reason("imu")
    return stream, None


def load_inertial(data: Path, kind: str, scan_stamps: np.ndarray | None, *, imu_enabled: bool,
                  gnss_enabled: bool, imu_offset_s: float | None = 0.0,
                  gnss_offset_s: float = 0.0,
                  imu_topic: str | None = None, gnss_topic: str | None = None,
                  carried: Carried | None = None, imu_mount_given: bool = False
                  ) -> InertialInput:
    """Read the IMU and GNSS of an input: imu.csv / gnss.csv beside a folder's scans (or in its
    scans/ subfolder), the sensor_msgs/Imu and NavSatFix topics of a bag (picked like the
    PointCloud2 topic, or named), or the streams a public dataset's layout carries (`carried`;
    its IMU only with a mounting, from the dataset or the config: imu_mount_given). scan_stamps
    (s) are checked against the streams' stamps (see check_overlap); a bag topic picked without
    being named that does not overlap them is not used (a warning, and the reason in the
    summary) instead of stopping the run. imu_offset_s None: the IMU's offset is to be found
    from the data; its stream comes back as read, to be placed by on_scan_clock."""
    is_bag = kind == "rosbag"
    for flag, value, enabled in (("--imu-topic", imu_topic, imu_enabled),
                                 ("--gnss-topic", gnss_topic, gnss_enabled)):
        if value is not None and not is_bag:
            log.warning("%s %s ignored: %s is not a rosbag", flag, value, data)
        elif value is not None and not enabled:
            log.warning("%s %s ignored: switched off (--no-%s or its enabled: false)", flag,
                        value, flag[2:-6])
    topics = {"imu": imu_topic, "gnss": gnss_topic}
    streams: dict[str, object] = {}
    summary: dict[str, dict] = {}
    for what, enabled, offset_s in (("imu", imu_enabled, imu_offset_s),
                                    ("gnss", gnss_enabled, gnss_offset_s)):
        if not enabled:
            stream, why = None, f"off (--no-{what} or {what}.enabled: false)"
        elif carried is not None:
            stream, why = _carried_stream(carried, what, imu_mount_given)
        elif is_bag:
            from lidar_slam.io import rosbag  # rosbags only when reading a bag

            reader = rosbag.read_imu_topic if what == "imu" else rosbag.read_gnss_topic
            stream, why = reader(data, topics[what])
        else:
            name, reader = (IMU_FILE, read_imu_csv) if what == "imu" else (GNSS_FILE,
                                                                             read_gnss_csv)
            stream, why = _folder_stream(data, name, reader, what)
        if stream is None:
            summary[what] = {"used": False, "reason": why}
            streams[what] = None
            continue
        if offset_s is None:  # to be found from the data (imu_calibration): placed later
            summary[what] = {"used": True, "source": stream.source}
            streams[what] = stream
            continue
        lenient = carried is not None or is_bag and topics[what] is None
        streams[what], summary[what] = on_scan_clock(stream, what, offset_s, scan_stamps,
                                                     lenient)
    return InertialInput(streams["imu"], streams["gnss"], summary)


def on_scan_clock(stream, what: str, offset_s: float, scan_stamps: np.ndarray | None,
                  lenient: bool):
    """The stream with offset_s added to its stamps, checked against the scan stamps (see
    check_overlap), and what summary.json says of it: (stream or None, summary). lenient: a
    stream that does not overlap the scans is not used (a warning, the reason in the summary)
    instead of stopping the run (a topic picked without being asked for, e.g. an Ouster's own
    IMU stamped by the sensor's clock, must not stop a run that can go on without it)."""
    stream = stream.shifted(offset_s) if offset_s else stream
    label = "IMU" if what == "imu" else "GNSS"
    if scan_stamps is not None and len(scan_stamps):
        span = float(scan_stamps[0]), float(scan_stamps[-1])
        problem = overlap_problem(stream.stamp_s, *span, label)
        if problem is not None and lenient:
            log.warning("%s: not used: %s; --no-%s silences this", stream.source, problem,
                        what)
            return None, {"used": False, "reason": f"{stream.source}: {problem}"}
        check_overlap(stream.source, stream.stamp_s, *span, label)
    return stream, {"used": True, **stream_info(stream.stamp_s, stream.source, stream.dropped,
                                               offset_s)}
