"""A sensor pcap: Ouster (with its metadata JSON) or Velodyne, told apart without decoding, and
its records checked once for a cut at the end (dpkt's reader, as velodyne-decoder's)."""

from __future__ import annotations

import logging
from pathlib import Path

from lidar_slam.errors import InputError
from lidar_slam.io.velodyne_pcap import INSTALL_HINT, VelodynePcapSource, looks_like_velodyne

log = logging.getLogger(__name__)


class _ShortReads:
    """A binary file that remembers a read returning less than was asked (a record cut short):
    dpkt's reader then silently yields a short packet, and the decoders drop it unsaid."""

    def __init__(self, fh):
        self.fh, self.name, self.missing = fh, fh.name, 0

    def read(self, n: int) -> bytes:
        data = self.fh.read(n)
        if 0 < len(data) < n:
            self.missing = n - len(data)
        return data


def cut_bytes(path: Path) -> int:
    """How many bytes a cut last record of a pcap lacks (0 for a whole file), warned about:
    ouster-sdk and velodyne-decoder both stop quietly at a cut, keeping the packets before it.
    InputError when the file is not a pcap (its header cut or missing)."""
    try:
        import dpkt
    except ImportError:
        raise InputError(path, f"reading a pcap needs dpkt ({INSTALL_HINT})") from None
    try:
        with path.open("rb") as fh:
            reads = _ShortReads(fh)
            for _ in dpkt.pcap.Reader(reads):
                pass
    except (dpkt.dpkt.NeedData, dpkt.dpkt.UnpackError, ValueError) as exc:
        raise InputError(path, f"not a readable pcap ({' '.join(str(exc).split())[:100]})"
                         ) from None
    except OSError as exc:
        raise InputError(path, f"cannot read the pcap ({exc.strerror or exc})") from None
    if reads.missing:
        log.warning("%s: its last packet is cut (%d bytes missing: a recording cut short?); "
                    "the complete packets before it are used", path, reads.missing)
    return reads.missing


def open_pcap(path: Path, meta: Path | None = None):
    """An OusterPcapSource when there is sensor metadata (`meta`, or the same stem .json beside
    the pcap), else a VelodynePcapSource when its packets are Velodyne's; otherwise the one line
    saying the Ouster metadata is missing."""
    from lidar_slam.io.ouster_pcap import OusterPcapSource

    cut = cut_bytes(path)
    if meta is not None or path.with_suffix(".json").is_file():
        return OusterPcapSource(path, meta, cut_bytes=cut)
    if looks_like_velodyne(path):
        return VelodynePcapSource(path, cut_bytes=cut)
    raise InputError(path, f"no sensor metadata: expected {path.with_suffix('.json').name} "
                           "beside it (an Ouster pcap), or give it with --meta FILE.json; its "
                           "packets are not Velodyne's")
