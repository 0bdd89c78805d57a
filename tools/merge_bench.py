"""`lidar-slam merge` on simulated sessions, scored against their truth.

    python tools/merge_bench.py --root DIR [--sessions 3] [--motion handheld] [--world indoor]
                                [--duration-s 30] [--seed 1] [--changes 10] [--movers 2]
                                [--imu] [--gnss] [--reference I] [--json FILE]

Simulates DIR/sim (`simulate --sessions`), runs each session (`run`, DIR/runs/<i>, with the
overlay `simulate` wrote beside it, lidar_slam.yaml, when there is one) and merges
them (`merge`, DIR/merged), each step skipped when its folder is already there, then prints:

- keyframe error: every merged keyframe's position against its truth (truth_world.txt at the
  keyframe's frame) after ONE rigid alignment of the whole merged map to the truth (m: mean,
  95th percentile, max; target max <= 0.10 m);
- overlap linked: of the keyframes that truly overlap another session (a keyframe of it within
  OVERLAP_M, truth), the share that take part in a loop to that session kept by the solve
  (target >= 95 %);
- wrong loops: loops kept by the solve whose measured relative pose (loops.csv) is off the
  truth's by more than WRONG_M or WRONG_DEG (target 0);
- changes, by object (targets >= 0.9): an object of changes.csv is right when its centre (moved
  into the world by the same alignment) lies within CHANGE_M of the footprint of a changed
  object of changes.json (a disappeared one where the object was before its change, an appeared
  one where it is after); precision: right objects / objects found; recall: changes with at
  least one right object / changes;
- moving things (sessions simulated with --movers): points of the keyframe clouds inside a
  mover's box (movers.csv at the keyframe's scan, MOVER_M larger, from 0.1 m above its floor;
  clouds placed by the truth), in the runs' keyframes and in the merged map's (target 0);
- on the Earth (--gnss: session 0 runs with its GNSS, the others without): every frame of every
  session through the merged map's geo-reference against the truth in the simulator's ENU, no
  alignment (RMS and max per session).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: `tools` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lidar_slam.eval.metrics import umeyama_rigid
from lidar_slam.geometry import inverse, rotation_angle_deg
from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.map.saved import open_map

OVERLAP_M = 2.0
WRONG_M = 0.5
WRONG_DEG = 3.0
CHANGE_M = 0.5
MOVER_M = 0.3
TRUTH = "truth_world.txt"


def _overlay(seq: Path) -> tuple:
    """--config SEQ/lidar_slam.yaml, the overlay simulate writes with an IMU or GNSS (the IMU's
    mounting and clock as simulated), when there is one."""
    overlay = seq / "lidar_slam.yaml"
    return ("--config", overlay) if overlay.is_file() else ()


def _cli(*args) -> None:
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"lidar-slam {' '.join(map(str, args))} failed: {proc.stderr[-2000:]}")


def evaluate(sim: Path, merged: Path) -> dict:
    """The three scores of a merged map (see the module doc) against sim's truth."""
    with open(merged / "sessions" / "keyframes.csv") as fh:
        rows = [(int(r["session"]), int(r["session_keyframe"]), int(r["frame"]))
                for r in csv.DictReader(fh)]
    truth = {}
    saved = open_map(merged)
    est = saved.T_map_kf.copy()
    saved.close()
    gt = np.stack([_truth(truth, sim, s, f) for s, _, f in rows])
    T = umeyama_rigid(est[:, :3, 3], gt[:, :3, 3])
    err = np.linalg.norm(est[:, :3, 3] @ T[:3, :3].T + T[:3, 3] - gt[:, :3, 3], axis=1)
    where = {(s, k): i for i, (s, k, _) in enumerate(rows)}
    linked, wrong, kept = set(), [], 0
    with open(merged / "loops.csv") as fh:
        for r in csv.DictReader(fh):
            if r["kept"] != "1":
                continue
            kept += 1
            a, b = (int(r["session_a"]), int(r["keyframe_a"])), (int(r["session_b"]),
                                                                 int(r["keyframe_b"]))
            ia, ib = where[a], where[b]
            linked |= {(a, b[0]), (b, a[0])}
            T_ab = np.eye(4)
            T_ab[:3] = np.array(r["T_a_b"].split(), dtype=float).reshape(3, 4)
            d = inverse(inverse(gt[ia]) @ gt[ib]) @ T_ab
            if np.linalg.norm(d[:3, 3]) > WRONG_M or rotation_angle_deg(d) > WRONG_DEG:
                wrong.append((a, b, float(np.linalg.norm(d[:3, 3])),
                              float(rotation_angle_deg(d))))
    sessions = sorted({s for s, _, _ in rows})
    overlapping = []
    for i, (s, k, _) in enumerate(rows):
        for o in sessions:
            if o == s:
                continue
            other = [j for j, r in enumerate(rows) if r[0] == o]
            if np.linalg.norm(gt[other, :3, 3] - gt[i, :3, 3], axis=1).min() < OVERLAP_M:
                overlapping.append(((s, k), o))
    n_linked = sum(1 for kf, o in overlapping if (kf, o) in linked)
    left_out = [json.loads(p.read_text()) for p in sorted((merged / "sessions").glob(
        "*/summary.json"))]
    change_scores = _changes(sim, merged, T) if (merged / "changes.csv").is_file() else {}
    if (sim / "session_0" / "movers.csv").is_file():
        change_scores.update(_movers(sim, merged, rows, gt))
    if (sim / "session_0" / "gnss_truth.csv").is_file():
        change_scores.update(_earth(sim, merged, sessions))
    return {"keyframes": len(rows), "sessions_kept": len(sessions),
            "sessions_left_out": [d["run"] for d in left_out if not d["kept"]],
            "keyframe_error_mean_m": float(err.mean()),
            "keyframe_error_p95_m": float(np.percentile(err, 95)),
            "keyframe_error_max_m": float(err.max()),
            "overlapping_keyframes": len(overlapping), "overlapping_linked": n_linked,
            "overlap_linked_pct": 100.0 * n_linked / max(len(overlapping), 1),
            "loops_kept": kept, "wrong_loops": len(wrong), **change_scores,
            "wrong": wrong[:10]}


