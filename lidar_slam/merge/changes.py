"""What changed between sessions: points one session saw where another saw through.

Each kept session's keyframe clouds (in the merged frame, voxelised) are tested against the
keyframes of the other sessions that see the same place: per cell of cell_m the max_keyframes
keyframes of other sessions nearest to it in the merged frame (within reach_m; one KD-tree over
every session's keyframe positions), so the cost grows with points x max_keyframes, not with
sessions squared. A keyframe "sees through" a point when, in the direction of the point, its
own cloud's nearest return (the minimum range in that direction's bin of its range image) lies
more than margin_m beyond the point; it "sees" the point when a return lies within margin_m of
it. Votes are counted per other session: a point that one other session saw through at least
min_votes times and through more than twice as often as it saw it is changed: appeared when
the point's session is the later one (in the order given), disappeared when it is the earlier.
Changed points are clustered (open3d DBSCAN) into objects.

The keyframe clouds are voxelised (keyframes.cloud_voxel_m), so range-image bins are wide
(bin_deg) and a bin without a return says nothing (no vote).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import inverse, transform_points
from lidar_slam.merge.loops import nearest_of_others
from lidar_slam.merge.session import Session

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChangeOptions:
    """Bin size of the range images (deg), how far beyond a point a return must lie to see
    through it (m), votes needed, reach of a keyframe (m), how many keyframes of other
    sessions vote on a point (the nearest to its cell of cell_m, m), the points' voxel (m),
    and the clustering radius (m) and minimum points of a changed object."""

    bin_deg: float = 3.0
    margin_m: float = 0.6
    min_votes: int = 3
    reach_m: float = 15.0
    max_keyframes: int = 60
    cell_m: float = 2.5
    voxel_m: float = 0.25
    cluster_m: float = 0.8
    cluster_min_points: int = 3
    object_min_points: int = 20  # a changed object: a cluster at least this big
    max_normal_z: float = 0.8  # floors, ceilings (|normal z| above this) never count as changed


@dataclass(frozen=True)
class ChangeCloud:
    """Changed points (N, 3) in the merged frame, the session each came from, appeared (True)
    or disappeared, and its cluster id (-1: noise)."""

    points: np.ndarray
    session: np.ndarray
    appeared: np.ndarray
    cluster: np.ndarray


class _RangeImage:
    """A keyframe's minimum range per (azimuth, elevation) bin, in its own frame, and its
    nearest return: a point nearer than that may have been cropped by the sensor or the
    recording (a minimum range), so no return beyond it says nothing about it."""

    def __init__(self, points_kf: np.ndarray, bin_deg: float):
        self.bin = np.radians(bin_deg)
        self.n_az = int(np.ceil(2 * np.pi / self.bin))
        self.n_el = int(np.ceil(np.pi / self.bin))
        self.ranges = np.full(self.n_az * self.n_el, np.inf)
        idx, r = self._index(points_kf)
        np.minimum.at(self.ranges, idx, r)
        self.nearest_m = float(r.min()) if len(r) else np.inf
        # A bin at the edge of what the sensor covers (its vertical field of view, a window,
        # the sky) may hold returns from only part of it, beyond what its other part would
        # have hit: only bins whose neighbours above and below hold returns too are judged.
        filled = np.isfinite(self.ranges).reshape(self.n_el, self.n_az)
        inner = filled.copy()
        inner[1:] &= filled[:-1]
        inner[:-1] &= filled[1:]
        inner[[0, -1]] = False
        self.inner = inner.ravel()

    def _index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.linalg.norm(points, axis=1)
        az = np.arctan2(points[:, 1], points[:, 0]) + np.pi
        el = np.arccos(np.clip(points[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))
        ia = np.minimum((az / self.bin).astype(np.int64), self.n_az - 1)
        ie = np.minimum((el / self.bin).astype(np.int64), self.n_el - 1)
        return ie * self.n_az + ia, r

    def votes(self, points: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(saw through, saw) per point (N, 3) in this keyframe's frame."""
        idx, r = self._index(points)
        nearest = self.ranges[idx]
        judged = r > self.nearest_m + margin_m
        return (judged & self.inner[idx] & (nearest > r + margin_m),
                judged & (np.abs(nearest - r) <= margin_m))


