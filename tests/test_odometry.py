"""Odometry: our kiss-icp wrapper gives stock KissICP's poses on real scans."""

import numpy as np
import pytest
from kiss_icp.config import load_config as kiss_load_config
from kiss_icp.kiss_icp import KissICP
from kiss_icp.pybind import kiss_icp_pybind as kp

from lidar_slam.config import load_config
from lidar_slam.frontend import odometry
from lidar_slam.frontend.crop import range_mask
from lidar_slam.frontend.odometry import Odometry, VoxelSelector, quantised
from lidar_slam.io.sources import open_source


def test_odometry_equals_stock_kiss_icp_on_kitti(kitti16):
    """Stock KissICP's poses. Our rounding of kiss-icp's pose (odometry.pose_quantum_m) made
    fine: at its 1e-6 a rounding step tipped frame 4 of these into another of ICP's minima 1.5 mm
    away, as any perturbation of that size can (a run's chaos, not a bias: test below)."""
    src = open_source(kitti16)
    stock = KissICP(kiss_load_config(None))
    ours = Odometry(load_config(overrides={"odometry": {"pose_quantum_m": 1e-12,
                                                        "coarse_every": None,
                                                        "second_start_deg": None}}))
    for scan in src.scans(0, 8):
        stock.register_frame(scan.points, np.array([]))
        T = ours.register(scan.points)
        np.testing.assert_allclose(T, stock.last_pose, atol=1e-6)
    assert np.linalg.norm(T[:3, 3]) > 5.0  # the car moved ~6 m


def test_quantised_pose_is_a_rigid_motion_within_the_quantum():
    rng = np.random.default_rng(3)
    for _ in range(50):
        w = rng.normal(size=3)
        th = np.linalg.norm(w)
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / th
        T = np.eye(4)
        T[:3, :3] = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
        T[:3, 3] = rng.normal(scale=300.0, size=3)
        Q = quantised(T)
        np.testing.assert_allclose(Q[:3, :3] @ Q[:3, :3].T, np.eye(3), atol=1e-14)
        assert np.linalg.det(Q[:3, :3]) > 0 and np.array_equal(Q[3], [0, 0, 0, 1])
        assert np.abs(Q - T).max() <= odometry.POSE_QUANTUM
        # Two inputs 1e-14 apart (kiss-icp's threads) give the same bytes, unless an entry is
        # that close to a rounding boundary (probability ~1e-7 here).
        T2 = T.copy()
        T2[:3] += rng.uniform(-1e-14, 1e-14, size=(3, 4))
        near = np.abs(T[:3] / odometry.POSE_QUANTUM % 1 - 0.5).min() < 1e-6
        assert np.array_equal(quantised(T2), Q) or near


def _selected_on_a_tagged_copy(points, voxel_m, min_range_m, max_range_m):
    """The selection as first written: kiss-icp's downsample of a NumPy copy of the points
    whose x carries each point's index in its lowest 22 bits, then the range crop."""
    tagged = np.array(points, dtype=np.float64, order="C")
    x = tagged[:, 0].view(np.uint64)
    x &= ~np.uint64((1 << 22) - 1)
    x |= np.arange(len(points), dtype=np.uint64)
    chosen = np.asarray(kp._voxel_down_sample(kp._Vector3dVector(tagged), voxel_m))
    chosen = chosen[range_mask(chosen, min_range_m, max_range_m)]
    return (np.ascontiguousarray(chosen[:, 0]).view(np.uint64) & ((1 << 22) - 1)).astype(np.int64)


def test_voxel_selection_is_the_tagged_copy_selection_in_the_same_order(kitti16):
    select = VoxelSelector()
    scans = list(open_source(kitti16).scans(0, 2))
    # a small input first: the tags grow for the larger scans after it
    for points in (scans[0].points[:1000], scans[0].points, scans[1].points,
                   scans[1].points.astype(np.float32)):
        untouched = points.copy()
        for voxel_m, min_range_m, max_range_m in ((0.5, 0.0, 100.0), (1.0, 5.0, 30.0)):
            idx = select(points, voxel_m, min_range_m, max_range_m)
            assert idx.dtype == np.int64
            np.testing.assert_array_equal(
                idx, _selected_on_a_tagged_copy(points, voxel_m, min_range_m, max_range_m))
        np.testing.assert_array_equal(points, untouched)  # the caller's points stay as read
    assert len(select(scans[0].points[:0], 0.5, 0.0, 100.0)) == 0


