"""What a new user hit on a first `lidar-slam run` (issue 30, item 7): an unreadable scan, a
--resume with nothing to resume, a scan of garbage bytes, no picture, a config typo."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_scans"
FEW = ("--n-scans", "4", "--no-loops")


def lidar_slam(*args, python_flags=(), timeout=600):
    return subprocess.run([sys.executable, *python_flags, "-m", "lidar_slam.cli",
                           *map(str, args)], capture_output=True, text=True, timeout=timeout)


def sample_copy(tmp_path: Path, n: int = 4) -> Path:
    """The first n scans of sample_scans (KITTI layout, with per-point times)."""
    data = tmp_path / "scans"
    for sub in ("velodyne", "velodyne_times"):
        (data / sub).mkdir(parents=True)
        for f in sorted((SAMPLE / sub).glob("*.bin"))[:n]:
            shutil.copy(f, data / sub / f.name)
    shutil.copy(SAMPLE / "calib.txt", data / "calib.txt")
    (data / "times.txt").write_text("".join((SAMPLE / "times.txt").read_text()
                                            .splitlines(keepends=True)[:n]))
    return data


def test_an_unreadable_scan_is_one_line_naming_it_and_exit_2(tmp_path, monkeypatch):
    """Permission denied on a scan: its path and the reason, exit 2 (it was "internal error",
    exit 1). chmod as a user; as root (who reads anything) the OS error NumPy raises."""
    data = sample_copy(tmp_path)
    bad = data / "velodyne" / "000002.bin"
    if os.geteuid() != 0:
        bad.chmod(0)
        proc = lidar_slam("run", data, "--out", tmp_path / "o", *FEW)
        assert_one_line_error(proc, str(bad), "Permission denied", "frames so far written")
        return
    from typer.testing import CliRunner

    from lidar_slam.cli import app

    real = np.fromfile

    def denied(file, *args, **kwargs):
        if Path(file) == bad:
            raise PermissionError(13, "Permission denied", str(file))
        return real(file, *args, **kwargs)

    monkeypatch.setattr(np, "fromfile", denied)
    res = CliRunner().invoke(app, ["run", str(data), "--out", str(tmp_path / "o"), *FEW])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("lidar-slam: error:")]
    assert len(lines) == 1 and f"{bad}: cannot read (Permission denied)" in lines[0], res.output


def test_resume_with_no_checkpoint_says_it_starts_over(tmp_path):
    """--resume on a folder with no run, on a finished run, on a run that ended before its
    first checkpoint and on a folder of someone else's files: one line each; it starts over,
    does nothing, starts over, and refuses (documented in the README)."""
    out = tmp_path / "o"
    proc = lidar_slam("run", SAMPLE, "--out", out, *FEW, "--resume")
    assert proc.returncode == 0, proc.stderr
    assert f"WARNING lidar_slam: --resume: {out} holds no run; starting from the first scan" \
        in proc.stderr
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    proc = lidar_slam("run", SAMPLE, "--out", out, *FEW, "--resume")
    assert proc.returncode == 0, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if "--resume" in ln]
    assert len(said) == 1 and f"the run in {out} had already finished" in said[0], proc.stderr
    assert f"nothing to resume in {out}: finished before" in proc.stdout
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    (out / "summary.json").unlink()  # as a run killed before its first checkpoint leaves it
    proc = lidar_slam("run", SAMPLE, "--out", out, *FEW, "--resume")
    assert proc.returncode == 0, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if "--resume" in ln]
    assert len(said) == 1 and f"no checkpoint in {out}" in said[0] \
        and "starting over from the first scan" in said[0], proc.stderr
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "poses_kitti.txt").write_text("their own\n")
    proc = lidar_slam("run", SAMPLE, "--out", theirs, *FEW, "--resume")
    assert_one_line_error(proc, str(theirs), "--resume: holds files but no lidar-slam run")
    assert (theirs / "poses_kitti.txt").read_text() == "their own\n"


def test_a_scan_of_garbage_bytes_warns_naming_it_with_no_numpy_warning(tmp_path):
    """Random bytes (signalling NaNs among them) in a scan and its times: warnings that name
    the file, the scan skipped, the run goes on; with -W error a NumPy RuntimeWarning would
    end the run."""
    data = sample_copy(tmp_path)
    rng = np.random.default_rng(3)
    for sub in ("velodyne", "velodyne_times"):
        f = data / sub / "000002.bin"
        f.write_bytes(rng.bytes(f.stat().st_size))
    proc = lidar_slam("run", data, "--out", tmp_path / "o", *FEW,
                      python_flags=("-W", "error::RuntimeWarning"))
    assert proc.returncode == 0, proc.stderr
    assert "RuntimeWarning" not in proc.stderr and "Traceback" not in proc.stderr
    named = [ln for ln in proc.stderr.splitlines()
             if ln.startswith("WARNING") and "000002.bin" in ln]
    assert named and any("skipped" in ln for ln in named), proc.stderr


def test_run_writes_a_top_view_of_trajectory_and_map(tmp_path):
    out = tmp_path / "o"
    proc = lidar_slam("run", SAMPLE, "--out", out, *FEW)
    assert proc.returncode == 0, proc.stderr
    png = (out / "top_view.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000


@pytest.mark.parametrize("text,hint", [
    ("odometry:\n  voxle_size_m: 0.5\n", "did you mean odometry.voxel_size_m?"),
    ("data:\n  time_offset_s: 0.1\n", "did you mean imu.time_offset_s or gnss.time_offset_s?"),
])
def test_a_config_typo_is_one_line_with_did_you_mean(tmp_path, text, hint):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    assert_one_line_error(lidar_slam("run", SAMPLE, "--out", tmp_path / "o", "--config", cfg),
                          str(cfg), hint)


def test_an_out_that_is_an_input_is_refused_before_anything_is_deleted(tmp_path):
    """--out naming the input folder, the map a run extends or the map localize reads (with
    --overwrite, which would delete their files first): one line, exit 2, nothing touched."""
    data = sample_copy(tmp_path)
    proc = lidar_slam("run", data, "--out", data, *FEW, "--overwrite")
    assert_one_line_error(proc, f"{data}: --out is the input; write the outputs to another folder")
    assert not (data / "map.ply").exists()
    run = tmp_path / "map"
    assert lidar_slam("run", data, "--out", run, *FEW).returncode == 0
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    proc = lidar_slam("run", data, "--extend", run, "--out", run, *FEW, "--overwrite")
    assert_one_line_error(proc, f"{run}: --out is the map to extend")
    proc = lidar_slam("localize", data, "--map", run, "--out", run, "--overwrite")
    assert_one_line_error(proc, f"{run}: --out is the map; write the outputs to another folder")
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before


def test_overwrite_that_cannot_delete_says_where_and_deletes_nothing(tmp_path, monkeypatch):
    """--overwrite on a run whose keyframes folder is read-only: one line naming that folder,
    and the old run left whole (it deleted config.yaml and checkpoint/ first, then failed on
    a bare "map_poses.bin"). As root, who may delete anything, os.access is made to say no."""
    from lidar_slam.errors import RunFailed
    from lidar_slam.run.outdir import RUN_OUTPUTS, prepare_out_dir

    out = tmp_path / "run"
    for name in ("config.yaml", "summary.json", "checkpoint/state.bin", "keyframes/map_poses.bin"):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("x")
    locked = out / "keyframes"
    if os.geteuid() != 0:
        locked.chmod(0o555)
    else:
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode: Path(p) != locked and real(p, mode))
    try:
        with pytest.raises(RunFailed, match=f"{locked}: --overwrite cannot delete in it"):
            prepare_out_dir(out, RUN_OUTPUTS, overwrite=True)
    finally:
        locked.chmod(0o755)
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint", "config.yaml", "keyframes",
                                                     "summary.json"]
    monkeypatch.undo()
    prepare_out_dir(out, RUN_OUTPUTS, overwrite=True)  # writable again: all of it goes
    assert list(out.iterdir()) == []


def test_no_output_file_is_made_executable(tmp_path):
    """The keyframe store's files were created with os.open's default mode (0o777 less the
    umask: -rwxr-xr-x); every file a run writes is rw, never x."""
    import stat

    out = tmp_path / "o"
    assert lidar_slam("run", SAMPLE, "--out", out, *FEW).returncode == 0
    made = [p for p in out.rglob("*") if p.is_file()]
    assert any(p.parent.name == "keyframes" for p in made)
    x = stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH
    assert [p for p in made if p.stat().st_mode & x] == []


def test_overwrite_deletes_a_linked_output_folder_as_a_link(tmp_path):
    """A run whose keyframes/ is a link to a folder elsewhere: --overwrite removes the link and
    leaves what it points at (rmtree refused the link after the rest was gone)."""
    from lidar_slam.run.outdir import RUN_OUTPUTS, prepare_out_dir

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "points.bin").write_text("keep")
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.yaml").write_text("x")
    (out / "keyframes").symlink_to(elsewhere)
    prepare_out_dir(out, RUN_OUTPUTS, overwrite=True)
    assert list(out.iterdir()) == [] and (elsewhere / "points.bin").read_text() == "keep"


def test_an_rrd_on_an_input_or_an_existing_file_is_refused_and_nothing_is_written(tmp_path):
    """--rrd naming a scan replaced it with a recording (the next run stopped there); an
    existing file was replaced without a word. Now --out's rules: one line, nothing touched."""
    data = sample_copy(tmp_path)
    scan = sorted((data / "velodyne").glob("*.bin"))[2]
    before = scan.read_bytes()
    proc = lidar_slam("run", data, "--out", tmp_path / "o", *FEW, "--rrd", scan)
    assert_one_line_error(proc, f"{scan}: --rrd is an input of the run")
    assert scan.read_bytes() == before and not (tmp_path / "o").exists()
    old = tmp_path / "notes.txt"
    old.write_text("mine")
    proc = lidar_slam("run", data, "--out", tmp_path / "o", *FEW, "--rrd", old)
    assert_one_line_error(proc, f"{old}: --rrd already exists; pass --overwrite")
    assert old.read_text() == "mine"


