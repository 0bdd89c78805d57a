"""Global map: keyframe clouds placed with the final poses, voxel-downsampled, written as PLY."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import transform_points
from lidar_slam.types import Keyframe


def build_map(keyframes: list[Keyframe], T_world_kf: dict[int, np.ndarray], voxel_m: float
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """World-frame map points (M,3) and intensity (M,) or None, downsampled to voxel_m."""
    if not keyframes:
        return np.zeros((0, 3)), None
    has_intensity = all(kf.intensity is not None for kf in keyframes)
    pts = np.concatenate([transform_points(T_world_kf[kf.id], kf.points.astype(np.float64))
                          for kf in keyframes])
    inten = np.concatenate([kf.intensity for kf in keyframes]) if has_intensity else None
    return voxel_downsample(pts, voxel_m, inten)


def write_ply(path: str | Path, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with float32 x, y, z and an `intensity` property when given."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if intensity is not None:
        fields.append(("intensity", "<f4"))
    rows = np.empty(len(points), dtype=fields)
    rows["x"], rows["y"], rows["z"] = points[:, 0], points[:, 1], points[:, 2]
    if intensity is not None:
        rows["intensity"] = intensity
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property float {name}" for name, _ in fields] + ["end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rows.tobytes())
