"""RosbagSource: the PointCloud2 messages of one topic of a bag as Scans (see the package
docstring for stamps and per-point times)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.inertial_input import ImuGnssStreams, Stream
from lidar_slam.io.rosbag.bag import open_bag, topic_messages
from lidar_slam.io.rosbag.imu_gnss import read_gnss_topic, read_imu_topic
from lidar_slam.io.rosbag.pointcloud2 import PointCloud2Error, decode_pointcloud2, header_stamp_ns
from lidar_slam.io.rosbag.reader import BAG_ERRORS, LEAKS, problem
from lidar_slam.io.rosbag.topics import pick_cloud_topic
from lidar_slam.types import Scan

log = logging.getLogger(__name__)


class RosbagSource(ImuGnssStreams):
    """PointCloud2 messages of one topic of a ROS1/ROS2 bag or MCAP file, as Scans.

    index = 0-based position among the scans kept: a message whose header stamp is not after
    the previous kept one (a duplicate or a step back) is dropped, so stamps strictly increase
    and `len`, `scans(start, count)` and a resumed run all count the same scans. A recording cut
    short gives its complete messages. Both are counted in `input_notes` and logged once.
    See the package docstring for stamps and times. Its IMU and GNSS are the bag's Imu and
    NavSatFix topics: the one named, else the only one (io.rosbag.imu_gnss).
    """

    kind = "rosbag"
    topics_apply = True  # --imu-topic / --gnss-topic

    def __init__(self, path: str | Path, topic: str | None = None):
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "does not exist")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise InputError(self.path, "folder is not a ROS2 bag (no metadata.yaml)")
        self.name = self.path.stem if self.path.is_file() else self.path.name
        self.ground_truth: np.ndarray | None = None
        with open_bag(self.path) as bag:
            topics = bag.topics()
            recovered = bag.recovered
        self.topic = pick_cloud_topic(self.path, topics, topic)
        self._count = topics[self.topic][1]
        self._notes: dict[str, int] = {}
        if recovered is not None:
            if self._count == 0:  # the error says it all: no warning line before it
                raise InputError(self.path, f"truncated recording (no footer/index): recovered "
                                            f"{recovered} complete messages, none on {self.topic}")
            self._notes["recovered_truncated_messages"] = self._count
            log.warning("%s: truncated recording (no footer/index): recovered %d complete "
                        "messages, %d of them on %s", self.path, recovered, self._count,
                        self.topic)
        if self._count == 0:
            raise InputError(self.path, f"topic {self.topic} has no messages")
        self._kept: list[int] | None = None  # topic positions of the kept messages
        self._stamps_s = np.empty(0)  # their header stamps (s), set with _kept

    @property
    def input_notes(self) -> dict[str, int]:
        """Counts of what the reader dropped or recovered (for summary.json)."""
        self._kept_positions()
        return dict(self._notes)


    def _kept_positions(self) -> list[int]:
        """Positions in the topic of the messages kept: one pass over the header stamps, each
        one kept when after the last kept stamp (the count is needed before the first scan)."""
        if self._kept is not None:
            return self._kept
        kept: list[int] = []
        stamps_ns: list[int] = []
        duplicate = backwards = n_read = 0
        last = None
        with open_bag(self.path) as bag:
            for n_read, deserialize in enumerate(topic_messages(bag, self.topic), 1):
                stamp = header_stamp_ns(self._message(n_read - 1, deserialize))
                if last is not None and stamp <= last:
                    duplicate += stamp == last
                    backwards += stamp < last
                    continue
                kept.append(n_read - 1)
                stamps_ns.append(stamp)
                last = stamp
        if n_read < self._count:
            raise InputError(self.path, f"{self.topic}: the bag lists {self._count} messages but "
                                        f"only {n_read} could be read (damaged bag?)")
        if duplicate or backwards:
            log.warning("%s: %s: dropped %d of %d scans whose header stamp is not after the "
                        "previous scan's (%d duplicate, %d going backwards)", self.path,
                        self.topic, duplicate + backwards, n_read, duplicate, backwards)
        self._notes.update(dropped_duplicate_stamps=duplicate, dropped_backwards_stamps=backwards)
        self._kept = kept
        self._stamps_s = np.array(stamps_ns, dtype=np.float64) * 1e-9
        return kept

    @property
    def stamps(self) -> np.ndarray:
        """Header stamps (s) of the kept scans, as Scan.stamp_s."""
        self._kept_positions()
        return self._stamps_s

    def __len__(self) -> int:
        return len(self._kept_positions())

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        """Kept scans start .. start+count-1 of the topic (header stamps, times relative to
        them)."""
        kept = self._kept_positions()
        stop = len(kept) if count is None else min(len(kept), start + count)
        if start >= stop:
            return
        wanted = {position: index for index, position in enumerate(kept[start:stop], start)}
        last = kept[stop - 1]
        i = -1
        with open_bag(self.path) as bag:
            for i, deserialize in enumerate(topic_messages(bag, self.topic)):
                if i > last:
                    break
                if i in wanted:
                    yield self._scan(wanted[i], i, self._message(i, deserialize))
        if i < last:
            raise InputError(self.path, f"{self.topic}: message {last} could be read before but "
                                        f"not now (only {i + 1}; damaged bag?)")

    def _message(self, position: int, deserialize: Any) -> Any:
        try:
            return deserialize()
        except (*BAG_ERRORS, *LEAKS) as exc:
            raise InputError(self.path, f"{self.topic} message {position} cannot be "
                                        f"deserialized ({problem(exc)})") from exc

    def _scan(self, index: int, position: int, msg: Any) -> Scan:
        try:
            cloud = decode_pointcloud2(msg)
        except PointCloud2Error as exc:
            raise InputError(self.path, f"{self.topic} message {position}: {exc}") from exc
        total = len(cloud.points) + cloud.n_dropped
        log.debug("%s[%d]: %d of %d points kept (%d NaN/inf or (0,0,0) returns dropped)",
                  self.topic, position, len(cloud.points), total, cloud.n_dropped)
        return Scan(index, header_stamp_ns(msg) * 1e-9, cloud.points, cloud.point_times,
                    cloud.intensity, f"{self.path}:{self.topic}[{position}]")

    def own_stream(self, what: str, topic: str | None) -> tuple[Stream | None, str | None]:
        """The bag's sensor_msgs/Imu ("imu") or NavSatFix ("gnss") topic: topic, else the only
        one; (None, why not) when there is none."""
        reader = read_imu_topic if what == "imu" else read_gnss_topic
        return reader(self.path, topic)

    def own_mounting(self, imu_topic: str | None) -> tuple[np.ndarray | None, str]:
        """T_lidar_imu from the bag's /tf_static between the frames of its clouds and of its
        Imu messages (io.rosbag.tf), or (None, why not)."""
        from lidar_slam.io.rosbag.tf import imu_mounting

        return imu_mounting(self.path, self.topic, imu_topic)

    def lenient(self, what: str, topic: str | None) -> bool:
        """A topic picked without being named that misses the scans is left out (an Ouster's
        own IMU, stamped by the sensor's clock), a named one stops the run."""
        return topic is None
