"""Odometry edges weighed by their own data (lidar_slam.frontend.edge_information) and the
odometry's variance checked against the IMU
(lidar_slam.backend.imu_gnss_solve.odometry_variance)."""

import numpy as np
import pytest

from lidar_slam.backend.factors import BetweenFactor, with_rotation_floor
from lidar_slam.backend.imu_gnss_solve import VARIANCE_FACTOR_MIN, odometry_variance
from lidar_slam.config import OdometryInformationConfig
from lidar_slam.frontend.edge_information import EdgeInformation
from lidar_slam.geometry import make_pose


def _corridor(rng, noise_m: float, length_m: float = 60.0) -> np.ndarray:
    """Two walls (y = +-2 m), a floor and a ceiling along x, sampled every ~5 cm."""
    x = rng.uniform(-length_m / 2, length_m / 2, 40000)
    u = rng.uniform(0.0, 1.0, 40000)
    side = rng.integers(0, 4, 40000)
    y = np.where(side == 0, 2.0, np.where(side == 1, -2.0, 4.0 * u - 2.0))
    z = np.where(side == 2, -1.0, np.where(side == 3, 1.5, 2.5 * u - 1.0))
    return np.c_[x, y, z] + rng.normal(0.0, noise_m, (40000, 3))


def _room(rng, noise_m: float) -> np.ndarray:
    """A 12 x 8 x 3 m box with a pillar: every direction constrained."""
    pts = []
    for axis, value in [(0, -6), (0, 6), (1, -4), (1, 4), (2, -1), (2, 2)]:
        p = rng.uniform([-6, -4, -1], [6, 4, 2], (8000, 3))
        p[:, axis] = value
        pts.append(p)
    pillar = rng.uniform([1.0, 1.0, -1.0], [1.5, 1.5, 2.0], (2000, 3))
    pts.append(pillar)
    return np.concatenate(pts) + rng.normal(0.0, noise_m, (50000, 3))


def _sigmas(info: np.ndarray) -> np.ndarray:
    return np.sqrt(np.diag(np.linalg.inv(info)))


def _edge(cloud_a: np.ndarray, cloud_b: np.ndarray, cfg=OdometryInformationConfig()):
    edges = EdgeInformation(cfg, cloud_voxel_m=0.5)
    assert edges.add(np.eye(4), cloud_a) is None  # the first keyframe has no edge
    return edges.add(make_pose(np.eye(3), [0.5, 0.0, 0.0]), cloud_b)


def test_a_corridor_edge_is_weak_along_the_corridor_and_sure_across_it():
    rng = np.random.default_rng(0)
    sig = _sigmas(_edge(_corridor(rng, 0.01), _corridor(rng, 0.01) - [0.5, 0, 0]))
    assert sig[3] > 0.3, sig  # along x: nothing but the weak prior (1 m)
    assert sig[4] < 0.02 and sig[5] < 0.02, sig  # across: the walls, the floor


def test_noisier_clouds_give_a_less_certain_edge_and_the_floor_holds():
    rng = np.random.default_rng(1)
    a, b = _room(rng, 0.0), _room(rng, 0.0) - [0.5, 0, 0]
    sharp = _sigmas(_edge(a, b))
    blurred = _sigmas(_edge(a + rng.normal(0, 0.05, a.shape), b + rng.normal(0, 0.05, b.shape)))
    assert np.all(blurred[3:] > 1.5 * sharp[3:]), (sharp, blurred)
    cfg = OdometryInformationConfig()
    # Noise-free clouds: the residual is taken as min_residual_m (1 cm), and the floors are
    # added: no axis surer than its floor, none far above it.
    assert np.all((sharp[3:] >= cfg.min_trans_sigma_m) & (sharp[3:] < 1.5 * cfg.min_trans_sigma_m))
    rot_deg = np.degrees(sharp[:3])
    assert np.all((rot_deg >= cfg.min_rot_sigma_deg) & (rot_deg < 1.5 * cfg.min_rot_sigma_deg))


