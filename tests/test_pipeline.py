"""The pipeline on sample_scans (simulated, true motion distortion, exact truth): deskew, loops."""

from pathlib import Path

import numpy as np
import pytest

from lidar_slam import pipeline
from lidar_slam.config import load_config
from lidar_slam.eval.metrics import rpe
from lidar_slam.frontend.odometry import Odometry
from lidar_slam.geometry import inverse
from lidar_slam.io.sources import open_source

SAMPLE = Path(__file__).resolve().parents[1] / "sample_scans"
SAMPLE_CONFIG = SAMPLE.parent / "configs" / "sample.yaml"


def _odometry_rpe(deskew: bool) -> float:
    src = open_source(SAMPLE)
    cfg = load_config(overrides={"loop": {"enabled": False}, "data": {"deskew": deskew}})
    result = pipeline.run(src.scans(), cfg)
    gt = inverse(src.ground_truth[0]) @ src.ground_truth
    return rpe(result.final_poses(), gt).trans_m_mean


def test_deskew_lowers_per_frame_error_on_distorted_scans():
    with_deskew, without = _odometry_rpe(True), _odometry_rpe(False)
    assert with_deskew < 0.9 * without, (with_deskew, without)


def test_kiss_icp_never_deskews_a_second_time():
    # Our front-end deskews; kiss-icp's preprocessor (used for its range crop) must leave the
    # points where they are, even with a large motion estimate and per-point times at hand.
    from kiss_icp.pybind import kiss_icp_pybind as kp

    odo = Odometry(load_config())
    pts = np.random.default_rng(0).uniform(-20, 20, (5000, 3))
    motion = np.eye(4)
    motion[0, 3] = 2.0
    for times in (np.zeros(0), np.linspace(0, 1, len(pts))):
        out = np.asarray(odo._crop._preprocess(kp._Vector3dVector(pts), times, motion))
        np.testing.assert_array_equal(out, pts)  # all in range: nothing moved, nothing dropped


def test_heavy_libraries_load_only_when_needed():
    """scipy.spatial (~0.4 s) loads when the ring-key tree is first needed and gtsam when the
    back-end starts, not at import: `--no-loops` skips both; a run never loads open3d
    (tests/test_verify.py checks a whole run)."""
    import subprocess
    import sys

    code = ("import sys, lidar_slam.cli, lidar_slam.pipeline, lidar_slam.loop.detector, "
            "lidar_slam.run.outputs\n"
            "print(sorted(m for m in ('open3d', 'gtsam', 'scipy.spatial') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_an_empty_scan_does_not_shift_the_next_poses():
    """A skipped (empty) scan's predicted pose is moved to its stamp and the clock keeps going,
    so the next scan's stamp correction spans one period (it spanned two: 0.40 m off)."""
    import dataclasses

    src = open_source(SAMPLE)
    cfg = load_config(SAMPLE_CONFIG, {"loop": {"enabled": False}})
    k = 30

    def scans():
        for s in src.scans():
            if s.index == k:
                s = dataclasses.replace(s, points=s.points[:0], point_times=s.point_times[:0],
                                        intensity=None)
            yield s

    P = np.stack(pipeline.run(scans(), cfg).odom_poses)
    G = src.ground_truth
    for j in (k + 1, k + 2, k + 3):
        err = inverse(inverse(G[k - 1]) @ G[j]) @ (inverse(P[k - 1]) @ P[j])
        assert np.linalg.norm(err[:3, 3]) < 0.15, j


def test_first_frame_refers_to_its_stamp_when_moving():
    """Frame 0 is registered before any velocity is known; once the first motion is estimated
    its pose moves from mid-sweep to its stamp. Starting sample_scans at 20 (1.37 m/frame), the
    first step was off by half a sweep's motion (0.73 m); it is now like the others."""
    src = open_source(SAMPLE)
    cfg = load_config(SAMPLE_CONFIG, {"loop": {"enabled": False}})
    P = np.stack(pipeline.run(src.scans(20, 10), cfg).odom_poses)
    G = src.ground_truth[20:30]
    err = inverse(inverse(G[0]) @ G[1]) @ (inverse(P[0]) @ P[1])
    assert np.linalg.norm(err[:3, 3]) < 0.2


@pytest.mark.shared_data
def test_default_config_closes_the_indoor_ouster_loop(ouster_loop):
    """With no overlay, the loop settings follow the data (lidar_slam.loop.adapt): the hand-held
    indoor loop (files 168-176 back to 106-115) is closed, and no accepted loop is grossly off
    the reference relative pose (1 m / 5 deg: the reference itself is ~7 cm off at this loop)."""
    from lidar_slam.geometry import relative, rotation_angle_deg
    from lidar_slam.io.trajectory import read_kitti_poses

    cfg = load_config(None)
    res = pipeline.run(open_source(ouster_loop).scans(), cfg)
    res.store.close()
    assert res.adaptive["max_radius_m"] <= 40.0 and res.adaptive["distance_m"] <= 1.0
    ref = read_kitti_poses(ouster_loop / "poses.txt")
    accepted = [r for r in res.loops if r.accepted]
    assert any(68 <= r.query_frame <= 76 and 6 <= r.match_frame <= 15 for r in accepted)
    for r in accepted:
        d = inverse(relative(ref[r.match_frame], ref[r.query_frame])) @ r.T_match_query
        assert np.linalg.norm(d[:3, 3]) < 1.0 and rotation_angle_deg(d) < 5.0, r


def test_loop_worker_gets_the_odometry_priority_only_for_a_long_or_final_backlog():
    from lidar_slam.loop.worker import is_urgent

    assert not is_urgent(0, 200, 0)  # nothing to do
    assert not is_urgent(100, 200, 5000)  # mid-drive, half the lag: the idle CPU will do
    assert is_urgent(150, 200, 5000)  # the odometry would soon wait for it
    assert is_urgent(100, 200, 300) and not is_urgent(10, 200, 300)  # the last scans
    assert not is_urgent(100, 200, None)  # end unknown (a stream): only the lag rule
    assert is_urgent(1, 200, 0)  # after the last scan
