"""Two built floors that defeat a place descriptor: an aliasing office and a pillared warehouse.

office: parallel corridors along x joined by cross corridors at both ends, between them blocks of
identical rooms (same width, same door, same desk and cabinet) at a fixed pitch, rooms of the
same pitch around the outside. Every stretch of corridor looks like the one a room further on,
like the same place on the next corridor, and like itself turned 180 deg; every junction like the
others turned 90 deg. The loop walked goes round one block.

warehouse: a hall with a square grid of identical pillars, rows of identical racks (uprights,
shelves, a few pallets) and rows of parked cars, under a low flat ceiling. The loop goes round
one block of racks in the aisles.

Both are closed (envelope, floor, ceiling) and built with indoor._Interior's walls; the frame is
the one of indoor.py (floor z = 0, z up). The walked / flown loop is returned with the layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_slam.sim.indoor import WALL_M, _Interior, close_interior
from lidar_slam.sim.world import World, _box, _box_footprint, _MeshBuffer

DOOR_M = 0.9


@dataclass(frozen=True)
class OfficeLayout:
    """The office floor (m): n_corridors along x at pitch_m apart (corridor y = k * pitch_m),
    corridor_m wide; n_rooms rooms of room_m along each block; outer rooms outer_m deep."""

    n_corridors: int
    corridor_m: float
    room_m: float
    n_rooms: int
    block_m: float  # depth of a block of rooms between two corridors
    outer_m: float
    ceiling_m: float
    door_at: float  # the door's centre, as a fraction of the room's width

    @property
    def pitch_m(self) -> float:
        return self.corridor_m + self.block_m

    @property
    def length_m(self) -> float:
        """x of the far cross corridor's centreline (the near one is at x = 0)."""
        return self.n_rooms * self.room_m + self.corridor_m

    @staticmethod
    def draw(rng: np.random.Generator) -> OfficeLayout:
        """A seeded floor: 3-4 corridors 2.2-2.6 m wide, 3-4 rooms of 3.0-3.6 m per block."""
        return OfficeLayout(int(rng.integers(3, 5)), float(rng.uniform(2.2, 2.6)),
                            float(rng.uniform(3.0, 3.6)), int(rng.integers(3, 5)),
                            float(rng.uniform(4.0, 5.0)), float(rng.uniform(3.5, 4.5)),
                            float(rng.uniform(2.7, 3.0)), float(rng.uniform(0.25, 0.4)))

    def loop_corners(self, block: int) -> np.ndarray:
        """(4, 2) the corridor centrelines' crossings round block (0 .. n_corridors - 2)."""
        y0, y1 = block * self.pitch_m, (block + 1) * self.pitch_m
        return np.array([[0.0, y0], [self.length_m, y0], [self.length_m, y1], [0.0, y1]])


def _room_row(inside: _Interior, lay: OfficeLayout, a: tuple[float, float],
              b: tuple[float, float], depth_side: int, depth_m: float) -> None:
    """A wall a-b (along x or y) with one door per room at the same place in each, the rooms'
    partitions depth_m deep on its depth_side (+1 left of a-b, -1 right), and in each room the
    same desk and cabinet."""
    a_, b_ = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b_ - a_))
    u = (b_ - a_) / length
    n = np.array([-u[1], u[0]]) * depth_side
    yaw = float(np.arctan2(u[1], u[0]))
    k = max(1, int(round(length / lay.room_m)))
    width = length / k
    inside.wall(a, b, [width * (i + lay.door_at) for i in range(k)], DOOR_M)
    for i in range(1, k):
        p = a_ + u * i * width
        inside.wall(tuple(p), tuple(p + n * depth_m))
    for i in range(k):  # the same furniture, room-relative: desk by the window, cabinet by a wall
        o = a_ + u * i * width
        desk = o + u * width * 0.6 + n * depth_m * 0.65
        inside.buf["clutter"].add(*_box(*desk, yaw, 1.4, 0.7, 0.0, 0.75))
        cab = o + u * (WALL_M / 2 + 0.25) + n * depth_m * 0.5
        inside.buf["clutter"].add(*_box(*cab, yaw, 0.5, 1.2, 0.0, 1.9))
        inside.count["furniture"] += 2


