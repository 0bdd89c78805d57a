"""A spinning-lidar simulator: a procedural street world along a trajectory, ray cast with open3d.

Conventions (also written into every sequence's README):
- Input poses are T_world_lidar (K, 4, 4) at stamps_s (K,). The world is built along the stretch
  that is simulated. The ground is ONE height field fitted to the trajectory's heights minus the
  sensor mount height; the simulated poses keep the input x, y and heading, and take z (ground +
  mount height) and roll/pitch (ground normal) from that field. Those simulated poses are the
  ones written out.
- A scan's stamp is the START of its sweep. Column c of a sweep is captured at stamp + c * period /
  n_azimuth from the pose interpolated at that instant (slerp/lerp between the simulated poses,
  extrapolated past the last one), so scans carry true motion distortion. The head starts facing
  backwards (azimuth 180 deg) and turns clockwise seen from above, like a Velodyne.
- Points are in the sensor frame of their own capture instant (raw, not deskewed); per-point times
  are seconds relative to the stamp, in [0, period).
- Output is a KITTI-layout folder: velodyne/NNNNNN.bin (float32 x, y, z, intensity),
  velodyne_times/NNNNNN.bin (float32 s), times.txt, calib.txt (Tr: T_cam_lidar, identity unless
  given), poses.txt with P_i = Tr @ T_seq_lidar_i @ inv(Tr), where the sequence frame is the
  lidar frame of the first written scan (so P_0 = I, as in KITTI).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lidar_slam.geometry import inverse
from lidar_slam.io.atomic import atomic_path, write_text_atomic
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    read_times,
    write_kitti_poses,
)
from lidar_slam.o3d import o3d

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Sensors


@dataclass(frozen=True)
class SensorModel:
    """A spinning multi-beam lidar: beam elevations (deg), azimuth steps per sweep, sweep rate."""

    name: str
    elevations_deg: tuple[float, ...]
    n_azimuth: int
    rate_hz: float
    max_range_m: float
    min_range_m: float = 1.0
    range_noise_m: float = 0.015
    dropout: float = 0.02
    mount_height_m: float = 1.73
    # Intrinsic calibration error: the lasers really point this much higher than the nominal
    # elevations the points are computed with (KITTI's HDL-64E has ~0.2 deg: kiss-icp's
    # `correct_kitti_scan` undoes 0.205 deg). Makes drift as real as the sensor's.
    elevation_error_deg: float = 0.0

    @property
    def period_s(self) -> float:
        """Duration of one sweep (s)."""
        return 1.0 / self.rate_hz

    def column_times_s(self) -> np.ndarray:
        """(A,) capture time of each azimuth column, seconds after the sweep start."""
        return np.arange(self.n_azimuth) * (self.period_s / self.n_azimuth)

    def directions(self, elevation_offset_deg: float = 0.0) -> np.ndarray:
        """(A, B, 3) unit beam directions in the sensor frame, column by column in firing order."""
        az = np.pi - 2.0 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth
        el = np.radians(np.asarray(self.elevations_deg) + elevation_offset_deg)
        ce = np.cos(el)[None, :]
        return np.stack(
            [ce * np.cos(az)[:, None], ce * np.sin(az)[:, None], np.broadcast_to(
                np.sin(el)[None, :], (len(az), len(el)))], axis=-1)


def _hdl64_elevations() -> tuple[float, ...]:
    # Upper block 32 lasers at ~1/3 deg spacing, lower block 32 at ~1/2 deg, as the HDL-64E.
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(np.r_[upper, lower].round(4))


SENSORS: dict[str, SensorModel] = {
    "hdl64": SensorModel("hdl64", _hdl64_elevations(), n_azimuth=2000, rate_hz=10.0,
                         max_range_m=120.0, range_noise_m=0.015, mount_height_m=1.73,
                         elevation_error_deg=0.2),
    "vlp16": SensorModel("vlp16", tuple(np.linspace(-15.0, 15.0, 16)), n_azimuth=1800,
                         rate_hz=10.0, max_range_m=100.0, range_noise_m=0.02,
                         mount_height_m=1.8),
    "os1-64": SensorModel("os1-64", tuple(np.linspace(16.6, -16.6, 64).round(4)), n_azimuth=1024,
                          rate_hz=10.0, max_range_m=120.0, min_range_m=0.5,
                          range_noise_m=0.015, mount_height_m=1.8),
}


def get_sensor(sensor: str | SensorModel) -> SensorModel:
    """A sensor model by name (hdl64, vlp16, os1-64) or the model itself."""
    if isinstance(sensor, SensorModel):
        return sensor
    if sensor not in SENSORS:
        raise ValueError(f"unknown sensor {sensor!r}; choose one of {sorted(SENSORS)}")
    return SENSORS[sensor]


# ----------------------------------------------------------------------------------------------
# Trajectory helpers


class PoseInterpolator:
    """T_world_lidar at any time: slerp/lerp between key poses, linear extrapolation past the ends."""

    def __init__(self, stamps_s: np.ndarray, poses: np.ndarray):
        self.t = np.asarray(stamps_s, dtype=float)
        self.poses = np.asarray(poses, dtype=float)
        if len(self.t) != len(self.poses) or len(self.t) == 0:
            raise ValueError("need as many stamps as poses, at least one")
        if np.any(np.diff(self.t) <= 0):
            raise ValueError("stamps must increase strictly")
        self.R = Rotation.from_matrix(self.poses[:, :3, :3])
        if len(self.t) > 1:
            self.dr = (self.R[:-1].inv() * self.R[1:]).as_rotvec()

    def __call__(self, times_s: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses at times_s (s)."""
        times_s = np.atleast_1d(np.asarray(times_s, dtype=float))
        out = np.tile(np.eye(4), (len(times_s), 1, 1))
        if len(self.t) == 1:
            out[:] = self.poses[0]
            return out
        i = np.clip(np.searchsorted(self.t, times_s, side="right") - 1, 0, len(self.t) - 2)
        s = (times_s - self.t[i]) / (self.t[i + 1] - self.t[i])
        out[:, :3, :3] = (self.R[i] * Rotation.from_rotvec(s[:, None] * self.dr[i])).as_matrix()
        p = self.poses[:, :3, 3]
        out[:, :3, 3] = p[i] + s[:, None] * (p[i + 1] - p[i])
        return out


