"""Motion compensation under a constant-velocity model, and the sweep-timing bookkeeping.

Convention: a scan's pose refers to the instant of its stamp (`Scan.stamp_s`), and per-point
times are seconds relative to that stamp. A point captured at time t is moved into the sensor
frame at a reference instant ref_s with T_ref_t = interpolate(I, T_prev_curr, (t - ref_s) /
period_s), where T_prev_curr is the last frame-to-frame motion (over period_s seconds). Rotation
is interpolated on SO(3) about the fixed axis of the motion, translation linearly.

Deskewing happens once, here, and only on the points that are used: one point per voxel of the
odometry's input (what kiss-icp registers and adds to its map) and, at keyframes, one point per
voxel of the keyframe cloud (about 6k of the ~120k points of an HDL-64E sweep). In NumPy the
deskew of every point is cheap (~2 ms), but the selection after it is not: selecting on the raw
scan in kiss-icp's C++ and deskewing the selection took the odometry from 64 to 41 ms/frame on
sim 07 (tools/compare_deskew.py).

With an IMU (lidar_slam.frontend.imu_prediction) the motion within the sweep is not constant:
it comes as a SweepMotion, the sensor's pose at knots through the sweep (the IMU sample times),
and each point is moved along it instead (same reference instant, same points, still deskewed
once).
"""

from __future__ import annotations

import bisect
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar_slam.config import DataConfig
from lidar_slam.frontend.crop import range_mask
from lidar_slam.geometry import interpolate, make_pose, matrix_from_rotvec, rotvec_from_matrix
from lidar_slam.types import Scan

# (points (N,3), voxel_m, min_range_m, max_range_m) -> indices of one point per voxel in range
Selector = Callable[[np.ndarray, float, float, float], np.ndarray]


def deskew(points: np.ndarray, point_times_s: np.ndarray, T_prev_curr: np.ndarray,
           period_s: float) -> np.ndarray:
    """Points (N,3) captured at point_times_s (relative to the target instant), expressed in the
    sensor frame at that instant."""
    if period_s <= 0:
        return points
    s = point_times_s * (1.0 / period_s)
    rotvec = rotvec_from_matrix(T_prev_curr[:3, :3])
    theta = float(np.linalg.norm(rotvec))
    out = s[:, None] * T_prev_curr[:3, 3]
    out += points
    if theta > 1e-12:
        # Rodrigues about the motion's fixed axis k: R(a) p = p + sin(a) K p + (1 - cos(a)) K^2 p,
        # as (N,3) x (3,3) products into one reused buffer (fresh temporaries cost page faults).
        k = rotvec / theta
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        ang = s * theta
        tmp = np.empty_like(out)
        np.matmul(points, K.T, out=tmp)
        tmp *= np.sin(ang)[:, None]
        out += tmp
        np.matmul(points, (K @ K).T, out=tmp)
        tmp *= (1.0 - np.cos(ang))[:, None]
        out += tmp
    return out


