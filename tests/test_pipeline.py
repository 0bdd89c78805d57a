"""The pipeline on sample_scans (simulated, true motion distortion, exact truth): deskew, loops."""

from pathlib import Path

import numpy as np
import pytest
from conftest import stop_pipeline_after

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


def test_sweep_end_stamps_lie_between_two_registrations_without_an_imu(trot_end):
    """With stamps at sweep end and no IMU, a scan is registered at its sweep's middle and its
    stamp lies half a sweep later: carried there along the last motion (the only one known),
    a trot's turn rate changes in between. Once the next scan is registered the stamp pose is
    interpolated between the two, and keyframe nodes stay at the registered instant. On 6 s of
    the bank's trot (office-legged-xt32) the frame-to-frame rotation error was 2.15 deg median
    (p90 5.2) extrapolated; 1.43 (3.1) now."""
    from lidar_slam.geometry import rotation_angle_deg

    src = open_source(trot_end)
    res = pipeline.run(src.scans(), load_config(None, {"loop": {"enabled": False}}))
    P, G = np.stack(res.odom_poses), src.ground_truth
    err = [rotation_angle_deg(inverse(inverse(G[k]) @ G[k + 1]) @ (inverse(P[k]) @ P[k + 1]))
           for k in range(len(P) - 1)]
    assert np.median(err) < 1.8, np.median(err)
    # a keyframe's node is half a sweep before its frame's stamp pose (0.1 s sweeps)
    table = res.store.table()
    k = len(table["T"]) // 2
    i = res.indices.index(int(table["frame_index"][k]))
    node_to_stamp = inverse(table["T"][k]) @ P[i]
    assert 0.005 < np.linalg.norm(node_to_stamp[:3, 3]) < 0.2
    # and the run says so (covariances.csv node_dt_s): every node at its sweep's middle
    assert sorted(res.kf_node_dt) == list(table["id"])
    assert np.allclose(list(res.kf_node_dt.values()), -0.05, atol=1e-3)
    res.store.close()


def _with_empty_scans(seq: Path, out: Path, scans: tuple[int, ...]) -> Path:
    import shutil

    shutil.copytree(seq, out)
    for k in scans:
        (out / "velodyne" / f"{k:06d}.bin").write_bytes(b"")
        (out / "velodyne_times" / f"{k:06d}.bin").write_bytes(b"")
    return out


def test_scans_skipped_mid_turn_lie_between_the_registrations_around_them(trot_end, tmp_path):
    """Two empty scans (30, 31) of the trot with sweep-end stamps: their predicted poses, and
    the registered frame before them, are placed between the registrations of frames 29 and 32
    by their stamps, not carried along the last motion: frame-to-frame error at most 6.3 deg /
    0.22 m before, 2.7 deg / 0.05 m now."""
    from lidar_slam.geometry import rotation_angle_deg

    seq = _with_empty_scans(trot_end, tmp_path / "gap", (30, 31))
    src = open_source(seq)
    res = pipeline.run(src.scans(), load_config(None, {"loop": {"enabled": False}}))
    res.store.close()
    assert res.skipped_empty == 2
    P, G = np.stack(res.odom_poses), src.ground_truth
    for k in range(28, 33):
        d = inverse(inverse(G[k]) @ G[k + 1]) @ (inverse(P[k]) @ P[k + 1])
        assert rotation_angle_deg(d) < 3.5 and np.linalg.norm(d[:3, 3]) < 0.1, k


