"""Odometry failure (lidar_slam.frontend.failure): scans spliced from another street are one
reported failure, kiss-icp's local map is cut back and its threshold restarted; a good run is
left alone."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from lidar_slam import pipeline
from lidar_slam.config import SlamConfig
from lidar_slam.io.sources import open_source
from lidar_slam.sim import SENSORS, simulate_sequence

SENSOR = dataclasses.replace(SENSORS["vlp16"], n_azimuth=600)
N = 24  # scans per street, 1 m apart
SPLICE = 12  # the first scan from the other street


@pytest.fixture(scope="module")
def streets(tmp_path_factory):
    """Two streets (world seeds 1 and 2) driven straight at 10 m/s."""
    t = np.arange(N) / 10.0
    poses = np.tile(np.eye(4), (N, 1, 1))
    poses[:, 0, 3] = np.arange(N, dtype=float)
    out = []
    for seed in (1, 2):
        d = tmp_path_factory.mktemp(f"street{seed}")
        simulate_sequence(poses, t, d, SENSOR, seed=seed, n_scans=N)
        out.append(d)
    return out


def run(scans) -> tuple[pipeline.RunResult, list[int], list[float]]:
    """The result, kiss-icp's map size and its threshold after each scan (no loops)."""
    cfg = SlamConfig()
    cfg = cfg.model_copy(update={"loop": cfg.loop.model_copy(update={"enabled": False})})
    pipe = pipeline.Pipeline(cfg, None)
    sizes, sigmas = [], []
    try:
        for scan in scans:
            pipe.process(scan)
            sizes.append(len(pipe.odometry._map._point_cloud()))
            sigmas.append(pipe.odometry._threshold._compute_threshold())
        return pipe.finish(), sizes, sigmas
    finally:
        pipe.close()


def test_scans_from_another_street_are_one_reported_failure_and_a_map_reset(streets, caplog):
    a, b = (list(open_source(s).scans(0, N)) for s in streets)
    good, _, _ = run(a)
    assert good.failure_resets == [] and good.failure_episodes == []

    with caplog.at_level(logging.WARNING):
        spliced, sizes, sigmas = run(a[:SPLICE] + b[SPLICE:])
    cfg = SlamConfig().odometry
    # found within failure_scans scans of the splice, reported once, reset once
    assert len(spliced.failure_resets) == 1 and spliced.failure_episodes == spliced.failure_resets
    at = spliced.failure_resets[0]
    assert SPLICE <= at < SPLICE + cfg.failure_scans + 1
    said = [r for r in caplog.records if r.name == "lidar_slam.frontend.failure"]
    assert len(said) == 1 and f"scan {at}: odometry failed" in said[0].getMessage()
    # bounded: the map is cut back to the last keyframes and this scan, the threshold restarts
    assert sizes[at] < 0.7 * sizes[at - 1]
    assert sigmas[at] == cfg.initial_threshold_m


def test_a_resumed_odometry_keeps_its_failures_and_its_restarted_threshold(streets):
    """The restart is in the deviations a checkpoint replays (lidar_slam.run.checkpoint)."""
    from lidar_slam.frontend.odometry import Odometry

    a, b = (list(open_source(s).scans(0, N)) for s in streets)
    cfg = SlamConfig()
    pipe = pipeline.Pipeline(cfg.model_copy(update={"loop": cfg.loop.model_copy(
        update={"enabled": False})}), None)
    try:
        for scan in a[:SPLICE] + b[SPLICE:SPLICE + 6]:
            pipe.process(scan)
        odo = pipe.odometry
        assert odo.failures.resets
        resumed = Odometry(pipe.cfg)
        resumed.restore(odo.state(), odo.take_deviations())
    finally:
        pipe.close()
    sigma = odo._threshold._compute_threshold()
    assert resumed._threshold._compute_threshold() == sigma
    assert resumed.failures.resets == odo.failures.resets
    assert resumed.failures.episodes == odo.failures.episodes
    assert resumed.failures.kernel(sigma, 2.0) == odo.failures.kernel(sigma, 2.0)


def test_the_odometry_edge_across_a_reset_is_as_unsure_as_the_threshold_was(streets):
    """Weights from the data: across a reset the odometry's motion is known no better than
    kiss-icp's threshold when it was reset, so that edge's covariance holds it (the keyframes
    after it were 224x overconfident on a failed walk of the bank); the other edges keep the
    registration's own information."""
    a, b = (list(open_source(s).scans(0, N)) for s in streets)
    good, _, _ = run(a)
    spliced, _, sigmas = run(a[:SPLICE] + b[SPLICE:])
    at = spliced.failure_resets[0]
    sigma_at_reset = sigmas[at - 1]  # the threshold the reset was decided with (then restarted)
    frames = [spliced.store.frame_index(k) for k in range(len(spliced.store))]
    across = next(k for k in range(1, len(frames)) if frames[k - 1] < at <= frames[k])
    cov = np.linalg.inv(spliced.odom_information[across])
    assert np.all(np.diag(cov)[3:] >= sigma_at_reset ** 2 * 0.99)
    assert np.diag(cov)[3:].max() < 2 * sigma_at_reset ** 2
    for k, info in spliced.odom_information.items():
        if frames[k] < at and k in good.odom_information:
            np.testing.assert_array_equal(info, good.odom_information[k])
        elif k != across:
            assert np.diag(np.linalg.inv(info))[3:].max() < sigma_at_reset ** 2 / 10
