"""Loops between sessions through one place index over every session's keyframes.

Candidates by place, not by session pair: a KD-tree (scipy) over the Scan Context ring keys of
all sessions' keyframes gives each keyframe the nearest ring keys of the other sessions, each
compared at every column shift (sessions may go the other way round); the best are verified by
the loop-closure ICP gates (lidar_slam.loop.verify) on the query keyframe's cloud against the
match keyframe's submap, as within a run. Once a solve has placed the sessions, a guided pass
verifies each keyframe against the other sessions' keyframes nearest to it in the merged frame
(a KD-tree over positions). Each keyframe gets a bounded number of candidates, verifications
and links (at most max_links other sessions), so the cost grows with keyframes, not with
sessions squared.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

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


def nearest_of_others(tree: cKDTree, owner: np.ndarray, x: np.ndarray, session: int, n: int,
                      upper: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """(distances, entries) of the n entries of tree nearest to x whose owner is not session,
    nearest first, within upper: the query widened (doubled) until n others are found or the
    tree is exhausted."""
    k = 2 * n
    while True:
        k = min(k, tree.n)
        d, j = tree.query(x, k=k, distance_upper_bound=upper)
        d, j = np.atleast_1d(d), np.atleast_1d(j)
        ok = np.isfinite(d)
        ok[ok] = owner[j[ok]] != session
        if ok.sum() >= n or k == tree.n or not np.isfinite(d[-1]):
            return d[ok][:n], j[ok][:n]
        k *= 2


class PlaceIndex:
    """Every session's keyframe descriptors in one index: a KD-tree over the ring keys of all
    of them, each entry's session, keyframe id and grid."""

    def __init__(self, grids: dict[int, SessionGrids]):
        self.session = np.concatenate([np.full(len(g.ids), i) for i, g in grids.items()])
        self.kf = np.concatenate([g.ids for g in grids.values()]).astype(np.int64)
        self.grids = np.concatenate([g.grids for g in grids.values()])
        self.tree = cKDTree(np.concatenate([g.ring_keys for g in grids.values()]))

    def candidates(self, session: int, query_grid: np.ndarray, n: int, cfg: SlamConfig
                   ) -> list[tuple[float, int, int, float]]:
        """(distance, session, keyframe id, yaw guess rad) below the threshold, best first:
        the n ring keys of other sessions nearest to the query's, each compared at every
        column shift."""
        sc = cfg.loop.scan_context
        _, near = nearest_of_others(self.tree, self.session, query_grid.mean(axis=1),
                                    session, n)
        shifts = np.arange(sc.sectors)
        out = []
        for j in near:
            dist = column_distances(query_grid, self.grids[j], shifts)
            best = int(np.argmin(dist))
            if dist[best] < sc.threshold:
                out.append((float(dist[best]), int(self.session[j]), int(self.kf[j]),
                            shift_to_yaw(best, sc.sectors)))
        return sorted(out)


def find_loops(sessions: list[Session], cfg: SlamConfig, max_verify: int = 3,
               max_links: int = 2) -> tuple[list[SessionLoop], LoopSearch]:
    """Verified loops between sessions through the place index (module doc): per keyframe the
    loop.scan_context.candidates x max_links nearest ring keys of other sessions; per other
    session the best max_verify of them verified until one is accepted, until the keyframe has
    loops to max_links sessions (counting those where it was the match of another session's
    query: such a keyframe is not queried again for them). A pair verified one way round is
    not verified the other way. Verification sides are built once per keyframe."""
    grids = {s.index: SessionGrids(s, cfg) for s in sessions}
    index = PlaceIndex(grids)
    by_index = {s.index: s for s in sessions}
    vcfg = cfg.loop.verify
    radius = vcfg.submap_radius
    n_cand = cfg.loop.scan_context.candidates * max_links
    stats = LoopSearch()
    loops: list[SessionLoop] = []
    matches: dict[tuple[int, int], Side] = {}
    tried: set[tuple[int, int, int, int]] = set()
    links: dict[tuple[int, int], set[int]] = {}  # (session, keyframe) -> sessions linked
    n_links = min(max_links, len(sessions) - 1)
    for sq in sessions:
        for k, grid in zip(grids[sq.index].ids, grids[sq.index].grids):
            k = int(k)
            mine = links.setdefault((sq.index, k), set())
            if len(mine) >= n_links:
                continue  # linked as the match of other sessions' queries
            q_side = None
            stats.queries += 1
            found = index.candidates(sq.index, grid, n_cand, cfg)
            stats.candidates += len(found)
            tries: dict[int, int] = {}
            done = set(mine)  # sessions linked (or already verified the other way)
            for dist, o, m, yaw in found:
                if o in done or tries.get(o, 0) >= max_verify:
                    continue
                key = (sq.index, k, o, m) if sq.index < o else (o, m, sq.index, k)
                if key in tried:
                    done.add(o)  # already verified the other way round
                    continue
                tried.add(key)
                tries[o] = tries.get(o, 0) + 1
                if q_side is None:
                    q_side = query_side(sq.map.keyframe(k).points.astype(np.float64), vcfg)
                if (o, m) not in matches:
                    matches[(o, m)] = match_side(by_index[o].map.submap(m, radius), vcfg)
                stats.verified += 1
                res = verify(LoopCandidate(k, m, dist, yaw), q_side, matches[(o, m)], vcfg)
                if res.accepted:
                    c = res.constraint
                    loops.append(SessionLoop(o, m, sq.index, k, c.T_match_query,
                                             c.information, c.fitness, c.rmse_m, dist))
                    stats.accepted += 1
                    done.add(o)
                    mine.add(o)
                    links.setdefault((o, m), set()).add(sq.index)
                    if len(mine) >= n_links:
                        break
        log.info("session %d: %d loops so far (%d verified)", sq.index, len(loops),
                 stats.verified)
    return loops, stats


