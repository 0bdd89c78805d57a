"""Voxel downsampling that keeps an intensity channel (keyframe and map clouds).

Plain NumPy so that odometry-only runs never pay for importing open3d.
"""

from __future__ import annotations

import numpy as np


def voxel_downsample(points: np.ndarray, voxel_m: float, intensity: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per voxel of voxel_m metres (the mean of its points), intensity averaged alike."""
    if len(points) == 0 or voxel_m <= 0:
        return points, intensity
    cells = np.floor(points / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
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
