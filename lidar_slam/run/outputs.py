"""The run folder: poses, map, config, loops, graph and summary."""

from __future__ import annotations

import csv
import json
import logging
import resource
from pathlib import Path

import numpy as np

from lidar_slam.config import SlamConfig, dump_config
from lidar_slam.eval import metrics
from lidar_slam.eval.evaluate import plot_run_top_view, run_summary_metrics
from lidar_slam.geo import GeoReference
from lidar_slam.geometry import inverse
from lidar_slam.io.atomic import atomic_path, write_atomic
from lidar_slam.io.trajectory import write_kitti_poses, write_tum
from lidar_slam.map.keyframes import DESCRIPTORS, KeyframeStore
from lidar_slam.map.writer import write_map
from lidar_slam.pipeline import RunResult

log = logging.getLogger(__name__)


def peak_rss_mb() -> float:
    """Peak resident memory in MB of this process plus that of its finished children (the loop
    worker process): an upper bound of the peak of their sum."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return (own + children) / 1024.0


def write_loops(out_dir: Path, result: RunResult) -> dict:
    """loops.csv and graph.g2o; returns the loop counts for the summary."""
    from lidar_slam.loop.detector import loops_csv_rows

    with atomic_path(out_dir / "loops.csv") as tmp, open(tmp, "w", newline="") as fh:
        csv.writer(fh).writerows(loops_csv_rows(result.loops, result.loop_backend,
                                                node_to_frame(result)))
    if result.graph is not None:
        result.graph.write_g2o(out_dir / "graph.g2o")
    return {"loops_candidates": len(result.loops),
            "loops_accepted": sum(1 for r in result.loops if r.accepted),
            "loops_backend_rejected": sum(s == "rejected" for s in result.loop_backend.values()),
            "loops_submap_splits": len(result.loop_split_edges)}


def node_to_frame(result: RunResult) -> dict[int, np.ndarray]:
    """Per keyframe whose graph node is not at its frame's stamp (keyframe 0, at the middle of
    its sweep; without an IMU every keyframe of a scan with point times: Pipeline._node_at_ref),
    T_node_frame: the node to its frame at the stamp, along the run's odometry."""
    out: dict[int, np.ndarray] = {}
    if not len(result.store) or not result.odom_poses:
        return out
    table = result.store.table()
    pos = np.searchsorted(np.asarray(result.indices), table["frame_index"])
    for k, (T_node, i) in enumerate(zip(table["T"], pos)):
        if i < len(result.odom_poses) and not np.array_equal(T_node, result.odom_poses[i]):
            out[k] = inverse(T_node) @ result.odom_poses[i]
    return out


def write_map_manifest(store: KeyframeStore, T_map_kf: dict[int, np.ndarray],
                       cfg: SlamConfig) -> None:
    """Make the run's keyframe store a reusable map (see lidar_slam.map.keyframes): the final
    keyframe poses in the map frame and the manifest that vouches for them."""
    if len(T_map_kf) != len(store):
        log.warning("no map manifest: %d final poses for %d keyframes", len(T_map_kf),
                    len(store))
        return
    sc = cfg.loop.scan_context
    descriptors = store.root / DESCRIPTORS
    rows = descriptors.stat().st_size // (4 * sc.rings * sc.sectors) if descriptors.is_file() else 0
    store.flush(np.stack([T_map_kf[k] for k in range(len(store))]), rows)


TANGENT = ("rx", "ry", "rz", "tx", "ty", "tz")  # gtsam Pose3 order: rotation first (rad, m)
COVARIANCE_COLUMNS = tuple(f"{TANGENT[i]}_{TANGENT[j]}" for i in range(6) for j in range(i, 6))


