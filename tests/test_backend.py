"""Back-end: the NumPy pose-graph interface over gtsam, g2o I/O, `optimize` on benchmark files."""

from __future__ import annotations

import re
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_slam.backend.factors import sigmas_to_information
from lidar_slam.backend.g2o_optimize import optimize_g2o
from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.errors import InputError
from lidar_slam.geometry import make_pose, relative, rotation_angle_deg
from lidar_slam.io.g2o import G2oEdge, G2oGraph, read_g2o, se2_params, write_g2o

REPO = Path(__file__).resolve().parents[1]
ODOM_ROT_DEG, ODOM_TRANS_M = 0.2, 0.02
LOOP_ROT_DEG, LOOP_TRANS_M = 0.5, 0.1


def _perturb(T: np.ndarray, rng: np.random.Generator, rot_deg: float, trans_m: float) -> np.ndarray:
    dR = Rotation.from_rotvec(np.radians(rot_deg) * rng.standard_normal(3)).as_matrix()
    return T @ make_pose(dR, trans_m * rng.standard_normal(3))


def _square_trajectory() -> np.ndarray:
    """60 poses T_world_node around a 20 m x 10 m rectangle, climbing 2 m, facing along the path."""
    corners = np.array([[0, 0], [20, 0], [20, 10], [0, 10], [0, 0]], dtype=float)
    pts = np.concatenate([np.linspace(a, b, 15, endpoint=False)
                          for a, b in pairwise(corners)])
    poses = []
    for k, (x, y) in enumerate(pts):
        nxt = pts[(k + 1) % len(pts)]
        yaw = np.arctan2(nxt[1] - y, nxt[0] - x)
        R = Rotation.from_euler("z", yaw).as_matrix()
        poses.append(make_pose(R, [x, y, 2.0 * k / len(pts)]))
    return np.stack(poses)


def _graph_with_wrong_loop(robust_k: float | None) -> tuple[PoseGraph, np.ndarray]:
    """Noisy odometry, three true loops and one WRONG loop (node 52 claimed on top of node 22)."""
    rng = np.random.default_rng(7)
    truth = _square_trajectory()
    graph = PoseGraph()
    graph.add_prior(0, truth[0], 1e-3, 1e-3)
    graph.set_initial(0, truth[0])
    pose = truth[0]
    for k in range(1, len(truth)):
        T = _perturb(relative(truth[k - 1], truth[k]), rng, ODOM_ROT_DEG, ODOM_TRANS_M)
        graph.add_odometry(k - 1, k, T, rot_sigma_deg=ODOM_ROT_DEG, trans_sigma_m=ODOM_TRANS_M)
        pose = pose @ T
        graph.set_initial(k, pose)
    info = sigmas_to_information(LOOP_ROT_DEG, LOOP_TRANS_M)
    for i, j in [(0, 59), (1, 58), (15, 45)]:
        T = _perturb(relative(truth[i], truth[j]), rng, LOOP_ROT_DEG, LOOP_TRANS_M)
        graph.add_loop(i, j, T, info, robust_k=robust_k)
    # Wrong: 22 and 52 are 10 m apart on opposite sides of the rectangle.
    graph.add_loop(22, 52, np.eye(4), info, robust_k=robust_k)
    return graph, truth


def _max_position_error_m(poses: dict[int, np.ndarray], truth: np.ndarray) -> float:
    est = np.stack([poses[k] for k in range(len(truth))])
    return float(np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1).max())


def test_backend_huber_resists_wrong_loop():
    huber, truth = _graph_with_wrong_loop(robust_k=1.345)
    plain, _ = _graph_with_wrong_loop(robust_k=None)
    err_huber = _max_position_error_m(huber.optimize(100), truth)
    err_plain = _max_position_error_m(plain.optimize(100), truth)
    assert err_huber < 0.5, err_huber
    assert err_plain > 2.0, err_plain
    assert huber.summary is not None and huber.summary.final_error < huber.summary.initial_error


def test_backend_huber_through_g2o_file(tmp_path):
    """The same wrong loop through `optimize`: Huber on loop edges only, plain LS fails."""
    graph, truth = _graph_with_wrong_loop(robust_k=None)
    graph.write_g2o(tmp_path / "wrong_loop.g2o")
    errors = {}
    for robust in ("huber", "none"):
        out = tmp_path / f"{robust}.g2o"
        report = optimize_g2o(tmp_path / "wrong_loop.g2o", out, robust=robust)
        sizes = (report.dims, report.n_vertices, report.n_edges, report.n_loop_edges)
        assert sizes == (3, 60, 63, 4)
        errors[robust] = _max_position_error_m(read_g2o(out).poses, truth)
    assert errors["huber"] < 0.5, errors
    assert errors["none"] > 2.0, errors


