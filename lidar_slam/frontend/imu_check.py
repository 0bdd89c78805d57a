"""Whether the IMU agrees with the lidar, checked while the run goes (issue 30, item 6): an IMU
that disagrees is never trusted silently.

The registered lidar motion between consecutive scans is the reference the IMU is held to:

- Units: between two scans the gyro turns through sum |w| dt (its path, IMU frame), the lidar
  through the angle of its relative rotation; the two are the same whatever the mounting. Their
  median ratio over UNIT_SCANS turning intervals (the lidar turned TURNING_DEG or more) is ~1
  for rad/s and ~57.3 for deg/s: the gyro is then converted (one warning), and any other ratio
  switches the IMU off. Before that verdict, the IMU is not initialised while the gyro reads
  far more rotation than the lidar (blocks_init): a gyro in deg/s never reaches kiss-icp.
- Mounting: the gyro's rotation vectors, put in the lidar frame by imu.T_lidar_imu, and the
  lidar's (MOUNT_SCANS turning intervals about at least two axes) are matched by the best
  rotation (gtsam's Rot3.ClosestTo of their correlation: the Kabsch solution); more than
  MAX_MOUNT_DEG from the identity means the config's mounting is not the IMU's: IMU off.
- Prediction: the front-end re-initialises the IMU whenever its prediction of a scan is more
  than 1 m or 10 deg off the registration; the MAX_DISAGREEMENTS-th time, the disagreement is
  persistent (a clock offset, a wrong mounting, another sensor's IMU) and the IMU is switched
  off. (Comparing the IMU's prediction with constant velocity's, scan by scan, was tried: on a
  car at steady speed constant velocity is as close, yet the IMU helps the final solve, 0.091
  m ATE against 0.199 m lidar-only on the bank's car00.)

- Accelerometer (after the run, before the final solve: acceleration_disagreement): the gyro
  checks above do not see an accelerometer whose sign, axes or one sample are wrong, and the
  front-end barely feels it (the registration corrects its prediction), but the final solve
  follows it (a 12 s walk: 0.015 m with the true imu.csv, 0.19 m without, 1.6 m with the
  accelerometer's sign flipped, 2.7 m with its axes turned 90 deg about z, 1.9 m with one
  sample of 1000 m/s^2). The odometry's accelerations, smoothed over ACCEL_WINDOW_S, are
  compared with the IMU's (specific force turned by the odometry's rotations, the same kernel,
  plus the gravity that fits best): their squared difference over the odometry's own variation
  about its mean is the disagreement, ~0 for an IMU that explains the lidar's motion and 1 for
  one that explains nothing (a constant would do as well). Past MAX_ACCEL_DISAGREEMENT, or
  with a fitted gravity off Earth's by MAX_GRAVITY_ERROR_MPS2 (a scale error), the IMU
  is left out of the final solve with one warning (summary.json imu.reason). On the bank's 16
  sequences, right calibration: 0.003-0.12, 0.42 on the 16-beam car whose odometry is the
  bank's noisiest; the 12 s walk's faults: 2.8 (accelerometer x2) to 214 (axes permuted). A
  motion whose accelerations vary by less than MIN_ACCEL_VARIATION_MPS2 gets no verdict. A
  glitch (one bad sample) is one window among many and barely moves the sum: the reader drops
  it first (io.imu_gnss, GLITCH_FACTOR).

Switched off, the run goes on lidar-only (the front-end's constant velocity, no IMU in the final
solve), says so in one warning line and in summary.json ("imu_check"). The verdicts rest on
ratios and angles the data gives (1 or 57.3, a mounting angle) and on a count that is zero on
every correctly calibrated sequence of the bank, not on a threshold tuned to one world.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidar_slam.geometry import Slerp, rotvec_from_matrix
from lidar_slam.imu import ImuStream, closest_rotation

log = logging.getLogger(__name__)

TURNING_DEG = 1.0  # lidar rotation between two registered scans for the gyro to be compared
UNIT_SCANS = 8  # turning intervals before the gyro's unit is decided
RATIO_TOLERANCE = 1.5  # gyro / lidar rotation within [1/x, x] (of 1, or of 57.3 for deg/s)
DEG_PER_RAD = float(np.degrees(1.0))
# Before the unit is decided: the IMU waits while the gyro's path over the last BLOCK_SCANS
# intervals exceeds BLOCK_FACTOR x the lidar's rotation + BLOCK_SLACK_DEG per interval (gyro
# noise and bias of a unit at rest: ~0.05 deg per 0.1 s for a consumer MEMS).
BLOCK_SCANS, BLOCK_FACTOR, BLOCK_SLACK_DEG = 10, 5.0, 1.0
MOUNT_SCANS = 20  # turning intervals (about two axes or more) before the mounting is checked
MOUNT_MIN_SPREAD = 0.05  # second / first singular value of the rotation vectors' correlation
MAX_MOUNT_DEG = 10.0  # best-matching rotation farther than this from the config's: IMU off
# The front-end re-initialises the IMU whenever its prediction of a scan is more than 1 m or
# 10 deg off the registration (imu_prediction.MAX_DISAGREEMENT_*). Never on the 15 sequences
# of the bank with their right calibration (docs/bank.md); 3 to 8 times on a 30 s walk with a
# wrong mounting or a 50 ms clock offset. This many times: a persistent disagreement.
MAX_DISAGREEMENTS = 3
# The accelerometer check (module doc): windows of +-ACCEL_WINDOW_S (a triangle kernel) every
# ACCEL_WINDOW_S; no verdict with fewer than MIN_ACCEL_WINDOWS or too little motion
# (MIN_ACCEL_VARIATION_MPS2). The bank's right IMUs: at most 0.088; the faults: an accelerometer
# 200 ms behind its gyro 1.17 (ATE 0.80 m against 0.19 without the IMU), flipped 4, turned
# 7-12. Leaving a right IMU out of the final solve costs little (the front-end keeps it: a
# hand-held walk about 0.02 -> 0.03 m), keeping a wrong one tens of times that: the verdict is
# at half the variation unexplained.
ACCEL_WINDOW_S = 1.0
MIN_ACCEL_WINDOWS = 5
MAX_ACCEL_DISAGREEMENT = 0.5
# The fitted gravity's magnitude must be Earth's (9.78-9.83 m/s^2 at the surface) to within
# this: beyond, the accelerometer's scale is off (x1.08: 10.6 m/s^2, ATE 0.37 m against 0.02
# m with the true scale, its disagreement only 0.03: gravity is what it scales most). The bank:
# 9.71-9.91; a consumer unit's scale error, 1-3 %, stays inside.
MAX_GRAVITY_ERROR_MPS2 = 0.4
MAX_ACCEL_GAP_S = 0.1  # IMU samples further apart inside a window: the window is not compared
# Below this RMS of the odometry's accelerations (windows of 2 s) there is nothing to compare:
# a lidar odometry's tilt drifts by a degree or so over a minute, and turns g x sin(1.2 deg)
# = 0.2 m/s^2 of gravity into its accelerations (a car at a steady 2 m/s, 60 s: the check said
# 19.6 for a right IMU before this floor). The bank's sequences and the walks vary by 0.33-1.4.
MIN_ACCEL_VARIATION_MPS2 = 0.2
CHUNK_SAMPLES = 50_000  # IMU samples turned into the world at a time


def _rotvec(R: np.ndarray) -> np.ndarray:
    return rotvec_from_matrix(R)


class ImuCheck:
    """The running checks of the module doc, fed by the IMU front-end with every registered
    scan. verdict: "pending" (units not decided yet), "ok", or "off" (then `reason`);
    gyro_scale: what the gyro was multiplied by (pi/180 after a deg/s verdict)."""

    def __init__(self, R_lidar_imu: np.ndarray):
        self.R_lidar_imu = np.asarray(R_lidar_imu, dtype=np.float64)
        self.verdict, self.reason = "pending", ""
        self.off_at: str | None = None  # the scan at which the IMU was switched off (its file)
        self.gyro_scale = 1.0
        self.mount_checked = False
        self.last: tuple[float, np.ndarray] | None = None  # (t_ref, T_Wo_L) last registered
        # per covered interval: lidar angle (deg), gyro path (deg), lidar and gyro (lidar
        # frame) rotation vectors (rad)
        self.intervals: list[tuple[float, float, np.ndarray, np.ndarray]] = []
        self.n_disagreements = 0
        self.ratio: float | None = None
        self.mount_error_deg: float | None = None

    # -- evidence --------------------------------------------------------------------------------

    def observe(self, stream: ImuStream, t_ref: float, T: np.ndarray) -> str | None:
        """A registered scan (reference instant t_ref, T_Wo_lidar): the interval from the last
        one compared with the gyro. Returns "deg" (convert the gyro), "off", or None."""
        last, self.last = self.last, (t_ref, T)
        if self.verdict == "off" or last is None or t_ref <= last[0]:
            return None
        t0, T0 = last
        if not (stream.start_s <= t0 and t_ref <= stream.end_s):
            return None  # the gyro does not cover the interval (held ends compare nothing)
        iv = stream.interval(t0, t_ref)
        if len(iv.dt_s) and iv.dt_s.max() > stream.gap_s:
            return None  # the gyro misses part of the interval: held across, it compares nothing
        w = iv.gyro_radps * self.gyro_scale
        path_deg = float(np.degrees((np.linalg.norm(w, axis=1) * iv.dt_s).sum()))
        gyro_vec = self.R_lidar_imu @ (w * iv.dt_s[:, None]).sum(axis=0)
        lidar_vec = _rotvec(T0[:3, :3].T @ T[:3, :3])
        self.intervals.append((float(np.degrees(np.linalg.norm(lidar_vec))), path_deg,
                               lidar_vec, gyro_vec))
        del self.intervals[:-max(4 * MOUNT_SCANS, BLOCK_SCANS)]
        return self._units() if self.verdict == "pending" else self._mounting()

    def disagreed(self) -> str | None:
        """The front-end re-initialised the IMU after its prediction disagreed with the
        registration (or its smoother failed). Returns "off" at the MAX_DISAGREEMENTS-th."""
        if self.verdict == "off":
            return None
        self.n_disagreements += 1
        if self.n_disagreements >= MAX_DISAGREEMENTS:
            return self._off(f"its prediction disagreed with the registration "
                             f"{self.n_disagreements} times (by more than 1 m or 10 deg: a "
                             f"clock offset, imu.T_lidar_imu, or not this sensor's IMU?)")
        return None

    def blocks_init(self) -> bool:
        """Whether the IMU must not be initialised yet: off, or, before the unit verdict, a
        gyro reading far more rotation than the lidar over the last intervals."""
        if self.verdict == "off":
            return True
        if self.verdict != "pending" or not self.intervals:
            return False
        recent = self.intervals[-BLOCK_SCANS:]
        lidar = sum(i[0] for i in recent)
        gyro = sum(i[1] for i in recent)
        return gyro > BLOCK_FACTOR * lidar + BLOCK_SLACK_DEG * len(recent)

    # -- verdicts --------------------------------------------------------------------------------

    def _units(self) -> str | None:
        turning = [(g / a) for a, g, _, _ in self.intervals if a >= TURNING_DEG]
        if len(turning) < UNIT_SCANS:
            return None
        self.ratio = float(np.median(turning))
        if 1 / RATIO_TOLERANCE <= self.ratio <= RATIO_TOLERANCE:
            self.verdict = "ok"
            return None
        if DEG_PER_RAD / RATIO_TOLERANCE <= self.ratio <= DEG_PER_RAD * RATIO_TOLERANCE:
            self.gyro_scale = float(np.radians(1.0))
            self.verdict, self.intervals = "ok", []
            return "deg"
        return self._off(f"its gyro turned {self.ratio:.3g}x as far as the lidar over "
                         f"{len(turning)} turning scans (neither rad/s nor deg/s)")

    def _mounting(self) -> str | None:
        if self.mount_checked:
            return None
        pairs = [(lv, gv) for a, _, lv, gv in self.intervals if a >= TURNING_DEG]
        if len(pairs) < MOUNT_SCANS:
            return None
        lidar = np.array([p[0] for p in pairs])
        gyro = np.array([p[1] for p in pairs])
        H = lidar.T @ gyro  # lidar ~ R gyro: R = argmax tr(R^T H)
        spread = np.linalg.svd(lidar.T @ lidar, compute_uv=False)
        if spread[1] < MOUNT_MIN_SPREAD * spread[0]:
            return None  # turning about one axis only: a rotation about it is not seen
        self.mount_checked = True
        axis_angle = rotvec_from_matrix(closest_rotation(H))
        self.mount_error_deg = float(np.degrees(np.linalg.norm(axis_angle)))
        if self.mount_error_deg > MAX_MOUNT_DEG:
            axis = axis_angle / np.linalg.norm(axis_angle)
            return self._off(f"its rotations match the lidar's only turned by "
                             f"{self.mount_error_deg:.0f} deg about "
                             f"({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}) in the lidar frame "
                             f"(imu.T_lidar_imu is not the IMU's mounting?)")
        return None

    def _off(self, why: str) -> str:
        self.verdict, self.reason = "off", why
        return "off"

    def summary(self) -> dict:
        """What summary.json says of the check ("imu_check")."""
        return {"verdict": self.verdict, **({"reason": self.reason} if self.reason else {}),
                **({"off_at": self.off_at} if self.off_at else {}),
                "gyro_scale": self.gyro_scale,
                "gyro_to_lidar_rotation_ratio": (None if self.ratio is None
                                                 else round(self.ratio, 4)),
                "mounting_error_deg": (None if self.mount_error_deg is None
                                       else round(self.mount_error_deg, 2)),
                "disagreements": self.n_disagreements}

    # -- checkpoint ------------------------------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        iv = self.intervals
        return {"check_scalars": np.array([
                    ("pending", "ok", "off").index(self.verdict), self.gyro_scale,
                    float(self.mount_checked), self.n_disagreements,
                    np.nan if self.ratio is None else self.ratio,
                    np.nan if self.mount_error_deg is None else self.mount_error_deg,
                    np.nan if self.last is None else self.last[0]]),
                "check_last_T": np.eye(4) if self.last is None else self.last[1],
                "check_angles": np.array([i[:2] for i in iv]).reshape(-1, 2),
                "check_vectors": np.array([np.r_[i[2], i[3]] for i in iv]).reshape(-1, 6),
                "check_reason": np.array(self.reason),
                "check_off_at": np.array(self.off_at or "")}

    def restore(self, a: dict[str, np.ndarray]) -> None:
        verdict, scale, checked, n, ratio, mount, t_last = a["check_scalars"]
        self.verdict = ("pending", "ok", "off")[int(verdict)]
        self.gyro_scale, self.mount_checked = float(scale), bool(checked)
        self.n_disagreements = int(n)
        self.ratio = None if np.isnan(ratio) else float(ratio)
        self.mount_error_deg = None if np.isnan(mount) else float(mount)
        self.last = None if np.isnan(t_last) else (float(t_last), np.array(a["check_last_T"]))
        self.intervals = [(float(g[0]), float(g[1]), np.array(v[:3]), np.array(v[3:]))
                          for g, v in zip(a["check_angles"], a["check_vectors"])]
        self.reason = str(a["check_reason"])
        self.off_at = str(a["check_off_at"]) or None


@dataclass(frozen=True)
class AccelerationCheck:
    """acceleration_disagreement's answer: the disagreement, the windows compared, and the
    RMS of the odometry's accelerations about their mean (m/s^2)."""

    disagreement: float
    windows: int
    variation_mps2: float
    gravity_mps2: float = float("nan")  # the fitted gravity's magnitude


