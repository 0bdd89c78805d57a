"""The keyframe store: every keyframe's cloud on disk (selection: frontend/keyframes.py).

The store keeps every keyframe's cloud on disk in the run folder, so memory does not grow with the
drive; only a small table (ids, frames, odometry poses) and a bounded cache of recent clouds stay
in RAM. At the end of a run the same folder becomes the run's reusable map (`lidar-slam
localize --map`, `lidar-slam export`). Layout (version 3), under RUN/keyframes/:

- `manifest.json`: {"version", "keyframes", "points"}: how many table rows and points are valid
  when the run last flushed the store (at every checkpoint and at the end of the run); at the end
  of the run also "map" (see below).
- `table.bin`: one record per keyframe, little-endian: id int64, frame_index int64, first point
  int64, point count int64, T_world_kf_odom (4x4 float64, row-major), has_intensity uint8,
  stamp_s float64 (the scan's stamp, NaN when unknown; version 3 added it).
- `points.bin`: float32 x, y, z, intensity per point (metres, the keyframe's sensor frame at
  its scan's stamp; keyframe 0, and every scan with per-point times of a run without an IMU, at
  the middle of the sweep, where T_world_kf_odom is too), keyframe after keyframe.
- `map_poses.bin` (end of the run): T_map_kf per keyframe, 4x4 float64 row-major little-endian,
  in keyframe order: the final (loop-corrected) poses in the map frame, which is the frame of
  the run's `poses_kitti.txt` (frame 0 = identity), the frame `map.ply` is in.
- `descriptors.bin` (runs with loop closure): the Scan Context grid (rings x sectors float32,
  row-major; config in ../config.yaml, `loop.scan_context`) of every keyframe with a non-empty
  cloud, in keyframe order; `manifest["map"]["descriptor_rows"]` of them are valid (a reader
  computes the others from the clouds).

manifest["map"] = {"frame": "poses_kitti.txt", "poses": "map_poses.bin", "descriptors":
"descriptors.bin" or null, "descriptor_rows": int, "config": "../config.yaml"}. A store without
it (a run still going, or killed) is not a map.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.atomic import write_atomic
from lidar_slam.types import Keyframe

STORE_VERSION = 3
READABLE_VERSIONS = (3,)  # 3: stamps in the table (2: end-of-run map, 1: neither)
MAP_POSES = "map_poses.bin"
DESCRIPTORS = "descriptors.bin"
TABLE_DTYPE = np.dtype([("id", "<i8"), ("frame_index", "<i8"), ("first", "<i8"), ("count", "<i8"),
                        ("T", "<f8", (4, 4)), ("has_intensity", "u1"), ("stamp_s", "<f8")])
POINT_DTYPE = np.dtype("<f4")  # 4 per point: x, y, z, intensity


class KeyframeStore:
    """Append-only keyframe store in `root` (see the module doc); thread-safe reads."""

    def __init__(self, root: str | Path | None, keep: bool = False, cache_size: int = 64):
        """A new, empty store in root (a temporary folder when None); keep=True reopens the
        store there instead (see truncate)."""
        self._tmp = None
        if root is None:  # library use without a run folder: a temporary one, removed with self
            self._tmp = tempfile.TemporaryDirectory(prefix="lidar_slam_keyframes_")
            root = self._tmp.name
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._table = np.zeros(64, dtype=TABLE_DTYPE)
        self._n = 0
        self._n_points = 0
        self._cache: OrderedDict[int, Keyframe] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()
        table_path = self.root / "table.bin"
        if keep and table_path.is_file():
            self._read_manifest()  # refuses another layout version
            table = np.fromfile(table_path, dtype=TABLE_DTYPE)
            self._n = len(table)
            self._table = np.resize(table, max(64, 2 * self._n))
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | (0 if keep else os.O_TRUNC)
        self._table_fd = os.open(table_path, flags, 0o666)  # rw for all, less the umask
        self._points_fd = os.open(self.root / "points.bin", flags, 0o666)
        self._read_fd = os.open(self.root / "points.bin", os.O_RDONLY)
        self.truncate(self._n)

    def truncate(self, n_keyframes: int) -> None:
        """Keep only the first n_keyframes (what a checkpoint vouches for; a killed run may have
        stored more, or a partial record)."""
        if n_keyframes > self._n:
            raise InputError(self.root / "table.bin", f"holds {self._n} keyframes, "
                             f"{n_keyframes} expected")
        self._n = n_keyframes
        last = self._table[n_keyframes - 1] if n_keyframes else None
        self._n_points = 0 if last is None else int(last["first"] + last["count"])
        os.ftruncate(self._table_fd, self._n * TABLE_DTYPE.itemsize)
        os.ftruncate(self._points_fd, self._n_points * 4 * POINT_DTYPE.itemsize)
        with self._lock:
            self._cache.clear()

    def _read_manifest(self) -> dict | None:
        path = self.root / "manifest.json"
        if not path.is_file():
            return None
        try:
            manifest = json.loads(path.read_text())
        except ValueError as exc:
            raise InputError(path, f"not valid JSON ({exc})") from exc
        check_version(path, manifest)
        return manifest

    def __len__(self) -> int:
        return self._n

    def add(self, frame_index: int, T_world_kf_odom: np.ndarray, points: np.ndarray,
            intensity: np.ndarray | None, stamp_s: float = np.nan) -> Keyframe:
        """Append a keyframe (points (K,3) in its frame, the node's: at the stamp or the sweep's
        middle, lidar_slam.pipeline Pipeline._add_keyframe); returns it with its id."""
        kf_id = self._n
        rows = np.zeros((len(points), 4), dtype=POINT_DTYPE)
        rows[:, :3] = points
        if intensity is not None:
            rows[:, 3] = intensity
        os.write(self._points_fd, rows.tobytes())
        rec = np.zeros(1, dtype=TABLE_DTYPE)
        rec[0] = (kf_id, frame_index, self._n_points, len(points), T_world_kf_odom,
                  intensity is not None, stamp_s)
        os.write(self._table_fd, rec.tobytes())
        with self._lock:
            if self._n == len(self._table):
                self._table = np.resize(self._table, 2 * self._n)
            self._table[self._n] = rec[0]
            self._n += 1
            self._n_points += len(points)
        kf = Keyframe(kf_id, int(frame_index), np.array(T_world_kf_odom, dtype=np.float64),
                      rows[:, :3], rows[:, 3] if intensity is not None else None)
        self._remember(kf)
        return kf

    def _remember(self, kf: Keyframe) -> None:
        with self._lock:
            self._cache[kf.id] = kf
            self._cache.move_to_end(kf.id)
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)

    def T_world_kf_odom(self, kf_id: int) -> np.ndarray:
        """Odometry pose (4x4) of keyframe kf_id."""
        return np.array(self._table[kf_id]["T"])

    def odom_poses(self, first: int, last: int) -> np.ndarray:
        """Odometry poses (last - first + 1, 4, 4) of keyframes first..last."""
        if not 0 <= first <= last < self._n:
            raise KeyError((first, last))
        return np.array(self._table[first:last + 1]["T"])

    def frame_index(self, kf_id: int) -> int:
        return int(self._table[kf_id]["frame_index"])

    def stamp_s(self, kf_id: int) -> float:
        """The stamp (s) of keyframe kf_id's scan (NaN when unknown)."""
        return float(self._table[kf_id]["stamp_s"])

    def table(self) -> np.ndarray:
        """A copy of the valid table rows (structured array, TABLE_DTYPE)."""
        with self._lock:
            return self._table[: self._n].copy()

    def get(self, kf_id: int) -> Keyframe:
        """Keyframe kf_id with its cloud (from the cache, else read from disk)."""
        with self._lock:
            kf = self._cache.get(kf_id)
            if kf is not None:
                self._cache.move_to_end(kf_id)
                return kf
            if not 0 <= kf_id < self._n:
                raise KeyError(kf_id)
            rec = self._table[kf_id].copy()
        kf = _read_keyframe(self._read_fd, rec)
        self._remember(kf)
        return kf

    def flush(self, T_map_kf: np.ndarray | None = None, descriptor_rows: int = 0) -> None:
        """Make everything added so far durable and vouched for by the manifest (atomic). With
        T_map_kf (K, 4, 4), the final pose of every keyframe in the map frame (end of a run),
        the store is also written out as a map (map_poses.bin and the manifest's "map")."""
        manifest: dict = {"version": STORE_VERSION, "keyframes": self._n,
                          "points": self._n_points}
        if T_map_kf is not None:
            if len(T_map_kf) != self._n:
                raise ValueError(f"{len(T_map_kf)} map poses for {self._n} keyframes")
            write_atomic(self.root / MAP_POSES,
                         np.ascontiguousarray(T_map_kf, dtype="<f8").tobytes())
            has_descriptors = (self.root / DESCRIPTORS).is_file()
            manifest["map"] = {"frame": "poses_kitti.txt", "poses": MAP_POSES,
                               "descriptors": DESCRIPTORS if has_descriptors else None,
                               "descriptor_rows": descriptor_rows if has_descriptors else 0,
                               "config": "../config.yaml"}
        os.fsync(self._points_fd)
        os.fsync(self._table_fd)
        write_atomic(self.root / "manifest.json", json.dumps(manifest) + "\n")

    def close(self) -> None:
        for fd in (self._table_fd, self._points_fd, self._read_fd):
            os.close(fd)
        if self._tmp is not None:
            self._tmp.cleanup()


