"""Metrics stage, file side: run_eval on KITTI/TUM files, calib, loops.csv, plots, table, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lidar_slam.errors import InputError
from lidar_slam.eval.evaluate import format_table, run_eval
from lidar_slam.geometry import to_xyz_quat
from lidar_slam.io.trajectory import (
    camera_to_lidar_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
    write_kitti_poses,
    write_tum,
)

KEYS = ("t_err_pct", "r_err_deg_per_100m", "ate_rmse_m", "rpe_trans_m_mean", "rpe_rot_deg_mean")


@pytest.fixture
def seq00(kitti_gt):
    return (kitti_gt / "estimated_seq00" / "KITTI_00_ORB.txt", kitti_gt / "poses" / "00.txt",
            kitti_gt / "calib" / "00.txt")


@pytest.mark.shared_data
def test_evaluate_kitti_files_write_json_plots_and_table(seq00, tmp_path):
    est, gt, _ = seq00
    m = run_eval(est, gt, fmt="kitti", out_dir=tmp_path)
    assert set(KEYS) <= set(m)
    assert round(m["t_err_pct"], 2) == 0.70 and round(m["r_err_deg_per_100m"], 2) == 0.25
    assert m["ate_rmse_m"] == pytest.approx(1.303449714565045, abs=1e-6)  # evo_ape -a
    assert m["n_frames"] == 4541 and m["note"] is None and "warning" not in m
    assert json.loads((tmp_path / "metrics.json").read_text())["ate_rmse_m"] == m["ate_rmse_m"]
    for png in ("trajectory_top.png", "error_vs_distance.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = format_table(m)
    assert "0.700 %" in table and "0.253 deg/100 m" in table and "1.303 m" in table
    assert "0.0596 deg" in table and "0.0193 m" in table


@pytest.mark.shared_data
def test_evaluate_calib_moves_gt_to_lidar_frame(seq00, tmp_path):
    _, gt_path, calib = seq00
    gt_lidar = camera_to_lidar_poses(read_kitti_poses(gt_path)[:1200],
                                     read_kitti_calib_tr(calib))
    write_kitti_poses(tmp_path / "est.txt", gt_lidar)
    write_kitti_poses(tmp_path / "gt.txt", read_kitti_poses(gt_path)[:1200])
    m = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", calib_path=calib)
    # The lidar-frame truth, written and read back (%.9e), is measured against itself.
    assert m["t_err_pct"] < 1e-6 and m["r_err_deg_per_100m"] < 1e-6
    assert m["ate_rmse_m"] < 1e-6 and m["rpe_trans_m_mean"] < 1e-6
    assert m["gt_frame"].startswith("lidar")
    # Without the calib the same estimate is compared with camera-frame poses: nonsense, flagged.
    m_cam = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt")
    assert m_cam["t_err_pct"] > 10 and "different sensor frames" in m_cam["warning"]


def straight_drive(n: int = 300) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * 1.0
    poses[:, 1, 3] = 20.0 * np.sin(np.arange(n) / 40.0)
    return poses


def test_evaluate_tum_is_associated_by_timestamp(tmp_path):
    gt = straight_drive()
    stamps = 100.0 + 0.1 * np.arange(len(gt))
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    write_tum(tmp_path / "gt.tum", stamps, gt)
    # The estimate skips every third frame, carries 3 ms of stamp jitter and adds a stray pose.
    keep = np.flatnonzero(np.arange(len(gt)) % 3 != 1)
    est_stamps = np.r_[stamps[keep] + 0.003, 999.0]
    write_tum(tmp_path / "est.tum", est_stamps, np.concatenate([est[keep], est[:1]]))
    m = run_eval(tmp_path / "est.tum", tmp_path / "gt.tum", fmt="tum")
    assert m["n_frames"] == len(keep)
    ref = run_eval_kitti(tmp_path, est[keep], gt[keep])
    for key in KEYS[:3]:
        assert m[key] == pytest.approx(ref[key], rel=1e-6)


def run_eval_kitti(tmp_path, est, gt) -> dict:
    write_kitti_poses(tmp_path / "e.txt", est)
    write_kitti_poses(tmp_path / "g.txt", gt)
    return run_eval(tmp_path / "e.txt", tmp_path / "g.txt")


def test_evaluate_loops_csv_precision_and_recall(tmp_path):
    # Drive 0..149 along x, then back over the start: frames 250..269 revisit x 0..19.
    n = 300
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:150, 0, 3] = np.arange(150.0)
    gt[150:250, 0, 3] = 150.0
    gt[150:250, 1, 3] = np.arange(100.0)  # a leg far from the start
    gt[250:, 0, 3] = np.arange(50.0)
    gt[250:, 1, 3] = 0.5
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", gt)
    (tmp_path / "loops.csv").write_text(
        "query_frame,match_frame,score,accepted\n"
        "255,5,0.1,1\n"  # right: the trajectory agrees with the truth
        "260,10,0.2,0\n"  # proposed, rejected: not scored
        "200,20,0.3,true\n"  # accepted, but the frames are ~100 m apart in truth and estimate
    )
    m = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", loops_csv=tmp_path / "loops.csv",
                 out_dir=tmp_path / "out")
    assert m["loop_pose_source"] == "estimated trajectory"
    assert (m["loops_proposed"], m["loops_accepted"], m["loops_correct"]) == (3, 2, 2)
    assert m["loop_precision"] == 1.0  # both agree: the estimate IS the truth here
    assert (m["revisit_events"], m["revisit_events_found"]) == (1, 1)
    # With measured relative poses in the file, a wrong one is caught.
    rows = ["query_frame,match_frame,accepted,x,y,z,qx,qy,qz,qw"]
    for q, mm, dx in ((255, 5, 0.0), (200, 20, 3.0)):
        v = to_xyz_quat(np.linalg.inv(gt[mm]) @ gt[q])
        v[0] += dx
        rows.append(f"{q},{mm},1," + ",".join(f"{x:.9f}" for x in v))
    (tmp_path / "loops2.csv").write_text("\n".join(rows) + "\n")
    m2 = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", loops_csv=tmp_path / "loops2.csv")
    assert m2["loop_pose_source"] == "loops.csv T_match_query"
    assert (m2["loops_accepted"], m2["loops_correct"], m2["loop_precision"]) == (2, 1, 0.5)
    assert m2["loop_recall_events"] == 1.0
    assert "loop precision" in format_table(m2) and "50.0 % (1 / 2)" in format_table(m2)
    assert (tmp_path / "out" / "trajectory_top.png").exists()


def test_evaluate_short_sequence_reports_note(tmp_path):
    m = run_eval_kitti(tmp_path, straight_drive(40), straight_drive(40))
    assert m["t_err_pct"] is None and m["r_err_deg_per_100m"] is None
    assert "no KITTI segment" in m["note"]
    table = format_table(m)
    assert "KITTI t_err                        n/a" in table and "note" in table
    assert m["ate_rmse_m"] < 1e-9


def test_evaluate_bad_inputs_raise_input_error(tmp_path):
    gt = straight_drive(50)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "short.txt", gt[:49])
    with pytest.raises(InputError, match="49 poses but the ground truth"):
        run_eval(tmp_path / "short.txt", tmp_path / "gt.txt")
    (tmp_path / "junk.txt").write_text("this is not a pose file\n")
    with pytest.raises(InputError) as exc:
        run_eval(tmp_path / "junk.txt", tmp_path / "gt.txt")
    assert exc.value.path.endswith("junk.txt")
    with pytest.raises(InputError, match="does not exist"):
        run_eval(tmp_path / "missing.txt", tmp_path / "gt.txt")
    with pytest.raises(InputError, match="unknown trajectory format"):
        run_eval(tmp_path / "gt.txt", tmp_path / "gt.txt", fmt="euroc")
    (tmp_path / "loops.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="missing columns"):
        run_eval(tmp_path / "gt.txt", tmp_path / "gt.txt", loops_csv=tmp_path / "loops.csv")
    # a cut row (a field short: csv hands None) and a row with a word for a frame: the line
    head = "query_frame,match_frame,accepted\n"
    for body, says in (("5,1,1\n1,2\n", "line 3: 2 columns, the header has 3"),
                       ("5,1,1,9\n", "line 2: 4 columns"),
                       ("5,1,1\nabc,2,1\n", "line 3: bad value")):
        (tmp_path / "loops.csv").write_text(head + body)
        with pytest.raises(InputError, match=says):
            run_eval(tmp_path / "gt.txt", tmp_path / "gt.txt", loops_csv=tmp_path / "loops.csv")
    # spaces after the header's commas are read as the names; a zero quaternion is refused
    pose = "query_frame, match_frame, accepted, x, y, z, qx, qy, qz, qw\n"
    (tmp_path / "loops.csv").write_text(pose + "5, 1, 1, 0, 0, 0, 0, 0, 0, 1\n")
    m = run_eval(tmp_path / "gt.txt", tmp_path / "gt.txt", loops_csv=tmp_path / "loops.csv")
    assert m["loops_accepted"] == 1
    (tmp_path / "loops.csv").write_text(pose + "5, 1, 1, 0, 0, 0, 0, 0, 0, 0\n")
    with pytest.raises(InputError, match="line 2: .*zero quaternion"):
        run_eval(tmp_path / "gt.txt", tmp_path / "gt.txt", loops_csv=tmp_path / "loops.csv")
    nan = gt.copy()
    nan[3, 0, 3] = np.nan
    write_kitti_poses(tmp_path / "nan.txt", nan)
    with pytest.raises(InputError, match="NaN"):
        run_eval(tmp_path / "nan.txt", tmp_path / "gt.txt")


def test_evaluate_start_offsets_the_ground_truth_and_the_loop_frames(tmp_path):
    """A run made with --start 40 --n-scans 200: its line 0 is ground-truth line 40, and its
    loops.csv numbers frames from the input's first scan."""
    gt = straight_drive(300)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", gt[40:240])
    with pytest.raises(InputError, match="--start"):
        run_eval(tmp_path / "est.txt", tmp_path / "gt.txt")
    m = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", start=40)
    assert m["ate_rmse_m"] < 1e-6 and m["n_frames"] == 200
    assert "lines 40..239" in m["pairing"]
    (tmp_path / "loops.csv").write_text("query_frame,match_frame,accepted\n230,45,1\n")
    m = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", start=40,
                 loops_csv=tmp_path / "loops.csv")
    assert (m["loops_accepted"], m["loops_correct"], m["loops_unscored"]) == (1, 1, 0)
    with pytest.raises(InputError, match="need 350 lines"):
        run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", start=150)