def build_office_world(lay: OfficeLayout, path_xy: np.ndarray, seed: int) -> World:
    """The office floor of lay around the loop path_xy (N, 2); identical rooms everywhere."""
    inside = _Interior(lay, path_xy, np.random.default_rng([seed, 40]))
    h, L, P = lay.corridor_m / 2, lay.length_m, lay.pitch_m
    top = (lay.n_corridors - 1) * P
    lo = np.array([-h - lay.outer_m, -h - lay.outer_m])
    hi = np.array([L + h + lay.outer_m, top + h + lay.outer_m])
    for a, b in (((lo[0], lo[1]), (hi[0], lo[1])), ((hi[0], lo[1]), (hi[0], hi[1])),
                 ((hi[0], hi[1]), (lo[0], hi[1])), ((lo[0], hi[1]), (lo[0], lo[1]))):
        inside.wall(a, b)
    # Blocks between corridors: rooms facing the corridor below, rooms facing the one above,
    # back to back (each half the block deep); their end walls face the cross corridors.
    for k in range(lay.n_corridors - 1):
        y0, y1 = k * P + h, (k + 1) * P - h
        mid = (y0 + y1) / 2
        _room_row(inside, lay, (h, y0), (L - h, y0), 1, mid - y0)
        _room_row(inside, lay, (L - h, y1), (h, y1), 1, y1 - mid)
        inside.wall((h, mid), (L - h, mid))
        inside.wall((h, y0), (h, y1))
        inside.wall((L - h, y0), (L - h, y1))
    # Outer rooms: below the first corridor, above the last, beyond both cross corridors.
    _room_row(inside, lay, (L + h, -h), (-h, -h), 1, lay.outer_m)
    _room_row(inside, lay, (-h, top + h), (L + h, top + h), 1, lay.outer_m)
    _room_row(inside, lay, (-h, -h), (-h, top + h), 1, lay.outer_m)
    _room_row(inside, lay, (L + h, top + h), (L + h, -h), 1, lay.outer_m)
    return close_interior(inside, lo, hi, lay.ceiling_m, path_xy)


@dataclass(frozen=True)
class WarehouseLayout:
    """The hall (m): pillars on a square grid of pitch_m (nx x ny bays), the loop round a block
    of bays in the aisles (on the pillar grid's half lines), racks rack_m high, ceiling_m."""

    nx: int
    ny: int
    pitch_m: float
    rack_m: float
    ceiling_m: float
    loop_bays: tuple[int, int, int, int]  # first bay x, first bay y, bays along x, along y

    @staticmethod
    def draw(rng: np.random.Generator) -> WarehouseLayout:
        """A seeded hall: 5-6 x 4-5 bays of 7-8 m, ceiling 7.0-7.5 m (a drone flies up to
        6 m under it), racks 3.5-4.5 m."""
        nx, ny = int(rng.integers(5, 7)), int(rng.integers(4, 6))
        bx, by = int(rng.integers(1, nx - 2)), int(rng.integers(1, ny - 1))
        return WarehouseLayout(nx, ny, float(rng.uniform(7.0, 8.0)), float(rng.uniform(3.5, 4.5)),
                               float(rng.uniform(7.0, 7.5)), (bx, by, 2, 1))

    def loop_corners(self) -> np.ndarray:
        """(4, 2) the loop's corners: aisle centres on the pillar grid's half lines."""
        bx, by, mx, my = self.loop_bays
        x0, y0 = (bx + 0.5) * self.pitch_m, (by + 0.5) * self.pitch_m
        x1, y1 = x0 + mx * self.pitch_m, y0 + my * self.pitch_m
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def _rack(inside: _Interior, x0: float, x1: float, y: float, height: float) -> None:
    """A rack along x from x0 to x1 centred on y, 1.1 m deep: uprights every ~2.7 m, three
    shelves, pallets on some of them."""
    rng = inside.rng
    for x in np.linspace(x0, x1, max(2, int(round((x1 - x0) / 2.7)) + 1)):
        for dy in (-0.5, 0.5):
            inside.buf["pole"].add(*_box(x, y + dy, 0.0, 0.1, 0.1, 0.0, height))
    for z in np.linspace(0.15, height - 0.1, 3):
        inside.buf["clutter"].add(*_box((x0 + x1) / 2, y, 0.0, x1 - x0, 1.1, z - 0.05, z))
        for x in np.arange(x0 + 0.7, x1 - 0.6, 1.35):
            if rng.random() < 0.55 and z < height - 1.0:
                inside.buf["clutter"].add(*_box(x, y, 0.0, 1.2, 1.0, z, z + 0.9))
    inside.count["furniture"] += 1


