"""The IMU's clock offset and mounting rotation found from the data (issue 30, item 5), for an
IMU whose config and input do not give them.

A short lidar-only odometry over the first scans (kiss-icp, as the front-end runs it) gives the
lidar's rotation over each interval between two registered scans (lidar frame); the gyro,
integrated over the same interval shifted by a candidate offset, gives the IMU's (IMU frame):

1. Coarse offset: 0 when the IMU stamps overlap the scans', else the difference of the two
   streams' first stamps (an IMU on its sensor's clock, 1.6e9 s or 1,622 s from the clouds').
2. Fine offset: the candidate (every OFFSET_STEP_S within SEARCH_S of the coarse one) at which
   the magnitudes of the two rotations correlate best (magnitudes do not depend on the
   mounting), refined by a parabola through the peak.
3. Rotation R_lidar_imu: the best rotation from the gyro's rotation vectors to the lidar's
   (Kabsch: imu.closest_rotation), both centred (a constant gyro bias drops out) and with a
   scale (a gyro in deg/s is frontend.imu_check's to tell; the rotation does not depend on it).
4. Offset again, with the rotation: the least-squares residual of the vectors at offsets around
   the peak (the rotation re-fitted at each), a parabola through its minimum; 3-4 again until
   the offset settles (at most PASSES times).

Confidence: the offset's and the rotation's standard deviations, each the larger of the least
squares' (the residual's variance over the parabola's curvature; over the excitation about the
least determined axis: a turn about one axis only leaves the mounting about it undetermined, an
infinite sigma) and a block jackknife's (the odometry's errors follow the motion, which the
least squares take as independent); and the correlation of the magnitudes at the offset. An
estimate is used when its sigma is within MAX_OFFSET_SIGMA_S, MAX_ROTATION_SIGMA_DEG and the
magnitudes correlate (MIN_CORRELATION); else the IMU is not used, said in one line (the run goes
on lidar-only).

The lidar-only window grows CHECK_EVERY scans at a time, from MIN_INTERVALS, until the estimate
is confident at two checks in a row or WINDOW_S of scans were registered: a walk that turns
about two axes early stops early. Gyro-aided passes over the same scans then deskew each sweep
and guess each pose with the gyro's rotation as the last estimate places it, and estimate again
within SECOND_SEARCH_S, until the offset moves less than SETTLED_S (at most GYRO_PASSES): a
lidar-only odometry lags a fast turn (its deskew assumes the last interval's motion), which put
the offset 2 to 16 ms off on 30 s walks and cost one 27 % of ATE; aided, within 1 ms
(docs/benchmarks/2026-12-04-imu-calibration.md, with the cost).
None is made when the rotation is needed, not found, and the magnitudes already agree
(LAG_FREE_CORRELATION): no lag to take out, the motion hides the mounting.

The rotation found is refined in the back-end's final solve (imu.T_lidar_imu_sigma_deg, set
here to REFINE_SIGMA_FACTOR x its sigma; backend.inertial_graph.mount_edge): the odometry's
rotation errors leave the turn vectors' fit 0.2-0.4 deg off, a few tenths the final solve's
IMU factors are sensitive to (docs/benchmarks/2026-12-04b-imu-calibration.md).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_slam.geometry import matrices_from_rotvecs, rotvec_from_matrix
from lidar_slam.imu import closest_rotation
from lidar_slam.io.imu_gnss import ImuSamples

log = logging.getLogger(__name__)

SEARCH_S = 1.0  # the fine offset is searched within this of the coarse one (s)
OFFSET_STEP_S = 0.002  # grid of the magnitudes' correlation (s); a parabola refines the peak
REFINE_STEP_S = 0.0005  # grid of the vector residual around the peak (s)
PASSES = 10  # at most: rotation, then offset around the last one, until it settles
MIN_INTERVALS = 30  # registered intervals before a first estimate
CHECK_EVERY = 20  # scans between two estimates while the window grows
WINDOW_S = 30.0  # the window's longest span (s of scans)
# An estimate is used when its standard deviation (the larger of the least-squares one and the
# block jackknife's) is within these: the bound for the offset (found within 2 ms), and
# twice its bound for the rotation (within 1 deg), as a mounting off by 2 deg still lets the IMU
# help (frontend.imu_check takes up to 10 deg as the same mounting). Measured errors against
# these sigmas: docs/benchmarks/2026-12-04-imu-calibration.md.
MAX_OFFSET_SIGMA_S = 0.002
MAX_ROTATION_SIGMA_DEG = 2.0
# Pearson correlation of the rotation magnitudes at the offset below which the two streams are
# not taken to be of the same motion (another sensor's IMU, a clock drifting within the window).
MIN_CORRELATION = 0.8
N_PARAMETERS = 8  # rotation 3, scale 1, centre (bias) 3, offset 1
JACKKNIFE_BLOCKS = 6  # stretches of the window for the confidence
TRIM_FACTOR = 3.0  # intervals with a residual beyond this x the median are left out
GYRO_PASSES = 3  # gyro-aided passes at most (calibrate), until the offset moves < SETTLED_S
SETTLED_S = 0.001
GYRO_KNOTS = 9  # knots of a sweep's gyro motion in that pass
SECOND_SEARCH_S = 0.05  # the offset searched within this of the first pass's (s)
# The gyro-aided passes take out the lidar-only odometry's lag in fast turns, which shows as
# magnitudes that correlate below 1 (the three 30 s walks' first passes: 0.89-0.999, their
# rotation sigma then 1.7 -> 0.17 deg on one). A first pass whose magnitudes correlate at least
# this has no such error left: a rotation it could not find is the motion's (a drive turning
# about one axis: 0.9998, sigma 5.2 deg, the same after three aided passes that cost 20 s), and
# no pass is made. No bank row calibrates (each gives its overlay): the bank's runs are unchanged.
LAG_FREE_CORRELATION = 0.999
# A rotation found here is refined in the back-end's final solve (imu.T_lidar_imu_sigma_deg),
# with a prior of this x its sigma: the sigmas are honest to a factor of about two (the grid's
# errors 0.23-0.37 deg for sigmas 0.15-0.39), and a prior too tight keeps the error
# (docs/benchmarks/2026-12-04b-imu-calibration.md).
REFINE_SIGMA_FACTOR = 2.0
# A first estimate whose gyro scale (lidar turn over gyro turn) is within this of 1/57.3 reads a
# gyro in deg/s: it is converted and the calibration made again (issue 30, item 6: it was
# dropped as "mounting cannot be found", the aided passes having turned it 57x).
DEG_SCALE_TOLERANCE = 0.15


@dataclass(frozen=True)
class LidarTurns:
    """The lidar's rotation over intervals between registered scans: their ends t0_s, t1_s (K,)
    on the scans' clock (the scans' reference instants) and the rotation vectors (K, 3) of
    R_world_lidar(t0)^T R_world_lidar(t1) (rad, lidar frame at t0)."""

    t0_s: np.ndarray
    t1_s: np.ndarray
    rotvec: np.ndarray

    @staticmethod
    def from_poses(t_s: np.ndarray, poses: np.ndarray) -> LidarTurns:
        """From registered poses T_world_lidar (K+1, 4, 4) at instants t_s (K+1,)."""
        t = np.asarray(t_s, dtype=np.float64)
        R = np.asarray(poses)[:, :3, :3]
        rv = np.array([rotvec_from_matrix(a.T @ b) for a, b in zip(R[:-1], R[1:])])
        return LidarTurns(t[:-1], t[1:], rv.reshape(-1, 3))

    def __len__(self) -> int:
        return len(self.t0_s)

    @property
    def span_s(self) -> float:
        return float(self.t1_s[-1] - self.t0_s[0]) if len(self) else 0.0


class GyroIntegral:
    """The gyro's integral (rad, IMU frame) from its first sample, linearly interpolated: the
    rotation vector over [a, b] is W(b) - W(a) (small-angle sum of the rates, trapezoid)."""

    def __init__(self, stamp_s: np.ndarray, gyro_radps: np.ndarray):
        self.t = np.asarray(stamp_s, dtype=np.float64)
        w = np.asarray(gyro_radps, dtype=np.float64)
        steps = 0.5 * (w[1:] + w[:-1]) * np.diff(self.t)[:, None]
        self.W = np.vstack([np.zeros((1, 3)), np.cumsum(steps, axis=0)])

    def over(self, a_s: np.ndarray, b_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation vectors (..., 3) over [a_s, b_s] (IMU clock), and whether the samples cover
        each interval (...)."""
        out = np.stack([np.interp(b_s, self.t, self.W[:, k]) - np.interp(a_s, self.t, self.W[:, k])
                        for k in range(3)], axis=-1)
        return out, (a_s >= self.t[0]) & (b_s <= self.t[-1])


