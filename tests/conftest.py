"""Shared fixtures. Tests that read ../shared/data skip with a reason where it is absent, unless
LIDAR_SLAM_REQUIRE_SHARED=1 (set by .ci/run), where its absence is a failure.

The exception: the public sensor pcaps (`public_captures`, marker of the same name) are fetched
data that CI's ../shared does not hold (shared/data/pcaps/README.txt says where they come from):
their tests skip with a reason wherever the folder is absent, CI included. Point
LIDAR_SLAM_PCAPS at another folder of them (or LIDAR_SLAM_SHARED_DATA at a shared/data holding
pcaps/) to run them; CI tests the pcap readers on pcaps written at test time instead."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("LIDAR_SLAM_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_path(*parts: str) -> Path:
    """Path under ../shared/data; skip (or fail in CI) when it is missing."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        msg = f"shared data not found: {p} (clone ../shared beside the repo to run this test)"
        if os.environ.get("LIDAR_SLAM_REQUIRE_SHARED") == "1":
            pytest.fail(msg)
        pytest.skip(msg)
    return p


PUBLIC_PCAPS = Path(os.environ.get("LIDAR_SLAM_PCAPS", SHARED_DATA / "pcaps"))


@pytest.fixture
def public_captures() -> Path:
    """The folder of public sensor pcaps (LIDAR_SLAM_PCAPS, else ../shared/data/pcaps); the
    test skips when it is absent, even under LIDAR_SLAM_REQUIRE_SHARED=1 (see the docstring).
    Tests using it carry the `public_captures` marker (-m "not public_captures" leaves them)."""
    if not PUBLIC_PCAPS.is_dir():
        pytest.skip(f"public sensor pcaps not found: {PUBLIC_PCAPS} (fetched data, not in CI: "
                    "set LIDAR_SLAM_PCAPS to a copy; its README.txt names the sources)")
    return PUBLIC_PCAPS


@pytest.fixture
def kitti16() -> Path:
    return shared_path("kitti00_first16")


@pytest.fixture
def ouster_loop() -> Path:
    return shared_path("ouster_os0_loop_balm")


@pytest.fixture
def rosbags_dir() -> Path:
    return shared_path("rosbags")


@pytest.fixture
def posegraphs() -> Path:
    return shared_path("posegraphs")


@pytest.fixture
def kitti_gt() -> Path:
    return shared_path("kitti_gt")


@dataclass(frozen=True)
class SimMap:
    """A small simulated drive and a finished run on part of it, shared by the map tests:
    `seq` holds scans 0..SIM_SCANS-1 of simulated KITTI 07 (seed 0), `run` the map made by
    `lidar-slam run seq --n-scans MAP_SCANS` (default config)."""

    seq: Path
    run: Path
    run_summary: dict
    truth: object  # lidar_slam.sim.SimSummary


SIM_SCANS = 180
MAP_SCANS = 180


@pytest.fixture(scope="session")
def sim_map(tmp_path_factory) -> SimMap:
    """Simulate 07 frames 0..179 and map them once per test session."""
    from lidar_slam.sim import load_kitti_truth, simulate_sequence

    kt = load_kitti_truth(shared_path("kitti_gt"), 7)
    root = tmp_path_factory.mktemp("sim_map")
    truth = simulate_sequence(kt.poses_world_lidar, kt.stamps_s, root / "seq", start=0,
                              n_scans=SIM_SCANS, Tr_cam_lidar=kt.Tr_cam_lidar)
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(root / "seq"),
                           "--out", str(root / "run"), "--n-scans", str(MAP_SCANS)],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((root / "run" / "summary.json").read_text())
    return SimMap(root / "seq", root / "run", summary, truth)


@pytest.fixture(scope="session")
def handheld_walk(tmp_path_factory) -> Path:
    """20 s of `simulate --motion handheld --world indoor --seed 0 --imu` (200 OS1-64 scans)."""
    seq = tmp_path_factory.mktemp("handheld") / "seq"
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "simulate", "--motion",
                           "handheld", "--world", "indoor", "--seed", "0", "--duration-s", "20",
                           "--imu", "--out", str(seq)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    return seq


@pytest.fixture(scope="session")
def trot_end(tmp_path_factory) -> Path:
    """6 s of `simulate --motion legged --world office --sensor xt32 --stamp end --seed 112`
    (60 scans of bank office-legged-xt32's trot, stamps at sweep end, no IMU)."""
    seq = tmp_path_factory.mktemp("trot") / "seq"
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "simulate", "--motion",
                           "legged", "--world", "office", "--sensor", "xt32", "--stamp", "end",
                           "--seed", "112", "--duration-s", "6", "--out", str(seq)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return seq


def stop_pipeline_after(monkeypatch, n_scans: int):
    """Pipeline.process raises KeyboardInterrupt (as Ctrl-C) when handed the scan after the
    first n_scans; returns a function that puts the real one back."""
    from lidar_slam import pipeline

    process, seen = pipeline.Pipeline.process, []

    def stopped(self, scan):
        if len(seen) == n_scans:
            raise KeyboardInterrupt
        seen.append(scan.index)
        return process(self, scan)

    monkeypatch.setattr(pipeline.Pipeline, "process", stopped)
    return lambda: monkeypatch.setattr(pipeline.Pipeline, "process", process)


def require_ray() -> None:
    """Skip a test that needs Ray (the cluster extra) where it is not installed, unless
    LIDAR_SLAM_REQUIRE_RAY=1 (set by .ci/run, whose install includes the extra): then fail."""
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        msg = "Ray is not installed (pip install -e '.[cluster]')"
        if os.environ.get("LIDAR_SLAM_REQUIRE_RAY") == "1":
            pytest.fail(msg)
        pytest.skip(msg)


def assert_one_line_error(proc, *needles):
    """Exit code 2, no traceback, one error line (warnings about the input may come first)."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and not ln.startswith("WARNING")]
    assert len(lines) == 1, proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
