"""Velodyne pcap through velodyne-decoder; the only module that imports velodyne_decoder.

velodyne-decoder reads the pcap (its dpkt-based `util.iter_pcap`), decodes the data packets into
sweeps (`StreamDecoder`: VLP-16, VLP-32, HDL-32E, HDL-64E with the calibration it reads from the
stream, VLS-128, Alpha Prime) and parses the position (telemetry) packets' NMEA sentence
(`TelemetryPacket`): nothing here decodes a packet.

- `Scan.stamp_s` is the decoder's device stamp of the sweep (the sensor's time since the top of
  the hour, the hour taken from the capture clock): GNSS time when the sensor's PPS is locked. The
  decoder stamps a sweep at its *last* packet, so `point_times` (its per-point `time`, already
  relative to that stamp) lie in [~-0.1, ~0] s, as a ROS Velodyne cloud stamped at the sweep end.
- GNSS: one fix per distinct NMEA sentence with a fix, stamped with the sentence's UTC time
  (the instant the position was measured). That is the lidar's clock only when its PPS is locked;
  otherwise a warning says so (the fixes are then used only if they overlap the scans, or with
  gnss.time_offset_s). RMC carries no altitude and no sentence carries an accuracy: the sigmas
  below are assumed (and said in summary.json's gnss source).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.imu_gnss import gnss_from_rows
from lidar_slam.io.inertial_input import Carried, CarriedStreams
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'lidar-slam[pcap]'"

# An NMEA fix carries no accuracy: 1-sigma of a standalone (uncorrected) GPS fix, m. RMC has
# no altitude at all (velodyne-decoder gives 0): the vertical sigma then says "unknown".
NMEA_SIGMA_H_M = 5.0
NMEA_SIGMA_V_M = 10.0
NO_ALTITUDE_SIGMA_V_M = 1.0e4


def _vd(path: Path):
    """The velodyne_decoder module, or the one line saying how to install it."""
    try:
        import velodyne_decoder
    except ImportError:
        raise InputError(path, f"reading a Velodyne pcap needs velodyne-decoder ({INSTALL_HINT})"
                         ) from None
    return velodyne_decoder


def looks_like_velodyne(path: Path, n_packets: int = 50) -> bool:
    """Whether the first UDP payloads of a pcap hold Velodyne data packets (1206 bytes); False
    when velodyne-decoder is not installed (then it cannot be read as one anyway)."""
    try:
        vd = _vd(path)
    except InputError:
        return False
    sizes = [len(data) for _, (_, data) in zip(range(n_packets), _packets(vd, path))]
    return vd.PACKET_SIZE in sizes


def _packets(vd, path: Path) -> Iterator[tuple[float, bytes]]:
    """(capture stamp s, UDP payload) of every packet, through velodyne-decoder's pcap reader
    (io.pcap.cut_bytes has checked the file: a cut record at its end just ends the packets)."""
    with path.open("rb") as fh:
        yield from vd.util.iter_pcap(fh)


class VelodynePcapSource(CarriedStreams):
    """The sweeps and position packets of a Velodyne pcap (see the module docstring).

    Opening decodes the file once (sweep stamps, GNSS); `scans()` decodes it again for the points.
    Sweeps whose stamp does not increase are dropped and counted in `input_notes`.
    """

    kind, topic = "velodyne_pcap", None

    def __init__(self, path: Path, cut_bytes: int = 0):
        self.path = path
        self.name = path.stem
        self.ground_truth = None
        self._notes = {"sweeps_out_of_order": 0, "cut_bytes_missing": cut_bytes}
        self.model: str | None = None
        stamps: list[float] = []
        telemetry = []
        for item in self._sweeps_and_telemetry():
            if isinstance(item, tuple):
                stamp = float(item[0].device)
                if stamps and stamp <= stamps[-1]:
                    self._notes["sweeps_out_of_order"] += 1
                    continue
                stamps.append(stamp)
            else:
                telemetry.append(item)
        if not stamps:
            raise InputError(path, "no Velodyne sweep in the pcap")
        self.stamps = np.array(stamps)
        gnss, why = _gnss(path, telemetry) if telemetry else (None, f"{path}: no position "
                                                                        "packets")
        self.sensor_streams = Carried(gnss=gnss, why_not=(
            ("imu", f"{path}: no IMU is read from a Velodyne pcap"), ("gnss", why)))

    @property
    def input_notes(self) -> dict[str, int]:
        """Sweeps dropped because their stamp did not increase; bytes a cut last packet lacks."""
        return {k: v for k, v in self._notes.items() if v}

    def __len__(self) -> int:
        return len(self.stamps)

    def _sweeps_and_telemetry(self) -> Iterator:
        """(TimePair, (N, 8) float32 points) per sweep and a TelemetryPacket per position packet,
        in file order (velodyne-decoder's own read_pcap loop, with the position packets kept)."""
        vd = _vd(self.path)
        config = vd.Config()
        try:  # HDL-64E: model and calibration from the stream's status bytes, as read_pcap does
            config.model, config.calibration = vd.hdl64e.detect_hdl64e(str(self.path))
        except ValueError as exc:
            raise InputError(self.path, f"HDL-64E data whose model or calibration cannot be "
                                        f"read ({exc})") from None
        decoder = vd.StreamDecoder(config)
        try:
            for host_stamp, data in _packets(vd, self.path):
                if len(data) == vd.PACKET_SIZE:
                    result = decoder.decode(host_stamp, data, False)
                    if result is not None:
                        yield tuple(result)
                elif len(data) == vd.TELEMETRY_PACKET_SIZE:
                    yield vd.TelemetryPacket(data)
            result = decoder.finish(False)
        except RuntimeError as exc:  # the decoder's own errors (e.g. an unknown model id)
            raise InputError(self.path, f"cannot decode the Velodyne packets ({exc})") from None
        if result is not None:
            yield tuple(result)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self) if count is None else min(len(self), start + count)
        if start >= stop:
            return
        vd = _vd(self.path)
        fields = vd.PointField
        index, last = 0, -np.inf
        for item in self._sweeps_and_telemetry():
            if not isinstance(item, tuple):
                continue
            stamp = float(item[0].device)
            if stamp <= last:
                continue
            last = stamp
            if index >= start:
                cloud = item[1]
                yield Scan(index, stamp,
                           cloud[:, [fields.x, fields.y, fields.z]].astype(np.float64),
                           cloud[:, fields.time].astype(np.float64),
                           np.ascontiguousarray(cloud[:, fields.intensity]),
                           f"{self.path}#sweep{index}")
            index += 1
            if index >= stop:
                return


