"""`lidar-slam optimize`: read a g2o pose graph, initialise (file / chordal / LAGO), optimise (LM,
Huber or GNC on loop edges), certify the rotations where Shonan can, write the result."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from lidar_slam.backend.pose_graph import Init, PoseGraph, Robust
from lidar_slam.backend.sesync import sesync_information, sesync_objective
from lidar_slam.io.g2o import G2oEdge, read_g2o

log = logging.getLogger(__name__)

# The prior on the first node, as in gtsam's Pose2/Pose3SLAMExample_g2o.py (variances 1e-6 rad^2
# and 1e-4 m^2 in 3D; 1e-6 m^2 and 1e-8 rad^2 in 2D). It sits at the node's initial pose, so it
# only fixes the gauge and adds ~0 to the error.
PRIOR_SIGMAS = {3: (float(np.degrees(1e-3)), 1e-2), 2: (float(np.degrees(1e-4)), 1e-3)}
# certify="auto" runs Shonan on graphs up to this many nodes: started at the solution's rotations
# it takes ~0.6 s on sphere2500 (2500 nodes) but tens of seconds on the 10k-15k node graphs.
CERTIFY_MAX_NODES = 6000

Certify = Literal["auto", "on", "off"]
Weights = Literal["file", "sesync"]


@dataclass(frozen=True)
class G2oOptimizeReport:
    """gtsam errors (prior on the first node included) at the file's guess and after the solve,
    SE-Sync's objective of the solution, sizes, the start kept and every start tried, Shonan's
    rotation certificate (None: not run), and timings (s: seconds = initialisation + solves)."""

    in_path: str
    out_path: str | None
    dims: int
    n_vertices: int
    n_edges: int
    n_loop_edges: int
    n_repaired: int
    robust: str
    init: str
    candidates: tuple[tuple[str, float | None], ...]
    initial_error: float
    final_error: float
    sesync_objective: float
    n_loops_rejected: int  # GNC: weight 0; none/Huber: residual beyond GNC's inlier threshold
    iterations: int | None
    seconds: float
    load_seconds: float
    certificate: object | None = None  # gtsam_graph.RotationCertificate
    certify_seconds: float = 0.0
    cpu_seconds: float = 0.0  # process CPU time of the solve (wall time varies with load)


def optimize_g2o(in_path: str | Path, out_path: str | Path | None, robust: Robust = "none",
                 huber_k: float = 1.345, max_iterations: int = 100, init: Init = "file",
                 certify: Certify = "off", weights: Weights = "file") -> G2oOptimizeReport:
    """Optimise a g2o file from its vertices (or chained odometry) and/or a global initialisation;
    the kernel (Huber, or GNC with odometry as known inliers) acts on loop edges only.
    weights="sesync" replaces every information matrix by SE-Sync's isotropic weights, so the
    problem solved is SE-Sync's own (its optimum is the published p*)."""
    if certify not in ("auto", "on", "off"):
        raise ValueError(f"certify must be auto, on or off, got {certify!r}")
    if weights not in ("file", "sesync"):
        raise ValueError(f"weights must be file or sesync, got {weights!r}")
    t0 = time.perf_counter()
    g2o = read_g2o(in_path)
    file_edges = g2o.edges  # SE-Sync's objective and weights come from the file's information
    if weights == "sesync":
        iso = sesync_information(np.stack([e.information for e in g2o.edges]), g2o.dims)
        g2o = replace(g2o, edges=[G2oEdge(e.i, e.j, e.T_i_j, info)
                                  for e, info in zip(g2o.edges, iso, strict=True)])
    graph = PoseGraph.from_g2o(g2o)
    first = min(g2o.poses)
    rot_sigma_deg, trans_sigma_m = PRIOR_SIGMAS[g2o.dims]
    graph.add_prior(first, g2o.poses[first], rot_sigma_deg, trans_sigma_m)
    load_seconds = time.perf_counter() - t0
    cpu0 = time.process_time()
    poses = graph.solve(robust, init, huber_k, max_iterations)
    cpu_seconds = time.process_time() - cpu0
    summary = graph.summary
    assert summary is not None and summary.inlier is not None
    # The objective and the certificate are those of the problem solved: with GNC, the kept edges.
    inlier = np.array(summary.inlier)
    keep = inlier if robust == "gnc" else np.ones(len(inlier), dtype=bool)
    certificate, certify_seconds = None, 0.0
    if certify == "on" or (certify == "auto" and len(poses) <= CERTIFY_MAX_NODES):
        from lidar_slam.backend.gtsam_graph import certify_rotations

        kept = [e for e, k in zip(file_edges, keep, strict=True) if k]
        certificate = certify_rotations(g2o.dims, kept, poses)
        certify_seconds = certificate.seconds
    if out_path is not None:
        graph.write_g2o(out_path)
    report = G2oOptimizeReport(
        in_path=str(in_path), out_path=None if out_path is None else str(out_path),
        dims=g2o.dims, n_vertices=len(g2o.poses), n_edges=len(g2o.edges),
        n_loop_edges=sum(e.is_loop for e in graph.edges), n_repaired=g2o.n_repaired,
        robust=robust, init=summary.init, candidates=summary.candidates,
        initial_error=summary.initial_error, final_error=summary.final_error,
        sesync_objective=sesync_objective(g2o.dims, file_edges, poses, keep),
        n_loops_rejected=int((~inlier).sum()), iterations=summary.iterations,
        seconds=summary.seconds, load_seconds=load_seconds, certificate=certificate,
        certify_seconds=certify_seconds, cpu_seconds=cpu_seconds)
    log.info("%s: %dD, %d vertices, %d edges: error %.6g -> %.6g (init %s, %.2f s)", in_path,
             report.dims, report.n_vertices, report.n_edges, report.initial_error,
             report.final_error, report.init, report.seconds)
    return report
