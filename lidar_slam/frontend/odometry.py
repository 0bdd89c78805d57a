"""Scan-to-map ICP odometry: the only module that imports kiss_icp.

This is kiss-icp's `KissICP.register_frame` step for step, on kiss-icp's own C++ components, with
two differences: the scan arrives (when it has per-point times) already deskewed by our front-end,
so kiss-icp's preprocessor runs with its deskew off (range crop only) and deskewing happens
exactly once;
and the components are built from our config without kiss-icp's pydantic-settings layer, whose
import alone costs ~50 ms of every run. tests/test_odometry.py checks the poses equal stock
KissICP's on real scans (to POSE_QUANTUM). On top of it, each step that kiss-icp does not take
is its own switch (config.py, OdometryConfig): a coarse pass before kiss-icp's alignment from
the constant-velocity guess, the slow-scan refinement after it, kiss-icp's iterations capped
from the IMU's prediction, the failure watch's local-map reset, the pose's rounding.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from kiss_icp.pybind import kiss_icp_pybind as kp

from lidar_slam.config import SlamConfig
from lidar_slam.frontend.crop import range_mask
from lidar_slam.frontend.deskew import DeskewedScan
from lidar_slam.frontend.failure import FailureWatch
from lidar_slam.geometry import (
    interpolate,
    matrix_from_rotvec,
    rotation_angle_deg,
    rotvec_from_matrix,
    transform_points,
)
from lidar_slam.registration import PlaneTarget, orthonormal, voxel_centroids

# kiss-icp's pose is rounded to this right after its alignment (rotation matrix entries, and
# metres): 1 micrometre / microradian, 100 times below the step at which kiss-icp's ICP stops
# (odometry.convergence_criterion). With more than one thread kiss-icp sums its normal equations
# in a varying order and its poses differ by up to ~2e-15 between runs (a hand-held walk, 450
# scans x 4 alignments each); a run's chaos carried that to 1.9 cm. Rounded, everything after
# the alignment sees the same pose: two runs (and runs on 1 or 2 threads) agree unless one of a
# pose's 12 numbers falls within ~2e-15 of a rounding boundary, about 12 x 4e-9 = 5e-8 per
# scan (docs/design.md, Determinism).
POSE_QUANTUM = 1e-6


def quantised(T: np.ndarray, q: float | None = None) -> np.ndarray:
    """T (4x4) rounded to q (default POSE_QUANTUM): the rotation's entries, then the nearest
    rotation to them (registration.orthonormal: SVD, deterministic for the same input), and the
    translation's metres."""
    q = POSE_QUANTUM if q is None else q
    out = np.eye(4)
    out[:3] = np.round(np.asarray(T[:3]) / q) * q
    return orthonormal(out)


def _vec(points: np.ndarray):
    return kp._Vector3dVector(points)


REFINE_ITERATIONS = 20  # at most, point-to-plane, per slow scan's refinement
_INDEX_BITS = 22  # up to 4M points per scan
_INDEX_MASK = np.uint64((1 << _INDEX_BITS) - 1)