def test_the_imu_solves_rotation_floor_is_the_edge_measured_with_that_floor():
    # backend.inertial_odom_min_rot_sigma_deg: the same clouds measured with the lower floor
    # directly, not a scaled copy (a uniform scale would also tighten the translation)
    rng = np.random.default_rng(2)
    a, b = _room(rng, 0.02), _room(rng, 0.02) - [0.5, 0, 0]
    low = OdometryInformationConfig(min_rot_sigma_deg=0.02)
    moved = with_rotation_floor(_edge(a, b), OdometryInformationConfig().min_rot_sigma_deg, 0.02)
    np.testing.assert_allclose(moved, _edge(a, b, low), rtol=1e-6)
    before, after = _sigmas(_edge(a, b)), _sigmas(moved)
    assert np.all(after[:3] < before[:3] - np.radians(0.01)), (before, after)
    np.testing.assert_allclose(after[3:], before[3:], rtol=1e-9)  # translation as measured


def test_an_empty_keyframe_has_no_edge_information():
    edges = EdgeInformation(OdometryInformationConfig(), 0.5)
    rng = np.random.default_rng(2)
    edges.add(np.eye(4), _room(rng, 0.01))
    assert edges.add(np.eye(4), np.zeros((0, 3))) is None
    assert edges.add(np.eye(4), _room(rng, 0.01)) is None  # its successor neither


def test_odometry_variance_grows_with_residuals_beyond_the_edges_own_information():
    info = np.diag([np.radians(0.1) ** -2] * 3 + [0.01 ** -2] * 3)
    rng = np.random.default_rng(3)
    poses = {0: np.eye(4)}
    edges = []
    for k in range(1, 200):
        poses[k] = poses[k - 1] @ make_pose(np.eye(3), [1.0, 0.0, 0.0])
        # measured motion off by 3 sigma-ish in translation, consistent in rotation
        err = make_pose(np.eye(3), rng.normal(0.0, 0.03, 3))
        edges.append(BetweenFactor(k - 1, k, make_pose(np.eye(3), [1.0, 0.0, 0.0]) @ err, info))
    rot, horizontal, vertical = odometry_variance(edges, poses)
    assert rot == VARIANCE_FACTOR_MIN  # no rotation residual at all: tightened to the guard
    assert 6.0 < horizontal < 14.0, horizontal  # (3 cm / 1 cm)^2 = 9
    assert 5.0 < vertical < 15.0, vertical


def test_odometry_variance_splits_translation_by_gravity_whatever_the_node_frames():
    """A vertical error three times the edges' sigma, none horizontally: only the vertical
    factor rises (~9), also with the nodes turned 90 deg about x (their y axis is up)."""
    from lidar_slam.backend.imu_gnss_solve import _scaled_odometry
    from lidar_slam.geometry import matrix_from_rotvec

    info = np.diag([np.radians(0.1) ** -2] * 3 + [0.01 ** -2] * 3)
    rng = np.random.default_rng(5)
    for R in (np.eye(3), matrix_from_rotvec([np.pi / 2, 0.0, 0.0])):
        poses, edges = {0: make_pose(R, [0.0, 0.0, 0.0])}, []
        for k in range(1, 300):
            poses[k] = make_pose(R, [float(k), 0.0, 0.0])
            step = np.linalg.inv(poses[k - 1]) @ poses[k]
            up = R.T @ np.array([0.0, 0.0, rng.normal(0.0, 0.03)])  # S's z in the node frame
            edges.append(BetweenFactor(k - 1, k, step @ make_pose(np.eye(3), up), info))
        rot, horizontal, vertical = odometry_variance(edges, poses)
        assert rot == horizontal == VARIANCE_FACTOR_MIN  # no residual there: the guard
        assert 7.0 < vertical < 11.0, vertical
        loosened = _scaled_odometry(edges, (rot, horizontal, vertical), poses)
        cov = np.linalg.inv(loosened[0].information)[3:, 3:]
        sd_up = np.sqrt((R @ cov @ R.T)[2, 2])
        sd_side = np.sqrt((R @ cov @ R.T)[0, 0])
        assert sd_up == pytest.approx(0.01 * np.sqrt(vertical), rel=1e-6)
        assert sd_side == pytest.approx(0.01 * np.sqrt(VARIANCE_FACTOR_MIN), rel=1e-6)


