"""The IMU in the front-end (issue 22, item 2): every used point deskewed along the integrated
IMU, and kiss-icp started from the IMU's prediction.

Frames: kiss-icp's world W_o (the first scan's lidar frame at its reference instant) stays the
odometry's world, so every stage downstream is unchanged. The IMU states live in a gravity-
aligned world G (z up, lidar_slam.imu). The two are tied only through relative motion: the
smoother sees the registered poses as relative-pose factors between consecutive states, so the
IMU's attitude w.r.t. gravity is the IMU's own estimate (refined with every scan), never a
rotation between W_o and G fixed from the first, possibly poorly registered, scans; and the
prediction handed back is the registered pose of the last state moved by the IMU's relative
motion. The IMU sits at T_lidar_imu (config imu.T_lidar_imu; its default is the identity).

Per scan, once initialised: the IMU state (gtsam NavState and bias) at the last registered
scan's reference instant is propagated with gtsam's preintegration through the new sweep,
predicting the pose at every IMU sample time and at the new reference instant (the middle of
the sweep, lidar_slam.frontend.deskew); each point is moved along those poses (interpolated
between samples: rotation and translation) into the frame at the reference instant, and the
predicted pose there is kiss-icp's initial guess. After registration a small smoother updates
attitude, velocity and bias, as LIO-SAM's imuPreintegration: gtsam ISAM2 over the states of the
last scans (CombinedImuFactor between consecutive ones, the registered motion between them as
BetweenFactorPose3), started afresh every RESET_EVERY states from the newest state with fixed
priors (RESET_SIGMA_*), which bounds its cost. gtsam's IncrementalFixedLagSmoother, and
LIO-SAM's reset from the marginal covariances, both stopped on an "indeterminate linear system"
with the config's BMI088 noise (Cholesky; the marginals of a 3-state chain already fail). The
pose handed on stays kiss-icp's registration; its pose at the stamp follows the IMU's motion
plus the share of the registration's correction accrued by then (see _at_stamp).

Initialisation: the first INIT_SECONDS (at least INIT_MIN_SCANS registered scans) run lidar-only
(constant velocity). A first attitude w.r.t. gravity then follows from the lidar velocities at
both ends of that window and the preintegrated specific force between them (v_b - v_a = g (t_b -
t_a) + R_a dV, right whether the sensor rests or moves, as good as the lidar velocities), and a
first batch (every scan of the window a state, that attitude a loose prior) starts the
smoother. A scan whose sweep the IMU does not cover (a gap, or past its end) falls back to
constant velocity; so does every scan after an IMU prediction that disagrees with the
registration by more than MAX_DISAGREEMENT_M / _DEG, or a smoother failure: both count, and the
IMU is initialised again (bias and attitude kept) from the next INIT_SECONDS of lidar-only
scans.

Every registered scan also feeds the IMU check (lidar_slam.frontend.imu_check): a gyro in deg/s
is converted, and a mounting that does not match the lidar's rotations, or a third disagreement,
switches the IMU off for the rest of the run (one warning; lidar-only from there). A prediction
that is not a rigid transform (a diverged state) is never handed to kiss-icp, whose Sophus
aborts the process on it.

gtsam's PreintegratedCombinedMeasurements.deskewPointsAtTimes is not used: it rotates points
into the frame at the START of the preintegration along an interpolated rotation and translates
them by velocity * t only (no gravity, no acceleration), whereas the points here go to the
middle of the sweep along the full prediction.
"""

from __future__ import annotations

import dataclasses
import logging

import gtsam
import numpy as np

from lidar_slam.config import ImuConfig
from lidar_slam.frontend.deskew import DeskewedScan, Deskewer, SweepMotion
from lidar_slam.frontend.imu_check import ImuCheck
from lidar_slam.frontend.odometry import OdometryResult, quantised
from lidar_slam.geometry import interpolate, inverse, make_pose
from lidar_slam.imu import GRAVITY_MPS2, ImuStream, combined_params, gravity_rotation
from lidar_slam.io.imu_gnss import GAP_PERIODS, ImuSamples
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