class SweepMotion:
    """The sensor's motion through a sweep as poses T_ref_t (K, 4, 4) at knot times t (K,),
    seconds relative to the reference instant, strictly increasing: a point captured at time t
    is moved with the pose interpolated between the knots around it (rotation about the
    segment's fixed axis, translation linearly), held constant past the end knots."""

    def __init__(self, times_s: np.ndarray, T_ref_t: np.ndarray):
        self.times_s = np.asarray(times_s, dtype=np.float64)
        self.T_ref_t = np.asarray(T_ref_t, dtype=np.float64)
        if len(self.times_s) < 2 or np.any(np.diff(self.times_s) <= 0):
            raise ValueError("a sweep motion needs at least two knots in increasing time")
        R = self.T_ref_t[:, :3, :3]
        # Per segment: the rotation vector from its start knot to its end (in the start's frame)
        self._rotvec = rotvec_from_matrix(np.swapaxes(R[:-1], 1, 2) @ R[1:])
        # Per segment, a row: the 3x11 matrix M with R0 Exp(a k) p + t0 + s dt = M [p, sin(a) p,
        # (1 - cos(a)) p, 1, s] (Rodrigues about its axis k: R0 + sin(a) R0 K + (1 - cos(a))
        # R0 K^2, K = [k]x; t0 the start knot's translation, dt the segment's), then its angle,
        # start time and duration: apply() gathers one row per point (np.take, the fastest
        # gather) and works on its columns.
        n = len(self._rotvec)
        theta = np.linalg.norm(self._rotvec, axis=1)
        k = self._rotvec / np.where(theta > 1e-12, theta, 1.0)[:, None]
        K = np.zeros((n, 9))
        K[:, [7, 2, 3]] = k  # [k]x, row-major
        K[:, [5, 6, 1]] = -k
        K = K.reshape(n, 3, 3)
        R0K = R[:-1] @ K
        t0 = self.T_ref_t[:-1, :3, 3]
        M = np.concatenate((R[:-1], R0K, R0K @ K, t0[:, :, None],
                            (self.T_ref_t[1:, :3, 3] - t0)[:, :, None]), axis=2)
        self._table = np.concatenate((M.reshape(n, 33), theta[:, None], self.times_s[:-1, None],
                                      np.diff(self.times_s)[:, None]), axis=1)
        self._knots = self.times_s.tolist()  # T_ref_at's lookup, in Python floats
        self._last_at: tuple[float, np.ndarray] | None = None  # T_ref_at's last answer

    def apply(self, points: np.ndarray, times_s: np.ndarray) -> np.ndarray:
        """Points (N,3) captured at times_s (relative to the reference instant), in the sensor
        frame at the reference instant."""
        # The segment around each time (times clipped to the knots), its row of the table, the
        # fraction s of it, then M u per point (~1.8x faster than per-point Rodrigues on (N,3)
        # arrays and per-point 4x4 poses, on 07-ig's 7.5k points; the same numbers to 1e-13 m).
        t = np.clip(np.asarray(times_s, dtype=np.float64), self.times_s[0], self.times_s[-1])
        i = np.searchsorted(self.times_s, t, side="right") - 1
        np.clip(i, 0, len(self.times_s) - 2, out=i)
        g = np.take(self._table, i, axis=0)
        s = (t - g[:, 34]) / g[:, 35]
        a = s * g[:, 33]
        u = np.empty((len(s), 11))
        u[:, :3] = points
        np.multiply(points, np.sin(a)[:, None], out=u[:, 3:6])
        np.multiply(points, (1.0 - np.cos(a))[:, None], out=u[:, 6:9])
        u[:, 9] = 1.0
        u[:, 10] = s
        return np.einsum("nij,nj->ni", g[:, :33].reshape(-1, 3, 11), u)

    def T_ref_at(self, t_s: float) -> np.ndarray:
        """The sensor's pose at t_s (relative to the reference instant) in the reference frame."""
        if self._last_at is not None and self._last_at[0] == t_s:  # the stamp: asked twice
            return self._last_at[1].copy()
        # As apply() finds the segment, in Python floats (~10x faster for one instant)
        knots = self._knots
        t = min(max(float(t_s), knots[0]), knots[-1])
        i = min(max(bisect.bisect_right(knots, t) - 1, 0), len(knots) - 2)
        s = (t - knots[i]) / (knots[i + 1] - knots[i])
        # interpolate(T_ref_t[i], T_ref_t[i + 1], s), with the segment's rotation vector known
        T0, T1 = self.T_ref_t[i], self.T_ref_t[i + 1]
        T = make_pose(T0[:3, :3] @ matrix_from_rotvec(s * self._rotvec[i]),
                      (1 - s) * T0[:3, 3] + s * T1[:3, 3])
        self._last_at = (t_s, T.copy())
        return T


@dataclass(frozen=True)
class DeskewedScan:
    """A scan ready for registration.

    points: (M,3) metres in the sensor frame at the reference instant (the middle of the sweep
    when the scan has per-point times, else its stamp); with times, only one point per voxel of
    `voxel_m` within the range crop, deskewed; without, every point as read (kiss-icp crops and
    downsamples them itself, exactly as stock). ref_s: the reference instant relative to the
    stamp; period_s: the time since the previous scan; T_prev_curr: the constant-velocity motion
    deskewing used, unless `motion` (the IMU's motion through the sweep) is set: then that.
    """

    scan: Scan
    points: np.ndarray
    ref_s: float
    period_s: float
    T_prev_curr: np.ndarray
    select: Selector
    # With per-point times, points are the range-cropped one-per-voxel selection: its indices
    # into the scan and its voxel size.
    selected_idx: np.ndarray | None = None
    selected_voxel_m: float = 0.0
    motion: SweepMotion | None = None

    def _deskew(self, points: np.ndarray, times_rel_ref: np.ndarray) -> np.ndarray:
        if self.motion is not None:
            return self.motion.apply(points, times_rel_ref)
        return deskew(points, times_rel_ref, self.T_prev_curr, self.period_s)

    @property
    def selected(self) -> bool:
        return self.selected_idx is not None

    def T_ref_stamp(self, T_prev_curr: np.ndarray) -> np.ndarray:
        """The stamp's sensor frame in the reference frame, along the motion T_prev_curr (the
        freshly estimated one: it spans the interval between the stamp and the sweep's middle)."""
        if self.ref_s == 0.0:
            return np.eye(4)
        if self.motion is not None:
            return self.motion.T_ref_at(-self.ref_s)
        return interpolate(np.eye(4), T_prev_curr, -self.ref_s / self.period_s)

    def with_motion(self, T_prev_curr: np.ndarray) -> DeskewedScan:
        """The same scan deskewed along another motion (a better estimate of the same sweep's),
        to the same reference instant and with the same points."""
        scan = self.scan
        if self.ref_s == 0.0:  # not deskewed (no per-point times, or deskew off)
            return dataclasses.replace(self, T_prev_curr=T_prev_curr, motion=None)
        idx = slice(None) if self.selected_idx is None else self.selected_idx
        points = deskew(scan.points[idx], scan.point_times[idx] - self.ref_s, T_prev_curr,
                        self.period_s)
        return dataclasses.replace(self, points=points, T_prev_curr=T_prev_curr, motion=None)

    def cloud(self, voxel_m: float, min_range_m: float, max_range_m: float
              ) -> tuple[np.ndarray, np.ndarray | None]:
        """One point per voxel_m voxel within the range, deskewed to the reference instant the
        same way as the registration points, with its intensity: (K,3) and (K,) or None."""
        scan = self.scan
        if self.selected_idx is not None and voxel_m == self.selected_voxel_m:
            # The registration points are this very selection over a wider range: reuse them.
            idx = self.selected_idx
            near = range_mask(self.points, min_range_m, max_range_m)
            return self.points[near], None if scan.intensity is None else scan.intensity[idx[near]]
        idx = self.select(scan.points, voxel_m, min_range_m, max_range_m)
        pts = scan.points[idx]
        if self.ref_s != 0.0:
            pts = self._deskew(pts, scan.point_times[idx] - self.ref_s)
        return pts, None if scan.intensity is None else scan.intensity[idx]


