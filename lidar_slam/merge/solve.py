"""The joint solve of a merge: each session's anchor (its frame in the reference's) first from
the consensus of its verified loops, then one robust solve of every session's keyframes.

Anchors: each verified loop between sessions a and b implies where b's frame lies in a's. The
loops that agree with the most others (their implied poses within CONSENSUS_M / CONSENSUS_DEG
where the other loop is) are the pair's consensus; a pair with fewer than min_loops agreeing
loops is not linked. From the reference, sessions are reached over linked pairs (the best linked
first); a session not reached is left out, never forced in. The graph then has every kept
session's keyframes (nodes), its odometry edges (known inliers), its own loops and the loops
between sessions (both GNC-weighted), a fixed prior on the reference's first keyframe and a weak
one on every other session's first keyframe at its consensus anchor (as LT-mapper's anchor
nodes: the frame is free, the start is not thrown away by GNC's first, odometry-only solve).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.geometry import inverse, rotation_angle_deg
from lidar_slam.merge.loops import SessionLoop
from lidar_slam.merge.session import Session

log = logging.getLogger(__name__)

CONSENSUS_M = 1.5
CONSENSUS_DEG = 5.0
REFERENCE_SIGMAS = (1e-3, 1e-4)  # deg, m: the reference fixes the frame
ANCHOR_SIGMAS = (90.0, 100.0)  # deg, m: a weak prior, the loops decide
KEY_STRIDE = 1_000_000  # node key = session index * KEY_STRIDE + keyframe id


def node(session: int, kf: int) -> int:
    return session * KEY_STRIDE + kf


def implied(loop: SessionLoop, T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """T_a_b (session b's frame in session a's) implied by one loop; T_a, T_b: the sessions'
    keyframe poses (K, 4, 4) in their own frames."""
    return T_a[loop.match] @ loop.T_match_query @ inverse(T_b[loop.query])


def consensus(loops: list[SessionLoop], T_a: np.ndarray, T_b: np.ndarray,
              chunk: int = 256) -> tuple[np.ndarray | None, list[int]]:
    """The T_a_b that the most loops agree on and the indices (into loops) of those that do
    (every loop's implied T_a_b against every other's at the other's query keyframe, in blocks
    of chunk rows)."""
    if not loops:
        return None, []
    offsets = np.stack([implied(lp, T_a, T_b) for lp in loops])
    R, t = offsets[:, :3, :3], offsets[:, :3, 3]
    points = np.stack([T_b[lp.query][:3, 3] for lp in loops])
    own = np.einsum("jab,jb->ja", R, points) + t  # T_j at loop j's point
    best, centre = np.zeros(0, dtype=np.int64), 0
    for lo in range(0, len(loops), chunk):
        Ri, ti = R[lo:lo + chunk], t[lo:lo + chunk]
        moved = np.linalg.norm(np.einsum("iab,jb->ija", Ri, points) + ti[:, None, :]
                               - own[None, :, :], axis=2)
        turned = rotation_angle_deg(np.einsum("iab,jac->ijbc", Ri, R))
        agree = (moved < CONSENSUS_M) & (turned < CONSENSUS_DEG)
        counts = agree.sum(axis=1)
        i = int(np.argmax(counts))
        if counts[i] > len(best):
            best, centre = np.flatnonzero(agree[i]), lo + i
    return offsets[centre], best.tolist()


@dataclass
class Anchors:
    """T_ref_session of every session reached from the reference; per left-out session why;
    per pair (a, b) the number of verified and of agreeing loops."""

    T_ref_session: dict[int, np.ndarray]
    left_out: dict[int, str]
    pairs: dict[tuple[int, int], tuple[int, int]] = field(default_factory=dict)


def anchors(sessions: list[Session], loops: list[SessionLoop], reference: int,
            min_loops: int) -> Anchors:
    """Consensus anchors from the reference over linked pairs (see the module doc)."""
    poses = {s.index: s.map.T_map_kf for s in sessions}
    by_pair: dict[tuple[int, int], list[SessionLoop]] = {}
    for lp in loops:
        by_pair.setdefault((lp.a, lp.b), []).append(lp)
    links: dict[tuple[int, int], tuple[np.ndarray, int]] = {}  # (a, b) -> (T_a_b, support)
    pairs = {}
    indices = [s.index for s in sessions]
    for a in indices:
        for b in indices:
            if a >= b:
                continue
            # Loops either way round, all expressed as b's keyframe in a's.
            both = by_pair.get((a, b), []) + [_flip(lp) for lp in by_pair.get((b, a), [])]
            T_ab, agree = consensus(both, poses[a], poses[b])
            pairs[(a, b)] = (len(both), len(agree))
            if T_ab is not None and len(agree) >= min_loops:
                links[(a, b)] = (T_ab, len(agree))
                links[(b, a)] = (inverse(T_ab), len(agree))
    T_ref = {reference: np.eye(4)}
    while True:  # grow from the reference, the best-supported link first
        reach = [(support, a, b) for (a, b), (_, support) in links.items()
                 if a in T_ref and b not in T_ref]
        if not reach:
            break
        _, a, b = max(reach)
        T_ref[b] = T_ref[a] @ links[(a, b)][0]
    left_out = {}
    for s in indices:
        if s in T_ref:
            continue
        found = sum(pairs.get((min(s, o), max(s, o)), (0, 0))[0] for o in indices if o != s)
        left_out[s] = (f"no verified overlap with the merged sessions: {found} verified loops "
                       f"with other sessions, {min_loops} agreeing with one kept session needed")
    return Anchors(T_ref, left_out, pairs)


def _flip(lp: SessionLoop) -> SessionLoop:
    """The same loop seen from the other session (query and match swapped), for the consensus
    only: its information stays in the original query's tangent."""
    return SessionLoop(lp.b, lp.query, lp.a, lp.match, inverse(lp.T_match_query),
                       lp.information, lp.fitness, lp.rmse_m, lp.distance)