def test_predict_extrapolates_constant_velocity():
    odo = Odometry(load_config())
    odo.last_delta = np.eye(4)
    odo.last_delta[0, 3] = 1.5
    assert odo.predict()[0, 3] == 1.5 and odo.predict()[0, 3] == 3.0


@pytest.mark.shared_data
def test_slow_scans_refined_against_keyframes_keep_the_turn_kiss_icp_loses(kitti_gt, tmp_path):
    """Sim 07 frames 636-675: the car brakes from 4.6 m/s to a stop while turning 5 deg.
    kiss-icp alone (as stock) is pulled towards standing still by the ground's scan rings and
    loses ~3 deg and ~2 m; with the slow scans refined (the default) both stay small."""
    from lidar_slam import pipeline
    from lidar_slam.geometry import inverse, rotation_angle_deg
    from lidar_slam.sim import load_kitti_truth, simulate_sequence

    kt = load_kitti_truth(kitti_gt, 7)
    sim = simulate_sequence(kt.poses_world_lidar, kt.stamps_s, tmp_path / "seq", start=636,
                            n_scans=40, Tr_cam_lidar=kt.Tr_cam_lidar)
    gt = inverse(sim.poses_world_lidar[0]) @ sim.poses_world_lidar

    def end_error(refine_below_mps: float) -> tuple[float, float, int]:
        cfg = load_config(overrides={"loop": {"enabled": False},
                                     "odometry": {"refine_below_mps": refine_below_mps,
                                                  "max_num_threads": 1}})
        res = pipeline.run(open_source(tmp_path / "seq").scans(), cfg)
        res.store.close()
        P = res.final_poses()
        err = inverse(inverse(P[0]) @ P[-1]) @ (inverse(gt[0]) @ gt[-1])
        return float(np.linalg.norm(err[:3, 3])), float(rotation_angle_deg(err)), \
            res.refined_scans[0]

    off_m, off_deg, n_off = end_error(0.0)
    on_m, on_deg, n_on = end_error(5.0)
    assert n_off == 0 and n_on >= 25
    assert off_deg > 1.5 and off_m > 1.0, (off_m, off_deg)  # the failure is still there
    assert on_deg < 0.5 and on_m < 0.3, (on_m, on_deg)


def test_a_fast_car_is_not_refined_and_a_braking_one_is():
    """odometry.refine_below_mps (5 m/s) on the last motion over the period; 0 switches the
    refinement off whatever the speed (lidar only, a speed that lasts is refined on proof:
    refine_fast_after_s, the test above)."""
    odo = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1}}))
    for step_m, period_s, slow in ((1.0, 0.1, False), (0.45, 0.1, True), (0.55, 0.1, False),
                                   (2.0, 0.5, True), (0.0, 0.1, True)):
        odo.last_delta = np.eye(4)
        odo.last_delta[:3, 3] = [0.6 * step_m, 0.8 * step_m, 0.0]
        assert odo.is_slow(period_s) is slow, (step_m, period_s)
    odo = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1,
                                                       "refine_below_mps": 0.0}}))
    odo.last_delta = np.eye(4)
    assert odo.is_slow(0.1) is False


@pytest.mark.shared_data
def test_a_car_at_speed_is_refined_lidar_only_once_the_speed_has_lasted(kitti_gt, tmp_path):
    """odometry.refine_fast_after_s (1 s): lidar only, scans at or above refine_below_mps are
    refined (each kept only when its held-out points prove it) once the motion has stayed that
    fast for a second, never before and never when it is off. KITTI 07 from frame 400: ~10 m/s."""
    from lidar_slam import pipeline
    from lidar_slam.sim import load_kitti_truth, simulate_sequence

    kt = load_kitti_truth(kitti_gt, 7)
    simulate_sequence(kt.poses_world_lidar, kt.stamps_s, tmp_path / "seq", start=400,
                      n_scans=16, Tr_cam_lidar=kt.Tr_cam_lidar)

    at_speed = []

    def asked(**odo) -> int:
        cfg = load_config(overrides={"loop": {"enabled": False},
                                     "odometry": {"max_num_threads": 1, **odo}})
        res = pipeline.run(open_source(tmp_path / "seq").scans(), cfg)
        res.store.close()
        n_refined, n_refused, n_unproven, n_skipped = res.refined_scans
        at_speed.append(res.refined_at_speed)
        assert res.refined_at_speed <= n_refined
        return n_refined + n_refused + n_unproven + n_skipped

    off = asked(refine_fast_after_s=None)  # scan 1 only: no motion known yet, so "slow"
    assert off <= 1
    # ten fast registrations (1 s) make the next scans refined: 11-15
    assert asked() - off == 5
    assert asked(refine_fast_after_s=5.0) == off  # 1.6 s never lasts 5 s
    assert at_speed[0] == at_speed[2] == 0 and at_speed[1] >= 1  # summary.json counts them


