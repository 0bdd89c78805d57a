"""Inputs: `open_source` picks the reader of a path (a folder of scans, KITTI, a rosbag, a pcap,
a public dataset's layout); this module holds the folder and KITTI readers.

Every source yields `Scan`s with 0-based `index` = position in the input, exposes
`ground_truth` as T_world_lidar (K, 4, 4) for all K input scans, or None, and hands over its
own IMU and GNSS with `inertial(...)` (io.inertial_input), so nothing outside io/ needs to
know which kind of input it reads.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.inertial_input import Carried, InertialInput, StreamsBesideScans
from lidar_slam.io.point_times import relative_seconds
from lidar_slam.io.pointcloud import SCAN_SUFFIXES, CloudData, make_scan, read_bin, read_cloud
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_kitti_raw_timestamps,
    read_times,
)
from lidar_slam.types import Scan

log = logging.getLogger(__name__)
DEFAULT_PERIOD_S = 0.1


class ScanSource(Protocol):
    path: Path  # the input as given
    name: str
    # "folder", "file", "kitti", "kitti_raw", "rosbag", a pcap or a dataset (io.datasets): for
    # summary.json (input_kind) and messages; the code outside io/ never branches on it
    # (tests/test_layout.py)
    kind: str
    topic: str | None  # the bag topic read, None for other inputs
    ground_truth: np.ndarray | None
    stamps: np.ndarray  # stamp (s) of every input scan, as Scan.stamp_s
    # The stamps the IMU / GNSS are checked and calibrated against (None: a single scan file)
    scan_clock: np.ndarray | None
    # IMU / GNSS / T_lidar_imu read from the same files as the scans (datasets, sensor pcaps);
    # None: beside the scans or in the bag
    sensor_streams: Carried | None

    @property
    def input_notes(self) -> dict[str, int]: ...  # what was dropped or recovered (summary.json)

    def __len__(self) -> int: ...

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]: ...

    def inertial(self, *, imu_enabled: bool, gnss_enabled: bool,
                 imu_offset_s: float | None = 0.0, gnss_offset_s: float = 0.0,
                 imu_topic: str | None = None, gnss_topic: str | None = None
                 ) -> InertialInput: ...  # the input's IMU and GNSS (io.inertial_input)


def natural_key(name: str) -> list:
    """Sort key that orders scan2 before scan10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _scan_files(folder: Path, strict: bool = True) -> list[Path]:
    """The scan files in folder, naturally sorted; strict: a link to nothing named as a scan is
    an error (not a scan dropped in silence)."""
    named = [p for p in folder.iterdir() if p.suffix.lower() in SCAN_SUFFIXES]
    broken = strict and sorted((p for p in named if p.is_symlink() and not p.exists()),
                               key=lambda p: natural_key(p.name))
    if broken:  # dropped, each scan after it would take the stamp of the one before
        raise InputError(broken[0], f"a link to {os.readlink(broken[0])}, which does not exist"
                                    + (f" ({len(broken)} such scans here)" if len(broken) > 1
                                       else ""))
    files = [p for p in named if p.is_file()]
    return sorted(files, key=lambda p: natural_key(p.name))


def _load_stamps(path: Path, n: int, files: list[Path] | None = None) -> np.ndarray | None:
    """Scan stamps (s) from a times file with one line per scan; None when there is none.
    files: KITTI scans, whose numbers pick their lines from a longer file."""
    if not path.is_file():
        return None
    stamps = read_times(path)
    if files is not None:
        stamps = _lines_of(path, stamps, files, "stamps")
    if len(stamps) != n:
        raise InputError(path, f"has {len(stamps)} stamps for {n} scans")
    return _stamps_in_s(path, stamps)


SCAN_RATES_HZ = (0.5, 200.0)  # a scanning lidar's sweep rate, in any unit of its stamps
SLOW_SCANS_S = 10.0  # scans further apart than this (median) are said to be
OTHER_UNIT_S = 3600.0  # read as s, scans this far apart (median) are stamps in another unit


