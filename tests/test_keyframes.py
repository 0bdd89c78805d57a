"""Keyframe store on disk and the streamed global map."""

import numpy as np
import pytest

from lidar_slam.errors import InputError
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.geometry import make_pose
from lidar_slam.io.ply import read_ply
from lidar_slam.map.keyframes import KeyframeReader, KeyframeStore
from lidar_slam.map.writer import write_map


def _fill(store, n=30, seed=0):
    rng = np.random.default_rng(seed)
    clouds = []
    for k in range(n):
        pts = rng.uniform(-40, 40, (500 + k, 3))
        inten = rng.uniform(0, 1, len(pts)).astype(np.float32)
        store.add(10 * k, make_pose(np.eye(3), [3.0 * k, 0, 0]), pts, inten)
        clouds.append((pts, inten))
    return clouds


def test_keyframes_store_reads_back_what_it_wrote(tmp_path):
    store = KeyframeStore(tmp_path / "kf", cache_size=4)
    clouds = _fill(store)
    for k in (0, 7, 29, 3):  # most are out of the small cache: read from disk
        kf = store.get(k)
        np.testing.assert_allclose(kf.points, clouds[k][0].astype(np.float32))
        np.testing.assert_array_equal(kf.intensity, clouds[k][1])
        assert kf.frame_index == 10 * k and kf.T_world_kf_odom[0, 3] == 3.0 * k
    store.flush()
    store.close()


def test_keyframes_odometry_poses_in_one_read_are_each_keyframes(tmp_path):
    store = KeyframeStore(tmp_path / "kf")
    _fill(store, n=12)
    store.flush()
    reader = KeyframeReader(tmp_path / "kf")  # the loop worker's view of the same store
    for view in (store, reader):
        poses = view.odom_poses(3, 9)
        assert poses.shape == (7, 4, 4)
        for i, k in enumerate(range(3, 10)):
            np.testing.assert_array_equal(poses[i], store.T_world_kf_odom(k))
        with pytest.raises(KeyError):
            view.odom_poses(5, 12)  # past the last keyframe
    store.close()


def test_keyframes_store_reopens_and_truncates_to_a_checkpoint(tmp_path):
    store = KeyframeStore(tmp_path / "kf")
    clouds = _fill(store, 12)
    store.flush()
    store.close()
    with open(tmp_path / "kf" / "table.bin", "ab") as fh:  # a killed run's partial record
        fh.write(b"\x01" * 17)
    again = KeyframeStore(tmp_path / "kf", keep=True)
    assert len(again) == 12
    again.truncate(9)
    assert len(again) == 9
    kf = again.add(999, np.eye(4), clouds[0][0], None)
    assert kf.id == 9 and again.get(9).intensity is None
    np.testing.assert_allclose(again.get(8).points, clouds[8][0].astype(np.float32))
    with pytest.raises(InputError):
        again.truncate(50)
    again.close()
    assert len(KeyframeStore(tmp_path / "kf")) == 0  # a fresh store starts empty


def test_keyframes_streamed_map_equals_downsampling_everything(tmp_path, monkeypatch):
    import lidar_slam.map.writer as mapping

    monkeypatch.setattr(mapping, "TILE_VOXELS", 50)  # many tiles: 10 m at 0.2 m
    monkeypatch.setattr(mapping, "CHUNK_POINTS", 3000)  # many spills
    store = KeyframeStore(tmp_path / "kf")
    clouds = _fill(store)
    poses = {k: store.T_world_kf_odom(k) for k in range(len(store))}
    n = write_map(tmp_path / "map.ply", store, poses, 0.2)
    pts, inten = read_ply(tmp_path / "map.ply")
    world = np.concatenate([c[0].astype(np.float32).astype(np.float64) + [3.0 * k, 0, 0]
                            for k, c in enumerate(clouds)])
    ref, ref_i = voxel_downsample(world, 0.2, np.concatenate([c[1] for c in clouds]))
    assert n == len(pts) == len(ref)
    key = lambda p: np.lexsort(np.floor(p / 0.2).T)  # noqa: E731
    np.testing.assert_allclose(pts[key(pts)], ref[key(ref)].astype(np.float32), atol=1e-4)
    np.testing.assert_allclose(inten[key(pts)], ref_i[key(ref)], atol=1e-5)


def test_keyframes_map_is_the_same_whatever_the_chunk_size(tmp_path, monkeypatch):
    import lidar_slam.map.writer as mapping

    store = KeyframeStore(tmp_path / "kf")
    _fill(store)
    poses = {k: store.T_world_kf_odom(k) for k in range(len(store))}
    n = write_map(tmp_path / "a.ply", store, poses, 0.5)
    monkeypatch.setattr(mapping, "CHUNK_POINTS", 137)  # keyframes (500+ points) split in pieces
    assert write_map(tmp_path / "b.ply", store, poses, 0.5) == n
    a, b = read_ply(tmp_path / "a.ply"), read_ply(tmp_path / "b.ply")
    np.testing.assert_allclose(a[0], b[0], atol=1e-5)
    np.testing.assert_allclose(a[1], b[1], atol=1e-5)


def test_keyframes_map_refuses_points_beyond_its_voxel_keys(tmp_path):
    store = KeyframeStore(tmp_path / "kf")
    store.add(0, np.eye(4), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0e5]]), None)
    with pytest.raises(ValueError, match="too far"):
        write_map(tmp_path / "map.ply", store, {0: np.eye(4)}, 0.2)


def test_a_keyframe_due_at_a_flick_waits_for_a_steady_scan_but_not_past_the_next_one_due():
    from lidar_slam.config import KeyframeConfig
    from lidar_slam.frontend.keyframes import SteadyWait

    w = SteadyWait(KeyframeConfig(steady_miss_deg=1.0, steady_wait_scans=3))
    assert w.take(True, 0.5)  # steady: made where it fell due
    assert not w.take(True, 2.0) and not w.take(False, 3.0)  # a flick: waits
    assert w.take(False, 0.9) and not w.pending  # the first steady scan
    assert (w.late, w.not_steady) == (1, 0)  # summary.json keyframes_steady_wait
    # never more than steady_wait_scans scans late
    w = SteadyWait(KeyframeConfig(steady_miss_deg=1.0, steady_wait_scans=3))
    assert [w.take(d, 5.0) for d in (True, False, False, False)] == [False, False, False, True]
    # one falling due makes the waiting one there, and waits in its place
    assert not w.take(True, 5.0) and w.take(True, 5.0) and w.pending
    assert (w.late, w.not_steady) == (2, 2)  # at the wait's end, and where the next fell due
    assert w.take(False, None) and not w.pending  # a miss not measured: made at once
    assert (w.late, w.not_steady) == (3, 3)  # counted, as not steady
    # a walk that always shakes by 2 deg: a flick is over twice that, steady within it
    w = SteadyWait(KeyframeConfig(steady_miss_deg=1.0, steady_wait_scans=3))
    assert not any(w.take(False, 2.0) for _ in range(30))
    assert w.take(True, 3.9)  # its usual shake: made where it fell due
    assert not w.take(True, 4.5) and not w.take(False, 2.5) and w.take(False, 1.9)
    # not measured (an IMU deskews) or switched off: made where it fell due
    assert SteadyWait(KeyframeConfig()).take(True, None)
    assert SteadyWait(KeyframeConfig(steady_miss_deg=0.0)).take(True, 9.0)
    assert SteadyWait(KeyframeConfig(steady_wait_scans=0)).take(True, 9.0)
    assert not SteadyWait(KeyframeConfig()).take(False, 0.0)  # nothing due, nothing made
