"""sensor_msgs/PointCloud2 topics of ROS bags as Scans; the only module that imports rosbags.

Containers: a ROS1 `.bag`, a ROS2 bag folder (metadata.yaml with .db3 or .mcap storage), and a
standalone `.mcap` of profile "ros2" (all through rosbags' AnyReader) or "ros1" (which rosbags'
MCAP reader rejects, so `_McapScan` below walks the records and deserializes with a rosbags
typestore built from the file's ros1msg schemas).

A recording cut short (a crashed recorder: no mcap footer, no ROS1 index, a .db3 shorter than
its header says), which rosbags refuses, is read up to its last complete message by the
sequential readers here (`_McapScan`, `_Ros1BagScan`, `_Db3Scan`), with one warning.

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
from bz2 import BZ2Decompressor
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import apsw
import numpy as np
from lz4.frame import LZ4FrameDecompressor
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1.reader import Header as Ros1Header
from rosbags.rosbag1.reader import RecordType, decompressors
from rosbags.rosbag1.reader import normalize as ros1_normalize
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2.storage_mcap import decompress as mcap_decompress
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.msg import normalize_msgtype

from lidar_slam.errors import InputError

if sys.version_info >= (3, 14):
    from compression.zstd import ZstdDecompressor, ZstdError
else:  # rosbags depends on the backport below 3.14
    from backports.zstd import ZstdDecompressor, ZstdError
from lidar_slam.io.imu_gnss import GnssFixes, ImuSamples, gnss_from_rows, imu_from_rows
from lidar_slam.io.point_times import relative_seconds
from lidar_slam.io.pointcloud import INTENSITY_FIELDS, TIME_FIELDS
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
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
# ... and, on damaged bytes, also these (an empty read into ord(), a seek past 2**63, bz2's end
# of stream, bogus ids): caught where rosbags, the decompressors and the deserializers are
# called, not around our own decoding, whose bugs they would hide.
_LEAKS = (TypeError, ValueError, KeyError, IndexError, EOFError)


_warned_intensity: list[bool] = []  # once per process, as point_times warns


class PointCloud2Error(ValueError):
    """A PointCloud2 message whose layout cannot be decoded (missing x/y/z, short data, ...)."""


class DecodedCloud(NamedTuple):
    """One decoded PointCloud2, invalid returns removed.

    points (N,3) float64 m in the message frame; point_times (N,) float64 s relative to the
    header stamp, or None; intensity (N,) float32, or None (none, or not all finite);
    n_dropped = NaN/inf or (0,0,0) returns.
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
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, refused below
            intensity = (rec["i"][keep] if n_dropped else rec["i"]).astype(np.float32)
        if not np.isfinite(intensity).all():
            if not _warned_intensity:
                _warned_intensity.append(True)
                log.warning("PointCloud2 %s field has NaN/inf values (or beyond float32); such "
                            "scans are used without intensity", iname)
            intensity = None
    return DecodedCloud(xyz, times, intensity, n_dropped)


def _records(msg: Any, wanted: dict[str, Any]) -> np.ndarray:
    """The wanted fields of every point as a 1-D structured array (rows concatenated)."""
    step, row_step = int(msg.point_step), int(msg.row_step)
    height, width = int(msg.height), int(msg.width)
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for f in wanted.values():
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


def _decompress_prefix(data: bytes, compression: str) -> bytes:
    """As much of a cut-off compressed chunk as decodes (the blocks before the cut)."""
    if compression in ("", "none"):
        return data
    if compression == "lz4":
        return LZ4FrameDecompressor().decompress(data)
    if compression == "zstd":
        return ZstdDecompressor().decompress(data)
    if compression == "bz2":
        return BZ2Decompressor().decompress(data)
    raise Ros2ReaderError(f"unsupported chunk compression {compression!r}")


def _typestore(definitions: dict[str, tuple[str, str]], fallback: Stores | None) -> Any:
    """A typestore of the file's own definitions (msgtype -> (encoding, text)), or, when one is
    missing or not in .msg form, rosbags' `fallback` store (as AnyReader's default)."""
    if definitions and all(enc in ("ros1msg", "ros2msg") for enc, _ in definitions.values()):
        typestore = get_typestore(Stores.EMPTY)
        for msgtype, (_, text) in definitions.items():
            typestore.register(get_types_from_msg(text, msgtype))
        return typestore
    if fallback is None:
        raise Ros2ReaderError(f"no usable message definition for {', '.join(definitions)}")
    return get_typestore(fallback)


