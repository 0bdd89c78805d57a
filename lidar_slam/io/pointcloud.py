"""Single point-cloud files: .bin (KITTI float32 x,y,z,intensity), .pcd, .ply, .npy."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.point_times import relative_seconds

SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")
TIME_FIELDS = ("t", "time", "timestamp", "timestamps", "offset_time")
INTENSITY_FIELDS = ("intensity", "intensities", "reflectivity", "remission")


@dataclass(frozen=True)
class CloudData:
    """Raw contents of one file: points (N,3) float64, times (N,) seconds or None, intensity or None."""

    points: np.ndarray
    times: np.ndarray | None
    intensity: np.ndarray | None


def read_bin(path: Path) -> CloudData:
    size = path.stat().st_size
    if size % 16 != 0:
        raise InputError(path, f"size {size} bytes is not a multiple of 16 (float32 x,y,z,intensity)")
    data = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    return CloudData(data[:, :3].astype(np.float64), None, data[:, 3].copy())


def _header_says_empty(path: Path) -> bool:
    head = path.read_bytes()[:4096].decode("latin-1")
    return ("POINTS 0\n" in head or "POINTS 0\r" in head) or "element vertex 0\n" in head


def read_o3d(path: Path, stamp_ns: int | None = None) -> CloudData:
    from lidar_slam.o3d import o3d

    try:
        with open(path, "rb") as fh:
            magic = fh.read(16)
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc
    kind = path.suffix.lower()
    if (kind == ".ply" and not magic.startswith(b"ply")) or (
        kind == ".pcd" and not (magic.startswith(b"#") or magic.startswith(b"VERSION")
                                or magic.startswith(b"FIELDS"))
    ):
        raise InputError(path, f"not a valid {kind[1:].upper()} file (bad header)")
    pcd = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pcd.point or len(pcd.point.positions) == 0:
        if _header_says_empty(path):
            return CloudData(np.zeros((0, 3)), None, None)
        raise InputError(path, f"unreadable {kind[1:].upper()} file (no points could be decoded)")
    pts = pcd.point.positions.numpy().astype(np.float64).reshape(-1, 3)
    times = intensity = None
    for name in TIME_FIELDS:
        if name in pcd.point:
            times = relative_seconds(pcd.point[name].numpy().ravel(), stamp_ns)
            break
    for name in INTENSITY_FIELDS:
        if name in pcd.point:
            intensity = pcd.point[name].numpy().ravel().astype(np.float32)
            break
    return CloudData(pts, times, intensity)


def read_npy(path: Path, stamp_ns: int | None = None) -> CloudData:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputError(path, f"unreadable .npy ({exc})") from exc
    if arr.dtype.names:
        names = arr.dtype.names
        if not {"x", "y", "z"} <= set(names):
            raise InputError(path, f"structured .npy needs x, y, z fields (has {', '.join(names)})")
        pts = np.c_[arr["x"], arr["y"], arr["z"]].astype(np.float64)
        tname = next((n for n in TIME_FIELDS if n in names), None)
        iname = next((n for n in INTENSITY_FIELDS if n in names), None)
        times = relative_seconds(arr[tname], stamp_ns) if tname else None
        inten = arr[iname].astype(np.float32) if iname else None
        return CloudData(pts, times, inten)
    if arr.ndim != 2 or arr.shape[1] not in (3, 4, 5):
        raise InputError(path, f"expected an (N,3|4|5) array [x y z (intensity) (time_s)], got {arr.shape}")
    pts = arr[:, :3].astype(np.float64)
    inten = arr[:, 3].astype(np.float32) if arr.shape[1] >= 4 else None
    times = relative_seconds(arr[:, 4], stamp_ns) if arr.shape[1] == 5 else None
    return CloudData(pts, times, inten)


def read_cloud(path: str | Path, stamp_ns: int | None = None) -> CloudData:
    """Read one scan file, by suffix; per-point times in seconds relative to the scan stamp
    (stamp_ns, when known, recognises absolute times; see lidar_slam.io.point_times)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".bin":
        return read_bin(p)
    if suffix in (".pcd", ".ply"):
        return read_o3d(p, stamp_ns)
    if suffix == ".npy":
        return read_npy(p, stamp_ns)
    raise InputError(p, f"unsupported scan format '{suffix}' (use {', '.join(SCAN_SUFFIXES)})")