def _stamps_in_s(path: Path, stamps: np.ndarray) -> np.ndarray:
    """A times file's stamps in s. Scans an hour or more apart (median) are stamps in ms, us or
    ns when one of those gives a sweep rate in SCAN_RATES_HZ: converted with one warning (read
    as s, ns stamps made the poses' stamps 1e18 and every velocity 0). Ten seconds or more
    apart, said in one warning (a survey's scans can be; 10 Hz in ms is 100 s in s)."""
    from lidar_slam.io.imu_units import STAMP_UNITS

    steps = np.diff(stamps)
    if not len(steps):
        return stamps
    spacing = float(np.median(steps))
    if spacing >= OTHER_UNIT_S:
        fits = [(scale, unit) for scale, unit in STAMP_UNITS[1:]
                if SCAN_RATES_HZ[0] <= 1.0 / (spacing * scale) <= SCAN_RATES_HZ[1]]
        if fits:
            scale, unit = fits[0]
            log.warning("%s: stamps read as %s (median spacing %.6g: %.3g Hz in %s); converted "
                        "to s", path, unit, spacing, 1.0 / (spacing * scale), unit)
            return stamps * scale
    if spacing >= SLOW_SCANS_S:
        log.warning("%s: scans %.6g s apart (median): taken as seconds; if the file is in ms, "
                    "us or ns, convert it to s", path, spacing)
    return stamps


def _lines_of(path: Path, rows: np.ndarray, files: list[Path], what: str) -> np.ndarray:
    """rows as many as files, or a part of a KITTI sequence beside its whole file (times.txt,
    poses): each scan's number (000123.bin) picks its line, said in one warning."""
    if len(rows) <= len(files):
        return rows
    numbers = [p.stem for p in files]
    if not all(n.isdigit() and int(n) < len(rows) for n in numbers):
        raise InputError(path, f"has {len(rows)} {what} for {len(files)} scans, and the scans' "
                               f"names are not the lines to take")
    log.warning("%s: %d %s for %d scans: each scan's number picks its line (%s..%s)", path,
                len(rows), what, len(files), numbers[0], numbers[-1])
    return rows[[int(n) for n in numbers]]


def _assumed_stamps(path: Path, n: int, holds: str = "one stamp in s per scan") -> np.ndarray:
    """Stamps DEFAULT_PERIOD_S apart, said out loud: a 5 Hz sensor read this way gets half its
    true speed (the poses are right, their stamps and the velocities are not). holds: what the
    missing file would hold, for the advice."""
    if n > 1:
        log.warning("%s not found: scans taken as %.1f s apart (%.0f Hz); add it (%s) if the "
                    "sensor ran at another rate", path, DEFAULT_PERIOD_S, 1.0 / DEFAULT_PERIOD_S,
                    holds)
    return np.arange(n) * DEFAULT_PERIOD_S


def _stamp_ns(stamp_s: float, known: bool) -> int | None:
    return round(stamp_s * 1e9) if known else None


# Files beside a folder's scans that name a public dataset, and the layout it then needs (the
# readers in io.datasets and docs/datasets.md).
LAYOUT_HINTS = (("ms25.csv", "an NCLT session? its scans go in velodyne_sync/"),
                ("gps.csv", "an NCLT session? its scans go in velodyne_sync/"),
                ("global_pose.csv", "a MulRan sequence? its scans go in sensor_data/Ouster/"),
                ("lidar/", "a Boreas sequence? it needs applanix/ or calib/ beside lidar/"))


def _subfolders_with_scans(root: Path) -> list[tuple[str, int]]:
    """(name, scan files) of root's subfolders that hold scans."""
    out = []
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        try:
            n = len(_scan_files(sub, strict=False))
        except OSError:
            continue
        if n:
            out.append((sub.name, n))
    return out


def _boreas_names(folder: Path) -> bool:
    """Whether a folder's .bin scans are named as Boreas's: 16-digit microsecond stamps."""
    names = [p.stem for p in folder.glob("*.bin")][:20]
    return bool(names) and all(n.isdigit() and len(n) == 16 for n in names)


