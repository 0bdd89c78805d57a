"""The pipeline's back-end stage: it owns the keyframe pose graph.

Keyframes arrive with their odometry poses and become nodes joined by odometry edges; verified
loops arrive as LoopConstraints and become Huber-robust edges. While the drive goes on, a loop
corrects the live estimate by Levenberg-Marquardt on a bounded window (the newest
`window_keyframes` keyframes, anchored at the window's first node, with each loop's older match
held where it is), so neither a keyframe nor a loop costs more time or memory as the drive grows;
the final poses come from one full solve of the complete graph (LM with Huber loops, or GNC),
started at the live estimate and at a global (chordal) initialisation, the lower final error
kept. That solve also says which loops the back-end keeps (loop_status).

Why not ISAM2: on a 10,000-scan drive with 2,085 loops, gtsam's ISAM2 grew by ~16 kB per keyframe
(55 MB over 3,376 keyframes) and its per-loop update time grew from 15 to 72 ms (median by thirds
of the drive; tools/backend_replay.py), while the full LM started from plain odometry reaches the
same optimum as one started from ISAM2's estimate (sim 00: identical; the 10,000-scan drive:
within 3 cm, graph error 440.337 vs 440.336).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from lidar_slam.backend.factors import BetweenFactor, PriorFactor, sigmas_to_information
from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.config import BackendConfig
from lidar_slam.geometry import relative
from lidar_slam.types import LoopConstraint

log = logging.getLogger(__name__)
WINDOW_ITERATIONS = 10  # LM iterations of a window solve (the final solve does the rest)
FINAL_RELATIVE_TOL = 1e-9


class Backend:
    """Keyframe pose graph: add_keyframe / add_loop, update() (window), finish() (full)."""

    def __init__(self, cfg: BackendConfig):
        # gtsam now, not at the first loop: importing it adds ~39 MB of RSS and 0.2 s once, and
        # a drive's memory then steps up when it is already under way (on the 10,000-scan drive,
        # at its first loop after frame 2,000, which read as growth).
        from lidar_slam.backend import gtsam_graph  # noqa: F401

        self.cfg = cfg
        self.graph = PoseGraph()  # every factor, as records (graph.g2o, the final solve)
        self._odom = np.empty((0, 4, 4))  # T_world_kf_odom by keyframe id
        self._rel = np.empty((0, 4, 4))  # odometry T_prev_kf by keyframe id
        self._prior_info = sigmas_to_information(cfg.prior_rot_sigma_deg, cfg.prior_trans_sigma_m)
        self._odom_info = sigmas_to_information(cfg.odom_rot_sigma_deg, cfg.odom_trans_sigma_m)
        self._live = np.empty((0, 4, 4))  # current estimate T_world_kf by keyframe id
        self._edge_info: list[np.ndarray] = []  # information of the odometry edge into each id
        self._n = 0
        self._loops_by_query: dict[int, list[LoopConstraint]] = {}
        self._loops_pending = 0
        self.constraints: list[LoopConstraint] = []  # every loop added, in order
        self.loop_update_s: list[tuple[int, float]] = []  # (keyframe id, seconds) per loop update
        # (match, query) keyframe ids -> "inlier" / "rejected", set by finish()
        self.loop_status: dict[tuple[int, int], str] = {}
        self.seconds = {"update": 0.0, "final": 0.0}  # live (window) updates, final solve
        self.final_init = ""  # the start the final solve kept: live / chordal (GNC: odometry)
        # keyframe id -> 6x6 marginal covariance of the final solve (rotation first, rad and m,
        # in the keyframe's frame: T_world_kf_true = T_world_kf @ Exp(xi)), set by finish()
        self.covariances: dict[int, np.ndarray] = {}
        self.variance_factor = 1.0  # the covariances' scale from the loops (_variance_factor)

    def __len__(self) -> int:
        return self._n

    def _grow(self) -> None:
        if self._n == len(self._odom):
            cap = max(64, 2 * self._n)
            for name in ("_odom", "_rel", "_live"):
                buf = np.empty((cap, 4, 4))
                buf[:self._n] = getattr(self, name)[:self._n]
                setattr(self, name, buf)

    def add_keyframe(self, kf_id: int, T_world_kf_odom: np.ndarray,
                     information: np.ndarray | None = None) -> None:
        """A new node, joined to the previous keyframe by its odometry (the first gets a prior)
        with the edge's own information (6x6, rotation first; lidar_slam.frontend.
        edge_information), else the configured sigmas; its live estimate is its odometry chained
        onto the previous keyframe's estimate."""
        if kf_id != self._n:
            raise ValueError(f"keyframe ids must be consecutive: got {kf_id}, expected {self._n}")
        b = self.cfg
        self._grow()
        self._odom[kf_id] = T_world_kf_odom
        if kf_id == 0:
            self.graph.add_prior(kf_id, T_world_kf_odom, b.prior_rot_sigma_deg,
                                 b.prior_trans_sigma_m)
            self._live[0] = T_world_kf_odom
        else:
            T_prev_kf = relative(self._odom[kf_id - 1], T_world_kf_odom)
            self._rel[kf_id] = T_prev_kf
            info = self._odom_info if information is None else information
            self.graph.add_odometry(kf_id - 1, kf_id, T_prev_kf, info)
            self._live[kf_id] = self._live[kf_id - 1] @ T_prev_kf
        self._edge_info.append(self._odom_info if kf_id == 0 else info)
        self._n += 1

    def add_loop(self, c: LoopConstraint) -> None:
        """A verified loop: Huber-robust edge T_match_query with the constraint's information."""
        self.graph.add_loop(c.match, c.query, c.T_match_query, c.information,
                            robust_k=self.cfg.huber_k)
        self.constraints.append(c)
        self._loops_by_query.setdefault(c.query, []).append(c)
        self._loops_pending += 1

    def update(self, force: bool = True) -> None:
        """Correct the live estimate for the loops added since the last update (a chain of
        odometry edges needs no solving); unless forced, only at every
        cfg.update_every_keyframes-th keyframe (by id: the same keyframes in every run)."""
        if not self._loops_pending or self._n == 0:
            return
        if not force and (self._n - 1) % self.cfg.update_every_keyframes:
            return
        t0 = time.perf_counter()
        self._solve_window()
        self.loop_update_s.append((self._n - 1, time.perf_counter() - t0))
        self._loops_pending = 0
        self.seconds["update"] += time.perf_counter() - t0

    def _solve_window(self) -> None:
        """LM over the newest window_keyframes keyframes: odometry edges, the loops whose query
        is in the window, the first node and every older match held at their live estimates.
        Factor records are built directly (no per-factor checks: they were checked on entry)."""
        from lidar_slam.backend import gtsam_graph

        b, last = self.cfg, self._n - 1
        first = max(0, self._n - b.window_keyframes)
        priors = [PriorFactor(first, self._live[first], self._prior_info)]
        edges: list[BetweenFactor] = []
        initial = {first: self._live[first]}
        for k in range(first + 1, last + 1):
            initial[k] = self._live[k]
            edges.append(BetweenFactor(k - 1, k, self._rel[k], self._edge_info[k]))
        for k in range(first, last + 1):
            for c in self._loops_by_query.get(k, ()):
                if c.match not in initial:  # older than the window: held where it is
                    priors.append(PriorFactor(c.match, self._live[c.match], self._prior_info))
                    initial[c.match] = self._live[c.match]
                edges.append(BetweenFactor(c.match, c.query, c.T_match_query, c.information,
                                           b.huber_k, True))
        if not any(e.is_loop for e in edges):
            return  # the loops are older than the window: only the final solve sees them
        res = gtsam_graph.solve(3, priors, edges, initial, WINDOW_ITERATIONS)
        for k in range(first, last + 1):
            self._live[k] = res.poses[k]

    def poses(self) -> dict[int, np.ndarray]:
        """Current (live) estimate T_world_kf of every keyframe."""
        self.update()
        return {k: self._live[k].copy() for k in range(self._n)}

    def state(self) -> np.ndarray:
        """The live estimate (n, 4, 4) with every loop added so far in it, for a checkpoint."""
        self.update()
        return self._live[:self._n].copy()

    def restore_live(self, live: np.ndarray) -> None:
        """Put back a checkpoint's live estimate (after its keyframes and loops are re-added)."""
        if len(live) != self._n:
            raise ValueError(f"live estimate has {len(live)} poses for {self._n} keyframes")
        self._live[:self._n] = live
        self._loops_pending = 0

    def finish(self) -> dict[int, np.ndarray]:
        """Final poses: a full solve of the complete graph (cfg.robust on the loops) from the
        live estimate and, with cfg.global_init, from a chordal initialisation, the lower final
        error kept (the graph's estimate is replaced by the result); GNC starts from the odometry
        (PoseGraph.solve). LM stops at a 1e-9 relative
        error decrease, so the answer does not depend on where it started."""
        if self._n == 0:
            return {}
        self.update()
        for key in range(self._n):
            self.graph.set_initial(key, self._live[key])
        if not self.constraints:
            self._covariances()
            return self.graph.estimate  # a chain: the live estimate is exact
        t0 = time.perf_counter()
        poses = self.graph.solve(self.cfg.robust, "auto" if self.cfg.global_init else "file",
                                 self.cfg.huber_k, self.cfg.max_iterations, given="live",
                                 relative_error_tol=FINAL_RELATIVE_TOL)
        summary = self.graph.summary
        for e, keep in zip(self.graph.edges, summary.inlier, strict=True):
            if e.is_loop:
                self.loop_status[(e.i, e.j)] = "inlier" if keep else "rejected"
        self.seconds["final"] += time.perf_counter() - t0
        self.final_init = summary.init
        log.info("final solve (%s from %s): %d of %d loops rejected, %.2f s", summary.robust,
                 summary.init, sum(s == "rejected" for s in self.loop_status.values()),
                 len(self.loop_status), self.seconds["final"])
        self._covariances()
        return poses

    def final_edges(self) -> list[BetweenFactor]:
        """The graph's edges as the final solve left them: odometry, and the loops it did not
        reject (with their Huber kernel), for a solve with more factors (backend.imu_gnss_solve)."""
        return [e for e in self.graph.edges
                if not e.is_loop or self.loop_status.get((e.i, e.j)) != "rejected"]

    def _covariances(self) -> None:
        t0 = time.perf_counter()
        try:
            self.covariances = self.graph.covariances(self.cfg.robust, self.cfg.huber_k)
        except RuntimeError as exc:  # gtsam: "Indeterminate linear system" on a degenerate graph
            log.warning("covariances not computed (gtsam: %s): the poses are written without "
                        "them (no covariances.csv)", str(exc).strip().splitlines()[0])
            self.covariances = {}
            self.seconds["covariances"] = time.perf_counter() - t0
            return
        self.variance_factor = self._variance_factor()
        if self.variance_factor > 1.0:
            self.covariances = {k: c * self.variance_factor for k, c in self.covariances.items()}
        self.seconds["covariances"] = time.perf_counter() - t0

    def _variance_factor(self) -> float:
        """The final solve's a posteriori variance factor (variance_factor) over the kept edges:
        where the loops show more drift than the edges' information allows (an odometry error
        the clouds cannot see: deskew, calibration), the covariances grow by it; the poses do
        not change."""
        kept = [e for e in self.graph.edges
                if not e.is_loop or self.loop_status.get((e.i, e.j)) == "inlier"]
        return variance_factor(kept, self.graph.estimate)


