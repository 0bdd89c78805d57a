"""Ouster pcap + sensor metadata JSON through ouster-sdk; the only module that imports ouster.sdk.

ouster-sdk parses the packets (PcapPacketSource), batches the lidar packets into frames
(FrameBatcher) and projects them (XYZLut): nothing here decodes a packet.

- Points are XYZLut's, in the metadata's *sensor frame* (lidar_to_sensor_transform applied): this
  is the "lidar frame" of the run. The frames stay staggered (each column one measurement block),
  so every point keeps its column's timestamp; destaggering would only reorder the image.
- `Scan.stamp_s` is the earliest valid column timestamp of the frame (the sweep's start, on the
  sensor clock of `timestamp_mode`), and `point_times` are the column timestamps minus it, in
  [0, ~0.1] s (integer nanoseconds subtracted first).
- The IMU packets are on the same clock. ouster-sdk's ImuPacket.accel() / gyro() already give m/s^2
  and rad/s: the legacy profile's g and deg/s are scaled in the SDK (9.80665, pi/180), so they
  are not scaled again here. The IMU's mounting is the metadata's imu_to_sensor_transform (mm),
  T_lidar_imu with the translation in metres.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.imu_gnss import imu_from_rows
from lidar_slam.io.inertial_input import Carried, CarriedStreams
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

# ouster-sdk's own requirements pin rosbags 0.9 (the bag reader needs 0.10+): see pyproject.toml
INSTALL_HINT = "pip install 'lidar-slam[pcap]' && pip install --no-deps 'ouster-sdk==1.0.1'"
COLUMN_VALID = 0x1  # bit 0 of a column's status: the measurement block is valid (sensor docs)


def _sdk(path: Path):
    """ouster.sdk's core and pcap modules, or the one line saying how to install them."""
    try:
        from ouster.sdk import core, pcap
    except ImportError:
        raise InputError(path, f"reading an Ouster pcap needs ouster-sdk ({INSTALL_HINT})"
                         ) from None
    return core, pcap


def metadata_path(pcap_path: Path, meta: Path | None) -> Path:
    """The sensor metadata JSON of a pcap: `meta` when given, else the same stem .json beside it."""
    if meta is not None:
        if not meta.is_file():
            raise InputError(meta, "sensor metadata file does not exist")
        return meta
    beside = pcap_path.with_suffix(".json")
    if not beside.is_file():
        raise InputError(pcap_path, f"no sensor metadata: expected {beside.name} beside it, or "
                                    "give it with --meta FILE.json")
    return beside


def read_sensor_info(meta: Path):
    """ouster-sdk's SensorInfo from a metadata JSON (InputError naming the file when it is not)."""
    core, _ = _sdk(meta)
    try:
        text = meta.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(meta, f"cannot read the sensor metadata ({exc})") from None
    try:
        return core.SensorInfo(text)
    except (RuntimeError, ValueError) as exc:
        raise InputError(meta, f"not Ouster sensor metadata ({' '.join(str(exc).split())[:120]})"
                         ) from None


def _t_lidar_imu(info) -> np.ndarray:
    """T_lidar_imu (4x4, m) from the metadata's imu_to_sensor_transform (translation in mm)."""
    T = np.array(info.imu_to_sensor_transform, dtype=np.float64)
    T[:3, 3] *= 1e-3
    return T