def _changes(sim: Path, merged: Path, T_world_merged: np.ndarray) -> dict:
    from lidar_slam.sim.sessions import read_changes

    truth = read_changes(sim / "changes.json")
    with open(merged / "changes.csv") as fh:
        found = [(np.array([float(r["x"]), float(r["y"]), float(r["z"])]),
                  r["change"] == "appeared") for r in csv.DictReader(fh)]
    right, hit = set(), 0
    for change in truth:
        got = False
        for box, appeared in ((change.before, False), (change.after, True)):
            if box is None:
                continue
            reach = np.hypot(box.length, box.width) / 2 + CHANGE_M
            for j, (centre, kind) in enumerate(found):
                c = T_world_merged[:3, :3] @ centre + T_world_merged[:3, 3]
                if kind == appeared and np.hypot(c[0] - box.x, c[1] - box.y) < reach:
                    got = True
                    right.add(j)
        hit += got
    return {"changes_true": len(truth), "change_objects_found": len(found),
            "change_precision": len(right) / max(len(found), 1),
            "change_recall": hit / max(len(truth), 1)}


def _mover_points(points_kf: np.ndarray, T_world_kf: np.ndarray, boxes: np.ndarray) -> int:
    """How many of a keyframe's points (its frame) lie in one of the boxes (movers.csv rows)."""
    w = points_kf @ T_world_kf[:3, :3].T + T_world_kf[:3, 3]
    inside = np.zeros(len(w), dtype=bool)
    for b in np.atleast_1d(boxes):
        c, s = np.cos(b["yaw"]), np.sin(b["yaw"])
        rx, ry = w[:, 0] - b["x"], w[:, 1] - b["y"]
        inside |= ((np.abs(c * rx + s * ry) < b["length"] / 2 + MOVER_M)
                   & (np.abs(-s * rx + c * ry) < b["width"] / 2 + MOVER_M)
                   & (w[:, 2] > b["z0"] + 0.1) & (w[:, 2] < b["z1"] + MOVER_M))
    return int(inside.sum())


