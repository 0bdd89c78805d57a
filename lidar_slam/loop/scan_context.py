"""Scan Context place recognition (Kim & Kim, IROS 2018): a rings x sectors polar grid of the
highest point per bin, nearest ring keys for retrieval, column-shift alignment for the yaw.

Yaw convention: a candidate's yaw_guess_rad is the yaw of T_match_query, i.e. the rotation that
takes query-frame directions into the match frame (p_match = Rz(yaw) p_query, about the levelled
z axis). A point seen at azimuth a by the query is seen at azimuth a + yaw by the match, so query
column j lines up with match column j + shift and yaw = shift * 360 / sectors degrees.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_slam.config import ScanContextConfig
from lidar_slam.geometry import make_pose
from lidar_slam.registration import level_ground
from lidar_slam.types import LoopCandidate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Descriptor:
    """A keyframe's scan context (rings, sectors), metres above ground; its keys and levelling."""

    grid: np.ndarray
    ring_key: np.ndarray
    sector_key: np.ndarray
    R_level_kf: np.ndarray


@dataclass(frozen=True)
class QueryResult:
    """Candidates below the threshold (best first) and the best distance seen, kept or not."""

    candidates: list[LoopCandidate] = field(default_factory=list)
    best_distance: float = 1.0
    best_match: int | None = None
    best_yaw_rad: float = 0.0
    compared: int = 0


# Sensor height above the ground where neither the cloud nor the config says (m).
DEFAULT_SENSOR_HEIGHT_M = 2.0


def describe(points_kf: np.ndarray, cfg: ScanContextConfig) -> Descriptor:
    """Scan context of a cloud given in its keyframe frame (N, 3) metres."""
    pts = np.asarray(points_kf, dtype=np.float64)
    R = np.eye(3)
    # "auto" is fixed from the first scan by the pipeline (loop.adapt); used directly, 2 m.
    height = (DEFAULT_SENSOR_HEIGHT_M if cfg.sensor_height_m == "auto"
              else cfg.sensor_height_m)
    if cfg.level_to_ground and len(pts):
        ground = level_ground(pts, max_tilt_deg=cfg.max_tilt_deg)
        R = ground.R_level_sensor
        if ground.height_m is not None:
            height = ground.height_m
        pts = pts @ R.T
    r = np.hypot(pts[:, 0], pts[:, 1])
    keep = (r < cfg.max_radius_m) & (r > 0)
    r, pts = r[keep], pts[keep]
    ring = np.minimum((r / cfg.max_radius_m * cfg.rings).astype(np.int64), cfg.rings - 1)
    azimuth = np.arctan2(pts[:, 1], pts[:, 0]) + np.pi
    sector = (azimuth / (2 * np.pi) * cfg.sectors).astype(np.int64) % cfg.sectors
    grid = np.zeros(cfg.rings * cfg.sectors)
    np.maximum.at(grid, ring * cfg.sectors + sector, np.maximum(pts[:, 2] + height, 0.0))
    grid = grid.reshape(cfg.rings, cfg.sectors)
    return Descriptor(grid, grid.mean(axis=1), grid.mean(axis=0), R)


def _shift_index(sectors: int, shifts: np.ndarray) -> np.ndarray:
    """(len(shifts), sectors) column indices j + s (mod sectors)."""
    return (np.arange(sectors)[None, :] + shifts[:, None]) % sectors