class OusterPcapSource(CarriedStreams):
    """The frames and IMU packets of an Ouster pcap (see the module docstring).

    Opening reads the file once (frame stamps and the IMU); `scans()` reads it again for the
    points. Frames with no valid column, or whose stamp does not increase, are dropped and
    counted in `input_notes`.
    """

    kind, topic = "ouster_pcap", None

    def __init__(self, path: Path, meta: Path | None = None, cut_bytes: int = 0):
        self.path = path
        self.name = path.stem
        self.meta_path = metadata_path(path, meta)
        self.info = read_sensor_info(self.meta_path)
        self.ground_truth = None
        self._notes = {"frames_without_valid_columns": 0, "frames_out_of_order": 0,
                       "incomplete_frames": 0, "cut_bytes_missing": cut_bytes}
        self._frame_ids: list[int] = []
        stamps: list[float] = []
        imu_rows: list[np.ndarray] = []
        for item in self._packets_and_frames():
            if isinstance(item, np.ndarray):
                imu_rows.append(item)
                continue
            stamp_ns = self._stamp_ns(item)
            if stamp_ns is None:
                self._notes["frames_without_valid_columns"] += 1
            elif stamps and stamp_ns * 1e-9 <= stamps[-1]:
                self._notes["frames_out_of_order"] += 1
            else:
                stamps.append(stamp_ns * 1e-9)
                self._frame_ids.append(item.frame_id)
                self._notes["incomplete_frames"] += not item.complete()
        if not stamps:
            raise InputError(path, f"no lidar frame matching {self.meta_path.name} (another "
                                   "sensor's or another session's metadata?)")
        self.stamps = np.array(stamps)
        dropped = {k: v for k, v in self._notes.items() if v and k != "cut_bytes_missing"}
        if dropped:
            log.warning("%s: %s", path, ", ".join(f"{v} {k.replace('_', ' ')}"
                                                   for k, v in dropped.items()))
        self.sensor_streams = self._streams(imu_rows)

    def _streams(self, imu_rows: list[np.ndarray]) -> Carried:
        T = _t_lidar_imu(self.info)
        no_gnss = ("gnss", f"{self.path}: Ouster GNSS (NMEA) is not read")
        if len(imu_rows) == 0 or sum(len(r) for r in imu_rows) < 2:
            return Carried(T_lidar_imu=T, why_not=(("imu", f"{self.path}: no IMU packets"),
                                                   no_gnss))
        imu = imu_from_rows(f"{self.path} (IMU packets)", np.concatenate(imu_rows))
        return Carried(imu=imu, T_lidar_imu=T, why_not=(no_gnss,))

    @property
    def input_notes(self) -> dict[str, int]:
        """Frames dropped (no valid column, stamp not increasing), frames with lost packets and
        the bytes a cut last packet lacks."""
        return {k: v for k, v in self._notes.items() if v}

    def __len__(self) -> int:
        return len(self.stamps)

    def _packets_and_frames(self, imu: bool = True) -> Iterator:
        """Every finished LidarFrame and (with `imu`), per IMU packet, its (M, 7) imu.csv rows, in
        file order."""
        core, pcap = _sdk(self.path)
        try:
            source = pcap.PcapPacketSource(str(self.path), sensor_info=[self.info])
        except RuntimeError as exc:  # e.g. "truncated dump file" (a cut pcap header)
            raise InputError(self.path, f"not a readable pcap ({exc})") from None
        batcher = core.FrameBatcher(self.info)
        frame = core.LidarFrame(self.info)
        try:
            for _, packet in source:
                if isinstance(packet, core.ImuPacket):
                    if imu:
                        yield _imu_rows(packet)
                elif isinstance(packet, core.LidarPacket) and batcher.batch(packet, frame):
                    yield frame
                    frame = core.LidarFrame(self.info)
        except RuntimeError as exc:
            raise InputError(self.path, f"cannot read the pcap ({exc})") from None
        finally:
            source.close()

    @staticmethod
    def _stamp_ns(frame) -> int | None:
        valid = (frame.status & COLUMN_VALID).astype(bool)
        return int(frame.timestamp[valid].min()) if valid.any() else None

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self) if count is None else min(len(self), start + count)
        if start >= stop:
            return
        core, _ = _sdk(self.path)
        lut = core.XYZLut(self.info)
        index, last = 0, -np.inf
        for item in self._packets_and_frames(imu=False):
            stamp_ns = self._stamp_ns(item)
            if stamp_ns is None or stamp_ns * 1e-9 <= last:
                continue
            last = stamp_ns * 1e-9
            if index >= start:
                yield self._scan(index, item, stamp_ns, lut)
            index += 1
            if index >= stop:
                return

    def _scan(self, index: int, frame, stamp_ns: int, lut) -> Scan:
        valid = (frame.status & COLUMN_VALID).astype(bool)
        rng = frame.field("RANGE")
        keep = (rng > 0) & valid[None, :]
        points = lut(frame)[keep]
        col_ns = np.broadcast_to(frame.timestamp.astype(np.int64), rng.shape)[keep]
        times = (col_ns - stamp_ns).astype(np.float64) * 1e-9
        names = frame.fields
        inten_field = next((f for f in ("SIGNAL", "REFLECTIVITY") if f in names), None)
        intensity = (frame.field(inten_field)[keep].astype(np.float32)
                     if inten_field is not None else None)
        return Scan(index, stamp_ns * 1e-9, np.ascontiguousarray(points, dtype=np.float64),
                    times, intensity, f"{self.path}#frame{frame.frame_id}")


def _imu_rows(packet) -> np.ndarray:
    """(M, 7) rows stamp_s, wx, wy, wz (rad/s), ax, ay, az (m/s^2) of one IMU packet: its
    measurements' timestamps (ns, the lidar's clock), ouster-sdk's gyro() and accel() (already
    SI for every IMU profile: the legacy profile's g and deg/s are scaled in the SDK)."""
    stamp_ns = np.asarray(packet.timestamp(), dtype=np.int64)
    rows = np.column_stack([stamp_ns * 1e-9, np.asarray(packet.gyro(), dtype=np.float64),
                            np.asarray(packet.accel(), dtype=np.float64)])
    return rows[stamp_ns > 0]  # a measurement slot the sensor did not fill has no timestamp
