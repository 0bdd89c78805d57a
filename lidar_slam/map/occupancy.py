"""A 2-D occupancy grid of a saved map, written in the ROS map_server format (map.png +
map.yaml).

Each keyframe's cloud is levelled on the ground fitted below its sensor (lidar_slam.registration).
Points in the height band above that ground are obstacles: their cell gets a hit. Free space
comes from the rays: from the sensor towards each point, the stretch of the ray that lies inside
the band (all of it for a ground point: an obstacle standing there would have stopped the ray;
up to the cell before the point for an obstacle) marks the cells it crosses free. Rays are taken
per azimuth bin of each keyframe (the longest free stretch of the bin: rays from one origin along
one bearing cover each other). Hits and passes are combined per cell in log-odds; cells that no
ray reached stay unknown.

The grid lies in the map frame's x-y plane (the frame of the run's poses_kitti.txt, whose z is
the first scan's sensor axis: level for a vehicle-mounted lidar). A run with GNSS also gets
map.yaml's `geo` keys (map_server ignores them): the map frame's origin in WGS84, the compass
heading of its x axis, and the image's lower-left corner in UTM (see write_map_server).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import LidarSlamError
from lidar_slam.geo import GeoReference
from lidar_slam.io.atomic import atomic_path, write_text_atomic
from lidar_slam.map.saved import SavedMap
from lidar_slam.registration import level_ground

log = logging.getLogger(__name__)

UNKNOWN, FREE, OCCUPIED = -1, 0, 100  # cell states, as in nav_msgs/OccupancyGrid
PNG_VALUE = {OCCUPIED: 0, FREE: 254, UNKNOWN: 205}  # map_server's trinary image values
MAX_CELLS = 400_000_000


@dataclass(frozen=True)
class OccupancyParams:
    """resolution_m: cell side; band_m: (low, high) heights above the fitted ground that count
    as obstacles; max_range_m: rays and hits beyond this distance from the sensor are cut;
    azimuth_bins: rays per keyframe; p_hit / p_miss: the inverse sensor model; occupied_thresh
    / free_thresh: written into map.yaml and used to classify the cells."""

    resolution_m: float = 0.1
    band_m: tuple[float, float] = (0.3, 2.0)
    max_range_m: float = 40.0
    azimuth_bins: int = 1440
    p_hit: float = 0.7
    p_miss: float = 0.4
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196


@dataclass(frozen=True)
class OccupancyGrid:
    """state (rows, cols) int8 UNKNOWN / FREE / OCCUPIED; row 0 at origin_xy[1] (the lowest
    y), column 0 at origin_xy[0]; origin_xy: map-frame corner of cell (0, 0), metres; geo: the
    map's geo reference, or None."""

    state: np.ndarray
    resolution_m: float
    origin_xy: np.ndarray
    geo: GeoReference | None = None

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of map-frame points (N, 2); may lie outside the grid."""
        ij = np.floor((np.asarray(xy) - self.origin_xy) / self.resolution_m).astype(np.int64)
        return ij[:, 1], ij[:, 0]

    def at(self, xy: np.ndarray) -> np.ndarray:
        """States of the cells holding map-frame points (N, 2) (UNKNOWN outside the grid)."""
        rows, cols = self.cells(xy)
        h, w = self.state.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        out = np.full(len(rows), UNKNOWN, np.int8)
        out[inside] = self.state[rows[inside], cols[inside]]
        return out

    def centres(self, state: int) -> np.ndarray:
        """Map-frame centres (N, 2) of the cells in a state."""
        rows, cols = np.nonzero(self.state == state)
        return self.origin_xy + (np.c_[cols, rows] + 0.5) * self.resolution_m


@dataclass(frozen=True)
class _Rays:
    """One keyframe's contribution: origin (2,), free stretch per azimuth bin (bearing unit
    vectors (B, 2), start and end distances (B,)), and obstacle points (M, 2), map frame."""

    origin: np.ndarray
    bearings: np.ndarray
    start_m: np.ndarray
    end_m: np.ndarray
    hits: np.ndarray


def _keyframe_rays(points_kf: np.ndarray, T_map_kf: np.ndarray, default_height_m: float,
                   params: OccupancyParams) -> _Rays:
    """Obstacle points and free ray stretches of one keyframe cloud (N, 3), its frame."""
    ground = level_ground(points_kf)
    h0 = ground.height_m if ground.height_m is not None else default_height_m
    height = points_kf @ ground.R_level_sensor[2] + h0  # above the fitted ground
    xy = points_kf @ T_map_kf[:2, :3].T + T_map_kf[:2, 3]
    origin = T_map_kf[:2, 3]
    d = xy - origin
    dist = np.hypot(d[:, 0], d[:, 1])
    lo, hi = params.band_m
    near = (dist > 1e-3) & (dist <= params.max_range_m)
    hits = xy[near & (height >= lo) & (height <= hi)]
    # The part of each ray (fractions f0..f1 of it) whose height lies in the band: the height
    # goes linearly from h0 at the sensor to the point's.
    with np.errstate(divide="ignore", invalid="ignore"):
        f_lo = (lo - h0) / (height - h0)
        f_hi = (hi - h0) / (height - h0)
    f0 = np.where(h0 > hi, f_hi, np.where(h0 < lo, f_lo, 0.0))
    f1 = np.where(height > hi, np.where(h0 > hi, 0.0, f_hi), 1.0)
    f1 = np.where(height < lo, 1.0, f1)  # a ground point: free up to it
    end = f1 * dist
    end = np.where((height >= lo) & (height <= hi), dist - params.resolution_m, end)
    start = np.clip(f0, 0.0, 1.0) * dist
    end = np.minimum(end, params.max_range_m)
    ok = (dist > 1e-3) & np.isfinite(start) & np.isfinite(end) & (end > start)
    azimuth = np.arctan2(d[ok, 1], d[ok, 0])
    bins = ((azimuth + np.pi) / (2 * np.pi) * params.azimuth_bins).astype(np.int64)
    bins = np.minimum(bins, params.azimuth_bins - 1)
    # Per bin the ray that reaches farthest (its start kept with it).
    order = np.lexsort((end[ok], bins))
    last = np.r_[bins[order][1:] != bins[order][:-1], True]
    pick = order[last]
    centre = (bins[pick] + 0.5) / params.azimuth_bins * 2 * np.pi - np.pi
    return _Rays(origin, np.c_[np.cos(centre), np.sin(centre)], start[ok][pick], end[ok][pick],
                 hits)


def _free_cells(rays: _Rays, origin_xy: np.ndarray, shape: tuple[int, int],
                res: float) -> np.ndarray:
    """Flat cell index of every sample along the free stretches (a sample per cell length)."""
    n0 = np.floor(rays.start_m / res).astype(np.int64)
    n1 = np.floor(rays.end_m / res).astype(np.int64)
    count = np.maximum(n1 - n0, 0)
    total = int(count.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    ray = np.repeat(np.arange(len(count)), count)
    step = np.arange(total) - np.repeat(np.cumsum(count) - count, count) + np.repeat(n0, count)
    dist = (step + 0.5) * res
    xy = rays.origin + rays.bearings[ray] * dist[:, None]
    return _flat(xy, origin_xy, shape, res)


def _flat(xy: np.ndarray, origin_xy: np.ndarray, shape: tuple[int, int], res: float
          ) -> np.ndarray:
    ij = np.floor((xy - origin_xy) / res).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[0])
    return ij[inside, 1] * shape[1] + ij[inside, 0]


def build_grid(saved_map: SavedMap, params: OccupancyParams = OccupancyParams()
               ) -> OccupancyGrid:
    """The occupancy grid of a saved map (see the module doc)."""
    res = params.resolution_m
    default_h = saved_map.cfg.loop.scan_context.sensor_height_m
    all_rays = []
    for k in range(len(saved_map)):
        if saved_map.counts[k]:
            pts = saved_map.keyframe(k).points.astype(np.float64)
            all_rays.append(_keyframe_rays(pts, saved_map.T_map_kf[k], default_h, params))
    if not all_rays:
        raise LidarSlamError(f"{saved_map.run_dir}: the map holds no points")
    # The grid spans every hit and the far end of every free stretch.
    reach = np.concatenate([np.r_[r.origin[None], r.hits, r.origin + r.bearings * r.end_m[:, None]]
                            for r in all_rays])
    origin_xy = np.floor(reach.min(0) / res) * res - res
    shape = (int(np.ceil((reach.max(0)[1] - origin_xy[1]) / res)) + 2,
             int(np.ceil((reach.max(0)[0] - origin_xy[0]) / res)) + 2)
    if shape[0] * shape[1] > MAX_CELLS:
        raise LidarSlamError(f"{shape[1]} x {shape[0]} cells at {res:g} m: too many; pass a "
                             f"coarser --resolution")
    n_cells = shape[0] * shape[1]
    hits = np.zeros(n_cells, np.int64)
    free = np.zeros(n_cells, np.int64)
    hit_chunk: list[np.ndarray] = []
    free_chunk: list[np.ndarray] = []
    size = 0
    for i, r in enumerate(all_rays):  # cell counts by bincount over chunks of samples
        hit_chunk.append(_flat(r.hits, origin_xy, shape, res))
        free_chunk.append(_free_cells(r, origin_xy, shape, res))
        size += len(free_chunk[-1])
        if size > 20_000_000 or i == len(all_rays) - 1:
            hits += np.bincount(np.concatenate(hit_chunk), minlength=n_cells)
            free += np.bincount(np.concatenate(free_chunk), minlength=n_cells)
            hit_chunk, free_chunk, size = [], [], 0
    logit = lambda p: np.log(p / (1.0 - p))  # noqa: E731
    odds = hits * logit(params.p_hit) + free * logit(params.p_miss)
    p = 1.0 / (1.0 + np.exp(-odds))
    state = np.full(n_cells, UNKNOWN, np.int8)
    seen = (hits + free) > 0
    state[seen & (p > params.occupied_thresh)] = OCCUPIED
    state[seen & (p < params.free_thresh)] = FREE
    grid = OccupancyGrid(state.reshape(shape), res, origin_xy, saved_map.geo)
    log.info("occupancy grid %d x %d: %d occupied, %d free cells", shape[1], shape[0],
             int((state == OCCUPIED).sum()), int((state == FREE).sum()))
    return grid


def write_map_server(grid: OccupancyGrid, out_dir: Path, params: OccupancyParams,
                     name: str = "map") -> tuple[Path, Path]:
    """NAME.png (trinary: 0 occupied, 254 free, 205 unknown; top row = highest y) and NAME.yaml
    (image, mode, resolution, origin, negate, thresholds; with a geo reference also `geo`, see
    geo_yaml), both written atomically."""
    from PIL import Image

    image = np.full(grid.state.shape, PNG_VALUE[UNKNOWN], np.uint8)
    image[grid.state == FREE] = PNG_VALUE[FREE]
    image[grid.state == OCCUPIED] = PNG_VALUE[OCCUPIED]
    png, yaml_path = out_dir / f"{name}.png", out_dir / f"{name}.yaml"
    with atomic_path(png) as tmp:
        Image.fromarray(image[::-1]).save(tmp, format="PNG")
    x0, y0 = (float(v) for v in grid.origin_xy)
    write_text_atomic(yaml_path, (
        "# lidar-slam occupancy grid (ROS map_server format); frame: the map run's\n"
        "# poses_kitti.txt frame; origin: map-frame pose of the lower-left pixel (x, y, yaw)\n"
        f"image: {png.name}\nmode: trinary\nresolution: {grid.resolution_m:g}\n"
        f"origin: [{x0:.6f}, {y0:.6f}, 0.0]\nnegate: 0\n"
        f"occupied_thresh: {params.occupied_thresh:g}\nfree_thresh: {params.free_thresh:g}\n"
        + ("" if grid.geo is None else geo_yaml(grid))))
    return png, yaml_path


def geo_yaml(grid: OccupancyGrid) -> str:
    """map.yaml's `geo` mapping: the map frame's origin (WGS84 lat, lon deg, ellipsoidal height
    m), the compass heading of its x axis (deg clockwise from true north), the UTM zone's EPSG
    code and the lower-left image corner (map-frame z = 0) in UTM (easting, northing, height m)."""
    lat, lon, alt = grid.geo.origin_wgs84
    x0, y0 = (float(v) for v in grid.origin_xy)
    corner = grid.geo.map_to_utm(np.array([x0, y0, 0.0]))[0]
    return ("# geo: where the map frame lies on the Earth (lidar-slam's keys, not map_server's)\n"
            f"geo:\n  origin_lat_deg: {lat:.9f}\n  origin_lon_deg: {lon:.9f}\n"
            f"  origin_alt_m: {alt:.4f}\n  heading_deg: {grid.geo.heading_deg:.6f}\n"
            f"  utm_epsg: {grid.geo.utm_epsg}\n"
            f"  image_origin_utm: [{corner[0]:.3f}, {corner[1]:.3f}, {corner[2]:.3f}]\n")
