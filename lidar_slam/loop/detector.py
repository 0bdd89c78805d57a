"""Loop detection for the pipeline: keyframe -> scan-context query -> ICP verify -> constraint.

The back-end (lidar_slam.backend.slam_backend) turns accepted constraints into graph edges.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from lidar_slam.backend.factors import sigmas_to_information
from lidar_slam.config import SlamConfig
from lidar_slam.frontend.edge_information import EdgeInformation
from lidar_slam.geometry import between_error, inverse, relative, to_xyz_quat, transform_points
from lidar_slam.loop.scan_context import ScanContextIndex
from lidar_slam.loop.verify import (
    Side,
    evaluate_fit,
    information_matrix,
    match_side,
    query_side,
    verify,
)
from lidar_slam.map.keyframes import KeyframeStore
from lidar_slam.registration import Cloud, align, make_cloud
from lidar_slam.types import LoopCandidate, LoopConstraint

log = logging.getLogger(__name__)

# Match submaps whose verification clouds are kept (about 2 MB each). With the odometry
# plausibility gate, consecutive query keyframes matching the same old keyframe are most of the
# reuse: on simulated 00 the last 2 kept serve 37 of 351 verifications, 16 kept 49; on the
# 10,000-scan drive 124 vs 144 of 2,171. Replaying that drive's keyframe store, the detector
# ended at 140 MB with 16 kept, 86.5 MB with 2, 75 MB with none (cache and heap fragmentation).
MATCH_SIDES_KEPT = 2
# Fewer points (or matched points) than this in either keyframe: an edge is not checked.
MIN_EDGE_POINTS = 30
# Keyframe clouds kept for the edge checks (a query's 2 edges, a match submap's 4).
EDGE_CLOUDS_KEPT = 8


def chi2_isf_6(p: float) -> float:
    """x with P(chi2 with 6 dof > x) = p (0 < p < 1): scipy.special.chdtri(6, p), without the
    0.4 s its import adds to the loop worker's start (a process of its own, beside the run on
    the same cores). For an even dof the survival function is closed: exp(-x/2) (1 + x/2 +
    (x/2)^2 / 2) for 6, decreasing in x, so bisection finds it to the last bits."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"probability {p} not in (0, 1)")
    lo, hi = 0.0, 1.0
    while math.exp(-hi / 2) * (1 + hi / 2 + hi * hi / 8) > p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if math.exp(-mid / 2) * (1 + mid / 2 + mid * mid / 8) > p:
            lo = mid
        else:
            hi = mid
    return hi


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


@dataclass(frozen=True)
class LoopResult:
    """What loop detection found for one query keyframe: every verified candidate (loops.csv
    rows) and the accepted constraint, if any."""

    kf_id: int
    records: tuple[LoopRecord, ...]
    constraint: LoopConstraint | None
    # the information of the odometry edge into kf_id (6x6, rotation first), from the clouds
    # (frontend.edge_information; None: too thin, or off: the configured sigmas)
    edge_information: np.ndarray | None = None
    # odometry edges (the keyframe ids they lead into) found contradicted by their clouds while
    # building this keyframe's submaps (LoopDetector.edge_consistent)
    split_edges: tuple[int, ...] = ()


