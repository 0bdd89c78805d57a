"""Loop verification stage: multi-hypothesis ICP and its gates on the real indoor Ouster sequence
(reference poses: line k of poses.txt is file 100 + k), plus the information matrix's layout.

Query clouds are single keyframe clouds (0.5 m voxels, as the pipeline keeps them); match clouds
are submaps of the match scan and its +-2 neighbours merged with the reference poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_slam.config import ScanContextConfig, VerifyConfig
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import (
    inverse,
    make_pose,
    relative,
    rotation_angle_deg,
    transform_points,
    yaw_matrix,
    yaw_rad,
)
from lidar_slam.io.pointcloud import read_cloud
from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.loop.scan_context import align, describe, shift_to_yaw
from lidar_slam.loop.verify import information_matrix, match_side, query_side, verify
from lidar_slam.registration import level_ground
from lidar_slam.types import LoopCandidate

TRUE_PAIRS = [(175, 108), (172, 109), (168, 113), (176, 114)]  # 2.2-4.1 m apart
# Far apart in the reference, or places where ICP slides to a wrong pose 6-7 m off along the
# hall with a plausible fitness (found by tools/loop_tuning.py sweep).
WRONG_PAIRS = [(150, 100), (130, 100), (162, 124), (163, 100), (162, 100), (138, 111),
               (157, 129)]


class Ouster:
    def __init__(self, root: Path):
        self.root = root
        self.poses = read_kitti_poses(root / "poses.txt")
        self._clouds: dict[int, np.ndarray] = {}

    def cloud(self, frame: int) -> np.ndarray:
        """Keyframe cloud in its sensor frame: range <= 60 m, 0.5 m voxels."""
        if frame not in self._clouds:
            pts = read_cloud(self.root / "scans" / f"{frame:06d}.bin").points
            pts = pts[np.linalg.norm(pts, axis=1) <= 60.0]
            self._clouds[frame] = voxel_downsample(pts, 0.5)[0]
        return self._clouds[frame]

    def pose(self, frame: int) -> np.ndarray:
        return self.poses[frame - 100]

    def submap(self, frame: int, radius: int = 2) -> np.ndarray:
        """Scans frame-radius..frame+radius merged into frame's sensor frame."""
        frames = range(max(100, frame - radius), min(176, frame + radius) + 1)
        return np.vstack([transform_points(relative(self.pose(frame), self.pose(f)), self.cloud(f))
                          for f in frames])

    def T_match_query(self, query: int, match: int) -> np.ndarray:
        return relative(self.pose(match), self.pose(query))

    def errors(self, T: np.ndarray, query: int, match: int) -> tuple[float, float]:
        d = inverse(self.T_match_query(query, match)) @ T
        return float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d))

    def levelled_yaw(self, query: int, match: int) -> float:
        """Reference yaw of T_match_query about the fitted ground normals (as verify uses it)."""
        L_q = make_pose(level_ground(self.cloud(query)).R_level_sensor, np.zeros(3))
        L_m = make_pose(level_ground(self.submap(match)).R_level_sensor, np.zeros(3))
        return yaw_rad(L_m @ self.T_match_query(query, match) @ inverse(L_q))


@pytest.fixture(scope="module")
def data() -> Ouster:
    from conftest import shared_path

    return Ouster(shared_path("ouster_os0_loop_balm"))


def sc_candidate(data: Ouster, query: int, match: int) -> LoopCandidate:
    """The candidate scan context would produce (its yaw guess is often off by ~90 deg here)."""
    cfg = ScanContextConfig(max_radius_m=30.0)
    dist, shift = align(describe(data.cloud(query), cfg), describe(data.cloud(match), cfg),
                        cfg.local_search_sectors)
    return LoopCandidate(query, match, dist, shift_to_yaw(shift, cfg.sectors))