@dataclass
class JointSolution:
    """Merged keyframe poses per kept session (K, 4, 4) in the reference's frame; per loop
    (in the order given) whether the solve kept it (None: its sessions were not both kept);
    intra-session loops kept / given."""

    T_merged_kf: dict[int, np.ndarray]
    kept: list[bool | None]
    intra_kept: int
    intra_total: int
    seconds: float


def solve(sessions: list[Session], loops: list[SessionLoop], anchors_: Anchors,
          reference: int) -> JointSolution:
    """One GNC solve of every kept session's keyframes (see the module doc)."""
    graph = PoseGraph(3)
    kept_sessions = [s for s in sessions if s.index in anchors_.T_ref_session]
    for s in kept_sessions:
        T0 = anchors_.T_ref_session[s.index]
        for k, T in enumerate(s.map.T_map_kf):
            graph.set_initial(node(s.index, k), T0 @ T)
        rot, trans = REFERENCE_SIGMAS if s.index == reference else ANCHOR_SIGMAS
        graph.add_prior(node(s.index, 0), T0 @ s.map.T_map_kf[0], rot, trans)
        for e in s.odometry:
            graph.add_odometry(node(s.index, e.i), node(s.index, e.j), e.T_i_j, e.information)
        for e in s.loops:
            graph.add_loop(node(s.index, e.i), node(s.index, e.j), e.T_i_j, e.information)
    n_intra = sum(len(s.loops) for s in kept_sessions)
    used = []
    for i, lp in enumerate(loops):
        if lp.a in anchors_.T_ref_session and lp.b in anchors_.T_ref_session:
            graph.add_loop(node(lp.a, lp.match), node(lp.b, lp.query), lp.T_match_query,
                           lp.information)
            used.append(i)
    graph.solve(robust="gnc", init="file")
    inlier = graph.summary.inlier
    loop_flags = [flag for e, flag in zip(graph.edges, inlier) if e.is_loop]
    intra_flags, inter_flags = loop_flags[:n_intra], loop_flags[n_intra:]
    kept: list[bool | None] = [None] * len(loops)
    for i, flag in zip(used, inter_flags):
        kept[i] = bool(flag)
    est = graph.estimate
    T = {s.index: np.stack([est[node(s.index, k)] for k in range(len(s))])
         for s in kept_sessions}
    log.info("joint solve: %d sessions, %d of %d loops between them kept, %d of %d within",
             len(kept_sessions), sum(bool(f) for f in inter_flags), len(inter_flags),
             sum(intra_flags), n_intra)
    return JointSolution(T, kept, int(sum(intra_flags)), n_intra, graph.summary.seconds)
