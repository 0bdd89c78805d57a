"""Sequential readers of a ROS1 .bag and a ROS2 .db3 that rosbags refuses (cut short, no
index): their complete messages, in file / row order."""

from __future__ import annotations

import logging
import struct
from collections import Counter
from collections.abc import Iterator
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

import apsw
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1.reader import Header as Ros1Header
from rosbags.rosbag1.reader import RecordType, decompressors
from rosbags.rosbag1.reader import normalize as ros1_normalize
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.typesys import Stores
from rosbags.typesys.msg import normalize_msgtype

from lidar_slam.io.rosbag.reader import (
    BAG_ERRORS,
    LEAKS,
    BagReader,
    decompress_prefix,
    typestore_of,
)

log = logging.getLogger(__name__)


def _ros1_record(src: BinaryIO, end: int) -> tuple[Ros1Header, bytes, bool] | None:
    """(header, data, complete) of the ROS1 bag record at the current position, None when its
    header does not fit before `end`; the data is cut short when the record runs past `end`."""
    pos = src.tell()
    if pos + 4 > end:
        return None
    (size,) = struct.unpack("<I", src.read(4))
    if pos + 8 + size > end:
        return None
    src.seek(pos)
    header = Ros1Header.read(src)
    (size,) = struct.unpack("<I", src.read(4))
    data = src.read(min(size, end - src.tell()))
    return header, data, len(data) == size


class Ros1BagScan(BagReader):
    """The complete messages of a ROS1 bag whose index rosbags cannot use: a recording cut short
    (the index sits at the end) or left unindexed by a recorder that crashed. rosbags has no
    reindex, so the records are walked in file order with rosbags' record-header parser; the
    first record that is cut off or unreadable ends the walk."""

    def __init__(self, path: Path):
        self.path = path
        self.size = path.stat().st_size
        self.connections: dict[int, tuple[str, str, str]] = {}  # id -> (topic, msgtype, def)
        with path.open("rb") as fh:
            if fh.readline(64) != b"#ROSBAG V2.0\n":
                raise Ros1ReaderError("not a ROS1 v2.0 bag (bad magic)")
            self.data_start = fh.tell()
        by_topic = Counter(topic for topic, _ in self._messages(None))
        self.counts = by_topic
        self.recovered = sum(by_topic.values())

    def _messages(self, topic: str | None) -> Iterator[tuple[str, bytes]]:
        """(topic, raw ROS1 message) in file order, up to the first cut-off or bad record."""
        with self.path.open("rb") as fh:
            fh.seek(self.data_start)
            try:
                while (rec := _ros1_record(fh, self.size)) is not None:
                    header, data, complete = rec
                    if header.get_uint8("op") == RecordType.CHUNK:
                        compression = header.get_string("compression")
                        inner = (decompress_prefix(data, compression) if not complete
                                 else decompressors[compression](data))
                        yield from self._records(inner, topic)
                    elif complete:
                        yield from self._record(header, data, topic)
                    if not complete:
                        return
            except (*BAG_ERRORS, *LEAKS) as exc:
                log.debug("%s: records unreadable from offset %d on (%s)", self.path,
                          fh.tell(), exc)

    def _records(self, buf: bytes, topic: str | None) -> Iterator[tuple[str, bytes]]:
        src = BytesIO(buf)
        while (rec := _ros1_record(src, len(buf))) is not None and rec[2]:
            yield from self._record(rec[0], rec[1], topic)

    def _record(self, header: Ros1Header, data: bytes, topic: str | None
                ) -> Iterator[tuple[str, bytes]]:
        op = header.get_uint8("op")
        if op == RecordType.CONNECTION:
            conn = Ros1Header.read(BytesIO(struct.pack("<I", len(data)) + data))
            self.connections[header.get_uint32("conn")] = (
                ros1_normalize(header.get_string("topic")),
                normalize_msgtype(conn.get_string("type")), conn.get_string("message_definition"))
        elif op == RecordType.MSGDATA:
            known = self.connections.get(header.get_uint32("conn"))
            if known is not None and (topic is None or known[0] == topic):
                yield known[0], data

    def topics(self) -> dict[str, tuple[str, int]]:
        return {t: (typ, self.counts.get(t, 0)) for t, typ, _ in self.connections.values()}

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        definitions = {typ: ("ros1msg", text) for t, typ, text in self.connections.values()
                       if t == topic}
        typestore = typestore_of(definitions, None)
        msgtype = next(iter(definitions))
        for _, raw in self._messages(topic):
            yield (lambda r=raw: typestore.deserialize_ros1(r, msgtype)), raw


class Db3Scan(BagReader):
    """The messages sqlite still reads from a ROS2 .db3 cut short, in row order, up to the first
    row it cannot read."""

    def __init__(self, path: Path):
        self.path = path
        self.db = apsw.Connection(str(path), flags=apsw.SQLITE_OPEN_READONLY)
        try:
            # sqlite refuses a file shorter than its header's page count as corrupt unless the
            # schema is "writable"; nothing is written (read-only connection).
            self.db.execute("PRAGMA writable_schema=ON")
            topics = self.db.execute("SELECT id, name, type FROM topics")
            self.topic_rows = {tid: (ros1_normalize(name), normalize_msgtype(typ))
                               for tid, name, typ in topics}
            try:
                self.definitions = {normalize_msgtype(t): (e, d) for t, e, d in self.db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition "
                    "FROM message_definitions")}
            except apsw.SQLError:  # older bags have no such table: rosbags' types are used
                self.definitions = {}
            self.counts = Counter(self.topic_rows[tid][0] for tid, _ in self._rows(None)
                                  if tid in self.topic_rows)
        except BaseException:
            self.db.close()
            raise
        self.recovered = sum(self.counts.values())

    def close(self) -> None:
        self.db.close()

    def _rows(self, topic_ids: set[int] | None) -> Iterator[tuple[int, bytes]]:
        try:
            for tid, data in self.db.execute("SELECT topic_id, data FROM messages ORDER BY id"):
                if topic_ids is None or tid in topic_ids:
                    yield tid, data
        except apsw.Error as exc:
            log.debug("%s: rows unreadable from here on (%s)", self.path, exc)

    def topics(self) -> dict[str, tuple[str, int]]:
        return {name: (typ, self.counts.get(name, 0)) for name, typ in self.topic_rows.values()}

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        ids = {tid for tid, (name, _) in self.topic_rows.items() if name == topic}
        msgtype = self.topic_rows[next(iter(ids))][1]
        typestore = typestore_of({msgtype: self.definitions[msgtype]}
                               if msgtype in self.definitions else {}, Stores.LATEST)
        if msgtype not in typestore.fielddefs:
            raise Ros2ReaderError(f"no message definition for {msgtype}")
        for _, raw in self._rows(ids):
            yield (lambda r=raw: typestore.deserialize_cdr(r, msgtype)), raw