def test_a_few_flicks_get_their_own_factor_and_leave_the_other_edges_as_they_are():
    """White edge errors at their own sigma, and 5 of 300 edges (flicks) 20 sigma off in
    rotation: the mean over every edge loosens all of them ~3x; the robust factors stay ~1
    and only the flicks are loosened, each to fit its residual."""
    from scipy.stats import chi2

    from lidar_slam.backend.imu_gnss_solve import (
        ODOMETRY_OUTLIER_CHI2,
        _scaled_odometry,
        odometry_variance_robust,
    )
    from lidar_slam.geometry import matrix_from_rotvec

    assert ODOMETRY_OUTLIER_CHI2 == pytest.approx(chi2.ppf(0.9999, 6), abs=1e-3)

    sr, st = np.radians(0.1), 0.01
    info = np.diag([sr ** -2] * 3 + [st ** -2] * 3)
    rng = np.random.default_rng(6)
    poses, edges, flicks = {0: np.eye(4)}, [], {30, 90, 150, 210, 270}
    for k in range(1, 301):
        poses[k] = poses[k - 1] @ make_pose(np.eye(3), [0.5, 0.0, 0.0])
        rot = rng.normal(0.0, sr, 3) + (np.array([20.0 * sr, 0.0, 0.0]) if k in flicks else 0.0)
        err = make_pose(matrix_from_rotvec(rot), rng.normal(0.0, st, 3))
        edges.append(BetweenFactor(k - 1, k, make_pose(np.eye(3), [0.5, 0.0, 0.0]) @ err, info))
    assert odometry_variance(edges, poses)[0] > 2.5  # every edge loosened for five
    factors, own = odometry_variance_robust(edges, poses)
    assert all(0.7 < f < 1.4 for f in factors), factors
    assert set(own) == {(k - 1, k) for k in flicks}
    assert all(50.0 < g < 110.0 for g in own.values()), own  # ~400 / 6 with the noise
    scaled = {(e.i, e.j): e for e in _scaled_odometry(edges, factors, poses, own)}
    sd = np.sqrt(np.linalg.inv(scaled[(29, 30)].information)[0, 0])
    assert sd == pytest.approx(sr * np.sqrt(factors[0] * own[(29, 30)]), rel=1e-6)


def test_the_drift_gate_passes_a_loop_within_the_odometrys_drift_and_refuses_an_aliased_one():
    from lidar_slam.config import load_config
    from lidar_slam.loop.detector import LoopDetector
    from lidar_slam.map.keyframes import KeyframeStore

    rng = np.random.default_rng(4)
    store = KeyframeStore(None)
    room = _room(rng, 0.01)
    for k in range(20):  # 20 keyframes 0.5 m apart along x in the same room
        store.add(k, make_pose(np.eye(3), [0.5 * k, 0.0, 0.0]), room - [0.5 * k, 0, 0], None)
    det = LoopDetector(load_config(), store)
    loop_info = np.diag([np.radians(0.2) ** -2] * 3 + [0.02 ** -2] * 3)
    T_odom = make_pose(np.eye(3), [9.5, 0.0, 0.0])  # keyframe 19 seen from keyframe 0
    drifted = T_odom @ make_pose(np.eye(3), [0.03, -0.02, 0.0])
    assert det.drift_d2(0, 19, drifted, loop_info) < 10.0
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    turned = T_odom @ make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), [0.0, 0.0, 0.0])
    assert det.drift_d2(0, 19, turned, loop_info) > 1000.0
    shifted = T_odom @ make_pose(np.eye(3), [3.0, 0.0, 0.0])  # a look-alike one bay further
    assert det.drift_d2(0, 19, shifted, loop_info) > det._gate_d2
    # the gate is chi-square's (6 dof) at loop.drift_gate_p, taken without importing
    # scipy.stats into the worker: the same number
    from scipy.stats import chi2

    assert det._gate_d2 == float(chi2.isf(load_config().loop.drift_gate_p, 6))
    store.close()


