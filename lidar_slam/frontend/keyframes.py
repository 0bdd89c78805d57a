"""Keyframe selection: a new keyframe by travelled distance or rotation (the store that keeps
them is lidar_slam.map.keyframes)."""

from __future__ import annotations

import numpy as np

from lidar_slam.config import KeyframeConfig
from lidar_slam.geometry import relative, rotation_angle_deg


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
