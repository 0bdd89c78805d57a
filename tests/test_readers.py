"""Readers: folder of scans (.bin/.pcd/.ply/.npy), KITTI layout, and bad inputs."""

import numpy as np
import pytest

from lidar_slam.errors import InputError
from lidar_slam.io.ply import write_xyz_ply
from lidar_slam.io.point_times import relative_seconds
from lidar_slam.io.pointcloud import read_cloud
from lidar_slam.io.sources import FolderSource, KittiSource, correct_kitti_scan, open_source
from lidar_slam.io.trajectory import read_times
from lidar_slam.o3d import o3d


def _cloud(n=100, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-20, 20, (n, 3)), rng.uniform(0, 1, n).astype(np.float32)


def test_bin_ply_pcd_npy_give_the_same_points(tmp_path):
    pts, inten = _cloud()
    np.c_[pts, inten].astype(np.float32).tofile(tmp_path / "a.bin")
    write_xyz_ply(tmp_path / "b.ply", pts, inten)
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
    pcd.point.intensity = o3d.core.Tensor(inten.reshape(-1, 1))
    o3d.t.io.write_point_cloud(str(tmp_path / "c.pcd"), pcd)
    np.save(tmp_path / "d.npy", np.c_[pts, inten])
    for name in ("a.bin", "b.ply", "c.pcd", "d.npy"):
        cloud = read_cloud(tmp_path / name)
        np.testing.assert_allclose(cloud.points, pts.astype(np.float32), atol=1e-6, err_msg=name)
        np.testing.assert_allclose(cloud.intensity, inten, atol=1e-6, err_msg=name)


def test_time_field_is_picked_up_and_converted_to_seconds(tmp_path):
    pts, _ = _cloud(50)
    t_ns = np.linspace(1.6e18, 1.6e18 + 0.1e9, 50)
    rec = np.zeros(50, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("t", "f8")])
    rec["x"], rec["y"], rec["z"], rec["t"] = pts.T[0], pts.T[1], pts.T[2], t_ns
    np.save(tmp_path / "s.npy", rec)
    cloud = read_cloud(tmp_path / "s.npy")
    assert cloud.times is not None
    assert cloud.times.min() == 0.0 and abs(cloud.times.max() - 0.1) < 1e-6
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
    pcd.point.time = o3d.core.Tensor(np.linspace(0, 0.1, 50, dtype=np.float32).reshape(-1, 1))
    o3d.t.io.write_point_cloud(str(tmp_path / "t.pcd"), pcd)
    assert abs(read_cloud(tmp_path / "t.pcd").times.max() - 0.1) < 1e-6


@pytest.mark.parametrize("raw,span", [(np.array([0, 50_000, 100_000]), 0.1),
                                      (np.array([5.0, 5.05, 5.1]), 0.1),
                                      (np.array([0, 1e8]), 0.1)])
def test_time_units_are_inferred(raw, span):
    assert abs(relative_seconds(raw).max() - span) < 1e-9


@pytest.mark.parametrize("dtype", ["f4", "f8", "i4", "i8", "u4", "u8"])
def test_offsets_written_in_s_us_and_ns_come_back_in_seconds(dtype):
    """Sweeps of 0.05-1 s written as offsets from the stamp in seconds, microseconds and
    nanoseconds (every datatype that holds them) come back in seconds: the expected values are
    the unit each file was written in, not what time_unit_s decides."""
    rng = np.random.default_rng(0)
    for sweep_s in (0.05, 0.1, 0.5, 1.0):
        t = np.sort(rng.uniform(0, sweep_s, 1000))
        for unit_s in (1.0, 1e-6, 1e-9):
            if dtype[0] in "iu" and unit_s == 1.0:
                continue  # whole seconds cannot hold a sweep
            raw = t / unit_s
            raw = (np.round(raw) if dtype[0] in "iu" else raw).astype(dtype)
            expected = raw.astype(np.float64) * unit_s  # the written values, in seconds
            np.testing.assert_allclose(relative_seconds(raw), expected, rtol=1e-12, atol=0,
                                       err_msg=f"{sweep_s} s sweep in {unit_s} s units")
            np.testing.assert_allclose(relative_seconds(raw), t, atol=max(unit_s, 1e-6) * 0.6
                                       + (1e-7 * sweep_s if dtype == "f4" else 0.0))


