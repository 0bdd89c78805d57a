"""Things that move during a session (pedestrians, a car): boxes travelling along the loop, hit
by the sweep's rays at each firing instant, with their truth per scan.

A mover follows the session's own loop at a lateral offset (m, + to the left of the walking
direction) at a constant speed (m/s; negative: against the session's direction), from arc
length s0_m. Rays are intersected with each mover's box analytically (slab test in the box's
frame) and the nearer of that hit and the static world's is the return (`simulate_scan`).
OUT/session_<i>/movers.csv is their truth: per scan and mover, the box at the sweep's middle.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.io.atomic import write_text_atomic
from lidar_slam.sim.handheld import LoopPath
from lidar_slam.sim.world import CLASSES

MOVERS_FILE = "movers.csv"
# (class, length, width, height (m), speed range (m/s), lateral offset (m)) per motion, both
# coming towards the session (one lingering beside the sensor, overtaking at walking pace,
# fills half its scans and breaks the odometry, which is not what they are here to test).
# Offsets keep them off the objects changed between sessions (sessions.py puts those
# 1.2-1.5 m beside a walk, 3.6-9 m beside a drive) and clear of the sensor.
_KINDS = {"handheld": (("clutter", 0.5, 0.5, 1.75, (1.1, 1.5), 0.7),
                       ("clutter", 0.5, 0.5, 1.75, (1.0, 1.4), -0.7)),
          "car": (("car", 4.4, 1.8, 1.5, (5.0, 7.0), 2.1),
                  ("clutter", 0.5, 0.5, 1.75, (1.2, 1.5), -1.9))}


@dataclass(frozen=True)
class Mover:
    """One box moving along path: its class (CLASSES name) and size (m), speed (m/s, signed),
    start arc length s0_m and lateral offset_m; ground(xy) gives the floor height under it."""

    cls: str
    length: float
    width: float
    height: float
    speed_mps: float
    s0_m: float
    offset_m: float
    path: LoopPath
    ground: Callable[[np.ndarray], np.ndarray]

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 4) x, y, yaw (rad), z0 (m) of the box's centre footprint at the times t_s."""
        s = self.s0_m + self.speed_mps * np.asarray(t_s, dtype=float)
        tangent = self.path.xy(s, 1)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        xy = self.path.xy(s) + self.offset_m * np.c_[-tangent[:, 1], tangent[:, 0]]
        yaw = np.arctan2(tangent[:, 1], tangent[:, 0]) + (np.pi if self.speed_mps < 0 else 0.0)
        return np.c_[xy, yaw, self.ground(xy)]


class Movers:
    """The movers of one session; cast() is what simulate_scan adds to the world's rays."""

    def __init__(self, movers: list[Mover]):
        self.movers = movers

    def cast(self, origins: np.ndarray, dirs: np.ndarray, times_s: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays (N, 3) in the world frame fired at times_s (N,): distance to the nearest mover
        (inf: none), its outward normal (N, 3) and class (index into CLASSES)."""
        best = np.full(len(origins), np.inf)
        normal = np.zeros((len(origins), 3))
        cls = np.full(len(origins), -1, dtype=np.int64)
        for m in self.movers:
            pose = m.at(times_s)
            c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
            rel = origins - np.c_[pose[:, :2], pose[:, 3] + m.height / 2]
            # Into the box frame: rotate by -yaw about z.
            o = np.c_[c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]]
            d = np.c_[c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1],
                      dirs[:, 2]]
            half = np.array([m.length, m.width, m.height]) / 2
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-half - o) / d, (half - o) / d
            near = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
            far = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2))
            t_in, axis = near.max(axis=1), near.argmax(axis=1)
            hit = (t_in > 0) & (t_in <= far.min(axis=1)) & (t_in < best)
            n_box = np.zeros((int(hit.sum()), 3))
            n_box[np.arange(len(n_box)), axis[hit]] = -np.sign(d[hit, axis[hit]])
            ch, sh = c[hit], s[hit]
            normal[hit] = np.c_[ch * n_box[:, 0] - sh * n_box[:, 1],
                                sh * n_box[:, 0] + ch * n_box[:, 1], n_box[:, 2]]
            best[hit] = t_in[hit]
            cls[hit] = CLASSES.index(m.cls)
        return best, normal, cls


def draw_movers(path: LoopPath, ground, motion: str, n: int, seed: int) -> list[Mover]:
    """n movers for a session, coming towards it along its path from 12-20 m ahead, 25-35 m,
    ... (a drive: five times as far), alternately on its left and right."""
    rng = np.random.default_rng([seed, 70])
    scale = 5.0 if motion == "car" else 1.0
    out = []
    for k in range(n):
        cls, length, width, height, speeds, offset = _KINDS[motion][k % 2]
        lo, hi = (12.0, 20.0) if k == 0 else (12.0 + 13.0 * k, 20.0 + 15.0 * k)
        out.append(Mover(cls, length, width, height, -float(rng.uniform(*speeds)),
                         scale * float(rng.uniform(lo, hi)), offset, path, ground))
    return out


def write_movers(path: Path, movers: list[Mover], stamps_s: np.ndarray, period_s: float) -> None:
    """movers.csv: per scan (its stamp, s) and mover, the box at the sweep's middle (world
    frame: x, y (m), yaw (rad), length, width, z0, z1 (m)), and its class."""
    rows = ["scan,stamp_s,mover,cls,x,y,yaw,length,width,z0,z1"]
    for j, m in enumerate(movers):
        pose = m.at(stamps_s + period_s / 2)
        rows += [f"{k},{stamps_s[k]:.6f},{j},{m.cls},{p[0]:.4f},{p[1]:.4f},{p[2]:.5f},"
                 f"{m.length:.3f},{m.width:.3f},{p[3]:.4f},{p[3] + m.height:.4f}"
                 for k, p in enumerate(pose)]
    write_text_atomic(path, "\n".join(rows) + "\n")


def read_movers(path: Path) -> np.ndarray:
    """movers.csv as a structured array (fields as its header; cls as text)."""
    return np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="ascii")