def test_the_worker_weighs_each_edge_as_the_pipeline_would_in_any_order():
    """The loop detector weighs each keyframe's odometry edge from the stored clouds (what the
    back-end takes, LoopResult.edge_information): the same matrices as the pipeline's
    EdgeInformation fed in keyframe order, whatever order they are asked in (a resumed run
    asks for the later ones first), a thin keyframe None (the configured sigmas), and the
    same drift gate."""
    from lidar_slam.config import load_config
    from lidar_slam.loop import adapt
    from lidar_slam.loop.detector import LoopDetector
    from lidar_slam.map.keyframes import KeyframeStore

    rng = np.random.default_rng(5)
    store = KeyframeStore(None)
    room = _room(rng, 0.01)
    cfg = load_config()
    cfg = adapt.apply(cfg, adapt.auto_values(cfg, room))  # as the pipeline's first scan does
    for k in range(12):
        pts = room[:10] if k == 6 else room - [0.4 * k, 0, 0]
        store.add(k, make_pose(np.eye(3), [0.4 * k, 0.0, 0.0]), pts, None)
    edges = EdgeInformation(cfg.backend.odom_information, cfg.keyframes.cloud_voxel_m)
    in_order = [edges.add(store.get(k).T_world_kf_odom, store.get(k).points) for k in range(12)]
    assert in_order[0] is None and in_order[6] is None and in_order[7] is None
    loop_info = np.diag([np.radians(0.2) ** -2] * 3 + [0.02 ** -2] * 3)
    T = make_pose(np.eye(3), [4.4 + 0.03, -0.02, 0.0])
    d2 = LoopDetector(cfg, store).drift_d2(0, 11, T, loop_info)
    det = LoopDetector(cfg, store)
    for k in (11, 3, 7, 6, 0, 8, 1, 2, 4, 5, 9, 10):
        got = det.edge_information(k)
        if in_order[k] is None:
            assert got is None
        else:
            np.testing.assert_array_equal(got, in_order[k])
    assert det.drift_d2(0, 11, T, loop_info) == d2
    result = det.process(11)  # its result carries the edge's information
    np.testing.assert_array_equal(result.edge_information, in_order[11])
    store.close()


def test_loop_submaps_do_not_cross_an_odometry_edge_its_clouds_contradict():
    """A revisit where kiss-icp snapped onto its own older map: the odometry puts keyframe 7
    0.6 m above keyframe 6 while both clouds see the same room at the same height. That edge
    fails its check (the clouds registered from the odometry's pose move back by far more than
    both covariances allow), the others pass, and a submap centred on either side stops at it."""
    from lidar_slam.config import load_config
    from lidar_slam.loop import adapt
    from lidar_slam.loop.detector import LoopDetector
    from lidar_slam.map.keyframes import KeyframeStore

    rng = np.random.default_rng(6)
    store = KeyframeStore(None)
    room = _room(rng, 0.01)
    cfg = load_config()
    cfg = adapt.apply(cfg, adapt.auto_values(cfg, room))
    for k in range(12):
        jump = 0.6 if k >= 7 else 0.0  # the odometry's error from keyframe 7 on
        store.add(k, make_pose(np.eye(3), [0.4 * k, 0.0, jump]), room - [0.4 * k, 0, 0], None)
    det = LoopDetector(cfg, store)
    assert [det.edge_consistent(k) for k in range(1, 12)] == [True] * 6 + [False] + [True] * 4
    assert det.n_split == 1
    assert det._edge_d2(7) > 2 * det._gate_d2 and det._edge_d2(8) < det._gate_d2
    radius = cfg.loop.verify.submap_radius

    def n_points(centre):
        return len(det.submap(centre, radius, 11))

    per_kf = len(store.get(0).points)
    assert n_points(4) == 5 * per_kf  # 2..6: no jump inside
    assert n_points(7) == 3 * per_kf  # 7, 8, 9: not 5 or 6
    assert n_points(6) == 3 * per_kf  # 4, 5, 6: not 7 or 8
    off = LoopDetector(cfg.model_copy(update={"loop": cfg.loop.model_copy(
        update={"drift_gate_p": 0.0})}), store)  # the drift gate off: no check either
    assert off.edge_consistent(7) and len(off.submap(7, radius, 11)) == 5 * per_kf
    store.close()


