"""Voxel downsampling that keeps an intensity channel (keyframe and map clouds).

Plain NumPy so that odometry-only runs never pay for importing open3d. Two reductions:
"mean" (the centroid of each voxel's points, for the final map) and "first" (one input point
per voxel, as kiss-icp keeps; a scatter into a dense cell grid, several times faster, for the
per-keyframe clouds on the odometry's hot path).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

_MAX_DENSE_CELLS = 1 << 25  # 128 MB of int32 at most for the scatter grid


def _cell_keys(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, int]:
    cells = np.floor(points * (1.0 / voxel_m)).astype(np.int64)
    lo = cells.min(axis=0)
    dims = cells.max(axis=0) - lo + 1
    cells -= lo
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    return keys, int(dims.prod())


def voxel_downsample(points: np.ndarray, voxel_m: float, intensity: np.ndarray | None = None,
                     reduce: Literal["mean", "first"] = "mean"
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per voxel of voxel_m metres (see the module doc for `reduce`)."""
    if len(points) == 0 or voxel_m <= 0:
        return points, intensity
    keys, n_cells = _cell_keys(points, voxel_m)
    if reduce == "first" and n_cells <= _MAX_DENSE_CELLS:
        grid = np.empty(n_cells, dtype=np.int32)  # only the cells written below are read
        idx = np.arange(len(keys), dtype=np.int32)
        grid[keys] = idx
        keep = grid[keys] == idx
        return points[keep], None if intensity is None else intensity[keep]
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    if reduce == "first":
        keep = order[starts]
        return points[keep], None if intensity is None else intensity[keep]
    counts = np.diff(np.r_[starts, len(keys)])[:, None]
    out = np.add.reduceat(points[order], starts, axis=0) / counts
    out_i = None
    if intensity is not None:
        out_i = (np.add.reduceat(np.asarray(intensity, np.float64)[order], starts)
                 / counts[:, 0]).astype(np.float32)
    return out, out_i