def acceleration_disagreement(stream: ImuStream, stamps_s: np.ndarray, T_world_lidar: np.ndarray,
                              T_lidar_imu: np.ndarray) -> AccelerationCheck | None:
    """How far the IMU's accelerations are from the odometry's (module doc, "Accelerometer"):
    the odometry's T_world_lidar at stamps_s (every frame), the IMU's samples turned by the
    odometry's rotation (slerp between frames) and T_lidar_imu. The odometry's acceleration at
    c is the second difference of the IMU's position at c - h, c, c + h (h = ACCEL_WINDOW_S),
    which is the true one averaged with the triangle kernel (h - |s|) / h^2 over c +- h; the
    IMU's is its specific force in the world averaged with the same kernel, plus gravity: the
    best fit of a constant and a slow drift (linear in time: the odometry's own tilt drifts, and
    turns gravity into it). Windows every h from the first to the last instant both cover, the
    last one ending there; one the IMU does not cover to within MAX_ACCEL_GAP_S is left out.
    The disagreement: the sum of squared differences over the sum of squared deviations of the
    odometry's accelerations from their mean. None with fewer than MIN_ACCEL_WINDOWS windows or
    a motion whose accelerations vary by less than MIN_ACCEL_VARIATION_MPS2 (RMS): too little
    to tell an accelerometer from the odometry's tilt."""
    t = np.asarray(stamps_s, dtype=float)
    keep = np.concatenate(([True], np.diff(t) > 0))
    t, T = t[keep], np.asarray(T_world_lidar, dtype=float)[keep]
    h = ACCEL_WINDOW_S
    lo, hi = max(t[0], stream.start_s) + h, min(t[-1], stream.end_s) - h
    if len(t) < 3 or hi < lo:
        return None
    centres = np.arange(lo, hi + 1e-9, h)
    if hi - centres[-1] > 1e-6:
        centres = np.append(centres, hi)  # the run's last stretch is compared too
    p = T[:, :3, :3] @ T_lidar_imu[:3, 3] + T[:, :3, 3]  # the IMU's position at each frame

    def at(x: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(x, t, p[:, i]) for i in range(3)], axis=-1)

    a_odom = (at(centres + h) - 2.0 * at(centres) + at(centres - h)) / h ** 2
    i0, i1 = np.searchsorted(stream.t, [lo - h, hi + h])
    ts = stream.t[max(i0 - 1, 0):i1 + 1]
    f = np.asarray(stream.samples.accel_mps2[max(i0 - 1, 0):i1 + 1], dtype=float)
    slerp = Slerp(t, T[:, :3, :3])  # the odometry's rotation between frames
    f_imu_in_lidar = f @ T_lidar_imu[:3, :3].T
    f_world = np.empty_like(f)
    for a in range(0, len(ts), CHUNK_SAMPLES):  # an hour at 200 Hz: 52 MB of matrices at once
        b = a + CHUNK_SAMPLES
        f_world[a:b] = slerp.apply(np.clip(ts[a:b], t[0], t[-1]), f_imu_in_lidar[a:b])
    a_imu, used = [], []
    for k, c in enumerate(centres):
        j0, j1 = np.searchsorted(ts, [c - h, c + h])
        knots = np.concatenate(([c - h], ts[j0:j1], [c + h]))
        if j1 - j0 < 2 or np.diff(knots).max() > MAX_ACCEL_GAP_S:
            continue  # not covered to within MAX_ACCEL_GAP_S
        # each sample stands for half the steps on either side (the window's ends included)
        dt = 0.5 * (knots[2:] - knots[:-2])
        w = (h - np.abs(ts[j0:j1] - c)) * dt
        a_imu.append(w @ f_world[j0:j1] / w.sum())
        used.append(k)
    if len(used) < MIN_ACCEL_WINDOWS:
        return None
    a_odom = a_odom[used]
    deviation = float(((a_odom - a_odom.mean(axis=0)) ** 2).sum())
    variation = float(np.sqrt(deviation / len(used)))
    if variation < MIN_ACCEL_VARIATION_MPS2:
        return None
    diff = a_odom - np.array(a_imu)
    tc = centres[used] - centres[used].mean()
    A = np.c_[np.ones(len(used)), tc / max(float(np.abs(tc).max()), 1e-9)]
    fit, *_ = np.linalg.lstsq(A, diff, rcond=None)  # gravity and its drift, per axis
    misfit = float(((diff - A @ fit) ** 2).sum())
    return AccelerationCheck(misfit / deviation, len(used), variation,
                             float(np.linalg.norm(fit[0])))


def trusted_input(inertial, frontend):
    """The run's IMU / GNSS input (io.inertial_input.InertialInput) as the check left it, for
    the final solve and summary.json: without the IMU when it was switched off ("used": false
    and why), with the converted gyro when it was read as deg/s."""
    if frontend is None or inertial is None or inertial.imu is None:
        return inertial
    import dataclasses

    check = frontend.check
    imu = dict(inertial.summary["imu"])
    if check.verdict == "off":
        imu.update(used=False, reason=f"switched off at {check.off_at} by the IMU check: "
                                      f"{check.reason}")
        return dataclasses.replace(inertial, imu=None, summary={**inertial.summary, "imu": imu})
    if check.gyro_scale != 1.0:
        imu["gyro_scale"] = check.gyro_scale
        return dataclasses.replace(inertial, imu=frontend.samples,
                                   summary={**inertial.summary, "imu": imu})
    return inertial
