"""The data that flows between stages: frozen dataclasses, NumPy inside, frames in the names."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scan:
    """One lidar sweep in the sensor frame.

    points: (N, 3) float64 metres. point_times: (N,) float64 seconds relative to stamp_s
    (the instant the scan's pose refers to), or None. intensity: (N,) float32 or None.
    index: 0-based position of the scan in the input sequence.
    """

    index: int
    stamp_s: float
    points: np.ndarray
    point_times: np.ndarray | None = None
    intensity: np.ndarray | None = None
    source: str = ""


@dataclass(frozen=True)
class Keyframe:
    """A keyframe: its frame index, odometry pose, and a downsampled cloud in its own frame."""

    id: int
    frame_index: int
    T_world_kf_odom: np.ndarray
    points: np.ndarray
    intensity: np.ndarray | None = None


@dataclass(frozen=True)
class LoopCandidate:
    """A place-recognition match: query keyframe revisits match keyframe (ids), with a yaw guess."""

    query: int
    match: int
    score: float
    yaw_guess_rad: float


@dataclass(frozen=True)
class LoopConstraint:
    """A verified loop: relative pose T_match_query, 6x6 information (rotation first), fitness."""

    query: int
    match: int
    T_match_query: np.ndarray
    information: np.ndarray
    fitness: float
    rmse_m: float