def _run_whole(cfg, scans, out):
    """One uninterrupted run of scans (the reference a resumed run must reproduce)."""
    from lidar_slam import pipeline

    full = pipeline.Pipeline(cfg, out)
    try:
        for s in scans:
            full.process(s)
        return full.finish()
    finally:
        full.close()


def _cut_at_a_keyframe(cfg, scans, run, ready):
    """Process scans until a keyframe is made with ready(i, pipe) true, checkpoint there as the
    CLI does, and return (the pipeline, still open, the number of scans processed)."""
    from lidar_slam import pipeline
    from lidar_slam.run import checkpoint

    first = pipeline.Pipeline(cfg, run)
    checkpoint.start_run(run, {"test": 1})
    for i, s in enumerate(scans):
        n_kf = len(first.result.store)
        first.process(s)
        if len(first.result.store) != n_kf and ready(i, first):
            checkpoint.save(run, first, first.loops_applied_upto)
            return first, i + 1
    first.close()
    raise AssertionError("no keyframe where the cut was wanted")


def _resume_to_the_end(cfg, scans, run, k, check=None):
    """Restore the checkpoint in run (taken after k scans) into a fresh pipeline, call
    check(pipeline) if given, process the rest of scans and return the finished result."""
    from lidar_slam import pipeline
    from lidar_slam.run import checkpoint

    resumed = pipeline.Pipeline(cfg, run, resume=True)
    try:
        assert checkpoint.restore(run, resumed) == k
        if check is not None:
            check(resumed)
        for s in scans[k:]:
            resumed.process(s)
        return resumed.finish()
    finally:
        resumed.close()


@pytest.mark.shared_data
def test_resume_rebuilds_the_slow_scan_refinement_exactly(kitti_gt, tmp_path):
    """A checkpoint taken at a keyframe in the middle of a slow stretch, restored into a fresh
    pipeline, continues with the same refinement target: every later pose within 1e-9."""
    from lidar_slam.sim import load_kitti_truth, simulate_sequence

    kt = load_kitti_truth(kitti_gt, 7)
    simulate_sequence(kt.poses_world_lidar, kt.stamps_s, tmp_path / "seq", start=636,
                      n_scans=30, Tr_cam_lidar=kt.Tr_cam_lidar)
    cfg = load_config(overrides={"loop": {"enabled": False},
                                 "odometry": {"max_num_threads": 1}})
    scans = list(open_source(tmp_path / "seq").scans())
    res_full = _run_whole(cfg, scans, tmp_path / "full")
    P_full = res_full.final_poses()

    run = tmp_path / "cut"
    first, k = _cut_at_a_keyframe(cfg, scans, run, lambda i, pipe: i >= 10)
    assert first.odometry.n_refined > 0
    first.close()
    res = _resume_to_the_end(cfg, scans, run, k)
    assert res.refined_scans[0] > 0
    # the coarse pass's count (odometry_coarse_scans) survives the checkpoint too
    assert res.coarse_scans == res_full.coarse_scans > 0
    assert res.second_start == res_full.second_start  # (odometry_second_start) likewise
    # kiss-icp's map comes back point by point, so its sums may run in another order: the
    # last bits may differ (1e-13 m seen); without the target rebuilt it is centimetres.
    np.testing.assert_allclose(res.final_poses(), P_full, rtol=0, atol=1e-9)


