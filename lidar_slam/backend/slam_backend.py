"""The pipeline's back-end stage: it owns the keyframe pose graph.

Keyframes arrive with their odometry poses and become nodes joined by odometry edges; verified
loops arrive as LoopConstraints and become Huber-robust edges. The graph is kept solved
incrementally (gtsam ISAM2), so that neither a keyframe nor a loop costs more as the drive grows;
the final poses come from one full Levenberg-Marquardt solve of the complete graph, started at
the incremental estimate.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.config import BackendConfig
from lidar_slam.geometry import relative
from lidar_slam.types import LoopConstraint

log = logging.getLogger(__name__)
UPDATE_EVERY = 25  # keyframes without a loop between incremental updates


class Backend:
    """Keyframe pose graph: add_keyframe / add_loop, update() (incremental), finish() (full)."""

    def __init__(self, cfg: BackendConfig):
        from lidar_slam.backend.gtsam_graph import Incremental  # gtsam: imported when needed

        self.cfg = cfg
        self.graph = PoseGraph()  # every factor, as records (graph.g2o, the final solve)
        self._solver = Incremental(3)
        self._n_priors = self._n_edges = 0
        self._last: tuple[int, np.ndarray] | None = None  # (id, T_world_kf_odom) of the newest
        self._new_nodes: dict[int, np.ndarray] = {}
        self._loops_pending = 0
        self.constraints: list[LoopConstraint] = []  # every loop added, in order
        self.loop_update_s: list[tuple[int, float]] = []  # (keyframe id, seconds) per loop update

    def __len__(self) -> int:
        return len(self.graph.estimate)

    def add_keyframe(self, kf_id: int, T_world_kf_odom: np.ndarray) -> None:
        """A new node, joined to the previous keyframe by its odometry (the first gets a prior)."""
        b = self.cfg
        if self._last is None:
            self.graph.add_prior(kf_id, T_world_kf_odom, b.prior_rot_sigma_deg,
                                 b.prior_trans_sigma_m)
            T_init = T_world_kf_odom
        else:
            prev_id, T_prev = self._last
            T_prev_kf = relative(T_prev, T_world_kf_odom)
            self.graph.add_odometry(prev_id, kf_id, T_prev_kf, rot_sigma_deg=b.odom_rot_sigma_deg,
                                    trans_sigma_m=b.odom_trans_sigma_m)
            T_init = self._current(prev_id) @ T_prev_kf
        self.graph.set_initial(kf_id, T_init)
        self._new_nodes[kf_id] = T_init
        self._last = (kf_id, np.array(T_world_kf_odom))

    def _current(self, kf_id: int) -> np.ndarray:
        if kf_id in self._new_nodes:
            return self._new_nodes[kf_id]
        return self._solver.pose(kf_id)

    def add_loop(self, c: LoopConstraint) -> None:
        """A verified loop: Huber-robust edge T_match_query with the constraint's information."""
        self.graph.add_loop(c.match, c.query, c.T_match_query, c.information,
                            robust_k=self.cfg.huber_k)
        self.constraints.append(c)
        self._loops_pending += 1

    def update(self, force: bool = True) -> None:
        """Fold the new keyframes and loops into the incremental solution; force=False only does
        so when a loop is waiting or UPDATE_EVERY keyframes are (a chain of odometry edges needs
        no solving: new nodes start at their odometry, chained onto the last estimate)."""
        if not self._new_nodes and not self._loops_pending:
            return
        if not force and not self._loops_pending and len(self._new_nodes) < UPDATE_EVERY:
            return
        t0 = time.perf_counter()
        priors = self.graph.priors[self._n_priors:]
        edges = self.graph.edges[self._n_edges:]
        self._solver.add(priors, edges, self._new_nodes)
        # A loop moves many nodes far from their linearisation point: a few more steps.
        self._solver.update(extra_iterations=3 if self._loops_pending else 0)
        self._n_priors, self._n_edges = len(self.graph.priors), len(self.graph.edges)
        if self._loops_pending:
            self.loop_update_s.append((max(self._new_nodes, default=-1) if self._new_nodes
                                       else self._last[0], time.perf_counter() - t0))
        self._new_nodes = {}
        self._loops_pending = 0

    def poses(self) -> dict[int, np.ndarray]:
        """Current (incremental) estimate T_world_kf of every keyframe."""
        self.update()
        return self._solver.estimate()

    def finish(self) -> dict[int, np.ndarray]:
        """Final poses: a full Levenberg-Marquardt solve of the complete graph from the
        incremental estimate (the graph's estimate is replaced by the result)."""
        if not len(self.graph.edges) and not self.graph.priors:
            return {}
        for key, T in self.poses().items():
            self.graph.set_initial(key, T)
        if not any(e.is_loop for e in self.graph.edges):
            return self.graph.estimate  # a chain: the incremental solution is exact
        return self.graph.optimize(self.cfg.max_iterations)