def test_an_out_in_the_folder_the_scans_are_read_from_is_refused(tmp_path):
    """--out DATA/velodyne wrote map.ply among the scans, read back as a scan by the next run."""
    data = sample_copy(tmp_path)
    proc = lidar_slam("run", data, "--out", data / "velodyne", *FEW, "--overwrite")
    assert_one_line_error(proc, f"{data / 'velodyne'}: --out is the folder the input's scans are "
                                "read from")
    assert not (data / "velodyne" / "map.ply").exists()


def _plain_folder(tmp_path: Path, n: int = 4) -> Path:
    folder = tmp_path / "plain"
    folder.mkdir()
    for f in sorted((SAMPLE / "velodyne").glob("*.bin"))[:n]:
        shutil.copy(f, folder / f.name)
    return folder


def test_a_link_to_nothing_among_the_scans_is_one_line_naming_it(tmp_path):
    folder = _plain_folder(tmp_path, 2)
    (folder / "000009.bin").symlink_to(tmp_path / "gone.bin")
    proc = lidar_slam("run", folder, "--out", tmp_path / "o", "--no-loops")
    assert_one_line_error(proc, f"{folder / '000009.bin'}: a link to {tmp_path / 'gone.bin'}, "
                                "which does not exist")


def test_scan_stamps_in_ns_are_converted_with_a_warning(tmp_path):
    data = sample_copy(tmp_path)
    t0 = 1_630_577_808_570_040_832
    (data / "times.txt").write_text("".join(f"{t0 + k * 200_000_000}\n" for k in range(4)))
    proc = lidar_slam("run", data, "--out", tmp_path / "o", *FEW)
    assert proc.returncode == 0, proc.stderr
    assert "stamps read as ns" in proc.stderr and "converted to s" in proc.stderr
    stamps = np.loadtxt(tmp_path / "o" / "poses_tum.txt")[:, 0]
    assert np.allclose(np.diff(stamps), 0.2, atol=1e-6) and abs(stamps[0] - t0 * 1e-9) < 1e-3
    # in ms, 5 Hz: 200 s apart read as s, which a survey's scans can be: said, not converted
    (data / "times.txt").write_text("".join(f"{k * 200}\n" for k in range(4)))
    proc = lidar_slam("run", data, "--out", tmp_path / "o2", *FEW)
    assert proc.returncode == 0, proc.stderr
    assert "scans 200 s apart (median): taken as seconds" in proc.stderr


