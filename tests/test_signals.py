"""Signals and process death (issue 23): `timeout`, docker stop and Ctrl-C signal a command's
whole process group; the run must stop after the scan in hand, write every output and exit 130,
and no process of it may outlive it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from lidar_slam.io.trajectory import read_kitti_poses

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_scans"
OUTPUTS = ("poses_kitti.txt", "poses_tum.txt", "odometry_kitti.txt", "map.ply", "loops.csv",
           "graph.g2o", "config.yaml", "summary.json")


def _start(args: list, **kwargs) -> subprocess.Popen:
    """A command in a session (process group) of its own, as a shell would start it."""
    return subprocess.Popen([*map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, **kwargs)


def _run_cmd(data: Path, out: Path) -> list:
    return [sys.executable, "-m", "lidar_slam.cli", "run", data, "--out", out]


def _wait_for_lines(proc: subprocess.Popen, path: Path, lines: int, timeout_s: float = 120):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        if path.is_file() and len(path.read_text().splitlines()) >= lines:
            return
        time.sleep(0.02)


def _wait_for_worker(proc: subprocess.Popen, timeout_s: float = 120) -> psutil.Process | None:
    """The loop-worker process of a running `lidar-slam run` (a python child), once it exists."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        for child in psutil.Process(proc.pid).children(recursive=True):
            try:
                if "multiprocessing" in " ".join(child.cmdline()) and \
                        "resource_tracker" not in " ".join(child.cmdline()):
                    return child
            except psutil.Error:
                pass
        time.sleep(0.02)
    return None


def _group_alive(pgid: int, within_s: float = 10.0) -> list[int]:
    """Processes of the group still alive after within_s (multiprocessing's resource tracker
    ends on its own once the run's process has closed its pipe)."""
    deadline = time.monotonic() + within_s
    while True:
        alive = _group_members(pgid)
        if not alive or time.monotonic() > deadline:
            return alive
        time.sleep(0.1)


def _group_members(pgid: int) -> list[int]:
    alive = []
    for p in psutil.process_iter(["pid"]):
        try:
            if os.getpgid(p.pid) == pgid and p.status() != psutil.STATUS_ZOMBIE:
                alive.append(p.pid)
        except (OSError, psutil.Error):
            pass
    return alive


def assert_complete_interrupted_run(out: Path, proc: subprocess.Popen, err: str,
                                    sig: signal.Signals) -> None:
    """Exit 130, no traceback, every output present and consistent with summary.json, which
    names the signal."""
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "BrokenProcessPool" not in err, err
    assert err.strip().splitlines()[-1].startswith("lidar-slam: error: interrupted;"), err
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True
    assert summary["stopped"] == f"interrupted ({sig.name})"
    assert summary["frames_requested"] == 71
    frames = summary["frames"]
    assert 1 <= frames < 71
    assert len(read_kitti_poses(out / "poses_kitti.txt")) == frames
    assert len(read_kitti_poses(out / "odometry_kitti.txt")) == frames
    assert len((out / "poses_tum.txt").read_text().splitlines()) == frames
    header = (out / "map.ply").read_bytes()[:400].decode("latin-1")
    assert "end_header" in header and "element vertex 0\n" not in header
    assert (out / "loops.csv").read_text().startswith("query")
    assert "VERTEX_SE3:QUAT" in (out / "graph.g2o").read_text()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_to_the_process_group_keeps_every_output(tmp_path, sig):
    """`timeout -s TERM`, docker stop, Ctrl-C: the signal reaches the loop worker too, which
    used to die of SIGTERM (BrokenProcessPool traceback, exit 1, no poses_kitti.txt)."""
    out = tmp_path / "o"
    proc = _start(_run_cmd(SAMPLE, out))
    _wait_for_lines(proc, out / "odometry_kitti.txt", 2)
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=120)
    assert_complete_interrupted_run(out, proc, err, sig)
    assert _group_alive(proc.pid) == []


def test_timeout_command_keeps_every_output(tmp_path):
    """The real `timeout` (GNU coreutils): when it fires it signals its whole process group.
    Sending TERM to `timeout` itself takes the same path without racing the run's length."""
    out = tmp_path / "o"
    proc = _start(["timeout", "-s", "TERM", "600", *_run_cmd(SAMPLE, out)])
    _wait_for_lines(proc, out / "odometry_kitti.txt", 2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert_complete_interrupted_run(out, proc, err, signal.SIGTERM)


def test_the_loop_worker_dies_with_a_killed_run(tmp_path):
    """SIGKILL to the run's process alone (no handler runs): its loop-worker process must not
    outlive it (it used to, for minutes, after a test suite had ended)."""
    out = tmp_path / "o"
    proc = _start(_run_cmd(SAMPLE, out))
    worker = _wait_for_worker(proc)
    assert worker is not None, "no loop-worker process seen"
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    gone, alive = psutil.wait_procs([worker], timeout=10)
    assert not alive, f"loop worker {worker.pid} still alive after its run was killed"
    assert [p.pid for p in gone] == [worker.pid]


def test_a_bug_is_one_line_with_the_traceback_in_a_file(monkeypatch, capsys):
    """An unexpected exception (a bug, not bad input) is one line naming it and a file with the
    traceback, exit 1; it used to be two tracebacks (typer 0.2x has no click.Abort), hiding the
    cause."""
    import lidar_slam.eval.evaluate
    from lidar_slam.cli import app

    def broken(*args, **kwargs):
        raise RuntimeError("boom in run_eval")

    monkeypatch.setattr(lidar_slam.eval.evaluate, "run_eval", broken)
    with pytest.raises(SystemExit) as exit_info:
        app(args=["eval", "est.txt", "gt.txt"])
    assert exit_info.value.code == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("lidar-slam: error: internal error: RuntimeError: boom in run_eval")
    path = Path(lines[0].split("traceback in ")[1].rstrip(")"))
    try:
        assert "boom in run_eval" in path.read_text() and "Traceback" in path.read_text()
    finally:
        path.unlink()