def _two_conflicting_edges(use_sigmas: bool) -> np.ndarray:
    """A says 'no rotation, 1 m' (rotation certain), B says '20 deg, 3 m' (translation certain)."""
    graph = PoseGraph()
    graph.add_prior(0, np.eye(4), 1e-4, 1e-5)
    graph.set_initial(0, np.eye(4))
    graph.set_initial(1, make_pose(np.eye(3), [2.0, 0.5, 0.0]))
    T_a = make_pose(np.eye(3), [1.0, 0.0, 0.0])
    T_b = make_pose(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [3.0, 0.0, 0.0])
    if use_sigmas:
        graph.add_odometry(0, 1, T_a, rot_sigma_deg=0.01, trans_sigma_m=100.0)
        graph.add_odometry(0, 1, T_b, rot_sigma_deg=100.0, trans_sigma_m=0.001)
    else:  # information matrices in rotation-first order
        graph.add_odometry(0, 1, T_a, np.diag([1e8, 1e8, 1e8, 1e-4, 1e-4, 1e-4]))
        graph.add_odometry(0, 1, T_b, np.diag([1e-4, 1e-4, 1e-4, 1e6, 1e6, 1e6]))
    return graph.optimize(50)[1]


@pytest.mark.parametrize("use_sigmas", [True, False])
def test_backend_noise_is_rotation_first(use_sigmas):
    T = _two_conflicting_edges(use_sigmas)
    # Right order: rotation from A, translation from B. Swapped: 20 deg and 1 m.
    assert rotation_angle_deg(T) < 0.01
    np.testing.assert_allclose(T[:3, 3], [3.0, 0.0, 0.0], atol=1e-3)


def test_backend_sigmas_to_information_order():
    info = sigmas_to_information(rot_sigma_deg=2.0, trans_sigma_m=0.1)
    np.testing.assert_allclose(np.diag(info), [1 / np.radians(2.0) ** 2] * 3 + [100.0] * 3)
    info2 = sigmas_to_information(rot_sigma_deg=2.0, trans_sigma_m=0.1, dims=2)
    np.testing.assert_allclose(np.diag(info2), [100.0, 100.0, 1 / np.radians(2.0) ** 2])


def test_backend_interface_rejects_bad_input():
    graph = PoseGraph()
    with pytest.raises(ValueError, match="not both"):
        graph.add_odometry(0, 1, np.eye(4), np.eye(6), rot_sigma_deg=1.0, trans_sigma_m=0.1)
    with pytest.raises(ValueError, match="positive definite"):
        graph.add_loop(0, 1, np.eye(4), -np.eye(6))
    with pytest.raises(ValueError, match="4x4"):
        graph.add_loop(0, 1, np.eye(3), np.eye(6))
    graph.add_odometry(0, 1, np.eye(4), rot_sigma_deg=1.0, trans_sigma_m=0.1)
    graph.set_initial(0, np.eye(4))
    with pytest.raises(ValueError, match=r"no initial pose, e\.g\. 1"):
        graph.optimize()


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return A @ A.T + n * np.eye(n)


def test_backend_g2o_round_trip_3d(tmp_path):
    rng = np.random.default_rng(3)
    poses = {k: make_pose(Rotation.random(random_state=k).as_matrix(), rng.normal(size=3) * 5)
             for k in range(6)}
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0)]
    edges = [G2oEdge(i, j, relative(poses[i], poses[j]) @ _perturb(np.eye(4), rng, 1, 0.1),
                     _random_spd(rng, 6)) for i, j in pairs]
    write_g2o(tmp_path / "a.g2o", G2oGraph(3, poses, edges, len(poses)))
    back = read_g2o(tmp_path / "a.g2o")
    assert back.dims == 3 and back.n_vertex_lines == 6 and sorted(back.poses) == sorted(poses)
    for k, T in poses.items():
        np.testing.assert_allclose(back.poses[k], T, atol=1e-12)
    for e, b in zip(edges, back.edges, strict=True):
        assert (b.i, b.j) == (e.i, e.j)
        np.testing.assert_allclose(b.T_i_j, e.T_i_j, atol=1e-12)
        np.testing.assert_allclose(b.information, e.information, rtol=1e-15)
    # The file holds g2o's translation-first order: its first info entry is the (x, x) element,
    # which is element (3, 3) of the rotation-first matrix; entry 6 (x, y) is element (3, 4).
    first_edge = next(ln for ln in (tmp_path / "a.g2o").read_text().splitlines()
                      if ln.startswith("EDGE"))
    file_info = np.array(first_edge.split()[10:], dtype=float)
    assert file_info[0] == edges[0].information[3, 3]
    assert file_info[1] == edges[0].information[3, 4]
    assert file_info[15] == edges[0].information[0, 0]  # (rx, rx)


