"""A built interior for the handheld simulator: a ring corridor around a block of rooms, rooms
behind doors on its outer side, a hall with pillars on one side, furniture, floor and ceiling.

Frame: the ring corridor's centreline is the rectangle (0, 0)-(length_m, width_m), the floor is
z = 0, z up. Everything is closed (outer walls, ceiling), so every ray hits something.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar_slam.sim.world import (
    CLASSES,
    Centerline,
    World,
    _box,
    _box_footprint,
    _MeshBuffer,
    _prism,
    assemble_world,
    fit_terrain,
)

WALL_M = 0.2  # wall thickness
DOOR_HEIGHT_M = 2.1


@dataclass(frozen=True)
class IndoorLayout:
    """The interior's dimensions (m): the ring corridor's centreline rectangle, its width, the
    depth of the rooms outside it and of the hall on its y < 0 side, the ceiling height."""

    length_m: float
    width_m: float
    corridor_m: float
    room_depth_m: float
    hall_depth_m: float
    ceiling_m: float

    @staticmethod
    def draw(rng: np.random.Generator) -> IndoorLayout:
        """A seeded layout: a 16-22 x 8-11 m ring, corridors 3.2-4.0 m wide."""
        return IndoorLayout(float(rng.uniform(16.0, 22.0)), float(rng.uniform(8.0, 11.0)),
                            float(rng.uniform(3.2, 3.6)), float(rng.uniform(4.0, 5.5)),
                            float(rng.uniform(6.0, 8.0)), float(rng.uniform(2.9, 3.4)))


class _Interior:
    """Walls with doors, pillars and furniture, kept clear of the walked path."""

    def __init__(self, lay: IndoorLayout, path_xy: np.ndarray, rng: np.random.Generator):
        self.lay, self.rng = lay, rng
        self.path = cKDTree(path_xy)
        self.buf = {c: _MeshBuffer() for c in ("ground", "facade", "pole", "clutter")}
        self.count = {"wall": 0, "door": 0, "pillar": 0, "furniture": 0}

    def clear(self, xy: np.ndarray, clearance_m: float) -> bool:
        return bool(np.all(self.path.query(np.asarray(xy).reshape(-1, 2))[0] >= clearance_m))

    def wall(self, a: tuple[float, float], b: tuple[float, float], doors: list[float] = (),
             door_m: float = 1.0) -> None:
        """A wall from a to b (axis-aligned, full height) with doors (centres, m from a)."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        yaw = float(np.arctan2(u[1], u[0]))
        cuts = sorted(d for d in doors if door_m < d < length - door_m)
        edges = [0.0] + [e for d in cuts for e in (d - door_m / 2, d + door_m / 2)] + [length]
        top = self.lay.ceiling_m
        for s0, s1 in zip(edges[0::2], edges[1::2]):
            if s1 - s0 > 1e-3:
                c = a + u * (s0 + s1) / 2
                self.buf["facade"].add(*_box(*c, yaw, s1 - s0 + WALL_M, WALL_M, 0.0, top))
        for d in cuts:  # the lintel over each door
            c = a + u * d
            self.buf["facade"].add(*_box(*c, yaw, door_m, WALL_M, DOOR_HEIGHT_M, top))
        self.count["wall"] += 1
        self.count["door"] += len(cuts)

    def doors_along(self, length: float) -> list[float]:
        """Door centres every 3.5-6 m along a wall of this length."""
        out, s = [], float(self.rng.uniform(1.5, 3.5))
        while s < length - 1.5:
            out.append(s)
            s += float(self.rng.uniform(3.5, 6.0))
        return out

    def furniture(self, lo: np.ndarray, hi: np.ndarray, n: int, clearance_m: float) -> None:
        """Up to n pieces (tables, shelves, cabinets, crates) in the box lo..hi (xy), each kept
        clearance_m from the path and inside the walls."""
        rng = self.rng
        for _ in range(n):
            kind = rng.integers(4)
            length, width, height = [(rng.uniform(1.2, 2.0), rng.uniform(0.7, 0.9), 0.75),
                                     (rng.uniform(0.8, 2.0), 0.4, rng.uniform(1.6, 2.2)),
                                     (rng.uniform(0.5, 1.0), 0.5, rng.uniform(0.9, 1.3)),
                                     (rng.uniform(0.4, 0.8), rng.uniform(0.4, 0.8),
                                      rng.uniform(0.4, 1.0))][kind]
            yaw = float(rng.choice([0.0, np.pi / 2]) + rng.normal(0.0, 0.15))
            margin = WALL_M / 2 + 0.5 * max(length, width) + 0.05
            if np.any(hi - lo <= 2 * margin):
                continue
            cx, cy = rng.uniform(lo + margin, hi - margin)
            if not self.clear(_box_footprint(cx, cy, yaw, length, width, 0.3), clearance_m):
                continue
            if kind == 0:  # a table: top and four legs
                self.buf["clutter"].add(*_box(cx, cy, yaw, length, width, height - 0.04, height))
                c, s = np.cos(yaw), np.sin(yaw)
                for fx, fy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                    lx, ly = fx * (length / 2 - 0.06), fy * (width / 2 - 0.06)
                    self.buf["clutter"].add(*_prism(cx + lx * c - ly * s, cy + lx * s + ly * c,
                                                    0.025, 0.0, height - 0.04, sides=6))
            else:
                self.buf["clutter"].add(*_box(cx, cy, yaw, length, width, 0.0, height))
            self.count["furniture"] += 1

    def pillar(self, x: float, y: float, clearance_m: float) -> None:
        if not self.clear([[x, y]], clearance_m + 0.35):
            return
        if self.rng.random() < 0.5:
            self.buf["pole"].add(*_prism(x, y, float(self.rng.uniform(0.2, 0.3)), 0.0,
                                         self.lay.ceiling_m, sides=12))
        else:
            side = float(self.rng.uniform(0.4, 0.6))
            self.buf["pole"].add(*_box(x, y, 0.0, side, side, 0.0, self.lay.ceiling_m))
        self.count["pillar"] += 1

    def dressing(self, a: tuple[float, float], b: tuple[float, float], side: int) -> None:
        """Pilasters, cabinets and benches against the wall a-b, on its left (side=+1) or
        right (-1) face, kept 1.2 m from the path: no two stretches of corridor alike."""
        rng = self.rng
        a, b = np.asarray(a, float), np.asarray(b, float)
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        normal = np.array([-u[1], u[0]]) * side
        yaw = float(np.arctan2(u[1], u[0]))
        s = float(rng.uniform(0.5, 2.5))
        while s < length - 0.5:
            kind = rng.choice(["pilaster", "cabinet", "bench"], p=[0.4, 0.35, 0.25])
            width, depth, height = {"pilaster": (rng.uniform(0.3, 0.6), 0.25, self.lay.ceiling_m),
                                    "cabinet": (rng.uniform(0.6, 1.6), 0.45,
                                                rng.uniform(0.9, 2.0)),
                                    "bench": (rng.uniform(1.2, 2.0), 0.4, 0.45)}[kind]
            c = a + u * s + normal * (WALL_M / 2 + depth / 2)
            if self.clear(_box_footprint(*c, yaw, width, depth, 0.2), 1.2):
                cls = "facade" if kind == "pilaster" else "clutter"
                self.buf[cls].add(*_box(*c, yaw, width, depth, 0.0, height))
                self.count["furniture"] += 1
            s += float(rng.uniform(1.5, 4.5))

    def build(self) -> tuple[np.ndarray, np.ndarray]:
        """Everything; returns the interior's bounds (xy min, xy max)."""
        lay, rng = self.lay, self.rng
        L, W = lay.length_m, lay.width_m
        # Half-widths of the corridor's four sides (bottom, right, top, left) differ.
        hb, hr, ht, hl = lay.corridor_m / 2 + rng.uniform(0.0, 0.4, 4)
        D, H = lay.room_depth_m, lay.hall_depth_m
        lo = np.array([-hl - D, -hb - H])
        hi = np.array([L + hr + D, W + ht + D])
        # The envelope, closed.
        for a, b in (((lo[0], lo[1]), (hi[0], lo[1])), ((hi[0], lo[1]), (hi[0], hi[1])),
                     ((hi[0], hi[1]), (lo[0], hi[1])), ((lo[0], hi[1]), (lo[0], lo[1]))):
            self.wall(a, b)
        # The inner block: its ring walls with doors, split into rooms by partitions.
        x0, x1, y0, y1 = hl, L - hr, hb, W - ht
        inner = [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)),
                 ((x0, y1), (x0, y0))]
        self.wall(*inner[0], self.doors_along(x1 - x0))
        self.wall(*inner[1], [float(rng.uniform(1.5, y1 - y0 - 1.5))]
                  if y1 - y0 > 3.2 and rng.random() < 0.5 else [])
        self.wall(*inner[2], self.doors_along(x1 - x0))
        self.wall(*inner[3], [float(rng.uniform(1.5, y1 - y0 - 1.5))]
                  if y1 - y0 > 3.2 else [])
        n_rooms = int(rng.integers(2, 4))
        xs = np.sort(np.r_[x0, rng.uniform(x0 + 3.0, x1 - 3.0, n_rooms - 1), x1])
        for x in xs[1:-1]:
            self.wall((x, y0), (x, y1), [float(rng.uniform(1.2, max(1.3, y1 - y0 - 1.2)))])
        for xa, xb in zip(xs[:-1], xs[1:]):
            self.furniture(np.array([xa, y0]), np.array([xb, y1]), 4, 1.0)
        # Rooms behind the corridor's outer walls on three sides; the hall on y < 0.
        outer = [((L + hr, -hb), (L + hr, W + ht)), ((L + hr, W + ht), (-hl, W + ht)),
                 ((-hl, W + ht), (-hl, -hb))]
        for a, b in outer:
            self.wall(a, b, self.doors_along(float(np.linalg.norm(np.subtract(b, a)))))
        y = float(rng.uniform(0.3, 0.7) * (W + ht + hb) - hb)
        self.wall((L + hr, y), (hi[0], y), [D / 2])
        y = float(rng.uniform(0.3, 0.7) * (W + ht + hb) - hb)
        self.wall((lo[0], y), (-hl, y), [D / 2])
        x = -hl + float(rng.uniform(3.0, 6.0))
        while x < L + hr - 3.0:
            self.wall((x, W + ht), (x, hi[1]), [D / 2])
            x += float(rng.uniform(3.5, 7.0))
        for a, b in (((L + hr, -hb), (hi[0], W + ht)), ((-hl, W + ht), (hi[0], hi[1])),
                     ((lo[0], -hb), (-hl, W + ht))):
            self.furniture(np.array(a), np.array(b), 10, 1.0)
        for a, b in inner:  # the corridor side of a wall a-b is on its right, then left
            self.dressing(a, b, -1)
        for a, b in outer:
            self.dressing(a, b, 1)
        # The hall: a row or two of pillars, desks and benches, open to the corridor.
        self.wall((lo[0], -hb), (-hl, -hb), [D / 2])
        self.wall((L + hr, -hb), (hi[0], -hb), [D / 2])
        for y in (-hb - H / 3, -hb - 2 * H / 3)[: int(rng.integers(1, 3))]:
            for x in np.arange(rng.uniform(0.5, 2.5), L, rng.uniform(3.5, 5.5)):
                self.pillar(float(x), float(y), 1.0)
        self.furniture(np.array([-hl, lo[1]]), np.array([L + hr, -hb]), 8, 1.5)
        return lo, hi