@dataclass(frozen=True)
class Centerline:
    """The trajectory resampled every step_m along its xy path: road centre points and tangents."""

    xyz: np.ndarray  # (M, 3) world, z = sensor height of the input
    tangent: np.ndarray  # (M, 2) unit xy direction of travel
    arc_m: np.ndarray  # (M,) distance along the path
    tree: cKDTree

    def distance_m(self, xy: np.ndarray) -> np.ndarray:
        """Horizontal distance (m) of (N, 2) points to the nearest centre point."""
        return self.tree.query(np.asarray(xy).reshape(-1, 2))[0]


def make_centerline(poses: np.ndarray, step_m: float = 1.0, extend_m: float = 0.0) -> Centerline:
    """Resample the xy path of poses (K, 4, 4) every step_m metres, extended straight by extend_m
    before the first and after the last pose along their headings (so the world reaches ahead)."""
    p = poses[:, :3, 3]
    heading = np.c_[poses[:, 0, 0], poses[:, 1, 0], np.zeros(len(poses))]
    heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
    if extend_m > 0:
        p = np.r_[p[:1] - extend_m * heading[:1], p, p[-1:] + extend_m * heading[-1:]]
    seg = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    keep = np.r_[True, seg > 1e-6]
    p = p[keep]
    arc = np.r_[0.0, np.cumsum(seg[keep[1:]])]
    if arc[-1] < step_m:
        tan = heading[:1, :2] / np.linalg.norm(heading[0, :2])
        return Centerline(p[:1].copy(), tan, np.zeros(1), cKDTree(p[:1, :2]))
    s = np.arange(0.0, arc[-1], step_m)
    xyz = np.stack([np.interp(s, arc, p[:, j]) for j in range(3)], axis=1)
    d = np.gradient(xyz[:, :2], axis=0) if len(s) > 1 else np.diff(p[:2, :2], axis=0)
    tan = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    return Centerline(xyz, tan, s, cKDTree(xyz[:, :2]))


# ----------------------------------------------------------------------------------------------
# Terrain: one height field under the whole trajectory


@dataclass(frozen=True)
class Terrain:
    """Road-surface height field on a regular grid (world frame, metres) with a smooth evaluator."""

    x0: float
    y0: float
    resolution_m: float
    heights: np.ndarray  # (ny, nx) heights at nodes (x0 + j*res, y0 + i*res)
    spline: RectBivariateSpline

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (m) at (N, 2) world points."""
        xy = np.asarray(xy).reshape(-1, 2)
        return self.spline.ev(xy[:, 1], xy[:, 0])

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) slope (dh/dx, dh/dy) of the ground at world points."""
        xy = np.asarray(xy).reshape(-1, 2)
        return np.stack([self.spline.ev(xy[:, 1], xy[:, 0], dy=1),
                         self.spline.ev(xy[:, 1], xy[:, 0], dx=1)], axis=1)


