"""What mean NEES a lidar-only run would show if its covariances were exactly right.

Usage: python tools/nees_spread.py RUN [RUN ...] [--bank-json FILE] [--draws 4000]
       python tools/nees_spread.py --captures DIR [--bank-json FILE] [--only NAME,...]

The bank's covariance bar is the mean, over one run's keyframes, of each keyframe position's
NEES e' P^-1 e (3 when consistent; issue 29 asks for 1..9 on every sequence). Consecutive
keyframes share one drift, so that mean is not the mean of K independent chi-square(3) draws:
it swings from run to run even when every covariance is right. This tool draws the errors a
consistent run would have, e ~ N(0, C) with C the joint covariance of all keyframe positions,
and prints the spread of their mean NEES (each against covariances.csv's marginal P, as the
bank scores it): its 5 / 50 / 95 % points and the chance it falls below 1 or above 9. With
--bank-json (a tools/bank.py run's JSON) it also prints where the run's own mean NEES lies in
that spread (its quantile: near 0 underconfident, near 1 overconfident).

C is built from the run's own lidar graph (graph.g2o: the odometry edges and the loops; the
loops the final solve rejected, loops.csv, left out; the kept ones with their Huber kernel at
the final poses; keyframe 0 anchored as the pipeline does), scaled by the run's a posteriori
variance factor and widened by each keyframe's deskew error as covariances.csv says (the
rotation blocks give the factor, each position block's excess is that keyframe's own
independent term). Where the run's covariances took the rotation floor and bias of its
refinement at speed (summary.json covariance_refinement_floor: backend.refinement_floor), so
does C: the measured odometry edges (those not at the configured sigmas) get that floor, and
the bias's sensitivity adds its joint part. For runs whose covariances came from the solve with
the IMU or GNSS the lidar graph is not what they are: such runs are refused. For them,
--captures takes the captures of tools/solve_replay.py (the solve's inputs, one per bank
sequence), solves each again with its joint covariance (imu_gnss_solve.solve(joint=True): every
keyframe pose relative to the first, as covariances.csv) and prints the same; the run's own
NEES is the bank JSON's first draw of `lidar-slam` (the captures are of that draw; the JSON's
commit is printed: one from before 832f4ec scored NEES against covariances that were not
relative to the first keyframe).

What the spread leaves out, so that it is if anything narrower than a consistent run's: the
a posteriori variance factor is taken as known (it is max(1, chi2 / dof) of the same residuals;
1.00 on every lidar-only bank row), and each keyframe's deskew term is drawn independently of
its neighbours' (one flick reaches the keyframes of three scans).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: `tools` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

def joint_position_covariance(run: Path) -> tuple[np.ndarray, list[np.ndarray], float]:
    """(C, P, factor): the joint covariance (3K x 3K, each keyframe's position in its own frame,
    keyframe 0 left out) a consistent run's errors follow, the marginal position blocks of
    covariances.csv (K of 3x3), and the variance factor found in its rotation blocks."""
    import gtsam

    from lidar_slam.backend.factors import BetweenFactor, PriorFactor
    from lidar_slam.backend.gtsam_graph import Problem
    from lidar_slam.config import load_config
    from lidar_slam.io.g2o import read_g2o
    from lidar_slam.map.keyframes import TABLE_DTYPE
    from lidar_slam.run.outputs import read_covariances

    cfg = load_config(run / "config.yaml")
    g = read_g2o(run / "graph.g2o")
    table = np.fromfile(run / "keyframes" / "table.bin", dtype=TABLE_DTYPE)
    kf_of_frame = {int(f): k for k, f in enumerate(table["frame_index"])}
    rejected = set()
    if (run / "loops.csv").is_file():
        for r in csv.DictReader(open(run / "loops.csv")):
            if r["accepted"] == "1" and r["backend"] == "rejected":
                rejected.add((kf_of_frame[int(r["match_frame"])],
                              kf_of_frame[int(r["query_frame"])]))
    edges = []
    for e in g.edges:
        loop = e.j != e.i + 1
        if loop and ((e.i, e.j) in rejected or (e.j, e.i) in rejected):
            continue
        huber = loop and cfg.backend.robust == "huber"
        edges.append(BetweenFactor(e.i, e.j, e.T_i_j, e.information,
                                   robust_k=cfg.backend.huber_k if huber else None, is_loop=loop))
    keys = sorted(g.poses)
    b = cfg.backend
    prior_info = np.diag([np.radians(b.prior_rot_sigma_deg) ** -2] * 3
                         + [b.prior_trans_sigma_m ** -2] * 3)
    priors = [PriorFactor(keys[0], g.poses[keys[0]], prior_info)]
    frames = [int(f) for f in table["frame_index"][:len(keys)]]
    summary = json.loads((run / "summary.json").read_text())
    taken = summary.get("covariance_refinement_floor")
    bias = np.zeros((6 * len(keys), 0))
    if taken:  # the covariances' graph: backend.refinement_floor's floor and bias
        from lidar_slam.backend.factors import sigmas_to_information
        from lidar_slam.backend.refinement_floor import (
            bias_sensitivity,
            edge_lengths,
            floored_edges,
        )

        # the measured edges: those not at the configured sigmas (an edge of configured sigmas
        # widened across an odometry failure is taken as measured here, not in the run)
        configured = sigmas_to_information(b.odom_rot_sigma_deg, b.odom_trans_sigma_m)
        measured = {e.j for e in edges if not e.is_loop
                    and not np.allclose(e.information, configured)}
        edges = floored_edges(edges, measured, np.radians(b.odom_information.min_rot_sigma_deg),
                              np.radians(taken["floor_deg"]))
        J = bias_sensitivity(priors, edges, dict(g.poses), edge_lengths(edges),
                             np.radians(np.asarray(taken["bias_sd_deg_per_m"])))
        bias = np.concatenate([J[k] for k in keys])  # (6K, 3): the bias's joint part
    graph = Problem(3, priors, edges).graph
    values = gtsam.Values()
    for k in keys:
        values.insert(k, gtsam.Pose3(g.poses[k]))
    order = gtsam.Ordering()
    for k in keys:
        order.push_back(k)
    H, _ = graph.linearize(values).hessian(order)
    S = np.linalg.inv(H)
    covs = read_covariances(run / "covariances.csv")
    B = bias @ bias.T
    ratios = [np.trace(covs[frames[i]][:3, :3] - B[6 * i:6 * i + 3, 6 * i:6 * i + 3])
              / np.trace(S[6 * i:6 * i + 3, 6 * i:6 * i + 3]) for i in range(1, len(keys))]
    factor = float(np.median(ratios))
    if max(ratios) > 1.01 * factor or min(ratios) < 0.99 * factor:
        raise ValueError(f"{run}: graph.g2o does not give covariances.csv's rotations "
                         f"(ratios {min(ratios):.3f}-{max(ratios):.3f})")
    idx = np.concatenate([np.arange(6 * i + 3, 6 * i + 6) for i in range(1, len(keys))])
    C = factor * S[np.ix_(idx, idx)] + B[np.ix_(idx, idx)]
    P = []
    for n, i in enumerate(range(1, len(keys))):
        block = slice(3 * n, 3 * n + 3)
        p = covs[frames[i]][3:, 3:]
        w, v = np.linalg.eigh(p - C[block, block])  # the keyframe's own term, kept PSD
        C[block, block] += (v * np.clip(w, 0.0, None)) @ v.T
        P.append(p)
    return C, P, factor


def spread(C: np.ndarray, P: list[np.ndarray], draws: int, seed: int = 0) -> np.ndarray:
    """Mean NEES of `draws` error vectors e ~ N(0, C), each keyframe's against its P."""
    rng = np.random.default_rng(seed)
    w, v = np.linalg.eigh(0.5 * (C + C.T))
    L = v * np.sqrt(np.clip(w, 0.0, None))
    e = (L @ rng.standard_normal((len(C), draws))).T.reshape(draws, -1, 3)
    Pinv = np.linalg.inv(np.asarray(P))
    return np.einsum("mki,kij,mkj->mk", e, Pinv, e).mean(axis=1)


