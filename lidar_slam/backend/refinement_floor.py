"""Lidar only, on a drive: the covariances with the odometry edges' rotation floor taken from the
run's own refinement at speed instead of a constant.

Each odometry edge's covariance is its registration's (frontend.edge_information) plus a floor
of `min_rot_sigma_deg` per rotation axis: what no Hessian sees (deskew, calibration,
quantisation). On a drive that floor is what the position covariance grows by, and one constant
does not fit every car: on the bank's four car rows a good OS0 odometry is 4x looser than its
error at 0.1 deg while a VLP-16's is about right (docs/bank.md, Decisions). A drive measures it
itself: scans at a lasting speed are refined against the last keyframes (frontend.odometry,
refine_keyframes_at_speed), and each accepted refinement's correction is how far kiss-icp's
rotation strayed from those keyframes on that scan. Their rms per axis matches the truth's
per-edge rotation error on the bank's car rows; their mean says which drives carry a bias.

So when at least `floor_from_refinement_scans` scans were refined at speed, the covariances
are computed again from the final graph (its poses, loops and kernels as solved) with:

- each measured odometry edge's rotation floor swapped for sigma = the largest per-axis rms of
  the corrections, on every axis (the yaw corrections of a car are small even where its yaw
  error is not: the keyframes share it);
- a constant rotation bias per scan of `refinement_bias_fraction` x their mean, per axis, as a
  consider parameter: each edge turns by (its scans) x bias, the solution's sensitivity to it
  comes from the linearised graph (two sparse solves per axis), and each node's covariance gains
  J diag(sd^2) J^T. The fraction is what the refinement leaves of the bias it corrects (on the
  bank's most biased drive, car05-vlp16, 3.0 of 29 deg of pitch);
- the a posteriori variance factor of the new weights (at least 1, from the kept loops).

The poses stay the solve's (with min_rot_sigma_deg): this changes what the run says about them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidar_slam.backend.factors import BetweenFactor, PriorFactor
from lidar_slam.geometry import matrix_from_rotvec

STEP_RAD = 1e-6  # the bias per scan by which the sensitivity is taken (the graph is linear there)


@dataclass(frozen=True)
class RefinementFloor:
    """What the run's refinement at speed measured: scans, and per axis the mean and rms of the
    rotation corrections (rad, rotation vectors in the scan's frame)."""

    scans: int
    mean_rad: np.ndarray
    rms_rad: np.ndarray

    @classmethod
    def from_sums(cls, n: int, total: np.ndarray, squares: np.ndarray) -> RefinementFloor:
        n = int(n)
        d = max(n, 1)
        return cls(n, np.asarray(total, float) / d, np.sqrt(np.asarray(squares, float) / d))

    def floor_rad(self) -> float:
        return float(self.rms_rad.max())


def floored_edges(edges: list[BetweenFactor], measured: set[int], old_floor_rad: float,
                  new_floor_rad: float) -> list[BetweenFactor]:
    """edges with the rotation floor of each measured odometry edge (its second key in
    measured) swapped: covariance - old^2 + new^2 on the rotation diagonal; an edge where that
    would not stay positive definite is kept as it is."""
    out = []
    shift = np.diag([new_floor_rad ** 2 - old_floor_rad ** 2] * 3 + [0.0] * 3)
    for e in edges:
        if e.is_loop or e.j not in measured:
            out.append(e)
            continue
        cov = np.linalg.inv(e.information) + shift
        cov = 0.5 * (cov + cov.T)
        if np.linalg.eigvalsh(cov).min() <= 0.0:
            out.append(e)
            continue
        info = np.linalg.inv(cov)
        out.append(replace(e, information=0.5 * (info + info.T)))
    return out


def bias_sensitivity(priors: list[PriorFactor], edges: list[BetweenFactor],
                     poses: dict[int, np.ndarray], scans: dict[int, int],
                     bias_sd_rad: np.ndarray) -> dict[int, np.ndarray]:
    """Each node's (6, 3) change of the solution (tangent, rotation first, its own frame) for a
    constant rotation bias per scan of one sd on each axis, on every odometry edge: the edge
    into j turns by scans[j] x bias. Taken from the linearised graph's solution, which is linear
    in the edges' measurements there."""
    from lidar_slam.backend import gtsam_graph

    base = gtsam_graph.linear_step(3, priors, edges, poses)
    out = {k: np.zeros((6, 3)) for k in base}
    for axis in range(3):
        sd = float(bias_sd_rad[axis])
        if sd == 0.0:
            continue
        turned = []
        for e in edges:
            if e.is_loop or e.j not in scans:
                turned.append(e)
                continue
            T = np.eye(4)
            rv = np.zeros(3)
            rv[axis] = scans[e.j] * STEP_RAD
            T[:3, :3] = matrix_from_rotvec(rv)
            turned.append(replace(e, T_i_j=e.T_i_j @ T))
        step = gtsam_graph.linear_step(3, priors, turned, poses)
        for k in out:
            out[k][:, axis] = (step[k] - base[k]) / STEP_RAD * sd
    return out


def bias_covariance(priors: list[PriorFactor], edges: list[BetweenFactor],
                    poses: dict[int, np.ndarray], scans: dict[int, int],
                    bias_sd_rad: np.ndarray) -> dict[int, np.ndarray]:
    """Each node's covariance (6x6, rotation first, its own frame) from a constant rotation bias
    per scan, sd bias_sd_rad per axis (independent): J J^T of bias_sensitivity."""
    return {k: J @ J.T for k, J in bias_sensitivity(priors, edges, poses, scans,
                                                     bias_sd_rad).items()}


def refloored(priors: list[PriorFactor], edges: list[BetweenFactor],
              poses: dict[int, np.ndarray], measured: set[int], scans: dict[int, int],
              old_floor_rad: float, floor: RefinementFloor, bias_fraction: float
              ) -> dict[int, np.ndarray]:
    """The nodes' marginal covariances of the graph (priors; edges as the covariances weigh them:
    odometry and the kept loops with their kernels) at the poses, with the refinement's floor
    and bias (module doc), scaled by the new weights' variance factor."""
    from lidar_slam.backend import gtsam_graph
    from lidar_slam.backend.slam_backend import variance_factor

    edges = floored_edges(edges, measured, old_floor_rad, floor.floor_rad())
    covs = gtsam_graph.marginal_covariances(3, priors, edges, poses)
    factor = variance_factor(edges, poses)
    bias = bias_covariance(priors, edges, poses, scans,
                           np.abs(bias_fraction * floor.mean_rad)) if bias_fraction else {}
    return {k: factor * c + bias.get(k, 0.0) for k, c in covs.items()}