def test_loops_csv_gives_the_loop_between_the_frames_at_their_stamps():
    """A loop measured between graph nodes off their frames' stamps (sweep-end stamps without
    an IMU; keyframe 0) is written to loops.csv between the frames at their stamps."""
    from lidar_slam.geometry import from_xyz_quat, make_pose, matrix_from_rotvec
    from lidar_slam.loop.detector import LoopRecord, loops_csv_rows

    T = make_pose(matrix_from_rotvec([0.0, 0.1, 0.3]), [1.0, 2.0, 0.1])
    D7 = make_pose(matrix_from_rotvec([0.02, -0.01, 0.05]), [0.3, 0.0, 0.01])
    D2 = make_pose(matrix_from_rotvec([0.0, 0.03, 0.0]), [-0.2, 0.1, 0.0])
    rec = LoopRecord(70, 20, 7, 2, 0.1, 0.0, 0.9, 0.1, True, "", T)
    for nodes, want in (({}, T), ({7: D7}, T @ D7), ({7: D7, 2: D2}, inverse(D2) @ T @ D7)):
        row = loops_csv_rows([rec], None, nodes)[1]
        got = from_xyz_quat(np.array([float(v) for v in row[8:15]]))
        np.testing.assert_allclose(got, want, atol=2e-6)