class Deskewer:
    """Keeps the sweep timing between scans (period, reference instant) and deskews each scan
    with the last estimated frame-to-frame motion."""

    def __init__(self, cfg: DataConfig, voxel_m: float, select: Selector,
                 default_period_s: float = 0.1):
        self.cfg = cfg
        self.voxel_m = voxel_m  # one registration point per voxel: kiss-icp's 0.5 x voxel size
        self.select = select
        self.last_stamp_s: float | None = None
        self.last_period_s = default_period_s
        self._sweep: tuple[Scan, tuple[float, float]] | None = None  # sweep_s's last

    def state(self) -> dict:
        return {"last_stamp_s": self.last_stamp_s, "last_period_s": self.last_period_s}

    def restore(self, state: dict) -> None:
        self.last_stamp_s = state["last_stamp_s"]
        self.last_period_s = state["last_period_s"]

    def will_deskew(self, scan: Scan) -> bool:
        """Whether __call__ deskews scan (deskew on, per-point times, points)."""
        return bool(self.cfg.deskew and scan.point_times is not None and len(scan.points))

    def sweep_s(self, scan: Scan) -> tuple[float, float]:
        """The first and last point time of a scan with per-point times (s, relative to its
        stamp); each pass over the times once per scan (the IMU front-end asks first)."""
        if self._sweep is None or self._sweep[0] is not scan:
            times = scan.point_times
            self._sweep = (scan, (float(times.min()), float(times.max())))
        return self._sweep[1]

    def reference_s(self, scan: Scan) -> float:
        """The reference instant of a scan with per-point times, relative to its stamp: the
        middle of its sweep."""
        first, last = self.sweep_s(scan)
        return 0.5 * (first + last)

    def __call__(self, scan: Scan, T_prev_curr: np.ndarray,
                 motion: SweepMotion | None = None) -> DeskewedScan:
        """Deskew the used points of scan to the middle of its sweep (when it has point times),
        along motion when given (the IMU's, relative to that instant), else at constant
        velocity T_prev_curr."""
        if self.last_stamp_s is not None and scan.stamp_s > self.last_stamp_s:
            period_s = scan.stamp_s - self.last_stamp_s
        else:
            period_s = self.last_period_s
        self.last_stamp_s, self.last_period_s = scan.stamp_s, period_s
        times = scan.point_times
        if not self.will_deskew(scan):
            return DeskewedScan(scan, scan.points, 0.0, period_s, T_prev_curr, self.select)
        # Deskew to the middle of the sweep: the correction, and with it the effect of a wrong
        # velocity guess, is half what deskewing to an end of the sweep gives; that feedback
        # makes start-referenced deskew diverge on fast sparse scans. The points are voxel-
        # selected before deskewing, and used as they are (one per voxel of the raw scan): a
        # second selection after deskewing would open holes where deskewing moved two points
        # into one voxel (sample_scans: odometry ATE 8 % worse).
        ref_s = self.reference_s(scan)
        if self.cfg.deskew_all_points:
            out = DeskewedScan(scan, scan.points, ref_s, period_s, T_prev_curr, self.select,
                               motion=motion)
            return dataclasses.replace(out, points=out._deskew(scan.points, times - ref_s))
        idx = self.select(scan.points, self.voxel_m, self.cfg.min_range_m, self.cfg.max_range_m)
        raw = scan.points[idx]  # (gathered once: ~0.1 ms a scan)
        out = DeskewedScan(scan, raw, ref_s, period_s, T_prev_curr, self.select, idx,
                           self.voxel_m, motion)
        return dataclasses.replace(out, points=out._deskew(raw, times[idx] - ref_s))