def test_a_folder_with_scans_and_a_scans_subfolder_says_which_it_reads(tmp_path):
    folder = _plain_folder(tmp_path, 3)
    (folder / "scans").mkdir()
    for f in sorted((SAMPLE / "velodyne").glob("*.bin"))[:4]:
        shutil.copy(f, folder / "scans" / f.name)
    proc = lidar_slam("run", folder, "--out", tmp_path / "o", "--no-loops", "--n-scans", "5")
    assert proc.returncode == 0, proc.stderr
    assert "3 scans in the folder itself are read, not the 4 in its scans/" in proc.stderr
    assert "--n-scans 5 from --start 0: only 3 scans there" in proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["n_scans"] == 5 and summary["frames_requested"] == 3


@pytest.mark.parametrize("args,said", [
    # 1e-20 overflowed the voxel indices and kept 2214 of 99,659 points; inf kept one
    (("export", "RUN", "--out", "OUT/m.ply", "--voxel", "1e-20"),
     "--voxel must be a finite size of at least 0.001 m, got 1e-20"),
    (("export", "RUN", "--out", "OUT/m.ply", "--voxel", "inf"), "--voxel must be a finite"),
    # inf crashed ("internal error: cannot convert float NaN to integer")
    (("export", "RUN", "--occupancy", "--out", "OUT", "--resolution", "inf"),
     "--resolution must be a finite size"),
    (("export", "RUN", "--occupancy", "--out", "OUT", "--band", "0.3,inf"),
     "--band: need 0 <= LOW < HIGH, both finite"),
    (("localize", "RUN", "--map", "RUN", "--out", "OUT", "--initial-pose", "1,2,3,nan"),
     "--initial-pose: expected x,y,z,yaw, finite"),
])
def test_a_size_or_pose_that_is_not_finite_is_one_line(tmp_path, args, said):
    args = [str(a).replace("RUN", str(tmp_path / "run")).replace("OUT", str(tmp_path / "out"))
            for a in args]
    assert_one_line_error(lidar_slam(*args), said)
    assert not (tmp_path / "out").exists()