def _car_row(inside: _Interior, x0: float, x1: float, y: float) -> None:
    """Cars parked along x between x0 and x1, centred on y, one every ~5.5 m."""
    rng = inside.rng
    for x in np.arange(x0 + 2.5, x1 - 2.2, 5.5):
        if rng.random() < 0.2:  # an empty space
            continue
        length, width = float(rng.uniform(4.2, 4.8)), float(rng.uniform(1.75, 1.9))
        inside.buf["car"].add(*_box(x, y, 0.0, length, width, 0.3, 0.95))
        inside.buf["car"].add(*_box(x - 0.2, y, 0.0, length * 0.55, width * 0.9, 0.95,
                                    float(rng.uniform(1.4, 1.55))))
        inside.count["furniture"] += 1


RACK_OFFSET_M = 1.1  # rack rows run this far either side of each pillar line


def build_warehouse_world(lay: WarehouseLayout, path_xy: np.ndarray, seed: int) -> World:
    """The hall of lay around the loop path_xy (N, 2): a pillar at every grid node, rows of racks
    (or parked cars) along x either side of each pillar line, two per bay, each kept 1.2 m from
    the path (so the aisles on the grid's half lines stay open)."""
    rng = np.random.default_rng([seed, 50])
    inside = _Interior(lay, path_xy, rng)
    inside.buf["car"] = _MeshBuffer()
    P = lay.pitch_m
    lo, hi = np.array([0.0, 0.0]), np.array([lay.nx * P, lay.ny * P])
    for a, b in (((lo[0], lo[1]), (hi[0], lo[1])), ((hi[0], lo[1]), (hi[0], hi[1])),
                 ((hi[0], hi[1]), (lo[0], hi[1])), ((lo[0], hi[1]), (lo[0], lo[1]))):
        inside.wall(a, b)
    for i in range(1, lay.nx):
        for j in range(1, lay.ny):
            if inside.clear([[i * P, j * P]], 1.0 + 0.35):
                inside.buf["pole"].add(*_box(i * P, j * P, 0.0, 0.6, 0.6, 0.0, lay.ceiling_m))
                inside.count["pillar"] += 1
    for j in range(lay.ny + 1):
        for y in (j * P - RACK_OFFSET_M, j * P + RACK_OFFSET_M):
            if not 0.8 < y < hi[1] - 0.8:
                continue
            cars = rng.random() < 0.3  # a row of cars: one per bay; racks: two per bay
            step = P if cars else P / 2
            for x0 in np.arange(0.45, hi[0] - 1.0, step):
                x1 = x0 + step - 0.9
                foot = _box_footprint((x0 + x1) / 2, y, 0.0, x1 - x0, 2.0 if cars else 1.1, 0.3)
                if not inside.clear(foot, 1.2):
                    continue
                if cars:
                    _car_row(inside, x0, x1, y)
                else:
                    _rack(inside, x0, x1, y, lay.rack_m)
    return close_interior(inside, lo, hi, lay.ceiling_m, path_xy)