def _read_keyframe(points_fd: int, rec) -> Keyframe:
    """The keyframe of table record rec, its cloud read from the points file."""
    nbytes = int(rec["count"]) * 4 * POINT_DTYPE.itemsize
    raw = os.pread(points_fd, nbytes, int(rec["first"]) * 4 * POINT_DTYPE.itemsize)
    rows = np.frombuffer(raw, dtype=POINT_DTYPE).reshape(-1, 4)
    return Keyframe(int(rec["id"]), int(rec["frame_index"]), np.array(rec["T"]), rows[:, :3],
                    rows[:, 3] if rec["has_intensity"] else None)


class KeyframeReader:
    """Read-only view of a store that another process appends to (the loop worker process):
    every table record is read from table.bin when asked for, with a bounded cache of clouds."""

    def __init__(self, root: str | Path, cache_size: int = 64):
        self.root = Path(root)
        self._table_fd = os.open(self.root / "table.bin", os.O_RDONLY)
        self._points_fd = os.open(self.root / "points.bin", os.O_RDONLY)
        self._cache: OrderedDict[int, Keyframe] = OrderedDict()
        self._cache_size = cache_size

    def _record(self, kf_id: int):
        raw = os.pread(self._table_fd, TABLE_DTYPE.itemsize, kf_id * TABLE_DTYPE.itemsize)
        if kf_id < 0 or len(raw) != TABLE_DTYPE.itemsize:
            raise KeyError(kf_id)
        return np.frombuffer(raw, dtype=TABLE_DTYPE)[0]

    def T_world_kf_odom(self, kf_id: int) -> np.ndarray:
        return np.array(self._record(kf_id)["T"])

    def odom_poses(self, first: int, last: int) -> np.ndarray:
        """Odometry poses (last - first + 1, 4, 4) of keyframes first..last (one read)."""
        n = last - first + 1
        raw = os.pread(self._table_fd, n * TABLE_DTYPE.itemsize, first * TABLE_DTYPE.itemsize)
        if first < 0 or n < 1 or len(raw) != n * TABLE_DTYPE.itemsize:
            raise KeyError((first, last))
        return np.array(np.frombuffer(raw, dtype=TABLE_DTYPE)["T"])

    def frame_index(self, kf_id: int) -> int:
        return int(self._record(kf_id)["frame_index"])

    def stamp_s(self, kf_id: int) -> float:
        return float(self._record(kf_id)["stamp_s"])

    def get(self, kf_id: int) -> Keyframe:
        kf = self._cache.get(kf_id)
        if kf is None:
            kf = _read_keyframe(self._points_fd, self._record(kf_id))
            self._cache[kf_id] = kf
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(kf_id)
        return kf

    def close(self) -> None:
        os.close(self._table_fd)
        os.close(self._points_fd)


def check_version(path: Path, manifest: dict) -> None:
    """Refuse a manifest of a layout version this lidar-slam cannot read."""
    if manifest.get("version") not in READABLE_VERSIONS:
        raise InputError(path, f"keyframe store version {manifest.get('version')}, this "
                         f"lidar-slam reads versions {', '.join(map(str, READABLE_VERSIONS))}")

