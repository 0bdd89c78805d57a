"""The run folder: poses, map, config, loops, graph and summary."""

from __future__ import annotations

import csv
import json
import resource
from pathlib import Path

import numpy as np

from lidar_slam.config import SlamConfig, dump_config
from lidar_slam.geometry import inverse
from lidar_slam.io.trajectory import write_kitti_poses, write_tum
from lidar_slam.keyframes import write_atomic
from lidar_slam.mapping import write_map
from lidar_slam.pipeline import RunResult


def peak_rss_mb() -> float:
    """Peak resident memory in MB of this process plus that of its finished children (the loop
    worker process): an upper bound of the peak of their sum."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return (own + children) / 1024.0


def path_length_m(poses: np.ndarray) -> float:
    """Length of the polyline through the poses' positions."""
    if len(poses) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def ground_truth_metrics(est: np.ndarray, gt_world: np.ndarray) -> dict:
    """Per-frame RPE, ATE and end drift of est against gt (re-expressed in the first frame)."""
    from lidar_slam import metrics

    gt = inverse(gt_world[0]) @ gt_world
    out: dict = {}
    if len(est) >= 2:
        rpe = metrics.rpe(est, gt)
        out["rpe_trans_m_mean"] = rpe.trans_m_mean
        out["rpe_rot_deg_mean"] = rpe.rot_deg_mean
        gt_len = path_length_m(gt)
        if gt_len > 0:
            out["end_drift_pct"] = float(
                100.0 * np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) / gt_len)
    out["ate_rmse_m"] = metrics.ate(est, gt).rmse_m
    return out


def write_loops(out_dir: Path, result: RunResult) -> dict:
    """loops.csv and graph.g2o; returns the loop counts for the summary."""
    from lidar_slam.loop.closer import loops_csv_rows

    with open(out_dir / "loops.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(loops_csv_rows(result.loops))
    if result.graph is not None:
        result.graph.write_g2o(out_dir / "graph.g2o")
    return {"loops_candidates": len(result.loops),
            "loops_accepted": sum(1 for r in result.loops if r.accepted)}


class OdometryStream:
    """odometry_kitti.txt written while the run goes, one line per frame (line-buffered: every
    line reaches the file as one write), so even a killed run (SIGKILL, out of memory) keeps its
    odometry. write_run rewrites the file from the result at the end, with the same content."""

    def __init__(self, out_dir: Path, done: list[np.ndarray] = ()):
        self.path = out_dir / "odometry_kitti.txt"
        self._fh = open(self.path, "w", buffering=1)
        for T in done:  # a resumed run: the frames of its checkpoint
            self.append(T)

    def append(self, T_world_scan: np.ndarray) -> None:
        self._fh.write(" ".join(f"{v:.9e}" for v in T_world_scan[:3, :4].ravel()) + "\n")

    def close(self) -> None:
        self._fh.close()


def write_run(out_dir: Path, result: RunResult, cfg: SlamConfig, ground_truth: np.ndarray | None,
              wall_s: float, extra: dict | None = None) -> dict:
    """Write every output file; return the summary (also written as summary.json)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    dump_config(cfg, out_dir / "config.yaml")
    n = len(result.indices)
    summary: dict = {"frames": n, "keyframes": len(result.store)}
    if n:
        # World = the first frame at its stamp: frame 0 is the identity in every pose file.
        poses = result.final_poses()
        anchor = inverse(poses[0])
        poses = anchor @ poses
        odom = inverse(result.odom_poses[0]) @ np.stack(result.odom_poses)
        # Exactly the identity: the products above leave round-off there (1e-19) that depends on
        # memory alignment, and a re-run must write the same bytes.
        poses[0] = odom[0] = np.eye(4)
        stamps = np.asarray(result.stamps_s)
        write_kitti_poses(out_dir / "poses_kitti.txt", poses)
        write_tum(out_dir / "poses_tum.txt", stamps, poses)
        write_kitti_poses(out_dir / "odometry_kitti.txt", odom)
        summary["map_points"] = write_map(
            out_dir / "map.ply", result.store,
            {k: anchor @ T for k, T in result.kf_poses.items()}, cfg.map.voxel_size_m)
        summary["path_length_m"] = path_length_m(poses)
        if ground_truth is not None:
            gt = ground_truth[np.asarray(result.indices)]
            summary.update(ground_truth_metrics(poses, gt))
            if cfg.loop.enabled:  # the same ATE before loop closure, for comparison
                from lidar_slam import metrics

                summary["odometry_ate_rmse_m"] = metrics.ate(odom, inverse(gt[0]) @ gt).rmse_m
    if cfg.loop.enabled:
        summary.update(write_loops(out_dir, result))
    summary["wall_s"] = wall_s
    summary["fps"] = n / wall_s if wall_s > 0 else 0.0
    summary["odometry_ms_per_frame"] = 1e3 * result.seconds["odometry"] / max(n, 1)
    summary["loops_ms_per_frame"] = 1e3 * result.seconds["loops"] / max(n, 1)
    if "loop_worker" in result.seconds:  # detection off the critical path: its cost, and
        # how long the odometry waited for it
        summary["loop_worker_ms_per_frame"] = 1e3 * result.seconds["loop_worker"] / max(n, 1)
        summary["loop_wait_ms_per_frame"] = 1e3 * result.seconds["loop_wait"] / max(n, 1)
    if result.loop_update_s:
        summary["backend_ms_per_loop_max"] = 1e3 * max(s for _, s in result.loop_update_s)
    summary["peak_rss_mb"] = peak_rss_mb()
    summary["skipped_empty_scans"] = result.skipped_empty
    summary.update(extra or {})
    write_atomic(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