def guided_loops(sessions: list[Session], T_ref_kf: dict[int, np.ndarray],
                 have: list[SessionLoop], cfg: SlamConfig, radius_m: float,
                 max_links: int = 2) -> tuple[list[SessionLoop], int]:
    """More loops where the sessions are now known to overlap: each keyframe of a placed
    session with loops to fewer than max_links other placed sessions, against the nearest
    keyframe of each other placed session it has no loop to (within radius_m, nearest first,
    until it would have max_links; positions T_ref_kf (K, 4, 4) per session from a first
    solve, one KD-tree over all of them), verified by the same gates from the pose the solve
    implies. Returns the new loops and how many were verified."""
    vcfg = cfg.loop.verify
    links: dict[tuple[int, int], set[int]] = {}
    for lp in have:
        links.setdefault((lp.b, lp.query), set()).add(lp.a)
        links.setdefault((lp.a, lp.match), set()).add(lp.b)
    by_index = {s.index: s for s in sessions if s.index in T_ref_kf}
    owner = np.concatenate([np.full(int((s.map.counts > 0).sum()), s.index)
                            for s in by_index.values()])
    kf = np.concatenate([np.flatnonzero(s.map.counts > 0) for s in by_index.values()])
    tree = cKDTree(np.concatenate([T_ref_kf[s.index][s.map.counts > 0, :3, 3]
                                   for s in by_index.values()]))
    n_other = len(by_index) - 1
    new: list[SessionLoop] = []
    verified = 0
    matches: dict[tuple[int, int], Side] = {}
    for sq in by_index.values():
        for k in np.flatnonzero(sq.map.counts > 0):
            k = int(k)
            mine = links.setdefault((sq.index, k), set())
            want = min(max_links, n_other) - len(mine)
            if want <= 0:
                continue
            # Enough neighbours to hold the nearest keyframe of every session wanted.
            _, j = nearest_of_others(tree, owner, T_ref_kf[sq.index][k, :3, 3], sq.index,
                                     8 * (want + len(mine)), radius_m)
            tries = []
            for o, m in zip(owner[j], kf[j]):
                o, m = int(o), int(m)
                if o in mine or any(o == t[0] for t in tries):
                    continue
                tries.append((o, m))
                if len(tries) == want:
                    break
            for o, m in tries:
                so = by_index[o]
                if (o, m) not in matches:
                    matches[(o, m)] = match_side(so.map.submap(m, vcfg.submap_radius), vcfg)
                init = np.linalg.inv(T_ref_kf[o][m]) @ T_ref_kf[sq.index][k]
                verified += 1
                res = verify(LoopCandidate(k, m, np.nan, 0.0),
                             sq.map.keyframe(k).points.astype(np.float64),
                             matches[(o, m)], vcfg, T_match_query_init=init)
                if res.accepted:
                    c = res.constraint
                    new.append(SessionLoop(o, m, sq.index, k, c.T_match_query,
                                           c.information, c.fitness, c.rmse_m, np.nan))
                    mine.add(o)
                    links.setdefault((o, m), set()).add(sq.index)
    log.info("guided search: %d of %d verified accepted", len(new), verified)
    return new, verified
