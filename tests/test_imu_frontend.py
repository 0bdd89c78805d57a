"""The IMU in the front-end: deskew along the integrated IMU and kiss-icp started from its
prediction (lidar_slam.frontend.imu_prediction), on short simulated hand-held walks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_slam import pipeline
from lidar_slam.config import SlamConfig
from lidar_slam.eval.metrics import ate
from lidar_slam.frontend.deskew import SweepMotion, deskew
from lidar_slam.geometry import interpolate, make_pose, rotation_angle_deg
from lidar_slam.io.imu_gnss import ImuSamples
from lidar_slam.io.sources import open_source
from lidar_slam.sim import SENSORS, simulate_sequence
from lidar_slam.sim.imu_gnss import NOISELESS, ImuOptions

SENSOR = dataclasses.replace(SENSORS["vlp16"], n_azimuth=600)
N_SCANS = 45
EXTRINSIC = (0.05, -0.02, -0.04, 180.0, 0.0, 90.0)  # x y z (m), roll pitch yaw (deg)


def shaky_walk(n: int, rate_hz: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and T_world_lidar of a person with a lidar: 1 s at rest, then walking at 1.4 m/s
    while turning the sensor left and right (yaw rate up to ~150 deg/s)."""
    t = np.arange(n + 5) / rate_hz
    move = np.clip(t - 1.0, 0.0, None)
    yaw = 1.0 * np.sin(2.6 * move) * np.clip(move, 0.0, 1.0)
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    poses[:, :3, 3] = np.c_[1.4 * move, 0.3 * np.sin(0.9 * move), 1.8 + 0.0 * t]
    return t, poses


def extrinsic_matrix(xyz_rpy) -> np.ndarray:
    R = Rotation.from_euler("xyz", xyz_rpy[3:], degrees=True).as_matrix()
    return make_pose(R, np.asarray(xyz_rpy[:3], dtype=float))


def cfg_with(extrinsic=(0.0,) * 6, enabled: bool = True) -> SlamConfig:
    cfg = SlamConfig()
    return cfg.model_copy(update={
        "loop": cfg.loop.model_copy(update={"enabled": False}),
        "odometry": cfg.odometry.model_copy(update={"max_num_threads": 1}),
        "imu": cfg.imu.model_copy(update={"T_lidar_imu": list(extrinsic), "enabled": enabled})})


@pytest.fixture(scope="module")
def walks(tmp_path_factory):
    """The same noise-free walk simulated with an identity and a non-identity T_lidar_imu (the
    scans are the same; only the IMU differs)."""
    t, poses = shaky_walk(N_SCANS)
    out = {}
    for name, xyz_rpy in (("identity", (0.0,) * 6), ("rotated", EXTRINSIC)):
        d = tmp_path_factory.mktemp(name)
        simulate_sequence(poses, t, d, SENSOR, seed=5, n_scans=N_SCANS,
                          imu=ImuOptions(rate_hz=200.0, noise=NOISELESS,
                                         T_lidar_imu=extrinsic_matrix(xyz_rpy)))
        out[name] = (d, xyz_rpy)
    return out


def run(seq, cfg: SlamConfig, imu: bool = True, edit=None):
    """(poses at the stamps, ground truth, the IMU front-end or None) of a run over seq."""
    src = open_source(seq)
    given = src.inertial(imu_enabled=True, gnss_enabled=False)
    if edit is not None:
        given = dataclasses.replace(given, imu=edit(given.imu))

    pipe = pipeline.Pipeline(cfg, None, inertial=given if imu else None)
    try:
        for scan in src.scans(0, len(src)):
            pipe.process(scan)
        result = pipe.finish()
    finally:
        pipe.close()
    deviations = pipe.odometry.take_deviations()
    return np.array(result.odom_poses), src.ground_truth, pipe.inertial, deviations


