"""`lidar-slam optimize`: read a g2o pose graph, run Levenberg-Marquardt, write the result."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.io.g2o import read_g2o

log = logging.getLogger(__name__)

# The prior on the first node, as in gtsam's Pose2/Pose3SLAMExample_g2o.py (variances 1e-6 rad^2
# and 1e-4 m^2 in 3D; 1e-6 m^2 and 1e-8 rad^2 in 2D). It sits at the node's initial pose, so it
# only fixes the gauge and adds ~0 to the error.
PRIOR_SIGMAS = {3: (float(np.degrees(1e-3)), 1e-2), 2: (float(np.degrees(1e-4)), 1e-3)}


@dataclass(frozen=True)
class G2oOptimizeReport:
    """gtsam errors (prior on the first node included) before/after LM, sizes, and timings (s)."""

    in_path: str
    out_path: str | None
    dims: int
    n_vertices: int
    n_edges: int
    n_loop_edges: int
    robust: str
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    load_seconds: float


def optimize_g2o(in_path: str | Path, out_path: str | Path | None,
                 robust: Literal["huber", "none"] = "none", huber_k: float = 1.345,
                 max_iterations: int = 100) -> G2oOptimizeReport:
    """Optimise a g2o file from its vertices (or chained odometry); Huber only on loop edges."""
    if robust not in ("huber", "none"):
        raise ValueError(f"robust must be 'huber' or 'none', got {robust!r}")
    t0 = time.perf_counter()
    g2o = read_g2o(in_path)
    graph = PoseGraph.from_g2o(g2o, robust_k=huber_k if robust == "huber" else None)
    first = min(g2o.poses)
    rot_sigma_deg, trans_sigma_m = PRIOR_SIGMAS[g2o.dims]
    graph.add_prior(first, g2o.poses[first], rot_sigma_deg, trans_sigma_m)
    load_seconds = time.perf_counter() - t0
    graph.optimize(max_iterations)
    summary = graph.summary
    assert summary is not None
    if out_path is not None:
        graph.write_g2o(out_path)
    report = G2oOptimizeReport(
        in_path=str(in_path), out_path=None if out_path is None else str(out_path),
        dims=g2o.dims, n_vertices=len(g2o.poses), n_edges=len(g2o.edges),
        n_loop_edges=sum(e.is_loop for e in graph.edges), robust=robust,
        initial_error=summary.initial_error, final_error=summary.final_error,
        iterations=summary.iterations, seconds=summary.seconds, load_seconds=load_seconds)
    log.info("%s: %dD, %d vertices, %d edges: error %.6g -> %.6g (%d iterations, %.2f s)",
             in_path, report.dims, report.n_vertices, report.n_edges, report.initial_error,
             report.final_error, report.iterations, report.seconds)
    return report