def _other_layout_hint(root: Path) -> str:
    """What the folder might be instead: a public dataset whose telltale file is here, and the
    subfolders that hold scans (pass one as a folder of scans)."""
    said = [why for name, why in LAYOUT_HINTS if (root / name).exists()
            and (name != "lidar/" or _boreas_names(root / "lidar"))]
    subs = _subfolders_with_scans(root)
    if subs and not said:  # a dataset's scan folder read as plain scans misreads them
        said.append("or pass a folder of scans: " + ", ".join(
            f"{root / name} ({n} scans)" for name, n in subs[:3]))
    return "; ".join(dict.fromkeys(said)) or "or pass a folder of scans"


class FolderSource(StreamsBesideScans):
    """A folder of scan files (in the folder or in its scans/ subfolder), naturally sorted, or a
    single scan file.

    Optional beside them: poses.txt (KITTI 12-column T_world_sensor, one line per scan) as reference
    and times.txt (one stamp per scan, s). Without times.txt, scans are 0.1 s apart (a warning).
    """

    topic = None

    def __init__(self, root: Path):
        self.root = self.path = root
        self.ground_truth = None
        if root.is_file():  # one scan
            self.kind, self.name, self.files = "file", root.stem, [root]
            self.stamps, self.stamps_known = np.zeros(1), False
            return
        self.kind = "folder"
        files = _scan_files(root)
        if not files and (root / "scans").is_dir():
            files = _scan_files(root / "scans")
        elif (root / "scans").is_dir() and (
                n_sub := len(_scan_files(root / "scans", strict=False))):
            log.warning("%s: %d scans in the folder itself are read, not the %d in its scans/ "
                        "(move the folder's own away to read those)", root, len(files), n_sub)
        if not files:
            bags = sorted(p.name for p in root.iterdir() if p.suffix in (".bag", ".mcap", ".db3"))
            hint = (f"; a recording is here: pass the file itself ({root / bags[0]})" if bags
                    else f"; {_other_layout_hint(root)}" if _subfolders_with_scans(root) else "")
            raise InputError(root, f"no scans found (looked for {', '.join(SCAN_SUFFIXES)} "
                                   f"files){hint}")
        self.files = files
        self.name = root.name
        stamps = _load_stamps(root / "times.txt", len(files))
        self.stamps_known = stamps is not None
        self.stamps = stamps if stamps is not None else _assumed_stamps(root / "times.txt",
                                                                          len(files))
        if (root / "poses.txt").is_file():
            gt = read_kitti_poses(root / "poses.txt")
            if len(gt) != len(files):
                raise InputError(root / "poses.txt", f"has {len(gt)} poses for {len(files)} scans")
            self.ground_truth = gt

    @property
    def input_notes(self) -> dict[str, int]:
        """Nothing dropped or recovered: stamps that do not increase are refused, not dropped."""
        return {}

    @property
    def scan_clock(self) -> np.ndarray | None:
        """The scan stamps, or None for one scan file (no clock to check the IMU against)."""
        return None if self.kind == "file" else self.stamps

    def __len__(self) -> int:
        return len(self.files)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self.files) if count is None else min(len(self.files), start + count)
        for i in range(start, stop):
            cloud = read_cloud(self.files[i], _stamp_ns(self.stamps[i], self.stamps_known))
            yield make_scan(i, self.stamps[i], cloud, str(self.files[i]))


