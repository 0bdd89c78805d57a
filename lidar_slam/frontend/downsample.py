"""Voxel downsampling in NumPy: the package's one voxel grid (keyframe, map and export clouds).

A point's voxel is floor(point / voxel_m) on each axis (voxel_cells); every NumPy downsampling
of the package keys its points by it. Two reductions: "mean" (the centroid of each voxel's
points, with their mean intensity: the run's map, whose streamed form in lidar_slam.map.writer adds
up the same per-voxel sums tile by tile, sum_by_key) and "first" (the first input point of each
voxel, in input order: `lidar-slam export --voxel`).

Not here, on purpose: the odometry's selection and kiss-icp's own downsampling
(kiss_icp's C++ `_voxel_down_sample`, lidar_slam.frontend.odometry) and small_gicp's voxel centroids
(lidar_slam.registration): the poses and loop constraints are those libraries' results bit for
bit. Plain NumPy so that odometry-only runs never pay for importing open3d.
"""

from __future__ import annotations

from typing import Literal

import numpy as np


def voxel_cells(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The voxel (N, 3) int64 of each point of points (N, 3), metres: floor(points / voxel_m)."""
    return np.floor(points / voxel_m).astype(np.int64)


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 per point, equal for points in the same voxel and different otherwise."""
    cells = voxel_cells(points, voxel_m)
    if len(cells) == 0:
        return np.zeros(0, dtype=np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:  # too many cells for one int64
        return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)
    return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]


def sum_by_key(keys: np.ndarray, rows: np.ndarray, counts: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sum the rows (K, C) that share a key, and their counts (each row counts `counts`, else
    1): (unique keys ascending, summed rows, summed counts)."""
    order = np.argsort(keys)
    keys = keys[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    sums = np.add.reduceat(rows[order], starts, axis=0)
    if counts is None:
        counts = np.diff(np.r_[starts, len(keys)]).astype(np.float64)
    else:
        counts = np.add.reduceat(counts[order], starts)
    return keys[starts], sums, counts


def voxel_first_indices(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of the first input point of each occupied voxel of voxel_m metres (ascending)."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    _, first = np.unique(voxel_keys(points, voxel_m), return_index=True)
    return np.sort(first)


def voxel_downsample(points: np.ndarray, voxel_m: float, intensity: np.ndarray | None = None,
                     reduce: Literal["mean", "first"] = "mean"
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per voxel of voxel_m metres (see the module doc for `reduce`), with its
    intensity (float32 for "mean") when given."""
    if len(points) == 0 or voxel_m <= 0:
        return points, intensity
    if reduce == "first":
        keep = voxel_first_indices(points, voxel_m)
        return points[keep], None if intensity is None else intensity[keep]
    rows = points if intensity is None else np.c_[points, np.asarray(intensity, np.float64)]
    _, sums, counts = sum_by_key(voxel_keys(points, voxel_m), rows)
    mean = sums / counts[:, None]
    if intensity is None:
        return mean, None
    return mean[:, :3], mean[:, 3].astype(np.float32)
