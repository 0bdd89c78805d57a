"""`simulate --sessions` and `merge`: sessions of one world in their own frames, merged into one
saved map that `localize` and `export` open (issue 31)."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error

from lidar_slam.eval.metrics import umeyama_rigid
from lidar_slam.geometry import inverse, rotation_angle_deg
from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.map.saved import open_map


def lidar_slam(*args, timeout=900):
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_sessions_same_seed_same_bytes_each_in_its_own_frame(tmp_path):
    """Two drives of one outdoor world: identical bytes for the same seed, each session's first
    pose its origin, truth in the common frame, the second driven the other way round from
    another start, and every change recorded."""
    from lidar_slam.sim.handheld import build_site
    from lidar_slam.sim.sensor import get_sensor

    for name in ("a", "b"):
        proc = lidar_slam("simulate", "--motion", "car", "--sessions", "2", "--duration-s", "3",
                          "--changes", "3", "--seed", "3", "--out", tmp_path / name)
        assert proc.returncode == 0, proc.stderr
    assert _tree_bytes(tmp_path / "a") == _tree_bytes(tmp_path / "b")
    sim = tmp_path / "a"
    truth = [read_kitti_poses(sim / f"session_{i}" / "truth_world.txt") for i in range(2)]
    for i in range(2):
        poses = read_kitti_poses(sim / f"session_{i}" / "poses.txt")
        assert np.allclose(poses[0], np.eye(4))
        assert np.allclose(inverse(truth[i][0]) @ truth[i], poses, atol=1e-6)
    assert np.linalg.norm(truth[0][0, :3, 3] - truth[1][0, :3, 3]) > 5.0
    centre = build_site("outdoor", 3, get_sensor("os1-64")).corners.mean(axis=0)

    def turning(T):  # +1 counter-clockwise round the loop's centre, -1 clockwise
        p, v = T[:-1, :2, 3] - centre, np.diff(T[:, :2, 3], axis=0)
        return np.sign(np.sum(p[:, 0] * v[:, 1] - p[:, 1] * v[:, 0]))

    assert turning(truth[0]) == -turning(truth[1]) != 0
    doc = json.loads((sim / "changes.json").read_text())
    assert sorted(c["kind"] for c in doc["changes"]) == ["added", "moved", "removed"]
    for c in doc["changes"]:
        assert c["session"] == 1 and (c["before"] is None) == (c["kind"] == "added")
        assert (c["after"] is None) == (c["kind"] == "removed")


def test_changed_objects_are_in_the_world_of_their_session():
    """A removed object is hit by a ray in the sessions before its change, not after."""
    from lidar_slam.sim.handheld import build_site
    from lidar_slam.sim.sensor import get_sensor
    from lidar_slam.sim.sessions import draw_changes, with_objects
    from lidar_slam.sim.world import CLASSES

    sensor = get_sensor("os1-64")
    changes = draw_changes(build_site("indoor", 2, sensor), "handheld", 2, 3, 2)
    removed = next(c for c in changes if c.kind == "removed")
    box = removed.before
    for session, there in ((0, True), (1, False)):
        site = build_site("indoor", 2, sensor)
        world = with_objects(site.world, [(c.cls, c.box_in(session)) for c in changes
                                          if c.box_in(session) is not None])
        top = np.array([[box.x, box.y, box.z1 + 0.5]])
        hit = world.cast(top, np.array([[0.0, 0.0, -1.0]]))
        hit_box = bool(abs(hit["t_hit"][0] - 0.5) < 1e-3
                       and hit["class"][0] == CLASSES.index("clutter"))
        assert hit_box == there, (session, hit)


def test_a_mover_is_hit_where_it_is_at_each_rays_instant():
    """A pedestrian box walking along the loop is met by a ray at the box's face where the box
    is at the ray's time, with the face's normal; a ray beside it misses."""
    from lidar_slam.sim.handheld import LoopPath
    from lidar_slam.sim.movers import Mover, Movers

    path = LoopPath.rectangle(20.0, 10.0, 0.6, False, 0.0)  # along +x from the origin
    walker = Movers([Mover("clutter", 0.5, 0.5, 1.75, -1.0, 5.0, 0.0, path,
                           lambda xy: np.zeros(len(xy)))])
    origins = np.tile([0.0, 0.0, 0.8], (3, 1))
    dirs = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    t, normal, cls = walker.cast(origins, dirs, np.array([0.0, 2.0, 0.0]))
    centre = walker.movers[0].at(np.array([0.0, 2.0]))
    assert np.allclose(centre[:, 1], 0.0, atol=1e-3) and centre[0, 0] > 4.0  # on the x axis
    assert np.allclose(centre[:, 2], np.pi, atol=1e-3)  # facing the way it walks: -x
    assert np.allclose(t[:2], centre[:, 0] - 0.25, atol=1e-3) and np.isinf(t[2])
    assert abs(centre[0, 0] - centre[1, 0] - 2.0) < 0.01  # 1 m/s towards the origin
    assert np.allclose(normal[:2], [[-1.0, 0.0, 0.0]] * 2, atol=1e-3)
    assert (cls[:2] >= 0).all() and cls[2] == -1


def test_votes_come_from_the_keyframes_of_others_nearest_the_point():
    """place_votes: a wall at x = 5 seen by keyframes of another session; only the
    max_keyframes of them nearest to the point's cell vote, never the point's own session's,
    never one beyond reach; a keyframe whose cloud lies beyond the point sees through it."""
    from scipy.spatial import cKDTree

    from lidar_slam.merge.changes import place_votes
    from lidar_slam.merge.loops import nearest_of_others

    yz = np.stack(np.meshgrid(np.linspace(-8, 8, 161), np.linspace(-4, 4, 81)), -1).reshape(
        -1, 2)
    origins = np.array([[x, 0.0, 0.0] for x in (0.0, -1.0, -2.0, -3.0, -30.0)])
    owner = np.array([1, 1, 1, 0, 1])  # keyframe 3 is the point's own session's

    def voter(v):  # keyframes 0-2 see the wall at x = 5, 4 one at x = 12 (the wall gone)
        wall = 5.0 if v < 4 else 12.0
        T = np.eye(4)
        T[:3, 3] = origins[v]
        behind = [[-1.0, 0.0, 0.0]]  # its nearest return: points beyond it are judged
        return np.r_[np.c_[np.full(len(yz), wall - origins[v, 0]), yz], behind], T

    point = np.array([[5.0, 0.0, 0.0]])
    through, seen = place_votes(point, np.array([0]), origins, owner, np.zeros(5, int), 1,
                                voter, 2, 15.0, 2.5, 3.0, 0.6)
    assert seen[0, 0] == 2 and through[0, 0] == 0  # keyframes 0 and 1: 2 nearest others
    through, seen = place_votes(point, np.array([0]), origins, owner, np.zeros(5, int), 1,
                                voter, 5, 40.0, 2.5, 3.0, 0.6)
    assert seen[0, 0] == 3 and through[0, 0] == 1  # 0-2 see it, 4 (35 m away) sees through
    d, j = nearest_of_others(cKDTree(origins), owner, point[0], 0, 10, 15.0)
    assert list(j) == [0, 1, 2] and np.all(np.diff(d) > 0)


def test_merged_geo_follows_the_session_that_had_gnss():
    """No GNSS in the reference, GNSS in session 1: the merged frame is put on the Earth by
    session 1's geo-reference carried by where the merge put that session."""
    from types import SimpleNamespace

    from lidar_slam.geo import GeoReference, LocalEnu
    from lidar_slam.merge.build import geo_disagreement_m, merged_geo

    T_enu_run1 = np.eye(4)
    T_enu_run1[:3, 3] = [100.0, -50.0, 2.0]
    geo1 = GeoReference(LocalEnu(48.1, 11.5, 520.0), T_enu_run1)
    kf_run1 = np.tile(np.eye(4), (3, 1, 1))
    kf_run1[:, 0, 3] = [0.0, 1.0, 2.0]
    T_merged_run1 = np.eye(4)
    T_merged_run1[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T_merged_run1[:3, 3] = [5.0, 0.0, 0.0]
    sessions = [SimpleNamespace(index=0, map=SimpleNamespace(geo=None, T_map_kf=np.eye(4)[None])),
                SimpleNamespace(index=1, map=SimpleNamespace(geo=geo1, T_map_kf=kf_run1))]
    T_merged_kf = {0: np.eye(4)[None], 1: T_merged_run1 @ kf_run1}
    geo, source = merged_geo(sessions, T_merged_kf, reference=0)
    assert source == 1
    # Session 1's keyframes land on the Earth where its own run put them.
    assert geo_disagreement_m(sessions[1], geo, T_merged_kf[1]).max() < 1e-6
    assert np.allclose(geo.map_to_enu(T_merged_kf[1][:, :3, 3]),
                       geo1.map_to_enu(kf_run1[:, :3, 3]), atol=1e-9)
    assert merged_geo(sessions[:1], {0: np.eye(4)[None]}, 0) == (None, None)


def _ply_columns(path: Path) -> dict[str, np.ndarray]:
    """The vertex columns of a binary little-endian PLY (float / int properties)."""
    types = {"float": "<f4", "int": "<i4", "uint": "<u4"}
    with open(path, "rb") as fh:
        header = []
        while not header or header[-1] != "end_header":
            header.append(fh.readline().decode("ascii").strip())
        n = int(next(h.split()[2] for h in header if h.startswith("element vertex")))
        fields = [(h.split()[2], types[h.split()[1]]) for h in header
                  if h.startswith("property")]
        rows = np.fromfile(fh, dtype=np.dtype(fields), count=n)
    return {name: rows[name] for name, _ in fields}


@pytest.fixture(scope="module")
def merged(tmp_path_factory):
    """Two 12 s hand-held walks with an IMU through one indoor world, starting close together,
    the second the other way round, two pedestrians walking about in each; each run, then
    merged."""
    from lidar_slam.sim.imu_gnss import ImuOptions
    from lidar_slam.sim.sessions import simulate_sessions

    root = tmp_path_factory.mktemp("merge")
    simulate_sessions(root / "sim", 2, "handheld", "indoor", 4, 12.0, n_changes=4,
                      imu=ImuOptions(), spread=0.4, n_movers=2)
    runs = []
    for i in range(2):
        runs.append(root / f"run{i}")
        proc = lidar_slam("run", root / "sim" / f"session_{i}", "--out", runs[-1])
        assert proc.returncode == 0, proc.stderr
    proc = lidar_slam("merge", *runs, "--out", root / "map")
    assert proc.returncode == 0, proc.stderr
    return root, runs, proc.stdout


def test_merged_keyframes_land_on_the_truth(merged):
    root, _, stdout = merged
    assert "LEFT OUT" not in stdout, stdout
    with open(root / "map" / "sessions" / "keyframes.csv") as fh:
        rows = [(int(r["session"]), int(r["frame"])) for r in csv.DictReader(fh)]
    truth = [read_kitti_poses(root / "sim" / f"session_{i}" / "truth_world.txt")
             for i in range(2)]
    gt = np.stack([truth[s][f] for s, f in rows])
    saved = open_map(root / "map")
    est = saved.T_map_kf
    saved.close()
    assert {s for s, _ in rows} == {0, 1}
    T = umeyama_rigid(est[:, :3, 3], gt[:, :3, 3])
    err = np.linalg.norm(est[:, :3, 3] @ T[:3, :3].T + T[:3, 3] - gt[:, :3, 3], axis=1)
    assert err.max() < 0.15, err.max()
    with open(root / "map" / "loops.csv") as fh:
        loops = [r for r in csv.DictReader(fh) if r["kept"] == "1"]
    assert len(loops) >= 5


def test_objects_changed_between_the_walks_are_found(merged):
    """4 objects moved, added or removed between the two walks: found by object (the bench's
    rule, tools/merge_bench.py), each point with its session and kind in changes.ply."""
    from tools.merge_bench import evaluate

    root, _, _ = merged
    scores = evaluate(root / "sim", root / "map")
    assert scores["change_precision"] >= 0.75 and scores["change_recall"] >= 0.5, scores
    assert scores["wrong_loops"] == 0 and scores["overlap_linked_pct"] >= 90.0, scores
    # The pedestrians: most of their points, in the runs' keyframes, are not in the map.
    assert scores["mover_points_in_merged"] < 0.5 * scores["mover_points_in_runs"], scores
    assert (root / "map" / "top_view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    cols = _ply_columns(root / "map" / "changes.ply")
    assert set(cols) >= {"x", "y", "z", "session", "appeared", "object"}
    assert set(np.unique(cols["session"]).tolist()) <= {0, 1}
    appeared = cols["appeared"] == 1
    assert (cols["session"][appeared] == 1).all()  # appeared: seen by the later session only
    later = json.loads((root / "map" / "sessions" / "1" / "summary.json").read_text())
    assert later["changes"]["appeared_points"] == int(appeared.sum())
    assert later["changes"]["appeared_objects"] >= 1


def test_every_frame_of_every_session_is_written_in_the_merged_frame(merged):
    root, runs, _ = merged
    for i, run in enumerate(runs):
        mine = read_kitti_poses(root / "map" / "sessions" / str(i) / "poses_kitti.txt")
        own = read_kitti_poses(run / "poses_kitti.txt")
        assert len(mine) == len(own)
        summary = json.loads((root / "map" / "sessions" / str(i) / "summary.json").read_text())
        assert summary["kept"] and summary["loops_with_sessions"][str(1 - i)]["kept"] > 0
        # One rigid motion (nearly) takes the run's own poses to the merged ones.
        d = inverse(own[0]) @ own[-1], inverse(mine[0]) @ mine[-1]
        assert np.linalg.norm(d[0][:3, 3] - d[1][:3, 3]) < 0.3
    ref = read_kitti_poses(root / "map" / "sessions" / "0" / "poses_kitti.txt")
    assert np.allclose(ref[0], np.eye(4), atol=0.05)  # the reference fixes the frame


def test_localize_and_export_accept_a_merged_map(merged, tmp_path):
    root, _, _ = merged
    proc = lidar_slam("localize", root / "sim" / "session_1", "--map", root / "map", "--out",
                      tmp_path / "loc", "--start", "60", "--n-scans", "15")
    assert proc.returncode == 0, proc.stderr
    loc = read_kitti_poses(tmp_path / "loc" / "poses_kitti.txt")
    mine = read_kitti_poses(root / "map" / "sessions" / "1" / "poses_kitti.txt")[60:75]
    assert np.linalg.norm(loc[:, :3, 3] - mine[:, :3, 3], axis=1).max() < 0.2
    proc = lidar_slam("export", root / "map", "--out", tmp_path / "map.ply", "--voxel", "0.3")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "map.ply").stat().st_size > 10_000


def test_a_session_of_another_place_is_left_out(merged, tmp_path):
    """The shipped street scans share nothing with the indoor walks: reported, left out, and
    the others merged all the same."""
    root, runs, _ = merged
    repo = Path(__file__).resolve().parents[1]
    proc = lidar_slam("run", repo / "sample_scans", "--out", tmp_path / "street")
    assert proc.returncode == 0, proc.stderr
    proc = lidar_slam("merge", runs[0], tmp_path / "street", runs[1], "--out", tmp_path / "map")
    assert proc.returncode == 0, proc.stderr
    assert "session 1: LEFT OUT (no verified overlap" in proc.stdout, proc.stdout
    summary = json.loads((tmp_path / "map" / "sessions" / "1" / "summary.json").read_text())
    assert not summary["kept"] and "no verified overlap" in summary["why"]
    assert not (tmp_path / "map" / "sessions" / "1" / "poses_kitti.txt").exists()
    assert (tmp_path / "map" / "sessions" / "2" / "poses_kitti.txt").is_file()


def test_run_extend_adds_a_session_to_a_run_and_to_a_merged_map(merged, tmp_path):
    """`run DATA --extend MAP --out NEW`: DATA run into NEW/run and merged with MAP's
    sessions, in MAP's frame; NEW extended again keeps all three."""
    root, runs, _ = merged
    proc = lidar_slam("run", root / "sim" / "session_1", "--extend", runs[0], "--out",
                      tmp_path / "one")
    assert proc.returncode == 0, proc.stderr
    assert "2 of 2 sessions kept" in proc.stdout, proc.stdout
    ref = read_kitti_poses(tmp_path / "one" / "sessions" / "0" / "poses_kitti.txt")
    assert np.allclose(ref[0], np.eye(4), atol=0.05)
    proc = lidar_slam("run", root / "sim" / "session_0", "--start", "40", "--n-scans", "50",
                      "--extend", tmp_path / "one", "--out", tmp_path / "two")
    assert proc.returncode == 0, proc.stderr
    assert "3 of 3 sessions kept" in proc.stdout, proc.stdout
    summary = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary["merged_from"][:2] == [str(runs[0].resolve()),
                                          str((tmp_path / "one" / "run").resolve())]
    assert len(read_kitti_poses(tmp_path / "two" / "sessions" / "2" / "poses_kitti.txt")) == 50
    proc = lidar_slam("run", root / "sim" / "session_1", "--extend", root / "sim", "--out",
                      tmp_path / "three")
    assert_one_line_error(proc, "not a saved map")
    assert not (tmp_path / "three").exists()


def test_bad_input_is_one_line(merged, tmp_path):
    root, runs, _ = merged
    proc = lidar_slam("merge", runs[0], root / "sim" / "session_0", "--out", tmp_path / "m")
    assert_one_line_error(proc, str(root / "sim" / "session_0"), "not a run folder")
    proc = lidar_slam("merge", runs[0], tmp_path / "nowhere", "--out", tmp_path / "m")
    assert_one_line_error(proc, "nowhere")
    empty = tmp_path / "empty"
    (empty / "keyframes").mkdir(parents=True)
    (empty / "config.yaml").write_bytes((runs[0] / "config.yaml").read_bytes())
    for name in ("table.bin", "points.bin", "map_poses.bin"):
        (empty / "keyframes" / name).write_bytes(b"")
    (empty / "keyframes" / "manifest.json").write_text(json.dumps(
        {"version": 3, "keyframes": 0, "points": 0,
         "map": {"frame": "poses_kitti.txt", "poses": "map_poses.bin", "descriptors": None,
                 "descriptor_rows": 0, "config": "../config.yaml"}}))
    proc = lidar_slam("merge", runs[0], empty, "--out", tmp_path / "m")
    assert_one_line_error(proc, str(empty), "no keyframes")
    proc = lidar_slam("merge", runs[0], runs[1], "--reference", "2", "--out", tmp_path / "m")
    assert_one_line_error(proc, "--reference 2")
    # a merged map given as a run: it said "keyframes without stamps (an older run)"
    proc = lidar_slam("merge", root / "map", runs[1], "--out", tmp_path / "m")
    assert_one_line_error(proc, f"{root / 'map'}: a merged map, not a run",
                          f"--extend {root / 'map'}")
    # a copy of a run was merged as a second session (20 "loops" with itself)
    shutil.copytree(runs[1], tmp_path / "copy")
    proc = lidar_slam("merge", runs[0], runs[1], tmp_path / "copy", "--out", tmp_path / "m")
    assert_one_line_error(proc, f"{tmp_path / 'copy'}: the same run as {runs[1]}")
    assert not (tmp_path / "m").exists()


@pytest.mark.shared_data
def test_the_ouster_set_cut_in_two_merges_into_the_single_runs_loop(tmp_path):
    """Scans 0-49 and 40-76 of the indoor Ouster loop (the second re-based to its own origin:
    a run from --start 40), merged: the last frames of the second session, which close the loop
    on the first, land where the single run of all 77 puts them."""
    from conftest import shared_path

    seq = shared_path("ouster_os0_loop_balm")
    for name, args in (("full", ()), ("a", ("--n-scans", "50")), ("b", ("--start", "40"))):
        proc = lidar_slam("run", seq, "--out", tmp_path / name, *args)
        assert proc.returncode == 0, proc.stderr
    b = read_kitti_poses(tmp_path / "b" / "poses_kitti.txt")
    assert np.allclose(b[0], np.eye(4))  # its own origin
    proc = lidar_slam("merge", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "m")
    assert proc.returncode == 0, proc.stderr
    full = read_kitti_poses(tmp_path / "full" / "poses_kitti.txt")
    second = read_kitti_poses(tmp_path / "m" / "sessions" / "1" / "poses_kitti.txt")
    assert len(second) == 37
    err = np.linalg.norm(second[-5:, :3, 3] - full[-5:, :3, 3], axis=1)
    rot = [rotation_angle_deg(inverse(x) @ y) for x, y in zip(second[-5:], full[-5:])]
    assert err.max() < 0.05 and max(rot) < 0.5, (err, rot)
    # One recording cut in two: nothing changed between the halves.
    with open(tmp_path / "m" / "changes.csv") as fh:
        assert list(csv.DictReader(fh)) == []


def test_sessions_refuse_sweep_end_stamps_and_an_imu_clock_offset_in_one_line(tmp_path):
    """--sessions are stamped at the sweep's start on the IMU's clock: --stamp end or
    --imu-time-offset with them is one line, not silently ignored (a new user's pass)."""
    for extra in (["--stamp", "end"], ["--imu", "--imu-time-offset", "0.02"]):
        proc = lidar_slam("simulate", "--motion", "handheld", "--sessions", "2", "--duration-s",
                          "3", "--out", tmp_path / "s", *extra)
        assert_one_line_error(proc, "--sessions", "sweep's start")
        assert not (tmp_path / "s").exists()


def test_a_session_of_one_keyframe_is_merged_or_left_out_not_an_error(merged, tmp_path):
    """A run of two scans (one keyframe: its graph.g2o has no edge) merged with another: placed
    by its loops or reported and left out, never `no EDGE_SE2 ...` and exit 2 (a new user's
    pass)."""
    root, runs, _ = merged
    short = tmp_path / "short"
    proc = lidar_slam("run", root / "sim" / "session_1", "--out", short, "--n-scans", "2")
    assert proc.returncode == 0, proc.stderr
    proc = lidar_slam("merge", runs[0], short, "--out", tmp_path / "map")
    assert proc.returncode == 0, proc.stderr
    assert "session 1:" in proc.stdout and "1 keyframes" in proc.stdout, proc.stdout
