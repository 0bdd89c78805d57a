"""backend.refinement_floor: a drive's covariances with the rotation floor and bias its own
refinement at speed measured."""

import numpy as np
import pytest

from lidar_slam.backend import gtsam_graph
from lidar_slam.backend.factors import BetweenFactor, PriorFactor
from lidar_slam.backend.refinement_floor import (
    RefinementFloor,
    bias_covariance,
    edge_lengths,
    floored_edges,
    refloored,
)


def _step(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def _chain(n: int, length: float, info: np.ndarray):
    """A straight drive along x: n nodes, its prior, its odometry edges."""
    poses = {k: _step(k * length) for k in range(n)}
    priors = [PriorFactor(0, poses[0], np.diag([1e6] * 6))]
    edges = [BetweenFactor(k - 1, k, _step(length), info) for k in range(1, n)]
    return poses, priors, edges


def test_the_floor_is_the_largest_axis_rms_and_the_bias_its_mean_per_metre():
    f = RefinementFloor.from_sums(4, np.array([0.4, -0.2, 0.0]), np.array([0.04, 0.16, 0.01]),
                                  8.0)
    assert f.scans == 4 and f.step_m == pytest.approx(2.0)
    np.testing.assert_allclose(f.mean_rad, [0.1, -0.05, 0.0])
    np.testing.assert_allclose(f.rms_rad, [0.1, 0.2, 0.05])
    assert f.floor_rad() == pytest.approx(0.2)
    assert f.floor_rad(0.3) == pytest.approx(0.3)  # the configured lower bound
    np.testing.assert_allclose(f.bias_per_m(0.1), [0.005, 0.0025, 0.0])
    still = RefinementFloor.from_sums(4, np.ones(3), np.ones(3), 0.0)
    np.testing.assert_array_equal(still.bias_per_m(0.1), 0.0)  # no motion: no bias


def test_only_measured_odometry_edges_have_their_rotation_floor_swapped():
    old, new = np.radians(0.1), np.radians(0.03)
    measured_cov = np.diag([np.radians(0.02) ** 2] * 3 + [0.01 ** 2] * 3)
    measured_cov[0, 4] = measured_cov[4, 0] = 1e-7  # a rotation-translation coupling stays
    floored = measured_cov + np.diag([old ** 2] * 3 + [0.0] * 3)
    info = np.linalg.inv(floored)
    edges = [BetweenFactor(0, 1, _step(1.0), info),
             BetweenFactor(1, 2, _step(1.0), info),  # configured sigmas: not in measured
             BetweenFactor(0, 2, _step(2.0), info, robust_k=1.345, is_loop=True)]
    out = floored_edges(edges, {1}, old, new)
    np.testing.assert_allclose(np.linalg.inv(out[0].information),
                               measured_cov + np.diag([new ** 2] * 3 + [0.0] * 3),
                               rtol=1e-9, atol=1e-18)
    assert out[1] is edges[1] and out[2] is edges[2]
    # a covariance the swap would leave indefinite: the edge as it was
    thin = np.linalg.inv(np.diag([np.radians(0.05) ** 2] * 3 + [0.01 ** 2] * 3))
    edge = BetweenFactor(0, 1, _step(1.0), thin)
    assert floored_edges([edge], {1}, old, new)[0] is edge


def test_a_constant_yaw_bias_bends_a_straight_chain_as_its_sum_says():
    """Every edge of a straight drive of edges L long turned by b L about z (b per metre):
    node k turns by k b L and lies b L^2 k (k - 1) / 2 to the left in its own frame; with sd s
    the covariance is s^2 J J^T with J = L (0, 0, k, 0, L k (k-1) / 2, 0)."""
    n, length, s = 8, 3.0, np.radians(0.01)
    poses, priors, edges = _chain(n, length, np.diag([1e4] * 6))
    lengths = edge_lengths(edges)
    assert lengths == {k: pytest.approx(length) for k in range(1, n)}
    covs = bias_covariance(priors, edges, poses, lengths, np.array([0.0, 0.0, s]))
    for k in range(n):
        J = length * np.array([0.0, 0.0, k, 0.0, length * k * (k - 1) / 2, 0.0])
        np.testing.assert_allclose(covs[k], s ** 2 * np.outer(J, J), rtol=1e-4,
                                   atol=1e-6 * s ** 2)


def test_a_loop_holds_the_bias_back_and_the_same_floor_changes_nothing():
    """With the old floor kept and no bias, refloored gives the graph's own marginals; a loop
    back to the start makes the bias's covariance at the end smaller than the chain's."""
    n, length = 6, 2.0
    info = np.linalg.inv(np.diag([np.radians(0.1) ** 2] * 3 + [0.01 ** 2] * 3))
    poses, priors, edges = _chain(n, length, info)
    old, new, bias = np.radians(0.1), np.radians(0.05), np.array([0.0, 0.0, np.radians(0.005)])
    measured = set(range(1, n))
    plain, factor = refloored(priors, edges, poses, measured, old, old, np.zeros(3))
    assert factor == 1.0  # a chain says nothing about its weights
    marg = gtsam_graph.marginal_covariances(3, priors, edges, poses)
    for k in range(n):
        np.testing.assert_allclose(plain[k], marg[k], rtol=1e-9, atol=1e-15)
    chain, _ = refloored(priors, edges, poses, measured, old, new, bias)
    loop = BetweenFactor(0, n - 1, _step((n - 1) * length), info, is_loop=True)
    closed, factor = refloored(priors, edges + [loop], poses, measured, old, new, bias)
    assert factor == 1.0  # the loop agrees with the chain exactly
    assert closed[n - 1][4, 4] < 0.5 * chain[n - 1][4, 4]
    # the smaller floor tightens a chain's end
    assert chain[n - 1][2, 2] < marg[n - 1][2, 2]