@pytest.mark.shared_data
@pytest.mark.parametrize("query,match", TRUE_PAIRS)
def test_true_loops_are_accepted_with_the_reference_relative_pose(data, query, match):
    cfg = VerifyConfig()
    res = verify(sc_candidate(data, query, match), data.cloud(query), data.submap(match), cfg)
    assert res.accepted, res.reason
    assert res.reason == ""
    err_m, err_deg = data.errors(res.constraint.T_match_query, query, match)
    assert err_m < 1.0 and err_deg < 5.0
    assert res.fitness >= cfg.min_fitness and res.margin >= cfg.min_margin
    c = res.constraint
    assert (c.query, c.match) == (query, match)
    info = c.information
    assert info.shape == (6, 6)
    np.testing.assert_allclose(info, info.T)
    assert np.linalg.eigvalsh(info).min() > 0
    assert not np.allclose(info / info[0, 0], np.eye(6))
    std = np.sqrt(np.diag(np.linalg.inv(info)))
    # Each block scaled so that its best-constrained axis sits exactly at its floor.
    floor_r, floor_t = np.radians(cfg.info_min_rot_sigma_deg), cfg.info_min_trans_sigma_m
    assert std[:3].min() == pytest.approx(floor_r, rel=1e-6)
    assert std[3:].min() == pytest.approx(floor_t, rel=1e-6)
    assert std[3:].max() < 0.5  # a real room constrains every translation


@pytest.mark.shared_data
@pytest.mark.parametrize("query,match", WRONG_PAIRS)
def test_wrong_places_are_never_accepted_with_a_wrong_pose(data, query, match):
    # No translation gate: fitness, margin and yaw gates alone must hold the line.
    cfg = VerifyConfig(max_translation_m=100.0)
    for yaw_guess in (sc_candidate(data, query, match).yaw_guess_rad, 0.0, np.radians(45.0)):
        cand = LoopCandidate(query, match, 0.2, yaw_guess)
        res = verify(cand, data.cloud(query), data.submap(match), cfg)
        if res.accepted:
            assert max(data.errors(res.T_match_query, query, match)) < 1.0, res
        else:
            assert res.constraint is None and res.reason


@pytest.mark.shared_data
@pytest.mark.parametrize("query,match", TRUE_PAIRS[:2])
@pytest.mark.parametrize("offset_deg", [90.0, 180.0, 270.0])
def test_a_yaw_guess_off_by_a_right_angle_is_corrected_or_rejected(data, query, match, offset_deg):
    yaw = data.levelled_yaw(query, match) + np.radians(offset_deg)
    cand = LoopCandidate(query, match, 0.2, yaw)
    no_search = VerifyConfig(try_yaw_offsets=False)
    single = verify(cand, data.cloud(query), data.submap(match), no_search)
    if single.accepted:
        err_m, err_deg = data.errors(single.T_match_query, query, match)
        assert err_m < 1.0 and err_deg < 5.0
    searched = verify(cand, data.cloud(query), data.submap(match), VerifyConfig())
    assert searched.accepted, searched.reason
    err_m, err_deg = data.errors(searched.T_match_query, query, match)
    assert err_m < 1.0 and err_deg < 5.0
    yaw_hyps = [h for h in searched.hypotheses if h.push_m == (0.0, 0.0)]
    assert [h.offset_deg for h in yaw_hyps] == [0.0, 90.0, 180.0, 270.0]
    assert len(searched.hypotheses) == 8  # and four basin probes around the winner
    winner = max(yaw_hyps, key=lambda h: h.coarse_fitness)
    assert winner.offset_deg == (360.0 - offset_deg) % 360.0


@pytest.mark.shared_data
def test_an_initial_pose_from_the_graph_is_used_instead_of_the_yaw_guess(data):
    query, match = 176, 113
    T_init = data.T_match_query(query, match) @ make_pose(np.eye(3), [0.6, -0.4, 0.0])
    T_init = T_init @ yaw_matrix(np.radians(8.0))
    cand = LoopCandidate(query, match, 0.2, 0.0)  # a useless yaw guess: the init must win
    res = verify(cand, data.cloud(query), data.submap(match), VerifyConfig(), T_init)
    assert res.accepted, res.reason
    assert max(data.errors(res.constraint.T_match_query, query, match)) < 1.0