def test_imu_deskew_and_prediction_track_a_fast_turning_walk_at_least_as_well_as_constant_velocity(
        walks):
    seq, xyz_rpy = walks["rotated"]
    """kiss-icp corrects the IMU's prediction far less than the constant-velocity one (its model
    deviation), and the trajectory is at least as good."""
    est_imu, gt, fe, dev_imu = run(seq, cfg_with(xyz_rpy))
    est_cv, _, _, dev_cv = run(seq, cfg_with(xyz_rpy), imu=False)
    ate_imu, ate_cv = ate(est_imu, gt).rmse_m, ate(est_cv, gt).rmse_m
    assert fe.n_imu >= N_SCANS - 10 and fe.n_gaps == 0 and fe.n_diverged == 0
    moving = slice(15, None)  # after the second at rest and the IMU's initialisation
    m_imu, m_cv = (np.median(np.linalg.norm(d[moving, :3, 3], axis=1)) for d in (dev_imu, dev_cv))
    r_imu, r_cv = (np.median(rotation_angle_deg(d[moving])) for d in (dev_imu, dev_cv))
    print(f"ATE imu {ate_imu:.4f} cv {ate_cv:.4f}; deviation imu {m_imu:.4f} m {r_imu:.3f} deg, "
          f"cv {m_cv:.4f} m {r_cv:.3f} deg")
    assert m_imu < 0.5 * m_cv and r_imu < 0.5 * r_cv
    # Measured: ATE 0.0218 m with the IMU, 0.1500 m without; bounds 1.3x (and the IMU's
    # advantage kept at 3x where it is 6.9x).
    assert ate_imu < 0.028, (ate_imu, ate_cv)
    assert ate_cv < 0.20 and ate_imu < ate_cv / 3, (ate_imu, ate_cv)


def test_a_rotated_and_offset_imu_gives_the_poses_of_an_imu_at_the_lidar(walks):
    """T_lidar_imu is applied: the same walk with the IMU mounted elsewhere, told by the
    config, ends with the same poses."""
    est_a, *_ = run(walks["identity"][0], cfg_with(walks["identity"][1]))
    est_b, _, fe, _ = run(walks["rotated"][0], cfg_with(walks["rotated"][1]))
    assert fe.n_imu >= N_SCANS - 10
    assert np.abs(est_a[:, :3, 3] - est_b[:, :3, 3]).max() < 0.01


def test_the_same_input_gives_the_same_poses_with_an_imu(walks):
    seq, xyz_rpy = walks["rotated"]
    first, *_ = run(seq, cfg_with(xyz_rpy))
    second, *_ = run(seq, cfg_with(xyz_rpy))
    # Bit for bit: one kiss-icp thread (the default), which also bounds gtsam's TBB (kiss-icp
    # sets the process-wide limit); 8e-13 m seen once under load came from two TBB threads.
    np.testing.assert_array_equal(first, second)


def test_without_an_imu_or_with_it_switched_off_the_poses_are_those_of_lidar_only(walks):
    seq, xyz_rpy = walks["rotated"]
    est_none, _, fe_none, _ = run(seq, cfg_with(xyz_rpy), imu=False)
    est_off, _, fe_off, _ = run(seq, cfg_with(xyz_rpy, enabled=False))
    assert fe_none is None and fe_off is None
    np.testing.assert_array_equal(est_none, est_off)


def test_a_gap_in_the_imu_falls_back_to_constant_velocity_counts_it_and_starts_again(walks):
    seq, xyz_rpy = walks["rotated"]

    def cut(s: ImuSamples) -> ImuSamples:
        keep = (s.stamp_s < 2.0) | (s.stamp_s > 2.4)
        return ImuSamples(s.stamp_s[keep], s.gyro_radps[keep], s.accel_mps2[keep], s.source)

    est, _, fe, _ = run(seq, cfg_with(xyz_rpy), edit=cut)
    assert fe.n_gaps >= 1 and fe.n_inits >= 2
    assert np.all(np.isfinite(est)) and len(est) == N_SCANS
    assert fe.summary()["fallbacks_imu_gap"] == fe.n_gaps


def test_a_sweep_motion_at_constant_velocity_deskews_as_the_constant_velocity_model():
    rng = np.random.default_rng(0)
    T = make_pose(Rotation.from_rotvec([0.02, -0.05, 0.3]).as_matrix(), [0.8, -0.1, 0.05])
    period, ref = 0.1, 0.05
    knots = np.linspace(-0.104, 0.06, 23) - 0.0
    motion = SweepMotion(knots, np.array([interpolate(np.eye(4), T, k / period)
                                          for k in knots]))
    points = rng.uniform(-30, 30, (500, 3))
    times = rng.uniform(-ref, ref, 500)
    np.testing.assert_allclose(motion.apply(points, times), deskew(points, times, T, period),
                               atol=1e-9)
    np.testing.assert_allclose(motion.T_ref_at(-ref), interpolate(np.eye(4), T, -ref / period),
                               atol=1e-12)


