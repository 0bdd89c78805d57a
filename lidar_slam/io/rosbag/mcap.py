"""The sequential MCAP reader: profile "ros1" files (which rosbags' MCAP reader refuses) and the
complete messages of an MCAP file cut short."""

from __future__ import annotations

import logging
import struct
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2.storage_mcap import decompress as mcap_decompress
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


MCAP_MAGIC = b"\x89MCAP0\r\n"


class McapScan(BagReader):
    """Sequential MCAP reader, for what rosbags' MCAP reader refuses: profile "ros1" files, and
    the complete messages of a file cut short (no footer or summary, the last chunk cut off:
    a crashed recorder). Messages of a chunk are yielded in log-time order."""

    def __init__(self, path: Path):
        self.path = path
        self.size = path.stat().st_size
        self.schemas: dict[int, tuple[str, str, str]] = {}  # id -> (msgtype, encoding, text)
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
        with path.open("rb") as fh:
            if fh.read(8) != MCAP_MAGIC:
                raise Ros2ReaderError("not an MCAP file (bad magic)")
            header = self._record(fh, 0x01)
            self.profile = McapStrings(header, 0).next()
            self.data_start = 8 + 9 + len(header)
            fh.seek(max(self.data_start, self.size - 37))
            footer = fh.read(37)
            self.truncated = not (len(footer) == 37 and footer[-8:] == MCAP_MAGIC
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
        strings = McapStrings(rec, 2 if op == 0x03 else 4)
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
                strings = McapStrings(rec, 28)
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
            strings = McapStrings(rec, 28)
            compression = strings.next()
            body = rec[strings.pos + 8:strings.pos + 8 + struct.unpack_from("<Q", rec,
                                                                            strings.pos)[0]]
            inner = decompress_prefix(body, compression)
            msgs = list(self._chunk_records(inner, channel_ids, partial=True))
        except (*BAG_ERRORS, *LEAKS) as exc:
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
        typestore = typestore_of(definitions, None if ros1 else Stores.LATEST)
        deserialize = typestore.deserialize_ros1 if ros1 else typestore.deserialize_cdr
        msgtype = normalize_msgtype(self.schemas[self.channels[next(iter(ids))][1]][0])
        with self.path.open("rb") as fh:
            for _, _, raw in self._messages(fh, ids):
                yield (lambda r=raw: deserialize(r, msgtype)), raw


class McapStrings:
    """Sequential reader of MCAP length-prefixed (uint32) strings inside one record."""

    def __init__(self, rec: bytes, pos: int):
        self.rec, self.pos = rec, pos

    def next(self) -> str:
        (n,) = struct.unpack_from("<I", self.rec, self.pos)
        self.pos += 4 + n
        if self.pos > len(self.rec):
            raise Ros2ReaderError("MCAP string runs past the end of its record")
        return self.rec[self.pos - n:self.pos].decode()


def mcap_profile(path: Path) -> str:
    """Profile string of an MCAP file's header record ("" when unreadable)."""
    with path.open("rb") as fh:
        head = fh.read(8 + 9 + 4 + 64)
    if len(head) < 21 or head[:8] != MCAP_MAGIC or head[8] != 0x01:
        return ""
    (n,) = struct.unpack_from("<I", head, 17)
    return head[21:21 + n].decode(errors="replace")


