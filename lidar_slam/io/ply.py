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

from lidar_slam.errors import InputError
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


# PLY scalar type names -> numpy type codes (byte order added by the reader)
PLY_TYPE_CODES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4",
                  "uint": "u4", "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1",
                  "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4", "float32": "f4",
                  "float64": "f8"}


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N,3) float64 and intensity (N,) float32 or None of a binary little-endian PLY
    whose first element is the vertices, with x, y, z and any other scalar properties (the
    run's map.ply, `export`'s PLY with its keyframe column, write_xyz_ply's)."""
    path = Path(path)
    with open(path, "rb") as fh:
        header: list[str] = []
        while not header or header[-1] != "end_header":
            line = fh.readline()
            if not line:
                raise InputError(path, "not a PLY file (no end_header)")
            header.append(line.decode("ascii", "replace").strip())
        if header[0] != "ply" or "format binary_little_endian 1.0" not in header:
            raise InputError(path, "read_ply reads binary little-endian PLY files only "
                             "(open3d reads the others)")
        elements = [i for i, h in enumerate(header) if h.startswith("element ")]
        if not elements or header[elements[0]].split()[1] != "vertex":
            raise InputError(path, "the first element of the PLY is not its vertices")
        n = int(header[elements[0]].split()[2])
        end = elements[1] if len(elements) > 1 else len(header)
        props = [h.split() for h in header[elements[0] + 1:end] if h.startswith("property ")]
        if any(len(p) != 3 or p[1] not in PLY_TYPE_CODES for p in props):
            raise InputError(path, "a vertex property is a list or of an unknown type")
        dtype = np.dtype([(p[2], "<" + PLY_TYPE_CODES[p[1]]) for p in props])
        if not {"x", "y", "z"} <= set(dtype.names or ()):
            raise InputError(path, "the vertices have no x, y, z")
        rows = np.fromfile(fh, dtype=dtype, count=n)
    if len(rows) < n:
        raise InputError(path, f"truncated: {len(rows)} of {n} vertices")
    points = np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float64)
    return points, (rows["intensity"].astype(np.float32) if "intensity" in dtype.names else None)