def test_backend_g2o_reads_translation_first_information(tmp_path):
    # g2o order [x y z rx ry rz]: diag 1..6, plus a cross term between x and rx.
    upper = np.zeros((6, 6))
    upper[np.diag_indices(6)] = [1, 2, 3, 4, 5, 6]
    upper[0, 3] = 0.5
    fields = " ".join(str(v) for v in upper[np.triu_indices(6)])
    (tmp_path / "e.g2o").write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {fields}\n")
    info = read_g2o(tmp_path / "e.g2o").edges[0].information
    np.testing.assert_array_equal(np.diag(info), [4, 5, 6, 1, 2, 3])
    assert info[0, 3] == info[3, 0] == 0.5  # (rx, tx) in gtsam order


def test_backend_g2o_round_trip_2d_and_chaining(tmp_path):
    rng = np.random.default_rng(5)
    (tmp_path / "chain.g2o").write_text("\n".join(
        f"EDGE_SE2 {i} {i + 1} 1.0 0.0 {np.pi / 2} 10 0 0 10 0 100" for i in range(4)) +
        "\n\nEDGE_SE2 0 4 0.0 0.0 0.0 1 0 0 1 0 1\n")
    g = read_g2o(tmp_path / "chain.g2o")
    assert g.dims == 2 and g.n_vertex_lines == 0 and len(g.edges) == 5
    # Four quarter turns of 1 m: a unit square back to the start.
    np.testing.assert_allclose([se2_params(g.poses[k])[:2] for k in range(5)],
                               [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], atol=1e-12)
    info = _random_spd(rng, 3)
    g = G2oGraph(2, g.poses, [G2oEdge(e.i, e.j, e.T_i_j, info) for e in g.edges], 5)
    write_g2o(tmp_path / "b.g2o", g)
    back = read_g2o(tmp_path / "b.g2o")
    assert back.n_vertex_lines == 5
    for k in g.poses:
        np.testing.assert_allclose(back.poses[k], g.poses[k], atol=1e-12)
    for e, b in zip(g.edges, back.edges, strict=True):
        np.testing.assert_allclose(b.T_i_j, e.T_i_j, atol=1e-12)
        np.testing.assert_array_equal(b.information, info)


@pytest.mark.parametrize("text, problem", [
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", "line 2: EDGE_SE2 needs 11 fields"),
    ("EDGE_SE2 0 1 1 0 zero 1 0 0 1 0 1\n", "line 1: EDGE_SE2 has a field that is not a number"),
    ("EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1\n", "line 1: EDGE_SE2 node ids must be integers"),
    ("# comment\nVERTEX_XY 0 1 2\n", "line 2: unsupported record 'VERTEX_XY'"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n", "line 1: information matrix is not positive definite"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n", "line 2: edge uses node 1"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE3:QUAT 1 2" + " 0" * 30 + "\n", "line 2: EDGE_SE3"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n", "not connected"),
    ("VERTEX_SE2 0 0 0 0\n", "no EDGE_SE2 or EDGE_SE3:QUAT records"),
])
def test_backend_g2o_malformed(tmp_path, text, problem):
    (tmp_path / "bad.g2o").write_text(text)
    with pytest.raises(InputError) as exc:
        read_g2o(tmp_path / "bad.g2o")
    assert exc.value.path == str(tmp_path / "bad.g2o")
    assert problem in exc.value.problem


