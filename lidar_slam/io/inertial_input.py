"""The IMU and GNSS half of every input (issue 22, item 1; issue 30, item 1): each source
returned by io.sources.open_source hands over its own streams with `source.inertial(...)`,
checked against its scan stamps, with what summary.json says of them. Where a source's streams
come from is the source's business, in one of three bases here:

- StreamsBesideScans: imu.csv / gnss.csv beside a folder's scans (or in its scans/ subfolder);
- CarriedStreams: the streams a public dataset's layout or a sensor pcap carries (`Carried`);
- a bag's sensor_msgs/Imu and NavSatFix topics (io.rosbag.source.RosbagSource).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.io.imu_gnss import (
    GNSS_FILE,
    IMU_FILE,
    GnssFixes,
    ImuSamples,
    check_overlap,
    find_beside,
    overlap_problem,
    read_gnss_csv,
    read_imu_csv,
    stream_info,
)
from lidar_slam.io.imu_units import EPOCH_S, STAMP_UNITS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InertialInput:
    """The IMU samples and GNSS fixes of a run (None when not used), on the scans' clock (the
    config's time offsets applied), and what summary.json says of each ("imu", "gnss")."""

    imu: ImuSamples | None
    gnss: GnssFixes | None
    summary: dict


@dataclass(frozen=True)
class Carried:
    """The IMU and GNSS an input holds in the same files as its scans (a public dataset's
    layout, a sensor pcap), on the scans' clock, with what its calibration says of the mounting:
    T_lidar_imu (4x4, IMU-frame vectors into the lidar frame) or None when the input gives
    none; `why_not` says why a stream is None (summary.json)."""

    imu: ImuSamples | None = None
    gnss: GnssFixes | None = None
    T_lidar_imu: np.ndarray | None = None
    why_not: tuple[tuple[str, str], ...] = ()

    def reason(self, what: str) -> str:
        return dict(self.why_not).get(what, f"the layout carries no {what}")


Stream = ImuSamples | GnssFixes


class ImuGnssStreams:
    """What every source does with its IMU and GNSS: `inertial(...)` reads them (the subclass's
    `own_stream` says from where), puts them on the scans' clock and checks them against the
    scan stamps (`scan_clock`). `topics_apply`: --imu-topic / --gnss-topic name something in
    this input (a bag); elsewhere they are ignored with a warning."""

    topics_apply = False
    path: Path  # the input as given to open_source: csv files are found, warnings named, by it
    # io.imu_calibration reads it: the IMU / GNSS / mounting of an input that carries them in
    # the same files as its scans (Carried); None when they come from beside them or a bag
    sensor_streams: Carried | None = None

    @property
    def scan_clock(self) -> np.ndarray | None:
        """The scan stamps (s) the streams are checked and calibrated against; None when there
        is nothing to check with (a single scan file)."""
        return self.stamps

    def own_stream(self, what: str, topic: str | None) -> tuple[Stream | None, str | None]:
        """The input's "imu" or "gnss" stream as read, or (None, why not)."""
        raise NotImplementedError

    def own_mounting(self, imu_topic: str | None) -> tuple[np.ndarray | None, str]:
        """T_lidar_imu (4x4) the input's own calibration gives and from where (summary.json),
        or (None, why not): a dataset's or a pcap's (sensor_streams); a bag's /tf_static."""
        carried = self.sensor_streams
        if carried is None or carried.T_lidar_imu is None:
            return None, "the input gives none"
        return carried.T_lidar_imu, getattr(self, "kind", "input")

    def lenient(self, what: str, topic: str | None) -> bool:
        """Whether a stream that does not overlap the scans is left out (a warning) instead of
        stopping the run: one the user did not name (see on_scan_clock)."""
        return False

    def inertial(self, *, imu_enabled: bool, gnss_enabled: bool,
                 imu_offset_s: float | None = 0.0, gnss_offset_s: float = 0.0,
                 imu_topic: str | None = None, gnss_topic: str | None = None) -> InertialInput:
        """The input's IMU and GNSS (own_stream), checked against the scan stamps (see
        check_overlap). imu_offset_s None: the IMU's offset is to be found from the data; its
        stream comes back as read, to be placed by on_scan_clock."""
        for flag, value, enabled in (("--imu-topic", imu_topic, imu_enabled),
                                     ("--gnss-topic", gnss_topic, gnss_enabled)):
            if value is not None and not self.topics_apply:
                log.warning("%s %s ignored: %s is not a rosbag", flag, value, self.path)
            elif value is not None and not enabled:
                log.warning("%s %s ignored: switched off (--no-%s or its enabled: false)", flag,
                            value, flag[2:-6])
        topics = {"imu": imu_topic, "gnss": gnss_topic}
        streams: dict[str, object] = {}
        summary: dict[str, dict] = {}
        for what, enabled, offset_s in (("imu", imu_enabled, imu_offset_s),
                                        ("gnss", gnss_enabled, gnss_offset_s)):
            if not enabled:
                stream, why = None, f"off (--no-{what} or {what}.enabled: false)"
            else:
                stream, why = self.own_stream(what, topics[what])
            if stream is None:
                summary[what] = {"used": False, "reason": why}
                streams[what] = None
                continue
            if offset_s is None:  # to be found from the data (imu_calibration): placed later
                summary[what] = {"used": True, "source": stream.source}
                streams[what] = stream
                continue
            streams[what], summary[what] = on_scan_clock(
                stream, what, offset_s, self.scan_clock, self.lenient(what, topics[what]))
        return InertialInput(streams["imu"], streams["gnss"], summary)