def test_relative_times_keep_their_zero_and_absolute_ones_start_at_zero():
    """Times already relative to the stamp (a scan stamped at the sweep's end) are kept; UNIX
    times become relative to the sweep's first point."""
    np.testing.assert_allclose(relative_seconds(np.array([-0.1, -0.05, 0.0])),
                               [-0.1, -0.05, 0.0])
    np.testing.assert_allclose(relative_seconds(np.array([-100_000, 0])), [-0.1, 0.0])
    unix_ns = np.array([1_630_577_758_000_000_000, 1_630_577_758_100_000_000], dtype=np.int64)
    np.testing.assert_allclose(relative_seconds(unix_ns), [0.0, 0.1], atol=1e-6)


def _write_pcd_with_time(path, pts, name, ptype, values):
    """Binary PCD with float x y z and one time field of PCD type ptype (U/I/F) and its size."""
    size = np.dtype(values.dtype).itemsize
    head = (f"VERSION 0.7\nFIELDS x y z {name}\nSIZE 4 4 4 {size}\nTYPE F F F {ptype}\n"
            f"COUNT 1 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {len(pts)}\nDATA binary\n")
    rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("t", values.dtype.newbyteorder("<"))])
    rec["x"], rec["y"], rec["z"], rec["t"] = pts[:, 0], pts[:, 1], pts[:, 2], values
    path.write_bytes(head.encode() + rec.tobytes())


SWEEP_S = np.linspace(0.0, 0.15, 40)  # a 0.15 s sweep (span above 1e5 us: misread as ns before)


@pytest.mark.parametrize("name,ptype,values,stamp_ns", [
    ("t", "U", np.round(SWEEP_S * 1e6).astype(np.uint32), None),         # integer microseconds
    ("t", "U", np.round(SWEEP_S * 1e9).astype(np.uint32), None),         # integer nanoseconds
    ("offset_time", "U", np.round(SWEEP_S * 1e9).astype(np.uint32), None),  # Livox
    ("time", "F", SWEEP_S.astype(np.float32), None),                     # float seconds
    ("timestamp", "U", (1_588_075_038_629_915_872                         # absolute UNIX ns
                        + np.round(SWEEP_S * 1e9)).astype(np.uint64), 1_588_075_038_629_915_872),
])
def test_pcd_time_fields_read_as_the_rosbag_reader_reads_them(tmp_path, name, ptype, values,
                                                              stamp_ns):
    """One per-point-time conversion for every reader: a PCD file and a PointCloud2 message with
    the same field give the same seconds relative to the scan stamp."""
    from test_rosbag import STAMP_NS, _cloud_msg, _rec

    from lidar_slam.io.rosbag import decode_pointcloud2

    pts = np.random.default_rng(3).uniform(-20, 20, (len(values), 3))
    _write_pcd_with_time(tmp_path / "s.pcd", pts, name, ptype, values)
    from_pcd = read_cloud(tmp_path / "s.pcd", stamp_ns)
    in_bag = values.astype(np.float64) if values.dtype == np.uint64 else values  # no UINT64
    rec = _rec(pts, step=24, extra={name: (in_bag.dtype.str, 16, in_bag)})
    from_bag = decode_pointcloud2(_cloud_msg(rec, stamp_ns=stamp_ns or STAMP_NS))
    np.testing.assert_allclose(from_pcd.times, SWEEP_S, atol=1e-6)
    # (float64 nanoseconds since 1970 are exact to ~0.2 us only)
    np.testing.assert_allclose(from_pcd.times, from_bag.point_times,
                               atol=1e-9 if in_bag is values else 1e-6)


def test_folder_gives_absolute_pcd_times_relative_to_the_stamps_in_times_txt(tmp_path):
    """A sweep stamped at its middle: absolute integer-nanosecond point times minus the stamp."""
    stamp_ns = 1_630_577_758_000_000_000
    pts = np.random.default_rng(4).uniform(-20, 20, (len(SWEEP_S), 3))
    for i in range(2):
        t0 = stamp_ns + i * 100_000_000
        ns = (t0 - 75_000_000 + np.round(SWEEP_S * 1e9)).astype(np.uint64)
        _write_pcd_with_time(tmp_path / f"{i}.pcd", pts, "t", "U", ns)
    (tmp_path / "times.txt").write_text(f"{stamp_ns * 1e-9:.9f}\n{stamp_ns * 1e-9 + 0.1:.9f}\n")
    for scan in open_source(tmp_path).scans():
        np.testing.assert_allclose(scan.point_times, SWEEP_S - 0.075, atol=1e-6)


