"""The procedural street world: terrain, facades, cars, poles, trees, ray cast with open3d."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from lidar_slam.o3d import o3d
from lidar_slam.sim.sensor import SensorModel, get_sensor

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Trajectory helpers


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
    num = (gaussian_filter(wz, s, mode="constant")
           + 1e-2 * gaussian_filter(wz, 5 * s, mode="constant"))
    den = gaussian_filter(w, s, mode="constant") + 1e-2 * gaussian_filter(w, 5 * s, mode="constant")
    mean = float(np.mean(ground_xyz[:, 2]))
    h = (num + 1e-12 * mean) / (den + 1e-12)
    xs = xmin + resolution_m * np.arange(nx)
    ys = ymin + resolution_m * np.arange(ny)
    spline = RectBivariateSpline(ys, xs, h, kx=3, ky=3, s=0)
    return Terrain(float(xmin), float(ymin), resolution_m, h, spline)


def place_on_terrain(poses: np.ndarray, terrain: Terrain, mount_height_m: float) -> np.ndarray:
    """Poses with the input x, y and heading, z = ground + mount height, roll/pitch = ground
    normal."""
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
    """The street world along poses (K, 4, 4): terrain fitted to z - mount height, objects
    seeded."""
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
    meshes = {"ground": _ground_mesh(terrain, builder, reach)}
    meshes.update({c: b.arrays() for c, b in builder.buf.items()})
    world = assemble_world(meshes, origin, terrain, cl, dict(builder.count))
    log.info("world: %d triangles, objects %s, %.1f s", world.n_triangles, builder.count,
             time.perf_counter() - t0)
    return world


def assemble_world(meshes: dict[str, tuple[np.ndarray, np.ndarray]], origin: np.ndarray,
                   terrain: Terrain, centerline: Centerline, n_objects: dict) -> World:
    """A World from triangle meshes per class (vertices (V, 3) world frame, triangles (T, 3)),
    ray cast in the frame world minus origin (float32 precision near the scene)."""
    scene = o3d.t.geometry.RaycastingScene()
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
    return World(scene, origin, terrain, centerline, cog, n_tri, n_objects)
