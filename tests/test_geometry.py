"""SE(3) helpers against scipy's reference implementation."""

import numpy as np
from scipy.spatial.transform import Rotation

from lidar_slam import geometry as g


def test_quaternion_and_rotvec_conversions_match_scipy():
    R = Rotation.random(200, random_state=0)
    mats = R.as_matrix()
    q = g.quat_from_matrix(mats)
    ref = R.as_quat()
    ref = ref * np.where(ref[:, 3:4] < 0, -1, 1)
    np.testing.assert_allclose(q, ref, atol=1e-12)
    np.testing.assert_allclose(g.matrix_from_quat(q), mats, atol=1e-12)
    np.testing.assert_allclose(g.rotvec_from_matrix(mats), R.as_rotvec(), atol=1e-10)
    for rv in R.as_rotvec()[:20]:
        np.testing.assert_allclose(g.matrix_from_rotvec(rv), Rotation.from_rotvec(rv).as_matrix(),
                                   atol=1e-12)


def test_small_rotation_angle_is_exact():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0, 0, np.radians(0.01)]).as_matrix()
    assert abs(g.rotation_angle_deg(T) - 0.01) < 1e-9


def test_rotvec_and_angle_are_exact_from_tiny_angles_to_pi():
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(600, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([10.0 ** rng.uniform(-9, -2, 200), rng.uniform(0, 3.0, 200),
                             rng.uniform(3.0, np.pi, 199), [np.pi]])
    rv = axes * angles[:, None]
    mats = Rotation.from_rotvec(rv).as_matrix()
    got = g.rotvec_from_matrix(mats)
    # at pi the axis's sign is either
    err = np.minimum(np.abs(got - rv).max(axis=1), np.abs(got + rv).max(axis=1))
    assert err.max() < 1e-12 * 10  # the small ones to ~1e-20, relative
    assert (np.abs(got - rv).max(axis=1)[angles < 1e-2] < 1e-15 * angles[angles < 1e-2]).all()
    T = np.tile(np.eye(4), (len(mats), 1, 1))
    T[:, :3, :3] = mats
    np.testing.assert_allclose(np.radians(g.rotation_angle_deg(T)), angles, rtol=1e-12,
                               atol=1e-15)
    assert g.rotvec_from_matrix(mats[5]).shape == (3,) and np.ndim(g.rotation_angle_deg(T[5])) == 0


def test_inverse_relative_and_interpolate():
    rng = np.random.default_rng(0)
    A = g.make_pose(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3))
    B = g.make_pose(Rotation.random(random_state=2).as_matrix(), rng.normal(size=3))
    np.testing.assert_allclose(g.inverse(A) @ A, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(A @ g.relative(A, B), B, atol=1e-12)
    np.testing.assert_allclose(g.interpolate(A, B, 0.0), A, atol=1e-12)
    np.testing.assert_allclose(g.interpolate(A, B, 1.0), B, atol=1e-12)
    np.testing.assert_allclose(g.from_xyz_quat(g.to_xyz_quat(A)), A, atol=1e-12)


def test_slerp_and_rodrigues_equal_scipys():
    """geometry.Slerp (the IMU check's rotation between frames) and the vectorised Rodrigues
    helpers are scipy's Slerp / Rotation.from_rotvec, on knots, between them, at the ends, for
    zero and tiny turns; times outside the knots are refused as scipy refuses them."""
    import pytest
    from scipy.spatial.transform import Slerp

    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.01, 0.2, 40))
    R = Rotation.random(40, random_state=3).as_matrix()
    R[5] = R[4]  # an interval without a turn
    tq = np.concatenate([rng.uniform(t[0], t[-1], 500), t])
    v = rng.normal(size=(len(tq), 3))
    want = Slerp(t, Rotation.from_matrix(R))(tq)
    ours = g.Slerp(t, R)
    assert np.allclose(ours.apply(tq, v), want.apply(v), atol=1e-13)
    assert np.allclose(ours.matrices(tq), want.as_matrix(), atol=1e-13)
    with pytest.raises(ValueError):
        ours.apply(np.array([t[0] - 1e-3]), v[:1])
    rv = rng.normal(size=(60, 3)) * 2.0
    rv[0], rv[1] = 0.0, 1e-14
    assert np.allclose(g.matrices_from_rotvecs(rv), Rotation.from_rotvec(rv).as_matrix(),
                       atol=1e-14)
    assert np.allclose(g.rotate_by_rotvec(rv, v[:60]), Rotation.from_rotvec(rv).apply(v[:60]),
                       atol=1e-13)


def test_between_error_equals_gtsams():
    """The loop worker's NumPy between_error is gtsam's BetweenFactorPose3 error: large turns,
    near pi, tiny and zero turns."""
    import gtsam

    from lidar_slam.backend import gtsam_graph

    rng = np.random.default_rng(11)

    def pose(rotvec, t):
        return gtsam.Pose3.Expmap(np.concatenate([rotvec, t])).matrix()

    cases = []
    for _ in range(300):
        a = pose(rng.normal(size=3), rng.normal(size=3) * 5)
        b = pose(rng.normal(size=3), rng.normal(size=3) * 5)
        cases.append((np.linalg.inv(a) @ b @ pose(rng.normal(size=3) * 0.05,
                                                  rng.normal(size=3) * 0.2), a, b))
    for angle in (0.0, 1e-12, 1e-9, 1e-6, 1e-3, 3.0, np.pi - 1e-6):
        axis = rng.normal(size=3)
        cases.append((pose(angle * axis / np.linalg.norm(axis), rng.normal(size=3) * 3),
                      np.eye(4), np.eye(4)))
    for T_i_j, T_w_i, T_w_j in cases:
        want = gtsam_graph.between_error(T_i_j, T_w_i, T_w_j)
        assert np.allclose(g.between_error(T_i_j, T_w_i, T_w_j), want, rtol=0, atol=1e-11)