class _BagReader:
    """What RosbagSource needs of an open bag; `recovered` is the number of complete messages
    read from a recording cut short (None when the file is whole)."""

    recovered: int | None = None

    def close(self) -> None:
        return None

    def topics(self) -> dict[str, tuple[str, int]]:
        """topic -> (normalized msgtype, message count)."""
        raise NotImplementedError

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        """(deserializer, raw bytes) of every message on the topic."""
        raise NotImplementedError


class _McapScan(_BagReader):
    """Sequential MCAP reader, for what rosbags' MCAP reader refuses: profile "ros1" files, and
    the complete messages of a file cut short (no footer or summary, the last chunk cut off:
    a crashed recorder). Messages of a chunk are yielded in log-time order."""

    def __init__(self, path: Path):
        self.path = path
        self.size = path.stat().st_size
        self.schemas: dict[int, tuple[str, str, str]] = {}  # id -> (msgtype, encoding, text)
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
        with path.open("rb") as fh:
            if fh.read(8) != _MCAP_MAGIC:
                raise Ros2ReaderError("not an MCAP file (bad magic)")
            header = self._record(fh, 0x01)
            self.profile = _McapStrings(header, 0).next()
            self.data_start = 8 + 9 + len(header)
            fh.seek(max(self.data_start, self.size - 37))
            footer = fh.read(37)
            self.truncated = not (len(footer) == 37 and footer[-8:] == _MCAP_MAGIC
                                  and footer[:9] == b"\x02\x14" + bytes(7))
            counts = None
            if not self.truncated:
                summary_start = struct.unpack_from("<Q", footer, 9)[0]
                if self.data_start <= summary_start < self.size - 37:
                    fh.seek(summary_start)
                    counts = self._read_summary(fh, self.size - 37)
            if counts is None:
                counts = Counter(cid for cid, _, _ in self._messages(fh, None))
        self.counts = counts
        if self.truncated:
            self.recovered = sum(counts.values())

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
        """(channel id, log time ns, raw message) of the data section; in a truncated file, up
        to the last complete message (a record cut off ends the walk, a chunk cut off gives the
        messages of its decodable part)."""
        fh.seek(self.data_start)
        while True:
            head = fh.read(9)
            if len(head) < 9:
                if self.truncated:
                    return
                raise Ros2ReaderError("MCAP data section ends without a DataEnd record (truncated)")
            op, length = struct.unpack("<BQ", head)
            if op in (0x0F, 0x02):
                return
            if self.truncated and fh.tell() + length > self.size:
                if op == 0x06:
                    yield from self._chunk_prefix(fh.read(), channel_ids)
                return
            rec = self._content(fh, length)
            if op == 0x06:
                _, _, size, crc = struct.unpack_from("<QQQI", rec)
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

    def _chunk_prefix(self, rec: bytes, channel_ids: set[int] | None
                      ) -> Iterator[tuple[int, int, bytes]]:
        """The complete messages in the decodable part of a chunk record cut off by the end of
        the file (no size or CRC to check them against: the compressed stream itself is)."""
        try:
            strings = _McapStrings(rec, 28)
            compression = strings.next()
            body = rec[strings.pos + 8:strings.pos + 8 + struct.unpack_from("<Q", rec,
                                                                            strings.pos)[0]]
            inner = _decompress_prefix(body, compression)
            msgs = list(self._chunk_records(inner, channel_ids, partial=True))
        except (*_BAG_ERRORS, *_LEAKS) as exc:
            log.debug("%s: the chunk cut off at the end is unreadable (%s)", self.path, exc)
            return
        yield from sorted(msgs, key=lambda m: m[1])

    def _chunk_records(self, buf: bytes, channel_ids: set[int] | None, partial: bool = False
                       ) -> Iterator[tuple[int, int, bytes]]:
        pos = 0
        while pos + (9 if partial else 0) < len(buf):
            op, length = struct.unpack_from("<BQ", buf, pos)
            pos += 9
            if pos + length > len(buf):
                if partial:
                    return
                raise Ros2ReaderError("MCAP chunk record runs past the end of its chunk")
            if op == 0x03 or op == 0x04:
                self._add_definition(op, buf[pos:pos + length])
            elif op == 0x05:
                cid, _, log_time = struct.unpack_from("<HIQ", buf, pos)
                if channel_ids is None or cid in channel_ids:
                    yield cid, log_time, buf[pos + 22:pos + length]
            pos += length

    def topics(self) -> dict[str, tuple[str, int]]:
        out: dict[str, tuple[str, int]] = {}
        for cid, (topic, sid) in self.channels.items():
            msgtype = normalize_msgtype(self.schemas[sid][0]) if sid in self.schemas else "?"
            count = out.get(topic, ("", 0))[1] + self.counts.get(cid, 0)
            out[topic] = (msgtype, count)
        return out

    def raw_messages(self, topic: str) -> Iterator[tuple[Any, bytes]]:
        """(deserializer, raw bytes) of every message on the topic, in log-time order."""
        ids = {cid for cid, (t, _) in self.channels.items() if t == topic}
        if missing := [cid for cid in ids if self.channels[cid][1] not in self.schemas]:
            raise Ros2ReaderError(f"MCAP channel(s) {missing} have no schema")
        ros1 = self.profile == "ros1"
        definitions = {normalize_msgtype(name): (encoding, text) for name, encoding, text
                       in (self.schemas[self.channels[cid][1]] for cid in ids)}
        if ros1 and (bad := {e for e, _ in definitions.values()} - {"ros1msg"}):
            raise Ros2ReaderError(f"schema encoding {bad.pop()!r} is not ros1msg")
        typestore = _typestore(definitions, None if ros1 else Stores.LATEST)
        deserialize = typestore.deserialize_ros1 if ros1 else typestore.deserialize_cdr
        msgtype = normalize_msgtype(self.schemas[self.channels[next(iter(ids))][1]][0])
        with self.path.open("rb") as fh:
            for _, _, raw in self._messages(fh, ids):
                yield (lambda r=raw: deserialize(r, msgtype)), raw