def test_a_scan_refined_at_speed_matches_more_keyframes_than_a_slow_one(monkeypatch):
    """odometry.refine_keyframes_at_speed (12): lidar only, a scan refined for its lasting
    speed is matched against the last 12 keyframes' clouds; a slow scan, the failure watch and
    a reset's map keep the last refine_keyframes (4). With an IMU, and in an IMU run's
    calibration pass, every target stays 4 keyframes."""
    from lidar_slam.frontend import odometry as odometry_module

    built = []

    class Target:  # records which clouds each target is made of, then refines nothing
        def __init__(self, points, *args):
            built.append(len(points))

        def __len__(self):
            return 0

    monkeypatch.setattr(odometry_module, "PlaneTarget", Target)
    cfg = load_config(overrides={"odometry": {"max_num_threads": 1}})
    odo = Odometry(cfg)
    assert odo.n_anchors == 12
    for k in range(14):  # keyframe k's cloud has k + 1 points
        T = np.eye(4)
        T[0, 3] = k
        odo.add_anchor(T, np.zeros((k + 1, 3)))
    pose = np.eye(4)
    odo._refine(np.zeros((50, 3)), pose, evidence=False, predicted=False, at_speed=True)
    odo._refine(np.zeros((50, 3)), pose, evidence=False, predicted=False, at_speed=False)
    assert built == [sum(range(3, 15)), sum(range(11, 15))]  # the last 12, the last 4
    assert [len(p) for _, p in odo._recent()] == [11, 12, 13, 14]
    assert Odometry(cfg, imu=True).n_anchors == 4
    assert Odometry(cfg, lidar_only=False).n_anchors == 4
    off = load_config(overrides={"odometry": {"refine_keyframes_at_speed": None}})
    assert Odometry(off).n_anchors == 4
    slow_off = load_config(overrides={"odometry": {"refine_below_mps": 0.0}})
    assert Odometry(slow_off).n_anchors == 4  # nothing is refined, at speed or not


@pytest.mark.shared_data
def test_resume_rebuilds_the_refinement_at_speed_exactly(kitti_gt, tmp_path):
    """A checkpoint taken at a keyframe while a car is refined at speed, against more keyframes
    than a slow scan would be (refine_keyframes_at_speed): the resumed run gets the same
    anchors back and every later pose within 1e-9, and the same corrections' statistics for
    the covariances' floor (backend.refinement_floor). A checkpoint from before those were
    kept with their count starts them again rather than divide old counts into new sums."""
    from lidar_slam.sim import load_kitti_truth, simulate_sequence

    kt = load_kitti_truth(kitti_gt, 7)
    simulate_sequence(kt.poses_world_lidar, kt.stamps_s, tmp_path / "seq", start=400,
                      n_scans=40, Tr_cam_lidar=kt.Tr_cam_lidar)
    cfg = load_config(overrides={"loop": {"enabled": False},
                                 "odometry": {"max_num_threads": 1, "refine_keyframes": 2,
                                              "refine_keyframes_at_speed": 5},
                                 "backend": {"odom_information": {
                                     "floor_from_refinement_scans": 1}}})
    scans = list(open_source(tmp_path / "seq").scans())
    full = _run_whole(cfg, scans, tmp_path / "full")
    P_full = full.final_poses()
    assert full.refinement_floor is not None

    run = tmp_path / "cut"
    first, k = _cut_at_a_keyframe(cfg, scans, run,
                                  lambda i, pipe: i >= 20 and len(pipe.odometry._anchors) > 2)
    assert first.odometry.n_refined_at_speed > 0
    assert first.odometry._at_speed()  # cut while the car is refined at speed
    n_anchors, at_speed_before = len(first.odometry._anchors), first.odometry.n_refined_at_speed
    first.close()

    def same_anchors(resumed):
        assert len(resumed.odometry._anchors) == n_anchors

    res = _resume_to_the_end(cfg, scans, run, k, check=same_anchors)
    assert res.refined_at_speed > at_speed_before  # refined at speed after the resume too
    np.testing.assert_allclose(res.final_poses(), P_full, rtol=0, atol=1e-9)
    for key, value in full.refinement_floor.items():
        if key != "seconds":
            np.testing.assert_allclose(res.refinement_floor[key], value, rtol=1e-9)

    # an older checkpoint: the counters before the corrections' count (15 of them, or fewer)
    from lidar_slam.frontend.odometry import Odometry

    odo = Odometry(cfg)
    state = first.odometry.state()
    assert first.odometry.speed_corrections > 0
    odo.restore(state, np.zeros((0, 4, 4)))
    assert odo.speed_corrections == first.odometry.speed_corrections
    np.testing.assert_array_equal(odo.speed_correction_sq, first.odometry.speed_correction_sq)
    state["counters"] = state["counters"][:18]  # 3 + 15: the sums without their count
    odo.restore(state, np.zeros((0, 4, 4)))
    assert odo.speed_corrections == 0 and odo.speed_correction_m == 0.0
    assert not odo.speed_correction_sum.any() and not odo.speed_correction_sq.any()
    assert odo.n_refined_at_speed == first.odometry.n_refined_at_speed


