"""Keyframe selection: a new keyframe by travelled distance or rotation (the store that keeps
them is lidar_slam.map.keyframes)."""

from __future__ import annotations

from collections import deque

import numpy as np

from lidar_slam.config import KeyframeConfig
from lidar_slam.geometry import inverse, relative, rotation_angle_deg


class KeyframeSelector:
    """Declares a new keyframe once the sensor moved distance_m or turned rotation_deg."""

    def __init__(self, cfg: KeyframeConfig):
        self.cfg = cfg
        self.last: np.ndarray | None = None

    def is_keyframe(self, T_world_scan: np.ndarray) -> bool:
        """True for the first scan and whenever the motion since the last keyframe is large
        enough."""
        if self.last is None:
            self.last = T_world_scan
            return True
        T_kf_scan = relative(self.last, T_world_scan)
        moved = np.linalg.norm(T_kf_scan[:3, 3]) >= self.cfg.distance_m
        turned = rotation_angle_deg(T_kf_scan) >= self.cfg.rotation_deg
        if moved or turned:
            self.last = T_world_scan
            return True
        return False


class SteadyWait:
    """Where each due keyframe (KeyframeSelector) is made. Without an IMU a distance or a turn is
    reached in a flick, whose sweep the constant-velocity deskew bent: the keyframes were the
    worst-placed scans of a hand-held walk (docs/bank.md, Decisions, "a keyframe due at a flick
    waits"). So one falling due at a flick (a scan whose miss, the rotation in deg by which its
    registered pose or the scan before's missed the constant-velocity prediction, is over both
    steady_miss_deg and twice the median miss of the last RECENT scans) is made at the first
    registered scan after it whose miss is within steady_miss_deg or that median, at most
    steady_wait_scans late, and at the latest where the next one falls due (KeyframeConfig).
    A trot's steady bounce is not a flick, a car never misses by a degree. The odometry's own
    keyframe copies stay at the due scans (Pipeline._add_anchor), so its poses do not move. One
    still waiting when the input ends is not made: its last few frames stay with the keyframe
    before, as frames after the last keyframe always have."""

    RECENT = 100  # scans whose median miss is the walk's usual one
    MIN_RECENT = 10  # before that many, the median is not trusted (taken as 0)

    def __init__(self, cfg: KeyframeConfig):
        self.cfg = cfg
        self.pending = False  # a keyframe fell due and is not made yet
        self.waited = 0  # registered scans it has waited
        self.recent: deque[float] = deque(maxlen=self.RECENT)  # misses of the last scans
        self.late = 0  # keyframes made after a wait (summary.json keyframes_steady_wait)
        self.not_steady = 0  # of them, made at the limit or the next one due, not steady
        self.last: list[np.ndarray] = []  # the last two registered poses (miss_deg)
        self.last_miss = 0.0  # the last one's own miss (deg)

    def miss_deg(self, T_world_ref: np.ndarray | None) -> float | None:
        """The larger of this scan's and the last one's miss (deg): the rotation by which its
        registered pose T_world_ref missed the constant-velocity prediction from the two
        registered before it. T_world_ref None (not registered, or not deskewed at constant
        velocity): None, and the next scans start again; None also before three in a row."""
        if T_world_ref is None:
            self.last, self.last_miss = [], 0.0
            return None
        miss = None
        if len(self.last) == 2:
            pred = self.last[1] @ inverse(self.last[0]) @ self.last[1]
            m = float(rotation_angle_deg(inverse(pred) @ T_world_ref))
            miss, self.last_miss = max(m, self.last_miss), m
        self.last = [*self.last[-1:], T_world_ref]
        return miss

    def take(self, due: bool, miss_deg: float | None) -> bool:
        """Whether this registered scan is a keyframe; due: one fell due at it (a keyframe
        still waiting is made here, and this one waits in its place when the scan is a flick).
        miss_deg None: not measured (an IMU deskews, or too few scans registered in a row)."""
        bar = self.cfg.steady_miss_deg
        if miss_deg is None or bar <= 0.0 or self.cfg.steady_wait_scans == 0:
            # not measured, or off: one waiting (a skipped scan restarts the misses) is made
            # here, unmeasured, with the one due here
            self._count(self.pending, False)
            made = due or self.pending
            self.pending, self.waited = False, 0
            return made
        self.recent.append(float(miss_deg))
        usual = float(np.median(self.recent)) if len(self.recent) >= self.MIN_RECENT else 0.0
        steady = miss_deg <= max(bar, usual)
        if due:
            made = self.pending
            self._count(made, steady)
            self.pending = miss_deg > max(bar, 2.0 * usual)
            self.waited = 0
            return made or not self.pending
        if not self.pending:
            return False
        if steady or self.waited + 1 >= self.cfg.steady_wait_scans:
            self._count(True, steady)
            self.pending, self.waited = False, 0
            return True
        self.waited += 1
        return False

    def _count(self, made_late: bool, steady: bool) -> None:
        self.late += int(made_late)
        self.not_steady += int(made_late and not steady)
