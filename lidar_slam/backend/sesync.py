"""SE-Sync's objective (Rosen et al., IJRR 2019, eq. 12), so a solution can be compared with the
certified optima SE-Sync publishes (../shared/data/posegraphs/reference_costs.tsv).

    F = sum_ij kappa_ij * ||R_j - R_i Rt_ij||_F^2 + tau_ij * ||t_j - t_i - R_i tt_ij||^2

with isotropic weights taken from each edge's information matrix as SE-Sync's read_g2o_file does:
2D tau = 2 / trace(inv(I_xy)), kappa = I_theta_theta; 3D tau = 3 / trace(inv(I_t)),
kappa = 3 / (2 trace(inv(I_R))). It is not gtsam's error (0.5 * sum of whitened squares with the
full information and the geodesic rotation error): the two are only comparable within a few %.
Pure NumPy; information in gtsam tangent order (3D rotation first, 2D x y theta).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np


class _Edge(Protocol):
    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray


def sesync_weights(information: np.ndarray, dims: int) -> tuple[np.ndarray, np.ndarray]:
    """(kappa, tau) per edge from information matrices stacked as (E, n, n), gtsam order."""
    info = np.asarray(information, dtype=np.float64)
    if dims == 2:
        kappa = info[:, 2, 2]
        tau = 2.0 / np.trace(np.linalg.inv(info[:, :2, :2]), axis1=1, axis2=2)
    else:
        kappa = 3.0 / (2.0 * np.trace(np.linalg.inv(info[:, :3, :3]), axis1=1, axis2=2))
        tau = 3.0 / np.trace(np.linalg.inv(info[:, 3:, 3:]), axis1=1, axis2=2)
    return kappa, tau


def sesync_objective(dims: int, edges: Sequence[_Edge], poses: Mapping[int, np.ndarray],
                     keep: np.ndarray | None = None) -> float:
    """SE-Sync's objective F at poses T_world_node (homogeneous, 3x3 or 4x4); only the edges
    where keep is True (all when None)."""
    if keep is not None:
        edges = [e for e, k in zip(edges, keep, strict=True) if k]
    if not edges:
        return 0.0
    d = dims
    i = np.array([e.i for e in edges])
    j = np.array([e.j for e in edges])
    T_ij = np.stack([e.T_i_j for e in edges])
    kappa, tau = sesync_weights(np.stack([e.information for e in edges]), dims)
    keys = np.array(sorted(poses))
    T = np.stack([poses[k] for k in keys])
    ii, jj = np.searchsorted(keys, i), np.searchsorted(keys, j)
    R_i, t_i = T[ii, :d, :d], T[ii, :d, d]
    R_j, t_j = T[jj, :d, :d], T[jj, :d, d]
    rot = R_j - R_i @ T_ij[:, :d, :d]
    trans = t_j - t_i - np.einsum("eab,eb->ea", R_i, T_ij[:, :d, d])
    return float(np.sum(kappa * np.sum(rot**2, axis=(1, 2))) + np.sum(tau * np.sum(trans**2, 1)))


def sesync_information(information: np.ndarray, dims: int) -> np.ndarray:
    """Isotropic information (E, n, n), gtsam order, whose gtsam error is SE-Sync's objective
    for small rotation errors: ||R - I||_F^2 = 2 theta^2 per rotation axis, so the rotation
    precision is 4 kappa; the translation precision is 2 tau (gtsam's error has a 1/2)."""
    kappa, tau = sesync_weights(information, dims)
    if dims == 2:
        diag = np.stack([2 * tau, 2 * tau, 4 * kappa], axis=1)
    else:
        diag = np.concatenate([np.repeat(4 * kappa[:, None], 3, 1),
                               np.repeat(2 * tau[:, None], 3, 1)], axis=1)
    return diag[:, :, None] * np.eye(diag.shape[1])[None]