class _McapStrings:
    """Sequential reader of MCAP length-prefixed (uint32) strings inside one record."""

    def __init__(self, rec: bytes, pos: int):
        self.rec, self.pos = rec, pos

    def next(self) -> str:
        (n,) = struct.unpack_from("<I", self.rec, self.pos)
        self.pos += 4 + n
        if self.pos > len(self.rec):
            raise Ros2ReaderError("MCAP string runs past the end of its record")
        return self.rec[self.pos - n:self.pos].decode()


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


class _Ros1BagScan(_BagReader):
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
                        inner = (_decompress_prefix(data, compression) if not complete
                                 else decompressors[compression](data))
                        yield from self._records(inner, topic)
                    elif complete:
                        yield from self._record(header, data, topic)
                    if not complete:
                        return
            except (*_BAG_ERRORS, *_LEAKS) as exc:
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
        typestore = _typestore(definitions, None)
        msgtype = next(iter(definitions))
        for _, raw in self._messages(topic):
            yield (lambda r=raw: typestore.deserialize_ros1(r, msgtype)), raw


class _Db3Scan(_BagReader):
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
        typestore = _typestore({msgtype: self.definitions[msgtype]}
                               if msgtype in self.definitions else {}, Stores.LATEST)
        if msgtype not in typestore.fielddefs:
            raise Ros2ReaderError(f"no message definition for {msgtype}")
        for _, raw in self._rows(ids):
            yield (lambda r=raw: typestore.deserialize_cdr(r, msgtype)), raw


class _AnyBag(_BagReader):
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


def _mcap_profile(path: Path) -> str:
    """Profile string of an MCAP file's header record ("" when unreadable)."""
    with path.open("rb") as fh:
        head = fh.read(8 + 9 + 4 + 64)
    if len(head) < 21 or head[:8] != _MCAP_MAGIC or head[8] != 0x01:
        return ""
    (n,) = struct.unpack_from("<I", head, 17)
    return head[21:21 + n].decode(errors="replace")