def test_folder_is_sorted_naturally_and_nan_points_dropped(tmp_path):
    for i in (10, 2, 1):
        pts, inten = _cloud(20, seed=i)
        pts[0] = np.nan
        np.c_[pts, inten].astype(np.float32).tofile(tmp_path / f"scan{i}.bin")
    src = open_source(tmp_path)
    assert isinstance(src, FolderSource)
    assert [f.name for f in src.files] == ["scan1.bin", "scan2.bin", "scan10.bin"]
    scans = list(src.scans())
    assert [s.index for s in scans] == [0, 1, 2]
    assert all(len(s.points) == 19 for s in scans)
    assert [s.stamp_s for s in scans] == pytest.approx([0.0, 0.1, 0.2])


def test_kitti_layout_reads_lidar_frame_ground_truth(kitti16):
    src = open_source(kitti16)
    assert isinstance(src, KittiSource) and len(src) == 16
    scan = next(src.scans(start=3, count=1))
    assert scan.index == 3 and len(scan.points) > 100_000
    # The car drives forward along the lidar's x axis ~0.86 m per frame.
    step = np.linalg.inv(src.ground_truth[0]) @ src.ground_truth[1]
    assert 0.8 < step[0, 3] < 0.9 and abs(step[1, 3]) < 0.1
    assert src.ground_truth[0][:3, 3] == pytest.approx([0, 0, 0], abs=1e-6)


def test_kitti_vertical_correction_matches_kiss_icp():
    from kiss_icp.pybind import kiss_icp_pybind as kp

    pts, _ = _cloud(500)
    ref = np.asarray(kp._correct_kitti_scan(kp._Vector3dVector(pts)))
    np.testing.assert_allclose(correct_kitti_scan(pts), ref, atol=1e-9)
    # A point on the sensor's z axis has no rotation axis: like kiss-icp, only scaled by cos.
    on_axis = np.array([[0.0, 0.0, 3.0]])
    ref_axis = np.asarray(kp._correct_kitti_scan(kp._Vector3dVector(on_axis)))
    np.testing.assert_allclose(correct_kitti_scan(on_axis), ref_axis, atol=1e-9)


def test_folder_with_scans_subfolder_and_reference_poses(ouster_loop):
    src = open_source(ouster_loop)
    assert len(src) == 77 and src.ground_truth.shape == (77, 4, 4)
    assert src.stamps[1] - src.stamps[0] == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("make,problem", [
    (lambda d: d / "missing", "does not exist"),
    (lambda d: d, "no scans found"),
])
def test_bad_paths(tmp_path, make, problem):
    with pytest.raises(InputError, match=problem):
        open_source(make(tmp_path))


def test_bin_with_wrong_size(tmp_path):
    (tmp_path / "x.bin").write_bytes(b"\0" * 1234)
    with pytest.raises(InputError) as err:
        next(open_source(tmp_path).scans())
    assert str(err.value) == (f"{tmp_path / 'x.bin'}: 1234 bytes is not a multiple of 16 "
                              "(float32 x,y,z,intensity)")


@pytest.mark.parametrize("layout,problem", [
    ("float64", "holds float64 x, y, z, intensity (read as float32 x, y, z, intensity,"),
    ("float64-xyz", "holds float64 x, y, z (read as float32"),
    ("xyz", "the 4th column (intensity) is negative on")])