def capture_covariance(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """(C, P) as joint_position_covariance gives them, from the solve with the IMU of one
    tools/solve_replay.py capture solved again with its joint covariance."""
    import pickle

    from lidar_slam.backend import imu_gnss_solve
    from tools import solve_replay

    args, kwargs = pickle.loads(path.read_bytes())
    cfg = solve_replay.override(args[0], [])
    result = imu_gnss_solve.solve(cfg, *args[1:], **kwargs, joint=True)
    keys = sorted(result.covariances)
    idx = np.concatenate([np.arange(6 * i + 3, 6 * i + 6) for i in range(1, len(keys))])
    C = result.joint_covariance[np.ix_(idx, idx)]
    return C, [result.covariances[k][3:, 3:] for k in keys[1:]]


def _row(label: str, n: np.ndarray, keyframes: int, factor: str, own: float | None) -> str:
    tail = f"{own:.2f} | {np.mean(n <= own):.3f}" if own is not None else "- | -"
    return (f"{label} | {keyframes} | {factor} | {np.percentile(n, 5):.2f} / {np.median(n):.2f}"
            f" / {np.percentile(n, 95):.2f} | {np.mean(n < 1):.3f} | {np.mean(n > 9):.3f} | "
            f"{tail}")


def observed(bank_json: dict, run: Path) -> float | None:
    """The run's own mean NEES from a tools/bank.py JSON (its sequence, system and draw: a
    run under perturb-N/ is the JSON's perturbed[N-1]); None where the JSON has no such cell."""
    system, name, parent = run.name, run.parent.name, run.parent.parent.name
    tail = parent.removeprefix("perturb-")
    draw = int(tail) if parent != tail and tail.isdigit() else 0
    cell = bank_json.get("results", {}).get(name, {}).get(system)
    if cell is None:
        return None
    if draw:
        perturbed = cell.get("perturbed") or []
        cell = perturbed[draw - 1] if draw <= len(perturbed) and perturbed[draw - 1] else {}
    return cell.get("nees_mean")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--bank-json", type=Path)
    ap.add_argument("--draws", type=int, default=4000)
    ap.add_argument("--captures", type=Path, help="tools/solve_replay.py captures (with IMU)")
    ap.add_argument("--only", default="", help="with --captures: these sequences (a,b,...)")
    args = ap.parse_args(argv)
    bank_json = json.loads(args.bank_json.read_text()) if args.bank_json else {}
    if bank_json:
        print(f"the runs' own NEES: {args.bank_json} (commit {bank_json.get('commit', '?')})")
    print("run | keyframes | variance factor | mean NEES if consistent: 5 / 50 / 95 % | "
          "P(< 1) | P(> 9) | the run's | its quantile")
    only = {n for n in args.only.split(",") if n}
    for path in sorted(args.captures.glob("*.pkl")) if args.captures else []:
        if only and path.stem not in only:
            continue
        C, P = capture_covariance(path)
        cell = bank_json.get("results", {}).get(path.stem, {}).get("lidar-slam", {})
        print(_row(path.stem, spread(C, P, args.draws), len(P), "-", cell.get("nees_mean")),
              flush=True)
    for run in args.runs:
        summary = json.loads((run / "summary.json").read_text())
        if summary.get("imu", {}).get("factors") or summary.get("gnss", {}).get("used"):
            print(f"{run}: covariances from the solve with the IMU / GNSS, not its lidar "
                  "graph: skipped")
            continue
        try:
            C, P, factor = joint_position_covariance(run)
        except (ValueError, FileNotFoundError) as exc:
            print(f"{run}: {exc}")
            continue
        print(_row(str(run), spread(C, P, args.draws), len(P), f"{factor:.2f}",
                   observed(bank_json, run)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