def _recovery_reader(path: Path) -> _BagReader | None:
    """A reader of the complete messages of a recording rosbags refuses (cut short, no index),
    or None when the file is not one (or not even that can be read)."""
    if path.is_dir():
        files = [f for f in path.iterdir() if f.suffix.lower() in (".db3", ".mcap")]
        if len(files) != 1:
            return None
        path = files[0]
    suffix = path.suffix.lower()
    kinds = {".bag": _Ros1BagScan, ".mcap": _McapScan, ".db3": _Db3Scan}
    if suffix not in kinds:
        return None
    try:
        reader = kinds[suffix](path)
    except (*_BAG_ERRORS, *_LEAKS) as exc:
        log.debug("%s: no message recoverable (%s)", path, exc)
        return None
    return reader if reader.recovered is not None else None


def _problem(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _open_reader(path: Path) -> _BagReader:
    """The reader for a bag: rosbags' AnyReader, ours for ros1-profile mcap, and, when rosbags
    refuses a recording cut short, ours of its complete messages (`recovered` set)."""
    try:
        if path.is_file() and path.suffix.lower() == ".mcap" and _mcap_profile(path) == "ros1":
            return _McapScan(path)
        try:
            return _AnyBag(path)
        except (*_BAG_ERRORS, *_LEAKS) as exc:
            recovered = _recovery_reader(path)
            if recovered is None:
                raise
            if recovered.recovered == 0:
                recovered.close()
                raise InputError(path, "truncated or damaged recording: not one complete "
                                       f"message in it ({_problem(exc)})") from exc
            return recovered
    except (*_BAG_ERRORS, *_LEAKS) as exc:
        raise InputError(path, f"unreadable or damaged bag ({_problem(exc)})") from exc


def _topic_messages(bag: _BagReader, topic: str) -> Iterator[Any]:
    """The deserializers of a topic's messages, in order (see _LEAKS)."""
    try:
        for deserialize, _ in bag.raw_messages(topic):
            yield deserialize
    except _LEAKS as exc:
        raise Ros2ReaderError(f"{type(exc).__name__}: {exc}") from exc


@contextmanager
def open_bag(path: Path) -> Iterator[_BagReader]:
    """An open bag; the errors of rosbags and of the readers here become InputError naming
    the file."""
    bag = _open_reader(path)
    try:
        yield bag
    except _BAG_ERRORS as exc:
        raise InputError(path, f"unreadable or damaged bag ({_problem(exc)})") from exc
    finally:
        bag.close()


class RosbagSource:
    """PointCloud2 messages of one topic of a ROS1/ROS2 bag or MCAP file, as Scans.

    index = 0-based position among the scans kept: a message whose header stamp is not after
    the previous kept one (a duplicate or a step back) is dropped, so stamps strictly increase
    and `len`, `scans(start, count)` and a resumed run all count the same scans. A recording cut
    short gives its complete messages. Both are counted in `input_notes` and logged once.
    See the module docstring for stamps and times.
    """

    kind = "rosbag"
    sensor_streams = None  # the IMU / GNSS topics are read by io.inertial_input.load_inertial

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
        self.topic = self._pick_topic(topics, topic)
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
            for n_read, deserialize in enumerate(_topic_messages(bag, self.topic), 1):
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
            for i, deserialize in enumerate(_topic_messages(bag, self.topic)):
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
        except (*_BAG_ERRORS, *_LEAKS) as exc:
            raise InputError(self.path, f"{self.topic} message {position} cannot be "
                                        f"deserialized ({_problem(exc)})") from exc

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


def _pick_typed_topic(path: Path, topics: dict[str, tuple[str, int]], topic: str | None,
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


def _typed_rows(path: Path, topic: str | None, msgtype: str, flag: str, row: Any
                ) -> tuple[str | None, np.ndarray]:
    """The picked topic and row(message) of each of its messages as an (N, k) array (None and
    an empty array when there is no such topic); messages are not kept (an hour of IMU at
    200 Hz is 720k of them)."""
    with open_bag(path) as bag:
        picked = _pick_typed_topic(path, bag.topics(), topic, msgtype, flag)
        if picked is None:
            return None, np.empty((0, 0))
        rows = []
        for position, deserialize in enumerate(_topic_messages(bag, picked)):
            try:
                msg = deserialize()
            except (*_BAG_ERRORS, *_LEAKS) as exc:
                raise InputError(path, f"{picked} message {position} cannot be deserialized "
                                       f"({_problem(exc)})") from exc
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