def column_distances(query: np.ndarray, match: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Cosine column distance in [0, 1] for each shift: query column j against match column j+s,
    averaged over the columns that are non-empty in both (1.0 when none are)."""
    m = match[:, _shift_index(query.shape[1], shifts)]  # (rings, n_shifts, sectors)
    dot = np.einsum("rj,rsj->sj", query, m)
    nq = np.linalg.norm(query, axis=0)[None, :]
    nm = np.linalg.norm(m, axis=0)
    valid = (nq > 0) & (nm > 0)
    cos = np.where(valid, dot / np.where(valid, nq * nm, 1.0), 0.0)
    count = valid.sum(axis=1)
    return np.where(count > 0, 1.0 - cos.sum(axis=1) / np.maximum(count, 1), 1.0)


def align(query: Descriptor, match: Descriptor, local_search_sectors: int) -> tuple[float, int]:
    """(distance, shift): coarse shift from the sector keys, refined by a local search."""
    sectors = query.grid.shape[1]
    all_shifts = np.arange(sectors)
    rolled = match.sector_key[_shift_index(sectors, all_shifts)]
    coarse = int(np.argmin(np.linalg.norm(rolled - query.sector_key[None, :], axis=1)))
    local = (coarse + np.arange(-local_search_sectors, local_search_sectors + 1)) % sectors
    dist = column_distances(query.grid, match.grid, local)
    best = int(np.argmin(dist))
    return float(dist[best]), int(local[best])


def shift_to_yaw(shift: int, sectors: int) -> float:
    """Yaw of T_match_query in radians, wrapped to (-pi, pi], for a column shift."""
    yaw = 2 * np.pi * shift / sectors
    return float(np.arctan2(np.sin(yaw), np.cos(yaw)))


class _Rows:
    """A growable 2-D float array (amortised doubling)."""

    def __init__(self, width: int, dtype=np.float32):
        self.data = np.zeros((16, width), dtype=dtype)
        self.n = 0

    def append(self, row: np.ndarray) -> None:
        if self.n == len(self.data):
            self.data = np.resize(self.data, (2 * self.n, self.data.shape[1]))
        self.data[self.n] = row
        self.n += 1

    def view(self) -> np.ndarray:
        return self.data[: self.n]


class ScanContextIndex:
    """Keyframe descriptors; query before add.

    Memory per keyframe is a few hundred bytes: ring keys, sector keys and levelling rotations
    stay in RAM (float32), the full grids (rings x sectors) go to `grid_path` when given (read
    back only for the candidates of a query), else stay in RAM. Candidates are the exact nearest
    ring keys, by brute force over all eligible keyframes (0.2 ms for 10,000 keyframes).
    """

    def __init__(self, cfg: ScanContextConfig, grid_path: str | Path | None = None):
        self.cfg = cfg
        size = cfg.rings * cfg.sectors
        self._ids = _Rows(1, np.int64)
        self._when = _Rows(2, np.float64)  # path travelled (m) and stamp (s) of each keyframe
        self._stamped = True  # every indexed keyframe has a stamp
        self._ring = _Rows(cfg.rings)
        self._sector = _Rows(cfg.sectors)
        self._R = _Rows(9, np.float64)
        self._pos: dict[int, int] = {}
        self._grid_path = None if grid_path is None else Path(grid_path)
        self._grids = _Rows(size) if grid_path is None else None
        self._grid_fd = None
        if self._grid_path is not None:
            self._grid_fd = os.open(self._grid_path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        self._last: tuple[int, Descriptor] | None = None

    def __len__(self) -> int:
        return self._ids.n

    def close(self) -> None:
        if self._grid_fd is not None:
            os.close(self._grid_fd)
            self._grid_fd = None

    def _describe(self, kf_id: int, points_kf: np.ndarray) -> Descriptor:
        if self._last is not None and self._last[0] == kf_id:
            return self._last[1]
        desc = describe(points_kf, self.cfg)
        self._last = (kf_id, desc)
        return desc

    def add(self, kf_id: int, points_kf: np.ndarray, path_m: float,
            stamp_s: float = np.nan) -> None:
        """Index a keyframe (ids, path travelled in metres and stamps increasing); reuses the
        descriptor a query of kf_id computed."""
        if self._ids.n and kf_id <= int(self._ids.data[self._ids.n - 1, 0]):
            raise ValueError(f"keyframe ids must increase: {kf_id} after "
                             f"{int(self._ids.data[self._ids.n - 1, 0])}")
        self._append(kf_id, self._describe(kf_id, points_kf), path_m, stamp_s)

    def add_grid(self, kf_id: int, grid: np.ndarray) -> None:
        """Index a keyframe by a stored descriptor grid (rings, sectors), as a saved map holds
        them (ids increasing); its levelling rotation is not stored, so it is NaN here (verify()
        levels the clouds itself; initial_guess() cannot be used)."""
        grid = np.asarray(grid, np.float64)
        self._append(kf_id, Descriptor(grid, grid.mean(axis=1), grid.mean(axis=0),
                                       np.full((3, 3), np.nan)), np.nan, np.nan)

    def _append(self, kf_id: int, desc: Descriptor, path_m: float, stamp_s: float) -> None:
        grid = desc.grid.astype(np.float32).ravel()
        if self._grids is not None:
            self._grids.append(grid)
        else:
            os.pwrite(self._grid_fd, grid.tobytes(), self._ids.n * grid.nbytes)
        self._pos[kf_id] = self._ids.n
        self._ids.append(kf_id)
        self._when.append(np.array([path_m, stamp_s]))
        self._stamped = self._stamped and not np.isnan(stamp_s)
        self._ring.append(desc.ring_key)
        self._sector.append(desc.sector_key)
        self._R.append(desc.R_level_kf.ravel())

    def _stored(self, pos: int) -> Descriptor:
        """The descriptor of the keyframe at position pos (grid from RAM or disk)."""
        shape = (self.cfg.rings, self.cfg.sectors)
        if self._grids is not None:
            grid = self._grids.data[pos]
        else:
            nbytes = shape[0] * shape[1] * 4
            grid = np.frombuffer(os.pread(self._grid_fd, nbytes, pos * nbytes), np.float32)
        return Descriptor(grid.reshape(shape).astype(np.float64),
                          self._ring.data[pos].astype(np.float64),
                          self._sector.data[pos].astype(np.float64),
                          self._R.data[pos].reshape(3, 3))

    def R_level_kf(self, kf_id: int) -> np.ndarray:
        """Levelling rotation (3x3) used for an indexed keyframe's descriptor."""
        return self._R.data[self._pos[kf_id]].reshape(3, 3)

    def initial_guess(self, candidate: LoopCandidate, query_points: np.ndarray | None = None
                      ) -> np.ndarray:
        """T_match_query (4x4) from the yaw guess and both keyframes' levelling rotations."""
        R_q = (self.R_level_kf(candidate.query) if candidate.query in self._pos
               else self._describe(candidate.query, query_points).R_level_kf)
        R_m = self.R_level_kf(candidate.match)
        c, s = np.cos(candidate.yaw_guess_rad), np.sin(candidate.yaw_guess_rad)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return make_pose(R_m.T @ Rz @ R_q, np.zeros(3))

    def _nearest(self, key: np.ndarray, n_eligible: int) -> np.ndarray:
        """Positions (< n_eligible) of the cfg.candidates ring keys nearest to key."""
        keys = self._ring.data[:n_eligible].astype(np.float64)
        dist = np.linalg.norm(keys - key[None, :], axis=1)
        return np.argsort(dist, kind="stable")[: self.cfg.candidates]

    def n_eligible(self, path_m: float, stamp_s: float = np.nan) -> int:
        """How many indexed keyframes (the oldest ones) are loop candidates for a keyframe at
        this path length and stamp: exclude_recent_m of path or exclude_recent_s seconds back."""
        when = self._when.view()
        n_path = int(np.searchsorted(when[:, 0], path_m - self.cfg.exclude_recent_m, "right"))
        if np.isnan(stamp_s) or not self._stamped:
            return n_path
        n_time = int(np.searchsorted(when[:, 1], stamp_s - self.cfg.exclude_recent_s, "right"))
        return max(n_path, n_time)

    def is_eligible(self, kf_id: int, path_m: float, stamp_s: float = np.nan) -> bool:
        """Whether keyframe kf_id is a loop candidate for a keyframe at this path length and
        stamp (n_eligible's rule); False for a keyframe that is not indexed (no points)."""
        pos = self._pos.get(kf_id)
        return pos is not None and pos < self.n_eligible(path_m, stamp_s)

    def query(self, kf_id: int, points_kf: np.ndarray, path_m: float,
              stamp_s: float = np.nan, keep: Callable[[int], bool] | None = None
              ) -> QueryResult:
        """Loop candidates for keyframe kf_id among the eligible older keyframes; keep(match
        id), when given, drops ring-key neighbours before their grids are compared (the same
        candidates as filtering the result, without the cost)."""
        n_eligible = self.n_eligible(path_m, stamp_s)
        if n_eligible == 0:
            return QueryResult()
        return self._query(kf_id, self._describe(kf_id, points_kf), n_eligible, keep)

    def query_all(self, points: np.ndarray) -> QueryResult:
        """Candidates among every indexed keyframe for a cloud that is not indexed (a scan to
        localise in a saved map); the candidates' query id is -1."""
        if len(self) == 0:
            return QueryResult()
        return self._query(-1, describe(points, self.cfg), len(self))

    def _query(self, kf_id: int, desc: Descriptor, n_eligible: int,
               keep: Callable[[int], bool] | None = None) -> QueryResult:
        scored = []
        for j in self._nearest(desc.ring_key, n_eligible):
            if keep is not None and not keep(int(self._ids.data[j, 0])):
                continue
            dist, shift = align(desc, self._stored(int(j)), self.cfg.local_search_sectors)
            scored.append((dist, int(self._ids.data[j, 0]), shift_to_yaw(shift, self.cfg.sectors)))
        if not scored:
            return QueryResult()
        scored.sort()
        best = scored[0]
        kept = [LoopCandidate(kf_id, m, d, y) for d, m, y in scored if d < self.cfg.threshold]
        log.debug("kf %d: best scan-context distance %.3f to kf %d (%d kept)", kf_id, best[0],
                  best[1], len(kept))
        return QueryResult(kept, best[0], best[1], best[2], len(scored))