def _similarity_scale(est: np.ndarray, truth: np.ndarray) -> float:
    """The scale s that best maps truth positions onto est's (Umeyama with scale)."""
    a, b = truth - truth.mean(0), est - est.mean(0)
    U, S, Vt = np.linalg.svd(b.T @ a / len(a))
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(U @ Vt))
    return float((S * d).sum() / (a ** 2).sum(1).mean())


def test_refined_slow_scans_do_not_stretch_a_handheld_indoor_walk(handheld_walk, tmp_path):
    """A walk is all slow scans, each refined. Its source used to be the centroids of kiss-icp's
    1.5 m source voxels (~200 points per OS1-64 scan indoors, corners averaged off the walls):
    the odometry came out 2.7 % too long on this walk (1.1 % with the half-voxel points)."""
    import subprocess
    import sys

    from lidar_slam.io.trajectory import read_kitti_poses

    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(handheld_walk),
                           "--out", str(tmp_path / "run"), "--no-loops"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    est = read_kitti_poses(tmp_path / "run" / "odometry_kitti.txt")
    truth = open_source(handheld_walk).ground_truth[: len(est)]
    scale = _similarity_scale(est[:, :3, 3], truth[:, :3, 3])
    assert abs(scale - 1.0) < 0.02, scale


def _room(rng, n: int, noise_m: float, shift_wall_m: float = 0.0) -> np.ndarray:
    """n points (N, 3) on the floor, ceiling and walls of a 20 x 10 x 3 m room around the origin
    (sensor at 1.5 m), the +x end wall moved out by shift_wall_m, with Gaussian noise."""
    u = rng.uniform(-1, 1, size=(n, 2))
    face = rng.integers(0, 6, size=n)
    x, y, z = 10.0 * u[:, 0], 5.0 * u[:, 1], 1.5 * u[:, 1]
    pts = np.select([face[:, None] == k for k in range(6)], [
        np.c_[x, y, np.full(n, -1.5)], np.c_[x, y, np.full(n, 1.5)],
        np.c_[np.full(n, 10.0 + shift_wall_m), y, z], np.c_[np.full(n, -10.0), y, z],
        np.c_[x, np.full(n, 5.0), z], np.c_[x, np.full(n, -5.0), z]])
    return pts + rng.normal(0, noise_m, size=pts.shape)


def _refined(target: np.ndarray, scan: np.ndarray, T_kiss: np.ndarray) -> tuple[Odometry,
                                                                                  np.ndarray]:
    odo = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1,
                                                       "refine_evidence": True}}))
    odo.add_anchor(np.eye(4), target)
    return odo, odo._refine(scan, T_kiss, evidence=True, predicted=False)


def test_refinement_matches_closer_on_a_scan_the_imu_predicted(monkeypatch):
    """A run with an IMU refines a scan the IMU predicted with matches up to
    odometry.refine_imu_correspondence_m (kiss-icp started within centimetres: farther matches
    are mostly to surfaces the keyframes never saw); a scan from the constant-velocity guess,
    and every scan of a lidar-only run, with refine_max_correspondence_m."""
    from lidar_slam.registration import PlaneTarget

    seen = []
    align = PlaneTarget.align
    monkeypatch.setattr(PlaneTarget, "align", lambda self, src, T, corr: (
        seen.append(corr), align(self, src, T, corr))[1])
    rng = np.random.default_rng(0)
    target, scan = _room(rng, 40000, 0.005), _room(rng, 6000, 0.01)
    cfg = load_config(overrides={"odometry": {"max_num_threads": 1, "refine_evidence": False,
                                              "refine_imu_correspondence_m": 0.25}})
    for imu, predicted, expected in ((True, True, 0.25), (True, False, 1.0),
                                     (False, True, 1.0), (False, False, 1.0)):
        odo = Odometry(cfg, imu=imu)
        odo.add_anchor(np.eye(4), target)
        odo._refine(scan, np.eye(4), evidence=False, predicted=predicted)
        assert seen[-1] == expected, (imu, predicted, seen)


