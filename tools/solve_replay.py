"""Replay the final solve with the IMU on the bank in seconds, not a bank run in an hour.

Usage: python tools/solve_replay.py capture --root /work/bank --out DIR [--only NAME,...]
       python tools/solve_replay.py replay DIR [--set backend.KEY=VALUE ...] [--only NAME,...]

capture runs lidar-slam (in this process, with each sequence's bank overlay: tools/bank.py)
on every built bank sequence and pickles the arguments of lidar_slam.backend.imu_gnss_solve.solve
(config, keyframe poses, edges, trajectory, IMU, fixes, edge information) to DIR/<name>.pkl.
replay re-runs only that solve on each capture, with config overrides, and prints per sequence
the keyframe ATE (m, rigid alignment) of the pose graph it starts from and of the solve, the mean
NEES of the solve's keyframe positions (tools/bank.py's position_nees, expected 3) and the
odometry variance factors (rotation, translation) it found; then the median and the worst.

Keyframe ATE is not the bank's frame ATE (no frames between keyframes, no front-end change):
use it to choose what to run on the whole bank, never as the bank's result. A capture holds
the code's own objects: capture again after changing the front-end or these classes.
"""

from __future__ import annotations

import argparse
import pickle
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: `tools` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools import bank, benchmark  # noqa: E402


def capture(root: Path, out: Path, only: set[str]) -> None:
    import typer

    from lidar_slam.backend import imu_gnss_solve
    from lidar_slam.cli import app

    command = typer.main.get_command(app)
    out.mkdir(parents=True, exist_ok=True)
    original = imu_gnss_solve.solve
    for spec in bank.BANK:
        seq = root / spec.name
        if not seq.is_dir() or (only and spec.name not in only):
            continue
        target = out / f"{spec.name}.pkl"

        def wrapped(*args, _target=target, **kwargs):
            _target.write_bytes(pickle.dumps((args, kwargs)))
            return original(*args, **kwargs)

        imu_gnss_solve.solve = wrapped
        cfg = bank.lidar_slam_config(spec, seq, out / "configs" / f"{spec.name}.yaml")
        with tempfile.TemporaryDirectory() as run:
            try:
                command(["run", str(seq), "--out", run, "--overwrite", "--config", str(cfg)],
                        standalone_mode=False)
            finally:
                imu_gnss_solve.solve = original
        print(f"{spec.name}: {'captured' if target.is_file() else 'no solve with the IMU'}",
              flush=True)


def _ate(est: np.ndarray, gt: np.ndarray) -> float:
    from lidar_slam.eval.metrics import umeyama_rigid

    T = umeyama_rigid(est[:, :3, 3], gt[:, :3, 3])
    err = est[:, :3, 3] @ T[:3, :3].T + T[:3, 3] - gt[:, :3, 3]
    return float(np.sqrt((err ** 2).sum(axis=1).mean()))


def _fields(model) -> dict:
    """A pydantic model's stored values, nested, of the fields its class has now: a config
    pickled by an older lidar_slam lacks the fields added since (validated again, they take
    their defaults) and may hold some removed since (left out)."""
    from pydantic import BaseModel

    names = type(model).model_fields
    return {k: _fields(v) if isinstance(v, BaseModel) else v
            for k, v in vars(model).items() if k in names}


def override(cfg, settings: list[str]):
    """cfg with SECTION.KEY=VALUE settings, each VALUE read as YAML (false, 0.5, null, [1, 2])
    and the whole validated again."""
    import yaml

    fields = _fields(cfg)
    for item in settings:
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        fields[section][name] = yaml.safe_load(value)
    return type(cfg).model_validate(fields)


def replay(captures: Path, settings: list[str], root: Path, only: set[str]) -> None:
    from lidar_slam.backend import imu_gnss_solve

    rows = []
    for path in sorted(captures.glob("*.pkl")):
        name = path.stem
        if only and name not in only:
            continue
        args, kwargs = pickle.loads(path.read_bytes())
        cfg, T_world_kf, tr = override(args[0], settings), args[1], args[3]
        keys = sorted(T_world_kf)
        seq = benchmark.load_sequence(str(root / name), 0, None, {})
        gt = benchmark.truth_at(seq, tr.kf_stamps_s[keys])
        result = imu_gnss_solve.solve(cfg, *args[1:], **kwargs)
        before = _ate(np.stack([T_world_kf[k] for k in keys]), gt)
        after = _ate(np.stack([result.kf_poses[k] for k in keys]), gt)
        factors = result.summary.get("imu", {}).get("odometry_variance_factor")
        covs = {i: result.covariances[k] for i, k in enumerate(keys) if k in result.covariances}
        # As the run's files: frame 0 at its stamp is the identity in both (the first node is
        # at the middle of its sweep: RunTrajectory)
        est = np.stack([result.kf_poses[k] for k in keys])
        k0 = keys[0]
        at_stamp = est[0] @ np.linalg.inv(tr.kf_odom[k0]) @ tr.kf_stamp_odom[k0]
        est[0] = at_stamp
        nees = bank.position_nees(np.linalg.inv(at_stamp) @ est, np.linalg.inv(gt[0]) @ gt, covs)
        nees_mean = float(nees.mean()) if len(nees) else float("nan")
        rows.append((name, before, after, nees_mean))
        print(f"{name:26s} graph {before:.4f} m  solve {after:.4f} m  NEES {nees_mean:6.2f}  "
              f"variance factors {factors}", flush=True)
    if rows:
        solved = [r[2] for r in rows]
        worst = max(rows, key=lambda r: r[2])
        print(f"{'median':26s} graph {statistics.median(r[1] for r in rows):.4f} m  solve "
              f"{statistics.median(solved):.4f} m; worst solve {worst[2]:.4f} m ({worst[0]})")
        inside = sum(1 <= r[3] <= 9 for r in rows)
        print(f"{'NEES':26s} median {statistics.median(r[3] for r in rows):.2f}; in 1..9 on "
              f"{inside} of {len(rows)}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture", help="run lidar-slam on the bank, keep the solve's inputs")
    c.add_argument("--root", type=Path, required=True)
    c.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("replay", help="re-run the solve on the captures with overrides")
    r.add_argument("captures", type=Path)
    r.add_argument("--root", type=Path, default=Path("/work/bank"),
                   help="the bank (for the truth)")
    r.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    for q in (c, r):
        q.add_argument("--only", default="", help="comma-separated sequence names")
    a = p.parse_args(argv)
    only = {s for s in a.only.split(",") if s}
    if a.cmd == "capture":
        capture(a.root, a.out, only)
    else:
        replay(a.captures, a.set, a.root, only)
    return 0


if __name__ == "__main__":
    sys.exit(main())