def test_bin_in_another_layout_is_refused_not_read_as_a_cloud(tmp_path, layout, problem):
    """float64 numbers and float32 without intensity (sizes that are multiples of 16 too) read
    as float32 x, y, z, intensity rows: each is refused in one line."""
    pts, inten = _cloud(n=1200)
    data = {"float64": np.c_[pts, inten].astype(np.float64).tobytes(),
            "float64-xyz": pts[:1000].astype(np.float64).tobytes(),
            "xyz": pts.astype(np.float32).tobytes()}[layout]
    (tmp_path / "x.bin").write_bytes(data)
    with pytest.raises(InputError, match="x.bin: ") as err:
        read_cloud(tmp_path / "x.bin")
    assert problem in str(err.value)
    # a cloud with a few points out of range (one in a hundred at most) still reads
    rows = np.c_[pts, inten].astype(np.float32)
    rows[:10, 0] = 3e19
    rows.tofile(tmp_path / "ok.bin")
    assert len(read_cloud(tmp_path / "ok.bin").points) == 1200


def test_bin_of_random_bytes_is_an_empty_scan_with_a_warning(tmp_path, caplog):
    """Bytes that are not numbers in any layout: the scan is skipped (the run goes on), not read
    as a cloud of which a thousand points fall in range."""
    (tmp_path / "x.bin").write_bytes(np.random.default_rng(3).bytes(16 * 1200))
    assert len(read_cloud(tmp_path / "x.bin").points) == 0
    assert "x.bin: " in caplog.text and "scan skipped" in caplog.text


def test_non_finite_intensities_become_zero():
    from lidar_slam.io.pointcloud import CloudData
    from lidar_slam.io.sources import make_scan

    inten = np.ones(10, np.float32)
    inten[[2, 5]] = [np.nan, np.inf]
    scan = make_scan(0, 1.0, CloudData(np.ones((10, 3)), None, inten), "x")
    np.testing.assert_array_equal(scan.intensity, [1, 1, 0, 1, 1, 0, 1, 1, 1, 1])


@pytest.mark.parametrize("name,content", [("bad.pcd", b"garbage\x00\x01"),
                                          ("bad.ply", b"not a ply"),
                                          ("trunc.pcd", (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n"
                                           b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\n"
                                           b"HEIGHT 1\nPOINTS 10\nDATA binary\n\x00\x00"))])
def test_unreadable_pcd_ply(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=name):
        read_cloud(tmp_path / name)