class StreamsBesideScans(ImuGnssStreams):
    """imu.csv / gnss.csv beside the scans of a folder input, or in its scans/ subfolder."""

    def own_stream(self, what: str, topic: str | None) -> tuple[Stream | None, str | None]:
        name, reader = (IMU_FILE, read_imu_csv) if what == "imu" else (GNSS_FILE, read_gnss_csv)
        data = self.path
        path = find_beside(data, name) if data.is_dir() else None
        if path is None:
            return None, f"no {name} beside the scans"
        return reader(path), None


class CarriedStreams(ImuGnssStreams):
    """The streams an input carries with its scans (`sensor_streams`, a Carried): a dataset
    layout's or a pcap's, already on the scans' clock, so one that misses the scans is left
    out, not refused. An IMU whose mounting the input does not give goes on to the run, which
    takes it from the config or finds it from the data (lidar_slam.imu_calibration)."""

    sensor_streams: Carried

    def own_stream(self, what: str, topic: str | None) -> tuple[Stream | None, str | None]:
        carried = self.sensor_streams
        stream = carried.imu if what == "imu" else carried.gnss
        return (None, carried.reason(what)) if stream is None else (stream, None)

    def lenient(self, what: str, topic: str | None) -> bool:
        return True


def _gnss_on_the_scans_unit(fixes, offset_s: float, scan_stamps: np.ndarray):
    """GNSS fixes whose stamps read in ms, us or ns put at least twice as many fixes within the
    scans' span as read in s (and at least two), converted to that unit with one warning:
    stamps counted from 0 in ms look like a fix every 1000 s, which their size alone cannot
    tell from a sparse receiver (io.imu_units.gnss_stamps_in_s). Of the units that put at least
    half the most fixes there, the one whose fixes span most of the scans' span."""
    if fixes.read_as:
        return fixes  # converted on reading already
    if EPOCH_S[0] <= float(np.median(np.abs(fixes.stamp_s))) <= EPOCH_S[1]:
        return fixes  # epoch seconds: another clock than the scans', which the overlap check says
    first, last = float(scan_stamps[0]), float(scan_stamps[-1])
    options = []
    for scale, unit in STAMP_UNITS:
        t = fixes.stamp_s * scale + offset_s
        inside = int(((t >= first) & (t <= last)).sum())
        covered = max(0.0, min(last, float(t[-1])) - max(first, float(t[0]))) / (last - first)
        options.append((inside, covered, scale, unit))
    most = max(o[0] for o in options)
    best = max((o for o in options if o[0] >= max(2, 0.5 * most)), key=lambda o: o[1],
               default=options[0])  # the first of equals: s before ms, us, ns
    if best[2] == 1.0 or best[0] < 2 * options[0][0]:
        return fixes
    log.warning("%s: stamps read as %s: %d fixes fall within the scans' %.6g..%.6g s so, %d "
                "read as s; converted to s", fixes.source, best[3], best[0], first, last,
                options[0][0])
    return dataclasses.replace(fixes, stamp_s=fixes.stamp_s * best[2],
                               read_as={"stamps": best[3]})


def on_scan_clock(stream, what: str, offset_s: float, scan_stamps: np.ndarray | None,
                  lenient: bool):
    """The stream with offset_s added to its stamps, checked against the scan stamps (see
    check_overlap), and what summary.json says of it: (stream or None, summary). lenient: a
    stream that does not overlap the scans is not used (a warning, the reason in the summary)
    instead of stopping the run (a topic picked without being asked for, e.g. an Ouster's own
    IMU stamped by the sensor's clock, must not stop a run that can go on without it)."""
    if what == "gnss" and scan_stamps is not None and len(scan_stamps) > 1:
        stream = _gnss_on_the_scans_unit(stream, offset_s, scan_stamps)
    stream = stream.shifted(offset_s) if offset_s else stream
    label = "IMU" if what == "imu" else "GNSS"
    if scan_stamps is not None and len(scan_stamps):
        span = float(scan_stamps[0]), float(scan_stamps[-1])
        problem = overlap_problem(stream.stamp_s, *span, label)
        if problem is not None and lenient:
            log.warning("%s: not used: %s; --no-%s silences this", stream.source, problem,
                        what)
            return None, {"used": False, "reason": f"{stream.source}: {problem}"}
        check_overlap(stream.source, stream.stamp_s, *span, label)
    return stream, {"used": True, **stream_info(stream.stamp_s, stream.source, stream.dropped,
                                               offset_s, stream.read_as)}