INIT_SECONDS = 0.5  # lidar-only at the start, and after a fallback, before the IMU takes over
INIT_MIN_SCANS = 4
GRAVITY_TOLERANCE_MPS2 = 1.0  # | |g estimated| - 9.81 | above this: not initialised yet
MAX_DISAGREEMENT_M, MAX_DISAGREEMENT_DEG = 1.0, 10.0  # prediction vs registration
RESET_EVERY = 20  # states in the smoother before it restarts from the newest one
# The priors on that state (1-sigma): attitude (rad; the gauge, and what the IMU learnt of its
# tilt), position (m), velocity (m/s), accelerometer (m/s^2) and gyro (rad/s) bias.
RESET_SIGMA_RAD, RESET_SIGMA_M, RESET_SIGMA_MPS = 0.01, 0.01, 0.1
RESET_SIGMA_ACCEL, RESET_SIGMA_GYRO = 0.02, 0.001
# The registered motion between consecutive scans (1-sigma): rotation (rad), position (m).
BETWEEN_SIGMA_RAD, BETWEEN_SIGMA_M = 0.005, 0.02
# The first state's pose (the gauge, 1-sigma): rotation (rad: its attitude w.r.t. gravity is a
# first guess, the IMU refines it), position (m).
FIRST_SIGMA_RAD, FIRST_SIGMA_M = 0.1, 0.01
INIT_VELOCITY_SIGMA_MPS = 1.0  # on the first state's velocity (its value: lidar differences)
# The bias prior at (re)initialisation (1-sigma): gyro (rad/s), accelerometer (m/s^2).
BIAS_SIGMA_GYRO, BIAS_SIGMA_ACCEL = 0.01, 0.2


def _sigmas(first: float, second: float):
    """A diagonal noise model with 3 x first then 3 x second as sigmas."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.r_[[first] * 3, [second] * 3])


# gtsam's noise models are immutable: made once, not per scan.
_BETWEEN_NOISE = _sigmas(BETWEEN_SIGMA_RAD, BETWEEN_SIGMA_M)


def _angle_deg(T: np.ndarray) -> float:
    """The rotation angle of T (deg) by gtsam's log: per scan, ~10x faster than
    geometry.rotation_angle_deg (its eigenvector route), the same to 1e-14 deg."""
    return float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(T[:3, :3])))))


def _towards(T: np.ndarray, f: float) -> np.ndarray:
    """geometry.interpolate(I, T, f) by gtsam's exp and log: per scan, ~10x faster, the same
    to 2e-16."""
    R = gtsam.Rot3.Expmap(f * gtsam.Rot3.Logmap(gtsam.Rot3(T[:3, :3]))).matrix()
    return make_pose(R, f * T[:3, 3])


def _is_rigid(T: np.ndarray, tol: float = 1e-11) -> bool:
    """Whether T is a finite 4x4 rigid transform: |R R^T - I| (Frobenius) under tol, 10x
    stricter than Sophus's check (1e-10), which aborts the process in kiss-icp."""
    if not np.isfinite(T).all():
        return False
    R = T[:3, :3]
    return bool(np.linalg.norm(R @ R.T - np.eye(3)) < tol and np.linalg.det(R) > 0)


def _isam_params() -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.1)
    # QR, not Cholesky: with the BMI088's small noise the combined IMU factors make the system
    # stiff enough for Cholesky to call it indeterminate (sim 00-s200-x: a smoother failure and
    # a re-initialisation at scan 19; with QR none, at the same speed).
    params.setFactorization("QR")
    return params


def _X(k: int) -> int:  # noqa: N802 (gtsam's key names)
    return gtsam.symbol("x", k)


def _V(k: int) -> int:  # noqa: N802
    return gtsam.symbol("v", k)


def _B(k: int) -> int:  # noqa: N802
    return gtsam.symbol("b", k)