def fit_terrain(ground_xyz: np.ndarray, bounds_xy: np.ndarray, resolution_m: float = 1.0,
                sigma_m: float = 8.0) -> Terrain:
    """Gaussian kernel regression of ground samples (N, 3) on a grid covering bounds_xy (2, 2).

    Every sample pulls the field towards its height with a weight that falls off with distance, so
    two passes over the same place that disagree in height give their average: one surface.
    Far from the samples a 5x wider kernel takes over, so the field stays defined everywhere.
    """
    (xmin, ymin), (xmax, ymax) = bounds_xy
    nx = int(np.ceil((xmax - xmin) / resolution_m)) + 1
    ny = int(np.ceil((ymax - ymin) / resolution_m)) + 1
    ix = np.clip(np.round((ground_xyz[:, 0] - xmin) / resolution_m).astype(int), 0, nx - 1)
    iy = np.clip(np.round((ground_xyz[:, 1] - ymin) / resolution_m).astype(int), 0, ny - 1)
    w = np.zeros((ny, nx))
    wz = np.zeros((ny, nx))
    np.add.at(w, (iy, ix), 1.0)
    np.add.at(wz, (iy, ix), ground_xyz[:, 2])
    s = sigma_m / resolution_m
    num = gaussian_filter(wz, s, mode="constant") + 1e-2 * gaussian_filter(wz, 5 * s, mode="constant")
    den = gaussian_filter(w, s, mode="constant") + 1e-2 * gaussian_filter(w, 5 * s, mode="constant")
    mean = float(np.mean(ground_xyz[:, 2]))
    h = (num + 1e-12 * mean) / (den + 1e-12)
    xs = xmin + resolution_m * np.arange(nx)
    ys = ymin + resolution_m * np.arange(ny)
    spline = RectBivariateSpline(ys, xs, h, kx=3, ky=3, s=0)
    return Terrain(float(xmin), float(ymin), resolution_m, h, spline)


def place_on_terrain(poses: np.ndarray, terrain: Terrain, mount_height_m: float) -> np.ndarray:
    """Poses with the input x, y and heading, z = ground + mount height, roll/pitch = ground normal."""
    xy = poses[:, :2, 3]
    g = terrain.gradient(xy)
    n = np.c_[-g, np.ones(len(g))]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    f = np.c_[np.cos(yaw), np.sin(yaw), np.zeros(len(yaw))]
    x = f - np.sum(f * n, axis=1, keepdims=True) * n
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(n, x)
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2] = x, y, n
    out[:, :2, 3] = xy
    out[:, 2, 3] = terrain.height(xy) + mount_height_m
    return out


# ----------------------------------------------------------------------------------------------
# Meshes