class KittiSource(StreamsBesideScans):
    """A KITTI odometry sequence: velodyne/*.bin, calib.txt (with Tr), times.txt, poses.

    Ground truth comes from poses.txt in the folder or <root>/poses/XX.txt for
    <root>/sequences/XX; it is in the left-camera frame and converted with
    T_world_lidar(i) = inv(Tr) @ P_i @ Tr. Optional velodyne_times/NNNNNN.bin holds float32
    per-point times (s, relative to the scan stamp) for simulated sequences.
    """

    kind, topic = "kitti", None

    def __init__(self, root: Path, vertical_correction: bool = False):
        self.root = self.path = root
        self.name = root.name
        self.files = sorted((root / "velodyne").glob("*.bin"), key=lambda p: natural_key(p.name))
        if not self.files:
            raise InputError(root / "velodyne", "no .bin scans found")
        self.vertical_correction = vertical_correction
        if not (root / "calib.txt").is_file():
            raise InputError(root, f"holds velodyne/ but no calib.txt: a KITTI sequence needs it "
                                   f"(its Tr); {_other_layout_hint(root)}")
        self.Tr = read_kitti_calib_tr(root / "calib.txt")
        stamps = _load_stamps(root / "times.txt", len(self.files), self.files)
        self.stamps_known = stamps is not None
        self.stamps = stamps if stamps is not None else _assumed_stamps(root / "times.txt",
                                                                          len(self.files))
        self.ground_truth = None
        for cand in (root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"):
            if cand.is_file():
                poses_cam = _lines_of(cand, read_kitti_poses(cand), self.files, "poses")
                if len(poses_cam) != len(self.files):
                    raise InputError(cand, f"has {len(poses_cam)} poses for "
                                           f"{len(self.files)} scans")
                self.ground_truth = camera_to_lidar_poses(poses_cam, self.Tr)
                break

    @property
    def input_notes(self) -> dict[str, int]:
        """Nothing dropped or recovered: stamps that do not increase are refused, not dropped."""
        return {}

    def __len__(self) -> int:
        return len(self.files)

    def _read(self, path: Path, stamp_ns: int | None) -> CloudData:
        cloud = read_bin(path)
        tfile = self.root / "velodyne_times" / path.name
        times = None
        if tfile.is_file() and len(cloud.points):  # (none: an empty or a skipped scan)
            try:
                raw = np.fromfile(tfile, dtype=np.float32)
            except OSError as exc:
                raise InputError(tfile, f"cannot read ({exc.strerror or exc})") from None
            if len(raw) != len(cloud.points):
                raise InputError(tfile, f"has {len(raw)} times for {len(cloud.points)} points")
            times = relative_seconds(raw, stamp_ns)
        elif len(cloud.points) and tfile.parent.is_dir():
            log.warning("%s: missing beside the other scans' point times: scan %s is not "
                        "deskewed", tfile, path.name)
        pts = correct_kitti_scan(cloud.points) if self.vertical_correction else cloud.points
        return CloudData(pts, times, cloud.intensity)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self.files) if count is None else min(len(self.files), start + count)
        for i in range(start, stop):
            cloud = self._read(self.files[i], _stamp_ns(self.stamps[i], self.stamps_known))
            yield make_scan(i, self.stamps[i], cloud, str(self.files[i]))


class KittiRawSource(StreamsBesideScans):
    """A KITTI raw drive: velodyne_points/data/*.bin with velodyne_points/timestamps.txt (the
    drive folder or its velodyne_points folder). No ground truth (the raw drives' OXTS poses are
    not read). path: the input as given (the drive folder, or root itself)."""

    kind, topic = "kitti_raw", None

    def __init__(self, root: Path, vertical_correction: bool = False, path: Path | None = None):
        self.root = root
        self.path = root if path is None else path
        self.name = root.parent.name if root.name == "velodyne_points" else root.name
        self.files = sorted((root / "data").glob("*.bin"), key=lambda p: natural_key(p.name))
        if not self.files:
            raise InputError(root / "data", "no .bin scans found")
        self.vertical_correction = vertical_correction
        self.ground_truth = None
        stamps_path = root / "timestamps.txt"
        if stamps_path.is_file():
            self.stamps = read_kitti_raw_timestamps(stamps_path)
            if len(self.stamps) != len(self.files):
                raise InputError(stamps_path, f"has {len(self.stamps)} stamps for "
                                              f"{len(self.files)} scans")
        else:
            self.stamps = _assumed_stamps(stamps_path, len(self.files),
                                          "KITTI raw's: one date and time per scan, "
                                          "2011-09-26 13:02:25.964389445, from the drive's "
                                          "download")

    @property
    def input_notes(self) -> dict[str, int]:
        """Nothing dropped or recovered: stamps that do not increase are refused, not dropped."""
        return {}

    def __len__(self) -> int:
        return len(self.files)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self.files) if count is None else min(len(self.files), start + count)
        for i in range(start, stop):
            cloud = read_bin(self.files[i])
            if self.vertical_correction:
                cloud = CloudData(correct_kitti_scan(cloud.points), None, cloud.intensity)
            yield make_scan(i, self.stamps[i], cloud, str(self.files[i]))


