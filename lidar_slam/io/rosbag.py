"""sensor_msgs/PointCloud2 topics of ROS bags as Scans; the only module that imports rosbags.

Containers: a ROS1 `.bag`, a ROS2 bag folder (metadata.yaml with .db3 or .mcap storage), and a
standalone `.mcap` of profile "ros2" (all through rosbags' AnyReader) or "ros1" (which rosbags'
MCAP reader rejects, so `_Ros1Mcap` below walks the records and deserializes with a rosbags
typestore built from the file's ros1msg schemas).

Time convention of the Scans produced here:
- `Scan.stamp_s` is the PointCloud2 header stamp in seconds (not the bag's receive time).
- `Scan.point_times` are seconds relative to `stamp_s`, converted by
  `lidar_slam.io.point_times.relative_seconds` (the conversion every reader shares): a relative
  field (Ouster `t`, Livox `offset_time`, Velodyne `time`) is an offset from the header stamp as
  it stands, so an Ouster cloud stamped at the sweep start gets times in [0, ~0.1] and a Velodyne
  cloud stamped at the sweep end gets times in [~-0.1, 0]; an absolute field (within 10 s of the
  header stamp, in s, us or ns) has the header stamp subtracted.
"""

from __future__ import annotations

import logging
import struct
import sys
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import apsw
import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2.storage_mcap import decompress as mcap_decompress
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.msg import normalize_msgtype

from lidar_slam.errors import InputError

if sys.version_info >= (3, 14):
    from compression.zstd import ZstdError
else:  # rosbags depends on the backport below 3.14
    from backports.zstd import ZstdError
from lidar_slam.io.point_times import relative_seconds
from lidar_slam.io.pointcloud import INTENSITY_FIELDS, TIME_FIELDS
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
# PointField datatype -> NumPy type code (sensor_msgs/PointField INT8..FLOAT64).
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}

# rosbags 0.11.9 raises its own errors for most damage, but fuzzing truncated/overwritten bags
# also leaked these from its dependencies and asserts: lz4 frame errors (RuntimeError), index
# asserts in the ROS1 reader (AssertionError), huge bogus record lengths (MemoryError,
# OverflowError), zstd and sqlite (apsw) errors, undecodable names (UnicodeDecodeError).
_BAG_ERRORS = (
    AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError, TypesysError, ZstdError,
    apsw.Error, AssertionError, RuntimeError, MemoryError, OverflowError, struct.error,
    UnicodeDecodeError, OSError,
)


class PointCloud2Error(ValueError):
    """A PointCloud2 message whose layout cannot be decoded (missing x/y/z, short data, ...)."""


class DecodedCloud(NamedTuple):
    """One decoded PointCloud2, invalid returns removed.

    points (N,3) float64 m in the message frame; point_times (N,) float64 s relative to the
    header stamp, or None; intensity (N,) float32 or None; n_dropped = NaN/inf or (0,0,0) returns.
    """

    points: np.ndarray
    point_times: np.ndarray | None
    intensity: np.ndarray | None
    n_dropped: int


