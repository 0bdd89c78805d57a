"""Which topic of a bag to read: the PointCloud2 topic of the scans, and the sensor_msgs/Imu and
NavSatFix topics (the one named, else the only one; several without a choice is refused)."""

from __future__ import annotations

from pathlib import Path

from lidar_slam.errors import InputError
from lidar_slam.io.rosbag.pointcloud2 import POINTCLOUD2


def pick_cloud_topic(path: Path, topics: dict[str, tuple[str, int]], topic: str | None
                     ) -> str:
    """The PointCloud2 topic to read: the one named, else the only one; none, or several
    without a choice, is refused."""
    clouds = sorted(t for t, (typ, _) in topics.items() if typ == POINTCLOUD2)
    if topic is not None:
        if topic not in topics:
            have = ", ".join(clouds) or "none"
            raise InputError(path, f"no topic {topic} (PointCloud2 topics: {have})")
        if topics[topic][0] != POINTCLOUD2:
            raise InputError(path, f"topic {topic} is {topics[topic][0]}, not PointCloud2")
        return topic
    if not clouds:
        listing = ", ".join(f"{t} [{typ}]" for t, (typ, _) in sorted(topics.items()))
        if not listing:  # a bag whose index names nothing: cut short, or empty
            raise InputError(path, "no topics at all (an empty bag, or one cut short before "
                                   "its index)")
        raise InputError(path, f"no sensor_msgs/PointCloud2 topic (topics: {listing})")
    if len(clouds) > 1:
        raise InputError(path, f"{len(clouds)} sensor_msgs/PointCloud2 topics "
                                    f"({', '.join(clouds)}): pass --topic to choose one")
    return clouds[0]


def pick_typed_topic(path: Path, topics: dict[str, tuple[str, int]], topic: str | None,
                      msgtype: str, flag: str) -> str | None:
    """The topic of msgtype to read: the one named, else the only one (None when there is
    none); several without a choice is refused, as PointCloud2 topics are."""
    short = msgtype.replace("/msg/", "/")
    typed = sorted(t for t, (typ, _) in topics.items() if typ == msgtype)
    if topic is not None:
        if topic not in topics:
            raise InputError(path, f"no topic {topic} ({short} topics: "
                                   f"{', '.join(typed) or 'none'})")
        if topics[topic][0] != msgtype:
            raise InputError(path, f"topic {topic} is {topics[topic][0]}, not {short}")
        return topic
    if len(typed) > 1:
        off = flag.replace("-topic", "").replace("--", "--no-")
        raise InputError(path, f"{len(typed)} {short} topics ({', '.join(typed)}): pass {flag} "
                               f"to choose one (or {off})")
    return typed[0] if typed else None

