"""tools/outlier_benchmark.py and tools/loose_gates.py: wrong loops against the back-end."""

from __future__ import annotations

import csv
import importlib
import json
from pathlib import Path

import numpy as np
import yaml

from lidar_slam.geometry import inverse, make_pose, to_xyz_quat
from lidar_slam.io.g2o import read_g2o

REPO = Path(__file__).resolve().parents[1]


def load_tool(name: str):
    return importlib.import_module(f"tools.{name}")


def test_wrong_loops_are_random_non_neighbours_as_confident_as_the_median_loop(posegraphs):
    tool = load_tool("outlier_benchmark")
    g2o = read_g2o(posegraphs / "se-sync" / "smallGrid3D.g2o")
    lo, hi = np.zeros(3), np.full(3, 4.0)
    bad = tool.add_wrong_loops(g2o, 10, seed=3, extent_lo=lo, extent_hi=hi)
    again = tool.add_wrong_loops(g2o, 10, seed=3, extent_lo=lo, extent_hi=hi)
    wrong = bad.edges[len(g2o.edges):]
    assert len(wrong) == 10 and bad.edges[: len(g2o.edges)] == g2o.edges
    joined = {(min(e.i, e.j), max(e.i, e.j)) for e in g2o.edges}
    info = tool.median_loop_information(g2o)
    for e, f in zip(wrong, again.edges[len(g2o.edges):], strict=True):
        assert abs(e.i - e.j) > 1 and (min(e.i, e.j), max(e.i, e.j)) not in joined
        np.testing.assert_array_equal(e.information, info)
        np.testing.assert_array_equal(e.T_i_j, f.T_i_j)  # deterministic in the seed
        assert np.all(np.abs(e.T_i_j[:3, 3]) <= 4.0)
    loop_logdets = sorted(np.linalg.slogdet(e.information)[1] for e in g2o.edges
                          if abs(e.j - e.i) != 1)
    assert np.linalg.slogdet(info)[1] == loop_logdets[len(loop_logdets) // 2]


def test_outlier_benchmark_gnc_ignores_wrong_loops(posegraphs, tmp_path):
    """smallGrid3D with 10 wrong loops: plain LM is dragged metres away, GNC stays on the
    clean solution and rejects every wrong loop; the table and JSON are written."""
    tool = load_tool("outlier_benchmark")
    g2o = read_g2o(posegraphs / "se-sync" / "smallGrid3D.g2o")
    clean, rows = tool.run(g2o, [10], [0], ["none", "huber", "gnc"], "file")
    by = {r["robust"]: r for r in rows}
    assert clean["nodes"] == 125 and clean["loop_edges"] > 0
    assert by["none"]["rms_m"] > 0.3
    assert by["gnc"]["rms_m"] < 0.01 and by["gnc"]["wrong_rejected"] == 10
    assert by["gnc"]["true_rejected"] <= 3  # TLS at the 99 % gate may drop a true loop or two
    text = tool.table(rows, ["none", "huber", "gnc"])
    assert text.splitlines()[0].startswith("| k | none RMS m") and "| 10 |" in text


def _write_run(run: Path, loops: list[tuple[int, int, np.ndarray, str]], ate: float) -> None:
    run.mkdir(parents=True)
    header = ["query_frame", "match_frame", "descriptor_distance", "yaw_guess_deg", "fitness",
              "rmse_m", "accepted", "reason", "x", "y", "z", "qx", "qy", "qz", "qw", "backend"]
    with open(run / "loops.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for q, m, T, verdict in loops:
            w.writerow([q, m, 0.1, 0.0, 0.8, 0.1, 1, "", *to_xyz_quat(T), verdict])
        w.writerow([9, 1, 0.2, 0.0, 0.3, 0.2, 0, "fitness", *[np.nan] * 7, ""])
    (run / "summary.json").write_text(json.dumps({"ate_rmse_m": ate, "backend_s": 0.5,
                                                  "backend_share_pct": 1.0, "wall_s": 50.0}))


def test_loose_gates_scores_loops_against_the_truth(tmp_path):
    tool = load_tool("loose_gates")
    gt = np.stack([make_pose(np.eye(3), [float(k), 0.0, 0.0]) for k in range(200)])
    true_T = inverse(gt[10]) @ gt[150]
    loops = [(150, 10, true_T, "inlier"),                       # right
             (160, 20, make_pose(np.eye(3), [5.0, 0, 0]), "rejected"),   # wrong, rejected
             (170, 30, make_pose(np.eye(3), [9.0, 0, 0]), "inlier"),     # wrong, kept
             (180, 40, inverse(gt[40]) @ gt[180], "rejected")]  # right, rejected
    _write_run(tmp_path / "run", loops, ate=0.2)
    row = tool.score_run(tmp_path / "run", gt, start=0)
    assert (row["loops_accepted"], row["wrong_admitted"], row["wrong_rejected_by_backend"],
            row["true_rejected_by_backend"]) == (4, 2, 1, 1)
    assert row["ate_m"] == 0.2 and row["backend_share_pct"] == 1.0


def test_loose_gates_config_overlays_the_gates_and_the_kernel(tmp_path):
    tool = load_tool("loose_gates")
    path = tool.loose_config(REPO / "configs" / "sim_hdl64.yaml",
                             REPO / "configs" / "loose_gates.yaml", "gnc", tmp_path / "c.yaml")
    cfg = yaml.safe_load(path.read_text())
    assert cfg["backend"]["robust"] == "gnc"
    assert cfg["loop"]["verify"]["min_margin"] == 0.0
    assert cfg["loop"]["scan_context"]["sensor_height_m"] == 1.73  # from sim_hdl64.yaml
    assert cfg["loop"]["verify"]["min_fitness"] < 0.5
