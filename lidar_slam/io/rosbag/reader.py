"""The interface every bag reader here implements (BagReader), the errors caught where
rosbags, the decompressors and the deserializers are called, and the helpers the sequential
readers share (a cut-off chunk's decodable prefix, a typestore of the file's own definitions)."""

from __future__ import annotations

import struct
import sys
from bz2 import BZ2Decompressor
from collections.abc import Iterator
from typing import Any

import apsw
from lz4.frame import LZ4FrameDecompressor
from rosbags.highlevel import AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

if sys.version_info >= (3, 14):
    from compression.zstd import ZstdDecompressor, ZstdError
else:  # rosbags depends on the backport below 3.14
    from backports.zstd import ZstdDecompressor, ZstdError


# rosbags 0.11.9 raises its own errors for most damage, but fuzzing truncated/overwritten bags
# also leaked these from its dependencies and asserts: lz4 frame errors (RuntimeError), index
# asserts in the ROS1 reader (AssertionError), huge bogus record lengths (MemoryError,
# OverflowError), zstd and sqlite (apsw) errors, undecodable names (UnicodeDecodeError).
BAG_ERRORS = (
    AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError, TypesysError, ZstdError,
    apsw.Error, AssertionError, RuntimeError, MemoryError, OverflowError, struct.error,
    UnicodeDecodeError, OSError,
)
# ... and, on damaged bytes, also these (an empty read into ord(), a seek past 2**63, bz2's end
# of stream, bogus ids): caught where rosbags, the decompressors and the deserializers are
# called, not around our own decoding, whose bugs they would hide.
LEAKS = (TypeError, ValueError, KeyError, IndexError, EOFError)


class BagReader:
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


def problem(exc: BaseException) -> str:
    """The first line of an error's message (its type when it has none)."""
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def decompress_prefix(data: bytes, compression: str) -> bytes:
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


def typestore_of(definitions: dict[str, tuple[str, str]], fallback: Stores | None) -> Any:
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