def test_a_run_with_an_imu_resumed_from_its_checkpoint_ends_as_the_uninterrupted_run(walks,
                                                                                       tmp_path):
    """The IMU front-end's state is in the checkpoint (its smoother rebuilt by replaying what
    it was fed since it was made): a run checkpointed mid-walk, with the IMU running, and
    resumed from there ends with the poses of the run never stopped, to the bit (the frame
    poses are rounded as kiss-icp's are: the replayed smoother is ~1e-14 off)."""
    from lidar_slam.run import checkpoint

    seq, xyz_rpy = walks["rotated"]
    cfg = cfg_with(xyz_rpy)
    src = open_source(seq)
    given = src.inertial(imu_enabled=True, gnss_enabled=False)
    uninterrupted, *_ = run(seq, cfg)
    out, stop = tmp_path / "run", 33
    checkpoint.start_run(out, checkpoint.describe_run(seq, 0, None, None, cfg))
    first = pipeline.Pipeline(cfg, out, inertial=given)
    for scan in src.scans(0, stop):
        first.process(scan)
    assert first.inertial.nav is not None and len(first.inertial._journal) >= 3
    checkpoint.save(out, first, first.loops_applied_upto)
    first.close()
    resumed = pipeline.Pipeline(cfg, out, resume=True, inertial=given)
    try:
        assert checkpoint.restore(out, resumed) == stop
        for scan in src.scans(stop, N_SCANS - stop):
            resumed.process(scan)
        poses = np.array(resumed.finish().odom_poses)
    finally:
        resumed.close()
    assert resumed.inertial.n_diverged == 0 and resumed.inertial.n_imu > N_SCANS - 10
    np.testing.assert_array_equal(poses, uninterrupted)


def test_a_sweep_motion_moves_each_point_with_the_pose_interpolated_between_its_knots():
    """Knots with a rate that changes from segment to segment (and one without rotation): each
    point as geometry.interpolate between the knots around it would move it, held at the ends;
    T_ref_at is that interpolation itself."""
    rng = np.random.default_rng(3)
    knots = np.cumsum(rng.uniform(0.002, 0.008, 25)) - 0.06
    poses = [make_pose(Rotation.from_rotvec(rng.normal(0.0, 0.3, 3)).as_matrix(),
                       rng.normal(0.0, 1.0, 3)) for _ in knots]
    poses[5] = poses[4].copy()  # a segment without motion
    motion = SweepMotion(knots, np.array(poses))
    points = rng.uniform(-40, 40, (2000, 3))
    times = rng.uniform(knots[0] - 0.01, knots[-1] + 0.01, 2000)
    times[:25] = knots  # on the knots themselves
    expected = np.empty_like(points)
    for n, (p, t) in enumerate(zip(points, times)):
        i = int(np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2))
        s = (np.clip(t, knots[0], knots[-1]) - knots[i]) / (knots[i + 1] - knots[i])
        T = interpolate(poses[i], poses[i + 1], s)
        expected[n] = T[:3, :3] @ p + T[:3, 3]
    np.testing.assert_allclose(motion.apply(points, times), expected, rtol=0, atol=1e-12)
    for t in (knots[0] - 1.0, knots[3], 0.5 * (knots[7] + knots[8]), knots[-1] + 1.0):
        i = int(np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2))
        s = (np.clip(t, knots[0], knots[-1]) - knots[i]) / (knots[i + 1] - knots[i])
        np.testing.assert_allclose(motion.T_ref_at(t), interpolate(poses[i], poses[i + 1], s),
                                   rtol=0, atol=1e-15)


def test_each_imu_predicted_scan_integrates_the_imu_once(walks, monkeypatch):
    """The smoother's IMU factor of a scan is the preintegration its sweep's prediction already
    ran (the same steps from the last state to the scan's reference instant): the stream is not
    integrated again per scan, only to initialise."""
    from lidar_slam.imu import ImuStream

    calls = []
    preintegrate = ImuStream.preintegrate

    def counted(self, *args, **kwargs):
        calls.append(args[:2])
        return preintegrate(self, *args, **kwargs)

    monkeypatch.setattr(ImuStream, "preintegrate", counted)
    seq, xyz_rpy = walks["rotated"]
    src = open_source(seq)
    pipe = pipeline.Pipeline(cfg_with(xyz_rpy), None,
                             inertial=src.inertial(imu_enabled=True, gnss_enabled=False))
    try:
        for scan in src.scans(0, len(src)):
            pipe.process(scan)
    finally:  # the front-end's calls only (finish's final solve integrates for its own factors)
        pipe.close()
    fe = pipe.inertial
    assert fe.n_imu >= N_SCANS - 10 and fe.n_diverged == 0
    print(f"{len(calls)} preintegrations, {fe.n_imu} IMU scans, {fe.n_inits} initialisations")
    # only _initialise's (one per scan of its window after the first) and _gravity's
    assert len(calls) < fe.n_imu // 2