def build_indoor_world(layout: IndoorLayout, path_xy: np.ndarray, seed: int) -> World:
    """The interior of layout around path_xy (N, 2), the walked path (nothing is put within 1 m
    of it but walls, which the layout keeps corridor_m / 2 away)."""
    inside = _Interior(layout, path_xy, np.random.default_rng([seed, 10]))
    lo, hi = inside.build()
    return close_interior(inside, lo, hi, layout.ceiling_m, path_xy)


def close_interior(inside: _Interior, lo: np.ndarray, hi: np.ndarray, ceiling: float,
                   path_xy: np.ndarray) -> World:
    """The World of an interior built within lo..hi (xy, m): floor and ceiling slabs over it,
    a flat terrain and the walked path (N, 2) as its centreline."""
    mid = (lo + hi) / 2
    size = hi - lo + WALL_M
    inside.buf["ground"].add(*_box(*mid, 0.0, size[0], size[1], -0.3, 0.0))
    inside.buf["facade"].add(*_box(*mid, 0.0, size[0], size[1], ceiling, ceiling + 0.3))
    ground = np.c_[path_xy, np.zeros(len(path_xy))]
    terrain = fit_terrain(ground, np.array([lo - 2.0, hi + 2.0]), 1.0, 8.0)
    tangent = np.gradient(path_xy, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path_xy, axis=0), axis=1))]
    cl = Centerline(ground, tangent, arc, cKDTree(path_xy))
    meshes = {c: b.arrays() for c, b in inside.buf.items()}
    assert set(meshes) <= set(CLASSES)
    return assemble_world(meshes, np.r_[mid, 0.0], terrain, cl, dict(inside.count))