def _corridor(n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Walls at y = +-2 m, floor and ceiling at z = -+1.5 m, 40 m along x: points and normals."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-20, 20, (4, n))
    t = rng.uniform(-1, 1, (4, n))
    pts = np.vstack([
        np.c_[x[0], np.full(n, 2.0), 1.5 * t[0]], np.c_[x[1], np.full(n, -2.0), 1.5 * t[1]],
        np.c_[x[2], 2 * t[2], np.full(n, -1.5)], np.c_[x[3], 2 * t[3], np.full(n, 1.5)],
    ])
    normals = np.repeat(np.array([[0, 1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1]], float), n, axis=0)
    return pts, normals


def test_information_matrix_is_rotation_first_and_weak_along_a_corridor():
    """Walls at y = +-2 m, floor and ceiling, 40 m along x: x translation is unobservable."""
    pts, normals = _corridor()
    corr = np.c_[np.arange(len(pts)), np.arange(len(pts))]
    info = information_matrix(pts, pts, normals, corr, np.eye(4), 0.05, VerifyConfig())
    # Order (rx, ry, rz, tx, ty, tz): tx (index 3) is free, ty and tz are strongly constrained.
    assert info[3, 3] < 1e-5 * info[4, 4]
    assert info[4, 4] > 0 and info[5, 5] > 0
    # Rotation about x turns walls and floor alike: constrained, and it sits first.
    assert info[0, 0] > 0.1 * info[5, 5]
    np.testing.assert_allclose(info, info.T)
    # Positive definite (the free axis keeps a weak 1 m), and floored: no direction is more
    # certain than 2 cm / 0.2 deg.
    assert np.linalg.eigvalsh(info).min() > 0
    sd = np.sqrt(np.diag(np.linalg.inv(info)))
    assert sd[3:].min() == pytest.approx(0.02, rel=1e-6)
    assert sd[:3].min() == pytest.approx(np.radians(0.2), rel=1e-6)


def test_information_matrix_is_in_the_query_frame():
    """gtsam's BetweenFactorPose3(match, query, T) measures its error as T_true = T exp(xi), in
    the query frame. A corridor along the match frame's x axis, seen from a query turned by
    90 deg, is free along the query's y axis."""
    tgt, normals = _corridor()
    T = make_pose(yaw_matrix(np.pi / 2)[:3, :3], [3.0, 1.0, 0.0])
    src = transform_points(inverse(T), tgt)  # the same points seen from the query
    corr = np.c_[np.arange(len(tgt)), np.arange(len(tgt))]
    info = information_matrix(src, tgt, normals, corr, T, 0.05, VerifyConfig())
    assert info[4, 4] < 1e-5 * info[3, 3]  # ty free, tx (the match's y) constrained
    # Numerically: the point-to-plane residuals' Hessian for T exp(xi) perturbations.
    from lidar_slam.geometry import matrix_from_rotvec

    def residuals(xi):
        D = make_pose(matrix_from_rotvec(xi[:3]), xi[3:])
        q = transform_points(T @ D, src)
        return np.einsum("ij,ij->i", q - tgt, normals)

    eps, J = 1e-6, np.zeros((len(src), 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        J[:, k] = (residuals(d) - residuals(-d)) / (2 * eps)
    H = J.T @ J
    # Compare shapes (each block is scaled by its own floor: D H D, D diagonal, which leaves
    # H_ij / sqrt(H_ii H_jj) as it is), without the free ty axis (only the weak prior there).
    keep = [0, 1, 2, 3, 5]
    raw, got = H[np.ix_(keep, keep)], info[np.ix_(keep, keep)]
    raw = raw / np.sqrt(np.outer(np.diag(raw), np.diag(raw)))
    got = got / np.sqrt(np.outer(np.diag(got), np.diag(got)))
    mask = np.abs(raw) > 1e-3
    np.testing.assert_allclose(got[mask], raw[mask], rtol=1e-3)


def test_small_gicp_hessian_invents_information_along_a_diagonal_corridor():
    """Why information_matrix keeps its own point-to-plane Hessian: small_gicp's PLANE_ICP H
    agrees along an axis-aligned corridor but not along one at 45 deg to the axes."""
    import small_gicp

    along = []
    for yaw_deg in (0.0, 45.0):
        tgt, normals = _corridor()
        R = yaw_matrix(np.radians(yaw_deg))[:3, :3]
        tgt, normals = tgt @ R.T, normals @ R.T
        T = make_pose(yaw_matrix(0.3)[:3, :3], [1.0, 0.5, 0.0])
        src = transform_points(inverse(T), tgt)
        cloud = small_gicp.PointCloud(tgt)
        tree = small_gicp.KdTree(cloud)
        small_gicp.estimate_normals(cloud, tree, num_neighbors=10)
        res = small_gicp.align(cloud, small_gicp.PointCloud(src), tree, init_T_target_source=T,
                               registration_type="PLANE_ICP", max_correspondence_distance=0.5,
                               num_threads=1, max_iterations=1)
        corr = np.c_[np.arange(len(src)), np.arange(len(src))]
        ours = information_matrix(src, tgt, normals, corr, T, 0.05, VerifyConfig())
        axis = T[:3, :3].T @ R[:, 0]  # the corridor's length, in the query frame
        along.append((axis @ res.H[3:, 3:] @ axis / res.H[5, 5],
                      axis @ ours[3:, 3:] @ axis / ours[5, 5]))
    (gicp_0, ours_0), (gicp_45, ours_45) = along
    assert ours_0 < 1e-4 and ours_45 < 1e-4  # ours: free along the corridor either way
    assert gicp_0 < 0.02  # small_gicp: weak along an axis-aligned corridor ...
    assert gicp_45 > 0.3  # ... but as stiff as across it when the corridor is diagonal


@pytest.mark.shared_data
def test_verification_is_repeatable_bit_for_bit(data):
    query, match = TRUE_PAIRS[0]
    cand = sc_candidate(data, query, match)
    runs = [verify(cand, data.cloud(query), data.submap(match), VerifyConfig()) for _ in range(2)]
    a, b = runs
    assert a.accepted and b.accepted
    np.testing.assert_array_equal(a.T_match_query, b.T_match_query)
    np.testing.assert_array_equal(a.constraint.information, b.constraint.information)
    assert (a.fitness, a.rmse_m, a.margin) == (b.fitness, b.rmse_m, b.margin)
    for ha, hb in zip(a.hypotheses, b.hypotheses, strict=True):
        np.testing.assert_array_equal(ha.T_match_query, hb.T_match_query)


@pytest.mark.shared_data
def test_prepared_sides_give_the_same_verification(data):
    """The loop detector builds a query's clouds once for all its candidates and keeps recent
    match submaps' clouds: the result must be that of verify() on the points, bit for bit,
    including when one match side serves two queries."""
    cfg = VerifyConfig()
    match = TRUE_PAIRS[0][1]
    shared = match_side(data.submap(match), cfg)
    for query in (TRUE_PAIRS[0][0], TRUE_PAIRS[1][0]):  # two queries, one match side
        cand = sc_candidate(data, query, match)
        plain = verify(cand, data.cloud(query), data.submap(match), cfg)
        built = verify(cand, query_side(data.cloud(query), cfg), shared, cfg)
        np.testing.assert_array_equal(plain.T_match_query, built.T_match_query)
        assert (plain.accepted, plain.fitness, plain.rmse_m, plain.margin) == \
            (built.accepted, built.fitness, built.rmse_m, built.margin)


def test_a_run_with_loops_never_imports_open3d(tmp_path):
    """open3d costs ~200 MB of RSS; `lidar-slam run` on .bin scans with loops on must not load
    it (small_gicp does the verification)."""
    import json
    import subprocess
    import sys

    sample = Path(__file__).resolve().parents[1] / "sample_scans"
    code = ("import runpy, sys\n"
            f"sys.argv = ['lidar-slam', 'run', {str(sample)!r}, '--out', {str(tmp_path)!r}]\n"
            "try:\n"
            "    runpy.run_module('lidar_slam.cli', run_name='__main__')\n"
            "except SystemExit as exc:\n"
            "    assert not exc.code, exc.code\n"
            "print(sorted(m for m in ('open3d', 'small_gicp') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "['small_gicp']"
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["loops_candidates"] > 0 and summary["loops_accepted"] > 0