def _gnss(path: Path, telemetry: list):
    """(GnssFixes or None, why not) from position packets: one fix per distinct NMEA
    sentence with a fix and a date, stamped with its UTC time."""
    rows, seen, locked = [], set(), False
    for packet in telemetry:
        locked |= packet.pps_status.name == "LOCKED"
        sentence = packet.nmea_sentence
        if not sentence or sentence in seen:
            continue
        seen.add(sentence)
        info = packet.parse_nmea()
        when = packet.nmea_time
        if info is None or not info.fix_available or not isinstance(when, datetime):
            continue
        has_alt = sentence[3:6] == "GGA"
        stamp = when.replace(tzinfo=timezone.utc).timestamp()
        rows.append([stamp, info.latitude, info.longitude, info.altitude if has_alt else 0.0,
                     NMEA_SIGMA_H_M, NMEA_SIGMA_V_M if has_alt else NO_ALTITUDE_SIGMA_V_M])
    if len(rows) < 2:
        return None, f"{path}: {len(rows)} NMEA fix(es) in the position packets (need 2)"
    if not locked:
        log.warning("%s: the sensor's PPS is not locked: its clock is not GNSS time, so the "
                    "NMEA fixes (stamped in UTC) may be off the scans' clock (gnss.time_offset_s)",
                    path)
    source = (f"{path} (NMEA in position packets; sigma {NMEA_SIGMA_H_M:g} m assumed"
              f"{'' if locked else ', PPS not locked'})")
    return gnss_from_rows(source, np.array(rows)), ""