class VoxelSelector:
    """One point per voxel within a range, chosen by kiss-icp's C++ voxel downsample (the first
    point of each voxel, as kiss-icp keeps), returned as indices into the input.

    kiss-icp returns points, not indices, so each point's index rides in the lowest 22 mantissa
    bits of its x coordinate while it is selected (a change of under 1e-9 of |x|: 0.1 um at
    100 m); the caller keeps using the untouched points. Several times faster than NumPy. The
    tags are written straight into kiss-icp's own copy of the points (its vector's buffer, which
    NumPy views without a copy), so the scan is copied once, by the C++ conversion it needs.
    """

    def __init__(self) -> None:
        self._ids = np.zeros(0, dtype=np.uint64)  # 0, 1, 2, ...: the tags, grown as needed

    def __call__(self, points: np.ndarray, voxel_m: float, min_range_m: float,
                 max_range_m: float) -> np.ndarray:
        """Indices (int64) of the selected points of points (N,3)."""
        n = len(points)
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        if n > int(_INDEX_MASK) + 1:
            raise ValueError(f"{n} points: at most {int(_INDEX_MASK) + 1} per scan")
        if len(self._ids) < n:
            self._ids = np.arange(n, dtype=np.uint64)
        vec = _vec(points)
        x = np.asarray(vec)[:, 0].view(np.uint64)  # a view into the vector: tagged in place
        x &= ~_INDEX_MASK
        x |= self._ids[:n]
        chosen = np.asarray(kp._voxel_down_sample(vec, voxel_m))
        if len(chosen) == 0:
            return np.zeros(0, dtype=np.int64)
        # The range crop after the selection, on one point per voxel instead of every point: a
        # voxel cut by the range sphere may lose the point that the crop-first order kept. (On
        # the indices: cheaper than gathering the points' rows first.)
        idx = (chosen[:, 0].view(np.uint64) & _INDEX_MASK).view(np.int64)
        return idx[range_mask(chosen, min_range_m, max_range_m)]


@dataclass(frozen=True)
class OdometryResult:
    """One scan's odometry. T_world_scan: the pose at the scan's stamp; T_world_ref: at the
    instant the scan was registered (the middle of its sweep when deskewed); T_ref_stamp links
    the two. registered: False for a scan with too few points in range (data.min_points; its pose
is the prediction).
    T_world_first: set once, on the second registered scan: frame 0's pose moved to its stamp,
    which needs the first motion estimate."""

    T_world_scan: np.ndarray
    T_world_ref: np.ndarray
    T_ref_stamp: np.ndarray
    registered: bool
    T_world_first: np.ndarray | None = None


@dataclass(frozen=True)
class PlaneEvidence:
    """Held-out points' point-to-plane residuals against the refinement's target at kiss-icp's
    pose and at another (refined, or one Gauss-Newton step fitted on them: the early check).
    gain_m: mean per-point decrease of the truncated residual (m, > 0: the other pose fits
    better); stderr_m: its standard error over the points; n: points matched at both poses."""

    gain_m: float
    stderr_m: float
    n: int

    def proven(self, z: float) -> bool:
        """Whether the gain exceeds z standard errors (a one-sided paired test)."""
        return self.n >= 6 and self.gain_m > z * self.stderr_m


