"""Shared fixtures. Tests that read ../shared/data skip with a reason where it is absent, unless
LIDAR_SLAM_REQUIRE_SHARED=1 (set by .ci/run), where its absence is a failure."""

from __future__ import annotations

import os
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