def header_stamp_ns(msg: Any) -> int:
    """Header stamp of a rosbags message in integer nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def decode_pointcloud2(msg: Any) -> DecodedCloud:
    """x/y/z, per-point time (s from the header stamp) and intensity of a PointCloud2 message."""
    fields: dict[str, Any] = {}
    for f in msg.fields:
        fields.setdefault(f.name, f)
    if missing := [n for n in "xyz" if n not in fields]:
        have = ", ".join(fields) or "none"
        raise PointCloud2Error(f"PointCloud2 lacks field(s) {', '.join(missing)} (fields: {have})")
    wanted = {"x": fields["x"], "y": fields["y"], "z": fields["z"]}
    tname = next((n for n in TIME_FIELDS if n in fields), None)
    iname = next((n for n in INTENSITY_FIELDS if n in fields), None)
    if tname:
        wanted["t"] = fields[tname]
    if iname:
        wanted["i"] = fields[iname]
    rec = _records(msg, wanted)

    x, y, z = rec["x"], rec["y"], rec["z"]
    # Column-wise: reductions along axis 1 of an (N,3) array are several times slower.
    keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0) | (y != 0) | (z != 0))
    xyz = np.empty((len(rec), 3), dtype=np.float64)
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = x, y, z
    n_dropped = int(len(keep) - np.count_nonzero(keep))
    if n_dropped:
        xyz = xyz[keep]
    times = intensity = None
    if tname:
        times = relative_seconds(rec["t"][keep] if n_dropped else rec["t"], header_stamp_ns(msg))
    if iname:
        intensity = (rec["i"][keep] if n_dropped else rec["i"]).astype(np.float32)
    return DecodedCloud(xyz, times, intensity, n_dropped)


def _records(msg: Any, wanted: dict[str, Any]) -> np.ndarray:
    """The wanted fields of every point as a 1-D structured array (rows concatenated)."""
    step, row_step = int(msg.point_step), int(msg.row_step)
    height, width = int(msg.height), int(msg.width)
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for key, f in wanted.items():
        code = _DATATYPES.get(int(f.datatype))
        if code is None:
            raise PointCloud2Error(f"field {f.name!r} has unknown datatype {f.datatype}")
        if f.offset + int(code[1]) > step:
            raise PointCloud2Error(
                f"field {f.name!r} (offset {f.offset}) does not fit in point_step {step}")
        formats.append(order + code)
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": list(wanted), "formats": formats, "offsets": offsets,
                      "itemsize": step})
    if height * width == 0:
        return np.zeros(0, dtype=dtype)
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(msg.data, np.uint8)
    if height > 1 and row_step < width * step:
        raise PointCloud2Error(f"row_step {row_step} < width {width} x point_step {step}")
    need = (height - 1) * row_step + width * step
    if data.nbytes < need:
        raise PointCloud2Error(
            f"data holds {data.nbytes} bytes, {height}x{width} points need {need}")
    grid = np.ndarray((height, width), dtype=dtype, buffer=data,
                      strides=(row_step if height > 1 else width * step, step))
    return grid.reshape(-1)


class _Ros1Mcap:
    """Reader for MCAP files of profile "ros1" (rosbags' MCAP reader accepts only "ros2")."""

    def __init__(self, path: Path):
        self.path = path
        self.size = path.stat().st_size
        self.schemas: dict[int, tuple[str, str, str]] = {}  # id -> (msgtype, encoding, text)
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
        with path.open("rb") as fh:
            if fh.read(8) != _MCAP_MAGIC:
                raise Ros2ReaderError("not an MCAP file (bad magic)")
            self.data_start = 8 + 9 + len(self._record(fh, 0x01))
            fh.seek(self.size - 37)
            footer = fh.read(37)
            if len(footer) != 37 or footer[-8:] != _MCAP_MAGIC or footer[0] != 0x02:
                raise Ros2ReaderError("MCAP footer missing (file truncated?)")
            summary_start = struct.unpack_from("<Q", footer, 9)[0]
            counts = None
            if self.data_start <= summary_start < self.size - 37:
                fh.seek(summary_start)
                counts = self._read_summary(fh, self.size - 37)
            if counts is None:
                counts = Counter(cid for cid, _, _ in self._messages(fh, None))
        self.counts = counts

    def _record(self, fh: BinaryIO, expect: int) -> bytes:
        """Content of the record at the current position, which must have opcode `expect`."""
        head = fh.read(9)
        if len(head) != 9 or head[0] != expect:
            raise Ros2ReaderError(f"MCAP record 0x{expect:02x} expected at {fh.tell() - len(head)}")
        return self._content(fh, struct.unpack_from("<Q", head, 1)[0])

    def _content(self, fh: BinaryIO, length: int) -> bytes:
        pos = fh.tell()
        if pos + length > self.size:
            raise Ros2ReaderError(f"MCAP record at offset {pos} runs past the end of the file")
        return fh.read(length)

    def _read_summary(self, fh: BinaryIO, end: int) -> Counter | None:
        """Schemas, channels and per-channel message counts from the summary section."""
        counts = None
        while fh.tell() < end:
            op, length = struct.unpack("<BQ", fh.read(9))
            rec = self._content(fh, length)
            if op in (0x03, 0x04):
                self._add_definition(op, rec)
            elif op == 0x0B:
                (nbytes,) = struct.unpack_from("<I", rec, 42)
                counts = Counter(dict(struct.iter_unpack("<HQ", rec[46:46 + nbytes])))
        return counts

    def _add_definition(self, op: int, rec: bytes) -> None:
        strings = _McapStrings(rec, 2 if op == 0x03 else 4)
        if op == 0x03:
            name, encoding, text = strings.next(), strings.next(), strings.next()
            self.schemas[struct.unpack_from("<H", rec)[0]] = (name, encoding, text)
        else:
            cid, sid = struct.unpack_from("<HH", rec)
            self.channels[cid] = (strings.next(), sid)

    def _messages(self, fh: BinaryIO, channel_ids: set[int] | None
                  ) -> Iterator[tuple[int, int, bytes]]:
        """(channel id, log time ns, ROS1 bytes) of the data section, time-sorted per chunk."""
        fh.seek(self.data_start)
        while True:
            head = fh.read(9)
            if len(head) < 9:
                raise Ros2ReaderError("MCAP data section ends without a DataEnd record (truncated)")
            op, length = struct.unpack("<BQ", head)
            if op in (0x0F, 0x02):
                return
            rec = self._content(fh, length)
            if op == 0x06:
                start, end, size, crc = struct.unpack_from("<QQQI", rec)
                strings = _McapStrings(rec, 28)
                compression = strings.next()
                (nbytes,) = struct.unpack_from("<Q", rec, strings.pos)
                if strings.pos + 8 + nbytes > len(rec):
                    raise Ros2ReaderError("MCAP chunk data runs past the end of its record")
                body = rec[strings.pos + 8:strings.pos + 8 + nbytes]
                inner = mcap_decompress(body, compression, size, crc)
                msgs = list(self._chunk_records(inner, channel_ids))
                yield from sorted(msgs, key=lambda m: m[1])
            elif op == 0x05:
                yield from self._chunk_records(head + rec, channel_ids)
            elif op in (0x03, 0x04):
                self._add_definition(op, rec)

    def _chunk_records(self, buf: bytes, channel_ids: set[int] | None
                       ) -> Iterator[tuple[int, int, bytes]]:
        pos = 0
        while pos < len(buf):
            op, length = struct.unpack_from("<BQ", buf, pos)
            pos += 9
            if pos + length > len(buf):
                raise Ros2ReaderError("MCAP chunk record runs past the end of its chunk")
            if op == 0x03 or op == 0x04:
                self._add_definition(op, buf[pos:pos + length])
            elif op == 0x05:
                cid, _, log_time = struct.unpack_from("<HIQ", buf, pos)
                if channel_ids is None or cid in channel_ids:
                    yield cid, log_time, buf[pos + 22:pos + length]
            pos += length

    def topics(self) -> dict[str, tuple[str, int]]:
        """topic -> (normalized msgtype, message count)."""
        out: dict[str, tuple[str, int]] = {}
        for cid, (topic, sid) in self.channels.items():
            msgtype = normalize_msgtype(self.schemas[sid][0]) if sid in self.schemas else "?"
            count = out.get(topic, ("", 0))[1] + self.counts.get(cid, 0)
            out[topic] = (msgtype, count)
        return out

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        """(deserializer, ROS1 bytes) of every message on the topic, in log-time order."""
        ids = {cid for cid, (t, _) in self.channels.items() if t == topic}
        typestore = get_typestore(Stores.EMPTY)
        if missing := [cid for cid in ids if self.channels[cid][1] not in self.schemas]:
            raise Ros2ReaderError(f"MCAP channel(s) {missing} have no schema")
        for cid in ids:
            name, encoding, text = self.schemas[self.channels[cid][1]]
            if encoding != "ros1msg":
                raise Ros2ReaderError(f"schema encoding {encoding!r} is not ros1msg")
            typestore.register(get_types_from_msg(text, normalize_msgtype(name)))
        msgtype = normalize_msgtype(self.schemas[self.channels[next(iter(ids))][1]][0])
        with self.path.open("rb") as fh:
            for _, _, raw in self._messages(fh, ids):
                yield (lambda r=raw: typestore.deserialize_ros1(r, msgtype)), raw


class _McapStrings:
    """Sequential reader of MCAP length-prefixed (uint32) strings inside one record."""

    def __init__(self, rec: bytes, pos: int):
        self.rec, self.pos = rec, pos

    def next(self) -> str:
        (n,) = struct.unpack_from("<I", self.rec, self.pos)
        self.pos += 4 + n
        return self.rec[self.pos - n:self.pos].decode()


class _AnyBag:
    """rosbags' AnyReader over one ROS1 .bag, ROS2 folder or ROS2-profile .mcap/.db3 file."""

    def __init__(self, path: Path):
        # Bags without embedded definitions (old ROS2 sqlite3) need a default typestore.
        self.reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))

    def topics(self) -> dict[str, tuple[str, int]]:
        return {name: (info.msgtype or "?", info.msgcount)
                for name, info in self.reader.topics.items()}

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        conns = [c for c in self.reader.connections if c.topic == topic]
        for conn, _, raw in self.reader.messages(conns):
            yield (lambda r=raw, t=conn.msgtype: self.reader.deserialize(r, t)), raw


