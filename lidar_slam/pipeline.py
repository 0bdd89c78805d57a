"""The SLAM pipeline in flow order:
reader -> deskew -> odometry -> keyframe? -> (loop worker: scan-context query -> ICP verify)
-> back-end (pose graph, bounded-window updates; full solve at the end) -> map / metrics.
With an IMU, deskew follows the integrated IMU and odometry starts from its prediction
(lidar_slam.frontend.imu_prediction).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.frontend.deskew import DeskewedScan, Deskewer
from lidar_slam.frontend.edge_information import EdgeInformation
from lidar_slam.frontend.keyframes import KeyframeSelector, SteadyWait
from lidar_slam.frontend.odometry import Odometry, OdometryResult, VoxelSelector
from lidar_slam.geo import GeoReference
from lidar_slam.geometry import interpolate, inverse, transform_points
from lidar_slam.loop import adapt
from lidar_slam.map.keyframes import KeyframeStore
from lidar_slam.types import Scan

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """Everything a run computed, frame by frame (lists grow as scans are processed)."""

    store: KeyframeStore  # keyframe clouds (on disk) and odometry poses
    indices: list[int] = field(default_factory=list)
    stamps_s: list[float] = field(default_factory=list)
    odom_poses: list[np.ndarray] = field(default_factory=list)  # T_world_scan before loops
    frame_kf: list[int] = field(default_factory=list)  # keyframe each frame hangs off
    kf_poses: dict[int, np.ndarray] = field(default_factory=dict)  # final T_world_kf
    # keyframe id -> 6x6 marginal covariance of kf_poses (rotation first, keyframe's frame)
    kf_covariances: dict[int, np.ndarray] = field(default_factory=dict)
    # keyframe id -> information of the odometry edge from the previous keyframe (its own data:
    # lidar_slam.frontend.edge_information), where it could be had
    odom_information: dict[int, np.ndarray] = field(default_factory=dict)
    # keyframes whose odometry edge's information is its clouds' (not the configured sigmas)
    odom_measured: set[int] = field(default_factory=set)
    # keyframe id -> unit vector against gravity in the keyframe's frame (the IMU's), with an IMU
    kf_up: dict[int, np.ndarray] = field(default_factory=dict)
    # keyframe id -> the node's instant minus its frame's stamp (s), for nodes not at the stamp
    # (at the registered instant, the sweep's middle: _add_keyframe); None: not known (a run
    # resumed from a checkpoint older than 2026-12-06)
    kf_node_dt: dict[int, float] | None = field(default_factory=dict)
    loops: list = field(default_factory=list)  # LoopRecord rows for loops.csv
    skipped_empty: int = 0
    skipped_small: int = 0  # scans with fewer than data.min_points points in range
    graph: object | None = None  # the keyframe PoseGraph when loops are on (for graph.g2o)
    seconds: dict[str, float] = field(default_factory=lambda: {"odometry": 0.0, "loops": 0.0})
    loop_update_s: list = field(default_factory=list)  # (keyframe, s) of each loop's update
    adaptive: dict = field(default_factory=dict)  # the config's "auto" settings as fixed
    # (match kf, query kf) -> "inlier" / "rejected": what the final solve made of each loop
    loop_backend: dict = field(default_factory=dict)
    # keyframe ids whose odometry edge the loop stage found contradicted by its clouds (loop
    # submaps stop there: LoopDetector.edge_consistent)
    loop_split_edges: set = field(default_factory=set)
    backend_init: str = ""  # the start the final solve kept (live / chordal; GNC: odometry)
    # slow scans refined against the last keyframes; refinements refused by the correction
    # gate, by the held-out points' evidence after the ICP, and before it (see odometry)
    refined_scans: tuple[int, int, int, int] = (0, 0, 0, 0)
    refined_at_speed: int = 0  # of refined_scans[0]: for a lasting speed (lidar only)
    # the covariances' rotation floor and bias from those scans' corrections
    # (Pipeline._with_refinement_floor), None when the covariances do not take them
    refinement_floor: dict | None = None
    coarse_scans: int = 0  # registrations that started from a coarse pass (lidar only)
    # scans from constant velocity that also started from the last pose (odometry.
    # second_start_deg), and of them those it kept
    second_start: tuple[int, int] = (0, 0)
    # keyframes made after waiting for a steady scan, and of them those made at the wait's end
    # or the next one due instead (frontend.keyframes SteadyWait)
    steady_wait: tuple[int, int] = (0, 0)
    # Without IMU factors in the final solve: the deskew's white position sd added to the
    # keyframes' covariances (backend.odom_information.deskew_white_scale): keyframes given 1 cm
    # or more, the largest (m); None where the solve had IMU factors (not added)
    deskew_white: tuple[int, float] | None = (0, 0.0)
    # odometry failures (lidar_slam.frontend.failure): scan indices of every local-map reset
    # and of the first reset of each episode
    failure_resets: list[int] = field(default_factory=list)
    failure_episodes: list[int] = field(default_factory=list)
    # With IMU / GNSS in the final solve (backend.imu_gnss_solve), both taking the frame of
    # the output poses (poses_kitti.txt: frame 0 at its stamp is the identity): where it lies
    # on the Earth (GNSS; lidar_slam.geo.GeoReference), and the rotation from it to a
    # gravity-aligned z-up frame (the smallest one: no heading change), else None.
    geo: GeoReference | None = None
    T_gravity_map: np.ndarray | None = None
    gnss_fixes: list = field(default_factory=list)  # FixReport per input fix (gnss_fixes.csv)
    inertial_summary: dict = field(default_factory=dict)  # merged into summary.json imu / gnss
    # frames placed by the final solve with the IMU (position in the run -> T_world_lidar at
    # the frame's stamp); the others move with their keyframes (final_poses)
    frame_poses: dict[int, np.ndarray] = field(default_factory=dict)

    def final_poses(self) -> np.ndarray:
        """Every frame's pose (K, 4, 4): its odometry moved by the correction (optimised pose
        less odometry) of the keyframe it hangs off and of the next one, blended by its stamp
        between theirs. A keyframe's own frame gets exactly the keyframe's pose (moved from
        its node to the stamp where the node is not at the stamp: keyframe 0, and scans with
        point times without an IMU, Pipeline._node_at_ref); one moved
        by its own keyframe alone would jump at the next (on a car with an IMU the final
        solve corrects keyframes by a few cm and 0.01 deg). Frames the final solve placed with
        the IMU (frame_poses) take those."""
        n = len(self.odom_poses)
        out = np.empty((n, 4, 4))
        corr = {k: T @ inverse(self.store.T_world_kf_odom(k)) for k, T in self.kf_poses.items()}
        start: dict[int, int] = {}  # keyframe -> its own frame (the first that hangs off it)
        for i, k in enumerate(self.frame_kf):
            start.setdefault(k, i)
        t = np.asarray(self.stamps_s, dtype=float)
        if len(t) != n or not np.all(np.isfinite(t)):
            t = np.arange(n, dtype=float)
        for i, (T_odom, k) in enumerate(zip(self.odom_poses, self.frame_kf)):
            if i in self.frame_poses:
                out[i] = self.frame_poses[i]
                continue
            out[i] = corr[k] @ T_odom
            j = start.get(k + 1)
            if j is None or k + 1 not in corr or i == start[k] or not t[j] > t[start[k]]:
                continue
            s = float(np.clip((t[i] - t[start[k]]) / (t[j] - t[start[k]]), 0.0, 1.0))
            out[i] = interpolate(out[i], corr[k + 1] @ T_odom, s)
        return out


def lost_information(info: np.ndarray | None, sigma_m: float, cfg: SlamConfig) -> np.ndarray:
    """The information of an odometry edge across a failure reset: its own (or the configured
    sigmas') covariance plus kiss-icp's threshold at the reset, sigma_m, in every translation
    and sigma_m / data.max_range_m (rad: kiss-icp counts a rotation as the arc it makes at the
    maximum range) in every rotation. The registration's Hessian says how well the scan fitted
    the local map; across a reset the local map itself was wrong by about that much."""
    from lidar_slam.backend.factors import sigmas_to_information

    b = cfg.backend
    if info is None:
        info = sigmas_to_information(b.odom_rot_sigma_deg, b.odom_trans_sigma_m)
    cov = np.linalg.inv(info)
    cov += np.diag([(sigma_m / cfg.data.max_range_m) ** 2] * 3 + [sigma_m ** 2] * 3)
    out = np.linalg.inv(cov)
    return 0.5 * (out + out.T)


class Pipeline:
    """Calls the stages in flow order for one scan at a time; finish() ends the run."""

    def __init__(self, cfg: SlamConfig, run_dir: str | Path | None = None, viz=None,
                 resume: bool = False, inertial=None):
        self.cfg = cfg
        use_imu = inertial is not None and inertial.imu is not None and cfg.imu.enabled
        self.odometry = Odometry(cfg, imu=use_imu)
        self.deskew = Deskewer(cfg.data, 0.5 * cfg.voxel_size_m(), VoxelSelector())
        # The run's IMU / GNSS (io.inertial_input.InertialInput, on the scans' clock), handed
        # over once: the IMU deskews and predicts in the front-end, both go into finish()'s
        # final solve. finish() leaves it as the IMU check left it (summary.json's "imu").
        self.input = inertial
        self.inertial = None  # the IMU front-end
        if use_imu:
            from lidar_slam.frontend.imu_prediction import ImuFrontend

            self.inertial = ImuFrontend(inertial.imu, cfg.imu)
        self.keyframes: KeyframeSelector | None = None  # made by start(), at the first scan
        self.edge_information = (EdgeInformation(cfg.backend.odom_information,
                                                 cfg.keyframes.cloud_voxel_m)
                                 if cfg.backend.odom_information.enabled else None)
        # Without a run folder (library use), keyframes go to a temporary folder; resume reopens
        # the run folder's store (lidar_slam.run.checkpoint cuts it back to it).
        self.result = RunResult(KeyframeStore(None if run_dir is None
                                              else Path(run_dir) / "keyframes", keep=resume))
        self.backend = self.loops = None
        if cfg.loop.enabled:
            from lidar_slam.backend.slam_backend import Backend

            self.backend = Backend(cfg.backend)
            self.result.graph = self.backend.graph
        self.viz = viz
        self.loops_applied_upto = -1  # keyframes whose loop results are in the graph
        # The last registered frame whose pose at its stamp is only an extrapolation so far
        # (_settle): (its position in the run, T_world_ref, ref_s), else None. Every frame after
        # it was predicted (not registered) and waits with it.
        self.unsettled: tuple[int, np.ndarray, float] | None = None
        self.frames_total: int | None = None  # scans the run will have, when known (pacing)
        self.adaptive: dict[str, float] | None = None  # the "auto" settings, once fixed

    def start(self, adaptive: dict[str, float]) -> None:
        """Fix the config's "auto" settings (lidar_slam.loop.adapt, from the first scan) and
        start the stages that use them: keyframe selection and the loop worker."""
        self.adaptive = self.result.adaptive = adaptive
        self.cfg = adapt.apply(self.cfg, adaptive)
        if adaptive:
            log.info("loop settings: %s", adapt.describe(adaptive))
        self.keyframes = KeyframeSelector(self.cfg.keyframes)
        self.steady_wait = SteadyWait(self.cfg.keyframes)
        if self.cfg.loop.enabled:
            from lidar_slam.loop.worker import LoopWorker

            self.loops = LoopWorker(self.cfg, self.result.store, self.cfg.loop.worker)

    def process(self, scan: Scan) -> None:
        """Run one scan through every stage."""
        if self.adaptive is None:
            adaptive = adapt.auto_values(self.cfg, scan.points)
            if adaptive and len(scan.points) < self.cfg.data.min_points:
                log.warning("%s: the first scan has %d points: the loop settings that are "
                            "\"auto\" take their outdoor defaults (%s); set them in the config "
                            "or start at a scan with points (--start)", scan.source,
                            len(scan.points), adapt.describe(adaptive))
            self.start(adaptive)
        r, t0 = self.result, time.perf_counter()
        if self.inertial is None:
            deskewed, guess = self.deskew(scan, self.odometry.last_delta), None
        else:
            deskewed, guess = self.inertial.prepare(scan, self.deskew, self.odometry.last_delta)
        odom = self.odometry.step(deskewed, guess)
        if self.inertial is not None:
            odom = self.inertial.update(deskewed, odom)
        if not odom.registered:
            n = self.odometry.last_n_points
            if n == 0:
                log.warning("%s: empty scan after cropping, skipped (pose predicted)",
                            scan.source)
                r.skipped_empty += 1
            else:
                log.warning("%s: %d points after cropping (data.min_points: %d), too few to "
                            "register: skipped (pose predicted)", scan.source, n,
                            self.cfg.data.min_points)
                r.skipped_small += 1
        if odom.T_world_first is not None:
            r.odom_poses[0] = odom.T_world_first
        self._settle(deskewed, odom)
        r.seconds["odometry"] += time.perf_counter() - t0
        due = odom.registered and self.keyframes.is_keyframe(odom.T_world_scan)
        # the miss of the constant-velocity prediction: measured where it deskewed the scan
        cv = self.inertial is None and deskewed.motion is None and odom.registered
        miss = self.steady_wait.miss_deg(odom.T_world_ref if cv else None)
        is_kf = odom.registered and self.steady_wait.take(due, miss)
        if is_kf or len(r.store) == 0:  # an empty first scan still needs a keyframe
            self._add_keyframe(deskewed, odom, due or len(r.store) == 0)
        elif due:  # the keyframe waits for a steady scan; the odometry's copy is made here
            T_node, pts, _, anchor = self._node(deskewed, odom, self._keyframe_cloud(deskewed)[0])
            self._add_anchor(T_node, pts, anchor)
        r.indices.append(scan.index)
        r.stamps_s.append(scan.stamp_s)
        r.odom_poses.append(odom.T_world_scan)
        r.frame_kf.append(len(r.store) - 1)
        if self._extrapolated(deskewed, odom):
            self.unsettled = (len(r.odom_poses) - 1, odom.T_world_ref, deskewed.ref_s)
        if self.viz is not None:
            self.viz.log_scan(self, scan, transform_points(inverse(odom.T_ref_stamp),
                                                           deskewed.points), odom.T_world_scan,
                              is_kf)

    def _extrapolated(self, deskewed: DeskewedScan, odom: OdometryResult) -> bool:
        """Whether the scan's pose at its stamp is the registered instant's (the sweep's middle)
        moved forward along a motion the scans so far only extrapolate: stamps at sweep end,
        deskewed at constant velocity (no IMU). The next scan's registration brings the stamp
        between two registered instants (_settle). With an IMU the IMU's motion carries the
        registered pose to the stamp; the scans before it is initialised (and after the IMU
        check switched it off) keep their extrapolation."""
        return (self.inertial is None and odom.registered and deskewed.ref_s < 0.0
                and deskewed.motion is None)

    def _node_at_ref(self, deskewed: DeskewedScan, odom: OdometryResult) -> bool:
        """Whether a keyframe's cloud and node stay at the registered instant (the sweep's
        middle) instead of its stamp: without an IMU, wherever the stamp is not the registered
        instant. The stamp pose is then only the registered one moved along the odometry's
        motion (extrapolated at sweep end, interpolated between two registrations at sweep
        start), which a shake faster than the scans cannot follow."""
        return (self.inertial is None and odom.registered and deskewed.ref_s != 0.0
                and deskewed.motion is None)

    def _settle(self, deskewed: DeskewedScan, odom: OdometryResult) -> None:
        """The previous frame's pose at its stamp, when it was extrapolated (sweep-end stamps,
        no IMU): interpolated between its registered instant and this scan's, as a sweep-start
        stamp is (lidar_slam.frontend.deskew T_ref_stamp), instead of carried forward along the
        previous motion. On a legged trot (bank office-legged-xt32, lidar only) the frame-to-frame
        rotation error of the stamp poses halves: 3.19 -> 1.68 deg median (docs/bank.md). Scans
        skipped in between (too few points: their poses predicted) wait with it and are placed
        between the same two registrations by their stamps, not carried along the last motion
        (two empty scans mid-turn: 10 deg off before)."""
        if self.unsettled is None or not odom.registered:
            return  # a skipped scan: it waits too
        pos, T_world_ref, ref_s = self.unsettled
        self.unsettled = None
        r = self.result
        # the two registered instants
        t_a = r.stamps_s[pos] + ref_s
        span = deskewed.scan.stamp_s + deskewed.ref_s - t_a
        if not span > 0.0:
            return
        D = inverse(T_world_ref) @ odom.T_world_ref
        for i in range(pos, len(r.odom_poses)):  # it, and the skipped scans since
            if i == 0 and odom.T_world_first is not None:
                continue  # frame 0: the odometry moved it already (T_world_first)
            s = (r.stamps_s[i] - t_a) / span
            if 0.0 < s < 1.0:
                self.result.odom_poses[i] = T_world_ref @ interpolate(np.eye(4), D, s)

    @property
    def settled_frames(self) -> int:
        """How many of the frames so far have their final odometry pose: all but an unsettled
        last one, and none before the second registered scan (frame 0's pose moves to its stamp
        then: lidar_slam.frontend.odometry T_world_first)."""
        if self.odometry.n_registered < 2:
            return 0
        if self.unsettled is None:
            return len(self.result.odom_poses)
        return self.unsettled[0]

    def _keyframe_cloud(self, deskewed: DeskewedScan) -> tuple[np.ndarray, np.ndarray | None]:
        """A keyframe's cloud: one deskewed point per voxel within the map range (and their
        intensities), in the registered instant's frame."""
        c = self.cfg
        return deskewed.cloud(c.keyframes.cloud_voxel_m, c.data.min_range_m,
                              min(c.data.max_range_m, c.map.max_range_m))

    def _node(self, deskewed: DeskewedScan, odom: OdometryResult, pts: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, bool, tuple | None]:
        """A keyframe of this scan: its node pose, its cloud in the node's frame, whether the
        node is at the registered instant, and the odometry's own copy (pose, points) when it is
        not the node's (None: the node's). The cloud and node are at the stamp, or without an
        IMU at the registered instant (the sweep's middle: _node_at_ref), whose stamp pose is
        only extrapolated or interpolated from it: there a loop measures what two registrations
        measured, not the stamp offsets' errors (on a legged trot 3-6 deg of tilt;
        office-handheld-mid360's shake loops up to 7 deg: docs/bank.md)."""
        T_node = odom.T_world_scan
        at_ref = self._node_at_ref(deskewed, odom)
        anchor = None
        if at_ref:
            T_node = odom.T_world_ref
            if not self._extrapolated(deskewed, odom):
                # a sweep-start stamp: the odometry keeps its keyframes at their stamps, as it
                # always has (the same poses; only the graph's nodes move to the sweep's middle)
                anchor = (np.array(odom.T_world_scan, dtype=np.float64), np.asarray(
                    transform_points(inverse(odom.T_ref_stamp), pts), dtype=np.float32))
        elif odom.registered:
            pts = transform_points(inverse(odom.T_ref_stamp), pts)
            # the first scan: no motion known yet, its stamp pose is its registered one
            at_ref = bool(np.array_equal(odom.T_ref_stamp, np.eye(4)))
        if not odom.registered:
            pts = pts[:0]
        return T_node, pts, at_ref, anchor

    def _add_anchor(self, T_node: np.ndarray, pts: np.ndarray, anchor: tuple | None) -> None:
        """The odometry's copy of a keyframe due at this scan (_node's anchor, else the node
        itself), when it has points."""
        if len(pts):
            self.odometry.add_anchor(*(anchor or (np.array(T_node, dtype=np.float64),
                                                  np.asarray(pts, dtype=np.float32))))

    def _add_keyframe(self, deskewed: DeskewedScan, odom: OdometryResult,
                      due: bool = True) -> None:
        """Keyframe cloud to the store; its node to the back-end and its loop search to the
        worker (_node); the odometry's copy of it when a keyframe fell due at this scan (due;
        else it was made where it did, _add_anchor)."""
        c = self.cfg
        pts, inten = self._keyframe_cloud(deskewed)
        T_node, pts, at_ref, anchor = self._node(deskewed, odom, pts)
        if not odom.registered:
            inten = None
        kf = self.result.store.add(deskewed.scan.index, T_node, pts, inten,
                                   deskewed.scan.stamp_s)
        if at_ref and deskewed.ref_s != 0.0 and self.result.kf_node_dt is not None:
            self.result.kf_node_dt[kf.id] = float(deskewed.ref_s)
        if due:
            self._add_anchor(kf.T_world_kf_odom, kf.points, anchor)
        up = self.inertial.up_in_lidar() if self.inertial is not None else None
        if up is not None and odom.registered:
            self.result.kf_up[kf.id] = odom.T_ref_stamp[:3, :3].T @ up
        if self.backend is None:
            self.weigh_keyframe(kf.id, kf.T_world_kf_odom, kf.points)
            return
        # The loop worker weighs the edge (LoopResult.edge_information): the keyframe joins the
        # graph when its loop result is collected (_apply_loops), with its loops.
        t0 = time.perf_counter()
        self.loops.submit(kf.id)
        self._apply_loops(kf.id - c.loop.collect_lag_keyframes)
        self.loops.pace(None if self.frames_total is None
                        else self.frames_total - len(self.result.indices) - 1)
        self.result.seconds["loops"] += time.perf_counter() - t0

    def weigh_keyframe(self, kf_id: int, T_world_kf: np.ndarray, points: np.ndarray
                       ) -> np.ndarray | None:
        """The information of the odometry edge into kf_id (kept in the result), or None (the
        configured sigmas), from the clouds of this keyframe and the one before; keyframes in
        order, as stored (a run without loops as it makes them, a resumed run replays them)."""
        raw = None if self.edge_information is None else \
            self.edge_information.add(T_world_kf, points)
        return self._widened(kf_id, raw)

    def _widened(self, kf_id: int, raw: np.ndarray | None) -> np.ndarray | None:
        """The edge information into kf_id as the clouds give it (raw; None: the configured
        sigmas), widened across an odometry failure, kept in the result."""
        info, store = raw, self.result.store
        if raw is not None:  # its own information, with the configured floors
            self.result.odom_measured.add(kf_id)
        if kf_id > 0:
            sigma = self.odometry.failures.sigma_between(store.frame_index(kf_id - 1),
                                                         store.frame_index(kf_id))
            if sigma > 0:
                info = lost_information(info, sigma, self.cfg)
        if info is not None:
            self.result.odom_information[kf_id] = info
        return info

    def _add_node(self, kf_id: int, raw: np.ndarray | None) -> None:
        """Keyframe kf_id into the back-end's graph with its odometry edge's information."""
        info = self._widened(kf_id, raw)
        self.backend.add_keyframe(kf_id, self.result.store.T_world_kf_odom(kf_id), info)

    def _apply_loops(self, upto: int) -> None:
        """Collect the loop results of keyframes <= upto (in order) and update the back-end."""
        for res in self.loops.collect(upto):
            self._add_node(res.kf_id, res.edge_information)
            res = self._check_tilt(res)
            self.result.loops.extend(res.records)
            self.result.loop_split_edges.update(res.split_edges)
            if res.constraint is not None:
                self.backend.add_loop(res.constraint)
            self.loops_applied_upto = res.kf_id
        self.backend.update(force=False)

    def _check_tilt(self, res):
        """res (a LoopResult) without its constraint when the IMU says the loop tilts the query
        keyframe (loop.max_tilt_disagreement_deg): the up direction seen at the match, carried
        by the loop into the query's frame, against the one seen at the query."""
        c, limit = res.constraint, self.cfg.loop.max_tilt_disagreement_deg
        if c is None or not limit:
            return res
        up_m, up_q = self.result.kf_up.get(c.match), self.result.kf_up.get(c.query)
        if up_m is None or up_q is None:
            return res
        cos = float(np.clip((c.T_match_query[:3, :3].T @ up_m) @ up_q, -1.0, 1.0))
        tilt = float(np.degrees(np.arccos(cos)))
        if tilt <= limit:
            return res
        log.info("loop %d -> %d refused: it tilts the query %.1f deg from the IMU's gravity",
                 c.query, c.match, tilt)
        records = tuple(dataclasses.replace(r, accepted=False, reason=f"gravity: tilt "
                                            f"{tilt:.1f} deg > {limit:.1f}") if r.accepted
                        else r for r in res.records)
        return dataclasses.replace(res, records=records, constraint=None)

    def current_kf_poses(self) -> dict[int, np.ndarray]:
        """Best current T_world_kf of every keyframe (live estimate, or odometry)."""
        if self.backend is not None:
            return self.backend.poses()
        table = self.result.store.table()
        return {int(k): T for k, T in zip(table["id"], table["T"])}

    def finish(self) -> RunResult:
        """Wait for the loop worker, solve the full graph, and return the run's result. With
        an IMU or GNSS (the constructor's inertial, as the IMU check left it: self.input), the
        final solve includes them (lidar_slam.backend.imu_gnss_solve), with or without loops."""
        from lidar_slam.frontend.imu_check import trusted_input

        self.input = inertial = trusted_input(self.input, self.inertial)
        r = self.result
        o = self.odometry
        r.refined_scans = (o.n_refined, o.n_refine_refused, o.n_refine_unproven,
                           o.n_refine_skipped)
        r.refined_at_speed = o.n_refined_at_speed
        r.coarse_scans = o.n_coarse
        r.second_start = (o.n_second_tried, o.n_second_taken)
        if self.keyframes is not None:
            r.steady_wait = (self.steady_wait.late, self.steady_wait.not_steady)
        r.failure_resets = list(self.odometry.failures.resets)
        r.failure_episodes = list(self.odometry.failures.episodes)
        if r.failure_resets:
            log.warning("odometry failed %d time(s) (episodes from scans %s): %d local-map "
                        "resets (summary.json odometry_failures)", len(r.failure_episodes),
                        r.failure_episodes, len(r.failure_resets))
        if self.adaptive is None:  # no scan at all
            self.start(adapt.auto_values(self.cfg, None))
        use_inertial = inertial is not None and (inertial.imu is not None
                                                 or inertial.gnss is not None)
        if self.backend is None and use_inertial and len(r.store):
            from lidar_slam.backend.slam_backend import Backend

            self.backend = Backend(self.cfg.backend)  # no loops: the odometry chain
        if self.backend is not None:
            t0 = time.perf_counter()
            if self.loops is not None:
                waited = self.loops.wait_s
                self.loops.pace(0)  # nothing left to share the cores with
                try:
                    self._apply_loops(len(r.store))
                finally:
                    self.loops.close()
            for kf_id in range(len(self.backend), len(r.store)):
                if self.loops is None:  # no loops: weighed as it was made (_add_keyframe)
                    self.backend.add_keyframe(kf_id, r.store.T_world_kf_odom(kf_id),
                                              r.odom_information.get(kf_id))
                else:  # stopped between the store and the worker
                    self._add_node(kf_id, None if self.edge_information is None
                                   else self.edge_information.stored(r.store, kf_id))
            r.kf_poses = self.backend.finish()
            r.kf_covariances = lidar_covariances = self.backend.covariances
            lidar_graph = self.backend.graph
            r.loop_update_s = self.backend.loop_update_s
            r.loop_backend, r.backend_init = self.backend.loop_status, self.backend.final_init
            if use_inertial and r.kf_poses:
                self._solve_inertial(inertial)
            r.seconds["backend"] = sum(self.backend.seconds.values())
            r.seconds["backend_final"] = (self.backend.seconds["final"]
                                          + self.backend.seconds.get("inertial", 0.0))
            if self.loops is not None:
                r.seconds["loop_worker"] = self.loops.busy_s
                r.seconds["loop_wait"] = self.loops.wait_s
                r.seconds["loop_wait_final"] = self.loops.wait_s - waited  # the final backlog
                r.seconds["loop_worker_urgent"] = self.loops.urgent_s
                r.seconds["loops"] += time.perf_counter() - t0
        else:
            from lidar_slam.backend.slam_backend import chain_graph

            r.kf_poses = self.current_kf_poses()
            lidar_graph = (chain_graph(self.cfg.backend, r.kf_poses, r.odom_information)
                           if r.kf_poses else None)
            r.kf_covariances = lidar_covariances = (lidar_graph.covariances() if lidar_graph
                                                    else {})
        r.refinement_floor = None
        if r.kf_covariances and r.kf_covariances is lidar_covariances:  # not the IMU / GNSS solve's
            r.kf_covariances = self._with_refinement_floor(lidar_graph, r.kf_covariances)
        r.kf_covariances = self._with_deskew_white(r.kf_covariances)
        return r

    def _with_refinement_floor(self, graph, covariances: dict[int, np.ndarray]
                               ) -> dict[int, np.ndarray]:
        """The lidar graph's covariances again with the rotation floor and bias the run's
        refinement at speed measured (backend.refinement_floor), when it made at least
        backend.odom_information.floor_from_refinement_scans corrections at speed and the edges
        carry their own information; else as they are. summary.json says which
        (covariance_refinement_floor)."""
        from lidar_slam.backend.refinement_floor import RefinementFloor, refloored

        cfg, o, r = self.cfg.backend, self.odometry, self.result
        oi = cfg.odom_information
        if (not oi.enabled or oi.floor_from_refinement_scans is None
                or o.speed_corrections < max(1, oi.floor_from_refinement_scans)):
            return covariances
        t0 = time.perf_counter()
        floor = RefinementFloor.from_sums(o.speed_corrections, o.speed_correction_sum,
                                          o.speed_correction_sq, o.speed_correction_m)
        floor_rad = floor.floor_rad(np.radians(oi.refinement_floor_min_deg))
        bias = floor.bias_per_m(oi.refinement_bias_fraction)
        try:
            out, factor = refloored(graph.priors, graph.covariance_edges(cfg.robust, cfg.huber_k),
                                    graph.estimate, r.odom_measured,
                                    np.radians(oi.min_rot_sigma_deg), floor_rad, bias)
        except RuntimeError as exc:  # gtsam: an indeterminate system (covariances had none)
            log.warning("covariances kept at the configured rotation floor (gtsam: %s)",
                        str(exc).strip().splitlines()[0])
            return covariances
        r.refinement_floor = {
            "seconds": time.perf_counter() - t0,
            "scans": floor.scans, "floor_deg": float(np.degrees(floor_rad)),
            "rms_deg": np.degrees(floor.rms_rad).tolist(),
            "mean_deg": np.degrees(floor.mean_rad).tolist(), "step_m": floor.step_m,
            "bias_sd_deg_per_m": np.degrees(bias).tolist(), "variance_factor": factor}
        return {k: out.get(k, c) for k, c in covariances.items()}

    def _with_deskew_white(self, covariances: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """The final keyframe covariances with the position error a constant-velocity deskew
        leaves (frontend.edge_information.deskew_white) added, when no IMU is in the final
        solve: lidar only, GNSS only (fixes metres apart and sure to decimetres do not see it),
        an IMU switched off by the check or too short to use (the scans before a switch-off
        were deskewed by the IMU: there the term is more than their error). With IMU factors
        the solve's own white terms stand; None in summary.json says so."""
        from lidar_slam.frontend.edge_information import deskew_white

        scale = self.cfg.backend.odom_information.deskew_white_scale
        r = self.result
        if r.inertial_summary.get("imu", {}).get("factors"):
            r.deskew_white = None
            return covariances
        r.deskew_white = (0, 0.0)
        if not scale or not covariances or len(r.odom_poses) < 3:
            return covariances
        frames = np.asarray(r.indices)
        kfs = sorted(covariances)
        positions = {k: int(np.searchsorted(frames, r.store.frame_index(k))) for k in kfs}
        ranges = {}
        for k in kfs:
            pts = r.store.get(k).points
            ranges[k] = float(np.median(np.linalg.norm(pts, axis=1))) if len(pts) else 0.0
        white = deskew_white(np.stack(r.odom_poses), positions, ranges, scale)
        out = {}
        for k, cov in covariances.items():
            cov = np.array(cov, dtype=float)
            cov[3:, 3:] += white[k] * np.eye(3)
            out[k] = cov
        sd = np.sqrt(np.fromiter(white.values(), dtype=float))
        r.deskew_white = (int((sd >= 0.01).sum()), float(sd.max()))
        return out

    def _solve_inertial(self, inertial) -> None:
        """The final solve again with the IMU and GNSS factors (when they can be used): the
        keyframe poses, covariances, geo-reference and gravity direction of the result."""
        from lidar_slam.backend import imu_gnss_solve as solver
        from lidar_slam.geo import GeoReference
        from lidar_slam.imu import gravity_rotation

        r, t0 = self.result, time.perf_counter()
        table = r.store.table()
        odom = np.stack(r.odom_poses)
        at_stamp = odom[np.searchsorted(np.asarray(r.indices), table["frame_index"])]
        tr = solver.RunTrajectory(np.asarray(table["stamp_s"], dtype=float),
                                  np.asarray(table["T"], dtype=float), at_stamp,
                                  np.asarray(r.stamps_s), odom)
        out = solver.solve(self.cfg, r.kf_poses, self.backend.final_edges(), tr, inertial.imu,
                           inertial.gnss, r.odom_information)
        self.backend.seconds["inertial"] = time.perf_counter() - t0
        if out is None:
            return
        r.gnss_fixes, r.inertial_summary = out.fixes, out.summary
        if out.T_S_world is None:  # the GNSS could not place the run, and no IMU
            return
        r.kf_poses, r.kf_covariances = out.kf_poses, out.covariances
        r.frame_poses = out.frame_poses
        # the output map frame: frame 0 at its stamp (lidar_slam.run.outputs anchors there)
        kf0 = r.frame_kf[0]
        T_world_map = r.kf_poses[kf0] @ inverse(r.store.T_world_kf_odom(kf0)) @ r.odom_poses[0]
        T_S_map = out.T_S_world @ T_world_map
        T_gravity_map = np.eye(4)
        T_gravity_map[:3, :3] = gravity_rotation(T_S_map[:3, :3].T @ [0.0, 0.0, 1.0])
        r.T_gravity_map = T_gravity_map
        if out.enu is not None:
            r.geo = GeoReference(out.enu, T_S_map)

    def close(self) -> None:
        """Stop the loop worker and release the keyframe store."""
        if self.loops is not None:
            self.loops.close()
        self.result.store.close()


def run(scans: Iterable[Scan], cfg: SlamConfig, run_dir: str | Path | None = None,
        on_scan: Callable[[Scan, RunResult], None] | None = None, inertial=None) -> RunResult:
    """Process scans in order and return the result (its keyframe store stays open): the bare
    loop over Pipeline, for library use and tests, with no run folder rules, signals or outputs,
    and errors propagate. The run driver (what `lidar-slam run` and `batch` do: --out rules,
    resume, signals, the frames so far kept on an error, the outputs) is
    lidar_slam.run.run_sequence. inertial: the IMU / GNSS (io.inertial_input.InertialInput):
    the IMU deskews and predicts in the front-end, both go into the final solve. on_scan sees
    the odometry poses so far; the last may still move (Pipeline.settled_frames)."""
    pipe = Pipeline(cfg, run_dir, inertial=inertial)
    try:
        for scan in scans:
            pipe.process(scan)
            if on_scan is not None:
                on_scan(scan, pipe.result)
        return pipe.finish()
    finally:
        if pipe.loops is not None:
            pipe.loops.close()