def test_evaluate_mixes_kitti_and_tum_files(tmp_path):
    """Each file's format is told by its columns: a TUM estimate against KITTI ground truth with
    its times file (paired by stamp), and a KITTI estimate against TUM ground truth (by line)."""
    gt = straight_drive(300)
    stamps = 50.0 + 0.1 * np.arange(len(gt))
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    write_kitti_poses(tmp_path / "gt_kitti.txt", gt)
    np.savetxt(tmp_path / "times.txt", stamps)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_kitti_poses(tmp_path / "est_kitti.txt", est)
    keep = np.arange(0, len(gt), 2)
    write_tum(tmp_path / "est.tum", stamps[keep], est[keep])
    ref = run_eval(tmp_path / "est_kitti.txt", tmp_path / "gt_kitti.txt")
    by_line = run_eval(tmp_path / "est_kitti.txt", tmp_path / "gt.tum")
    assert by_line["pairing"].startswith("line by line")
    for key in KEYS:
        assert by_line[key] == pytest.approx(ref[key], rel=1e-6)
    by_stamp = run_eval(tmp_path / "est.tum", tmp_path / "gt_kitti.txt",
                        gt_times=tmp_path / "times.txt")
    assert by_stamp["pairing"].startswith("by stamp") and by_stamp["n_frames"] == len(keep)
    assert by_stamp["ate_rmse_m"] == pytest.approx(
        run_eval_kitti(tmp_path, est[keep], gt[keep])["ate_rmse_m"], rel=1e-6)
    (tmp_path / "six.txt").write_text("1 2 3 4 5 6\n")
    with pytest.raises(InputError, match="neither KITTI"):
        run_eval(tmp_path / "six.txt", tmp_path / "gt_kitti.txt")