def test_backend_g2o_indefinite_cross_terms_are_dropped(tmp_path):
    # cubicle.g2o-style: PD diagonal blocks, indefinite because of a z-rx cross term.
    upper = np.eye(6) * 10
    upper[2, 3] = 100.0
    fields = " ".join(str(v) for v in upper[np.triu_indices(6)])
    (tmp_path / "c.g2o").write_text(f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {fields}\n")
    info = read_g2o(tmp_path / "c.g2o").edges[0].information
    np.testing.assert_array_equal(info, np.eye(6) * 10)


def test_backend_noisy_toy_graph_reaches_gtsam_optimum(posegraphs, tmp_path):
    """optimizedNoisyToyGraph.txt is LAGO's estimate, which gtsam's testLago.cpp accepts to 1e-2;
    the LM optimum must lie that close and have a lower error than it."""
    noisy = posegraphs / "gtsam" / "noisyToyGraph.txt"
    report = optimize_g2o(noisy, tmp_path / "out.g2o")
    assert report.dims == 2 and report.n_vertices == 4 and report.n_edges == 5
    ours = read_g2o(tmp_path / "out.g2o").poses
    expected = read_g2o(posegraphs / "gtsam" / "optimizedNoisyToyGraph.txt").poses
    for k in expected:
        x, y, th = se2_params(ours[k])
        ex, ey, eth = se2_params(expected[k])
        assert abs(x - ex) < 1e-2 and abs(y - ey) < 1e-2, (k, x, y, ex, ey)
        assert abs(np.angle(np.exp(1j * (th - eth)))) < 1e-2, (k, th, eth)
    graph = PoseGraph.from_g2o(read_g2o(noisy))
    assert graph.error(ours) < graph.error(expected)  # 0.068343 < 0.068357
    assert graph.error(ours) == pytest.approx(0.0683428, rel=1e-5)


@pytest.mark.parametrize("stem", ["intel", "smallGrid3D"])
def test_backend_optimize_writes_its_optimum(posegraphs, tmp_path, stem):
    """Re-reading `optimize`'s output gives back the same graph at the same error (3D information
    written in g2o order and permuted again on reading)."""
    first = optimize_g2o(posegraphs / "se-sync" / f"{stem}.g2o", tmp_path / "a.g2o")
    second = optimize_g2o(tmp_path / "a.g2o", None)
    assert (second.n_vertices, second.n_edges) == (first.n_vertices, first.n_edges)
    assert second.initial_error == pytest.approx(first.final_error, rel=1e-6)
    assert second.final_error == pytest.approx(first.final_error, rel=1e-6)


# (file stem, gtsam error at the initial guess, gtsam error after LM, source of the LM value).
# Initial errors agree with gtsam.readG2o (an independent parser, also chaining edges-only files)
# to 1e-12. "README": gtsam_err@LM of ../shared/data/posegraphs/README.txt; "pin": measured here
# with gtsam 4.3.0 (plain LM from the file's guess; regression value, not a known optimum).
FAST_FILES = [
    ("tinyGrid3D", 143.31787355350403, 9.313909533600555, "pin"),
    ("smallGrid3D", 83894.33343553312, 517.9253346774366, "pin"),
    ("MIT", 3548660355.520316, 385.12237176508694, "pin"),
    ("CSAIL", 1072150.1250268344, 20.28, "README"),
    ("intel", 276.99789778210055, 22.50, "README"),
    ("kitti_05", 1866608.4202196952, 78.55192464402505, "pin"),
    ("kitti_00", 37308573.87541639, 49.16106911562436, "pin"),
    ("kitti_02", 19525109.196758162, 39.38231169712003, "pin"),
    ("manhattan", 13515460719.768232, 1774.5, "README"),
    ("sphere2500", 1305657.711806087, 675.70, "README"),
    ("parking-garage", 8363.60194812, 0.6342, "README"),
    ("city10000", 359231215.6007709, 255.99, "README"),
]
# ~70 s together on one core (torus3D alone ~30 s); run by CI, skip locally with -m "not slow".
SLOW_FILES = [
    ("sphere_bignoise_vertex3", 165629610.45462978, 3761057.8300288985, "pin"),
    ("ais2klinik", 652821.6444440273, 86.41, "README"),
    ("cubicle", 5405432.267031737, 1372.8, "README"),
    ("torus3D", 2400615.1744463546, 29950.0, "README"),
]


def _check_benchmark(posegraphs: Path, stem: str, initial: float, final: float) -> None:
    report = optimize_g2o(posegraphs / "se-sync" / f"{stem}.g2o", None)
    assert report.initial_error == pytest.approx(initial, rel=1e-6)
    assert report.final_error == pytest.approx(final, rel=0.01)


@pytest.mark.parametrize("stem, initial, final, source", FAST_FILES, ids=[f[0] for f in FAST_FILES])
def test_backend_benchmark_matches_readme(posegraphs, stem, initial, final, source):
    _check_benchmark(posegraphs, stem, initial, final)


@pytest.mark.slow
@pytest.mark.parametrize("stem, initial, final, source", SLOW_FILES, ids=[f[0] for f in SLOW_FILES])
def test_backend_benchmark_matches_readme_large(posegraphs, stem, initial, final, source):
    _check_benchmark(posegraphs, stem, initial, final)


def test_backend_benchmark_list_covers_every_file(posegraphs):
    stems = {p.stem for p in (posegraphs / "se-sync").glob("*.g2o")}
    assert stems == {f[0] for f in FAST_FILES + SLOW_FILES}


def test_backend_only_gtsam_graph_imports_gtsam():
    # and three siblings for the IMU: preintegration (imu.py, shared with the front-end), the
    # front-end's velocity / bias smoother (frontend/imu_prediction.py) and the IMU / GNSS
    # factors of the final solve (backend/inertial_graph.py)
    importers = [p.relative_to(REPO).as_posix() for p in (REPO / "lidar_slam").rglob("*.py")
                 if re.search(r"^\s*(import gtsam|from gtsam)", p.read_text(), re.MULTILINE)]
    assert sorted(importers) == ["lidar_slam/backend/gtsam_graph.py",
                                 "lidar_slam/backend/inertial_graph.py",
                                 "lidar_slam/frontend/imu_prediction.py", "lidar_slam/imu.py"]


def test_backend_incremental_agrees_with_full_lm_huber():
    """The pipeline's back-end, fed keyframe by keyframe with loops arriving late (window solves),
    ends
    within 1 mm / 0.01 deg of one full LM solve of the same graph (Huber loop edges)."""
    from lidar_slam.backend.slam_backend import Backend
    from lidar_slam.config import BackendConfig
    from lidar_slam.types import LoopConstraint

    rng = np.random.default_rng(3)
    truth = _square_trajectory()
    odo = [truth[0]]
    for k in range(1, len(truth)):
        odo.append(odo[-1] @ _perturb(relative(truth[k - 1], truth[k]), rng, 0.3, 0.03))
    info = sigmas_to_information(LOOP_ROT_DEG, LOOP_TRANS_M)
    loops = {59: 0, 58: 1, 45: 15, 52: 22}  # query -> match; 52 -> 22 is wrong
    backend = Backend(BackendConfig())
    for k, T in enumerate(odo):
        backend.add_keyframe(k, T)
        if k - 5 in loops:  # results arrive a few keyframes late, as from the loop worker
            q = k - 5
            T_mq = relative(truth[loops[q]], truth[q]) if q != 52 else np.eye(4)
            backend.add_loop(LoopConstraint(q, loops[q], T_mq, info, 0.9, 0.1))
        backend.update()
    for q in (58, 59):
        backend.add_loop(LoopConstraint(q, loops[q], relative(truth[loops[q]], truth[q]), info,
                                        0.9, 0.1))
    incremental = backend.poses()
    full = PoseGraph()
    full.priors, full.edges = list(backend.graph.priors), list(backend.graph.edges)
    for k, T in enumerate(odo):
        full.set_initial(k, T)
    lm = full.optimize(200, relative_error_tol=1e-9)
    final = backend.finish()
    for k in lm:
        d = np.linalg.inv(lm[k]) @ final[k]
        assert np.linalg.norm(d[:3, 3]) < 1e-3 and rotation_angle_deg(d) < 0.01, k
        d = np.linalg.inv(lm[k]) @ incremental[k]
        assert np.linalg.norm(d[:3, 3]) < 0.05, k  # the live (window) estimate is already close
    assert np.linalg.norm(final[59][:3, 3] - truth[59][:3, 3]) < 0.5


# --- global initialisation, GNC, SE-Sync objective, Shonan certificate (issue 10) ---


def test_backend_sesync_objective_by_hand():
    """One 3D edge: F = kappa ||R_j - R_i R_ij||_F^2 + tau ||t_j - t_i - R_i t_ij||^2 with
    kappa = 3 / (2 tr(inv(I_R))), tau = 3 / tr(inv(I_t)) (SE-Sync's read_g2o_file)."""
    from lidar_slam.backend.sesync import sesync_objective

    info = np.diag([4.0, 4.0, 4.0, 9.0, 9.0, 9.0])  # rotation first
    kappa, tau = 3 / (2 * 3 / 4.0), 3 / (3 / 9.0)
    R = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    edge = G2oEdge(0, 1, make_pose(np.eye(3), [1.0, 0, 0]), info)
    poses = {0: np.eye(4), 1: make_pose(R, [1.0, 0.5, 0])}
    expected = kappa * np.sum((R - np.eye(3)) ** 2) + tau * 0.25
    assert sesync_objective(3, [edge], poses) == pytest.approx(expected, rel=1e-12)
    assert sesync_objective(3, [edge], poses, keep=np.array([False])) == 0.0
    edge2d = G2oEdge(0, 1, np.eye(3), np.diag([2.0, 8.0, 5.0]))  # tau = 2 / (1/2 + 1/8)
    poses2d = {0: np.eye(3), 1: np.array([[1.0, 0, 1.0], [0, 1.0, 0], [0, 0, 1.0]])}
    assert sesync_objective(2, [edge2d], poses2d) == pytest.approx(2 / 0.625, rel=1e-12)


@pytest.mark.parametrize("stem, readme_F", [("intel", 54.50), ("CSAIL", 53.49)])
def test_backend_sesync_objective_matches_readme(posegraphs, stem, readme_F):
    """SE-Sync's objective at plain LM's solution, as in the posegraphs README sanity check."""
    report = optimize_g2o(posegraphs / "se-sync" / f"{stem}.g2o", None, init="file")
    assert report.sesync_objective == pytest.approx(readme_F, rel=2e-4)


def _scrambled_circle(seed: int) -> tuple[PoseGraph, np.ndarray]:
    """A 3D loop of 40 poses (plus chords), exact measurements, and a file guess whose
    rotations are random: LM from it lands in a local minimum, a global init does not."""
    rng = np.random.default_rng(seed)
    n = 40
    truth = np.stack([make_pose(Rotation.from_euler("z", 2 * np.pi * k / n).as_matrix(),
                                [10 * np.cos(2 * np.pi * k / n), 10 * np.sin(2 * np.pi * k / n),
                                 0.5 * np.sin(4 * np.pi * k / n)]) for k in range(n)])
    graph = PoseGraph()
    graph.add_prior(0, truth[0], 1e-3, 1e-3)
    pairs = [(k, k + 1) for k in range(n - 1)] + [(k, (k + n // 2) % n) for k in range(0, n, 4)]
    pairs += [(0, n - 1)]
    for i, j in pairs:
        T = relative(truth[i], truth[j])
        if abs(i - j) == 1:
            graph.add_odometry(i, j, T, rot_sigma_deg=1.0, trans_sigma_m=0.1)
        else:
            graph.add_loop(i, j, T, sigmas_to_information(1.0, 0.1))
    for k in range(n):
        graph.set_initial(k, make_pose(Rotation.random(random_state=rng).as_matrix(),
                                       truth[k][:3, 3] + rng.normal(0, 3.0, 3)))
    graph.set_initial(0, truth[0])
    return graph, truth


def test_backend_chordal_init_escapes_the_file_guess_local_minimum():
    file_graph, truth = _scrambled_circle(1)
    auto_graph, _ = _scrambled_circle(1)
    file_graph.solve("none", "file")
    auto_graph.solve("none", "auto")
    assert file_graph.summary.final_error > 1.0  # stuck
    s = auto_graph.summary
    assert s.init == "chordal" and s.final_error < 1e-6, s
    assert _max_position_error_m(auto_graph.estimate, truth) < 1e-3
    assert s.initial_error == pytest.approx(file_graph.summary.initial_error)


def _planar_graph(drop_odometry: int | None) -> tuple[PoseGraph, np.ndarray]:
    """The square trajectory flattened to SE(2), exact edges, an all-identity file guess."""
    truth3 = _square_trajectory()
    truth = np.stack([[[T[0, 0], T[0, 1], T[0, 3]], [T[1, 0], T[1, 1], T[1, 3]], [0, 0, 1]]
                      for T in truth3])
    graph = PoseGraph(dims=2)
    graph.add_prior(0, truth[0], 1e-3, 1e-3)
    for k in range(1, len(truth)):
        if k - 1 != drop_odometry:
            graph.add_odometry(k - 1, k, np.linalg.inv(truth[k - 1]) @ truth[k],
                               rot_sigma_deg=0.5, trans_sigma_m=0.05)
    info = sigmas_to_information(0.5, 0.05, dims=2)
    for i, j in [(0, 59), (15, 45), (10, 40), (25, 55)]:
        graph.add_loop(i, j, np.linalg.inv(truth[i]) @ truth[j], info)
    for k in range(len(truth)):
        graph.set_initial(k, np.eye(3))
    return graph, truth


@pytest.mark.parametrize("drop, method", [(None, "lago"), (29, "chordal")])
def test_backend_2d_global_init_is_lago_along_the_odometry_chain(drop, method):
    """LAGO needs every (k, k+1) edge; without one, the planar graph goes through gtsam's
    chordal InitializePose3 (lifted to 3D). Both find the exact poses from identities."""
    graph, truth = _planar_graph(drop)
    graph.solve("none", "chordal")
    assert graph.summary.init == method
    est = np.stack([graph.estimate[k] for k in range(len(truth))])
    assert np.abs(est[:, :2, 2] - truth[:, :2, 2]).max() < 1e-4


@pytest.mark.parametrize("robust", ["gnc", "huber"])
def test_backend_solve_marks_the_wrong_loop(robust):
    """GNC drops the wrong loop (weight 0) and keeps the true ones; with Huber the wrong loop's
    residual is beyond the 99 % gate (reported as rejected too). Odometry is never rejected."""
    graph, truth = _graph_with_wrong_loop(robust_k=None)
    poses = graph.solve(robust, "auto")
    inlier = dict(zip([(e.i, e.j) for e in graph.edges], graph.summary.inlier, strict=True))
    assert inlier[(22, 52)] is False
    assert all(inlier[p] for p in [(0, 59), (1, 58), (15, 45)])
    assert all(v for (i, j), v in inlier.items() if j - i == 1)
    assert _max_position_error_m(poses, truth) < (0.3 if robust == "gnc" else 0.5)


def test_backend_gnc_beats_plain_least_squares_on_many_wrong_loops():
    rng = np.random.default_rng(11)
    graph, truth = _graph_with_wrong_loop(robust_k=None)
    info = sigmas_to_information(LOOP_ROT_DEG, LOOP_TRANS_M)
    for _ in range(8):
        i, j = sorted(rng.choice(60, 2, replace=False))
        if j - i > 1:
            graph.add_loop(int(i), int(j), make_pose(Rotation.random(random_state=rng).as_matrix(),
                                                     rng.uniform(-10, 10, 3)), info)
    plain = copy_graph(graph)
    plain.solve("none", "file")
    graph.solve("gnc", "file")
    assert _max_position_error_m(plain.estimate, truth) > 2.0
    assert _max_position_error_m(graph.estimate, truth) < 0.3


def _mostly_wrong_loops(n_wrong: int) -> tuple[PoseGraph, np.ndarray]:
    """The square with its 3 true loops and n_wrong random wrong ones (its own wrong one too)."""
    rng = np.random.default_rng(5)
    graph, truth = _graph_with_wrong_loop(robust_k=None)
    info = sigmas_to_information(LOOP_ROT_DEG, LOOP_TRANS_M)
    while sum(e.is_loop for e in graph.edges) < 3 + n_wrong:
        i, j = sorted(int(v) for v in rng.choice(60, 2, replace=False))
        if j - i > 1:
            graph.add_loop(i, j, make_pose(Rotation.random(random_state=rng).as_matrix(),
                                           rng.uniform(-10, 10, 3)), info)
    return graph, truth


def test_backend_gnc_keeps_the_true_loops_among_mostly_wrong_ones():
    """30 wrong loops against 3 true ones (91 % outliers, as loose gates admit on a drive with
    one revisit): GNC starts from the odometry alone (loops at weight 0), so the true loops are
    the ones with small residuals from the first step; started with every loop at weight 1 it
    rejected all of them."""
    graph, truth = _mostly_wrong_loops(30)
    poses = graph.solve("gnc", "file")
    inlier = dict(zip([(e.i, e.j) for e in graph.edges], graph.summary.inlier, strict=True))
    true_loops = [(0, 59), (1, 58), (15, 45)]
    assert all(inlier[p] for p in true_loops)
    assert not any(v for p, v in inlier.items() if p not in true_loops and p[1] - p[0] > 1)
    assert _max_position_error_m(poses, truth) < 0.3


def test_backend_gnc_keeps_loops_that_already_agree_with_the_start():
    """gtsam's degenerate case: every factor within its threshold at the start; GNC returns its
    first solve, so that solve must include the loops (they are kept, not left at weight 0)."""
    graph, truth = _graph_with_wrong_loop(robust_k=None)
    graph.edges = [e for e in graph.edges if (e.i, e.j) != (22, 52)]
    graph.solve("none", "file")  # the start is now the optimum: all residuals small
    poses = graph.solve("gnc", "file")
    assert all(graph.summary.inlier)
    assert _max_position_error_m(poses, truth) < 0.3


def copy_graph(graph: PoseGraph) -> PoseGraph:
    out = PoseGraph(graph.dims)
    out.priors, out.edges = list(graph.priors), list(graph.edges)
    for k, T in graph.estimate.items():
        out.set_initial(k, T)
    return out


def test_backend_shonan_certifies_rotations(posegraphs):
    report = optimize_g2o(posegraphs / "se-sync" / "smallGrid3D.g2o", None, certify="on")
    assert report.certificate is not None and report.certificate.certified
    assert report.certificate.lambda_min > -1e-4
    toy = optimize_g2o(posegraphs / "gtsam" / "noisyToyGraph.txt", None, certify="on")
    assert toy.certificate.certified  # ShonanAveraging2
    off = optimize_g2o(posegraphs / "se-sync" / "tinyGrid3D.g2o", None, certify="off")
    assert off.certificate is None
    # kitti_05's rotation weights are 1.5e6: unscaled, gtsam's eigensolver fails on them.
    kitti = optimize_g2o(posegraphs / "se-sync" / "kitti_05.g2o", None, certify="on")
    assert kitti.certificate.certified, kitti.certificate


def test_backend_g2o_counts_repaired_information(tmp_path):
    upper = np.eye(6) * 10
    upper[2, 3] = 100.0
    fields = " ".join(str(v) for v in upper[np.triu_indices(6)])
    good = " ".join(str(v) for v in np.eye(6)[np.triu_indices(6)])
    (tmp_path / "c.g2o").write_text(f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {fields}\n"
                                    f"EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 {good}\n")
    assert read_g2o(tmp_path / "c.g2o").n_repaired == 1
    report = optimize_g2o(tmp_path / "c.g2o", None, init="auto")
    assert report.n_repaired == 1 and report.init in ("file", "chordal")


@pytest.mark.slow
def test_backend_torus3d_reaches_the_certified_optimum(posegraphs):
    """Issue 10: LM from torus3D's file guess stalls at 29,950; auto ends <= 12,200, with
    SE-Sync's objective at SE-Sync's certified p* (24,230, 4 significant figures)."""
    report = optimize_g2o(posegraphs / "se-sync" / "torus3D.g2o", None, init="auto")
    assert report.init == "chordal" and report.final_error <= 12200
    assert report.sesync_objective == pytest.approx(24230, rel=1e-3)


def test_backend_finish_gnc_rejects_the_wrong_loop():
    """The pipeline's back-end with backend.robust gnc: the wrong loop 52 -> 22 is rejected
    (loop_status), the true ones kept, and the final poses ignore it."""
    from lidar_slam.backend.slam_backend import Backend
    from lidar_slam.config import BackendConfig
    from lidar_slam.types import LoopConstraint

    rng = np.random.default_rng(3)
    truth = _square_trajectory()
    odo = [truth[0]]
    for k in range(1, len(truth)):
        odo.append(odo[-1] @ _perturb(relative(truth[k - 1], truth[k]), rng, 0.3, 0.03))
    info = sigmas_to_information(LOOP_ROT_DEG, LOOP_TRANS_M)
    backend = Backend(BackendConfig(robust="gnc"))
    for k, T in enumerate(odo):
        backend.add_keyframe(k, T)
    for q, m in {59: 0, 58: 1, 45: 15}.items():
        backend.add_loop(LoopConstraint(q, m, relative(truth[m], truth[q]), info, 0.9, 0.1))
    backend.add_loop(LoopConstraint(52, 22, np.eye(4), info, 0.9, 0.1))
    final = backend.finish()
    assert backend.loop_status == {(0, 59): "inlier", (1, 58): "inlier", (15, 45): "inlier",
                                   (22, 52): "rejected"}
    assert backend.final_init == "odometry"  # GNC starts from the odometry chain
    assert backend.seconds["final"] > 0
    assert _max_position_error_m(final, truth) < 0.5


def test_backend_loops_csv_has_the_backend_column():
    from lidar_slam.loop.detector import LoopRecord, loops_csv_rows

    def rec(q, m, accepted):
        return LoopRecord(q * 10, m * 10, q, m, 0.1, 0.0, 0.9, 0.1, accepted, "",
                          np.eye(4) if accepted else None)

    rows = loops_csv_rows([rec(5, 1, True), rec(6, 2, True), rec(7, 3, False)],
                          {(1, 5): "inlier", (2, 6): "rejected"})
    header = rows[0]
    assert header[-1] == "backend" and header[6] == "accepted"
    assert [r[-1] for r in rows[1:]] == ["inlier", "rejected", ""]


def test_backend_default_yaml_lists_every_option():
    import yaml

    from lidar_slam.config import SlamConfig

    listed = yaml.safe_load((REPO / "configs" / "default.yaml").read_text())
    assert listed == SlamConfig().model_dump()


def test_backend_global_init_failure_falls_back_or_raises(monkeypatch):
    """A global initialisation gtsam rejects must not cost a run: auto goes on from the given
    estimate (logged); an explicit --init chordal is a one-line error."""
    from lidar_slam.backend import gtsam_graph
    from lidar_slam.errors import SolveError

    def indeterminate(*args, **kwargs):
        raise RuntimeError("Indeterminate linear system detected")

    monkeypatch.setattr(gtsam_graph, "global_initial", indeterminate)
    graph, truth = _graph_with_wrong_loop(robust_k=None)
    graph.solve("huber", "auto")
    assert graph.summary.init == "file" and [c[0] for c in graph.summary.candidates] == ["file"]
    assert _max_position_error_m(graph.estimate, truth) < 0.5
    with pytest.raises(SolveError, match="global initialisation failed"):
        _graph_with_wrong_loop(robust_k=None)[0].solve("none", "chordal")


def test_backend_sesync_weights_reach_the_published_optimum(posegraphs):
    """CSAIL's information matrices have large x-y cross terms that SE-Sync's isotropic weights
    ignore, so gtsam's optimum scores F = 53.5 against SE-Sync's p* = 31.70. Solving SE-Sync's
    own problem (--weights sesync) from LAGO lands on p* (4 significant figures)."""
    report = optimize_g2o(posegraphs / "se-sync" / "CSAIL.g2o", None, init="auto",
                          weights="sesync")
    assert report.init == "lago"
    assert report.sesync_objective == pytest.approx(31.70, rel=2e-3)
    assert report.final_error == pytest.approx(report.sesync_objective, rel=1e-3)


def test_a_graph_in_unconnected_parts_is_one_line(tmp_path):
    """Only the first node is anchored: a part no edge joins to it would be left where the file
    put it (or be an indeterminate system), so the file is refused naming a node of that part."""
    path = tmp_path / "two.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 5 5 0\n"
                    "VERTEX_SE2 3 6 5 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
                    "EDGE_SE2 2 3 2 0 0 1 0 0 1 0 1\n")
    with pytest.raises(InputError, match="in 2 unconnected parts .* joins node 2 to node 0"):
        read_g2o(path)
    with pytest.raises(InputError, match="is a folder, not a g2o file"):
        read_g2o(tmp_path)
