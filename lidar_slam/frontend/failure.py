"""Odometry failure (issue 29, item 6): when kiss-icp has clearly lost track, say so once per
episode, count it, and give it a fresh local map instead of letting it crawl.

Why a failing run crawls: kiss-icp's adaptive threshold sigma is the RMS of every model deviation
of the run (the correction of the prediction, its rotation counted as the arc it makes at
data.max_range_m), and it never forgets. One prediction far off (a hand-held flick the
constant-velocity model cannot follow) lifts it for the rest of the run: a 60 s outdoor walk
without the IMU went from 2 m to 15.6 m by scan 30 and stayed at 12-16 m (with the IMU: 0.39 m).
ICP's kernel is sigma, so its Geman-McClure weights are ~1 for every match: no robustness, more
iterations per scan, and the errors smear the local map (203k points by scan 300 against 94k
for the same walk with the IMU at scan 250), whose fuller voxels make every nearest-neighbour
search dearer. The correspondence distance (3 sigma) is not the cost: kiss-icp searches the 27
voxels around a point whatever it is. Per scan the registration grew ~10x.

The test, on each registered scan: the share of its points (at most FITNESS_POINTS, evenly
thinned) within failure_inlier_m of the clouds of the last keyframes, once placed at the
registered pose (each keyframe's KD-tree made once, in its own frame). failure_scans scans in a
row under failure_min_fitness (0.2) is a failure; while sigma is above failure_sigma_m, ICP's
kernel is too wide to reject a poor fit, and the bar is failure_wide_min_fitness (0.5). Then the
caller empties kiss-icp's map down to those keyframes and this scan, and starts the threshold
again from odometry.initial_threshold_m; from then on the kernel stays at most that (see
kernel()). Neither bar is reached by good runs (a sparse VLP-16 at
1 m per scan: >= 0.47; a hand-held walk with the IMU: >= 0.66), so they are unchanged bit for
bit; scans spliced from another street: 0.09. A real hand-held set at 2 Hz
(ouster_os0_loop_balm) reaches sigma 24 m lidar-only and registers well: the fitness, not sigma,
says which is which.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from lidar_slam.registration import make_cloud

log = logging.getLogger(__name__)

FITNESS_POINTS = 500  # scan points tested against the last keyframes
# Resets closer than this (registered scans) are one episode: one warning line, one count.
EPISODE_SCANS = 100


@dataclass
class FailureWatch:
    """Counts the odometry's failures (registered scan indices of every reset, and of the
    first one of each episode) and says when to reset."""

    sigma_m: float  # above it, kiss-icp's kernel is wide: wide_min_fitness applies
    min_fitness: float  # 0: off
    wide_min_fitness: float
    inlier_m: float
    scans: int  # failing scans in a row before a reset
    cloud_voxel_m: float  # voxel of the keyframe clouds' KD-tree
    resets: list[int] = field(default_factory=list)  # scan indices of the resets
    # kiss-icp's threshold (m) when each reset was decided: how far off the odometry could be
    reset_sigmas_m: list[float] = field(default_factory=list)
    episodes: list[int] = field(default_factory=list)  # scan index each episode started at
    _bad: int = 0
    _n_seen: int = 0
    _last_reset: int = -EPISODE_SCANS - 1  # in registered scans
    # id(keyframe points) -> (points, Cloud or None until first searched)
    _clouds: dict = field(default_factory=dict)

    def failed(self, scan_index: int, sigma: float, points: np.ndarray, T_world_points: np.ndarray,
               anchors) -> bool:
        """Whether the scan registered at T_world_points (points (N,3), its frame) means the
        odometry has failed: then the reset is counted and logged (once per episode).
        anchors: the last keyframes (T_world_kf, points_kf) (Odometry._recent())."""
        self._n_seen += 1
        if self.min_fitness <= 0 or not anchors:
            self._bad = 0
            return False
        bar = self.wide_min_fitness if 0 < self.sigma_m < sigma else self.min_fitness
        fitness = self.fitness(points, T_world_points, anchors, bar)
        self._bad = self._bad + 1 if fitness < bar else 0
        if self._bad < self.scans:
            return False
        self._bad = 0
        self.resets.append(scan_index)
        self.reset_sigmas_m.append(float(sigma))
        if self._n_seen - self._last_reset > EPISODE_SCANS:
            self.episodes.append(scan_index)
            log.warning("scan %d: odometry failed (%.0f %% of the scan within %.2f m of the last "
                        "keyframes, kiss-icp threshold %.1f m): local map reset to the last "
                        "keyframes, threshold to its initial value (warned once per episode)",
                        scan_index, 100 * fitness, self.inlier_m, sigma)
        self._last_reset = self._n_seen
        return True

    def sigma_between(self, after: int, upto: int) -> float:
        """The largest kiss-icp threshold (m) at a reset of a scan in (after, upto], else 0:
        across a reset the odometry's motion is known no better than that (the threshold is
        the RMS of its recent corrections)."""
        return max((s for i, s in zip(self.resets, self.reset_sigmas_m) if after < i <= upto),
                   default=0.0)

    def kernel(self, sigma: float, initial_m: float) -> float:
        """The kernel (and a third of the correspondence distance) kiss-icp registers with:
        its sigma, or after a first failure at most initial_m (odometry.initial_threshold_m)
        for the rest of the run: a motion that lifted sigma once lifts it again within scans
        of a reset (the walk's flicks), and a wide kernel is what made it crawl."""
        return min(sigma, initial_m) if self.resets else sigma

    def fitness(self, points: np.ndarray, T_world_points: np.ndarray, anchors,
                 enough: float = 1.0) -> float:
        """Share of points (thinned) within inlier_m of the anchors' clouds once placed. The
        newest keyframe first, and each older one only for the points not yet near (the share
        is the same in any order), until the share reaches `enough` (the bar: the rest cannot
        bring it under); a keyframe's KD-tree is made when first searched and kept with its
        points while it stays an anchor."""
        kept = self._clouds
        self._clouds = {id(p): kept[id(p)] if id(p) in kept and kept[id(p)][0] is p
                        else (p, None) for _, p in anchors}
        pts = np.asarray(points, np.float64)
        pts = pts[::max(1, len(pts) // FITNESS_POINTS)]
        if len(pts) == 0:
            return 1.0
        todo = np.arange(len(pts))
        for T_world_kf, p in reversed(anchors):
            if len(todo) == 0 or (len(pts) - len(todo)) / len(pts) >= enough:
                break
            cloud = self._clouds[id(p)][1]
            if cloud is None:
                cloud = make_cloud(np.asarray(p, np.float64), self.cloud_voxel_m, normals=False,
                                   covariances=False)
                self._clouds[id(p)] = (p, cloud)
            T_kf_points = np.linalg.inv(T_world_kf) @ T_world_points
            q = pts[todo]
            _, sq = cloud.nearest(q @ T_kf_points[:3, :3].T + T_kf_points[:3, 3])
            todo = todo[~((sq >= 0) & (sq <= self.inlier_m ** 2))]
        return (len(pts) - len(todo)) / len(pts)

    def state(self) -> dict[str, np.ndarray]:
        return {"failure_resets": np.asarray(self.resets, np.int64),
                "failure_reset_sigmas": np.asarray(self.reset_sigmas_m, np.float64),
                "failure_episodes": np.asarray(self.episodes, np.int64),
                "failure_counters": np.array([self._bad, self._n_seen, self._last_reset])}

    def restore(self, state: dict[str, np.ndarray]) -> None:
        if "failure_resets" not in state:  # a checkpoint from before 2026-12-03
            return
        self.resets = [int(i) for i in state["failure_resets"]]
        self.reset_sigmas_m = [float(v) for v in state.get(  # not in checkpoints before 12-04
            "failure_reset_sigmas", np.zeros(len(self.resets)))]
        self.episodes = [int(i) for i in state["failure_episodes"]]
        self._bad, self._n_seen, self._last_reset = (int(v) for v in state["failure_counters"])
        self._clouds = {}