def test_slow_scan_refinement_refused_when_its_target_pulls_it_off():
    """The keyframes' cloud has the end wall 0.3 m out (a moved wall, a keyframe placed
    wrongly): plane ICP from the true pose is pulled along x, and the scan's held-out points
    (which fit the truth) refuse it: kiss-icp's pose stands, counted as refused by evidence."""
    from lidar_slam.frontend.odometry import plane_evidence
    from lidar_slam.registration import PlaneTarget

    rng = np.random.default_rng(0)
    target, scan = _room(rng, 40000, 0.005, shift_wall_m=0.3), _room(rng, 6000, 0.01)
    odo, T = _refined(target, scan, np.eye(4))
    np.testing.assert_array_equal(T, np.eye(4))
    assert odo.n_refined == 0 and odo.n_refine_skipped + odo.n_refine_unproven == 1
    # The ICP itself (what the always rule kept) moves the pose off the truth, and the same
    # held-out points find it worse.
    pt = PlaneTarget(target, 0.5, 20, 1.0)
    T_icp = pt.align(scan[::3], np.eye(4), 1.0)
    assert T_icp[0, 3] > 0.02, T_icp[:3, 3]
    ev = plane_evidence(pt, scan[1::3], np.eye(4), T_icp, 1.0)
    assert ev.gain_m < 0 and not ev.proven(2.0), ev


def test_plane_evidence_with_the_early_checks_residuals_equals_it_without():
    """The refinement hands the held-out points' residuals at kiss-icp's pose from the early
    check to the check after the ICP (one nearest-neighbour search less per slow scan): the
    same evidence, bit for bit, for both checks."""
    from lidar_slam.frontend.odometry import _plane_residuals, plane_evidence
    from lidar_slam.geometry import matrix_from_rotvec
    from lidar_slam.registration import PlaneTarget

    rng = np.random.default_rng(2)
    target, scan = _room(rng, 40000, 0.005), _room(rng, 6000, 0.01)
    T_kiss = np.eye(4)
    T_kiss[:3, :3] = matrix_from_rotvec(np.radians([0.0, 0.2, 0.5]))
    T_kiss[:3, 3] = [0.08, -0.03, 0.02]
    pt = PlaneTarget(target, 0.5, 20, 1.0)
    held = scan[1::3]
    at_kiss = _plane_residuals(pt, held, T_kiss, 1.0)
    T_icp = pt.align(scan[::3], T_kiss, 1.0)
    for T_other in (None, T_icp):
        assert (plane_evidence(pt, held, T_kiss, T_other, 1.0, at_kiss)
                == plane_evidence(pt, held, T_kiss, T_other, 1.0))


def test_slow_scan_refinement_kept_when_it_mends_kiss_icps_pose():
    """kiss-icp's pose 8 cm and 0.5 deg off in a room the keyframes saw as it is: the plane
    ICP brings it back and the held-out points prove it; refined, counted."""
    from lidar_slam.geometry import matrix_from_rotvec

    rng = np.random.default_rng(1)
    target, scan = _room(rng, 40000, 0.005), _room(rng, 6000, 0.01)
    T_kiss = np.eye(4)
    T_kiss[:3, :3] = matrix_from_rotvec(np.radians([0.0, 0.0, 0.5]))
    T_kiss[:3, 3] = [0.08, -0.03, 0.02]
    odo, T = _refined(target, scan, T_kiss)
    assert odo.n_refined == 1 and odo.last_evidence.proven(2.0)
    assert np.linalg.norm(T[:3, 3]) < 0.01 and np.linalg.norm(T_kiss[:3, 3]) > 0.08
    assert odo.n_refine_skipped == odo.n_refine_unproven == odo.n_refine_refused == 0


