"""tools/nees_spread.py: the mean NEES a run would show if its covariances were right."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidar_slam.run.outputs import read_covariances

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_scans"


def tool():
    return importlib.import_module("tools.nees_spread")


def test_independent_errors_give_a_mean_near_3_and_a_drift_a_wide_spread_around_it():
    """K independent keyframes: the mean of K chi-square(3) / 3 draws, tight about 3. One
    random walk through K keyframes: the same mean, but a run's mean NEES falls outside 1..9
    several times in a hundred (the bar fails by chance on a drift, consistent or not)."""
    K = 100
    P = [np.eye(3)] * K
    white = tool().spread(np.eye(3 * K), P, 4000)
    assert abs(white.mean() - 3.0) < 0.05 and np.percentile(white, 95) < 3.5
    steps = np.tril(np.ones((K, K)))  # x_k = sum of k steps, one per axis
    C = np.kron(steps @ steps.T, np.eye(3))
    walk = tool().spread(C, [C[3 * k:3 * k + 3, 3 * k:3 * k + 3] for k in range(K)], 4000)
    assert abs(walk.mean() - 3.0) < 0.15
    assert 0.02 < np.mean((walk < 1) | (walk > 9)) < 0.15


@pytest.mark.parametrize("n_scans,floor", [(40, False), (71, True)],
                         ids=["configured-floor", "refinement-floor"])
def test_a_lidar_only_runs_lidar_graph_gives_its_covariances_csv(tmp_path, n_scans, floor):
    """The joint covariance rebuilt from graph.g2o has covariances.csv's position blocks on
    its diagonal (the deskew's white term included) and a variance factor of 1 (no loops in
    40 scans; the loops of 71 close nothing the edges do not allow): with the configured
    rotation floor (40 scans, too few refined at speed) and with the floor and bias the
    refinement at speed measured (71: backend.refinement_floor)."""
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run", str(SAMPLE), "--out",
                           str(out), "--n-scans", str(n_scans)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["covariance_refinement_floor"] is not None) == floor
    C, P, factor = tool().joint_position_covariance(out)
    assert abs(factor - 1.0) < 1e-3
    covs = read_covariances(out / "covariances.csv")
    assert len(P) == len(covs) - 1
    for k, p in enumerate(P):
        np.testing.assert_allclose(C[3 * k:3 * k + 3, 3 * k:3 * k + 3], p, rtol=1e-6,
                                   atol=1e-12)
    assert tool().main([str(out)]) == 0
