"""A saved map's points as a file other tools open: PLY (lidar_slam.io.ply), PCD (open3d's
writer) or LAS / LAZ (laspy, the only module that imports it), with intensity and the id of the
keyframe each point
comes from. Points are the keyframe clouds as the run stored them, placed with the final poses in
the map frame (the frame of the run's poses_kitti.txt); --voxel keeps the first of each voxel.

A run with GNSS (a geo reference, lidar_slam.geo) gives LAS / LAZ in UTM instead: easting,
northing (m) in the zone of the ENU datum and the ellipsoidal height (m), with the CRS (WGS 84 /
UTM zone N as WKT, its EPSG code 326NN / 327NN) in the header, so GIS tools place the cloud on a
map. PLY and PCD (float32 coordinates: millimetres would be lost at UTM magnitudes) stay in the
map frame."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np

from lidar_slam.errors import LidarSlamError
from lidar_slam.frontend.downsample import voxel_first_indices
from lidar_slam.geo import GeoReference
from lidar_slam.io.atomic import atomic_path
from lidar_slam.io.ply import write_ply
from lidar_slam.map.saved import SavedMap

log = logging.getLogger(__name__)


class PointFormat(str, Enum):
    ply = "ply"
    pcd = "pcd"
    las = "las"
    laz = "laz"


class MissingDependency(LidarSlamError):
    """An optional package needed for this output is not installed."""


LASPY_HINT = "LAS/LAZ export needs laspy: pip install 'laspy[lazrs]' (or 'lidar-slam[export]')"


@dataclass(frozen=True)
class MapPoints:
    """points (N, 3) float64 map frame metres; intensity (N,) float32 (zeros when the scans
    had none); keyframe (N,) uint32 id of the keyframe each point comes from; geo: the map's
    geo reference (LAS / LAZ are then written in UTM), or None."""

    points: np.ndarray
    intensity: np.ndarray
    keyframe: np.ndarray
    geo: GeoReference | None = None


def map_points(saved_map: SavedMap, voxel_m: float | None = None) -> MapPoints:
    """Every stored keyframe point in the map frame; with voxel_m, the first point (keyframe
    order) of each voxel_m voxel."""
    pts, inten, kf = [], [], []
    for k in range(len(saved_map)):
        if not saved_map.counts[k]:
            continue
        p, i = saved_map.points_map(k)
        pts.append(p)
        inten.append(np.zeros(len(p), np.float32) if i is None else i.astype(np.float32))
        kf.append(np.full(len(p), k, np.uint32))
    if not pts:
        return MapPoints(np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.uint32),
                         saved_map.geo)
    out = MapPoints(np.concatenate(pts), np.concatenate(inten), np.concatenate(kf),
                    saved_map.geo)
    if voxel_m is None:
        return out
    keep = voxel_first_indices(out.points, voxel_m)
    return MapPoints(out.points[keep], out.intensity[keep], out.keyframe[keep], out.geo)


def format_of(path: Path, fmt: PointFormat | None) -> PointFormat:
    """The format asked for, else the one the file name says."""
    named = path.suffix.lower().lstrip(".")
    if fmt is not None:
        if named in {f.value for f in PointFormat} and named != fmt.value:
            raise LidarSlamError(f"{path}: --format {fmt.value}, but the name says {named}; "
                                 f"name it .{fmt.value}, or drop --format")
        return fmt
    try:
        return PointFormat(named)
    except ValueError:
        raise LidarSlamError(f"{path}: cannot tell the format from the name; pass --format "
                             f"{'|'.join(f.value for f in PointFormat)}") from None


def write_points(path: Path, fmt: PointFormat, mp: MapPoints) -> int:
    """Write mp to path (atomically) in fmt; returns the number of points written. LAS / LAZ
    of a map with a geo reference are in UTM (see the module doc)."""
    if fmt in (PointFormat.las, PointFormat.laz):
        _write_las(path, mp, compressed=fmt == PointFormat.laz)
    elif fmt == PointFormat.ply:
        p = mp.points.astype(np.float32)
        # keyframe as int32: the type open3d's PLY writer gave it (it has no uint32 property).
        write_ply(path, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "intensity": mp.intensity,
                         "keyframe": mp.keyframe.astype(np.int32)})
    else:
        _write_pcd(path, mp)
    return len(mp.points)


def _write_pcd(path: Path, mp: MapPoints) -> None:
    from lidar_slam.o3d import o3d

    cloud = o3d.t.geometry.PointCloud()
    cloud.point.positions = o3d.core.Tensor(mp.points.astype(np.float32))
    cloud.point.intensity = o3d.core.Tensor(mp.intensity.reshape(-1, 1))
    cloud.point.keyframe = o3d.core.Tensor(mp.keyframe.astype(np.uint32).reshape(-1, 1))
    with atomic_path(path) as tmp:
        # open3d picks the writer by the file name's suffix.
        named = tmp.with_name(tmp.name + ".pcd")
        if not o3d.t.io.write_point_cloud(str(named), cloud):
            raise LidarSlamError(f"{path}: open3d could not write the PCD file")
        named.replace(tmp)


def las_intensity(intensity: np.ndarray) -> np.ndarray:
    """LAS intensity (uint16): values in 0..1 (KITTI-style reflectance) scaled to 0..65535,
    others rounded and clipped to that range."""
    scale = 65535.0 if len(intensity) and float(intensity.max()) <= 1.0 else 1.0
    return np.clip(np.rint(intensity * scale), 0, 65535).astype(np.uint16)


def require_laspy():
    """The laspy module, or MissingDependency (one line: what to install)."""
    try:
        import laspy
    except ImportError:
        raise MissingDependency(LASPY_HINT) from None
    return laspy


def _write_las(path: Path, mp: MapPoints, compressed: bool) -> None:
    laspy = require_laspy()
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="keyframe", type=np.uint32,
                                                description="lidar-slam keyframe id"))
    xyz = mp.points
    if mp.geo is not None:
        xyz = mp.geo.map_to_utm(mp.points) if len(mp.points) else mp.points
        header.add_crs(mp.geo.utm_crs())
    header.scales = np.array([0.001, 0.001, 0.001])  # mm
    # Offsets at the data's lower corner: 32-bit mm counts then reach 2147 km from it.
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = las_intensity(mp.intensity)
    las.keyframe = mp.keyframe
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        # A stream, not a name: given a name laspy decides compression by its suffix.
        if not compressed:
            las.write(fh, do_compress=False)
            return
        try:
            las.write(fh, do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
        except laspy.errors.LaspyException as exc:
            raise MissingDependency(f"{LASPY_HINT} ({exc})") from None
