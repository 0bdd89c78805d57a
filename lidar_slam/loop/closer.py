"""Loop closing for the pipeline: keyframe -> scan-context query -> ICP verify -> pose graph.

Every keyframe becomes a pose-graph node joined to the previous one by its odometry; an accepted
loop adds a Huber-robust edge and the graph is re-optimised, which moves every keyframe (and,
through them, every frame).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.config import SlamConfig
from lidar_slam.geometry import relative, to_xyz_quat, transform_points
from lidar_slam.loop.scan_context import ScanContextIndex
from lidar_slam.loop.verify import verify
from lidar_slam.types import Keyframe

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopRecord:
    """One verified candidate (a row of loops.csv); frames are 0-based input positions."""

    query_frame: int
    match_frame: int
    query_kf: int
    match_kf: int
    distance: float
    yaw_guess_deg: float
    fitness: float
    rmse_m: float
    accepted: bool
    reason: str
    T_match_query: np.ndarray | None


class LoopCloser:
    """Owns the scan-context index, the verification and the pose graph of the keyframes."""

    def __init__(self, cfg: SlamConfig):
        self.cfg = cfg
        self.index = ScanContextIndex(cfg.loop.scan_context)
        self.graph = PoseGraph()
        self.keyframes: list[Keyframe] = []
        self._poses: dict[int, np.ndarray] = {}

    def kf_poses(self) -> dict[int, np.ndarray]:
        """Current estimate T_world_kf of every keyframe."""
        return self._poses

    def submap(self, kf_id: int, radius: int) -> np.ndarray:
        """Clouds of keyframes kf_id-radius..kf_id+radius (those that exist) in kf_id's frame."""
        centre = self.keyframes[kf_id].T_world_kf_odom
        parts = []
        for j in range(max(0, kf_id - radius), min(len(self.keyframes), kf_id + radius + 1)):
            kf = self.keyframes[j]
            parts.append(transform_points(relative(centre, kf.T_world_kf_odom),
                                          kf.points.astype(np.float64)))
        return np.concatenate(parts)

    def add_keyframe(self, kf: Keyframe) -> list[LoopRecord]:
        """Add a keyframe node, look for loops, verify them; returns the verified candidates."""
        b = self.cfg.backend
        self.keyframes.append(kf)
        if kf.id == 0:
            self.graph.add_prior(0, kf.T_world_kf_odom, b.prior_rot_sigma_deg, b.prior_trans_sigma_m)
            self._poses[0] = kf.T_world_kf_odom
        else:
            prev = self.keyframes[kf.id - 1]
            T_prev_kf = relative(prev.T_world_kf_odom, kf.T_world_kf_odom)
            self.graph.add_odometry(prev.id, kf.id, T_prev_kf, rot_sigma_deg=b.odom_rot_sigma_deg,
                                    trans_sigma_m=b.odom_trans_sigma_m)
            self._poses[kf.id] = self._poses[prev.id] @ T_prev_kf
        self.graph.set_initial(kf.id, self._poses[kf.id])
        query_pts = kf.points.astype(np.float64)
        records: list[LoopRecord] = []
        if len(query_pts) == 0:  # nothing in range: a graph node, but nothing to describe
            return records
        found = self.index.query(kf.id, query_pts)
        for cand in found.candidates[: self.cfg.loop.max_verify]:
            match = self.keyframes[cand.match]
            query_cloud = self.submap(kf.id, self.cfg.loop.verify.submap_radius)
            res = verify(cand, query_cloud, self.submap(cand.match, self.cfg.loop.verify.submap_radius),
                         self.cfg.loop.verify)
            T = res.T_match_query  # the refined winner, logged for rejected candidates too
            records.append(LoopRecord(kf.frame_index, match.frame_index, kf.id, match.id,
                                      cand.score, float(np.degrees(cand.yaw_guess_rad)), res.fitness,
                                      res.rmse_m, res.accepted, res.reason, T))
            if res.accepted:
                self.graph.add_loop(match.id, kf.id, res.constraint.T_match_query,
                                    res.constraint.information, robust_k=b.huber_k)
                self._poses = self.graph.optimize(b.max_iterations)
                log.info("loop accepted: frame %d -> frame %d (fitness %.2f)", kf.frame_index,
                         match.frame_index, res.fitness)
                break
        self.index.add(kf.id, query_pts)
        return records


def loops_csv_rows(records: list[LoopRecord]) -> list[list]:
    """loops.csv rows (header first)."""
    rows: list[list] = [["query_frame", "match_frame", "descriptor_distance", "yaw_guess_deg",
                         "fitness", "rmse_m", "accepted", "reason", "x", "y", "z", "qx", "qy",
                         "qz", "qw"]]

    for r in records:
        pose = to_xyz_quat(r.T_match_query) if r.T_match_query is not None else [np.nan] * 7
        rows.append([r.query_frame, r.match_frame, f"{r.distance:.4f}", f"{r.yaw_guess_deg:.1f}",
                     f"{r.fitness:.4f}", f"{r.rmse_m:.4f}", int(r.accepted), r.reason,
                     *[f"{v:.6f}" for v in pose]])
    return rows