def test_empty_pcd_is_an_empty_cloud_not_an_error(tmp_path):
    (tmp_path / "e.pcd").write_bytes(b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
                                     b"TYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\n"
                                     b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 0\nDATA ascii\n")
    assert len(read_cloud(tmp_path / "e.pcd").points) == 0


def test_make_scan_drops_exactly_the_non_finite_rows():
    from lidar_slam.io.pointcloud import CloudData
    from lidar_slam.io.sources import make_scan

    pts = np.random.default_rng(1).uniform(-50, 50, (100, 3))
    pts[3] = [np.inf, -np.inf, 0.0]  # sums to NaN
    pts[7, 2] = np.nan
    pts[9] = [1e308, 1e308, 0.0]  # finite, but its sum overflows: kept
    times, inten = np.linspace(0, 0.1, 100), np.arange(100, dtype=np.float32)
    scan = make_scan(0, 1.0, CloudData(pts, times, inten), "x")
    keep = np.setdiff1d(np.arange(100), [3, 7])
    np.testing.assert_array_equal(scan.points, pts[keep])
    np.testing.assert_array_equal(scan.point_times, times[keep])
    np.testing.assert_array_equal(scan.intensity, inten[keep])
    clean = make_scan(0, 1.0, CloudData(pts[keep], None, None), "x")
    assert clean.points is not None and len(clean.points) == 98


def _sample_with_times(tmp_path, edit):
    """sample_scans copied with its times.txt lines changed by edit(list of lines)."""
    import shutil
    from pathlib import Path

    seq = tmp_path / "seq"
    shutil.copytree(Path(__file__).resolve().parents[1] / "sample_scans", seq)
    lines = (seq / "times.txt").read_text().splitlines()
    (seq / "times.txt").write_text("\n".join(edit(lines)) + "\n")
    return seq


@pytest.mark.parametrize("edit,needles", [
    # scan 11 stamped before scan 10 (lines 12 and 11 of times.txt)
    (lambda ls: ls[:10] + [ls[11], ls[10]] + ls[12:],
     [("times.txt: line 12: stamp 2.000000 s is not after line 11's 2.200000 s (stamps must "
       "increase)")]),
    (lambda ls: ls[:30] + [ls[29]] + ls[31:],
     ["line 31: stamp 5.800000 s is not after line 30's 5.800000 s"]),
    (lambda ls: ls[:5] + ["nan"] + ls[6:], ["times.txt: line 6: stamp nan is not a finite"]),
    (lambda ls: ls[:5] + ["inf"] + ls[6:], ["times.txt: line 6: stamp inf is not a finite"]),
], ids=["back", "repeated", "nan", "inf"])
def test_scan_stamps_that_do_not_increase_stop_the_run_with_the_line(tmp_path, edit, needles):
    """A times.txt with two stamps swapped ran (ATE 0.083 -> 0.149 m on the sample drive); now
    the run stops at once: exit 2, one line naming the file, the line and the stamps."""
    from test_cli import assert_one_line_error, lidar_slam

    seq = _sample_with_times(tmp_path, edit)
    proc = lidar_slam("run", seq, "--out", tmp_path / "out", "--n-scans", "3", timeout=120)
    assert_one_line_error(proc, *needles)
    assert not (tmp_path / "out").exists()


def test_a_comment_or_blank_line_keeps_the_line_numbers_of_the_file(tmp_path):
    (tmp_path / "times.txt").write_text("# stamps\n0.0\n\n0.1  # ok\n0.1\n")
    with pytest.raises(InputError, match="line 5: stamp 0.100000 s is not after line 4's"):
        read_times(tmp_path / "times.txt")
    (tmp_path / "times.txt").write_text("1.0000000001\n1.0000000002\n1.0000000001\n")
    with pytest.raises(InputError, match=r"line 3: stamp 1.0000000001 s is not after line 2's "
                                         r"1.0000000002 s"):
        read_times(tmp_path / "times.txt")


def test_kitti_raw_timestamps_that_go_back_are_refused(tmp_path):
    from lidar_slam.io.sources import read_kitti_raw_timestamps

    path = tmp_path / "timestamps.txt"
    path.write_text("2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.064389445\n"
                    "2011-09-26 13:02:26.014389445\n")
    with pytest.raises(InputError, match=r"timestamps.txt: line 3: stamp 1317042146.01439\d s "
                                         r"is not after line 2's 1317042146.064389 s"):
        read_kitti_raw_timestamps(path)
    path.write_text("2011-09-26 13:02:25.964389445\n2011-09-26 13:02:25.964389445\n")
    with pytest.raises(InputError, match="line 2: .* is not after line 1's"):
        read_kitti_raw_timestamps(path)


def test_shared_sequences_still_read(kitti16, ouster_loop):
    """The stamps of the shared data increase: both still open, with all their stamps."""
    assert len(open_source(kitti16).stamps) == 16
    assert len(open_source(ouster_loop).stamps) == 77


def test_a_calib_tr_that_is_not_rigid_or_finite_is_refused(tmp_path):
    from lidar_slam.io.trajectory import read_kitti_calib_tr

    calib = tmp_path / "calib.txt"
    for tr, problem in (("1 0 0 0 0 1 0 0 0 0 1 nan", "NaN or infinite"),
                        ("2 0 0 0 0 1 0 0 0 0 1 0", "not a rigid transform"),
                        ("0 0 0 0 0 0 0 0 0 0 0 0", "not a rigid transform"),
                        ("-1 0 0 0 0 1 0 0 0 0 1 0", "not a rigid transform")):
        calib.write_text(f"P0: 1 2 3\nTr: {tr}\n")
        with pytest.raises(InputError, match=f"line 2: Tr .*{problem}"):
            read_kitti_calib_tr(calib)
    calib.write_bytes(b"Tr: \xff\xfe\n")
    with pytest.raises(InputError, match="not a text file"):
        read_kitti_calib_tr(calib)


def test_reference_poses_with_nan_are_refused(tmp_path):
    from lidar_slam.io.trajectory import read_kitti_poses

    rows = np.tile(np.eye(4)[:3].ravel(), (3, 1))
    rows[1, 3] = np.inf
    np.savetxt(tmp_path / "poses.txt", rows)
    with pytest.raises(InputError, match="poses.txt: pose 2: NaN or infinite"):
        read_kitti_poses(tmp_path / "poses.txt")


def test_poses_that_are_not_rigid_motions_are_refused(tmp_path):
    """A scaled or all-zero rotation (KITTI rows) or a quaternion of norm 0 (TUM) would be
    scored as if it were a pose: one line naming the pose instead."""
    from lidar_slam.io.trajectory import read_kitti_poses, read_tum

    for bad in (2 * np.eye(3), np.zeros((3, 3)), np.diag([1.0, 1.0, -1.0])):
        rows = np.tile(np.eye(4)[:3].ravel(), (3, 1))
        rows[2] = np.c_[bad, [1.0, 2.0, 3.0]].ravel()
        np.savetxt(tmp_path / "poses.txt", rows)
        with pytest.raises(InputError, match="poses.txt: pose 3: not a rigid motion"):
            read_kitti_poses(tmp_path / "poses.txt")
    rows = np.array([[0.0, 0, 0, 0, 0, 0, 0, 1], [0.1, 1, 0, 0, 0, 0, 0, 0]])
    np.savetxt(tmp_path / "p.tum", rows)
    with pytest.raises(InputError, match="p.tum: pose 2: .* norm is not 1"):
        read_tum(tmp_path / "p.tum")


PCD_XYZ = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH %d\n"
           b"HEIGHT 1\nPOINTS %d\nDATA %s\n")
