"""tools/check_reference.py: is a reference trajectory consistent with its own scans?

On the real Ouster set the reference is ~7 cm off at its loop: independent registrations started
at the reference relative pose all move that far on loop pairs, and stay within ~2 cm on control
pairs with the same viewpoint change a few frames apart. Issue 3's "agrees with the reference"
line rests on this, so it is pinned here.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from lidar_slam.geometry import inverse, make_pose, yaw_matrix
from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import read_kitti_poses


def load_tool():
    return importlib.import_module("tools.forensics.check_reference")


def _square(n: int = 40, side_m: float = 5.0) -> np.ndarray:
    """A closed square drive, n poses, heading along the path."""
    poses, per = [], n // 4
    corners = [(0, 0), (side_m, 0), (side_m, side_m), (0, side_m)]
    for k in range(4):
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
        for s in np.arange(per) / per:
            T = yaw_matrix(np.pi / 2 * k)
            T[:3, 3] = [x0 + s * (x1 - x0), y0 + s * (y1 - y0), 0.0]
            poses.append(T)
    return np.stack(poses)


def test_close_reference_loop_removes_injected_drift():
    tool = load_tool()
    truth = _square()
    # A reference that drifts: each step gains 0.5 % length and 0.05 deg of yaw.
    steps = [inverse(truth[i - 1]) @ truth[i] for i in range(1, len(truth))]
    ref = [truth[0]]
    for T in steps:
        T = T.copy()
        T[:3, 3] *= 1.005
        ref.append(ref[-1] @ T @ yaw_matrix(np.radians(0.05)))
    ref = np.stack(ref)
    q, m = len(truth) - 1, 0
    loop = [(m, q, inverse(truth[m]) @ truth[q])]  # the true loop relative pose
    closed = tool.close_reference_loop(ref, loop)

    def end_gap(P):
        return float(np.linalg.norm((inverse(P[m]) @ P[q])[:3, 3] - loop[0][2][:3, 3]))

    assert end_gap(ref) > 0.05
    assert end_gap(closed) < 0.01
    assert np.allclose(closed[0], ref[0], atol=1e-4)


def test_orthonormalize():
    tool = load_tool()
    T = make_pose(yaw_matrix(0.3)[:3, :3], [1.0, 2.0, 3.0])
    T[0, 1] += 1e-6
    fixed = tool.orthonormalize(T[None])[0]
    assert np.allclose(fixed[:3, :3] @ fixed[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.allclose(fixed, T, atol=1e-5)


@pytest.mark.shared_data
@pytest.mark.slow
def test_ouster_reference_is_off_at_its_loop_not_elsewhere(ouster_loop):
    tool = load_tool()
    ref = tool.orthonormalize(read_kitti_poses(ouster_loop / "poses.txt"))
    scans = [s.points[:, :3].astype(np.float64) for s in open_source(ouster_loop).scans()]

    def moves(q, m):
        res = tool.register_pair(scans, ref, q - 100, m - 100, ("kiss", "submap"))
        T_ref = inverse(ref[m - 100]) @ ref[q - 100]
        return [tool._move(T_ref, T)[0] for T in res.values()]

    # Loop pair: 2.4 m apart, 88 deg of heading, 60 frames of path in between.
    assert min(moves(173, 113)) > 0.05
    # Control: 3.2 m apart, 99 deg of heading, 5 frames of path in between.
    assert max(moves(133, 128)) < 0.02
