"""PLY files: binary little-endian, one vertex element of named float32 / int32 / uint32 columns.

The one PLY writer of the package: the run's map.ply (lidar_slam.map.writer, streamed: header first,
then a body built tile by tile) and `lidar-slam export`'s PLY (lidar_slam.map.export) both go
through
it, and always atomically.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np

from lidar_slam.io.atomic import atomic_path

_PLY_TYPES = {np.dtype("<f4"): "float", np.dtype("<i4"): "int", np.dtype("<u4"): "uint"}


def ply_header(n: int, fields: Sequence[tuple[str, np.dtype]]) -> bytes:
    """The header of a binary little-endian PLY of n vertices with these (name, dtype) columns."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    lines += [f"property {_PLY_TYPES[np.dtype(dtype)]} {name}" for name, dtype in fields]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def xyz_fields(intensity: bool) -> list[tuple[str, np.dtype]]:
    """float32 x, y, z, and intensity when asked for (the map's columns)."""
    names = ["x", "y", "z"] + (["intensity"] if intensity else [])
    return [(name, np.dtype("<f4")) for name in names]


def xyz_rows(points: np.ndarray, intensity: np.ndarray | None) -> np.ndarray:
    """Vertex rows (N, 3 or 4) float32 of points (N, 3) and intensity (N,) or None."""
    cols = [points.astype(np.float32)]
    if intensity is not None:
        cols.append(np.asarray(intensity, np.float32)[:, None])
    return np.ascontiguousarray(np.hstack(cols))


@contextlib.contextmanager
def ply_body(path: str | Path, n: int, fields: Sequence[tuple[str, np.dtype]]
             ) -> Iterator[BinaryIO]:
    """A file to write the n vertex rows of a PLY to, its header already written; path appears
    (atomically) when the block ends without an error."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(ply_header(n, fields))
        yield fh


def write_ply(path: str | Path, columns: Mapping[str, np.ndarray]) -> None:
    """Write a PLY of the named columns (each (N,) float32, int32 or uint32), in this order."""
    fields = [(name, np.dtype(col.dtype).newbyteorder("<")) for name, col in columns.items()]
    n = len(next(iter(columns.values()))) if columns else 0
    rows = np.empty(n, dtype=np.dtype(fields))
    for name, col in columns.items():
        rows[name] = col
    with ply_body(path, n, fields) as fh:
        fh.write(rows.tobytes())


def write_xyz_ply(path: str | Path, points: np.ndarray,
                  intensity: np.ndarray | None = None) -> None:
    """PLY with float32 x, y, z and an `intensity` property when given (written atomically)."""
    with ply_body(path, len(points), xyz_fields(intensity is not None)) as fh:
        fh.write(xyz_rows(points, intensity).tobytes())


def copy_into_ply(path: str | Path, n: int, fields: Sequence[tuple[str, np.dtype]],
                  body: str | Path) -> None:
    """A PLY whose n vertex rows are the bytes of the file `body` (streamed, not loaded)."""
    with ply_body(path, n, fields) as out, open(body, "rb") as src:
        shutil.copyfileobj(src, out, 1 << 24)


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N,3) float64 and intensity (N,) or None of a PLY of float32 x, y, z[, intensity]
    (what write_xyz_ply and the run's map.ply hold)."""
    with open(path, "rb") as fh:
        header = []
        while not header or header[-1] != "end_header":
            header.append(fh.readline().decode("ascii").strip())
        n = int(next(h.split()[2] for h in header if h.startswith("element vertex")))
        ncol = sum(h.startswith("property float") for h in header)
        rows = np.fromfile(fh, dtype="<f4", count=n * ncol).reshape(n, ncol)
    return rows[:, :3].astype(np.float64), rows[:, 3].copy() if ncol == 4 else None