class LoopDetector:
    """Scan-context query and ICP verification of each new keyframe against the older ones.

    It reads keyframes from the store and never touches the pose graph; everything it uses for a
    query keyframe k (its descriptor, submaps of keyframes <= k at their odometry poses) is fixed
    once k is stored, so its results do not depend on when it runs.
    """

    def __init__(self, cfg: SlamConfig, store: KeyframeStore):
        self.cfg = cfg
        self.store = store
        # Descriptor grids go to the keyframe store's folder: RAM keeps a few hundred bytes each.
        self.index = ScanContextIndex(cfg.loop.scan_context, store.root / "descriptors.bin")
        self._path_m = [0.0]  # odometry path travelled up to each keyframe (metres)
        self._sides: dict[tuple[int, int], Side] = {}  # match submaps' clouds, oldest first
        # Each odometry edge's information (into keyframe k, rotation first, k's frame) from the
        # clouds: the back-end's (it comes with k's result) and, inverted, the drift gate's.
        b = cfg.backend
        self._edges = (EdgeInformation(b.odom_information, cfg.keyframes.cloud_voxel_m)
                       if b.odom_information.enabled else None)
        self._default_cov = np.linalg.inv(sigmas_to_information(b.odom_rot_sigma_deg,
                                                                b.odom_trans_sigma_m))
        # keyframe id -> its edge's information (None: the configured sigmas) and covariance,
        # computed when first needed: each keyframe's by process(), older ones (a resumed run's)
        # by the drift gate
        self._edge_info: dict[int, np.ndarray | None] = {}
        self._edge_cov: dict[int, np.ndarray] = {}
        self._gate_d2 = 0.0
        self._consistent: dict[int, bool] = {}  # keyframe id -> edge_consistent
        self._new_splits: list[int] = []  # ... since process() began
        self._edge_clouds: dict[int, Cloud] = {}  # keyframe id -> _edge_cloud, oldest first
        if cfg.loop.drift_gate_p > 0:
            self._gate_d2 = chi2_isf_6(cfg.loop.drift_gate_p)

    def path_m(self, kf_id: int) -> float:
        """Odometry path length from keyframe 0 to kf_id (keyframe to keyframe, metres)."""
        while len(self._path_m) <= kf_id:
            k = len(self._path_m)
            step = (self.store.T_world_kf_odom(k)[:3, 3]
                    - self.store.T_world_kf_odom(k - 1)[:3, 3])
            self._path_m.append(self._path_m[-1] + float(np.linalg.norm(step)))
        return self._path_m[kf_id]

    def _index(self, kf_id: int, points: np.ndarray) -> None:
        self.index.add(kf_id, points, self.path_m(kf_id), self.store.stamp_s(kf_id))

    def reindex(self, upto: int) -> None:
        """Index keyframes 0..upto from the store into a fresh detector, as process() would
        have (resuming a run)."""
        for kf_id in range(upto + 1):
            pts = self.store.get(kf_id).points
            if len(pts):
                self._index(kf_id, pts.astype(np.float64))

    def submap(self, kf_id: int, radius: int, upto: int) -> np.ndarray:
        """Clouds of keyframes kf_id-radius..kf_id+radius (none after `upto`) in kf_id's frame,
        but none beyond an odometry edge its own clouds contradict (edge_consistent): a
        neighbour placed across a jump of the odometry would smear the submap."""
        centre = self.store.T_world_kf_odom(kf_id)
        lo, hi = kf_id, kf_id
        while lo > max(0, kf_id - radius) and self.edge_consistent(lo):
            lo -= 1
        while hi < min(upto, kf_id + radius) and self.edge_consistent(hi + 1):
            hi += 1
        parts = []
        for j in range(lo, hi + 1):
            kf = self.store.get(j)
            parts.append(transform_points(relative(centre, kf.T_world_kf_odom),
                                          kf.points.astype(np.float64)))
        return np.concatenate(parts)

    def edge_consistent(self, kf_id: int) -> bool:
        """Do the clouds of keyframes kf_id - 1 and kf_id agree with the odometry edge between
        them? kf_id's cloud registered onto its predecessor's from the odometry's relative pose
        (the verification's fine clouds and ICP); the correction against the edge's covariance
        plus the registration's own (Mahalanobis, chi-square(6) at loop.drift_gate_p). An
        odometry that jumped between them (kiss-icp snapping onto its own older map at a
        revisit: 0.6 m in height in two scans of a legged trot, docs/bank.md) fails; so does
        nothing else on the bank. Cached; a function of the two stored keyframes only."""
        ok = self._consistent.get(kf_id)
        if ok is None:
            ok = True
            if self._gate_d2 > 0 and kf_id > 0:
                d2 = self._edge_d2(kf_id)
                ok = d2 <= self._gate_d2
                if not ok:
                    self._new_splits.append(kf_id)
                    log.info("keyframe %d: odometry edge from %d contradicted by its clouds "
                             "(Mahalanobis^2 %.0f > %.1f): loop submaps do not cross it",
                             kf_id, kf_id - 1, d2, self._gate_d2)
            self._consistent[kf_id] = ok
        return ok

    @property
    def n_split(self) -> int:
        """How many odometry edges edge_consistent has found contradicted so far."""
        return sum(not ok for ok in self._consistent.values())

    def _edge_d2(self, kf_id: int) -> float:
        """Squared Mahalanobis distance of kf_id's cloud registered onto kf_id - 1's from the
        odometry's pose (edge_consistent); 0 when either cloud is too thin to say."""
        v = self.cfg.loop.verify
        prev, kf = self.store.get(kf_id - 1), self.store.get(kf_id)
        if min(len(prev.points), len(kf.points)) < MIN_EDGE_POINTS:
            return 0.0
        tgt, src = self._edge_cloud(kf_id - 1), self._edge_cloud(kf_id)
        T0 = relative(prev.T_world_kf_odom, kf.T_world_kf_odom)
        T = align(tgt.cloud, tgt.tree, src.cloud, T0, v.max_correspondence_m,
                  v.max_iterations, "PLANE_ICP")
        fit = evaluate_fit(src, tgt, T, v.inlier_m)
        if len(fit.correspondences) < MIN_EDGE_POINTS:
            return 0.0
        info = information_matrix(src.points, tgt.points, tgt.normals, fit.correspondences, T,
                                  fit.rmse_m, v)
        cov = self._edge_covariance(kf_id) + np.linalg.inv(info)
        err = between_error(T0, np.eye(4), T)
        return float(err @ np.linalg.solve(cov, err))

    def _edge_cloud(self, kf_id: int) -> Cloud:
        """Keyframe kf_id's fine cloud with normals for the edge checks: the target of the edge
        after it and the source of the edge into it (PLANE_ICP reads the target's normals
        only, so one cloud serves both), the last EDGE_CLOUDS_KEPT kept."""
        cloud = self._edge_clouds.pop(kf_id, None)
        if cloud is None:
            cloud = make_cloud(self.store.get(kf_id).points.astype(np.float64),
                               self.cfg.loop.verify.voxel_m, True, False)
        self._edge_clouds[kf_id] = cloud  # newest last
        while len(self._edge_clouds) > EDGE_CLOUDS_KEPT:
            self._edge_clouds.pop(next(iter(self._edge_clouds)))
        return cloud

    def plausible(self, query: int, match: int) -> bool:
        """Could the odometry have drifted far enough to put these keyframes where it did, were
        they the same place? Their odometry positions at most loop.max_gap_m + loop.max_drift x
        the path travelled between them apart (fixed once both are stored: deterministic)."""
        cfg = self.cfg.loop
        gap = float(np.linalg.norm(self.store.T_world_kf_odom(query)[:3, 3]
                                   - self.store.T_world_kf_odom(match)[:3, 3]))
        allowed = cfg.max_gap_m + cfg.max_drift * abs(self.path_m(query) - self.path_m(match))
        if gap > allowed:
            log.debug("kf %d -> %d: odometry puts them %.1f m apart (> %.1f m): not a candidate",
                      query, match, gap, allowed)
        return gap <= allowed

    def edge_information(self, kf_id: int) -> np.ndarray | None:
        """The information of the odometry edge into kf_id (EdgeInformation on the stored
        clouds and poses of kf_id - 1 and kf_id: what the pipeline's back-end takes; None: the
        configured sigmas)."""
        if kf_id not in self._edge_info:
            self._edge_info[kf_id] = (None if self._edges is None
                                      else self._edges.stored(self.store, kf_id))
        return self._edge_info[kf_id]

    def _edge_covariance(self, kf_id: int) -> np.ndarray:
        """Covariance of the odometry edge into keyframe kf_id."""
        cov = self._edge_cov.get(kf_id)
        if cov is None:
            info = self.edge_information(kf_id)
            cov = self._default_cov if info is None else np.linalg.inv(info)
            self._edge_cov[kf_id] = cov
        return cov

    def drift_d2(self, match: int, query: int, T_match_query: np.ndarray,
                 information: np.ndarray) -> float:
        """Squared Mahalanobis distance of the correction a loop implies, Log(T_odom^-1 T_loop)
        in the query's frame, under the odometry edges' covariances chained from match to
        query (each moved into the query's frame by its adjoint) plus the loop's own. All edges
        at once: one loop looks back over up to the whole run."""
        C = np.array([self._edge_covariance(k) for k in range(match + 1, query + 1)])
        P = self.store.odom_poses(match, query)
        T_q_k = relative(P[-1], P[1:])  # keyframe k in the query's frame
        T_q_k[-1] = np.eye(4)
        R, t = T_q_k[:, :3, :3], T_q_k[:, :3, 3]
        Ad = np.zeros((len(R), 6, 6))  # gtsam's adjoint, rotation first: [R 0; [t]x R  R]
        Ad[:, :3, :3] = Ad[:, 3:, 3:] = R
        Ad[:, 3:, :3] = np.cross(t[:, :, None], R, axis=1)  # [t]x R, column by column
        cov = np.linalg.inv(information) + np.einsum("kij,kjl,kml->im", Ad, C, Ad)
        err = between_error(T_match_query, np.eye(4), relative(P[0], P[-1]))
        return float(err @ np.linalg.solve(cov, err))

    def candidates(self, kf_id: int, points: np.ndarray) -> list[LoopCandidate]:
        """Scan-context candidates of keyframe kf_id (its points, float64) that the odometry
        makes plausible, best descriptor distance first."""
        return self.index.query(kf_id, points, self.path_m(kf_id), self.store.stamp_s(kf_id),
                                lambda match: self.plausible(kf_id, match)).candidates

    def _match_side(self, kf_id: int, upto: int) -> Side:
        """Verification clouds of keyframe kf_id's submap (none after `upto`), built once for
        the queries that match it in turn (a revisit matches the same few old keyframes from
        several query keyframes in a row). Built from the same points, so the same result."""
        radius = self.cfg.loop.verify.submap_radius
        key = (kf_id, min(upto, kf_id + radius))
        side = self._sides.pop(key, None)
        if side is None:
            side = match_side(self.submap(kf_id, radius, upto), self.cfg.loop.verify)
        self._sides[key] = side  # newest last
        while len(self._sides) > MATCH_SIDES_KEPT:
            self._sides.pop(next(iter(self._sides)))
        return side

    def process(self, kf_id: int) -> LoopResult:
        """Look for loops of keyframe kf_id (the newest one processed): scan-context
        candidates, verified until one is accepted; then index the keyframe."""
        kf = self.store.get(kf_id)
        edge = self.edge_information(kf_id)
        self._new_splits = []
        query_pts = kf.points.astype(np.float64)
        records: list[LoopRecord] = []
        constraint = None
        if len(query_pts) == 0:  # nothing in range: a graph node, but nothing to describe
            return LoopResult(kf_id, (), None, edge)
        candidates = self.candidates(kf.id, query_pts)
        vcfg = self.cfg.loop.verify
        query = query_side(self.submap(kf.id, vcfg.submap_radius, kf.id), vcfg) if candidates \
            else None
        for cand in candidates[: self.cfg.loop.max_verify]:
            res = verify(cand, query, self._match_side(cand.match, kf.id), vcfg)
            records.append(LoopRecord(kf.frame_index, self.store.frame_index(cand.match),
                                      kf.id, cand.match, cand.score,
                                      float(np.degrees(cand.yaw_guess_rad)), res.fitness,
                                      res.rmse_m, res.accepted, res.reason, res.T_match_query))
            if res.accepted and self._gate_d2 > 0:
                d2 = self.drift_d2(cand.match, kf.id, res.T_match_query, res.constraint.information)
                log.debug("kf %d -> %d: drift Mahalanobis^2 %.1f", kf.id, cand.match, d2)
                if d2 > self._gate_d2:
                    records[-1] = dataclasses.replace(
                        records[-1], accepted=False,
                        reason=f"drift: Mahalanobis^2 {d2:.0f} > {self._gate_d2:.1f}")
                    continue
            if res.accepted:
                constraint = res.constraint
                log.info("loop accepted: frame %d -> frame %d (fitness %.2f)", kf.frame_index,
                         records[-1].match_frame, res.fitness)
                break
        self._index(kf.id, query_pts)
        return LoopResult(kf_id, tuple(records), constraint, edge, tuple(self._new_splits))