class _MeshBuffer:
    """Triangles of one surface class, accumulated as NumPy arrays."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.n = 0

    def add(self, v: np.ndarray, t: np.ndarray) -> None:
        self.verts.append(v)
        self.tris.append(t + self.n)
        self.n += len(v)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.verts:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        return np.concatenate(self.verts), np.concatenate(self.tris)


_BOX_TRIS = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6], [0, 4, 5], [0, 5, 1],
                      [1, 5, 6], [1, 6, 2], [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]])


def _box(cx: float, cy: float, yaw: float, length: float, width: float, z0: float, z1: float
         ) -> tuple[np.ndarray, np.ndarray]:
    """An upright box: footprint length x width centred at (cx, cy), rotated by yaw, z0..z1."""
    c, s = np.cos(yaw), np.sin(yaw)
    loc = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [length / 2, width / 2]
    xy = loc @ np.array([[c, s], [-s, c]]) + [cx, cy]
    v = np.r_[np.c_[xy, np.full(4, z0)], np.c_[xy, np.full(4, z1)]]
    return v, _BOX_TRIS


def _box_footprint(cx: float, cy: float, yaw: float, length: float, width: float,
                   step_m: float = 1.0) -> np.ndarray:
    """Points every ~step_m on the outline and centre of a rotated rectangle (for clearance)."""
    nl = max(2, int(np.ceil(length / step_m)) + 1)
    nw = max(2, int(np.ceil(width / step_m)) + 1)
    u = np.linspace(-length / 2, length / 2, nl)
    w = np.linspace(-width / 2, width / 2, nw)
    loc = np.r_[np.c_[u, np.full(nl, w[0])], np.c_[u, np.full(nl, w[-1])],
                np.c_[np.full(nw, u[0]), w], np.c_[np.full(nw, u[-1]), w], [[0.0, 0.0]]]
    c, s = np.cos(yaw), np.sin(yaw)
    return loc @ np.array([[c, s], [-s, c]]) + [cx, cy]


def _prism(cx: float, cy: float, radius: float, z0: float, z1: float, sides: int = 8
           ) -> tuple[np.ndarray, np.ndarray]:
    """A vertical n-sided prism (a pole or trunk) with caps."""
    a = 2 * np.pi * np.arange(sides) / sides
    ring = np.c_[cx + radius * np.cos(a), cy + radius * np.sin(a)]
    v = np.r_[np.c_[ring, np.full(sides, z0)], np.c_[ring, np.full(sides, z1)],
              [[cx, cy, z0], [cx, cy, z1]]]
    i = np.arange(sides)
    j = (i + 1) % sides
    side = np.r_[np.c_[i, j, j + sides], np.c_[i, j + sides, i + sides]]
    caps = np.r_[np.c_[np.full(sides, 2 * sides), j, i],
                 np.c_[np.full(sides, 2 * sides + 1), i + sides, j + sides]]
    return v, np.r_[side, caps]


def _unit_sphere() -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(1)
    v = np.asarray(m.vertices)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.asarray(m.triangles)


# ----------------------------------------------------------------------------------------------
# The world

CLASSES = ("ground", "facade", "car", "pole", "trunk", "crown", "bush", "clutter")
ALBEDO = {"ground": 0.25, "facade": 0.45, "car": 0.65, "pole": 0.5, "trunk": 0.3,
          "crown": 0.2, "bush": 0.25, "clutter": 0.55}


@dataclass(frozen=True)
class WorldParams:
    """Layout of the procedural street (metres)."""

    ground_resolution_m: float = 1.0
    terrain_sigma_m: float = 8.0
    curb_distance_m: float = 5.0
    curb_height_m: float = 0.12
    facade_setback_m: tuple[float, float] = (7.0, 12.0)
    facade_clearance_m: float = 5.5
    # A place already lined on an earlier pass (this close, this much earlier along the path) is
    # not lined again, so revisits see the same objects and not a second copy.
    revisit_radius_m: float = 6.0
    revisit_min_arc_m: float = 30.0
    # The road (and its terrain) goes on straight this far past the ends of the given poses, and
    # simulate_sequence lines this much of the input path before and after the simulated stretch.
    extend_m: float = 80.0
    # Street furniture (cars, poles, trees, bushes, clutter) besides the facades; False leaves a
    # street of buildings only (the facades are the same: they are placed first).
    objects: bool = True


@dataclass
class World:
    """A ray-castable scene in a local frame (world minus origin), its terrain and class albedos."""

    scene: object
    origin: np.ndarray  # (3,) world coordinates of the scene frame
    terrain: Terrain
    centerline: Centerline
    class_of_geometry: np.ndarray  # geometry id -> index into CLASSES
    n_triangles: int
    n_objects: dict

    def cast(self, origins_world: np.ndarray, dirs_world: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (N, 3) origins/directions in the world frame: t_hit, class, prim, normal."""
        rays = np.concatenate([origins_world - self.origin, dirs_world], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        hit = gid < len(self.class_of_geometry)
        cls = np.full(len(gid), -1)
        cls[hit] = self.class_of_geometry[gid[hit]]
        return {"t_hit": ans["t_hit"].numpy(), "class": cls,
                "prim": ans["primitive_ids"].numpy(), "normal": ans["primitive_normals"].numpy()}

    def closest(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (m) from each point (N, 3), world frame, to the nearest surface, and that
        surface's class (index into CLASSES)."""
        ans = self.scene.compute_closest_points(
            o3d.core.Tensor((np.asarray(points_world) - self.origin).astype(np.float32)))
        nearest = ans["points"].numpy().astype(np.float64) + self.origin
        cls = self.class_of_geometry[ans["geometry_ids"].numpy().astype(np.int64)]
        return np.linalg.norm(nearest - points_world, axis=1), cls


class _Builder:
    """Lines the road on both sides with facades, parked cars, poles, trees, bushes and clutter."""

    def __init__(self, cl: Centerline, terrain: Terrain, params: WorldParams, rng):
        self.cl, self.terrain, self.p, self.rng = cl, terrain, params, rng
        self.buf = {c: _MeshBuffer() for c in CLASSES if c != "ground"}
        self.count = {c: 0 for c in CLASSES if c != "ground"}
        self.sphere = _unit_sphere()
        self.covered = self._covered()

    def _covered(self) -> np.ndarray:
        cl, p = self.cl, self.p
        out = np.zeros(len(cl.arc_m), dtype=bool)
        for j, nb in enumerate(cl.tree.query_ball_point(cl.xyz[:, :2], p.revisit_radius_m)):
            out[j] = any(cl.arc_m[i] < cl.arc_m[j] - p.revisit_min_arc_m for i in nb)
        return out

    def ground_z(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy).reshape(-1, 2)
        curb = (self.cl.distance_m(xy) > self.p.curb_distance_m) * self.p.curb_height_m
        return self.terrain.height(xy) + curb

    def frame_at(self, arc: float, side: int, offset: float) -> tuple[np.ndarray, float] | None:
        """Point offset metres to the left (side=+1) or right (-1) of the path at arc; its yaw."""
        j = int(np.clip(np.searchsorted(self.cl.arc_m, arc), 0, len(self.cl.arc_m) - 1))
        if self.covered[j]:
            return None
        t = self.cl.tangent[j]
        normal = np.array([-t[1], t[0]]) * side
        return self.cl.xyz[j, :2] + offset * normal, float(np.arctan2(t[1], t[0]))

    def clear(self, xy: np.ndarray, clearance_m: float) -> bool:
        return bool(np.all(self.cl.distance_m(xy) >= clearance_m))

    def add(self, cls: str, mesh: tuple[np.ndarray, np.ndarray]) -> None:
        self.buf[cls].add(*mesh)
        self.count[cls] += 1

    def along(self, spacing: tuple[float, float], place) -> None:
        """Call place(arc, side) at random spacings along the path, on both sides."""
        for side in (1, -1):
            s = self.rng.uniform(0, spacing[1])
            while s < self.cl.arc_m[-1]:
                place(s, side)
                s += self.rng.uniform(*spacing)

    def facades(self) -> None:
        rng, p = self.rng, self.p
        for side in (1, -1):
            s = rng.uniform(0, 10)
            while s < self.cl.arc_m[-1]:
                if rng.random() < 0.25:  # a gap: side street, yard, parking lot
                    s += rng.uniform(4, 15)
                    continue
                setback = rng.uniform(*p.facade_setback_m)
                depth, height = rng.uniform(8, 16), rng.uniform(5, 22)
                for _ in range(rng.integers(1, 4)):  # irregular outline: parts of one block
                    length = rng.uniform(5, 14)
                    off = setback + rng.uniform(-1.5, 1.5)
                    h = max(3.5, height + rng.uniform(-4, 4))
                    self._facade_part(s + length / 2, side, length, off, depth, h)
                    s += length

    def _facade_part(self, arc, side, length, offset, depth, height) -> None:
        fr = self.frame_at(arc, side, offset + depth / 2)
        if fr is None:
            return
        (cx, cy), yaw = fr
        if not self.clear(_box_footprint(cx, cy, yaw, length, depth), self.p.facade_clearance_m):
            return
        z = float(self.ground_z([cx, cy])[0])
        self.add("facade", _box(cx, cy, yaw, length, depth, z - 1.0, z + height))

    def car(self, arc: float, side: int) -> None:
        rng = self.rng
        if rng.random() < 0.35:
            return
        fr = self.frame_at(arc, side, rng.uniform(3.3, 4.3))
        if fr is None:
            return
        (cx, cy), yaw = fr
        yaw += rng.normal(0, 0.05)
        length, width = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.95)
        if not self.clear(_box_footprint(cx, cy, yaw, length, width, 0.5), 2.0):
            return
        z = float(self.ground_z([cx, cy])[0])
        top = z + rng.uniform(1.35, 1.6)
        self.add("car", _box(cx, cy, yaw, length, width, z + 0.25, z + 0.9))
        c, s = np.cos(yaw), np.sin(yaw)
        shift = rng.uniform(-0.4, 0.2)
        self.add("car", _box(cx + shift * c, cy + shift * s, yaw, length * 0.55, width * 0.9,
                             z + 0.9, top))

    def pole(self, arc: float, side: int) -> None:
        fr = self.frame_at(arc, side, self.rng.uniform(5.2, 6.5))
        if fr is None or not self.clear(fr[0], 4.0):
            return
        (cx, cy), _ = fr
        z = float(self.ground_z([cx, cy])[0])
        r = self.rng.uniform(0.08, 0.16)
        self.add("pole", _prism(cx, cy, r, z - 0.3, z + self.rng.uniform(4.0, 9.0)))

    def tree(self, arc: float, side: int) -> None:
        rng = self.rng
        fr = self.frame_at(arc, side, rng.uniform(5.5, 9.0))
        if fr is None or not self.clear(fr[0], 4.0):
            return
        (cx, cy), _ = fr
        z = float(self.ground_z([cx, cy])[0])
        trunk_h = rng.uniform(1.8, 3.5)
        self.add("trunk", _prism(cx, cy, rng.uniform(0.12, 0.3), z - 0.3, z + trunk_h + 0.5))
        rxy, rz = rng.uniform(1.5, 3.5), rng.uniform(1.5, 3.5)
        self._blob("crown", [cx, cy, z + trunk_h + 0.7 * rz], [rxy, rxy, rz])

    def bush(self, arc: float, side: int) -> None:
        rng = self.rng
        fr = self.frame_at(arc, side, rng.uniform(5.5, 12.0))
        if fr is None or not self.clear(fr[0], 4.5):
            return
        (cx, cy), _ = fr
        r = rng.uniform(0.4, 1.3, size=3)
        self._blob("bush", [cx, cy, float(self.ground_z([cx, cy])[0]) + 0.3 * r[2]], r)

    def clutter(self, arc: float, side: int) -> None:
        rng = self.rng
        fr = self.frame_at(arc, side, rng.uniform(4.5, 14.0))
        if fr is None:
            return
        (cx, cy), _ = fr
        yaw = rng.uniform(0, np.pi)
        length, width = rng.uniform(0.3, 2.0), rng.uniform(0.3, 1.2)
        if not self.clear(_box_footprint(cx, cy, yaw, length, width, 0.5), 3.5):
            return
        z = float(self.ground_z([cx, cy])[0])
        self.add("clutter", _box(cx, cy, yaw, length, width, z - 0.2, z + rng.uniform(0.4, 2.5)))

    def _blob(self, cls: str, centre, radii) -> None:
        v, t = self.sphere
        bumps = 1.0 + self.rng.uniform(-0.12, 0.12, size=(len(v), 1))
        self.add(cls, (v * bumps * np.asarray(radii) + np.asarray(centre), t))

    def build(self) -> None:
        self.facades()
        if not self.p.objects:
            return
        self.along((4.0, 12.0), self.car)
        self.along((12.0, 35.0), self.pole)
        self.along((8.0, 25.0), self.tree)
        self.along((4.0, 15.0), self.bush)
        self.along((5.0, 20.0), self.clutter)


def _ground_mesh(terrain: Terrain, builder: _Builder, reach_m: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated height field (with curbs) over the cells within reach_m of the path."""
    ny, nx = terrain.heights.shape
    res = terrain.resolution_m
    gx, gy = np.meshgrid(terrain.x0 + res * np.arange(nx), terrain.y0 + res * np.arange(ny))
    xy = np.c_[gx.ravel(), gy.ravel()]
    d = builder.cl.distance_m(xy)
    z = terrain.heights.ravel() + (d > builder.p.curb_distance_m) * builder.p.curb_height_m
    verts = np.c_[xy, z]
    i, j = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).ravel()
    near = d[a] < reach_m
    a = a[near]
    b, c, e = a + 1, a + nx + 1, a + nx
    tris = np.r_[np.c_[a, b, c], np.c_[a, c, e]]
    return verts, tris


def build_world(poses_world_lidar: np.ndarray, sensor: str | SensorModel = "hdl64", seed: int = 0,
                params: WorldParams | None = None) -> World:
    """The street world along poses (K, 4, 4): terrain fitted to z - mount height, objects seeded."""
    sensor = get_sensor(sensor)
    params = params or WorldParams()
    t0 = time.perf_counter()
    cl = make_centerline(poses_world_lidar, extend_m=params.extend_m)
    ground = cl.xyz - [0.0, 0.0, sensor.mount_height_m]
    reach = sensor.max_range_m + 10.0
    bounds = np.array([cl.xyz[:, :2].min(0) - reach, cl.xyz[:, :2].max(0) + reach])
    bounds = np.floor(bounds / params.ground_resolution_m) * params.ground_resolution_m
    terrain = fit_terrain(ground, bounds, params.ground_resolution_m, params.terrain_sigma_m)
    builder = _Builder(cl, terrain, params, np.random.default_rng([seed, 0]))
    builder.build()
    origin = np.r_[cl.xyz[:, :2].mean(0), ground[:, 2].mean()]
    scene = o3d.t.geometry.RaycastingScene()
    meshes = {"ground": _ground_mesh(terrain, builder, reach)}
    meshes.update({c: b.arrays() for c, b in builder.buf.items()})
    class_of_geometry, n_tri = [], 0
    for cls, (v, t) in meshes.items():
        if len(t) == 0:
            continue
        gid = scene.add_triangles(o3d.core.Tensor((v - origin).astype(np.float32)),
                                  o3d.core.Tensor(t.astype(np.uint32)))
        class_of_geometry.append((gid, CLASSES.index(cls)))
        n_tri += len(t)
    cog = np.zeros(max(g for g, _ in class_of_geometry) + 1, dtype=np.int64)
    for g, c in class_of_geometry:
        cog[g] = c
    log.info("world: %d triangles, objects %s, %.1f s", n_tri, builder.count,
             time.perf_counter() - t0)
    return World(scene, origin, terrain, cl, cog, n_tri, dict(builder.count))


# ----------------------------------------------------------------------------------------------
# Scans


@dataclass(frozen=True)
class SimScan:
    """One simulated sweep: raw points (N, 3) in the sensor frame at each point's capture time,
    intensity (N,) in [0, 1], times_s (N,) seconds after the stamp (the sweep start)."""

    points: np.ndarray
    intensity: np.ndarray
    times_s: np.ndarray


def simulate_scan(world: World, sensor: SensorModel, poses_at, stamp_s: float, rng) -> SimScan:
    """Cast one sweep starting at stamp_s; poses_at(times) -> T_world_lidar (N, 4, 4)."""
    tau = sensor.column_times_s()
    T = poses_at(stamp_s + tau)  # (A, 4, 4) the sensor pose at each column's capture time
    d_loc = sensor.directions()  # (A, B, 3) nominal: what the points are computed with
    d_true = sensor.directions(sensor.elevation_error_deg) if sensor.elevation_error_deg else d_loc
    d_world = np.einsum("aij,abj->abi", T[:, :3, :3], d_true).reshape(-1, 3)
    n_b = d_loc.shape[1]
    o_world = np.repeat(T[:, :3, 3], n_b, axis=0)
    hit = world.cast(o_world, d_world)
    r = hit["t_hit"].astype(np.float64)
    cos_inc = np.abs(np.sum(hit["normal"] * d_world, axis=1))
    u = rng.random(len(r))
    noise = np.clip(rng.normal(0.0, sensor.range_noise_m, len(r)), -3 * sensor.range_noise_m,
                    3 * sensor.range_noise_m)
    # Dropouts: a base rate, and most returns at grazing incidence are lost.
    p_drop = sensor.dropout + 0.6 * np.clip(1.0 - cos_inc / 0.12, 0.0, 1.0)
    ok = np.isfinite(r) & (r >= sensor.min_range_m) & (r <= sensor.max_range_m) & (u >= p_drop)
    rn = r[ok] + noise[ok]
    points = d_loc.reshape(-1, 3)[ok] * rn[:, None]
    albedo = np.array([ALBEDO[c] for c in CLASSES])[hit["class"][ok]]
    texture = 0.8 + 0.4 * ((hit["prim"][ok].astype(np.int64) * 2654435761) % 1000) / 1000.0
    intensity = np.clip(albedo * texture * (0.35 + 0.65 * cos_inc[ok]) * np.exp(-rn / 400.0),
                        0.0, 1.0)
    times = np.repeat(tau, n_b)[ok]
    return SimScan(points, intensity, times)


# ----------------------------------------------------------------------------------------------
# Sequences


@dataclass(frozen=True)
class SimSummary:
    """What simulate_sequence wrote: poses are the simulated T_world_lidar at the scan stamps."""

    out_dir: Path
    sensor: SensorModel
    seed: int
    n_scans: int
    stamps_s: np.ndarray
    poses_world_lidar: np.ndarray  # (n, 4, 4) simulated, in the input world frame
    T_world_seq: np.ndarray  # the sequence frame (poses.txt) = lidar frame of the first scan
    Tr_cam_lidar: np.ndarray
    points_per_scan: float
    seconds_per_scan: float
    world_seconds: float
    n_triangles: int
    n_objects: dict = dataclasses.field(default_factory=dict)


def write_calib(path: Path, Tr_cam_lidar: np.ndarray) -> None:
    """calib.txt with P0..P3 placeholders (KITTI cam0 intrinsics) and the Tr line."""
    p = "7.188560e+02 0.0 6.071928e+02 0.0 0.0 7.188560e+02 1.852157e+02 0.0 0.0 0.0 1.0 0.0"
    tr = " ".join(f"{v:.12e}" for v in Tr_cam_lidar[:3, :4].ravel())
    write_text_atomic(path, "".join(f"P{i}: {p}\n" for i in range(4)) + f"Tr: {tr}\n")


def _write_readme(out: Path, summary: SimSummary) -> None:
    s = summary.sensor
    write_text_atomic(
        out / "README.txt",
        f"Simulated by lidar_slam.simulate (sensor {s.name}: {len(s.elevations_deg)} beams, "
        f"{s.n_azimuth} azimuth steps, {s.rate_hz:g} Hz, max range {s.max_range_m:g} m, "
        f"range noise {s.range_noise_m * 100:g} cm), seed {summary.seed}, "
        f"{summary.n_scans} scans.\n"
        "velodyne/NNNNNN.bin: float32 x y z intensity, raw (motion-distorted) sensor frame.\n"
        "velodyne_times/NNNNNN.bin: float32 seconds of each point after the scan stamp; the stamp\n"
        "  (times.txt) is the START of the sweep and the scan's pose refers to that instant.\n"
        "poses.txt: KITTI camera-frame poses P_i = Tr @ T_seq_lidar_i @ inv(Tr) (Tr from\n"
        "  calib.txt); read back with inv(Tr) @ P_i @ Tr. The sequence frame is the lidar frame of\n"
        "  scan 0 (P_0 = I). These are the poses actually simulated (z and roll/pitch from the\n"
        "  fitted terrain), not the input trajectory.\n")


def sequence_world(poses_world_lidar: np.ndarray, start: int, stop: int,
                   sensor: str | SensorModel = "hdl64", seed: int = 0,
                   params: WorldParams | None = None) -> World:
    """The world simulate_sequence builds for scans start..stop-1 of poses (K, 4, 4): it spans
    that stretch plus params.extend_m of the input path on either side."""
    params = params or WorldParams()
    xy = np.asarray(poses_world_lidar)[:, :2, 3]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    i0 = int(np.searchsorted(arc, arc[start] - params.extend_m, side="left"))
    i1 = int(np.searchsorted(arc, arc[stop - 1] + params.extend_m, side="right"))
    return build_world(poses_world_lidar[i0:i1], sensor, seed, params)


def simulate_sequence(poses_world_lidar: np.ndarray, stamps_s: np.ndarray, out_dir: str | Path,
                      sensor: str | SensorModel = "hdl64", seed: int = 0, start: int = 0,
                      n_scans: int | None = None, Tr_cam_lidar: np.ndarray | None = None,
                      params: WorldParams | None = None,
                      on_scan: Callable[[int], None] | None = None) -> SimSummary:
    """Simulate scans start..start+n_scans of a trajectory into a KITTI-layout folder out_dir.

    poses_world_lidar (K, 4, 4) with stamps_s (K,) in seconds. The world is built along that
    stretch only; the same seed gives the same bytes. Every file is written whole or not at all
    (temporary file + rename); on_scan(k) is called after scan k is written (progress).
    """
    sensor = get_sensor(sensor)
    poses_world_lidar = np.asarray(poses_world_lidar, dtype=float)
    stamps_s = np.asarray(stamps_s, dtype=float)
    stop = len(poses_world_lidar) if n_scans is None else min(len(poses_world_lidar),
                                                              start + n_scans)
    if stop <= start:
        raise ValueError(f"nothing to simulate: start {start}, stop {stop}")
    Tr = np.eye(4) if Tr_cam_lidar is None else np.asarray(Tr_cam_lidar, dtype=float)
    params = params or WorldParams()
    t0 = time.perf_counter()
    world = sequence_world(poses_world_lidar, start, stop, sensor, seed, params)
    world_s = time.perf_counter() - t0
    poses = place_on_terrain(poses_world_lidar[start:stop], world.terrain, sensor.mount_height_m)
    stamps = stamps_s[start:stop]
    interp = PoseInterpolator(stamps, poses)
    out = Path(out_dir)
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    (out / "velodyne_times").mkdir(exist_ok=True)
    n_points = 0
    t1 = time.perf_counter()
    for k in range(stop - start):
        rng = np.random.default_rng([seed, 1, start + k])
        scan = simulate_scan(world, sensor, interp, float(stamps[k]), rng)
        # Times first: a scan file never exists without its times (a killed simulate leaves
        # scans that a run reads correctly, never a half-written one).
        with atomic_path(out / "velodyne_times" / f"{k:06d}.bin", fsync=False) as tmp:
            scan.times_s.astype(np.float32).tofile(tmp)
        with atomic_path(out / "velodyne" / f"{k:06d}.bin", fsync=False) as tmp:
            np.c_[scan.points, scan.intensity].astype(np.float32).tofile(tmp)
        n_points += len(scan.points)
        if on_scan is not None:
            on_scan(k)
        if k % 100 == 0:
            log.info("scan %d/%d: %d points", k, stop - start, len(scan.points))
    per_scan = (time.perf_counter() - t1) / (stop - start)
    T_world_seq = poses[0].copy()
    write_kitti_poses(out / "poses.txt", Tr @ (inverse(T_world_seq) @ poses) @ inverse(Tr))
    with atomic_path(out / "times.txt") as tmp:
        np.savetxt(tmp, stamps, fmt="%.6f")
    write_calib(out / "calib.txt", Tr)
    summary = SimSummary(out, sensor, seed, stop - start, stamps, poses, T_world_seq, Tr,
                         n_points / (stop - start), per_scan, world_s, world.n_triangles,
                         world.n_objects)
    _write_readme(out, summary)
    return summary


@dataclass(frozen=True)
class KittiTruth:
    """A KITTI ground-truth trajectory in the lidar frame: T_world_lidar (K, 4, 4), stamps (s)."""

    sequence: str
    poses_world_lidar: np.ndarray
    stamps_s: np.ndarray
    Tr_cam_lidar: np.ndarray


def load_kitti_truth(kitti_gt_dir: str | Path, sequence: str | int) -> KittiTruth:
    """Read poses/XX.txt, calib/XX.txt, times/XX.txt; T_world_lidar = inv(Tr) @ P_i @ Tr."""
    root = Path(kitti_gt_dir)
    seq = f"{int(sequence):02d}"
    Tr = read_kitti_calib_tr(root / "calib" / f"{seq}.txt")
    poses = camera_to_lidar_poses(read_kitti_poses(root / "poses" / f"{seq}.txt"), Tr)
    stamps = read_times(root / "times" / f"{seq}.txt")
    return KittiTruth(seq, poses, stamps, Tr)
