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
    """One int64 key per point for its voxel, and the number of cells in the bounding grid."""
    inv = 1.0 / voxel_m
    keys = np.zeros(len(points), dtype=np.int64)
    n_cells = 1
    for axis in range(3):  # column by column: reductions over axis 0 of (N, 3) are slow
        c = points[:, axis] * inv
        c -= np.floor(c.min())
        cells = c.astype(np.int64)  # non-negative, so truncation is floor
        dim = int(cells.max()) + 1
        keys *= dim
        keys += cells
        n_cells *= dim
    return keys, n_cells


_GRID = np.empty(0, dtype=np.int32)


def _scatter_grid(n_cells: int) -> np.ndarray:
    """A reused int32 buffer of at least n_cells: a fresh one costs a page fault per touched page."""
    global _GRID
    if len(_GRID) < n_cells:
        _GRID = np.empty(n_cells, dtype=np.int32)
    return _GRID


def voxel_first_indices(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of one input point per occupied voxel of voxel_m metres (sorted, ascending)."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    keys, n_cells = _cell_keys(points, voxel_m)
    if n_cells <= _MAX_DENSE_CELLS:
        grid = _scatter_grid(n_cells)  # only the cells written below are read
        idx = np.arange(len(keys), dtype=np.int32)
        grid[keys] = idx
        return np.flatnonzero(grid[keys] == idx)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    return np.sort(order[np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]])


def voxel_downsample(points: np.ndarray, voxel_m: float, intensity: np.ndarray | None = None,
                     reduce: Literal["mean", "first"] = "mean"
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per voxel of voxel_m metres (see the module doc for `reduce`)."""
    if len(points) == 0 or voxel_m <= 0:
        return points, intensity
    if reduce == "first":
        keep = voxel_first_indices(points, voxel_m)
        return points[keep], None if intensity is None else intensity[keep]
    keys, _ = _cell_keys(points, voxel_m)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    counts = np.diff(np.r_[starts, len(keys)])[:, None]
    out = np.add.reduceat(points[order], starts, axis=0) / counts
    out_i = None
    if intensity is not None:
        out_i = (np.add.reduceat(np.asarray(intensity, np.float64)[order], starts)
                 / counts[:, 0]).astype(np.float32)
    return out, out_i