def coarse_offset_s(imu_stamp_s: np.ndarray, scan_stamp_s: np.ndarray) -> float:
    """0 when the IMU stamps overlap the scans', else the difference of the first stamps: what
    puts an IMU on another clock (a sensor's, a boot time's) roughly onto the scans'."""
    if imu_stamp_s[0] <= scan_stamp_s[-1] and imu_stamp_s[-1] >= scan_stamp_s[0]:
        return 0.0
    return float(scan_stamp_s[0] - imu_stamp_s[0])


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else 0.0


def _parabola_vertex(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The vertex x and the curvature a (y ~ a (x - x0)^2 + c) of a parabola through the
    points; a <= 0 when they do not bend upwards."""
    a, b, _ = np.polyfit(x - x[0], y, 2)
    if a <= 0:
        return float(x[np.argmin(y)]), float(a)
    return float(x[0] - b / (2 * a)), float(a)


@dataclass(frozen=True)
class VectorFit:
    """lidar_i - mean ~ scale R (gyro_i - mean) over the covered intervals at one offset."""

    R_lidar_imu: np.ndarray
    scale: float
    residual: float  # sum of squared residuals (rad^2)
    n: int
    information_min: float  # smallest eigenvalue of sum scale^2 (|v|^2 I - v v^T) (rad^2)


def _fit_vectors(lidar: np.ndarray, gyro: np.ndarray) -> VectorFit:
    lc, gc = lidar - lidar.mean(axis=0), gyro - gyro.mean(axis=0)
    R = closest_rotation(lc.T @ gc)  # argmax tr(R^T H): lidar ~ R gyro
    v = gc @ R.T
    vv = float((v * v).sum())
    scale = float((lc * v).sum() / vv) if vv > 0 else 0.0
    r = lc - scale * v
    M = scale ** 2 * (vv * np.eye(3) - v.T @ v)
    return VectorFit(R, scale, float((r * r).sum()), len(lidar),
                     float(np.linalg.eigvalsh(M)[0]))


@dataclass(frozen=True)
class Estimate:
    """The offset (added to IMU stamps: onto the scans' clock, s) and R_lidar_imu (IMU-frame
    vectors into the lidar frame) found, with their confidence."""

    time_offset_s: float
    coarse_offset_s: float
    offset_sigma_s: float
    correlation: float  # of the rotation magnitudes at the offset
    R_lidar_imu: np.ndarray
    rotation_sigma_deg: float  # about the least determined axis
    gyro_scale: float  # lidar rotation / gyro's (~1 in rad/s, ~1/57.3 in deg/s)
    n_intervals: int
    span_s: float
    excitation_dps: tuple[float, float, float]  # RMS lidar rate about its principal axes

    def offset_ok(self) -> bool:
        return bool(self.offset_sigma_s <= MAX_OFFSET_SIGMA_S
                    and self.correlation >= MIN_CORRELATION)

    def rotation_ok(self) -> bool:
        return bool(self.offset_ok() and self.rotation_sigma_deg <= MAX_ROTATION_SIGMA_DEG)

    def summary(self) -> dict:
        rv = np.degrees(rotvec_from_matrix(self.R_lidar_imu))
        return {"time_offset_s": round(self.time_offset_s, 6),
                "coarse_offset_s": round(self.coarse_offset_s, 6),
                "offset_sigma_ms": _rounded(1e3 * self.offset_sigma_s, 3),
                "correlation": round(self.correlation, 4),
                "R_lidar_imu": [[round(float(v), 6) + 0.0 for v in row]
                                for row in self.R_lidar_imu],
                "R_lidar_imu_rotvec_deg": [round(float(v), 3) + 0.0 for v in rv],
                "rotation_sigma_deg": _rounded(self.rotation_sigma_deg, 3),
                "gyro_scale": round(self.gyro_scale, 4),
                "intervals": self.n_intervals, "span_s": round(self.span_s, 3),
                "excitation_deg_per_s": [round(v, 2) for v in self.excitation_dps]}


def _rounded(v: float, digits: int) -> float | None:
    return round(float(v), digits) if np.isfinite(v) else None  # JSON has no inf


def _excitation_dps(turns: LidarTurns) -> tuple[float, float, float]:
    rates = turns.rotvec / (turns.t1_s - turns.t0_s)[:, None]
    ev = np.linalg.eigvalsh(rates.T @ rates / max(len(rates), 1))[::-1]
    return tuple(float(np.degrees(np.sqrt(max(e, 0.0)))) for e in ev)


def _sigma_deg(fit: VectorFit) -> float:
    dof = 3 * fit.n - N_PARAMETERS
    if dof <= 0 or fit.information_min <= 0:
        return float("inf")
    return float(np.degrees(np.sqrt(fit.residual / dof / fit.information_min)))


def estimate(imu: ImuSamples, turns: LidarTurns, coarse_s: float = 0.0,
             search_s: float = SEARCH_S) -> Estimate:
    """The offset within search_s of coarse_s (search_s 0: the offset is coarse_s, given) and
    the rotation, with their confidence, from the gyro and the lidar's turns (module doc)."""
    gyro = GyroIntegral(imu.stamp_s, imu.gyro_radps)
    lidar_mag = np.linalg.norm(turns.rotvec, axis=1)

    def at(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.asarray(offsets, dtype=np.float64)[:, None]
        return gyro.over(turns.t0_s[None, :] - d, turns.t1_s[None, :] - d)

    # 2. the magnitudes' correlation over the grid (every covered interval)
    n_steps = int(round(search_s / OFFSET_STEP_S))
    grid = coarse_s + OFFSET_STEP_S * np.arange(-n_steps, n_steps + 1)
    vecs, covered = at(grid)
    mags = np.linalg.norm(vecs, axis=2)
    corr = np.array([_pearson(lidar_mag[c], m[c]) if c.sum() >= MIN_INTERVALS else -1.0
                     for m, c in zip(mags, covered)])
    k = int(np.argmax(corr))
    offset = grid[k]
    if 0 < k < len(grid) - 1:
        offset, _ = _parabola_vertex(grid[k - 1:k + 2], -corr[k - 1:k + 2])
    # 3.-4. rotation, then the offset again from the vectors' residual around it
    sigma_s = float("inf") if search_s > 0 else 0.0
    keep = np.ones(len(turns), dtype=bool)
    for _ in range(PASSES if search_s > 0 else 0):
        keep = _inliers(turns, *at(np.array([offset])))
        fine = offset + REFINE_STEP_S * np.arange(-8, 9)
        vecs, covered = at(fine)
        use = covered & keep[None, :]
        if (use.sum(axis=1) < MIN_INTERVALS).any():
            break
        fits = [_fit_vectors(turns.rotvec[u], v[u]) for v, u in zip(vecs, use)]
        res = np.array([f.residual for f in fits])
        j = int(np.clip(np.argmin(res), 2, len(fine) - 3))
        new, a = _parabola_vertex(fine[j - 2:j + 3], res[j - 2:j + 3])
        dof = 3 * fits[j].n - N_PARAMETERS
        sigma_s = float(np.sqrt(fits[j].residual / dof / a)) if a > 0 and dof > 0 \
            else float("inf")
        moved = abs(new - offset)
        if moved > 8 * REFINE_STEP_S:  # the minimum is beyond the fine grid: another pass
            sigma_s = float("inf")
        offset = float(np.clip(new, fine[0], fine[-1]))
        if moved < 0.5 * REFINE_STEP_S:
            break
    vecs, covered = at(np.array([offset]))
    c = covered[0] & _inliers(turns, vecs, covered)
    if c.sum() < 3:
        return Estimate(offset, coarse_s, float("inf"), -1.0, np.eye(3), float("inf"), 0.0,
                        int(c.sum()), turns.span_s, _excitation_dps(turns))
    fit = _fit_vectors(turns.rotvec[c], vecs[0][c])
    jack_s, jack_deg = _jackknife(turns, at, offset, c, fit.R_lidar_imu, search_s > 0)
    return Estimate(float(offset), coarse_s, max(sigma_s, jack_s),
                    _pearson(lidar_mag[covered[0]], np.linalg.norm(vecs[0][covered[0]], axis=1)),
                    fit.R_lidar_imu, max(_sigma_deg(fit), jack_deg), fit.scale, int(c.sum()),
                    turns.span_s, _excitation_dps(turns))


def _jackknife(turns: LidarTurns, at, offset: float, use: np.ndarray, R: np.ndarray,
               with_offset: bool) -> tuple[float, float]:
    """Block-jackknife standard deviations of the offset (s) and of the rotation (deg): the
    estimate again with each of JACKKNIFE_BLOCKS stretches of the window left out. The
    odometry's errors follow the motion (a flick's under-turn lasts several scans), so the
    least-squares sigmas, which take them as independent, are several times too small on a
    short window; the spread between stretches is not."""
    fine = offset + REFINE_STEP_S * np.arange(-8, 9)
    vecs, covered = at(fine)
    offsets, angles = [], []
    for block in np.array_split(np.arange(len(turns)), JACKKNIFE_BLOCKS):
        m = use.copy()
        m[block] = False
        u = covered & m[None, :]
        if (u.sum(axis=1) < MIN_INTERVALS).any():
            return float("inf"), float("inf")
        fits = [_fit_vectors(turns.rotvec[k], v[k]) for v, k in zip(vecs, u)]
        if with_offset:
            res = np.array([f.residual for f in fits])
            j = int(np.clip(np.argmin(res), 2, len(fine) - 3))
            offsets.append(_parabola_vertex(fine[j - 2:j + 3], res[j - 2:j + 3])[0])
        angles.append(np.linalg.norm(rotvec_from_matrix(R.T @ fits[8].R_lidar_imu)))
    b = JACKKNIFE_BLOCKS
    sigma_s = float(np.sqrt((b - 1) / b * np.sum((np.array(offsets) - np.mean(offsets)) ** 2))) \
        if with_offset else 0.0
    return sigma_s, float(np.degrees(np.sqrt((b - 1) / b * np.sum(np.square(angles)))))


def _inliers(turns: LidarTurns, vecs: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """The intervals whose residual after a first fit is within TRIM_FACTOR x the median: a
    lidar-only odometry misses part of a fast flick (its deskew lags the motion), and those
    few intervals would tilt the rotation by a degree."""
    c = covered[0]
    keep = np.zeros(len(turns), dtype=bool)
    if c.sum() < 3:
        return keep
    fit = _fit_vectors(turns.rotvec[c], vecs[0][c])
    lc = turns.rotvec[c] - turns.rotvec[c].mean(axis=0)
    gc = vecs[0][c] - vecs[0][c].mean(axis=0)
    r = np.linalg.norm(lc - fit.scale * gc @ fit.R_lidar_imu.T, axis=1)
    keep[np.flatnonzero(c)] = r <= TRIM_FACTOR * np.median(r)
    return keep


# -- the lidar-only window -----------------------------------------------------------------------


@dataclass
class Window:
    """The lidar-only odometry over the first scans: registered poses at their reference
    instants, and what it cost."""

    t_s: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    scans: int = 0
    seconds: float = 0.0
    passes: int = 1
    first_pass: dict | None = None  # its estimate, when a second pass refined it

    def turns(self) -> LidarTurns:
        return LidarTurns.from_poses(np.array(self.t_s), np.array(self.poses))


def _gyro_motion(gyro: GyroIntegral, R: np.ndarray, offset_s: float, t_ref_s: float,
                 sweep_s: tuple[float, float], ref_s: float, T_prev_curr: np.ndarray,
                 period_s: float):
    """The sweep's motion (frontend.deskew.SweepMotion, relative to its reference instant)
    with the rotation the gyro read (put in the lidar frame by R, on the scans' clock by
    offset_s) and the translation at constant velocity."""
    from lidar_slam.frontend.deskew import SweepMotion

    knots = np.linspace(sweep_s[0], sweep_s[1], GYRO_KNOTS) - ref_s
    if not knots[-1] > knots[0]:
        return None
    rv, _ = gyro.over(np.full(len(knots), t_ref_s - offset_s), t_ref_s + knots - offset_s)
    T = np.tile(np.eye(4), (len(knots), 1, 1))
    T[:, :3, :3] = matrices_from_rotvecs(rv @ R.T)
    T[:, :3, 3] = knots[:, None] / period_s * T_prev_curr[:3, 3]
    return SweepMotion(knots, T)


def _window_pass(source, cfg, start: int, count: int, window_s: float, on_interval,
                 aid: tuple[GyroIntegral, np.ndarray, float] | None = None) -> Window:
    """One lidar-only odometry over the run's first scans, until window_s of them or
    on_interval(window) says stop; aid (gyro, R_lidar_imu, offset): deskew each sweep and
    guess each pose with the gyro's rotation (the second pass)."""
    from lidar_slam.frontend.deskew import Deskewer
    from lidar_slam.frontend.odometry import Odometry, VoxelSelector

    odo = Odometry(cfg, lidar_only=False)  # an IMU run's: no lidar-only coarse pass or target
    deskew = Deskewer(cfg.data, 0.5 * cfg.voxel_size_m(), VoxelSelector())
    win = Window()
    for scan in source.scans(start, count):
        motion = guess = None
        if aid is not None and win.t_s and deskew.will_deskew(scan):
            gyro, R, offset = aid
            ref = deskew.reference_s(scan)
            period = scan.stamp_s - deskew.last_stamp_s if deskew.last_stamp_s is not None \
                and scan.stamp_s > deskew.last_stamp_s else deskew.last_period_s
            t_ref = scan.stamp_s + ref
            motion = _gyro_motion(gyro, R, offset, t_ref, deskew.sweep_s(scan), ref,
                                  odo.last_delta, period)
            rv, _ = gyro.over(np.array([win.t_s[-1] - offset]), np.array([t_ref - offset]))
            step = np.eye(4)
            step[:3, :3] = _matrix(rv[0] @ R.T)
            step[:3, 3] = odo.last_delta[:3, 3] * (t_ref - win.t_s[-1]) / period
            guess = win.poses[-1] @ step
        d = deskew(scan, odo.last_delta, motion)
        # the gyro's rotation with a constant-velocity translation: not the IMU's full
        # prediction, so kiss-icp keeps all its iterations (odometry.imu_max_num_iterations)
        res = odo.step(d, guess, capped=False)
        win.scans += 1
        if res.registered:
            win.t_s.append(scan.stamp_s + d.ref_s)
            win.poses.append(res.T_world_ref)
        span = win.t_s[-1] - win.t_s[0] if win.t_s else 0.0
        last = span >= window_s or win.scans == count
        if on_interval(win, last) or last:
            break
    return win


def unobservable_rotation(est: Estimate, need_rotation: bool) -> bool:
    """Whether the rotation est could not find is the motion's, not the odometry's: needed, not
    found, and magnitudes that already agree (LAG_FREE_CORRELATION). Then the gyro-aided passes
    cannot change the verdict and are not made."""
    return bool(need_rotation and not est.rotation_ok()
                and est.correlation >= LAG_FREE_CORRELATION)


def _matrix(rotvec: np.ndarray) -> np.ndarray:
    from lidar_slam.geometry import matrix_from_rotvec

    return matrix_from_rotvec(rotvec)


def calibrate(source, imu: ImuSamples, cfg, given_offset_s: float | None = None,
              need_rotation: bool = True, window_s: float = WINDOW_S, start: int = 0,
              count: int | None = None) -> tuple[Estimate | None, Window]:
    """The estimate from a lidar-only odometry over the first scans of the run (source's
    scans start.. start + count, growing until confident or window_s; module doc), or None when
    too few intervals were registered; given_offset_s: the config's offset (then only the
    rotation is estimated). need_rotation: whether a confident rotation is needed to stop.

    Then the gyro-aided passes over the same scans (module doc)."""
    t_start = time.perf_counter()
    stamps = np.asarray(source.stamps, dtype=np.float64) if source.stamps is not None else None
    coarse = given_offset_s if given_offset_s is not None else \
        coarse_offset_s(imu.stamp_s, stamps) if stamps is not None and len(stamps) else 0.0
    search = 0.0 if given_offset_s is not None else SEARCH_S
    count = len(source) - start if count is None else count
    state = {"est": None, "before": False}

    def confident(win: Window, last: bool) -> bool:
        n = len(win.t_s) - 1
        if n < MIN_INTERVALS or not (win.scans % CHECK_EVERY == 0 or last):
            return False
        est = state["est"] = estimate(imu, win.turns(), coarse, search)
        ok = est.rotation_ok() or (not need_rotation and est.offset_ok())
        stop = ok and state["before"]  # twice in a row: the jackknife is itself noisy
        state["before"] = ok
        return stop

    win = _window_pass(source, cfg, start, count, window_s, confident)
    est = state["est"]
    first = est
    for _ in range(GYRO_PASSES if est is not None and est.correlation >= MIN_CORRELATION
                   and not unobservable_rotation(est, need_rotation) else 0):
        gyro = GyroIntegral(imu.stamp_s, imu.gyro_radps)
        aided = _window_pass(source, cfg, start, win.scans, np.inf, lambda w, last: False,
                             (gyro, est.R_lidar_imu, est.time_offset_s))
        again = estimate(imu, aided.turns(), est.time_offset_s if search else coarse,
                         SECOND_SEARCH_S if search else 0.0)
        if again.correlation < MIN_CORRELATION:
            break
        moved = abs(again.time_offset_s - est.time_offset_s)
        est = dataclasses.replace(again, coarse_offset_s=first.coarse_offset_s)
        win = dataclasses.replace(aided, scans=win.scans, passes=win.passes + 1,
                                  first_pass={"time_offset_s": round(first.time_offset_s, 6),
                                              "R_lidar_imu_rotvec_deg": first.summary()[
                                                  "R_lidar_imu_rotvec_deg"]})
        if moved < SETTLED_S:
            break
    win.seconds = time.perf_counter() - t_start
    return est, win


# -- the run's IMU: config, input, or the data ---------------------------------------------------


def offset_is_auto(cfg, source) -> bool:
    """Whether the IMU's clock offset is to be found from the data: "auto" in the config, or
    not set there and the input does not put its IMU on the scans' clock itself (a public
    dataset's layout and an Ouster pcap do: io.datasets.common.Carried)."""
    imu = cfg.imu
    if imu.time_offset_s == "auto":
        return True
    return "time_offset_s" not in imu.model_fields_set and source.sensor_streams is None


def mount_is_auto(cfg) -> bool:
    """Whether R_lidar_imu is to be found from the data: "auto" in the config, or set neither
    there nor by the input's own calibration (run.runner applied that one first)."""
    return cfg.imu.T_lidar_imu == "auto" or "T_lidar_imu" not in cfg.imu.model_fields_set


def _with_values(cfg, offset_s: float | None, R: np.ndarray | None,
                 sigma_deg: float | None = None):
    """cfg with the offset and the rotation used (the effective config of the run folder); the
    rotation's sigma_deg (found from the data): refined in the final solve (imu.
    T_lidar_imu_sigma_deg, REFINE_SIGMA_FACTOR x it)."""
    update = {}
    if offset_s is not None:
        update["time_offset_s"] = round(float(offset_s), 6) + 0.0
    if R is not None:
        given = cfg.imu.T_lidar_imu
        T = np.eye(4)
        if given != "auto" and "T_lidar_imu" in cfg.imu.model_fields_set:
            T = cfg.imu.T_lidar_imu_matrix()
        T[:3, :3] = R
        update["T_lidar_imu"] = [round(float(v), 9) + 0.0 for v in T.ravel()]
        if sigma_deg is not None:
            update["T_lidar_imu_sigma_deg"] = round(REFINE_SIGMA_FACTOR * sigma_deg, 4)
    if not update:
        return cfg
    return cfg.model_copy(update={"imu": cfg.imu.model_copy(update=update)})


def resolve(cfg, source, inertial, offset_auto: bool, mount_auto: bool, start: int = 0,
            count: int | None = None):
    """The run's config and IMU input once the offset and the mounting the config does not give
    are found from the data: (cfg with the values used, inertial with the IMU on the scans'
    clock, or without it and one warning line why when an estimate is not confident).
    summary.json's imu.calibration says what was estimated, its confidence and what was used.
    The window is the run's first scans (start, count)."""
    import dataclasses

    from lidar_slam.io.inertial_input import on_scan_clock

    if inertial.imu is None or not (offset_auto or mount_auto):
        return cfg, inertial
    imu = inertial.imu
    given_offset = None if offset_auto else 0.0  # a given offset: applied by load_inertial
    # The window's own odometry runs with the config's mounting unused: a plain lidar config.
    window_cfg = cfg.model_copy(update={"imu": cfg.imu.model_copy(
        update={"T_lidar_imu": [0.0] * 6, "time_offset_s": 0.0})})
    est, win = calibrate(source, imu, window_cfg, given_offset, need_rotation=mount_auto,
                         start=start, count=count)
    gyro_unit = None
    if est is not None and abs(est.gyro_scale * np.degrees(1.0) - 1.0) <= DEG_SCALE_TOLERANCE:
        # the lidar turned 1/57.3 of what the gyro read: deg/s (frontend.imu_check converts
        # so too, but only once the IMU is in use; the aided passes here need rad/s first)
        log.warning("%s: the IMU's gyro turned %.1fx as far as the lidar over the calibration "
                    "window: read as deg/s and converted to rad/s", imu.source,
                    1.0 / est.gyro_scale)
        imu = dataclasses.replace(imu, gyro_radps=np.radians(imu.gyro_radps))
        inertial = dataclasses.replace(inertial, imu=imu)
        gyro_unit = "deg/s, converted to rad/s"
        est, win = calibrate(source, imu, window_cfg, given_offset, need_rotation=mount_auto,
                             start=start, count=count)
    calibration = {**({} if gyro_unit is None else {"gyro_unit": gyro_unit}),
                   "time_offset_s_from": "data" if offset_auto else "config",
                   "R_lidar_imu_from": "data" if mount_auto else "config or input",
                   "window_scans": win.scans, "window_passes": win.passes,
                   "window_seconds": round(win.seconds, 2),
                   **({} if win.first_pass is None else {"first_pass": win.first_pass}),
                   **({} if est is None else {"estimate": est.summary()})}
    why = _not_confident(est, win, offset_auto, mount_auto, imu)
    stamps = getattr(source, "stamps", None)
    carried = getattr(source, "sensor_streams", None)
    if why is not None and mount_auto and carried is not None and carried.T_lidar_imu is None:
        why += f" ({carried.reason('imu')})"  # a dataset that publishes no mounting says so
    if why is not None:
        overlay = _imu_overlay(getattr(source, "root", None))
        if overlay is not None:  # `simulate` wrote the IMU's values beside the data
            why += f"; {overlay} gives them: --config {overlay}"
        log.warning("%s: IMU not used: %s; the run goes on lidar-only (imu.time_offset_s and "
                    "imu.T_lidar_imu in the config use it as given)", imu.source, why)
        summary = {**inertial.summary, "imu": {"used": False, "source": imu.source,
                                               "samples": len(imu), "reason": why,
                                               "calibration": calibration}}
        return cfg, dataclasses.replace(inertial, imu=None, summary=summary)
    cfg = _with_values(cfg, est.time_offset_s if offset_auto else None,
                       est.R_lidar_imu if mount_auto else None,
                       est.rotation_sigma_deg if mount_auto else None)
    if offset_auto:
        stream, imu_summary = on_scan_clock(imu, "imu", est.time_offset_s, stamps, lenient=True)
    else:  # on the scans' clock already
        stream, imu_summary = imu, dict(inertial.summary["imu"])
    log.info("IMU calibrated from the data over %d scans (%.1f s): %s", win.scans, win.seconds,
             calibration)
    if mount_auto:
        imu_summary["T_lidar_imu_from"] = ("the data (imu_calibration: the rotation; the "
                                           "translation the config's, or 0)")
    summary = {**inertial.summary, "imu": {**imu_summary, "calibration": calibration}}
    return cfg, dataclasses.replace(inertial, imu=stream, summary=summary)


def _imu_overlay(root) -> Path | None:
    """The lidar_slam.yaml beside an input folder (what `simulate` writes) when it gives the
    IMU's values (an `imu:` section), else None."""
    import yaml

    from lidar_slam.sim.sequence import OVERLAY_FILE

    if root is None:
        return None
    path = Path(root) / OVERLAY_FILE
    try:
        doc = yaml.safe_load(path.read_text()) if path.is_file() else None
    except (OSError, yaml.YAMLError):
        return None
    return path if isinstance(doc, dict) and isinstance(doc.get("imu"), dict) else None


def _gyro_path(imu: ImuSamples) -> str:
    """How far the gyro turned over its stream: the excitation there is to calibrate with."""
    w = np.linalg.norm(imu.gyro_radps, axis=1)
    path = float(np.degrees((0.5 * (w[1:] + w[:-1]) * np.diff(imu.stamp_s)).sum()))
    return (f"the gyro turned {path:.3g} deg in all over its {len(imu)} samples, "
            f"{imu.stamp_s[-1] - imu.stamp_s[0]:.3g} s")


def _not_confident(est: Estimate | None, win: Window, offset_auto: bool, mount_auto: bool,
                   imu: ImuSamples) -> str | None:
    """Why an estimate cannot be used (one line), or None."""
    wanted = " and ".join(w for w, on in (("clock offset", offset_auto),
                                          ("mounting", mount_auto)) if on)
    if est is None:
        return (f"its {wanted} cannot be found from the data: {len(win.t_s)} scans registered "
                f"in the first {win.scans} ({MIN_INTERVALS + 1} needed; {_gyro_path(imu)})")
    exc = ", ".join(f"{v:.1f}" for v in est.excitation_dps)
    over = (f"over {est.span_s:.1f} s of scans (lidar rotation rate RMS about its three "
            f"principal axes {exc} deg/s)")
    if offset_auto and not est.offset_ok():
        return (f"its clock offset cannot be found from the data {over}: best "
                f"{est.time_offset_s:+.4f} s, sigma {1e3 * est.offset_sigma_s:.2g} ms (at most "
                f"{1e3 * MAX_OFFSET_SIGMA_S:g}), rotation rates correlating {est.correlation:.2f} "
                f"(at least {MIN_CORRELATION:g})")
    if mount_auto and not est.rotation_ok():
        return (f"its mounting cannot be found from the data {over}: sigma "
                f"{est.rotation_sigma_deg:.2g} deg (at most {MAX_ROTATION_SIGMA_DEG:g}; a turn "
                f"about one axis leaves the mounting about it undetermined)")
    return None