def _movers(sim: Path, merged: Path, rows: list, gt: np.ndarray) -> dict:
    """Points of moving things in the runs' keyframe clouds and in the merged map's."""
    from lidar_slam.sim.movers import read_movers

    runs = json.loads((merged / "summary.json").read_text())["merged_from"]
    movers = {s: read_movers(sim / f"session_{s}" / "movers.csv") for s in {r[0] for r in rows}}
    before = after = total_after = 0
    saved = open_map(merged)
    own = {s: open_map(Path(runs[s])) for s in movers}
    try:
        for i, (s, k, f) in enumerate(rows):
            boxes = movers[s][movers[s]["scan"] == f]
            after += _mover_points(saved.keyframe(i).points.astype(float), gt[i], boxes)
            before += _mover_points(own[s].keyframe(k).points.astype(float), gt[i], boxes)
            total_after += len(saved.keyframe(i).points)
    finally:
        saved.close()
        for m in own.values():
            m.close()
    return {"mover_points_in_runs": before, "mover_points_in_merged": after,
            "merged_map_points": total_after}


def _earth(sim: Path, merged: Path, sessions: list[int]) -> dict:
    """Every frame of every kept session placed on the Earth by the merged map's geo-reference
    (summary.json), against its truth in the simulator's ENU frame: no alignment at all."""
    from lidar_slam.geo import GeoReference
    from tools.gnss_check import sim_datum

    summary = json.loads((merged / "summary.json").read_text())
    if "geo" not in summary:
        return {"geo": None}
    geo = GeoReference.from_dict(summary["geo"])
    datum = sim_datum(sim / "session_0")
    out = {"geo_from_session": summary.get("geo_from_session")}
    for s in sessions:
        est = read_kitti_poses(merged / "sessions" / str(s) / "poses_kitti.txt")[:, :3, 3]
        truth = read_kitti_poses(sim / f"session_{s}" / TRUTH)[:, :3, 3]
        err = np.linalg.norm(datum.from_wgs84(geo.map_to_wgs84(est)) - truth, axis=1)
        out[f"earth_rmse_m_session{s}"] = float(np.sqrt((err ** 2).mean()))
        out[f"earth_max_m_session{s}"] = float(err.max())
    return out


def _truth(cache: dict, sim: Path, session: int, frame: int) -> np.ndarray:
    if session not in cache:
        cache[session] = read_kitti_poses(sim / f"session_{session}" / TRUTH)
    return cache[session][frame]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--sessions", type=int, default=3)
    ap.add_argument("--motion", default="handheld")
    ap.add_argument("--world", default=None)
    ap.add_argument("--duration-s", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--changes", type=int, default=10)
    ap.add_argument("--imu", action="store_true", help="simulate an IMU too (runs use it)")
    ap.add_argument("--movers", type=int, default=2, help="things moving in each session")
    ap.add_argument("--gnss", action="store_true",
                    help="simulate GNSS; session 0's run uses it, the others run --no-gnss")
    ap.add_argument("--reference", type=int, default=0, help="merge --reference")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    sim, runs, merged = args.root / "sim", args.root / "runs", args.root / "merged"
    t0 = time.perf_counter()
    if not (sim / "changes.json").is_file():
        _cli("simulate", "--motion", args.motion, "--sessions", args.sessions, "--seed",
             args.seed, "--duration-s", args.duration_s, "--changes", args.changes, "--out", sim,
             "--overwrite", "--movers", args.movers, *(("--gnss",) if args.gnss else ()),
             *(("--world", args.world) if args.world else ()),
             *(("--imu",) if args.imu else ()))
    for i in range(args.sessions):
        if not (runs / str(i) / "summary.json").is_file():
            _cli("run", sim / f"session_{i}", "--out", runs / str(i), "--overwrite",
                 *_overlay(sim / f"session_{i}"), *(("--no-gnss",) if args.gnss and i > 0 else ()))
    t1 = time.perf_counter()
    _cli("merge", *(runs / str(i) for i in range(args.sessions)), "--out", merged,
         "--overwrite", "--reference", args.reference)
    scores = {"merge_s": time.perf_counter() - t1, "setup_s": t1 - t0,
              **evaluate(sim, merged)}
    for key, value in scores.items():
        print(f"{key:24s} {value:.3f}" if isinstance(value, float) else f"{key:24s} {value}")
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1) + "\n")


if __name__ == "__main__":
    main()