def test_simulate_gnss_without_pyproj_says_so_before_writing(tmp_path):
    """It stopped after the scans and the IMU were written, leaving a sequence without
    gnss.csv that `run` then ran without GNSS."""
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; sys.modules['pyproj'] = None; "
         "from lidar_slam.cli import app; app()", "simulate", "--motion", "handheld", "--world",
         "outdoor", "--duration-s", "2", "--imu", "--gnss", "--sensor", "vlp16", "--out",
         str(tmp_path / "sim")], capture_output=True, text=True, timeout=300)
    assert_one_line_error(proc, "GNSS needs pyproj: pip install 'lidar-slam[geo]'")
    assert not (tmp_path / "sim").exists()


def test_simulate_refusing_its_arguments_leaves_no_out_folder(tmp_path):
    poses = tmp_path / "poses.txt"
    poses.write_text("".join(f"1 0 0 {k} 0 1 0 0 0 0 1 0\n" for k in range(5)))
    calib = tmp_path / "calib.txt"
    calib.write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    proc = lidar_slam("simulate", poses, "--calib", calib, "--start", "99", "--out",
                      tmp_path / "sim")
    assert_one_line_error(proc, "--start 99 is past the last pose")
    assert not (tmp_path / "sim").exists()


@pytest.mark.parametrize("args,said", [
    (("export", "RUN", "--out", "OUT/m.ply", "--resolution", "0.2"),
     "--resolution: not used without --occupancy"),
    (("export", "RUN", "--occupancy", "--out", "OUT", "--voxel", "0.2"),
     "--voxel: not used with --occupancy"),
    (("optimize", "RUN/g.g2o", "--out", "OUT/o.g2o", "--huber-k", "2"),
     "--huber-k: not used without --robust huber"),
])
def test_an_option_that_does_nothing_here_is_said(tmp_path, args, said):
    args = [str(a).replace("RUN", str(tmp_path / "run")).replace("OUT", str(tmp_path))
            for a in args]
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "g.g2o").write_text("not a graph\n")
    proc = lidar_slam(*args)  # then refused: no run there, no graph in the file
    assert proc.returncode == 2 and f"WARNING lidar_slam: {said}" in proc.stderr, proc.stderr
