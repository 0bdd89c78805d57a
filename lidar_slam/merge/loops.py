"""Loops between sessions: every keyframe of one session against the keyframes of another by
Scan Context (nearest ring keys, then every column shift: sessions may go the other way round),
each candidate verified by the loop-closure ICP gates (lidar_slam.loop.verify) on the query
keyframe's cloud against the match keyframe's submap, as within a run."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.loop.scan_context import column_distances, describe, shift_to_yaw
from lidar_slam.loop.verify import Side, match_side, query_side, verify
from lidar_slam.merge.session import Session
from lidar_slam.types import LoopCandidate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionLoop:
    """A verified loop from keyframe query of session b to keyframe match of session a:
    T_match_query (4x4), its 6x6 information (rotation first), fitness and RMSE (m), and the
    Scan Context distance that proposed it."""

    a: int
    match: int
    b: int
    query: int
    T_match_query: np.ndarray
    information: np.ndarray
    fitness: float
    rmse_m: float
    distance: float


@dataclass
class LoopSearch:
    """Counts of a search (for the summaries)."""

    queries: int = 0
    candidates: int = 0
    verified: int = 0
    accepted: int = 0


def descriptor_shape(cfg: SlamConfig) -> tuple:
    """What makes two runs' descriptors comparable (a run fixes its radius from its first scan:
    two sessions of one place may not agree)."""
    sc = cfg.loop.scan_context
    return sc.rings, sc.sectors, sc.max_radius_m, sc.level_to_ground


class SessionGrids:
    """One session's descriptors: ids of keyframes with points, grids, ring keys; the run's
    stored grids when they were made as cfg makes them, else computed again with cfg's."""

    def __init__(self, session: Session, cfg: SlamConfig):
        if descriptor_shape(session.map.cfg) == descriptor_shape(cfg):
            self.ids, self.grids = session.map.descriptor_grids()
        else:
            sc = cfg.loop.scan_context
            self.ids = np.flatnonzero(session.map.counts > 0)
            self.grids = np.stack([describe(session.map.keyframe(int(k)).points
                                            .astype(np.float64), sc).grid for k in self.ids])
            log.info("%s: descriptors computed again with the reference's (radius %s m)",
                     session.run_dir, sc.max_radius_m)
        self.ring_keys = self.grids.mean(axis=2)


def candidates(query_grid: np.ndarray, target: SessionGrids, cfg: SlamConfig
               ) -> list[tuple[float, int, float]]:
    """(distance, match keyframe id, yaw guess rad) below the threshold, best first: the
    nearest ring keys, each compared at every column shift."""
    sc = cfg.loop.scan_context
    key = query_grid.mean(axis=1)
    near = np.argsort(np.linalg.norm(target.ring_keys - key[None, :], axis=1),
                      kind="stable")[: sc.candidates]
    shifts = np.arange(sc.sectors)
    out = []
    for j in near:
        dist = column_distances(query_grid, target.grids[j], shifts)
        best = int(np.argmin(dist))
        if dist[best] < sc.threshold:
            out.append((float(dist[best]), int(target.ids[j]), shift_to_yaw(best, sc.sectors)))
    return sorted(out)


def find_loops(sessions: list[Session], cfg: SlamConfig, max_verify: int = 3
               ) -> tuple[list[SessionLoop], LoopSearch]:
    """Verified loops between every pair of sessions, both ways (each keyframe of b queried
    among a's and each of a's among b's); per query keyframe the best max_verify candidates
    are verified until one is accepted. Verification sides are built once per keyframe."""
    grids = {s.index: SessionGrids(s, cfg) for s in sessions}
    vcfg = cfg.loop.verify
    radius = vcfg.submap_radius
    stats = LoopSearch()
    loops: list[SessionLoop] = []
    matches: dict[tuple[int, int], Side] = {}
    tried: set[tuple[int, int, int, int]] = set()
    for sq in sessions:
        for k, grid in zip(grids[sq.index].ids, grids[sq.index].grids):
            q_side = None
            for sm in sessions:
                if sm.index == sq.index:
                    continue
                stats.queries += 1
                found = candidates(grid, grids[sm.index], cfg)
                stats.candidates += len(found)
                for dist, m, yaw in found[:max_verify]:
                    pair = (min(sq.index, sm.index), max(sq.index, sm.index))
                    key = (pair[0], m if sm.index == pair[0] else int(k),
                           pair[1], int(k) if sm.index == pair[0] else m)
                    if key in tried:
                        break  # already verified the other way round
                    tried.add(key)
                    if q_side is None:
                        q_side = query_side(sq.map.keyframe(int(k)).points.astype(np.float64),
                                            vcfg)
                    if (sm.index, m) not in matches:
                        matches[(sm.index, m)] = match_side(sm.map.submap(m, radius), vcfg)
                    stats.verified += 1
                    res = verify(LoopCandidate(int(k), m, dist, yaw), q_side,
                                 matches[(sm.index, m)], vcfg)
                    if res.accepted:
                        c = res.constraint
                        loops.append(SessionLoop(sm.index, m, sq.index, int(k), c.T_match_query,
                                                 c.information, c.fitness, c.rmse_m, dist))
                        stats.accepted += 1
                        break
        log.info("session %d: %d loops so far (%d verified)", sq.index, len(loops),
                 stats.verified)
    return loops, stats


def guided_loops(sessions: list[Session], T_ref_kf: dict[int, np.ndarray],
                 have: list[SessionLoop], cfg: SlamConfig, radius_m: float
                 ) -> tuple[list[SessionLoop], int]:
    """More loops where the sessions are now known to overlap: each keyframe of a placed
    session that has no loop to another placed session yet, against that session's keyframe
    nearest to it (within radius_m, positions T_ref_kf (K, 4, 4) per session from a first
    solve), verified by the same gates from the pose the solve implies. Returns the new loops
    and how many were verified."""
    vcfg = cfg.loop.verify
    linked = {(lp.b, lp.query, lp.a) for lp in have} | {(lp.a, lp.match, lp.b) for lp in have}
    by_index = {s.index: s for s in sessions if s.index in T_ref_kf}
    new: list[SessionLoop] = []
    verified = 0
    matches: dict[tuple[int, int], Side] = {}
    for sq in by_index.values():
        for so in by_index.values():
            if so.index == sq.index:
                continue
            P = T_ref_kf[so.index][:, :3, 3]
            for k in np.flatnonzero(sq.map.counts > 0):
                k = int(k)
                if (sq.index, k, so.index) in linked:
                    continue
                d = np.linalg.norm(P - T_ref_kf[sq.index][k, :3, 3], axis=1)
                d[so.map.counts == 0] = np.inf
                m = int(np.argmin(d))
                if d[m] > radius_m:
                    continue
                if (so.index, m) not in matches:
                    matches[(so.index, m)] = match_side(
                        so.map.submap(m, vcfg.submap_radius), vcfg)
                init = np.linalg.inv(T_ref_kf[so.index][m]) @ T_ref_kf[sq.index][k]
                verified += 1
                res = verify(LoopCandidate(k, m, np.nan, 0.0),
                             sq.map.keyframe(k).points.astype(np.float64),
                             matches[(so.index, m)], vcfg, T_match_query_init=init)
                if res.accepted:
                    c = res.constraint
                    new.append(SessionLoop(so.index, m, sq.index, k, c.T_match_query,
                                           c.information, c.fitness, c.rmse_m, np.nan))
                    linked |= {(sq.index, k, so.index), (so.index, m, sq.index)}
    log.info("guided search: %d of %d verified accepted", len(new), verified)
    return new, verified