def _plane_residuals(target: PlaneTarget, points: np.ndarray, T: np.ndarray, max_m: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per point (N, 3) placed by T: n.(p - q) to its nearest target point q (m, signed),
    whether q is within max_m, the placed point and q's normal."""
    moved = transform_points(T, points)
    idx, sq = target.tree.batch_nearest_neighbor_search(moved, num_threads=1)
    idx = np.asarray(idx, np.int64)
    ok = (idx >= 0) & (np.asarray(sq) <= max_m**2)
    idx = np.where(ok, idx, 0)
    normal = target.cloud.normals()[idx, :3]
    r = np.einsum("ij,ij->i", normal, moved - target.cloud.points()[idx, :3])
    return r, ok, moved, normal


def _gauss_newton_step(r: np.ndarray, moved: np.ndarray, normal: np.ndarray,
                       weights: np.ndarray, T: np.ndarray) -> np.ndarray:
    """T moved by one point-to-plane Gauss-Newton step fitted on the signed residuals r of the
    placed points (world frame; the rotation about T's origin, for conditioning)."""
    J = np.hstack([np.cross(moved - T[:3, 3], normal), normal]) * weights[:, None]
    H = J.T @ J
    if np.linalg.cond(H) > 1e12:
        return T
    xi = -np.linalg.solve(H, J.T @ (r * weights))
    out = T.copy()
    out[:3, :3] = matrix_from_rotvec(xi[:3]) @ T[:3, :3]
    out[:3, 3] += xi[3:]
    return out


def plane_evidence(target: PlaneTarget, held: np.ndarray, T_kiss: np.ndarray,
                   T_other: np.ndarray | None, max_m: float,
                   at_kiss: tuple[np.ndarray, ...] | None = None) -> PlaneEvidence:
    """Whether T_other fits held-out points (N, 3) better than T_kiss against target. None:
    one Gauss-Newton step fitted on the held-out points (optimistic: the early check). The
    residual is truncated at 3 robust sigmas of kiss-icp's (1.4826 MAD of the matched ones),
    so that a few points off a wall's edge cannot decide. at_kiss: _plane_residuals of the
    same points at T_kiss, when already known (the early check's, reused after the ICP)."""
    if at_kiss is None:
        at_kiss = _plane_residuals(target, held, T_kiss, max_m)
    signed, ok0, moved, normal = at_kiss
    r0 = np.abs(signed)
    if ok0.sum() < 6:
        return PlaneEvidence(0.0, 0.0, int(ok0.sum()))
    tau = max(3 * 1.4826 * float(np.median(r0[ok0])), 1e-6)
    if T_other is None:
        inlier = (ok0 & (r0 < tau)).astype(np.float64)
        T_other = _gauss_newton_step(signed, moved, normal, inlier, T_kiss)
    r1, ok1, _, _ = _plane_residuals(target, held, T_other, max_m)
    both = ok0 & ok1
    n = int(both.sum())
    if n < 6:
        return PlaneEvidence(0.0, 0.0, n)
    d = np.minimum(r0[both], tau) - np.minimum(np.abs(r1[both]), tau)
    return PlaneEvidence(float(d.mean()), float(d.std(ddof=1) / math.sqrt(n)), n)


class Odometry:
    """kiss-icp scan-to-map registration; poses are T_world_scan with world = first scan."""

    def __init__(self, cfg: SlamConfig, imu: bool = False, lidar_only: bool | None = None):
        o = cfg.odometry
        self.cfg = cfg
        # lidar_only (default: without an IMU): the lidar-only coarse pass (_coarse, when
        # odometry.coarse_every is set) and the wider target of a scan refined at speed
        # (odometry.refine_keyframes_at_speed); False for an IMU run's calibration pass
        lidar_only = not imu if lidar_only is None else lidar_only
        self.coarse = lidar_only and o.coarse_every is not None
        # The second start (_second_start) on every scan a run starts from constant velocity:
        # a lidar-only run's, and an IMU run's that its IMU does not predict (before it is
        # initialised, across a gap, when it is found unusable: an IMU too short to use leaves
        # the lidar-only poses); not the T_lidar_imu calibration pass's.
        self.second_start = (lidar_only or imu) and o.second_start_deg is not None
        # scans that also started from the last pose (_second_start), and of them those kept
        self.n_second_tried = self.n_second_taken = 0
        # imu: the run's IMU predicts the scans (odometry.refine_evidence "with_imu": the
        # evidence is asked on every scan the IMU predicted, not after the IMU check's "off")
        self.imu = imu
        self.voxel_size_m = cfg.voxel_size_m()
        self.max_range_m = cfg.data.max_range_m
        self._map = kp._VoxelHashMap(voxel_size=self.voxel_size_m, max_distance=self.max_range_m,
                                     max_points_per_voxel=o.max_points_per_voxel)
        self._registration = kp._Registration(max_num_iterations=o.max_num_iterations,
                                              convergence_criterion=o.convergence_criterion,
                                              max_num_threads=o.max_num_threads)
        # from the IMU's prediction (odometry.imu_max_num_iterations): fewer iterations
        self._from_imu = self._registration if o.imu_max_num_iterations is None else \
            kp._Registration(max_num_iterations=min(o.imu_max_num_iterations,
                                                    o.max_num_iterations),
                             convergence_criterion=o.convergence_criterion,
                             max_num_threads=o.max_num_threads)
        self._new_threshold()
        # kiss-icp's range crop with its deskew switched off: ours runs before. Its thread count
        # is the registration's: kiss-icp's Registration and Preprocessor each set TBB's
        # process-wide limit once, from the first one a process makes (a static global_control),
        # and TBB takes the smaller: a one-thread crop kept the registration on one core.
        self._crop = kp._Preprocessor(cfg.data.max_range_m, cfg.data.min_range_m, False,
                                      o.max_num_threads)
        self.last_pose = np.eye(4)
        self.last_delta = np.eye(4)  # T_prev_curr, the constant-velocity prediction
        self.n_registered = 0
        self.n_coarse = 0  # registrations that started from a coarse pass (_coarse)
        self.last_n_points = 0  # points the last scan had after crop and selection
        self._last_ref_s = 0.0  # reference instant (from the stamp) of the last registered scan
        self._first_ref_s = 0.0
        # Model deviations fed to the adaptive threshold since the last take_deviations(): its
        # state is not exposed by kiss-icp, so a checkpoint appends them to a file and a resumed
        # run replays them all to rebuild it exactly.
        self._deviations: list[np.ndarray] = []
        # The refinement's targets: the last keyframes' clouds (odometry world frame), made into
        # a target when a scan to refine needs it. A scan refined at speed (lidar only) matches
        # the last refine_keyframes_at_speed (at least refine_keyframes); slow scans, the
        # failure watch and a reset's map the last refine_keyframes (_recent).
        self.n_anchors = o.refine_keyframes
        if (lidar_only and o.refine_below_mps > 0 and o.refine_fast_after_s is not None
                and o.refine_keyframes_at_speed):
            self.n_anchors = max(o.refine_keyframes, o.refine_keyframes_at_speed)
        self._anchors: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.n_anchors)
        # the targets made so far from the anchors: {False: of _recent(), True: of all of them}
        self._targets: dict[bool, PlaneTarget] = {}
        self.n_refined = 0
        self._fast_s = 0.0  # registered time at or above refine_below_mps, in a row (s)
        self.n_refined_at_speed = 0  # of n_refined: for their lasting speed
        # Of those scans' corrections (the refinement's pose in kiss-icp's pose's frame): their
        # count, the sums of the rotation vectors and of their squares per axis (rad, rad^2),
        # and of the scans' motion (m): how far kiss-icp's rotation strays from the keyframes,
        # scan by scan, how much of it is one way, over what distance
        # (backend.refinement_floor)
        self.speed_corrections = 0
        self.speed_correction_sum = np.zeros(3)
        self.speed_correction_sq = np.zeros(3)
        self.speed_correction_m = 0.0
        self.n_refine_refused = 0  # by the correction gate (refine_max_correction_*)
        self.n_refine_unproven = 0  # by the held-out points' evidence, after the ICP
        self.n_refine_skipped = 0  # by the held-out points' evidence, before the ICP
        self.last_evidence: PlaneEvidence | None = None  # of the last refinement looked at
        self.n_refine_refused = 0
        self.failures = FailureWatch(o.failure_sigma_m, o.failure_min_fitness,
                                     o.failure_wide_min_fitness, o.failure_inlier_m,
                                     o.failure_scans, cfg.keyframes.cloud_voxel_m)
        self._scan_index = 0  # of the scan in hand (for the failure report)

    def add_anchor(self, T_world_kf: np.ndarray, points_kf: np.ndarray) -> None:
        """A new keyframe for the refinement target: its odometry pose and its cloud (N, 3) in
        its own frame; it replaces the oldest (placed only when a scan to refine needs them)."""
        self._anchors.append((T_world_kf, points_kf))
        self._targets = {}

    def anchors(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every kept anchor (T_world_kf, points_kf), oldest first (a checkpoint keeps them:
        they are not always the keyframe store's clouds, Pipeline._add_keyframe)."""
        return list(self._anchors)

    def _recent(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The last odometry.refine_keyframes anchors (oldest first)."""
        k = self.cfg.odometry.refine_keyframes
        return list(self._anchors)[-k:]

    def _refine(self, frame_down, T_world_points: np.ndarray, evidence: bool, predicted: bool,
                at_speed: bool = False) -> np.ndarray:
        """T_world_points refined against the last keyframes, or kept: by the correction gate,
        or (odometry.refine_evidence) when the scan's held-out points do not prove it better.
        predicted: kiss-icp started from the IMU's prediction (then the matches reach
        odometry.refine_imu_correspondence_m, not refine_max_correspondence_m). at_speed: a
        scan refined for its lasting speed (odometry.refine_fast_after_s), counted apart too,
        against the last n_anchors keyframes (odometry.refine_keyframes_at_speed) where a slow
        scan's target is the last refine_keyframes."""
        o = self.cfg.odometry
        corr = (o.refine_imu_correspondence_m if predicted and self.imu
                else o.refine_max_correspondence_m)
        wide = at_speed and self.n_anchors > o.refine_keyframes
        target = self._targets.get(wide)
        if target is None:
            points = np.concatenate([transform_points(T, np.asarray(p, np.float64))
                                     for T, p in (self._anchors if wide else self._recent())])
            target = self._targets[wide] = PlaneTarget(
                points, self.cfg.keyframes.cloud_voxel_m, REFINE_ITERATIONS,
                o.refine_max_correspondence_m)
        points = np.asarray(frame_down)
        step = max(1, math.ceil(len(points) / o.refine_max_points))
        held = None
        if evidence:
            # The evidence needs points the refinement does not see: every other one of a
            # small scan's goes to the source, and the held-out set is offset half a stride.
            step = max(2, step)
            held = points[step // 2::step]
        source = points[::step]  # every k-th: kiss-icp's order is its hash map's, scattered
        if o.refine_voxel_m is not None:
            source = voxel_centroids(source if held is not None else points, o.refine_voxel_m)
        self.last_evidence = None
        if len(source) < 3 or len(target) < 3:
            return T_world_points
        at_kiss = None  # the held-out points' residuals at kiss-icp's pose, for both checks
        if held is not None:
            # Early: if even a Gauss-Newton step fitted on the held-out points themselves does
            # not improve them significantly, a fit on the other points will not: skip the ICP.
            at_kiss = _plane_residuals(target, held, T_world_points, corr)
            hope = plane_evidence(target, held, T_world_points, None, corr, at_kiss)
            if not hope.proven(o.refine_evidence_z):
                self.last_evidence = hope
                self.n_refine_skipped += 1
                return T_world_points
        T = target.align(source, T_world_points, corr)
        correction = np.linalg.inv(T_world_points) @ T
        if (np.linalg.norm(correction[:3, 3]) > o.refine_max_correction_m
                or rotation_angle_deg(correction) > o.refine_max_correction_deg):
            self.n_refine_refused += 1
            return T_world_points
        if held is not None:
            self.last_evidence = plane_evidence(target, held, T_world_points, T, corr,
                                                at_kiss)
            if not self.last_evidence.proven(o.refine_evidence_z):
                self.n_refine_unproven += 1
                return T_world_points
        self.n_refined += 1
        if at_speed:
            self.n_refined_at_speed += 1
            rv = rotvec_from_matrix(correction[:3, :3])
            self.speed_corrections += 1
            self.speed_correction_sum += rv
            self.speed_correction_sq += rv * rv
            self.speed_correction_m += float(np.linalg.norm(
                (np.linalg.inv(self.last_pose) @ T)[:3, 3]))
        return T

    def _new_threshold(self) -> None:
        o = self.cfg.odometry
        self._threshold = kp._AdaptiveThreshold(initial_threshold=o.initial_threshold_m,
                                                min_motion_th=o.min_motion_m,
                                                max_range=self.max_range_m)

    def register(self, points: np.ndarray, selected: bool = False, refine: bool = False,
                 initial_guess: np.ndarray | None = None, at_speed: bool = False,
                 capped: bool = True) -> np.ndarray | None:
        """kiss-icp's registration of points (N,3) in the sensor frame: T_world_points, or None
        (and no state change) when fewer than data.min_points are left after the range crop and
        the half-voxel selection (last_n_points says how many). selected: the points are already
        cropped and one per voxel of half the voxel size (see DeskewedScan). refine: refine the
        pose against the last keyframes' clouds (when there are any). initial_guess: where ICP
        starts (the IMU's prediction), else kiss-icp's constant-velocity one. at_speed: refined
        for a lasting speed (_at_speed): kept only when the scan's held-out points prove it
        better, and counted apart. capped: with an initial_guess, kiss-icp stops at
        odometry.imu_max_num_iterations (False: a guess that is not the IMU's full prediction,
        such as the extrinsic calibration's gyro-only one)."""
        if selected:
            frame_down = _vec(points)
        else:
            cropped = self._crop._preprocess(_vec(points), np.zeros(0), np.eye(4))
            frame_down = kp._voxel_down_sample(cropped, self.voxel_size_m * 0.5)
        self.last_n_points = len(frame_down)
        if len(frame_down) < max(1, self.cfg.data.min_points):
            return None  # too few to register: no state change, the caller predicts
        source = kp._voxel_down_sample(frame_down, self.voxel_size_m * 1.5)
        sigma = self._threshold._compute_threshold()
        kernel = self.failures.kernel(sigma, self.cfg.odometry.initial_threshold_m)
        predicted = initial_guess is not None  # by the IMU
        if initial_guess is None:
            initial_guess = self.last_pose @ self.last_delta
        registration = self._from_imu if predicted and capped else self._registration
        start = initial_guess if predicted else self._coarse(source, initial_guess, kernel)
        second = not predicted and self._second_start()
        if second and start is not initial_guess:  # both starts through the coarse pass
            start = self._fitter(frame_down, start,
                                 self._coarse(source, self.last_pose, kernel, count=False))
        new_pose = self._align(registration, source, start, kernel)
        if second and start is initial_guess:  # no coarse pass (a small source): both in full
            new_pose = self._fitter(frame_down, new_pose,
                                    self._align(registration, source, self.last_pose, kernel))
        new_pose = quantised(new_pose, self.cfg.odometry.pose_quantum_m)
        if refine and self._anchors:
            mode = self.cfg.odometry.refine_evidence
            evidence = at_speed or mode is True or (mode == "with_imu" and self.imu and predicted)
            new_pose = self._refine(frame_down, new_pose, evidence, predicted, at_speed)
        deviation = np.linalg.inv(initial_guess) @ new_pose
        self._threshold._update_model_deviation(model_deviation=deviation)
        self._deviations.append(deviation)
        if self.failures.failed(self._scan_index, sigma, np.asarray(frame_down), new_pose,
                                self._recent()):
            self._reset_local_map()
        self._map._update(frame_down, new_pose)
        self.last_delta = np.linalg.inv(self.last_pose) @ new_pose
        self.last_pose = new_pose
        return new_pose

    def _second_start(self) -> bool:
        """Whether kiss-icp, starting from the constant-velocity guess (not the IMU's), also
        starts from the last pose (no motion): the last motion turned more than
        odometry.second_start_deg and there are keyframes to judge the two by."""
        return (self.second_start and bool(self._anchors) and rotation_angle_deg(
            self.last_delta) > self.cfg.odometry.second_start_deg)

    def _fitter(self, frame_down, T_cv: np.ndarray, T_still: np.ndarray) -> np.ndarray:
        """Of two poses of the scan, from the constant-velocity start and from the last pose,
        the one whose points lie more often within odometry.failure_inlier_m of the last
        keyframes' clouds (the failure watch's fitness); the constant-velocity one on a tie."""
        self.n_second_tried += 1
        points = np.asarray(frame_down)
        if (self.failures.fitness(points, T_still, self._recent())
                > self.failures.fitness(points, T_cv, self._recent())):
            self.n_second_taken += 1
            return T_still
        return T_cv

    def _coarse(self, source, guess: np.ndarray, kernel: float, count: bool = True
                ) -> np.ndarray:
        """Lidar only: where kiss-icp starts aligning source from the constant-velocity guess:
        that guess improved by aligning every odometry.coarse_every-th point of source first
        (kiss-icp's order is its hash map's, scattered), or the guess itself (off, no map yet,
        or fewer than data.min_points in the subsample). A run with an IMU never takes it
        (self.coarse), not even on the scans its IMU does not predict, nor does its
        T_lidar_imu: auto calibration: their poses stay those the bank measured."""
        if not self.coarse or self._map._empty():
            return guess
        coarse = np.asarray(source)[::self.cfg.odometry.coarse_every]
        if len(coarse) < max(1, self.cfg.data.min_points):
            return guess
        self.n_coarse += count  # (a second start's pass is counted as one: n_second_tried)
        return self._align(self._registration, _vec(coarse), guess, kernel)

    def _align(self, registration, points, guess: np.ndarray, kernel: float) -> np.ndarray:
        """kiss-icp's alignment of points (its vector) to its map from guess, its kernel and a
        correspondence distance of 3 kernels (as kiss-icp's register_frame)."""
        return registration._align_points_to_map(
            points=points, voxel_map=self._map, initial_guess=guess,
            max_correspondance_distance=3 * kernel, kernel=kernel)

    def step(self, scan: DeskewedScan, initial_guess: np.ndarray | None = None,
             capped: bool = True) -> OdometryResult:
        """Register a deskewed scan and return its pose at the stamp. initial_guess: the IMU's
        prediction of the pose at the scan's reference instant (else constant velocity);
        capped: as register's."""
        self._scan_index = scan.scan.index
        slow = self.is_slow(scan.period_s)
        at_speed = not slow and self._at_speed()
        T_world_ref = self.register(scan.points, scan.selected, slow or at_speed, initial_guess,
                                    at_speed=at_speed, capped=capped)
        fast = T_world_ref is not None and not self.is_slow(scan.period_s)  # its new motion
        self._fast_s = self._fast_s + scan.period_s if fast else 0.0
        if T_world_ref is None:
            # The prediction is of the sweep's middle, like every registration: move it to the
            # stamp with the last registered scan's offset.
            T_world_ref = self.predict(initial_guess)
            T_ref_stamp = interpolate(np.eye(4), self.last_delta,
                                      -self._last_ref_s / scan.period_s)
            return OdometryResult(T_world_ref @ T_ref_stamp, T_world_ref, T_ref_stamp, False)
        T_ref_stamp = scan.T_ref_stamp(self.last_delta)
        first = None
        self.n_registered += 1
        if self.n_registered == 1:
            self._first_ref_s = scan.ref_s
        elif self.n_registered == 2 and self._first_ref_s:
            # Frame 0 was registered before any velocity was known, so its pose is of its
            # sweep's middle (the world origin). With the first motion now estimated, move it to
            # its stamp like every other frame.
            first = interpolate(np.eye(4), self.last_delta, -self._first_ref_s / scan.period_s)
        self._last_ref_s = scan.ref_s
        return OdometryResult(T_world_ref @ T_ref_stamp, T_world_ref, T_ref_stamp, True, first)

    def _reset_local_map(self) -> None:
        """After a failure: kiss-icp's map down to the last keyframes' clouds (the scan in hand
        is added next) and its threshold from its initial value (a NaN deviation marks the
        restart for a resumed run's replay)."""
        self._map._clear()
        for T_world_kf, points_kf in self._recent():
            self._map._update(_vec(np.asarray(points_kf, np.float64)), T_world_kf)
        self._new_threshold()
        self._deviations.append(np.full((4, 4), np.nan))

    def is_slow(self, period_s: float) -> bool:
        """Whether the last motion is slower than odometry.refine_below_mps (0: never)."""
        limit = self.cfg.odometry.refine_below_mps
        return limit > 0 and float(np.linalg.norm(self.last_delta[:3, 3])) < limit * period_s

    def _at_speed(self) -> bool:
        """Lidar only: whether the registered motion has stayed at or above
        odometry.refine_below_mps for odometry.refine_fast_after_s (a vehicle at speed, not a
        hand-held flick kiss-icp mistook for a jump)."""
        o = self.cfg.odometry
        return (not self.imu and o.refine_below_mps > 0 and o.refine_fast_after_s is not None
                and self._fast_s >= o.refine_fast_after_s - 1e-9)

    def predict(self, guess: np.ndarray | None = None) -> np.ndarray:
        """Constant-velocity prediction of the next pose (or guess, the IMU's); advances the
        state without a scan."""
        if guess is not None:
            self.last_delta = np.linalg.inv(self.last_pose) @ guess
        self.last_pose = self.last_pose @ self.last_delta
        return self.last_pose

    # -- checkpoint / resume -------------------------------------------------------------------

    def take_deviations(self) -> np.ndarray:
        """(K,4,4) model deviations since the last call (for the checkpoint's append-only log)."""
        out = np.stack(self._deviations) if self._deviations else np.zeros((0, 4, 4))
        self._deviations = []
        return out

    def state(self) -> dict[str, np.ndarray]:
        """Poses, counters and the local map's points (the deviations go by take_deviations)."""
        return {"last_pose": self.last_pose, "last_delta": self.last_delta,
                "map_points": np.asarray(self._map._point_cloud()),
                "counters": np.array([self.n_registered, self._last_ref_s, self._first_ref_s,
                                      self.n_refined, self.n_refine_refused,
                                      self.n_refine_unproven, self.n_refine_skipped,
                                      self._fast_s, self.n_refined_at_speed, self.n_coarse,
                                      self.n_second_tried, self.n_second_taken,
                                      *self.speed_correction_sum, *self.speed_correction_sq,
                                      self.speed_corrections, self.speed_correction_m]),
                **self.failures.state()}

    def restore(self, state: dict[str, np.ndarray], deviations: np.ndarray) -> None:
        """Continue from state(): the map's points go back into their voxels, the adaptive
        threshold replays every model deviation of the run so far."""
        self.last_pose = np.array(state["last_pose"])
        self.last_delta = np.array(state["last_delta"])
        self._map._clear()
        if len(state["map_points"]):
            self._map._add_points(_vec(np.asarray(state["map_points"], np.float64)))
        self._new_threshold()
        for dev in deviations:
            if np.isnan(dev).any():  # a failure's restart (_reset_local_map)
                self._new_threshold()
            else:
                self._threshold._update_model_deviation(model_deviation=dev)
        self.failures.restore(state)
        self._deviations = []
        n, last_ref, first_ref, *refined = state["counters"]  # (refined: since 2026-12)
        self.n_registered = int(n)
        # older: fewer (the corrections' sums since 2026-12-07 with their own count: a checkpoint
        # without it starts them again)
        corrections_kept = len(refined) >= 17
        refined = list(refined) + [0] * (17 - len(refined))
        (self.n_refined, self.n_refine_refused, self.n_refine_unproven,
         self.n_refine_skipped) = (int(v) for v in refined[:4])
        self._fast_s, self.n_refined_at_speed = float(refined[4]), int(refined[5])
        self.n_coarse = int(refined[6])
        self.n_second_tried, self.n_second_taken = int(refined[7]), int(refined[8])
        if not corrections_kept:
            refined[9:17] = [0] * 8
        self.speed_correction_sum = np.array(refined[9:12], dtype=float)
        self.speed_correction_sq = np.array(refined[12:15], dtype=float)
        self.speed_corrections, self.speed_correction_m = int(refined[15]), float(refined[16])
        self._last_ref_s, self._first_ref_s = float(last_ref), float(first_ref)