def test_a_sweep_end_run_stopped_by_a_signal_resumes_to_the_same_bytes(trot_end, tmp_path,
                                                                      monkeypatch):
    """The last frame's stamp pose waits for the next scan (sweep-end stamps, no IMU): a
    checkpoint keeps what it needs, so a run stopped there and resumed writes the bytes of the
    run never stopped; the odometry streamed while running holds only settled frames."""
    from lidar_slam.run import run_sequence

    files = ("poses_kitti.txt", "odometry_kitti.txt", "loops.csv", "covariances.csv")
    whole = run_sequence(trot_end, tmp_path / "whole", progress=False)
    assert whole.failure is None
    process, seen = pipeline.Pipeline.process, []
    streamed = {}

    def stopped_at_30(self, scan):
        if len(seen) == 30:
            streamed["odometry"] = (tmp_path / "run" / "odometry_kitti.txt").read_text()
            raise KeyboardInterrupt
        seen.append(scan.index)
        return process(self, scan)

    monkeypatch.setattr(pipeline.Pipeline, "process", stopped_at_30)
    first = run_sequence(trot_end, tmp_path / "run", progress=False)
    assert first.failure is not None and first.failure.exit_code == 130
    # 29 frames streamed while running: the 30th waited for the next scan
    assert len(streamed["odometry"].splitlines()) == 29
    monkeypatch.setattr(pipeline.Pipeline, "process", process)
    resumed = run_sequence(trot_end, tmp_path / "run", resume=True, progress=False)
    assert resumed.failure is None and resumed.summary["resumed_at_frame"] == 30
    for name in files:
        assert (tmp_path / "run" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()


def test_a_run_stopped_while_skipped_scans_wait_resumes_to_the_same_bytes(trot_end, tmp_path,
                                                                         monkeypatch):
    """Stopped after frame 30 (29 registered, 30 empty: both wait for frame 32), the checkpoint
    keeps both waiting frames: resumed, the run writes the bytes of the run never stopped."""
    from lidar_slam.run import run_sequence

    seq = _with_empty_scans(trot_end, tmp_path / "gap", (30, 31))
    files = ("poses_kitti.txt", "odometry_kitti.txt", "covariances.csv")
    assert run_sequence(seq, tmp_path / "whole", progress=False).failure is None
    resume = stop_pipeline_after(monkeypatch, 31)
    assert run_sequence(seq, tmp_path / "run", progress=False).failure.exit_code == 130
    resume()
    resumed = run_sequence(seq, tmp_path / "run", resume=True, progress=False)
    assert resumed.failure is None and resumed.summary["resumed_at_frame"] == 31
    for name in files:
        assert (tmp_path / "run" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()


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


def test_an_empty_first_scan_says_the_auto_loop_settings_are_defaults(trot_end, tmp_path,
                                                                      caplog):
    """The "auto" loop settings come from the first scan; an empty one left them at their
    outdoor defaults without a word (a 60 m loop exclusion on a 61 m indoor loop: a new
    user's pass). Now one warning names the scan and the values."""
    import logging

    seq = _with_empty_scans(trot_end, tmp_path / "first", (0,))
    with caplog.at_level(logging.WARNING, logger="lidar_slam.pipeline"):
        res = pipeline.run(open_source(seq).scans(0, 3), load_config(None))
    res.store.close()
    said = [r.getMessage() for r in caplog.records if "first scan has 0 points" in r.getMessage()]
    assert len(said) == 1 and "000000.bin" in said[0] and "defaults" in said[0], said


def _misses_deg(poses: np.ndarray) -> np.ndarray:
    """Per frame the rotation (deg) by which its pose missed the constant-velocity prediction
    from the two before (0 for the first two)."""
    from lidar_slam.geometry import rotation_angle_deg

    out = np.zeros(len(poses))
    for k in range(2, len(poses)):
        pred = poses[k - 1] @ inverse(poses[k - 2]) @ poses[k - 1]
        out[k] = rotation_angle_deg(inverse(pred) @ poses[k])
    return out


def test_keyframes_wait_for_steady_scans_and_the_odometry_does_not_move(handheld_walk):
    """Without an IMU a keyframe falls due mid-flick; it is made at the first steady scan
    after (keyframes.steady_miss_deg), at most steady_wait_scans late, while the odometry keeps
    its own keyframe copies where they fell due: its poses are the same bytes."""
    src = open_source(handheld_walk)
    runs = {}
    for bar in (0.0, 1.0):
        cfg = load_config(None, {"loop": {"enabled": False},
                                 "keyframes": {"steady_miss_deg": bar}})
        runs[bar] = pipeline.run(src.scans(), cfg)
    off, on = runs[0.0], runs[1.0]
    assert np.array_equal(np.stack(off.odom_poses), np.stack(on.odom_poses))
    due, made = off.store.table()["frame_index"], on.store.table()["frame_index"]
    late = made - due[np.searchsorted(due, made, side="right") - 1]
    assert late.max() <= load_config().keyframes.steady_wait_scans and (late > 0).sum() >= 3, late
    assert on.steady_wait[0] >= (late > 0).sum() and off.steady_wait == (0, 0)
    miss = _misses_deg(np.stack(on.odom_poses))
    assert np.median(miss[made]) < np.median(miss[due]), (miss[made], miss[due])
    off.store.close()
    on.store.close()


def test_a_run_stopped_while_a_keyframe_waits_resumes_to_the_same_bytes(handheld_walk, tmp_path,
                                                                       monkeypatch):
    """A checkpoint keeps the keyframe waiting for a steady scan and the poses it is judged by:
    stopped there and resumed, the run writes the bytes of the run never stopped."""
    from lidar_slam.frontend.keyframes import SteadyWait
    from lidar_slam.run import run_sequence

    take, waiting = SteadyWait.take, []

    def watched(self, due, miss):
        made = take(self, due, miss)
        waiting.append(self.pending)
        return made

    monkeypatch.setattr(SteadyWait, "take", watched)
    files = ("poses_kitti.txt", "odometry_kitti.txt", "loops.csv", "covariances.csv")
    lidar_only = {"imu": {"enabled": False}}
    assert run_sequence(handheld_walk, tmp_path / "whole", overrides=lidar_only,
                        progress=False).failure is None
    monkeypatch.setattr(SteadyWait, "take", take)
    n = next(i + 1 for i, w in enumerate(waiting) if w and i >= 30)
    resume = stop_pipeline_after(monkeypatch, n)
    assert run_sequence(handheld_walk, tmp_path / "run", overrides=lidar_only,
                        progress=False).failure.exit_code == 130
    resume()
    resumed = run_sequence(handheld_walk, tmp_path / "run", overrides=lidar_only, resume=True,
                           progress=False)
    assert resumed.failure is None and resumed.summary["resumed_at_frame"] == n
    import json

    counts = json.loads((tmp_path / "whole" / "summary.json").read_text())["keyframes_steady_wait"]
    assert resumed.summary["keyframes_steady_wait"] == counts and counts["late"] > 0, counts
    for name in files:
        assert (tmp_path / "run" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()