class ImuFrontend:
    """IMU deskew and prediction for the odometry; see the module doc."""

    def __init__(self, samples: ImuSamples, cfg: ImuConfig):
        self.samples = samples  # as used: the gyro converted when the check found deg/s
        self.stream = ImuStream(samples)
        self.params = combined_params(cfg)
        self.T_lidar_imu = cfg.T_lidar_imu_matrix()
        self.T_imu_lidar = inverse(self.T_lidar_imu)
        self.check = ImuCheck(self.T_lidar_imu[:3, :3])
        self._replaying = False  # restore() replays _learn: the check must not gate it
        self.max_step_s = GAP_PERIODS * float(np.median(np.diff(self.stream.t)))
        self.R_G_Wo: np.ndarray | None = None  # first guess of W_o's attitude w.r.t. gravity
        self.T_Wo_L = np.eye(4)  # registered pose of the last state (kiss-icp's world)
        self.bias = gtsam.imuBias.ConstantBias()
        self.nav: gtsam.NavState | None = None  # IMU state (in G) at t_last; None: lidar-only
        self.t_last = 0.0  # absolute reference instant of the last registered scan
        self._pending: list[tuple[float, np.ndarray]] = []  # (t_ref, T_Wo_lidar) to init from
        self._smoother: gtsam.ISAM2 | None = None
        self._n_states = 0  # states in the smoother
        self._k = 0  # key of the newest state
        self._guess: np.ndarray | None = None  # IMU prediction of the scan in hand
        self._to_t_ref = None  # (t_last, t_ref, bias, its preintegration): _propagate's
        self.n_imu = 0  # scans deskewed / predicted by the IMU
        self.n_constant_velocity = 0  # scans on constant velocity (initialising, fallbacks)
        self.n_gaps = 0  # fallbacks: the IMU does not cover the sweep
        self.n_diverged = 0  # fallbacks: prediction and registration disagree, or gtsam failed
        self.n_inits = 0
        self.first_imu_s: float | None = None
        # Per IMU-predicted scan: how far the prediction was from the registration (m, deg).
        self.prediction_error: list[tuple[float, float]] = []
        self._base: dict | None = None  # the state before the smoother was made (checkpoint)
        self._journal: list[tuple[float, np.ndarray, np.ndarray | None]] = []  # _learn since
        identity = np.array_equal(self.T_lidar_imu, np.eye(4))
        log.info("IMU front-end: %d samples %s, T_lidar_imu %s", len(samples), samples.source,
                 "identity (imu.T_lidar_imu, the config's default)" if identity
                 else np.round(self.T_lidar_imu[:3], 4).tolist())

    # -- per scan ------------------------------------------------------------------------------

    def prepare(self, scan: Scan, deskewer: Deskewer, T_prev_curr: np.ndarray
                ) -> tuple[DeskewedScan, np.ndarray | None]:
        """The scan deskewed along the IMU's motion and the predicted T_Wo_lidar at its
        reference instant (kiss-icp's initial guess); at constant velocity T_prev_curr and
        None while the IMU is not initialised or does not cover the sweep."""
        self._guess = None
        if self.nav is None:
            self.n_constant_velocity += 1
            return deskewer(scan, T_prev_curr), None
        deskewing = deskewer.will_deskew(scan)
        t_ref = scan.stamp_s + (deskewer.reference_s(scan) if deskewing else 0.0)
        first_s, last_s = deskewer.sweep_s(scan) if deskewing else (0.0, 0.0)
        t_end = scan.stamp_s + last_s if deskewing else t_ref
        t_start = scan.stamp_s + first_s if deskewing else t_ref
        if t_start < self.t_last or not self._covers(self.t_last, max(t_ref, t_end)):
            self.n_gaps += 1
            self.n_constant_velocity += 1
            log.warning("%s: the IMU does not cover the sweep (%.3f..%.3f s): constant velocity, "
                        "IMU initialised again", scan.source, t_start, t_end)
            self._restart()
            return deskewer(scan, T_prev_curr), None
        times, T_G_L, T_G_L_last = self._propagate(t_ref, max(t_ref, t_end),
                                                    min(scan.stamp_s, t_start))
        i_ref = int(np.searchsorted(times, t_ref))
        T_ref_G = inverse(T_G_L[i_ref])
        motion = None
        if deskewing and len(times) >= 2:
            motion = SweepMotion(times - t_ref, T_ref_G @ T_G_L)
        self._guess = self.T_Wo_L @ inverse(T_G_L_last) @ T_G_L[i_ref]
        if not _is_rigid(self._guess):
            # A diverged state (e.g. thousands of metres away, where float64 rounding leaves the
            # rotation unorthogonal): kiss-icp's Sophus would abort the process on it.
            self.n_diverged += 1
            self.n_constant_velocity += 1
            log.warning("%s: IMU prediction is not a rigid transform (diverged): constant "
                        "velocity, IMU initialised again", scan.source)
            self._guess = None
            self._restart()
            self._disagreed(scan.source)
            return deskewer(scan, T_prev_curr), None
        self.n_imu += 1
        return deskewer(scan, T_prev_curr, motion), self._guess

    def update(self, deskewed: DeskewedScan, odom: OdometryResult) -> OdometryResult:
        """Feed the registered pose of the scan prepare() returned to the smoother (or to the
        initialisation); returns odom with its pose at the stamp along the corrected motion."""
        guess, self._guess = self._guess, None
        if not odom.registered:
            return odom  # its pose is the prediction: nothing learnt, the state stays
        t_ref = deskewed.scan.stamp_s + deskewed.ref_s
        if guess is not None and deskewed.motion is not None:
            odom = self._at_stamp(deskewed, odom, guess)
        if self._check(t_ref, odom.T_world_ref, deskewed.scan.source):
            return odom  # the IMU is off: lidar-only from here
        before = self._light_state()
        smoother = self._smoother
        self._learn(t_ref, odom.T_world_ref, guess, deskewed.scan.source)
        # The smoother cannot be saved: a checkpoint keeps the state before the call that made
        # it and every call since, and restore() replays them (lidar_slam.run.checkpoint).
        if self._smoother is None:
            self._base, self._journal = None, []
        elif self._smoother is not smoother:
            self._base, self._journal = before, [(t_ref, odom.T_world_ref, guess)]
        else:
            self._journal.append((t_ref, odom.T_world_ref, guess))
        return odom

    def _check(self, t_ref: float, T: np.ndarray, source: str) -> bool:
        """Feed the IMU check (lidar_slam.frontend.imu_check) with a registered scan and act on
        its verdict: the gyro converted from deg/s, or the IMU switched off for the rest of the
        run (one warning each). Whether the IMU is off."""
        was_off = self.check.verdict == "off"
        action = self.check.observe(self.stream, t_ref, T)
        if action == "deg":
            log.warning("%s: the IMU's gyro turned %.1fx as far as the lidar: read as deg/s and "
                        "converted to rad/s (IMU initialised again)", self.samples.source,
                        self.check.ratio)
            self._rescale_gyro(self.check.gyro_scale)
        elif action == "off":
            self._switch_off(source)
        return was_off or action == "off"

    def _disagreed(self, source: str) -> None:
        """After a re-initialisation for a disagreement: the IMU check counts it (not when a
        resumed run replays the smoother's calls: the counts are restored)."""
        if not self._replaying and self.check.disagreed() == "off":
            self._switch_off(source)

    def _switch_off(self, source: str) -> None:
        self.check.off_at = source
        log.warning("%s: IMU not used from %s on: %s; the run goes on lidar-only (summary.json "
                    "imu_check)", self.samples.source, source, self.check.reason)
        self._restart()

    def _rescale_gyro(self, factor: float) -> None:
        """The gyro multiplied by factor from here on (and in the final solve: self.samples);
        the state learnt from the unscaled one dropped."""
        s = self.samples
        self.samples = dataclasses.replace(s, gyro_radps=s.gyro_radps * factor)
        self.stream = ImuStream(self.samples)
        self._restart()
        self.R_G_Wo, self.bias = None, gtsam.imuBias.ConstantBias()

    def _learn(self, t_ref: float, T: np.ndarray, guess: np.ndarray | None,
               source: str = "") -> None:
        """The registered pose T (kiss-icp's world) at t_ref into the smoother, or into the
        initialisation while there is none; guess: what the IMU predicted there."""
        if self.nav is None:
            self._pending.append((t_ref, T))
            self._initialise()
            return
        d = inverse(guess) @ T
        self.prediction_error.append((float(np.linalg.norm(d[:3, 3])), _angle_deg(d)))
        if (self.prediction_error[-1][0] > MAX_DISAGREEMENT_M
                or self.prediction_error[-1][1] > MAX_DISAGREEMENT_DEG):
            self.n_diverged += 1
            log.warning("%s: IMU prediction %.2f m / %.1f deg off the registration: IMU "
                        "initialised again", source, *self.prediction_error[-1])
            self._restart()
            self._pending.append((t_ref, T))
            self._disagreed(source)
            return
        k = self._k + 1
        pim = self._preintegrated(t_ref)
        pred = pim.predict(self.nav, self.bias)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(_X(k - 1), _X(k), self._imu_motion(self.T_Wo_L, T),
                                           _BETWEEN_NOISE))
        graph.add(gtsam.CombinedImuFactor(_X(k - 1), _V(k - 1), _X(k), _V(k), _B(k - 1), _B(k),
                                          pim))
        values = gtsam.Values()
        values.insert(_X(k), pred.pose())
        values.insert(_V(k), pred.velocity())
        values.insert(_B(k), self.bias)
        try:
            self._update(graph, values, k)
        except RuntimeError as exc:
            self.n_diverged += 1
            log.warning("%s: IMU smoother failed (%s): IMU initialised again", source,
                        (str(exc).strip().splitlines() or [type(exc).__name__])[0])
            self._restart()
            self._pending.append((t_ref, T))
            self._disagreed(source)
            return
        self._k, self.t_last, self.T_Wo_L = k, t_ref, T
        self._read_state(k)

    def _at_stamp(self, deskewed: DeskewedScan, odom: OdometryResult, guess: np.ndarray
                  ) -> OdometryResult:
        """odom with the pose at the stamp moved along the IMU's motion plus the share of the
        registration's correction to the prediction that accrues by the stamp (linear in time
        from the last registered scan, zero there): as constant-velocity odometry moves the
        stamp with the registered motion, so a registration error along the motion moves the
        stamp with it, half as much, instead of all of it."""
        t_stamp, t_ref = deskewed.scan.stamp_s, deskewed.scan.stamp_s + deskewed.ref_s
        f = (t_stamp - self.t_last) / (t_ref - self.t_last) if t_ref > self.t_last else 1.0
        correction = inverse(guess) @ odom.T_world_ref
        # Rounded as kiss-icp's pose is (to odometry.POSE_QUANTUM, 1e-6): the IMU's smoother,
        # rebuilt by replay on resume, predicts within ~1e-14 of the run never stopped, and the
        # final solve would carry that to half a millimetre; rounded, both write the same bytes.
        T_world_stamp = quantised(guess @ deskewed.motion.T_ref_at(-deskewed.ref_s)
                                  @ _towards(correction, f))
        T_ref_stamp = inverse(odom.T_world_ref) @ T_world_stamp
        return dataclasses.replace(odom, T_world_scan=T_world_stamp, T_ref_stamp=T_ref_stamp)

    # -- state -----------------------------------------------------------------------------------

    def summary(self) -> dict:
        """What the IMU front-end did, for summary.json."""
        err = np.array(self.prediction_error).reshape(-1, 2)
        return {"scans_deskewed_by_imu": self.n_imu,
                "scans_constant_velocity": self.n_constant_velocity,
                "fallbacks_imu_gap": self.n_gaps, "fallbacks_diverged": self.n_diverged,
                "initialisations": self.n_inits,
                "first_imu_scan_s": self.first_imu_s,
                # how far kiss-icp moved the IMU's prediction: median and max, m and deg
                "prediction_error_m": (None if not len(err) else
                                       [round(float(np.median(err[:, 0])), 4),
                                        round(float(err[:, 0].max()), 4)]),
                "prediction_error_deg": (None if not len(err) else
                                         [round(float(np.median(err[:, 1])), 3),
                                          round(float(err[:, 1].max()), 3)]),
                "gyro_bias_radps": np.round(self.bias.gyroscope(), 6).tolist(),
                "accel_bias_mps2": np.round(self.bias.accelerometer(), 5).tolist()}

    def up_in_lidar(self) -> np.ndarray | None:
        """Unit vector against gravity in the lidar frame of the last registered scan (at its
        reference instant), from the IMU's attitude; None while the IMU is not initialised."""
        if self.nav is None:
            return None
        R_G_L = self.nav.pose().rotation().matrix() @ self.T_imu_lidar[:3, :3]
        return R_G_L[2].copy()  # R_G_L^T @ (0, 0, 1)

    def _restart(self) -> None:
        """Back to lidar-only until initialised again (bias and the attitude reached kept)."""
        if self.nav is not None:
            self.R_G_Wo = (self.nav.pose().matrix() @ self.T_imu_lidar
                           @ inverse(self.T_Wo_L))[:3, :3]
        self.nav, self._smoother, self._pending = None, None, []
        self._base, self._journal = None, []

    def _covers(self, t0_s: float, t1_s: float) -> bool:
        """Whether the IMU samples span [t0_s, t1_s] with no gap (GAP_PERIODS periods)."""
        s = self.stream
        if t0_s < s.start_s - self.max_step_s or t1_s > s.end_s + self.max_step_s:
            return False  # (within a step past the ends, the end sample is held)
        return float(np.diff(s.knots(t0_s, t1_s)).max()) <= self.max_step_s

    def _imu_motion(self, T_Wo_La: np.ndarray, T_Wo_Lb: np.ndarray) -> gtsam.Pose3:
        """The IMU's motion between two registered lidar poses."""
        return gtsam.Pose3(self.T_imu_lidar @ inverse(T_Wo_La) @ T_Wo_Lb @ self.T_lidar_imu)

    def _propagate(self, t_ref: float, t_end: float, t_from: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Knot times (absolute, increasing; t_ref among them) from t_last to t_end, from the
        last but one at or before t_from on (what the sweep motion is asked about: the points'
        times and the stamp; at least two knots), the predicted T_G_lidar (K, 4, 4) at each, and
        T_G_lidar at t_last. Keeps the preintegration from t_last to t_ref for _learn."""
        nav, bias = self.nav, self.bias
        times, steps = [self.t_last], []
        for to_ref, (a, b) in ((True, (self.t_last, t_ref)), (False, (t_ref, t_end))):
            if b <= a:
                continue
            iv = self.stream.interval(a, b)
            dts = iv.dt_s.tolist()
            t = a
            for dt in dts:
                t += dt
                times.append(t)
            times[-1] = b  # exactly, not the sum of the steps
            steps += zip([to_ref] * len(dts), dts, iv.gyro_radps, iv.accel_mps2)
        first = max(0, min(int(np.searchsorted(times, t_from, side="right")) - 2,
                           len(times) - 2))
        # gtsam's prediction (and its 4x4) only at the knots asked about: the others only
        # integrate. The same steps to t_ref into a second one: _learn's IMU factor.
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
        to_t_ref = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
        T_G_I_last = nav.pose().matrix()
        poses = [T_G_I_last] if first == 0 else []
        for k, (to_ref, dt, w, f) in enumerate(steps, start=1):
            pim.integrateMeasurement(f, w, dt)
            if to_ref:
                to_t_ref.integrateMeasurement(f, w, dt)
            if k >= first:
                poses.append(pim.predict(nav, bias).pose().matrix())
        self._to_t_ref = (self.t_last, t_ref, bias, to_t_ref)
        return (np.asarray(times[first:]), np.asarray(poses) @ self.T_imu_lidar,
                T_G_I_last @ self.T_imu_lidar)

    def _preintegrated(self, t_ref: float) -> gtsam.PreintegratedCombinedMeasurements:
        """The IMU from t_last to t_ref about the current bias: kept by _propagate for the scan
        in hand (the same steps), else integrated (a replay, lidar_slam.run.checkpoint)."""
        kept, self._to_t_ref = self._to_t_ref, None
        if kept is not None and kept[:2] == (self.t_last, t_ref) and kept[2] is self.bias:
            return kept[3]
        return self.stream.preintegrate(self.t_last, t_ref, self.params, self.bias)

    def _update(self, graph, values, k: int, n_new: int = 1, fresh: bool = False) -> None:
        """Add factors and the n_new states up to state k to the smoother: to a new one when
        fresh (the initialisation), else restarted from the state before them when it holds
        RESET_EVERY states (or was not rebuilt: a resumed run's replay starts so)."""
        if fresh or self._smoother is None or self._n_states >= RESET_EVERY:
            self._smoother, self._n_states = gtsam.ISAM2(_isam_params()), 0
            if not fresh:  # the last state before these (its estimate) with priors
                j = k - n_new
                x, v, b = self.nav.pose(), self.nav.velocity(), self.bias
                graph.add(gtsam.PriorFactorPose3(_X(j), x, _sigmas(RESET_SIGMA_RAD,
                                                                   RESET_SIGMA_M)))
                graph.add(gtsam.PriorFactorVector(_V(j), v, gtsam.noiseModel.Isotropic.Sigma(
                    3, RESET_SIGMA_MPS)))
                graph.add(gtsam.PriorFactorConstantBias(_B(j), b, _sigmas(RESET_SIGMA_ACCEL,
                                                                          RESET_SIGMA_GYRO)))
                values.insert(_X(j), x)
                values.insert(_V(j), v)
                values.insert(_B(j), b)
        self._smoother.update(graph, values)
        self._n_states += n_new

    def _read_state(self, k: int) -> None:
        s = self._smoother
        self.nav = gtsam.NavState(s.calculateEstimatePose3(_X(k)),
                                  s.calculateEstimateVector(_V(k)))
        self.bias = s.calculateEstimateConstantBias(_B(k))

    # -- checkpoint -------------------------------------------------------------------------------

    def _light_state(self) -> dict:
        """What _learn computes from, besides the smoother (no copies of the counters and the
        prediction errors, which restore() takes as saved)."""
        return {"R_G_Wo": self.R_G_Wo, "T_Wo_L": self.T_Wo_L, "bias": self.bias,
                "nav": self.nav, "t_last": self.t_last, "k": self._k,
                "n_states": self._n_states, "pending": list(self._pending)}

    def _set_light(self, light: dict) -> None:
        self.R_G_Wo, self.T_Wo_L, self.bias = light["R_G_Wo"], light["T_Wo_L"], light["bias"]
        self.nav, self.t_last, self._k = light["nav"], light["t_last"], light["k"]
        self._n_states, self._pending = light["n_states"], list(light["pending"])

    @staticmethod
    def _pack(light: dict, prefix: str) -> dict[str, np.ndarray]:
        nav, bias = light["nav"], light["bias"]
        pend = light["pending"]
        return {
            f"{prefix}R_G_Wo": np.zeros((0, 3)) if light["R_G_Wo"] is None else light["R_G_Wo"],
            f"{prefix}T_Wo_L": np.asarray(light["T_Wo_L"]),
            f"{prefix}bias": np.r_[bias.accelerometer(), bias.gyroscope()],
            f"{prefix}nav_pose": np.zeros((0, 4)) if nav is None else nav.pose().matrix(),
            f"{prefix}nav_velocity": np.zeros(0) if nav is None else nav.velocity(),
            f"{prefix}scalars": np.array([light["t_last"], light["k"], light["n_states"]]),
            f"{prefix}pending_t": np.array([p[0] for p in pend], dtype=np.float64),
            f"{prefix}pending_T": np.array([p[1] for p in pend]).reshape(-1, 4, 4)}

    @staticmethod
    def _unpack(a: dict[str, np.ndarray], prefix: str) -> dict:
        R, pose, vel = a[f"{prefix}R_G_Wo"], a[f"{prefix}nav_pose"], a[f"{prefix}nav_velocity"]
        t_last, k, n_states = a[f"{prefix}scalars"]
        bias = a[f"{prefix}bias"]
        return {"R_G_Wo": None if R.size == 0 else np.array(R),
                "T_Wo_L": np.array(a[f"{prefix}T_Wo_L"]),
                "bias": gtsam.imuBias.ConstantBias(bias[:3], bias[3:]),
                "nav": None if pose.size == 0 else gtsam.NavState(gtsam.Pose3(pose), vel),
                "t_last": float(t_last), "k": int(k), "n_states": int(n_states),
                "pending": [(float(t), np.array(T)) for t, T in
                            zip(a[f"{prefix}pending_t"], a[f"{prefix}pending_T"])]}

    def state(self) -> dict[str, np.ndarray]:
        """Everything to continue exactly (lidar_slam.run.checkpoint): the state now, counters
        and prediction errors, and for the smoother the state before the call that made it and
        the registered poses fed to it since (restore() replays them)."""
        out = self._pack(self._light_state(), "now_")
        if self._base is not None:
            out.update(self._pack(self._base, "base_"))
        j = self._journal
        out["journal_t"] = np.array([e[0] for e in j], dtype=np.float64)
        out["journal_T"] = np.array([e[1] for e in j]).reshape(-1, 4, 4)
        out["journal_guess"] = np.array([np.full((4, 4), np.nan) if e[2] is None else e[2]
                                         for e in j]).reshape(-1, 4, 4)
        out["counters"] = np.array([self.n_imu, self.n_constant_velocity, self.n_gaps,
                                    self.n_diverged, self.n_inits,
                                    np.nan if self.first_imu_s is None else self.first_imu_s])
        out["prediction_error"] = np.array(self.prediction_error).reshape(-1, 2)
        out.update(self.check.state())
        return out

    def restore(self, a: dict[str, np.ndarray]) -> None:
        """Continue from state(): the smoother is rebuilt by replaying its calls."""
        now = self._unpack(a, "now_")
        if "check_scalars" in a:
            self.check.restore(a)
            if self.check.gyro_scale != 1.0:
                self._rescale_gyro(self.check.gyro_scale)
        self._smoother, self._base, self._journal = None, None, []
        if "base_scalars" in a:
            self._base = self._unpack(a, "base_")
            self._set_light(self._base)
            guesses = [None if np.isnan(G).any() else np.array(G) for G in a["journal_guess"]]
            self._journal = [(float(t), np.array(T), g) for t, T, g in
                             zip(a["journal_t"], a["journal_T"], guesses)]
            self._replaying = True
            try:
                for t, T, g in self._journal:
                    self._learn(t, T, g, "(replayed)")
            finally:
                self._replaying = False
        self._set_light(now)
        n_imu, n_cv, n_gaps, n_div, n_inits, first = a["counters"]
        self.n_imu, self.n_constant_velocity, self.n_gaps = int(n_imu), int(n_cv), int(n_gaps)
        self.n_diverged, self.n_inits = int(n_div), int(n_inits)
        self.first_imu_s = None if np.isnan(first) else float(first)
        self.prediction_error = [(float(m), float(d)) for m, d in a["prediction_error"]]

    # -- initialisation --------------------------------------------------------------------------

    def _initialise(self) -> None:
        """Start the IMU from the lidar-only scans in _pending once they span INIT_SECONDS."""
        pend = self._pending
        if not self._replaying and self.check.blocks_init():
            del pend[:-2 * INIT_MIN_SCANS]  # (bounded while the IMU waits)
            return
        for i in range(len(pend) - 1, 0, -1):  # only scans the IMU covers in one piece
            if not self._covers(pend[i - 1][0], pend[i][0]):
                del pend[:i]
                break
        if len(pend) < INIT_MIN_SCANS or pend[-1][0] - pend[0][0] < INIT_SECONDS:
            return
        t = np.array([p[0] for p in pend])
        T_Wo_I = np.array([p[1] for p in pend]) @ self.T_lidar_imu
        if self.R_G_Wo is None:
            self.R_G_Wo = self._gravity(t, T_Wo_I)
            if self.R_G_Wo is None:
                del pend[0]
                return
        T_G_Wo = np.eye(4)
        T_G_Wo[:3, :3] = self.R_G_Wo
        T_G_I = T_G_Wo @ T_Wo_I
        vel = np.gradient(T_G_I[:, :3, 3], t, axis=0)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k0 = self._k + 1
        for i in range(len(t)):
            k = k0 + i
            values.insert(_X(k), gtsam.Pose3(T_G_I[i]))
            values.insert(_V(k), vel[i])
            values.insert(_B(k), self.bias)
            if i:
                pim = self.stream.preintegrate(t[i - 1], t[i], self.params, self.bias)
                graph.add(gtsam.CombinedImuFactor(_X(k - 1), _V(k - 1), _X(k), _V(k), _B(k - 1),
                                                  _B(k), pim))
                graph.add(gtsam.BetweenFactorPose3(_X(k - 1), _X(k),
                                                   self._imu_motion(pend[i - 1][1], pend[i][1]),
                                                   _BETWEEN_NOISE))
        graph.add(gtsam.PriorFactorPose3(_X(k0), gtsam.Pose3(T_G_I[0]), gtsam.noiseModel.Diagonal
                                         .Sigmas(np.r_[[FIRST_SIGMA_RAD] * 3,
                                                       [FIRST_SIGMA_M] * 3])))
        graph.add(gtsam.PriorFactorVector(_V(k0), vel[0], gtsam.noiseModel.Isotropic.Sigma(
            3, INIT_VELOCITY_SIGMA_MPS)))
        graph.add(gtsam.PriorFactorConstantBias(_B(k0), self.bias, gtsam.noiseModel.Diagonal
                                                .Sigmas(np.r_[[BIAS_SIGMA_ACCEL] * 3,
                                                              [BIAS_SIGMA_GYRO] * 3])))
        # The window solved as a batch first (Levenberg-Marquardt), then handed to the smoother;
        # either may find the system indeterminate (garbage IMU data): tried again, not raised.
        try:
            values = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
            self._update(graph, values, k0 + len(t) - 1, len(t), fresh=True)
        except RuntimeError as exc:
            log.warning("IMU initialisation failed (%s); trying again", exc)
            self._restart()
            return
        self._k, self.t_last, self.T_Wo_L = k0 + len(t) - 1, float(t[-1]), pend[-1][1]
        self._read_state(self._k)
        self._pending = []
        self.n_inits += 1
        if self.first_imu_s is None:
            self.first_imu_s = float(t[-1])
        log.info("IMU front-end initialised at %.3f s (velocity %s m/s)", t[-1],
                 np.round(self.nav.velocity(), 3).tolist())

    def _gravity(self, t: np.ndarray, T_Wo_I: np.ndarray) -> np.ndarray | None:
        """R_G_Wo from the window's lidar velocities at both ends and the preintegrated specific
        force between them (see the module doc), or None if the estimate is not ~9.81 m/s^2."""
        p = T_Wo_I[:, :3, 3]
        ta, tb = 0.5 * (t[0] + t[1]), 0.5 * (t[-2] + t[-1])
        va = (p[1] - p[0]) / (t[1] - t[0])
        vb = (p[-1] - p[-2]) / (t[-1] - t[-2])
        R_a = interpolate(T_Wo_I[0], T_Wo_I[1], 0.5)[:3, :3]
        pim = self.stream.preintegrate(ta, tb, self.params)
        g = (vb - va - R_a @ pim.deltaVij()) / (tb - ta)
        if abs(float(np.linalg.norm(g)) - GRAVITY_MPS2) > GRAVITY_TOLERANCE_MPS2:
            log.info("IMU initialisation: gravity estimate %.2f m/s^2, waiting",
                     np.linalg.norm(g))
            return None
        return gravity_rotation(-g)