def test_evaluate_revisit_gap_scores_a_short_loop(tmp_path):
    """A 70-frame circuit closed at frames 63..69 (as sample_scans): no revisit with the default
    100-frame gap, one found with --revisit-gap 30."""
    n = 70
    a = 2 * np.pi * np.arange(n) / 63.0
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3], gt[:, 1, 3] = 15 * np.cos(a), 15 * np.sin(a)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", gt)
    (tmp_path / "loops.csv").write_text("query_frame,match_frame,accepted\n65,2,1\n")
    kwargs = {"loops_csv": tmp_path / "loops.csv"}
    default = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", **kwargs)
    assert default["revisit_events"] == 0 and default["loop_recall_events"] is None
    short = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", revisit_gap=30, **kwargs)
    assert (short["revisit_events"], short["revisit_events_found"]) == (1, 1)
    assert short["revisit_gap_frames"] == 30


def test_evaluate_plots_drift_against_segment_length(tmp_path):
    gt = straight_drive(400)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    write_kitti_poses(tmp_path / "e.txt", est)
    write_kitti_poses(tmp_path / "g.txt", gt)
    m = run_eval(tmp_path / "e.txt", tmp_path / "g.txt", out_dir=tmp_path / "out")
    assert [b["length_m"] for b in m["drift_by_length"]][:2] == [100.0, 200.0]
    png = tmp_path / "out" / "drift_vs_length.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list((tmp_path / "out").glob(".*.tmp"))  # written via a temporary file


