"""Global map: keyframe clouds placed with the final poses, voxel-downsampled, written as PLY.

Built by streaming, so memory does not grow with the drive (see write_map). read_ply (from
lidar_slam.io.ply) reads map.ply back; the README documents it as lidar_slam.map.writer.read_ply.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from lidar_slam.frontend.downsample import sum_by_key, voxel_cells
from lidar_slam.geometry import transform_points
from lidar_slam.io.ply import copy_into_ply, read_ply, xyz_fields, xyz_rows
from lidar_slam.map.keyframes import KeyframeStore

__all__ = ["read_ply", "write_map"]

TILE_VOXELS = 500  # tile side in voxels (100 m at 0.2 m)
CHUNK_POINTS = 250_000  # points gathered before reducing and spilling them to the tiles


_XY_BITS, _Z_BITS = 21, 20  # voxel coordinates: +-2^20 voxels across (+-210 km at 0.2 m),
# +-2^19 up (+-105 km)


def _sort_keys(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, int]:
    """One uint64 per point that sorts by tile (TILE_VOXELS^2 voxels) first, then by voxel
    (x, y, z) inside it, and the shift that leaves the tile: ((tile x, tile y), local x,
    local y, z) packed high to low, so one sort groups the points of each tile and of each voxel
    in the order the map is written."""
    cells = voxel_cells(points, voxel_m)
    cells[:, :2] += 1 << (_XY_BITS - 1)
    cells[:, 2] += 1 << (_Z_BITS - 1)
    if cells.size and (cells[:, :2].min() < 0 or cells[:, :2].max() >= 1 << _XY_BITS
                       or cells[:, 2].min() < 0 or cells[:, 2].max() >= 1 << _Z_BITS):
        raise ValueError(f"map points more than {(1 << (_XY_BITS - 1)) * voxel_m:.0f} m across "
                         f"or {(1 << (_Z_BITS - 1)) * voxel_m:.0f} m up or down from the first "
                         f"keyframe: too far for {voxel_m} m map voxels")
    local_bits = (TILE_VOXELS - 1).bit_length()
    tile_bits = ((1 << _XY_BITS) // TILE_VOXELS).bit_length()
    assert 2 * (tile_bits + local_bits) + _Z_BITS <= 64
    c = cells.astype(np.uint64)
    tx, lx = np.divmod(c[:, 0], np.uint64(TILE_VOXELS))
    ty, ly = np.divmod(c[:, 1], np.uint64(TILE_VOXELS))
    key = (tx << np.uint64(tile_bits)) | ty
    key = (key << np.uint64(local_bits)) | lx
    key = (key << np.uint64(local_bits)) | ly
    key = (key << np.uint64(_Z_BITS)) | c[:, 2]
    return key, 2 * local_bits + _Z_BITS


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
        chunk = np.empty((CHUNK_POINTS, 4))  # x y z intensity, world frame
        n_buf = 0

        def flush() -> None:
            nonlocal n_buf
            if not n_buf:
                return
            rows, n_buf = chunk[:n_buf], 0
            keys, tile_shift = _sort_keys(rows[:, :3], voxel_m)
            keys, sums, counts = sum_by_key(keys, rows)
            tile = keys >> np.uint64(tile_shift)  # ascending, like the keys
            cut = np.flatnonzero(tile[1:] != tile[:-1]) + 1
            records = np.hstack([keys.view(np.float64)[:, None], sums, counts[:, None]])
            for t, rec in zip(tile[np.r_[0, cut]], np.split(records, cut)):
                tiles.add(int(t))
                with open(spill / f"{int(t)}.bin", "ab") as fh:
                    fh.write(rec.tobytes())

        for kf_id in ids:
            kf = store.get(kf_id)
            pts, T = kf.points, T_world_kf[kf_id]
            done = 0
            while done < len(pts):  # a keyframe larger than the chunk goes in pieces
                take = min(len(pts) - done, CHUNK_POINTS - n_buf)
                part = slice(done, done + take)
                rows = chunk[n_buf:n_buf + take]
                rows[:, :3] = transform_points(T, pts[part].astype(np.float64))
                rows[:, 3] = kf.intensity[part] if has_intensity else 0.0
                n_buf += take
                done += take
                if n_buf == CHUNK_POINTS:
                    flush()
        flush()
        body = spill / "body.bin"
        n = 0
        with open(body, "wb") as out:
            for t in sorted(tiles):
                rec = np.fromfile(spill / f"{t}.bin").reshape(-1, 6)
                keys, sums, counts = sum_by_key(np.ascontiguousarray(rec[:, 0]).view(np.uint64),
                                             rec[:, 1:5], rec[:, 5])
                mean = sums / counts[:, None]
                out.write(xyz_rows(mean[:, :3], mean[:, 3] if has_intensity else None).tobytes())
                n += len(keys)
        copy_into_ply(path, n, xyz_fields(has_intensity), body)
        return n
    finally:
        shutil.rmtree(spill, ignore_errors=True)