def loops_csv_rows(records: list[LoopRecord],
                   backend: dict[tuple[int, int], str] | None = None,
                   node_to_frame: dict[int, np.ndarray] | None = None) -> list[list]:
    """loops.csv rows (header first). `accepted` means the loop passed the ICP gates; `backend`
    (accepted loops only) what the final solve made of it, keyed (match kf, query kf): inlier,
    or rejected (GNC weight 0; with Huber, residual beyond the 99 % inlier gate). The pose is
    T_match_query between the two frames at their stamps: a loop measured between graph nodes
    elsewhere (node_to_frame: keyframe -> T_node_frame) is carried to the stamps."""
    rows: list[list] = [["query_frame", "match_frame", "descriptor_distance", "yaw_guess_deg",
                         "fitness", "rmse_m", "accepted", "reason", "x", "y", "z", "qx", "qy",
                         "qz", "qw", "backend"]]
    backend = backend or {}
    for r in records:
        T = r.T_match_query
        if T is not None and node_to_frame and (r.query_kf in node_to_frame
                                                or r.match_kf in node_to_frame):
            I4 = np.eye(4)
            T = inverse(node_to_frame.get(r.match_kf, I4)) @ T @ node_to_frame.get(r.query_kf, I4)
        pose = to_xyz_quat(T) if T is not None else [np.nan] * 7
        status = backend.get((r.match_kf, r.query_kf), "") if r.accepted else ""
        rows.append([r.query_frame, r.match_frame, f"{r.distance:.4f}", f"{r.yaw_guess_deg:.1f}",
                     f"{r.fitness:.4f}", f"{r.rmse_m:.4f}", int(r.accepted), r.reason,
                     *[f"{v:.6f}" for v in pose], status])
    return rows