def test_an_evaluation_into_the_same_folder_says_so_and_leaves_no_stale_plot(tmp_path, caplog):
    """A short estimate evaluated where a long one was left the long one's drift plot beside
    its own metrics.json, in silence (a new user's pass)."""
    long_gt, short_gt = straight_drive(400), straight_drive(40)
    for name, poses in (("long", long_gt), ("short", short_gt)):
        write_kitti_poses(tmp_path / f"{name}.txt", poses)
    run_eval(tmp_path / "long.txt", tmp_path / "long.txt", out_dir=tmp_path / "out")
    assert (tmp_path / "out" / "drift_vs_length.png").is_file()
    run_eval(tmp_path / "short.txt", tmp_path / "short.txt", out_dir=tmp_path / "out")
    assert not (tmp_path / "out" / "drift_vs_length.png").exists()
    assert f"{tmp_path / 'out'}: replacing the evaluation there" in caplog.text


def test_eval_takes_the_runs_own_start_and_refuses_another(tmp_path):
    """A run's pose file with its summary.json beside it: eval pairs from the run's --start
    when none is given, and refuses a different one (every pose against another scan's truth)."""
    import json

    from lidar_slam.cli.eval import _run_start
    from lidar_slam.errors import RunFailed

    est = tmp_path / "poses_kitti.txt"
    assert _run_start(est, None) is None and _run_start(est, 3) == 3  # no summary: as given
    (tmp_path / "summary.json").write_text(json.dumps({"start": 5}))
    assert _run_start(est, None) == 5 and _run_start(est, 5) == 5
    with pytest.raises(RunFailed, match="--start 2, but the run was made with --start 5"):
        _run_start(est, 2)
    (tmp_path / "summary.json").write_text(json.dumps({"start": 0}))
    assert _run_start(est, None) is None and _run_start(est, 0) == 0
    with pytest.raises(RunFailed, match="made with --start 0"):
        _run_start(est, 4)