def _mcap_profile(path: Path) -> str:
    """Profile string of an MCAP file's header record ("" when unreadable)."""
    with path.open("rb") as fh:
        head = fh.read(8 + 9 + 4 + 64)
    if len(head) < 21 or head[:8] != _MCAP_MAGIC or head[8] != 0x01:
        return ""
    (n,) = struct.unpack_from("<I", head, 17)
    return head[21:21 + n].decode(errors="replace")


@contextmanager
def _open_bag(path: Path) -> Iterator[_AnyBag | _Ros1Mcap]:
    """An open bag; rosbags' exceptions become InputError naming the file."""
    try:
        if path.is_file() and path.suffix.lower() == ".mcap" and _mcap_profile(path) == "ros1":
            yield _Ros1Mcap(path)
            return
        bag = _AnyBag(path)
        with bag.reader:
            yield bag
    except _BAG_ERRORS as exc:
        problem = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(path, f"unreadable or damaged bag ({problem})") from exc


class RosbagSource:
    """PointCloud2 messages of one topic of a ROS1/ROS2 bag or MCAP file, as Scans.

    index = 0-based message position in the topic; see the module docstring for stamps and times.
    """

    kind = "rosbag"

    def __init__(self, path: str | Path, topic: str | None = None):
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "does not exist")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise InputError(self.path, "folder is not a ROS2 bag (no metadata.yaml)")
        self.name = self.path.stem if self.path.is_file() else self.path.name
        self.ground_truth: np.ndarray | None = None
        with _open_bag(self.path) as bag:
            topics = bag.topics()
        self.topic = self._pick_topic(topics, topic)
        self._count = topics[self.topic][1]
        if self._count == 0:
            raise InputError(self.path, f"topic {self.topic} has no messages")

    def _pick_topic(self, topics: dict[str, tuple[str, int]], topic: str | None) -> str:
        clouds = sorted(t for t, (typ, _) in topics.items() if typ == POINTCLOUD2)
        if topic is not None:
            if topic not in topics:
                have = ", ".join(clouds) or "none"
                raise InputError(self.path, f"no topic {topic} (PointCloud2 topics: {have})")
            if topics[topic][0] != POINTCLOUD2:
                raise InputError(self.path, f"topic {topic} is {topics[topic][0]}, not PointCloud2")
            return topic
        if not clouds:
            listing = ", ".join(f"{t} [{typ}]" for t, (typ, _) in sorted(topics.items()))
            raise InputError(self.path, f"no sensor_msgs/PointCloud2 topic (topics: {listing})")
        if len(clouds) > 1:
            raise InputError(self.path, f"{len(clouds)} sensor_msgs/PointCloud2 topics "
                                        f"({', '.join(clouds)}): pass --topic to choose one")
        return clouds[0]

    def __len__(self) -> int:
        return self._count

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        """Scans start .. start+count-1 of the topic (header stamps, times relative to them)."""
        stop = self._count if count is None else min(self._count, start + count)
        if start >= stop:
            return
        i = -1
        with _open_bag(self.path) as bag:
            for i, (deserialize, _) in enumerate(bag.raw_messages(self.topic)):
                if i >= stop:
                    break
                if i >= start:
                    yield self._scan(i, deserialize())
        if i + 1 < stop:
            raise InputError(self.path, f"{self.topic}: the bag lists {self._count} messages but "
                                        f"only {i + 1} could be read (damaged bag?)")

    def _scan(self, index: int, msg: Any) -> Scan:
        try:
            cloud = decode_pointcloud2(msg)
        except PointCloud2Error as exc:
            raise InputError(self.path, f"{self.topic} message {index}: {exc}") from exc
        total = len(cloud.points) + cloud.n_dropped
        log.debug("%s[%d]: %d of %d points kept (%d NaN/inf or (0,0,0) returns dropped)",
                  self.topic, index, len(cloud.points), total, cloud.n_dropped)
        return Scan(index, header_stamp_ns(msg) * 1e-9, cloud.points, cloud.point_times,
                    cloud.intensity, f"{self.path}:{self.topic}[{index}]")
