"""Checkpoints: a damaged one is refused with one line, never resumed into a wrong result."""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, stop_pipeline_after

from lidar_slam.config import load_config
from lidar_slam.io.trajectory import read_kitti_poses

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_scans"


def lidar_slam(*args, timeout=300):
    """The CLI in a process group of its own, output through files, and whatever it leaves
    running afterwards (a loop worker of a crashed run) killed: a test never hangs on it."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                                stdout=out, stderr=err, text=True, start_new_session=True)
        try:
            proc.wait(timeout=timeout)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
        out.seek(0)
        err.seek(0)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out.read(), err.read())


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """sample_scans run to the end with a checkpoint every 5 keyframes: its last checkpoint (50
    of 51 keyframes) stays in the folder, so --resume continues from there."""
    root = tmp_path_factory.mktemp("ckpt")
    cfg = root / "ck.yaml"
    cfg.write_text("checkpoint:\n  every_keyframes: 5\nodometry:\n  max_num_threads: 1\n")
    proc = lidar_slam("run", SAMPLE, "--out", root / "run", "--config", cfg)
    assert proc.returncode == 0, proc.stderr
    return root / "run", cfg


def _copy(finished, tmp_path) -> Path:
    run = tmp_path / "run"
    shutil.copytree(finished[0], run)
    return run


def _state(run: Path) -> Path:
    return next((run / "checkpoint").glob("state*.npz"))


def _truncate(path: Path) -> None:
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size // 2)


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x10
    path.write_bytes(bytes(data))


def test_an_intact_checkpoint_resumes_and_bytes_past_it_do_not_matter(finished, tmp_path):
    """A run killed after its checkpoint has appended more (here: garbage, as a kill in the
    middle of a write leaves) to the files the checkpoint covers a prefix of; the resume cuts
    them back and ends with the poses of the uninterrupted run."""
    run = _copy(finished, tmp_path)
    for name in ("checkpoint/deviations.bin", "keyframes/points.bin"):
        with open(run / name, "ab") as fh:
            fh.write(b"\x07" * 100)
    proc = lidar_slam("run", SAMPLE, "--out", run, "--config", finished[1], "--resume")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((run / "summary.json").read_text())["resumed_at_frame"] > 0
    np.testing.assert_allclose(read_kitti_poses(run / "poses_kitti.txt"),
                               read_kitti_poses(finished[0] / "poses_kitti.txt"), atol=1e-6)


DAMAGE = {
    "deviations.bin truncated": (lambda run: _truncate(run / "checkpoint/deviations.bin"),
                                 ("deviations.bin", "truncated")),
    "state truncated": (lambda run: _truncate(_state(run)), ("state", "truncated")),
    "run.json flipped": (lambda run: _flip(run / "checkpoint/run.json"),
                         ("run.json", "damaged")),
    "state flipped": (lambda run: _flip(_state(run)), ("state", "damaged")),
    "deviations.bin flipped": (lambda run: _flip(run / "checkpoint/deviations.bin"),
                               ("deviations.bin", "damaged")),
    "table.bin flipped": (lambda run: _flip(run / "keyframes/table.bin"),
                          ("table.bin", "damaged")),
    "points.bin flipped": (lambda run: _flip(run / "keyframes/points.bin"),
                           ("points.bin", "damaged")),
    "manifest flipped": (lambda run: _flip(run / "checkpoint/manifest.json"),
                         ("manifest.json", "damaged")),
    "manifest deleted": (lambda run: (run / "checkpoint/manifest.json").unlink(),
                         ("manifest.json", "missing")),
    "state deleted": (lambda run: _state(run).unlink(), ("state", "missing")),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_checkpoint_is_refused_with_one_line(finished, tmp_path, damage):
    """Every file the checkpoint depends on is checked against the manifest's sha256 and
    length before anything is resumed: a damaged, truncated or missing one (or manifest) stops
    the resume with one line that names it and says to start again with --overwrite."""
    run = _copy(finished, tmp_path)
    spoil, needles = DAMAGE[damage]
    spoil(run)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    proc = lidar_slam("run", SAMPLE, "--out", run, "--config", finished[1], "--resume")
    assert_one_line_error(proc, *needles, "cannot resume", "--overwrite")
    # refused before anything was touched: the evidence stays as it was
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before


@pytest.mark.slow
def test_a_run_killed_anywhere_ten_times_ends_as_if_never_killed(tmp_path):
    """tools/kill_anywhere.py: sample_scans SIGKILLed at 10 seeded points spread over the run
    (start-up, restore, frames, checkpoint writes, final outputs) and resumed each time ends
    with every pose within 1e-6 m of the uninterrupted run and the same loops; no process of
    the runs is left."""
    import psutil

    proc = subprocess.run([sys.executable, str(REPO / "tools" / "kill_anywhere.py"), "--out",
                           str(tmp_path), "--kills", "10", "--seed", "0"],
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((tmp_path / "kill_anywhere.json").read_text())
    assert report["ok"] and len(report["kills"]) == 10
    assert all(r["max_position_diff_m"] <= 1e-6 and r["same_loops"] and r["loops_accepted"][0]
               >= 3 for r in report["runs"])
    left = [p.pid for p in psutil.process_iter(["cmdline"])
            if any(str(tmp_path) in a for a in p.info["cmdline"] or ())]
    assert not left


def test_a_run_stopped_by_a_signal_resumes_from_where_it_stopped(tmp_path, monkeypatch):
    """Ctrl-C (or a bad scan) writes a checkpoint of every frame so far, not only the periodic
    one (every 100 keyframes): --resume goes on from that frame and ends with the bytes of the
    run never stopped (poses, odometry, loops, covariances)."""
    from lidar_slam.run import run_sequence

    files = ("poses_kitti.txt", "odometry_kitti.txt", "loops.csv", "covariances.csv")
    whole = run_sequence(SAMPLE, tmp_path / "whole", progress=False)
    assert whole.failure is None
    resume = stop_pipeline_after(monkeypatch, 30)
    first = run_sequence(SAMPLE, tmp_path / "run", progress=False)
    assert first.failure is not None and first.failure.exit_code == 130
    resume()
    resumed = run_sequence(SAMPLE, tmp_path / "run", resume=True, progress=False)
    assert resumed.failure is None and resumed.summary["resumed_at_frame"] == 30
    for name in files:
        assert (tmp_path / "run" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()


def test_a_run_killed_while_its_pipeline_starts_is_one_resume_knows(tmp_path, monkeypatch):
    """What the run is (checkpoint/run.json) is written before any other file of it: a run
    killed while its pipeline starts (a batch's worker stopped by Ray: the keyframe folder made,
    no checkpoint yet) is one --resume starts over, not a folder of someone's files it refuses
    (tests/test_batch.py's signal test met that under load)."""
    from lidar_slam import pipeline
    from lidar_slam.run import run_sequence

    init, out = pipeline.Pipeline.__init__, tmp_path / "run"

    def killed_after_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        assert (out / "checkpoint" / "run.json").is_file()
        raise KeyboardInterrupt  # as if killed here: nothing of the run's own handling runs

    monkeypatch.setattr(pipeline.Pipeline, "__init__", killed_after_init)
    with pytest.raises(KeyboardInterrupt):
        run_sequence(SAMPLE, out, progress=False, n_scans=10)
    assert any(out.iterdir())
    monkeypatch.setattr(pipeline.Pipeline, "__init__", init)
    resumed = run_sequence(SAMPLE, out, resume=True, progress=False, n_scans=10)
    assert resumed.failure is None and resumed.summary["resumed_at_frame"] == 0


def _stopped_run_checkpoint_without(tmp_path, monkeypatch, drop) -> tuple[Path, object]:
    """The sample stopped after 30 scans, its checkpoint's state rewritten without the arrays
    drop(name) picks (as an older lidar-slam wrote it, the manifest vouching for it); returns
    the run folder and the function that puts the real Pipeline.process back."""
    import io

    from lidar_slam.run import checkpoint, run_sequence

    resume = stop_pipeline_after(monkeypatch, 30)
    out = tmp_path / "run"
    assert run_sequence(SAMPLE, out, progress=False).failure.exit_code == 130
    d = out / "checkpoint"
    manifest = checkpoint._read_manifest(d)
    with np.load(d / manifest["state"]) as z:
        old = {k: z[k] for k in z.files if not drop(k)}
        assert len(old) < len(z.files)
    buf = io.BytesIO()
    np.savez(buf, **old)
    (d / manifest["state"]).write_bytes(buf.getvalue())
    manifest["files"][f"checkpoint/{manifest['state']}"] = checkpoint._whole_entry(buf.getvalue())
    checkpoint._write_manifest(d, {k: v for k, v in manifest.items()
                                   if k not in ("version", "sha256")})
    return out, resume


def test_a_checkpoint_without_the_odometrys_keyframe_copies_resumes(tmp_path, monkeypatch):
    """A checkpoint made before the odometry's keyframe copies were kept (before 393c040: the
    sample's sweep-start keyframes then at their stamps) resumes with the store's clouds as the
    copies, and the run ends (its keyframe nodes after it at mid-sweep, each with its own
    node_dt_s)."""
    from lidar_slam.run import run_sequence
    from lidar_slam.run.outputs import read_node_dt

    out, resume = _stopped_run_checkpoint_without(tmp_path, monkeypatch,
                                                  lambda k: k.startswith("anchor_"))
    resume()
    resumed = run_sequence(SAMPLE, out, resume=True, progress=False)
    assert resumed.failure is None and resumed.summary["resumed_at_frame"] == 30
    assert len(read_node_dt(out / "covariances.csv")) == resumed.summary["keyframes"]


def test_a_lidar_only_checkpoint_from_before_mid_sweep_keyframes_is_refused(tmp_path,
                                                                            monkeypatch):
    """A checkpoint without the unsettled frame (made before 8d17648, when a sweep-end scan's
    keyframe was kept at its stamp) of a run without an IMU is refused with one line, not
    continued into a store mixing the two conventions."""
    from lidar_slam import pipeline
    from lidar_slam.errors import InputError
    from lidar_slam.run import checkpoint

    out, resume = _stopped_run_checkpoint_without(tmp_path, monkeypatch,
                                                  lambda k: k == "unsettled")
    resume()
    with pytest.raises(InputError, match="older lidar-slam.*--overwrite"):
        checkpoint.restore(out, pipeline.Pipeline(load_config(), out, resume=True))
