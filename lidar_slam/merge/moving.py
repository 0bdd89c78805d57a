"""Moving things in the merged map: points that other scans of their session saw through.

A keyframe's point is tested against the range images (lidar_slam.merge.changes) of the other
keyframes of its own session that were near the point (the max_keyframes nearest to its cell,
within reach_m of it: merge.changes.place_votes): they *see* it (a return within margin_m of
it in its direction) or *see through* it (a return more than margin_m beyond it). What a
keyframe says about a point depends on how far it was from the point, not from the keyframe
that saw it: a car passing the sensor is seen from afar on the approach and seen through by
the keyframes that pass the place once it has gone, which may be far from the first. A point
seen through at least min_votes times and more than twice as often as seen is moving: there
in one scan (or the few next to it, for something slow), gone from that place in the others.
Between sessions that is a change (merge.changes), not this. Most of what one keyframe alone
holds is static all the same (seen from one place only, far away, behind something) and
stays: nothing saw through it. Moving points are left out of the merged map's clouds and of
change detection. Cost: max_keyframes range-image tests per point, linear in keyframes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidar_slam.geometry import transform_points
from lidar_slam.merge.changes import place_votes
from lidar_slam.merge.session import Session

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MovingOptions:
    """Votes needed, the see-through margin (m), the range images' bin (deg), a keyframe's
    reach (m) and how many of the keyframes nearest to a point's cell (of cell_m, m) vote."""

    min_votes: int = 3
    margin_m: float = 0.6
    bin_deg: float = 3.0
    reach_m: float = 15.0
    max_keyframes: int = 60  # the nearest keyframes within reach that vote
    cell_m: float = 2.5


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
        clouds = [s.map.keyframe(k).points.astype(np.float64) for k in range(len(s))]
        points = np.concatenate([transform_points(T[k], c) for k, c in enumerate(clouds)])
        owner = np.repeat(np.arange(len(s)), [len(c) for c in clouds])
        voters = np.flatnonzero(s.map.counts > 0)
        through, seen = place_votes(
            points, owner, T[voters, :3, 3], voters, np.zeros(len(voters), dtype=np.int64), 1,
            lambda v, c=clouds, i=voters, T=T: (c[i[v]], T[i[v]]), opts.max_keyframes,
            opts.reach_m, opts.cell_m, opts.bin_deg, opts.margin_m)
        moving = (through[:, 0] >= opts.min_votes) & (through[:, 0] > 2 * seen[:, 0])
        for k, part in enumerate(np.split(moving, np.cumsum([len(c) for c in clouds])[:-1])):
            out[(s.index, k)] = part
        n_moving += int(moving.sum())
        n_points += len(points)
    log.info("moving: %d of %d keyframe points seen through by the other keyframes of their "
             "session", n_moving, n_points)
    return out