def _session_points(s: Session, T_merged_kf: np.ndarray, opts: ChangeOptions,
                    moving: dict[tuple[int, int], np.ndarray] | None = None) -> np.ndarray:
    """The session's keyframe clouds in the merged frame, voxelised, without horizontal
    surfaces (a floor or ceiling seen at a grazing angle fills a range-image bin with returns
    beyond itself: a change that is not) and without moving points (merge.moving)."""
    from lidar_slam.o3d import o3d

    def static(k: int) -> np.ndarray:
        points = s.map.keyframe(k).points.astype(np.float64)
        return points if moving is None else points[~moving[(s.index, k)]]

    parts = [transform_points(T_merged_kf[k], static(k)) for k in range(len(s))
             if s.map.counts[k]]
    points = voxel_downsample(np.concatenate(parts), opts.voxel_m)[0]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=1.0, max_nn=30))
    return points[np.abs(np.asarray(cloud.normals)[:, 2]) <= opts.max_normal_z]


def place_votes(points: np.ndarray, owner: np.ndarray, origins: np.ndarray,
                voter_owner: np.ndarray, voter_column: np.ndarray, n_columns: int,
                voter: Callable[[int], tuple[np.ndarray, np.ndarray]], max_keyframes: int,
                reach_m: float, cell_m: float, bin_deg: float, margin_m: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """How often keyframes near each point saw through / saw it ((N, n_columns) counts, a
    voter's votes in its column). points (N, 3) and the keyframes' origins (V, 3) in one
    frame; a keyframe votes on a point when its owner differs from the point's, it is among
    the max_keyframes such keyframes nearest to the point's cell (cell_m; one KD-tree over the
    origins) and within reach_m of the point; voter(v): keyframe v's cloud in its own frame and
    its pose. Each voter's range image is built once."""
    through = np.zeros((len(points), n_columns), dtype=np.int16)
    seen = np.zeros((len(points), n_columns), dtype=np.int16)
    if len(points) == 0 or len(origins) == 0:
        return through, seen
    tree = cKDTree(origins)
    # Cells of one owner's points (a key: owner and cell, 16 bits per axis of cells): the
    # keyframes that vote on them are chosen per cell.
    cells = np.floor(points / cell_m).astype(np.int64)
    key = owner.astype(np.int64) << 48
    for axis, shift in enumerate((32, 16, 0)):
        key |= ((cells[:, axis] + (1 << 15)) & 0xFFFF) << shift
    _, first, group = np.unique(key, return_index=True, return_inverse=True)
    group = group.ravel()
    by_group = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[by_group], np.arange(len(first) + 1))
    centres = (cells[first] + 0.5) * cell_m
    g_owner = owner[first]
    reach = reach_m + cell_m * np.sqrt(3) / 2
    k = min(2 * max_keyframes, tree.n)
    pair_g, pair_v = [], []
    for lo in range(0, len(first), 4096):  # (cells, k) blocks: the nearest keyframes first
        d, j = tree.query(centres[lo:lo + 4096], k=k, distance_upper_bound=reach)
        d, j = d.reshape(len(d), -1), j.reshape(len(j), -1)
        ok = np.isfinite(d)
        ok[ok] = voter_owner[j[ok]] != np.repeat(g_owner[lo:lo + 4096], ok.sum(axis=1))
        rank = np.cumsum(ok, axis=1)
        ok &= rank <= max_keyframes
        rows, cols = np.nonzero(ok)
        pair_g.append(rows + lo)
        pair_v.append(j[rows, cols])
        # Cells whose k nearest are all within reach and hold too few others: search wider.
        for r in np.flatnonzero((rank[:, -1] < max_keyframes) & np.isfinite(d[:, -1])
                                & (k < tree.n)):
            g = lo + r
            _, near = nearest_of_others(tree, voter_owner, centres[g], int(g_owner[g]),
                                        max_keyframes, reach)
            pair_g.append(np.full(len(near), g))
            pair_v.append(near)
    pair_g, pair_v = np.concatenate(pair_g), np.concatenate(pair_v)
    order = np.argsort(pair_v, kind="stable")
    pair_g, pair_v = pair_g[order], pair_v[order]
    voters, starts = np.unique(pair_v, return_index=True)
    sizes = np.diff(bounds)
    for v, gs in zip(voters, np.split(pair_g, starts[1:])):
        lens = sizes[gs]
        pos = np.repeat(bounds[gs] - np.r_[0, np.cumsum(lens)[:-1]], lens) + np.arange(
            lens.sum())
        idx = by_group[pos]
        idx = idx[np.linalg.norm(points[idx] - origins[v], axis=1) < reach_m]
        if len(idx) == 0:
            continue
        cloud, T = voter(int(v))
        t, s = _RangeImage(cloud, bin_deg).votes(transform_points(inverse(T), points[idx]),
                                                 margin_m)
        through[idx, voter_column[v]] += t.astype(np.int16)
        seen[idx, voter_column[v]] += s.astype(np.int16)
    return through, seen


