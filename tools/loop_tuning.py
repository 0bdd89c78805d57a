"""Loop detection and verification, measured outside the pipeline.

python tools/loop_tuning.py sweep [DATA] [--config FILE] [--set loop.scan_context.threshold=0.25]
       [--every-scan] [--submap N] [--verify-top K] [--quiet]

sweep: loop detection + verification over a sequence with reference poses, as the pipeline would
run them: keyframes chosen in order (KeyframeSelector on the reference poses, or every scan), each
queried against the earlier non-recent ones, every candidate verified.

Prints one row per candidate (scan-context distance, yaw guess, fitness, rmse, accepted/reason,
and whether the verified pose is correct against the reference: within 1 m / 5 deg), then the
time per query for detection and for verification (ms, wall and CPU: on a shared machine the CPU
time is the fairer number; verification's small_gicp runs on one thread), and a summary.

Keyframe clouds are built like the pipeline's: range-cropped to map.max_range_m and voxelised at
keyframes.cloud_voxel_m. The match cloud may be a submap of +-N neighbouring keyframes merged
with the reference poses (the pipeline would use its odometry poses).

python tools/loop_tuning.py cost [KITTI_SEQ_DIR] [--config FILE] [--set a.b=value] [--repeats N]

cost: per keyframe on KITTI-sized scans (~120k points). KITTI 00 frames 0-15 hold no loop, so the
last scan is queried against the others (recent ones
not excluded) and verified against several earlier ones 3-13 m back, with the ground truth
saying whether the verified pose is right (1 m / 5 deg). Keyframe clouds are built like the
pipeline's (range <= map.max_range_m, keyframes.cloud_voxel_m voxels); query and match clouds are
submaps (LoopCloser: the keyframe and its predecessors / +-N neighbours, merged with GT poses).

Prints wall and CPU milliseconds (CPU sums threads; on a shared machine it is the fairer number).

python tools/loop_tuning.py gates RUN_DIR DATA [RUN_DIR DATA ...] [--threshold 0.4] [--json FILE]

gates: the descriptor threshold and the verification margin, chosen on finished runs. Each run's
keyframe store is replayed through the pipeline's own LoopDetector (same keyframes, descriptors,
submaps and verification as the run), at a loose descriptor threshold with the margin gate off and
every candidate verified, each verified pose scored against DATA's ground truth (or reference
poses: a gross-error gate of 1 m / 5 deg). Prints, per sequence, the margins of wrong poses that
passed every other gate and of true ones, then for each (threshold, margin) pair the loops the
pipeline would accept (first passing candidate of each keyframe, best descriptor first, at most
loop.max_verify), how many of them are wrong, and the verifications it would run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from lidar_slam.config import load_config
from lidar_slam.frontend.downsample import voxel_downsample
from lidar_slam.frontend.keyframes import KeyframeSelector
from lidar_slam.geometry import inverse, relative, rotation_angle_deg, transform_points, yaw_rad
from lidar_slam.io.pointcloud import read_cloud
from lidar_slam.io.sources import KittiSource
from lidar_slam.io.trajectory import read_kitti_poses
from lidar_slam.loop import adapt
from lidar_slam.loop.scan_context import ScanContextIndex, describe
from lidar_slam.loop.verify import verify
from lidar_slam.types import LoopCandidate

REPO = Path(__file__).resolve().parents[1]
OUSTER = REPO.parent / "shared" / "data" / "ouster_os0_loop_balm"
KITTI16 = REPO.parent / "shared" / "data" / "kitti00_first16"


def overrides(pairs: list[str]) -> dict:
    """'a.b.c=value' strings to a nested dict (values parsed as YAML scalars)."""
    out: dict = {}
    for pair in pairs:
        key, value = pair.split("=", 1)
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = yaml.safe_load(value)
    return out


def keyframe_cloud(path: Path, max_range_m: float, voxel_m: float) -> np.ndarray:
    pts = read_cloud(path).points
    pts = pts[np.linalg.norm(pts, axis=1) <= max_range_m]
    return voxel_downsample(pts, voxel_m)[0]


def sweep(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(prog="loop_tuning.py sweep")
    ap.add_argument("data", nargs="?", default=str(OUSTER))
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", action="append", default=[], help="config override a.b=value")
    ap.add_argument("--every-scan", action="store_true", help="every scan is a keyframe")
    ap.add_argument("--submap", type=int, default=None,
                    help="match submap +-N keyframes (default loop.verify.submap_radius)")
    ap.add_argument("--query-submap", type=int, default=None,
                    help="query cloud = the keyframe and its N predecessors, as LoopCloser does "
                         "(default loop.verify.submap_radius; 0 = the keyframe alone)")
    ap.add_argument("--verify-top", type=int, default=3, help="verify at most K candidates/query")
    ap.add_argument("--quiet", action="store_true", help="summary only")
    ap.add_argument("--csv", default=None, help="also write every candidate row to this CSV")
    args = ap.parse_args(argv)

    cfg = load_config(args.config, overrides(args.set))
    data = Path(args.data)
    files = sorted((data / "scans").glob("*.bin"))
    first = np.fromfile(files[0], np.float32).reshape(-1, 4)[:, :3]
    cfg = adapt.apply(cfg, adapt.auto_values(cfg, first))  # "auto" settings, as a run fixes them
    sc_cfg, v_cfg = cfg.loop.scan_context, cfg.loop.verify
    submap = v_cfg.submap_radius if args.submap is None else args.submap
    q_submap = v_cfg.submap_radius if args.query_submap is None else args.query_submap
    poses = read_kitti_poses(data / "poses.txt")
    selector = KeyframeSelector(cfg.keyframes)
    kf_scan = [i for i, T in enumerate(poses) if args.every_scan or selector.is_keyframe(T)]
    print(f"{len(kf_scan)} keyframes of {len(files)} scans; scan context {sc_cfg.rings}x"
          f"{sc_cfg.sectors} r={sc_cfg.max_radius_m} m thr={sc_cfg.threshold} exclude_recent="
          f"{sc_cfg.exclude_recent_m} m level={sc_cfg.level_to_ground}; verify {v_cfg.method} "
          f"voxel={v_cfg.voxel_m} min_fitness={v_cfg.min_fitness} min_margin={v_cfg.min_margin}; "
          f"match submap +-{submap} kf, query submap -{q_submap} kf; keyframe voxel "
          f"{cfg.keyframes.cloud_voxel_m} m")
    clouds = [keyframe_cloud(files[i], cfg.map.max_range_m, cfg.keyframes.cloud_voxel_m)
              for i in kf_scan]

    def submap_cloud(k: int, before: int, after: int) -> np.ndarray:
        parts = []
        for j in range(max(0, k - before), min(len(kf_scan), k + after + 1)):
            T_k_j = relative(poses[kf_scan[k]], poses[kf_scan[j]])
            parts.append(transform_points(T_k_j, clouds[j]))
        return np.vstack(parts)

    index = ScanContextIndex(sc_cfg)
    t_detect, t_verify, cpu_verify, rows = [], [], [], []
    if not args.quiet:
        print(" query match  dist  yaw_g  yaw_ref  ref_d_m  fitness  rmse   margin  result  "
              "vs_ref  err_m  err_deg  verify_ms  reason")
    path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poses[kf_scan][:, :3, 3], axis=0),
                                               axis=1))]
    for k, i in enumerate(kf_scan):
        t0 = time.perf_counter()
        res = index.query(k, clouds[k], path[k])
        index.add(k, clouds[k], path[k])
        t_detect.append((time.perf_counter() - t0) * 1e3)
        for cand in res.candidates[: args.verify_top]:
            m = cand.match
            source, target = submap_cloud(k, q_submap, 0), submap_cloud(m, submap, submap)
            t1, c1 = time.perf_counter(), time.process_time()
            v = verify(cand, source, target, v_cfg)
            t_verify.append((time.perf_counter() - t1) * 1e3)
            cpu_verify.append((time.process_time() - c1) * 1e3)
            T_ref = relative(poses[kf_scan[m]], poses[i])
            d = inverse(T_ref) @ v.T_match_query
            err_m, err_deg = float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d))
            correct = err_m < 1.0 and err_deg < 5.0
            rows.append((v.accepted, correct, float(np.linalg.norm(T_ref[:3, 3])), i, kf_scan[m],
                         cand.score, v.fitness, v.rmse_m, v.margin, err_m, err_deg, v.reason))
            if not args.quiet:
                name = lambda n: files[n].stem  # noqa: E731
                print(f"{name(i)} {name(kf_scan[m])} {cand.score:5.3f} "
                      f"{np.degrees(cand.yaw_guess_rad):6.0f} {np.degrees(yaw_rad(T_ref)):7.0f} "
                      f"{np.linalg.norm(T_ref[:3, 3]):7.1f} {v.fitness:8.2f} {v.rmse_m:6.3f} "
                      f"{v.margin:7.2f}  {'ACCEPT' if v.accepted else 'reject'}  "
                      f"{'correct' if correct else 'WRONG  '} {err_m:6.2f} {err_deg:7.1f} "
                      f"{t_verify[-1]:9.0f}  {v.reason}")
        if not args.quiet and not res.candidates and res.best_match is not None:
            print(f"{files[i].stem}   (best rejected: kf scan {files[kf_scan[res.best_match]].stem}"
                  f" distance {res.best_distance:.3f})")

    if args.csv:
        with open(args.csv, "w") as fh:
            fh.write("accepted,correct,ref_dist_m,query,match,sc_dist,fitness,rmse_m,margin,"
                     "err_m,err_deg,reason\n")
            for r in rows:
                fh.write(",".join(str(x) for x in r[:11]) + f",\"{r[11]}\"\n")
    acc = [r for r in rows if r[0]]
    print(f"candidates {len(rows)}: accepted {len(acc)} (correct {sum(r[1] for r in acc)}, "
          f"WRONG {sum(not r[1] for r in acc)}); rejected {len(rows) - len(acc)} (of which the "
          f"ICP pose was correct: {sum(r[1] for r in rows if not r[0])})")
    for name, t in (("detection per query (wall)", t_detect),
                    ("verification per candidate (wall)", t_verify),
                    ("verification per candidate (CPU, all threads)", cpu_verify)):
        if t:
            print(f"{name}: mean {np.mean(t):.1f} ms, median {np.median(t):.1f} ms, "
                  f"max {np.max(t):.1f} ms (n={len(t)})")


def timed(fn, repeats: int):
    """(result, median wall ms, median CPU ms) of fn() over repeats runs."""
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append((time.perf_counter() - w) * 1e3)
        cpus.append((time.process_time() - c) * 1e3)
    return out, float(np.median(walls)), float(np.median(cpus))


def cost(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(prog="loop_tuning.py cost")
    ap.add_argument("data", nargs="?", default=str(KITTI16))
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", action="append", default=[], help="config override a.b=value")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    cfg = load_config(args.config, overrides(args.set))
    src = KittiSource(Path(args.data))
    poses = src.ground_truth
    raw = [s.points for s in src.scans()]
    cfg = adapt.apply(cfg, adapt.auto_values(cfg, raw[0]))  # "auto" settings, as a run fixes them
    sc_cfg = cfg.loop.scan_context.model_copy(update={"exclude_recent_m": 0.0})
    v_cfg = cfg.loop.verify
    print(f"{len(raw)} scans, {np.mean([len(p) for p in raw]):.0f} points each on average")

    def kf_cloud(pts: np.ndarray) -> np.ndarray:
        pts = pts[np.linalg.norm(pts, axis=1) <= cfg.map.max_range_m]
        return voxel_downsample(pts, cfg.keyframes.cloud_voxel_m)[0]

    clouds, w, c = timed(lambda: [kf_cloud(p) for p in raw], 1)
    print(f"keyframe cloud (crop + {cfg.keyframes.cloud_voxel_m} m voxels, pipeline's cost): "
          f"{w / len(raw):.1f} ms wall per scan -> {np.mean([len(p) for p in clouds]):.0f} points")
    _, w, c = timed(lambda: describe(raw[-1], sc_cfg), args.repeats)
    print(f"scan context of a raw scan ({len(raw[-1])} points): {w:.1f} ms wall, {c:.1f} ms CPU")
    _, w, c = timed(lambda: describe(clouds[-1], sc_cfg), args.repeats)
    print(f"scan context of a keyframe cloud ({len(clouds[-1])} points): {w:.1f} ms wall, "
          f"{c:.1f} ms CPU")
    q = len(clouds) - 1

    def detect():
        index = ScanContextIndex(sc_cfg)
        for k in range(q):
            index.add(k, clouds[k], float(k))
        t = time.perf_counter(), time.process_time()
        res = index.query(q, clouds[q], float(q))
        return res, (time.perf_counter() - t[0]) * 1e3, (time.process_time() - t[1]) * 1e3

    res, w, c = detect()
    print(f"detection (query vs {q} keyframes, incl. descriptor): {w:.1f} ms wall, {c:.1f} ms CPU;"
          f" best match {res.best_match} at distance {res.best_distance:.3f}")

    def submap(k: int, before: int, after: int) -> np.ndarray:
        parts = [transform_points(relative(poses[k], poses[j]), clouds[j])
                 for j in range(max(0, k - before), min(len(clouds), k + after + 1))]
        return np.vstack(parts)

    r = v_cfg.submap_radius
    source = submap(q, r, 0)
    print(f"verification (query submap {len(source)} points, match submaps +-{r}):")
    for m in (0, 3, 5, 8, 10):
        target = submap(m, r, r)
        dist, yaw = 0.0, 0.0
        for cand in res.candidates:
            if cand.match == m:
                dist, yaw = cand.score, cand.yaw_guess_rad
        cand = LoopCandidate(q, m, dist, yaw)
        v, w, c = timed(lambda cand=cand, target=target: verify(cand, source, target, v_cfg),
                        args.repeats)
        d = inverse(relative(poses[m], poses[q])) @ v.T_match_query
        err_m, err_deg = float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d))
        ok = err_m < 1.0 and err_deg < 5.0
        print(f"  {q} -> {m} ({np.linalg.norm(poses[q][:3, 3] - poses[m][:3, 3]):4.1f} m, "
              f"{len(target)} pts): {w:6.1f} ms wall {c:6.1f} ms CPU  fitness {v.fitness:.2f} "
              f"margin {v.margin:.2f} {'ACCEPT' if v.accepted else 'reject'} "
              f"{'correct' if ok else 'WRONG'} ({err_m:.2f} m {err_deg:.1f} deg)  {v.reason}")


def replay_candidates(run: Path, data: str, threshold: float) -> list[dict]:
    """Every candidate of every keyframe of a finished run below `threshold`, verified with the
    margin gate off, as dicts (keyframe, rank, descriptor distance, gates, margin, correct)."""
    import itertools
    import json
    import shutil
    import tempfile

    from lidar_slam.config import SlamConfig
    from lidar_slam.eval import metrics
    from lidar_slam.io.sources import open_source
    from lidar_slam.loop.detector import LoopDetector
    from lidar_slam.loop.verify import match_side, query_side
    from lidar_slam.map.keyframes import KeyframeReader

    raw = yaml.safe_load((run / "config.yaml").read_text())
    raw["loop"]["scan_context"]["threshold"] = threshold
    raw["loop"]["verify"]["min_margin"] = 0.0
    auto = json.loads((run / "summary.json").read_text()).get("auto_settings", {})
    cfg = adapt.apply(SlamConfig(**raw), auto)  # the "auto" values the run fixed
    gt = open_source(data).ground_truth
    if gt is None:
        sys.exit(f"{data}: no ground truth or reference poses to score loops against")
    rows: list[dict] = []
    pairs, Ts = [], []
    with tempfile.TemporaryDirectory() as tmp:  # the detector writes its descriptor file there
        shutil.copytree(run / "keyframes", Path(tmp) / "kf")
        det = LoopDetector(cfg, KeyframeReader(Path(tmp) / "kf"))
        vcfg = cfg.loop.verify
        for k in itertools.count():  # until the store's first missing keyframe
            try:
                kf = det.store.get(k)
            except KeyError:
                break
            pts = kf.points.astype(np.float64)
            if not len(pts):
                continue
            cands = det.candidates(k, pts)
            query = query_side(det.submap(k, vcfg.submap_radius, k), vcfg) if cands else None
            for rank, c in enumerate(cands[: cfg.loop.max_verify]):
                side = match_side(det.submap(c.match, vcfg.submap_radius, k), vcfg)
                r = verify(c, query, side, vcfg)
                pairs.append((kf.frame_index, det.store.frame_index(c.match)))
                Ts.append(r.T_match_query)
                rows.append(dict(kf=k, rank=rank, distance=float(c.score),
                                 passed=bool(r.accepted), margin=float(r.margin),
                                 fitness=float(r.fitness)))
            det.index.add(k, pts, det.path_m(k), det.store.stamp_s(k))
    if rows:  # scored once: loop_precision_recall also finds the revisits of the whole sequence
        # Each loop is between two keyframe nodes; the truth is at the frames' stamps. Where a
        # node is not at its stamp (keyframe 0; without an IMU, mid-sweep), carry the loop to
        # the stamps along the run's own node-to-stamp offsets, as loops.csv does.
        to_frame = node_to_stamp(run)
        Ts = [inverse(to_frame.get(m, np.eye(4))) @ T @ to_frame.get(q, np.eye(4))
              for (q, m), T in zip(pairs, Ts)]
        correct = metrics.loop_precision_recall(np.array(pairs), np.array(Ts), gt,
                                                min_frame_gap=0).correct
        for row, ok in zip(rows, correct):
            row["correct"] = bool(ok)
    return rows


def node_to_stamp(run: Path) -> dict[int, np.ndarray]:
    """Per input frame of a keyframe, T_node_frame: its graph node to the frame's stamp, from a
    finished run's final poses (keyframes/map_poses.bin against poses_kitti.txt: a keyframe's
    own frame is its node moved along the odometry); {} for a run without map poses."""
    import json

    from lidar_slam.map.keyframes import MAP_POSES, TABLE_DTYPE

    path = run / "keyframes" / MAP_POSES
    if not path.is_file():
        return {}
    M = np.fromfile(path, dtype="<f8").reshape(-1, 4, 4)
    frames = np.fromfile(run / "keyframes" / "table.bin", dtype=TABLE_DTYPE)["frame_index"]
    start = json.loads((run / "summary.json").read_text()).get("start", 0)
    P = read_kitti_poses(run / "poses_kitti.txt")
    return {int(f): inverse(T) @ P[int(f) - start] for T, f in zip(M, frames[: len(M)])}


def simulate_gates(rows: list[dict], threshold: float, margin: float) -> tuple[int, int, int]:
    """(accepted, wrong, verified) if the pipeline ran with this threshold and margin."""
    accepted = wrong = verified = 0
    by_kf: dict[int, list[dict]] = {}
    for r in rows:
        by_kf.setdefault(r["kf"], []).append(r)
    for cands in by_kf.values():
        for r in sorted(cands, key=lambda r: r["rank"]):
            if r["distance"] >= threshold:
                break
            verified += 1
            if r["passed"] and r["margin"] >= margin:
                accepted += 1
                wrong += not r["correct"]
                break
    return accepted, wrong, verified


def gates(argv: list[str]) -> None:
    import json

    ap = argparse.ArgumentParser(prog="loop_tuning.py gates")
    ap.add_argument("pairs", nargs="+", help="RUN_DIR DATA pairs")
    ap.add_argument("--threshold", type=float, default=0.4)
    ap.add_argument("--json", default=None, help="write every replayed candidate here")
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        sys.exit("gates: give RUN_DIR DATA pairs")
    runs = list(zip(args.pairs[::2], args.pairs[1::2]))
    table = {}
    for run, data in runs:
        rows = replay_candidates(Path(run), data, args.threshold)
        table[data] = rows
        ok = [r for r in rows if r["passed"]]
        low = sorted(round(r["margin"], 3) for r in ok if r["correct"] and r["margin"] < 0.12)
        print(f"{data}: {len(rows)} candidates verified; passing every gate but the margin: "
              f"{len(ok)}; margins of the wrong ones "
              f"{sorted(round(r['margin'], 3) for r in ok if not r['correct'])}, true ones below "
              f"0.12 {low}")
    names = [Path(d).name for _, d in runs]
    print("threshold margin  " + "  ".join(f"{n:>22}" for n in names) +
          "   (loops accepted / wrong / verifications)")
    for t in sorted({0.3, 0.33, 0.35, args.threshold}):
        if t > args.threshold:
            continue
        for m in (0.12, 0.08, 0.06, 0.04, 0.02, 0.0):
            cells = ["%6d / %3d / %5d" % simulate_gates(table[d], t, m) for _, d in runs]
            print(f"{t:9.2f} {m:6.2f}  " + "  ".join(f"{c:>22}" for c in cells))
    if args.json:
        Path(args.json).write_text(json.dumps(table))


def main() -> None:
    commands = {"sweep": sweep, "cost": cost, "gates": gates}
    if len(sys.argv) < 2 or sys.argv[1] not in commands:
        sys.exit("usage: python tools/loop_tuning.py sweep|cost|gates [args...] "
                 "(see the docstring)")
    commands[sys.argv[1]](sys.argv[2:])


if __name__ == "__main__":
    main()
