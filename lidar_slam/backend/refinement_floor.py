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
  error is not: the keyframes share it), at least `refinement_floor_min_deg`;
- a constant rotation bias of `refinement_bias_fraction` x their mean, per axis and per metre
  driven (the mean over the mean motion of those scans: a car standing still does not turn),
  as a consider parameter: each odometry edge turns by its length x bias, the solution's
  sensitivity to it comes from the linearised graph (one sparse solve per axis, and one at the
  poses themselves), and each node's covariance gains J diag(sd^2) J^T. The fraction is what
  the refinement leaves of the bias it corrects (on the bank's most biased drive,
  car05-vlp16, about 3 of 24-29 deg of pitch);
- the a posteriori variance factor of the new weights (at least 1, from the kept loops).

The poses stay the solve's (with min_rot_sigma_deg): this changes what the run says about them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidar_slam.backend.factors import BetweenFactor, PriorFactor
from lidar_slam.geometry import matrix_from_rotvec

STEP_RAD = 1e-6  # the bias (rad per metre) by which the sensitivity is taken (linear there)


@dataclass(frozen=True)
class RefinementFloor:
    """What the run's refinement at speed measured: corrections, per axis the mean and rms of
    their rotations (rad, rotation vectors in the scan's frame), and the scans' mean motion
    (m)."""

    scans: int
    mean_rad: np.ndarray
    rms_rad: np.ndarray
    step_m: float

    @classmethod
    def from_sums(cls, n: int, total: np.ndarray, squares: np.ndarray, metres: float
                  ) -> RefinementFloor:
        n = int(n)
        d = max(n, 1)
        return cls(n, np.asarray(total, float) / d, np.sqrt(np.asarray(squares, float) / d),
                   float(metres) / d)

    def floor_rad(self, min_rad: float = 0.0) -> float:
        return max(float(self.rms_rad.max()), min_rad)

    def bias_per_m(self, fraction: float) -> np.ndarray:
        """The bias's sd per axis (rad per metre): fraction x the mean correction over the mean
        motion; none when the scans did not move."""
        if self.step_m <= 0.0:
            return np.zeros(3)
        return np.abs(fraction * self.mean_rad) / self.step_m


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


def edge_lengths(edges: list[BetweenFactor]) -> dict[int, float]:
    """The odometry edges' lengths (m), keyed by their second key."""
    return {e.j: float(np.linalg.norm(e.T_i_j[:3, 3])) for e in edges if not e.is_loop}


def bias_sensitivity(priors: list[PriorFactor], edges: list[BetweenFactor],
                     poses: dict[int, np.ndarray], lengths: dict[int, float],
                     bias_sd: np.ndarray) -> dict[int, np.ndarray]:
    """Each node's (6, 3) change of the solution (tangent, rotation first, its own frame) for a
    constant rotation bias of one sd on each axis (bias_sd, rad per unit of lengths), on every
    odometry edge: the edge into j turns by lengths[j] x bias. Taken from the linearised graph's
    solution, which is linear in the edges' measurements there."""
    from lidar_slam.backend import gtsam_graph

    if not np.any(bias_sd):
        return {k: np.zeros((6, 3)) for k in poses}
    base = gtsam_graph.linear_step(3, priors, edges, poses)
    out = {k: np.zeros((6, 3)) for k in base}
    for axis in range(3):
        sd = float(bias_sd[axis])
        if sd == 0.0:
            continue
        turned = []
        for e in edges:
            if e.is_loop or e.j not in lengths:
                turned.append(e)
                continue
            T = np.eye(4)
            rv = np.zeros(3)
            rv[axis] = lengths[e.j] * STEP_RAD
            T[:3, :3] = matrix_from_rotvec(rv)
            turned.append(replace(e, T_i_j=e.T_i_j @ T))
        step = gtsam_graph.linear_step(3, priors, turned, poses)
        for k in out:
            out[k][:, axis] = (step[k] - base[k]) / STEP_RAD * sd
    return out


def bias_covariance(priors: list[PriorFactor], edges: list[BetweenFactor],
                    poses: dict[int, np.ndarray], lengths: dict[int, float],
                    bias_sd: np.ndarray) -> dict[int, np.ndarray]:
    """Each node's covariance (6x6, rotation first, its own frame) from a constant rotation bias,
    sd bias_sd per axis (independent): J J^T of bias_sensitivity."""
    return {k: J @ J.T for k, J in bias_sensitivity(priors, edges, poses, lengths,
                                                     bias_sd).items()}


def refloored(priors: list[PriorFactor], edges: list[BetweenFactor],
              poses: dict[int, np.ndarray], measured: set[int], old_floor_rad: float,
              floor_rad: float, bias_sd_per_m: np.ndarray
              ) -> tuple[dict[int, np.ndarray], float]:
    """The nodes' marginal covariances of the graph (priors; edges as the covariances weigh them:
    odometry and the kept loops with their kernels) at the poses, with the measured edges'
    rotation floor floor_rad and a rotation bias of bias_sd_per_m (module doc), the marginals
    scaled by the new weights' variance factor; and that factor."""
    from lidar_slam.backend import gtsam_graph
    from lidar_slam.backend.slam_backend import variance_factor

    edges = floored_edges(edges, measured, old_floor_rad, floor_rad)
    covs = gtsam_graph.marginal_covariances(3, priors, edges, poses)
    factor = variance_factor(edges, poses)
    bias = bias_covariance(priors, edges, poses, edge_lengths(edges), bias_sd_per_m)
    return {k: factor * c + bias.get(k, 0.0) for k, c in covs.items()}, factor
