"""Global map: keyframe clouds placed with the final poses, voxel-downsampled, written as PLY.

Built by streaming, so memory does not grow with the drive (see write_map).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from lidar_slam.geometry import transform_points
from lidar_slam.io.atomic import atomic_path
from lidar_slam.keyframes import KeyframeStore

TILE_VOXELS = 500  # tile side in voxels (100 m at 0.2 m)
CHUNK_POINTS = 250_000  # points gathered before reducing and spilling them to the tiles


def _ply_header(n: int, intensity: bool) -> bytes:
    fields = ["x", "y", "z"] + (["intensity"] if intensity else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in fields] + ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii")


def write_ply(path: str | Path, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with float32 x, y, z and an `intensity` property when given
    (written atomically)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(_ply_header(len(points), intensity is not None))
        fh.write(_rows(points, intensity).tobytes())


def _rows(points: np.ndarray, intensity: np.ndarray | None) -> np.ndarray:
    cols = [points.astype(np.float32)]
    if intensity is not None:
        cols.append(np.asarray(intensity, np.float32)[:, None])
    return np.ascontiguousarray(np.hstack(cols))


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N,3) float64 and intensity (N,) or None of a PLY written by write_ply/write_map."""
    with open(path, "rb") as fh:
        header = []
        while not header or header[-1] != "end_header":
            header.append(fh.readline().decode("ascii").strip())
        n = int(next(h.split()[2] for h in header if h.startswith("element vertex")))
        ncol = sum(h.startswith("property float") for h in header)
        rows = np.fromfile(fh, dtype="<f4", count=n * ncol).reshape(n, ncol)
    return rows[:, :3].astype(np.float64), rows[:, 3].copy() if ncol == 4 else None


_AXIS_BITS = 21  # voxel coordinates per axis: +-2^20 voxels (+-210 km at 0.2 m)


def _voxel_keys(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World voxel key (int64) per point, and its tile (int64) of TILE_VOXELS^2 voxels."""
    cells = np.floor(points / voxel_m).astype(np.int64) + (1 << (_AXIS_BITS - 1))
    keys = (cells[:, 0] << (2 * _AXIS_BITS)) | (cells[:, 1] << _AXIS_BITS) | cells[:, 2]
    tiles = (cells[:, 0] // TILE_VOXELS) * (1 << _AXIS_BITS) + cells[:, 1] // TILE_VOXELS
    return keys, tiles


def _reduce(keys: np.ndarray, sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sum the rows of sums (K, C) that share a key: (unique keys, summed rows)."""
    order = np.argsort(keys, kind="stable")
    keys, sums = keys[order], sums[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    return keys[starts], np.add.reduceat(sums, starts, axis=0)


def write_map(path: str | Path, store: KeyframeStore, T_world_kf: dict[int, np.ndarray],
              voxel_m: float) -> int:
    """Stream the store's keyframes, placed at T_world_kf, into a PLY map of one point per
    voxel_m voxel (the centroid of its points, with their mean intensity); returns the number of
    map points.

    Memory stays bounded: keyframes are read a chunk at a time, each chunk is reduced to per-voxel
    sums (x, y, z, intensity, count) split by tile and spilled to temporary files, and each tile
    is then reduced on its own and appended to the PLY body. The result equals downsampling all
    points at once (up to the order of the float sums).
    """
    if not voxel_m > 0:
        raise ValueError(f"map voxel size must be positive, got {voxel_m}")
    path = Path(path)
    table = store.table()
    ids = [int(k) for k in table["id"] if int(k) in T_world_kf]
    has_intensity = bool(len(ids)) and bool(table["has_intensity"][ids].all())
    spill = Path(tempfile.mkdtemp(prefix="map_tiles_", dir=path.parent))
    try:
        tiles: set[int] = set()
        buf: list[np.ndarray] = []
        n_buf = 0

        def flush() -> None:
            nonlocal buf, n_buf
            if not buf:
                return
            rows = np.concatenate(buf)  # x y z intensity, world frame
            buf, n_buf = [], 0
            keys, tile = _voxel_keys(rows[:, :3], voxel_m)
            sums = np.hstack([rows, np.ones((len(rows), 1))])  # + count
            order = np.argsort(tile, kind="stable")
            tile, keys, sums = tile[order], keys[order], sums[order]
            cut = np.flatnonzero(tile[1:] != tile[:-1]) + 1
            for t, k, s in zip(tile[np.r_[0, cut]], np.split(keys, cut), np.split(sums, cut)):
                k, s = _reduce(k, s)
                tiles.add(int(t))
                with open(spill / f"{int(t)}.bin", "ab") as fh:
                    fh.write(np.hstack([k.view(np.float64)[:, None], s]).tobytes())

        for kf_id in ids:
            kf = store.get(kf_id)
            pts = transform_points(T_world_kf[kf_id], kf.points.astype(np.float64))
            inten = kf.intensity if has_intensity else np.zeros(len(pts), np.float32)
            buf.append(np.hstack([pts, inten.astype(np.float64)[:, None]]))
            n_buf += len(pts)
            if n_buf >= CHUNK_POINTS:
                flush()
        flush()
        body = spill / "body.bin"
        n = 0
        with open(body, "wb") as out:
            for t in sorted(tiles):
                rec = np.fromfile(spill / f"{t}.bin").reshape(-1, 6)
                keys, sums = _reduce(np.ascontiguousarray(rec[:, 0]).view(np.int64), rec[:, 1:])
                mean = sums[:, :4] / sums[:, 4:5]
                out.write(_rows(mean[:, :3], mean[:, 3] if has_intensity else None).tobytes())
                n += len(keys)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as out, open(body, "rb") as src:
            out.write(_ply_header(n, has_intensity))
            shutil.copyfileobj(src, out, 1 << 24)
        os.replace(tmp, path)
        return n
    finally:
        shutil.rmtree(spill, ignore_errors=True)