def test_summary_counts_each_slow_scan_refinement_outcome(tmp_path):
    """summary.json says how many slow scans were refined, refused by the correction gate, by
    the held-out evidence after the ICP, or before it; every slow registered scan after the
    first keyframe is one of them."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "sample_scans"
    (tmp_path / "proven.yaml").write_text("odometry:\n  refine_evidence: true\n")
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(sample), "--out",
                           str(tmp_path / "o"), "--no-loops", "--n-scans", "30",
                           "-c", str(tmp_path / "proven.yaml")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    counts = [s[k] for k in ("odometry_refined_scans", "odometry_refine_refused",
                             "odometry_refine_unproven", "odometry_refine_skipped")]
    assert all(isinstance(c, int) and c >= 0 for c in counts) and sum(counts) > 0, counts


def test_kiss_icp_iterations_are_capped_only_from_the_imus_prediction(kitti16):
    """odometry.imu_max_num_iterations: a scan started from the IMU's prediction stops there (one
    iteration leaves a 0.3 m-off start short of where 500 converge); a constant-velocity start
    keeps kiss-icp's max_num_iterations."""
    scans = [s.points for s in open_source(kitti16).scans(0, 2)]

    def second(cap, guess_offset_m, capped=True):
        odo = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1,
                                                           "imu_max_num_iterations": cap}}),
                       imu=True)
        odo.register(scans[0])
        guess = None
        if guess_offset_m is not None:
            guess = np.eye(4)
            guess[:3, 3] = [0.8 + guess_offset_m, guess_offset_m, 0.0]  # the car moves ~0.8 m
        return odo.register(scans[1], initial_guess=guess, capped=capped)

    converged = second(None, 0.3)
    capped = second(1, 0.3)
    assert np.linalg.norm(capped[:3, 3] - converged[:3, 3]) > 0.01
    np.testing.assert_array_equal(second(1, None), second(None, None))
    # a guess that is not the IMU's full prediction (the extrinsic calibration's) is not capped
    np.testing.assert_array_equal(second(1, 0.3, capped=False), converged)


def test_coarse_pass_starts_kiss_icp_only_without_the_imu_and_with_enough_points(kitti16):
    """odometry.coarse_every: from the constant-velocity guess kiss-icp first aligns every 4th
    point of its source, then all of it from there, to the same minimum on a car (within 1 mm);
    not from the IMU's prediction, not for the first scan (no map), and not when the subsample
    keeps fewer than data.min_points points. Counted in summary.json (odometry_coarse_scans)."""
    scans = [s.points for s in open_source(kitti16).scans(0, 4)]

    def run(guess=None, **odometry_cfg):
        odo = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1,
                                                           **odometry_cfg}}))
        poses = [odo.register(p, initial_guess=None if k == 0 else guess)
                 for k, p in enumerate(scans)]
        return odo, poses

    coarse, with_coarse = run()
    off, without = run(coarse_every=None)
    assert (coarse.n_coarse, off.n_coarse) == (3, 0)
    # the whole source starts where the pass on every 4th point ended, and kiss-icp's adaptive
    # threshold still sees the correction of the constant-velocity guess
    calls = []

    class Spy:
        def __init__(self, reg):
            self.reg = reg

        def _align_points_to_map(self, **kw):
            T = self.reg._align_points_to_map(**kw)
            calls.append((len(kw["points"]), np.array(kw["initial_guess"]), np.array(T)))
            return T

    spied = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1}}))
    spied._registration = Spy(spied._registration)
    T0 = spied.register(scans[0])
    cv_guess = spied.last_pose @ spied.last_delta
    T1 = spied.register(scans[1])
    assert len(calls) == 3  # scan 0 alone (no map), then two for scan 1
    (n_sub, guess_sub, T_sub), (n_all, guess_all, _) = calls[1], calls[2]
    assert n_all > 3 * n_sub
    np.testing.assert_array_equal(guess_sub, cv_guess)
    np.testing.assert_array_equal(guess_all, T_sub)
    np.testing.assert_array_equal(spied._deviations[-1], np.linalg.inv(cv_guess) @ T1)
    np.testing.assert_array_equal(T0, np.eye(4))
    for a, b in zip(with_coarse, without):
        assert np.linalg.norm(a[:3, 3] - b[:3, 3]) < 1e-3
    assert np.linalg.norm(with_coarse[-1][:3, 3]) > 2.0  # the car moved
    guess = np.eye(4)
    guess[0, 3] = 0.8  # an IMU's prediction of the next pose
    assert run(guess)[0].n_coarse == 0
    with_imu = Odometry(load_config(), imu=True)  # its constant-velocity scans too
    for p in scans:
        with_imu.register(p)
    assert with_imu.n_coarse == 0
    crop = coarse._crop._preprocess(kp._Vector3dVector(scans[1]), np.zeros(0), np.eye(4))
    source = kp._voxel_down_sample(kp._voxel_down_sample(crop, coarse.voxel_size_m * 0.5),
                                   coarse.voxel_size_m * 1.5)
    n_coarse = len(np.asarray(source)[::4])
    few = Odometry(load_config(overrides={"data": {"min_points": n_coarse + 1}}))
    few.register(scans[0])
    assert few.register(scans[1]) is not None and few.n_coarse == 0


