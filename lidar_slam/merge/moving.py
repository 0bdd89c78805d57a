"""Moving things in the merged map: points that other scans of their session saw through.

A keyframe's point is tested against the range images (lidar_slam.merge.changes) of the other
keyframes of its own session (the nearest max_keyframes within reach_m): they *see* it (a
return within margin_m of it in its direction) or *see through* it (a return more than
margin_m beyond it). A point seen through at least min_votes times and more than twice as
often as seen is moving: there in one scan (or the few next to it, for something slow), gone
from that place in the others. Between sessions that is a change (merge.changes), not this.
Most of what one keyframe alone holds is static all the same (seen from one place only, far
away, behind something) and stays: nothing saw through it. Moving points are left out of the
merged map's clouds and of change detection. Cost: one range-image test per keyframe and
neighbour, linear in keyframes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidar_slam.geometry import inverse, transform_points
from lidar_slam.merge.changes import _RangeImage
from lidar_slam.merge.session import Session

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MovingOptions:
    """Votes needed, the see-through margin (m), the range images' bin (deg), a keyframe's
    reach (m) and how many of the nearest keyframes within it vote."""

    min_votes: int = 3
    margin_m: float = 0.6
    bin_deg: float = 3.0
    reach_m: float = 15.0
    max_keyframes: int = 60  # the nearest keyframes within reach that vote


def moving_points(sessions: list[Session], T_merged_kf: dict[int, np.ndarray],
                  opts: MovingOptions | None = None) -> dict[tuple[int, int], np.ndarray]:
    """(session, keyframe) -> bool per point of its keyframe cloud: True where moving (the
    module doc), for every kept session's keyframes."""
    opts = opts or MovingOptions()
    out, n_moving, n_points = {}, 0, 0
    for s in sessions:
        if s.index not in T_merged_kf:
            continue
        T = T_merged_kf[s.index]
        images: dict[int, _RangeImage] = {}
        for k in range(len(s)):
            p = transform_points(T[k], s.map.keyframe(k).points.astype(np.float64))
            through = np.zeros(len(p), dtype=np.int64)
            seen = np.zeros(len(p), dtype=np.int64)
            dist = np.linalg.norm(T[:, :3, 3] - T[k, :3, 3], axis=1)
            near = [j for j in np.argsort(dist) if j != k and dist[j] < opts.reach_m
                    and s.map.counts[j]][:opts.max_keyframes]
            for j in near:
                if j not in images:
                    images[j] = _RangeImage(s.map.keyframe(j).points.astype(np.float64),
                                            opts.bin_deg)
                t, v = images[j].votes(transform_points(inverse(T[j]), p), opts.margin_m)
                through += t
                seen += v
            out[(s.index, k)] = (through >= opts.min_votes) & (through > 2 * seen)
            n_moving += int(out[(s.index, k)].sum())
            n_points += len(p)
    log.info("moving: %d of %d keyframe points seen through by the other keyframes of their "
             "session", n_moving, n_points)
    return out