def test_the_drift_gates_chi_square_quantile_is_scipys():
    from scipy.special import chdtri

    from lidar_slam.loop.detector import chi2_isf_6

    for p in (1e-12, 1e-6, 1e-3, 0.05, 0.5, 0.99):
        assert chi2_isf_6(p) == pytest.approx(float(chdtri(6, p)), rel=1e-14)
    with pytest.raises(ValueError):
        chi2_isf_6(0.0)


def test_a_loop_that_tilts_the_query_against_the_imus_gravity_is_refused(tmp_path):
    from lidar_slam.config import load_config
    from lidar_slam.loop.detector import LoopRecord, LoopResult
    from lidar_slam.pipeline import Pipeline
    from lidar_slam.types import LoopConstraint

    cfg = load_config()
    pipe = Pipeline(cfg.model_copy(update={"loop": cfg.loop.model_copy(update={"enabled": False})}),
                    tmp_path / "run")
    pipe.cfg = cfg
    pipe.result.kf_up = {0: np.array([0.0, 0.0, 1.0]), 9: np.array([0.0, 0.0, 1.0])}

    def result(roll_deg: float) -> LoopResult:
        a = np.radians(roll_deg)
        R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        T = make_pose(R, [1.0, 0.0, 0.0])
        rec = LoopRecord(90, 0, 9, 0, 0.2, 0.0, 0.9, 0.05, True, "", T)
        return LoopResult(9, (rec,), LoopConstraint(9, 0, T, np.eye(6), 0.9, 0.05))

    kept = pipe._check_tilt(result(1.0))
    assert kept.constraint is not None and kept.records[0].accepted
    refused = pipe._check_tilt(result(5.0))
    assert refused.constraint is None and not refused.records[0].accepted
    assert refused.records[0].reason.startswith("gravity: tilt 5.0 deg")
    pipe.close()


def _turning(n: int, deg_per_scan: float) -> list[np.ndarray]:
    """n poses 1 m apart turning deg_per_scan about z at every scan: constant velocity."""
    from lidar_slam.geometry import matrix_from_rotvec

    out, T = [], np.eye(4)
    step = make_pose(matrix_from_rotvec([0.0, 0.0, np.radians(deg_per_scan)]), [1.0, 0.0, 0.0])
    for _ in range(n):
        out.append(T.copy())
        T = T @ step
    return out


def test_a_keyframe_after_a_flick_carries_the_deskews_white_error_and_a_steady_one_none():
    """(scale x miss x range)^2: the miss is the rotation by which a scan left the constant-
    velocity prediction, the largest over the keyframe's scan and the two before, so a flick
    at scan 10 reaches the keyframes at scans 10-12 and no other; a steady turn misses nothing."""
    from lidar_slam.frontend.edge_information import deskew_white
    from lidar_slam.geometry import matrix_from_rotvec

    poses = _turning(20, 3.0)
    kfs = {k: p for k, p in enumerate(range(0, 20, 1))}
    ranges = dict.fromkeys(kfs, 8.0)
    assert max(deskew_white(poses, kfs, ranges, 0.03).values()) < 1e-20
    flick = np.radians(5.0)  # scan 10 turns 5 deg more about x, and stays there
    R = make_pose(matrix_from_rotvec([flick, 0.0, 0.0]), [0.0, 0.0, 0.0])
    poses = poses[:10] + [T @ R for T in poses[10:]]
    white = deskew_white(poses, kfs, ranges, 0.03)
    # scan 11 misses too: the prediction carries scan 10's flick on
    for k in (10, 11, 12, 13):
        assert white[k] == pytest.approx((0.03 * flick * 8.0) ** 2, rel=1e-6), k
    assert max(white[k] for k in kfs if k < 10 or k > 13) < 1e-20
    assert max(deskew_white(poses, kfs, ranges, 0.0).values()) == 0.0
    # a keyframe with an empty cloud (range 0) and one past the scans get nothing
    assert deskew_white(poses, {0: 11, 1: 99}, {0: 0.0, 1: 8.0}, 0.03) == {0: 0.0, 1: 0.0}
