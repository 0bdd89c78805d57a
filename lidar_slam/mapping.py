"""Global map: keyframe clouds placed with the final poses, voxel-downsampled, written as PLY.

Built by streaming, so memory does not grow with the drive: keyframes are read from the store a
chunk at a time, their world points are split into square tiles (whole voxels, so every voxel
lies in one tile) spilled to temporary files, and each tile is downsampled and appended to the
PLY on its own. The result is the same as downsampling everything at once.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import transform_points
from lidar_slam.keyframes import KeyframeStore

TILE_VOXELS = 1000  # tile side in voxels (200 m at 0.2 m)
CHUNK_POINTS = 2_000_000  # points gathered before spilling them to the tiles


def _ply_header(n: int, intensity: bool) -> bytes:
    fields = ["x", "y", "z"] + (["intensity"] if intensity else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in fields] + ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii")


def write_ply(path: str | Path, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with float32 x, y, z and an `intensity` property when given."""
    with open(path, "wb") as fh:
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


def write_map(path: str | Path, store: KeyframeStore, T_world_kf: dict[int, np.ndarray],
              voxel_m: float) -> int:
    """Stream the store's keyframes, placed at T_world_kf, into a voxel_m-downsampled PLY map;
    returns the number of map points."""
    path = Path(path)
    table = store.table()
    ids = [int(k) for k in table["id"] if int(k) in T_world_kf]
    has_intensity = bool(len(ids)) and bool(table["has_intensity"][ids].all())
    ncol = 4 if has_intensity else 3
    tile_m = voxel_m * TILE_VOXELS if voxel_m > 0 else np.inf
    spill = Path(tempfile.mkdtemp(prefix="map_tiles_", dir=path.parent))
    try:
        tiles: set[tuple[int, int]] = set()
        buf: list[np.ndarray] = []
        n_buf = 0

        def flush() -> None:
            nonlocal buf, n_buf
            if not buf:
                return
            rows = np.concatenate(buf)
            buf, n_buf = [], 0
            key = np.floor(rows[:, :2] / tile_m).astype(np.int64) if np.isfinite(tile_m) \
                else np.zeros((len(rows), 2), np.int64)
            order = np.lexsort((key[:, 1], key[:, 0]))
            rows, key = rows[order], key[order]
            cut = np.flatnonzero(np.any(np.diff(key, axis=0) != 0, axis=1)) + 1
            for part, k in zip(np.split(rows, cut), key[np.r_[0, cut]] if len(rows) else []):
                tiles.add((int(k[0]), int(k[1])))
                with open(spill / f"{k[0]}_{k[1]}.f64", "ab") as fh:
                    fh.write(part.tobytes())

        for kf_id in ids:
            kf = store.get(kf_id)
            pts = transform_points(T_world_kf[kf_id], kf.points.astype(np.float64))
            cols = [pts] + ([kf.intensity.astype(np.float64)[:, None]] if has_intensity else [])
            buf.append(np.hstack(cols))
            n_buf += len(pts)
            if n_buf >= CHUNK_POINTS:
                flush()
        flush()
        body = spill / "body.bin"
        n = 0
        with open(body, "wb") as out:
            for tx, ty in sorted(tiles):
                rows = np.fromfile(spill / f"{tx}_{ty}.f64").reshape(-1, ncol)
                pts, inten = voxel_downsample(rows[:, :3], voxel_m,
                                              rows[:, 3] if has_intensity else None)
                out.write(_rows(pts, inten).tobytes())
                n += len(pts)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as out, open(body, "rb") as src:
            out.write(_ply_header(n, has_intensity))
            shutil.copyfileobj(src, out, 1 << 24)
        os.replace(tmp, path)
        return n
    finally:
        shutil.rmtree(spill, ignore_errors=True)
