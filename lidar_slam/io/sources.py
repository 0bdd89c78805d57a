"""Scan sources: a folder of scans, a KITTI odometry sequence, or a rosbag; one `open_source`.

Every source yields `Scan`s with 0-based `index` = position in the input, and exposes
`ground_truth` as T_world_lidar (K, 4, 4) for all K input scans, or None.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.pointcloud import SCAN_SUFFIXES, CloudData, read_bin, read_cloud
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_times,
)
from lidar_slam.types import Scan

log = logging.getLogger(__name__)
DEFAULT_PERIOD_S = 0.1


class ScanSource(Protocol):
    name: str
    ground_truth: np.ndarray | None

    def __len__(self) -> int: ...

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]: ...


def make_scan(index: int, stamp_s: float, cloud: CloudData, source: str) -> Scan:
    """Build a Scan, dropping points with NaN/inf coordinates (counted in the log)."""
    points, times, inten = cloud.points, cloud.times, cloud.intensity
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf: NaN, no warning
        # One contiguous sum: a NaN/inf anywhere makes it non-finite (3x faster than per row).
        suspect = not np.isfinite(np.add.reduce(points.ravel()))
    finite = np.isfinite(points).all(axis=1) if suspect else None
    if finite is not None and not finite.all():  # (an overflowing finite sum lands here too)
        log.warning("%s: dropped %d points with NaN/inf coordinates", source, int((~finite).sum()))
        points = points[finite]
        times = times[finite] if times is not None else None
        inten = inten[finite] if inten is not None else None
    if times is not None and not np.isfinite(times).all():
        times = None
    return Scan(index, float(stamp_s), points, times, inten, source)


def natural_key(name: str) -> list:
    """Sort key that orders scan2 before scan10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _scan_files(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def _load_stamps(path: Path, n: int) -> np.ndarray:
    if path.is_file():
        stamps = read_times(path)
        if stamps.ndim != 1:
            raise InputError(path, f"expected one stamp per line, found {stamps.shape[1]} columns")
        if len(stamps) != n:
            raise InputError(path, f"has {len(stamps)} stamps for {n} scans")
        return stamps
    return np.arange(n) * DEFAULT_PERIOD_S


class FolderSource:
    """A folder of scan files (in the folder or in its scans/ subfolder), naturally sorted.

    Optional beside them: poses.txt (KITTI 12-column T_world_sensor, one line per scan) as reference
    and times.txt (one stamp per scan, s). Without times.txt, scans are 0.1 s apart.
    """

    def __init__(self, root: Path):
        self.root = root
        folder = root
        files = _scan_files(root)
        if not files and (root / "scans").is_dir():
            folder = root / "scans"
            files = _scan_files(folder)
        if not files:
            raise InputError(root, f"no scans found (looked for {', '.join(SCAN_SUFFIXES)} files)")
        self.files = files
        self.name = root.name
        self.stamps = _load_stamps(root / "times.txt", len(files))
        self.ground_truth = None
        if (root / "poses.txt").is_file():
            gt = read_kitti_poses(root / "poses.txt")
            if len(gt) != len(files):
                raise InputError(root / "poses.txt", f"has {len(gt)} poses for {len(files)} scans")
            self.ground_truth = gt

    def __len__(self) -> int:
        return len(self.files)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self.files) if count is None else min(len(self.files), start + count)
        for i in range(start, stop):
            yield make_scan(i, self.stamps[i], read_cloud(self.files[i]), str(self.files[i]))


class KittiSource:
    """A KITTI odometry sequence: velodyne/*.bin, calib.txt (with Tr), times.txt, poses.

    Ground truth comes from poses.txt in the folder or <root>/poses/XX.txt for
    <root>/sequences/XX; it is in the left-camera frame and converted with
    T_world_lidar(i) = inv(Tr) @ P_i @ Tr. Optional velodyne_times/NNNNNN.bin holds float32
    per-point times (s, relative to the scan stamp) for simulated sequences.
    """

    def __init__(self, root: Path, vertical_correction: bool = False):
        self.root = root
        self.name = root.name
        self.files = sorted((root / "velodyne").glob("*.bin"), key=lambda p: natural_key(p.name))
        if not self.files:
            raise InputError(root / "velodyne", "no .bin scans found")
        self.vertical_correction = vertical_correction
        self.Tr = read_kitti_calib_tr(root / "calib.txt")
        self.stamps = _load_stamps(root / "times.txt", len(self.files))
        self.ground_truth = None
        for cand in (root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"):
            if cand.is_file():
                poses_cam = read_kitti_poses(cand)
                if len(poses_cam) != len(self.files):
                    raise InputError(cand, f"has {len(poses_cam)} poses for {len(self.files)} scans")
                self.ground_truth = camera_to_lidar_poses(poses_cam, self.Tr)
                break

    def __len__(self) -> int:
        return len(self.files)

    def _read(self, path: Path) -> CloudData:
        cloud = read_bin(path)
        tfile = self.root / "velodyne_times" / path.name
        times = None
        if tfile.is_file():
            times = np.fromfile(tfile, dtype=np.float32).astype(np.float64)
            if len(times) != len(cloud.points):
                raise InputError(tfile, f"has {len(times)} times for {len(cloud.points)} points")
        pts = correct_kitti_scan(cloud.points) if self.vertical_correction else cloud.points
        return CloudData(pts, times, cloud.intensity)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self.files) if count is None else min(len(self.files), start + count)
        for i in range(start, stop):
            yield make_scan(i, self.stamps[i], self._read(self.files[i]), str(self.files[i]))


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


def open_source(path: str | Path, topic: str | None = None, kitti_vertical_correction: bool = False
                ) -> ScanSource:
    """Pick the reader for a path: rosbag/mcap, KITTI sequence, or a folder of scans."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "does not exist")
    is_bag = p.suffix.lower() in (".bag", ".mcap", ".db3") or (p / "metadata.yaml").is_file()
    if is_bag:
        from lidar_slam.io.rosbag import RosbagSource

        return RosbagSource(p, topic=topic)
    if p.is_file():
        raise InputError(p, "expected a folder of scans, a KITTI sequence or a rosbag")
    if (p / "velodyne").is_dir():
        return KittiSource(p, vertical_correction=kitti_vertical_correction)
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
        except BaseException as exc:  # handed to the consumer, raised there
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