def write_covariances(path: Path, result: RunResult) -> None:
    """covariances.csv: per keyframe its input frame, its id, node_dt_s (the instant its graph
    node and covariance are at, minus the frame's stamp: 0, or the sweep's middle for keyframe
    0 and, without an IMU, for every scan with per-point times; nan when not known) and the 21
    upper-triangle values (row by row) of the 6x6 marginal covariance of the final solve
    (rotation first, rad^2 and m^2, in the keyframe's frame: the true pose is
    T_world_kf @ Exp(xi), xi ~ N(0, cov))."""
    table = result.store.table()
    iu = np.triu_indices(6)
    dts = result.kf_node_dt
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        rows = csv.writer(fh)
        rows.writerow(["frame", "keyframe", "node_dt_s", *COVARIANCE_COLUMNS])
        for kf_id, frame in zip(table["id"], table["frame_index"], strict=True):
            cov = result.kf_covariances.get(int(kf_id))
            if cov is not None:
                dt = "nan" if dts is None else f"{dts.get(int(kf_id), 0.0):.6f}"
                rows.writerow([int(frame), int(kf_id), dt, *(f"{v:.9e}" for v in cov[iu])])


def read_covariances(path: Path) -> dict[int, np.ndarray]:
    """covariances.csv back as {frame: 6x6 covariance} (see write_covariances; also the files
    written before node_dt_s)."""
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    out = {}
    iu = np.triu_indices(6)
    for row in data:
        cov = np.zeros((6, 6))
        cov[iu] = row[-21:]
        out[int(row[0])] = cov + np.triu(cov, 1).T
    return out