PLY_XYZ = (b"ply\nformat %s 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
           b"property float z\nend_header\n")


@pytest.mark.parametrize("name,content,problem", [
    # open3d returned 5 points, 4 of them uninitialised memory, and printed nothing
    ("short.pcd", PCD_XYZ % (5, 5, b"ascii") + b"1 2 3\n4 5\n", "POINTS 5 but the ascii data"),
    # ... or took words that are not numbers as 0
    ("junk.pcd", PCD_XYZ % (2, 2, b"ascii") + b"a b c\n1 2 3\n", "'a' is not a number"),
    ("size2.pcd", PCD_XYZ.replace(b"SIZE 4 4 4", b"SIZE 2 2 2") % (1, 1, b"binary")
     + b"\0" * 6, "SIZE 2 TYPE F is not a supported type"),  # was a RuntimeError
    ("huge.pcd", PCD_XYZ % (2**31 - 1, 2**31 - 1, b"binary") + b"\0" * 24,
     "binary data is 24 bytes"),  # was a RuntimeError (malloc failed) or a large allocation
    ("short.ply", PLY_XYZ % (b"binary_little_endian", 100) + b"\0" * 24,
     "binary data is 24 bytes"),  # 96 of 100 points uninitialised
    ("short_ascii.ply", PLY_XYZ % (b"ascii", 2) + b"1 2 3\n4 5\n", "ascii data has 5 values"),
    ("no_z.ply", (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                  b"property float y\nend_header\n1 2\n"), "need x, y, z"),  # z was 0
])
def test_pcd_and_ply_that_open3d_would_fill_with_garbage_are_refused(tmp_path, name, content,
                                                                     problem):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=problem) as err:
        read_cloud(tmp_path / name)
    assert str(err.value).startswith(f"{tmp_path / name}: ") and "\n" not in str(err.value)


def test_good_ascii_pcd_and_ply_read_exactly(tmp_path):
    (tmp_path / "a.pcd").write_bytes(PCD_XYZ % (2, 2, b"ascii") + b"1 2 3\n-4.5 nan 6e3\n")
    (tmp_path / "a.ply").write_bytes(PLY_XYZ % (b"ascii", 2) + b"1 2 3\n-4.5 nan 6e3\n")
    for name in ("a.pcd", "a.ply"):
        np.testing.assert_array_equal(read_cloud(tmp_path / name).points,
                                      [[1, 2, 3], [-4.5, np.nan, 6000]])


def test_npy_files_that_numpy_cannot_read_as_points_are_one_error(tmp_path):
    import io

    buf = io.BytesIO()
    np.save(buf, np.zeros((2, 3), np.float32))
    cases = {
        "empty.npy": b"",  # was EOFError
        "huge.npy": buf.getvalue().replace(b"(2, 3)", b"(10000000000, 3)"),  # was MemoryError
    }
    text = np.zeros(2, dtype=[("x", "S4"), ("y", "f4"), ("z", "f4")])
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    np.save(tmp_path / "text.npy", text)  # was a ValueError from astype
    np.save(tmp_path / "complex.npy", np.zeros((2, 3), np.complex64))  # imaginary part dropped
    for name in ("empty.npy", "huge.npy", "text.npy", "complex.npy"):
        with pytest.raises(InputError, match=name):
            read_cloud(tmp_path / name)