def _votes(clouds: dict[int, np.ndarray], sessions: list[Session],
           T_merged_kf: dict[int, np.ndarray], opts: ChangeOptions
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """All sessions' points (N, 3) stacked, each one's session, and how often each other
    session's keyframes saw through / saw it ((N, S) counts, columns in the order of the
    returned session indices): per cell of points the max_keyframes keyframes of other
    sessions nearest to it vote (place_votes)."""
    order = [s.index for s in sessions]
    column = {i: c for c, i in enumerate(order)}
    points = np.concatenate([clouds[i] for i in order])
    owner = np.concatenate([np.full(len(clouds[i]), i) for i in order])
    voters = [(s, k) for s in sessions for k in range(len(s)) if s.map.counts[k]]
    origins = np.stack([T_merged_kf[s.index][k][:3, 3] for s, k in voters])

    def voter(v: int) -> tuple[np.ndarray, np.ndarray]:
        s, k = voters[v]
        return s.map.keyframe(k).points.astype(np.float64), T_merged_kf[s.index][k]

    through, seen = place_votes(
        points, owner, origins, np.array([s.index for s, _ in voters]),
        np.array([column[s.index] for s, _ in voters]), len(order), voter, opts.max_keyframes,
        opts.reach_m, opts.cell_m, opts.bin_deg, opts.margin_m)
    return points, owner, through, seen, order


def detect_changes(sessions: list[Session], T_merged_kf: dict[int, np.ndarray],
                   opts: ChangeOptions | None = None,
                   moving: dict[tuple[int, int], np.ndarray] | None = None) -> ChangeCloud:
    """Appeared and disappeared points between the kept sessions (module doc); moving:
    (session, keyframe) -> the points to leave out (merge.moving)."""
    from lidar_slam.o3d import o3d

    opts = opts or ChangeOptions()
    kept = [s for s in sessions if s.index in T_merged_kf]
    clouds = {s.index: _session_points(s, T_merged_kf[s.index], opts, moving) for s in kept}
    points, owner, through, seen, order = _votes(clouds, kept, T_merged_kf, opts)
    hit = (through >= opts.min_votes) & (through > 2 * seen)
    changed = hit.any(axis=1)
    earlier = np.array(order)[None, :] < owner[:, None]
    later = (hit & earlier).any(axis=1)
    points, session, appeared = points[changed], owner[changed].astype(np.int32), later[changed]
    cluster = np.full(len(points), -1, dtype=np.int32)
    for group in ((appeared, ), (~appeared, )):
        sel = np.flatnonzero(group[0])
        if len(sel) == 0:
            continue
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[sel]))
        labels = np.asarray(cloud.cluster_dbscan(opts.cluster_m, opts.cluster_min_points))
        sizes = np.bincount(labels[labels >= 0]) if (labels >= 0).any() else np.zeros(0, int)
        big = np.flatnonzero(sizes >= opts.object_min_points)
        ids = np.full(len(sizes), -1)
        ids[big] = cluster.max() + 1 + np.arange(len(big))
        if len(ids):  # else every point is noise
            cluster[sel] = np.where(labels >= 0, ids[np.maximum(labels, 0)], -1)
    log.info("changes: %d points appeared, %d disappeared, %d objects", int(appeared.sum()),
             int((~appeared).sum()), len(set(cluster[cluster >= 0].tolist())))
    return ChangeCloud(points, session, appeared, cluster)