def _seen_from(points: np.ndarray, T_world_sensor: np.ndarray) -> np.ndarray:
    """points (N, 3) of the world as a sensor at T_world_sensor sees them (no motion in the
    sweep)."""
    return (points - T_world_sensor[:3, 3]) @ T_world_sensor[:3, :3]


def test_a_flick_that_stops_is_registered_from_the_last_pose_too(kitti16):
    """odometry.second_start_deg: a 20 deg turn in one scan, then none. From the constant-velocity
    guess (40 deg) kiss-icp settles 17 deg off the scan's pose; started from the last pose as
    well, the better-fitting pose (against the last keyframe's cloud) is the scan's own.
    Counted in summary.json (odometry_second_start); never from the IMU's prediction (but on an
    IMU run's scans it does not predict), not in the T_lidar_imu calibration pass, and not
    after a turn under the limit."""
    from scipy.spatial.transform import Rotation

    from lidar_slam.geometry import make_pose, rotation_angle_deg

    world = next(iter(open_source(kitti16).scans(0, 1))).points[:, :3].astype(np.float64)
    turned = make_pose(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [0.0, 0.0, 0.0])

    def run(poses, guesses=None, kind=None, **odometry_cfg):
        odo = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1,
                                                           **odometry_cfg}}),
                       **(kind or {"lidar_only": True}))
        out = []
        for k, T in enumerate(poses):
            out.append(odo.register(_seen_from(world, T),
                                    initial_guess=None if guesses is None else guesses[k]))
            if k == 0:
                odo.add_anchor(np.eye(4), world)  # the first scan is a keyframe
        return odo, [rotation_angle_deg(np.linalg.inv(T) @ P) for T, P in zip(poses, out)]

    odo, off_deg = run([np.eye(4), turned, turned])
    assert max(off_deg) < 0.1
    assert (odo.n_second_tried, odo.n_second_taken) == (1, 1)
    again = Odometry(load_config(overrides={"odometry": {"max_num_threads": 1}}),
                     lidar_only=True)
    again.restore(odo.state(), odo.take_deviations())  # a checkpoint keeps the counts
    assert (again.n_second_tried, again.n_second_taken) == (1, 1)
    single, off_deg = run([np.eye(4), turned, turned], second_start_deg=None)
    assert off_deg[2] > 10.0 and single.n_second_tried == 0  # what it mends
    # the IMU's prediction: one start, its own
    imu, _ = run([np.eye(4), turned, turned], guesses=[None, turned, turned],
                 kind={"imu": True})
    assert imu.n_second_tried == 0
    # an IMU run's scan its IMU does not predict (a gap after the turn): as lidar only
    unpredicted, off_deg = run([np.eye(4), turned, turned], guesses=[None, turned, None],
                               kind={"imu": True})
    assert unpredicted.n_second_tried == 1 and max(off_deg) < 0.1
    # the T_lidar_imu calibration pass (neither): one start
    calibration, _ = run([np.eye(4), turned, turned], guesses=[None, turned, None],
                         kind={"lidar_only": False})
    assert calibration.n_second_tried == 0
    # a turn under the limit (3 deg a scan): one start
    slow = make_pose(Rotation.from_euler("z", 3, degrees=True).as_matrix(), [0.0, 0.0, 0.0])
    calm, _ = run([np.eye(4), slow, slow @ slow])
    assert calm.n_second_tried == 0


def test_resume_rebuilds_the_second_start_exactly(trot_end, tmp_path):
    """A checkpoint taken at a keyframe of a lidar-only trot whose turns have set off second
    starts (odometry.second_start_deg): the resumed run starts from the same places, judges by
    the same keyframes and gives every later pose within 1e-9, trying second starts again."""

    cfg = load_config(overrides={"loop": {"enabled": False},
                                 "odometry": {"max_num_threads": 1}})
    scans = list(open_source(trot_end).scans())
    res_full = _run_whole(cfg, scans, tmp_path / "full")
    run = tmp_path / "cut"
    first, k = _cut_at_a_keyframe(cfg, scans, run,
                                  lambda i, pipe: i >= 20 and pipe.odometry.n_second_tried > 0)
    tried_before = first.odometry.n_second_tried
    first.close()
    res = _resume_to_the_end(cfg, scans, run, k)
    assert res.second_start == res_full.second_start and res.second_start[0] > tried_before
    np.testing.assert_allclose(res.final_poses(), res_full.final_poses(), rtol=0, atol=1e-9)