def test_part_of_a_kitti_sequence_beside_its_whole_poses_and_times(tmp_path, caplog):
    """Scans 000005..000007 of a sequence whose poses.txt and times.txt cover all 10 frames: each
    scan's number picks its line (one warning each); names that are not line numbers are one
    error."""
    from lidar_slam.io.sources import KittiSource

    seq = tmp_path / "00"
    (seq / "velodyne").mkdir(parents=True)
    pts, inten = _cloud()
    for k in (5, 6, 7):
        np.c_[pts, inten].astype(np.float32).tofile(seq / "velodyne" / f"{k:06d}.bin")
    (seq / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    rows = np.tile(np.eye(4)[:3].ravel(), (10, 1))
    rows[:, 3] = np.arange(10)
    np.savetxt(seq / "poses.txt", rows)
    np.savetxt(seq / "times.txt", 0.1 * np.arange(10))
    src = KittiSource(seq)
    np.testing.assert_allclose(src.ground_truth[:, 0, 3], [5, 6, 7])
    np.testing.assert_allclose(src.stamps, [0.5, 0.6, 0.7])
    assert caplog.text.count("each scan's number picks its line (000005..000007)") == 2
    (seq / "velodyne" / "000007.bin").rename(seq / "velodyne" / "x.bin")
    with pytest.raises(InputError, match="times.txt: has 10 stamps for 3 scans, and the scans'"):
        KittiSource(seq)


def test_pose_file_errors_name_the_line_without_numpys_advice(tmp_path):
    from lidar_slam.eval.evaluate import trajectory_format
    from lidar_slam.io.trajectory import read_kitti_poses

    row = " ".join(map(str, np.eye(4)[:3].ravel()))
    (tmp_path / "a.txt").write_text(f"{row}\n{row}\n1 2 3\n")
    with pytest.raises(InputError, match=r"a.txt: not a KITTI pose file \(line 3 has 3 numbers, "
                                         r"the lines before 12\)$"):
        read_kitti_poses(tmp_path / "a.txt")
    (tmp_path / "b.txt").write_text(f"{row}\n{row.replace('0.0', 'x', 1)}\n")
    with pytest.raises(InputError, match=r"line 2, value 2: 'x' is not a number\)$"):
        read_kitti_poses(tmp_path / "b.txt")
    (tmp_path / "c.mcap").write_bytes(b"\x89MCAP0\r\n\xff\xfe")
    with pytest.raises(InputError, match="c.mcap: not a text pose file"):
        trajectory_format(tmp_path / "c.mcap")


def test_a_folder_holding_a_recording_says_to_pass_the_file(tmp_path):
    (tmp_path / "drive.mcap").write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(InputError, match=r"no scans found .*; a recording is here: pass the file "
                                         r"itself \(.*drive.mcap\)"):
        open_source(tmp_path)


def test_a_pickled_npy_says_so_in_one_line(tmp_path):
    np.save(tmp_path / "p.npy", np.array([{"x": 1.0}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match=r"p.npy: a .npy of Python objects \(pickled\), not of "
                                         r"numbers; save the points as a numeric array$"):
        read_cloud(tmp_path / "p.npy")


def test_a_scan_missing_its_point_times_beside_the_others_is_warned_by_name(trot_end, tmp_path,
                                                                            caplog):
    """velodyne_times/ holds every scan's times but one: that scan is read without deskew, and
    one warning names its missing file (it was only a count in summary.json's deskew)."""
    import logging
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(trot_end, seq)
    (seq / "velodyne_times" / "000002.bin").unlink()
    with caplog.at_level(logging.WARNING, logger="lidar_slam.io.sources"):
        scans = list(KittiSource(seq).scans(0, 4))
    assert [s.point_times is None for s in scans] == [False, False, True, False]
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "000002.bin" in said[0] and "not deskewed" in said[0], said