def correct_kitti_scan(points: np.ndarray, angle_deg: float = 0.205) -> np.ndarray:
    """KITTI HDL-64E intrinsic fix used by kiss-icp: rotate each point about the axis z x p.

    Rodrigues with the per-point unit axis k = (y, -x, 0) / rho (rho = hypot(x, y)), orthogonal
    to p: p' = p cos + (k x p) sin, where k x p = (-x z / rho, -y z / rho, rho). Written out
    (7 ms instead of 20 ms with two np.cross per 120k-point scan); points on the z axis are only
    scaled by cos, as with a zero axis.
    """
    th = np.radians(angle_deg)
    c, s = np.cos(th), np.sin(th)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rho = np.hypot(x, y)
    z_over_rho = np.divide(z, rho, out=np.zeros_like(rho), where=rho > 0)
    out = points * c
    out[:, 0] -= s * x * z_over_rho
    out[:, 1] -= s * y * z_over_rho
    out[:, 2] += s * rho
    return out


def open_source(path: str | Path, topic: str | None = None, kitti_vertical_correction: bool = False,
                meta: Path | None = None) -> ScanSource:
    """Pick the reader for a path: rosbag/mcap, sensor pcap (`meta`: an Ouster's metadata JSON),
    a public dataset's sequence (io.datasets), KITTI sequence, KITTI raw drive, a folder of scans
    or one scan file. `topic` only applies to bags (a warning otherwise)."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "does not exist")
    is_bag = p.suffix.lower() in (".bag", ".mcap", ".db3") or (p / "metadata.yaml").is_file()
    if is_bag:
        from lidar_slam.io.rosbag import RosbagSource

        return RosbagSource(p, topic=topic)
    if topic is not None:
        log.warning("--topic %s ignored: %s is not a rosbag", topic, p)
    if p.suffix.lower() == ".pcap":
        from lidar_slam.io.pcap import open_pcap

        return open_pcap(p, meta)
    if meta is not None:
        log.warning("--meta %s ignored: %s is not a pcap", meta, p)
    if p.is_dir():
        from lidar_slam.io.datasets import open_dataset  # the public dataset layouts

        dataset = open_dataset(p)
        if dataset is not None:
            dataset.path = p  # the layout's root may be above the folder given
            return dataset
    if p.is_file():
        if p.suffix.lower() in SCAN_SUFFIXES:
            return FolderSource(p)
        raise InputError(p, "expected a folder of scans, a scan file "
                            f"({', '.join(SCAN_SUFFIXES)}), a KITTI sequence or a rosbag")
    if (p / "velodyne").is_dir():
        return KittiSource(p, vertical_correction=kitti_vertical_correction)
    for raw in (p / "velodyne_points", p):
        if (raw / "data").is_dir() and (raw.name == "velodyne_points"
                                        or (raw / "timestamps.txt").is_file()):
            return KittiRawSource(raw, vertical_correction=kitti_vertical_correction, path=p)
    return FolderSource(p)


def read_ahead(scans: Iterator[Scan], depth: int = 2) -> Iterator[Scan]:
    """The same scans, in the same order, read up to `depth` ahead on a background thread, so
    that file reading (NumPy releases the GIL there) overlaps with the processing of the scan
    before. A reader error is raised here, at the scan where it happened."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def produce() -> None:
        try:
            for scan in scans:
                while not stop.is_set():
                    try:
                        q.put(scan, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(done)
        except BaseException as exc:  # noqa: BLE001 (handed to the consumer, raised there)
            q.put(exc)

    thread = threading.Thread(target=produce, name="read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
