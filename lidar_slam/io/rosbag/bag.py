"""Opening a bag: rosbags' AnyReader, the ros1-profile MCAP reader, or, for a recording cut
short, a reader of its complete messages; their errors become one InputError naming the file."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.typesys import Stores, get_typestore

from lidar_slam.errors import InputError
from lidar_slam.io.rosbag.mcap import McapScan, mcap_profile
from lidar_slam.io.rosbag.reader import BAG_ERRORS, LEAKS, BagReader, problem
from lidar_slam.io.rosbag.recovery import Db3Scan, Ros1BagScan

log = logging.getLogger(__name__)


class _AnyBag(BagReader):
    """rosbags' AnyReader over one ROS1 .bag, ROS2 folder or ROS2-profile .mcap/.db3 file."""

    def __init__(self, path: Path):
        # Bags without embedded definitions (old ROS2 sqlite3) need a default typestore.
        self.reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        self.reader.open()

    def close(self) -> None:
        self.reader.close()

    def topics(self) -> dict[str, tuple[str, int]]:
        return {name: (info.msgtype or "?", info.msgcount)
                for name, info in self.reader.topics.items()}

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        conns = [c for c in self.reader.connections if c.topic == topic]
        for conn, _, raw in self.reader.messages(conns):
            yield (lambda r=raw, t=conn.msgtype: self.reader.deserialize(r, t)), raw


def _recovery_reader(path: Path) -> BagReader | None:
    """A reader of the complete messages of a recording rosbags refuses (cut short, no index),
    or None when the file is not one (or not even that can be read)."""
    if path.is_dir():
        files = [f for f in path.iterdir() if f.suffix.lower() in (".db3", ".mcap")]
        if len(files) != 1:
            return None
        path = files[0]
    suffix = path.suffix.lower()
    kinds = {".bag": Ros1BagScan, ".mcap": McapScan, ".db3": Db3Scan}
    if suffix not in kinds:
        return None
    try:
        reader = kinds[suffix](path)
    except (*BAG_ERRORS, *LEAKS) as exc:
        log.debug("%s: no message recoverable (%s)", path, exc)
        return None
    return reader if reader.recovered is not None else None


def _open_reader(path: Path) -> BagReader:
    """The reader for a bag: rosbags' AnyReader, ours for ros1-profile mcap, and, when rosbags
    refuses a recording cut short, ours of its complete messages (`recovered` set)."""
    try:
        if path.is_file() and path.suffix.lower() == ".mcap" and mcap_profile(path) == "ros1":
            return McapScan(path)
        try:
            return _AnyBag(path)
        except (*BAG_ERRORS, *LEAKS) as exc:
            recovered = _recovery_reader(path)
            if recovered is None:
                raise
            if recovered.recovered == 0:
                recovered.close()
                raise InputError(path, "truncated or damaged recording: not one complete "
                                       f"message in it ({problem(exc)})") from exc
            return recovered
    except (*BAG_ERRORS, *LEAKS) as exc:
        raise InputError(path, f"unreadable or damaged bag ({problem(exc)})") from exc


def topic_messages(bag: BagReader, topic: str) -> Iterator[Any]:
    """The deserializers of a topic's messages, in order (see LEAKS)."""
    try:
        for deserialize, _ in bag.raw_messages(topic):
            yield deserialize
    except LEAKS as exc:
        raise Ros2ReaderError(f"{type(exc).__name__}: {exc}") from exc


@contextmanager
def open_bag(path: Path) -> Iterator[BagReader]:
    """An open bag; the errors of rosbags and of the readers here become InputError naming
    the file."""
    bag = _open_reader(path)
    try:
        yield bag
    except BAG_ERRORS as exc:
        raise InputError(path, f"unreadable or damaged bag ({problem(exc)})") from exc
    finally:
        bag.close()