def variance_factor(kept: list, poses: dict[int, np.ndarray]) -> float:
    """A posteriori variance factor, at least 1: the kept edges' summed squared whitened
    residuals at the poses over the graph's redundancy (6 per kept loop; a chain has none and
    says nothing, 1)."""
    from lidar_slam.backend import gtsam_graph

    n_loops = sum(e.is_loop for e in kept)
    if not n_loops:
        return 1.0
    chi2 = 0.0
    for e in kept:
        err = gtsam_graph.between_error(e.T_i_j, poses[e.i], poses[e.j])
        chi2 += float(err @ e.information @ err)
    log.info("covariances: a posteriori variance factor %.2f (chi2 %.1f, %d loops)",
             chi2 / (6 * n_loops), chi2, n_loops)
    return max(1.0, chi2 / (6 * n_loops))


def chain_covariances(cfg: BackendConfig, T_world_kf: dict[int, np.ndarray],
                      information: dict[int, np.ndarray] | None = None) -> dict[int, np.ndarray]:
    """Marginal covariances (as Backend.covariances) of keyframes joined by odometry alone, as
    in a run without loops: chain_graph's."""
    if not T_world_kf:
        return {}
    return chain_graph(cfg, T_world_kf, information).covariances()


def chain_graph(cfg: BackendConfig, T_world_kf: dict[int, np.ndarray],
                information: dict[int, np.ndarray] | None = None) -> PoseGraph:
    """The first keyframe's prior and one odometry edge per keyframe, with its information
    (keyed by the edge's second keyframe) where given, else the config's sigmas; the nodes at
    T_world_kf."""
    information = information or {}
    graph = PoseGraph()
    keys = sorted(T_world_kf)
    graph.add_prior(keys[0], T_world_kf[keys[0]], cfg.prior_rot_sigma_deg, cfg.prior_trans_sigma_m)
    for a, b in zip(keys[:-1], keys[1:], strict=True):
        if b in information:
            graph.add_odometry(a, b, relative(T_world_kf[a], T_world_kf[b]), information[b])
        else:
            graph.add_odometry(a, b, relative(T_world_kf[a], T_world_kf[b]),
                               rot_sigma_deg=cfg.odom_rot_sigma_deg,
                               trans_sigma_m=cfg.odom_trans_sigma_m)
    for k in keys:
        graph.set_initial(k, T_world_kf[k])
    return graph