def read_node_dt(path: Path) -> dict[int, float]:
    """covariances.csv's node_dt_s as {frame: s} (empty for a file written before it; nan where
    the run did not know it)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or "node_dt_s" not in rows[0]:
        return {}
    return {int(r["frame"]): float(r["node_dt_s"]) for r in rows}


def write_geo_poses(out_dir: Path, geo: GeoReference, frames: np.ndarray, stamps_s: np.ndarray,
                    T_map_lidar: np.ndarray) -> dict:
    """With a geo reference (GNSS): poses_enu.txt (T_enu_lidar per frame, 12 numbers a line as
    poses_kitti.txt, ENU at geo.enu's datum) and poses_wgs84.csv (frame, stamp_s, lat_deg,
    lon_deg, alt_m: the lidar's origin, ellipsoidal height); returns summary.json's `geo`."""
    T_enu_lidar = geo.T_enu_map @ T_map_lidar
    write_kitti_poses(out_dir / "poses_enu.txt", T_enu_lidar)
    llh = geo.enu.to_wgs84(T_enu_lidar[:, :3, 3])
    with atomic_path(out_dir / "poses_wgs84.csv") as tmp:
        np.savetxt(tmp, np.c_[frames, stamps_s, llh], delimiter=",", comments="",
                   fmt=["%d", "%.9f", "%.10f", "%.10f", "%.4f"],
                   header="frame,stamp_s,lat_deg,lon_deg,alt_m")
    return geo.to_dict()


class OdometryStream:
    """odometry_kitti.txt written while the run goes, one line per frame (line-buffered: every
    line reaches the file as one write), so even a killed run (SIGKILL, out of memory) keeps its
    odometry. Only settled frames (Pipeline.settled_frames), in the odometry's own world; write_run
    rewrites the file at the end, re-based so that frame 0 is the identity."""

    def __init__(self, out_dir: Path, done: list[np.ndarray] = ()):
        self.path = out_dir / "odometry_kitti.txt"
        self._fh = open(self.path, "w", buffering=1)
        for T in done:  # a resumed run: the frames of its checkpoint
            self.append(T)

    _LINE = " ".join(["%.9e"] * 12) + "\n"  # as np.savetxt(fmt="%.9e") writes it

    def append(self, T_world_scan: np.ndarray) -> None:
        self._fh.write(self._LINE % tuple(T_world_scan[:3, :4].ravel().tolist()))

    def close(self) -> None:
        self._fh.close()


def write_run(out_dir: Path, result: RunResult, cfg: SlamConfig, ground_truth: np.ndarray | None,
              wall_s: float, extra: dict | None = None, painter=None) -> dict:
    """Write every output file; return the summary (also written as summary.json). painter: a
    lidar_slam.run.painter.TopViewPainter to draw top_view.png beside the other outputs, else
    it is drawn here."""
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
        T_map_kf = {k: anchor @ T for k, T in result.kf_poses.items()}
        summary["map_points"] = write_map(out_dir / "map.ply", result.store, T_map_kf,
                                          cfg.map.voxel_size_m)
        write_map_manifest(result.store, T_map_kf, cfg)
        # A picture for a user with no ground truth (and no rerun): as eval's top view.
        if painter is None:
            plot_run_top_view(out_dir / "top_view.png", poses, out_dir / "map.ply")
        else:
            drawing = painter.draw(out_dir / "top_view.png", poses, out_dir / "map.ply")
        if result.kf_covariances:
            write_covariances(out_dir / "covariances.csv", result)
        if result.geo is not None:
            summary["geo"] = write_geo_poses(out_dir, result.geo, np.asarray(result.indices),
                                             stamps, poses)
        summary["path_length_m"] = metrics.path_length_m(poses)
        if ground_truth is not None:
            gt = ground_truth[np.asarray(result.indices)]
            # A dataset's ground truth may not reach every scan (NaN rows): scored where it does
            covered = np.isfinite(gt).all(axis=(1, 2))
            est, odo = poses, odom
            if not covered.all():
                summary["ground_truth_frames"] = int(covered.sum())
                est, odo, gt = (inverse(T[covered][0]) @ T[covered] if covered.any() else T[:0]
                                for T in (poses, odom, gt))
            if len(gt):
                summary.update(run_summary_metrics(est, gt))
                if cfg.loop.enabled:  # the same ATE before loop closure, for comparison
                    summary["odometry_ate_rmse_m"] = metrics.ate(odo, inverse(gt[0]) @ gt).rmse_m
    if cfg.loop.enabled:
        summary.update(write_loops(out_dir, result))
    if result.adaptive:
        summary["auto_settings"] = result.adaptive  # the config's "auto" values, as fixed
    summary["wall_s"] = wall_s
    summary["fps"] = n / wall_s if wall_s > 0 else 0.0
    summary["odometry_ms_per_frame"] = 1e3 * result.seconds["odometry"] / max(n, 1)
    summary["loops_ms_per_frame"] = 1e3 * result.seconds["loops"] / max(n, 1)
    if "loop_worker" in result.seconds:  # detection off the critical path: its cost, and
        # how long the odometry waited for it
        summary["loop_worker_ms_per_frame"] = 1e3 * result.seconds["loop_worker"] / max(n, 1)
        summary["loop_wait_ms_per_frame"] = 1e3 * result.seconds["loop_wait"] / max(n, 1)
        summary["loop_wait_final_s"] = result.seconds.get("loop_wait_final", 0.0)
        summary["loop_worker_urgent_s"] = result.seconds.get("loop_worker_urgent", 0.0)
    if result.loop_update_s:
        summary["backend_ms_per_loop_max"] = 1e3 * max(s for _, s in result.loop_update_s)
    if "backend" in result.seconds:  # live (window) updates + final solve, and their share
        summary["backend_s"] = result.seconds["backend"]
        summary["backend_final_s"] = result.seconds["backend_final"]
        summary["backend_share_pct"] = 100.0 * result.seconds["backend"] / max(wall_s, 1e-9)
        if result.backend_init:
            summary["backend_final_init"] = result.backend_init
    summary["peak_rss_mb"] = peak_rss_mb()
    summary["skipped_empty_scans"] = result.skipped_empty
    summary["skipped_small_scans"] = result.skipped_small
    (summary["odometry_refined_scans"], summary["odometry_refine_refused"],
     summary["odometry_refine_unproven"], summary["odometry_refine_skipped"]) = result.refined_scans
    summary["odometry_refined_at_speed"] = result.refined_at_speed
    # scans kiss-icp registered from a coarse pass's start (odometry.coarse_every)
    summary["odometry_coarse_scans"] = result.coarse_scans
    summary["odometry_second_start"] = {"tried": result.second_start[0],
                                        "taken": result.second_start[1]}
    # lidar only: keyframes due at a flick made at a later, steady scan, and of them those made
    # at the wait's end or where the next fell due instead (keyframes.steady_miss_deg)
    summary["keyframes_steady_wait"] = {"late": result.steady_wait[0],
                                        "not_steady": result.steady_wait[1]}
    # without IMU factors in the final solve: keyframes whose covariance the deskew's white sd
    # widened by 1 cm or more, the largest (backend.odom_information.deskew_white_scale); null
    # with them (not added)
    summary["covariance_deskew_white"] = (
        None if result.deskew_white is None else
        {"keyframes_1cm": result.deskew_white[0], "max_m": result.deskew_white[1]})
    # lidar only on a drive: the rotation floor (deg) and bias sd per metre (deg, per axis) the
    # covariances took from the scans refined at speed, the new weights' variance factor and the
    # seconds it took (backend.refinement_floor); null: the configured floor (too few such
    # scans, odom_information off, or the covariances are the IMU / GNSS solve's)
    summary["covariance_refinement_floor"] = result.refinement_floor
    # episodes of failed odometry (lidar_slam.frontend.failure), the scans they started at, and
    # the scans of every local-map reset
    summary["odometry_failures"] = len(result.failure_episodes)
    summary["odometry_failure_frames"] = result.failure_episodes
    summary["odometry_failure_resets"] = result.failure_resets
    summary.update(extra or {})
    for key, entry in result.inertial_summary.items():  # the back-end's use of the IMU / GNSS
        summary[key] = {**(summary.get(key) or {}), **entry}
    imu, front = summary.get("imu"), summary.get("imu_frontend")
    if (imu and imu.get("used") and imu.get("factors") == 0 and front
            and front.get("initialisations") == 0):  # read, but neither end could use it
        imu["used"] = False
    if result.gnss_fixes:
        write_gnss_fixes(out_dir / "gnss_fixes.csv", result.gnss_fixes)
    if n and painter is not None:
        painter.finish(drawing)
    write_atomic(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def write_gnss_fixes(path: Path, fixes: list) -> None:
    """gnss_fixes.csv: per input fix (lidar_slam.backend.imu_gnss_solve.FixReport) its stamp, the
    keyframe it was tied to (-1: none), its position in the run's ENU frame (m), its residual
    after the final solve (m) and normalised squared residual (chi-square, 3 dof), and whether
    it was used, rejected (a multipath jump) or unused, with why."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        rows = csv.writer(fh)
        rows.writerow(["stamp_s", "keyframe", "east_m", "north_m", "up_m", "residual_m", "d2",
                       "status", "why"])
        rows.writerows([f"{f.stamp_s:.6f}", f.keyframe, *(f"{v:.4f}" for v in f.enu_m),
                        f"{f.residual_m:.4f}", f"{f.d2:.3f}", f.status, f.why] for f in fixes)


LOCALIZE_OUTPUTS = ("poses_kitti.txt", "poses_tum.txt", "status.csv", "summary.json")


def write_localization(out_dir: Path, frames: list, summary: dict, poses: bool = True) -> dict:
    """The outputs of `localize` (LOCALIZE_OUTPUTS): poses in the map frame (unless poses is
    False: none localised) and status.csv, one line per input frame, and the summary (returned,
    with the frame counts added)."""
    from lidar_slam.localize import Status

    out_dir.mkdir(parents=True, exist_ok=True)
    if poses:
        T = np.stack([f.T_map_scan for f in frames]) if frames else np.zeros((0, 4, 4))
        write_kitti_poses(out_dir / "poses_kitti.txt", T)
        write_tum(out_dir / "poses_tum.txt", np.array([f.stamp_s for f in frames]), T)
    with atomic_path(out_dir / "status.csv") as tmp, open(tmp, "w", newline="") as fh:
        rows = csv.writer(fh)
        rows.writerow(["frame", "stamp_s", "status", "fitness"])
        rows.writerows([f.index, f"{f.stamp_s:.6f}", f.status.value, f"{f.fitness:.4f}"]
                       for f in frames)
    counts = {s: sum(f.status == s for f in frames) for s in Status}
    first = next((f.index for f in frames if f.status != Status.LOST), None)
    summary = {"frames": len(frames),
               "frames_localized": counts[Status.LOCALIZED] + counts[Status.TRACKING],
               "frames_tracking": counts[Status.TRACKING],
               "frames_relocalized": counts[Status.LOCALIZED],
               "frames_lost": counts[Status.LOST], "first_localized_frame": first, **summary}
    write_atomic(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
