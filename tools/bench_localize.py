"""Localisation, occupancy grid and export on a full simulated sequence (issue 13's figures).

Usage: python tools/bench_localize.py SEQ --out DIR [--sequence 07] [--kitti-gt PATH]
                                      [--other SEQ2] [--repeats 3] [--report FILE.md]

SEQ: a sequence simulated by `lidar-slam simulate` along KITTI --sequence (its poses.txt is the
truth). Steps, every one through the `lidar-slam` CLI:

1. map frames 0-799 (`run --n-scans 800`), then `localize --start 600 --n-scans 100` without an
   initial pose: statuses, and each pose against the map run's own pose of that frame and
   against the truth anchored at frame 600 on the map run's pose (and, in the JSON, against the
   truth placed in the map by the nearest map keyframe, see local_truth);
2. map the full sequence; localise frames 500-999 with 650-849 left out (a folder of links with
   the original stamps: a jump of 200 frames): frames from the jump to the relocalisation, and
   the worst `tracking` frame against the map run's poses;
3. localise SEQ2 (default: the first 100 scans of KITTI 00 simulated into DIR/other) in the
   full map: every frame should stay `lost`;
4. speed: `localize` against `run --no-loops` on frames 600-699, interleaved --repeats times:
   median frames/s of the whole command and per-frame compute (localize_ms_per_frame against
   odometry_ms_per_frame, both without reading the scans);
5. `export --occupancy` of the full map, checked against the simulator's world (share of the
   occupied cells within 0.5 m of a surface other than the ground, of a facade; share of the
   driven path free), and `export --format laz` (point count, seconds);
6. the same drive simulated into DIR/buildings on a street of buildings only (the same facades,
   no street furniture), mapped and gridded: the same occupancy figures, where every obstacle is
   a building face.

Writes DIR/bench_localize.json and the markdown report (--report, default DIR/report.md).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from lidar_slam.geometry import inverse, rotation_angle_deg
from lidar_slam.io.trajectory import read_kitti_calib_tr, read_kitti_poses

REPO = Path(__file__).resolve().parents[1]
KITTI_GT = REPO.parent / "shared" / "data" / "kitti_gt"
MAP_FRAMES = 800
SLICE = (600, 100)
JUMP_KEEP = ((500, 650), (850, 1000))  # frames kept: 500-649, 850-999


def cli(*args) -> tuple[subprocess.CompletedProcess, float]:
    """Run lidar-slam with args; (process, wall seconds). Raises on failure."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"lidar-slam {' '.join(map(str, args))} failed:\n{proc.stderr}")
    print(f"  lidar-slam {' '.join(map(str, args[:2]))} ... {wall:.1f} s", flush=True)
    return proc, wall


def truth(seq: Path) -> np.ndarray:
    """T_seq_lidar (K, 4, 4) of a simulated sequence."""
    Tr = read_kitti_calib_tr(seq / "calib.txt")
    return np.linalg.inv(Tr) @ read_kitti_poses(seq / "poses.txt") @ Tr


def status_of(out: Path) -> list[str]:
    with open(out / "status.csv", newline="") as fh:
        return [row["status"] for row in csv.DictReader(fh)]


def diff(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = inverse(ref) @ est
    return np.linalg.norm(d[:, :3, 3], axis=1), rotation_angle_deg(d)


def anchored(est: np.ndarray, gt: np.ndarray, T_anchor: np.ndarray) -> tuple:
    """Errors of est (K,4,4, map frame) against the truth gt (K,4,4) placed so that its first
    pose coincides with T_anchor (the map run's pose of that frame)."""
    return diff(est, T_anchor @ inverse(gt[0]) @ gt)


def local_truth(run: Path, gt_all: np.ndarray, frames: list[int]) -> np.ndarray:
    """Where the truth puts each frame in the map, as the map's own geometry sees it: the true
    motion from the map keyframe nearest in time to the frame, applied to that keyframe's map
    pose (its cloud sits there by construction). Free of the map's drift over longer spans,
    which a single alignment of the whole trajectory would count as error."""
    from lidar_slam.map.saved import open_map

    m = open_map(run)
    kf_frames, T_map_kf = m.frame_index.copy(), m.T_map_kf.copy()
    m.close()
    out = []
    for i in frames:
        k = int(np.argmin(np.abs(kf_frames - i)))
        out.append(T_map_kf[k] @ inverse(gt_all[kf_frames[k]]) @ gt_all[i])
    return np.stack(out)


def stats(t: np.ndarray, r: np.ndarray) -> dict:
    ok = (t <= 0.10) & (r <= 0.5)
    return {"max_m": float(t.max()), "mean_m": float(t.mean()),
            "p95_m": float(np.percentile(t, 95)), "max_deg": float(r.max()),
            "within_0.10m_0.5deg": float(np.mean(ok))}


def gap_sequence(src: Path, out: Path, keep: tuple[tuple[int, int], ...]) -> list[int]:
    """A KITTI-layout folder of links to the kept frames of src (original stamps and truth)."""
    frames = [i for a, b in keep for i in range(a, b)]
    if out.exists():
        shutil.rmtree(out)
    for sub in ("velodyne", "velodyne_times"):
        (out / sub).mkdir(parents=True)
        for k, i in enumerate(frames):
            os.symlink((src / sub / f"{i:06d}.bin").resolve(), out / sub / f"{k:06d}.bin")
    np.savetxt(out / "times.txt", np.loadtxt(src / "times.txt")[frames], fmt="%.6f")
    np.savetxt(out / "poses.txt", np.loadtxt(src / "poses.txt")[frames], fmt="%.9e")
    shutil.copy(src / "calib.txt", out / "calib.txt")
    return frames


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def case_slice(seq: Path, out: Path) -> dict:
    """Map 0-799, localise 600-699 without an initial pose."""
    run = out / "map0799"
    if not (run / "keyframes" / "map_poses.bin").is_file():
        cli("run", seq, "--out", run, "--n-scans", MAP_FRAMES, "--overwrite")
    a, n = SLICE
    loc = out / "loc0600"
    cli("localize", seq, "--map", run, "--out", loc, "--start", a, "--n-scans", n, "--overwrite")
    st = status_of(loc)
    est = read_kitti_poses(loc / "poses_kitti.txt")
    ref = read_kitti_poses(run / "poses_kitti.txt")[a:a + n]
    gt = truth(seq)[a:a + n]
    local = local_truth(run, truth(seq), list(range(a, a + n)))
    t, r = diff(est, ref)
    worst_ok = int(np.argmax((t > 0.10) | (r > 0.5))) if ((t > 0.10) | (r > 0.5)).any() else None
    return {"statuses": {s: st.count(s) for s in ("localized", "tracking", "lost")},
            "vs_map_run": stats(t, r),
            "first_frame_beyond_0.10m_0.5deg": None if worst_ok is None else a + worst_ok,
            "vs_truth_anchored": stats(*anchored(est, gt, ref[0])),
            "map_run_vs_truth_anchored": stats(*anchored(ref, gt, ref[0])),
            "vs_truth_in_the_map": stats(*diff(est, local)),
            "map_run_vs_truth_in_the_map": stats(*diff(ref, local)),
            "summary": summary(loc)}


def case_jump(seq: Path, out: Path) -> dict:
    """Full map; localise 500-999 without 650-849."""
    run = out / "mapfull"
    if not (run / "keyframes" / "map_poses.bin").is_file():
        cli("run", seq, "--out", run, "--overwrite")
    frames = gap_sequence(seq, out / "jump_seq", JUMP_KEEP)
    loc = out / "loc_jump"
    cli("localize", out / "jump_seq", "--map", run, "--out", loc, "--overwrite")
    st = np.array(status_of(loc))
    jump = JUMP_KEEP[0][1] - JUMP_KEEP[0][0]
    after = np.flatnonzero(st[jump:] == "localized")
    est = read_kitti_poses(loc / "poses_kitti.txt")
    ref = read_kitti_poses(run / "poses_kitti.txt")[frames]
    gt = truth(seq)[frames]
    local = local_truth(run, truth(seq), frames)
    t, r = diff(est, ref)
    tl, _ = diff(est, local)
    tracking = st == "tracking"
    segments = {}
    for name, part in (("before_jump", slice(0, jump)), ("after_jump", slice(jump, None))):
        tr = tracking[part]
        ta, _ = anchored(est[part], gt[part], ref[part][0])
        segments[name] = {"tracking_vs_map_run_max_m": float(t[part][tr].max()),
                          "tracking_vs_truth_anchored_max_m": float(ta[tr].max())}
    return {"statuses": {s: int((st == s).sum()) for s in ("localized", "tracking", "lost")},
            "frames_to_relocalise": int(after[0]) if len(after) else None,
            "jump_at_input_frame": frames[jump],
            "tracking_vs_map_run_max_m": float(t[tracking].max()),
            "tracking_over_0.5m_vs_map_run": int((t[tracking] > 0.5).sum()),
            "tracking_over_0.5m_frames": [frames[i] for i in np.flatnonzero(tracking & (t > 0.5))],
            "segments": segments,
            "tracking_vs_truth_in_the_map_max_m": float(tl[tracking].max()),
            "tracking_over_0.5m_vs_truth_in_the_map": int((tl[tracking] > 0.5).sum()),
            "vs_truth_in_the_map": stats(*diff(est, local)),
            "map_run_vs_truth_in_the_map": stats(*diff(ref, local)),
            "summary": summary(loc)}


def case_other(other: Path, out: Path) -> dict:
    loc = out / "loc_other"
    cli("localize", other, "--map", out / "mapfull", "--out", loc, "--overwrite")
    st = status_of(loc)
    return {"frames": len(st),
            "statuses": {s: st.count(s) for s in ("localized", "tracking", "lost")},
            "summary": summary(loc)}


def case_speed(seq: Path, out: Path, repeats: int) -> dict:
    """localize vs run --no-loops on the same frames, interleaved."""
    a, n = SLICE
    rows = {"localize": [], "odometry": []}
    for _ in range(repeats):
        cli("localize", seq, "--map", out / "map0799", "--out", out / "speed_loc", "--start", a,
            "--n-scans", n, "--overwrite")
        s = summary(out / "speed_loc")
        rows["localize"].append((s["fps"], s["localize_ms_per_frame"]))
        cli("run", seq, "--out", out / "speed_odo", "--start", a, "--n-scans", n, "--no-loops",
            "--overwrite")
        s = summary(out / "speed_odo")
        rows["odometry"].append((s["fps"], s["odometry_ms_per_frame"]))
    med = {k: np.median(np.array(v), axis=0) for k, v in rows.items()}
    return {"repeats": repeats, "raw": rows,
            "localize_fps": float(med["localize"][0]), "odometry_fps": float(med["odometry"][0]),
            "localize_ms_per_frame": float(med["localize"][1]),
            "odometry_ms_per_frame": float(med["odometry"][1])}


BAND_HEIGHTS_M = (0.3, 0.65, 1.0, 1.35, 1.7, 2.0)  # through the grid's 0.3-2.0 m band


def occupancy_metrics(n_frames: int, run: Path, occ: Path, kitti_gt: Path, sequence: str,
                      params=None) -> dict:
    """The grid in occ (map.yaml + map.png, read back as a map_server would) against the world
    the simulator built for the first n_frames of KITTI `sequence` (with WorldParams params).

    Each occupied cell is placed in the world through the map keyframe nearest to it (the map
    drifts over the whole drive, ATE ~1 m, so one rigid alignment would count that drift as grid
    error), then its distance to the world is the smallest, over heights through the obstacle
    band, of the distance to the nearest surface that is not the ground; its class is that
    surface's."""
    import yaml
    from PIL import Image

    from lidar_slam.map.saved import open_map
    from lidar_slam.sim import (
        CLASSES,
        SENSORS,
        load_kitti_truth,
        place_on_terrain,
        sequence_world,
    )

    meta = yaml.safe_load((occ / "map.yaml").read_text())
    image = np.asarray(Image.open(occ / meta["image"]), dtype=np.float64)[::-1]
    p = (255.0 - image) / 255.0
    state = np.where(p > meta["occupied_thresh"], 100, np.where(p < meta["free_thresh"], 0, -1))
    res, origin = meta["resolution"], np.array(meta["origin"][:2])
    kt = load_kitti_truth(kitti_gt, sequence)
    world = sequence_world(kt.poses_world_lidar, 0, n_frames, params=params)
    est = read_kitti_poses(run / "poses_kitti.txt")
    gt_world = place_on_terrain(kt.poses_world_lidar[:n_frames], world.terrain,
                                SENSORS["hdl64"].mount_height_m)  # the simulated poses
    m = open_map(run)
    kf_xy, T_map_kf, kf_frames = m.T_map_kf[:, :2, 3], m.T_map_kf.copy(), m.frame_index.copy()
    m.close()
    T_world_map = gt_world[kf_frames] @ inverse(T_map_kf)
    rows, cols = np.nonzero(state == 100)
    centres = origin + (np.c_[cols, rows] + 0.5) * res
    near_kf = np.argmin(np.linalg.norm(centres[:, None, :] - kf_xy[None], axis=2), axis=1)
    local = np.c_[centres, np.zeros(len(centres)), np.ones(len(centres))]
    pts = np.einsum("nij,nj->ni", T_world_map[near_kf], local)[:, :3]
    ground_z = world.terrain.height(pts[:, :2])
    dist = np.full(len(pts), np.inf)
    cls = np.full(len(pts), -1)
    for h in BAND_HEIGHTS_M:
        pts[:, 2] = ground_z + h
        d, c = world.closest(pts)
        d = np.where(c == CLASSES.index("ground"), np.inf, d)
        better = d < dist
        dist[better], cls[better] = d[better], c[better]
    near = dist <= 0.5
    by_class = {CLASSES[c]: float(np.mean(near & (cls == c))) for c in np.unique(cls[near])}
    ij = np.floor((est[:, :2, 3] - origin) / res).astype(int)
    path_free = float(np.mean(state[ij[:, 1], ij[:, 0]] == 0))
    return {"cells": [int(state.shape[1]), int(state.shape[0])], "resolution_m": res,
            "occupied": int(len(centres)), "free": int((state == 0).sum()),
            "occupied_within_0.5m_of_a_surface": float(np.mean(near)),
            "occupied_within_0.5m_nearest_a_facade": by_class.get("facade", 0.0),
            "occupied_within_0.5m_by_class": by_class,
            "world_objects": world.n_objects,
            "path_cells_free": path_free, "map_run_ate_m": summary(run).get("ate_rmse_m")}


def case_occupancy(seq: Path, out: Path, kitti_gt: Path, sequence: str) -> dict:
    run = out / "mapfull"
    occ = out / "occupancy"
    _, wall = cli("export", run, "--occupancy", "--out", occ, "--overwrite")
    res = occupancy_metrics(len(truth(seq)), run, occ, kitti_gt, sequence)
    laz_proc, laz_wall = cli("export", run, "--out", out / "map.laz", "--overwrite")
    n_laz = int(re.search(r"wrote (\d+) points", laz_proc.stdout).group(1))
    return {**res, "export_occupancy_s": wall, "laz_points": n_laz, "export_laz_s": laz_wall}


def case_occupancy_buildings(seq: Path, out: Path, kitti_gt: Path, sequence: str) -> dict:
    """The same drive simulated on a street of buildings only (WorldParams(objects=False): the
    same facades, no cars, poles, trees, bushes or clutter), mapped and gridded: where every
    obstacle is a building face, the share of occupied cells within 0.5 m of one."""
    from lidar_slam.sim import WorldParams, load_kitti_truth, simulate_sequence

    params = WorldParams(objects=False)
    n = len(truth(seq))
    bare = out / "buildings"
    if not (bare / "poses.txt").is_file():
        kt = load_kitti_truth(kitti_gt, sequence)
        t0 = time.perf_counter()
        simulate_sequence(kt.poses_world_lidar, kt.stamps_s, bare, n_scans=n,
                          Tr_cam_lidar=kt.Tr_cam_lidar, params=params)
        print(f"  simulated {n} scans on a street of buildings only ... "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    run = out / "map_buildings"
    if not (run / "keyframes" / "map_poses.bin").is_file():
        cli("run", bare, "--out", run, "--overwrite")
    occ = out / "occupancy_buildings"
    _, wall = cli("export", run, "--occupancy", "--out", occ, "--overwrite")
    return {**occupancy_metrics(n, run, occ, kitti_gt, sequence, params),
            "export_occupancy_s": wall}


def report_md(res: dict, cmd: str) -> str:
    a, j, o, s, g, b = (res[k] for k in ("slice", "jump", "other", "speed", "occupancy",
                                          "occupancy_buildings"))
    f = lambda x, d=3: "n/a" if x is None else f"{x:.{d}f}"  # noqa: E731
    over = j["tracking_over_0.5m_frames"]
    sb, sa = j["segments"]["before_jump"], j["segments"]["after_jump"]
    lines = [
        "# Localisation in a saved map, occupancy grid, export: full simulated 07",
        "",
        f"`{cmd}` at commit {res['commit']}, {res['date']}, on {os.cpu_count()} CPUs "
        f"(load average {res['load_start']:.1f} at the start, {res['load_end']:.1f} at the end: "
        "the machine was shared, so times are medians of interleaved repeats).",
        "",
        "## Done-when lines",
        "",
        "| line | measured |",
        "|---|---|",
        f"| map 0-799, localise 600-699 without a pose: every frame localized/tracking | "
        f"{a['statuses']['localized']} localized, {a['statuses']['tracking']} tracking, "
        f"{a['statuses']['lost']} lost |",
        f"| ... within 0.10 m / 0.5 deg of the map run's own poses | "
        f"{100 * a['vs_map_run']['within_0.10m_0.5deg']:.0f} % of the frames; worst "
        f"{f(a['vs_map_run']['max_m'])} m / {f(a['vs_map_run']['max_deg'])} deg; first frame "
        f"beyond: {a['first_frame_beyond_0.10m_0.5deg']} |",
        f"| (the same poses against the truth, anchored at frame 600 on the map run's pose) | "
        f"worst {f(a['vs_truth_anchored']['max_m'])} m / "
        f"{f(a['vs_truth_anchored']['max_deg'])} deg; the map run's own poses: "
        f"{f(a['map_run_vs_truth_anchored']['max_m'])} m / "
        f"{f(a['map_run_vs_truth_anchored']['max_deg'])} deg |",
        "| 500-999 without 650-849 in the full map: relocalised within 5 frames of the jump | "
        f"{j['frames_to_relocalise']} frames after input frame {j['jump_at_input_frame']} |",
        f"| ... no `tracking` frame more than 0.5 m off | worst `tracking` frame "
        f"{f(j['tracking_vs_map_run_max_m'])} m from the map run's pose "
        f"({j['tracking_over_0.5m_vs_map_run']} frames over 0.5 m: "
        f"{over[:3]}{'...' if len(over) > 3 else ''}); "
        f"after the jump {f(sa['tracking_vs_map_run_max_m'])} m; against the truth anchored "
        f"at each stretch's first frame: {f(sb['tracking_vs_truth_anchored_max_m'])} m before, "
        f"{f(sa['tracking_vs_truth_anchored_max_m'])} m after |",
        f"| scans of another sequence stay lost | {o['statuses']['lost']} of {o['frames']} lost, "
        f"{o['statuses']['localized'] + o['statuses']['tracking']} localised |",
        f"| localisation frames/s >= odometry frames/s (frames 600-699) | localize "
        f"{s['localize_fps']:.1f} vs `run --no-loops` {s['odometry_fps']:.1f} frames/s "
        f"(whole commands); per frame {s['localize_ms_per_frame']:.1f} vs "
        f"{s['odometry_ms_per_frame']:.1f} ms |",
        f"| occupancy, street of buildings only: >= 90 % of occupied cells within 0.5 m of a "
        f"building face | {100 * b['occupied_within_0.5m_nearest_a_facade']:.1f} % |",
        f"| ... >= 95 % of the driven path free | {100 * b['path_cells_free']:.1f} % |",
        f"| occupancy, street with furniture (sim 07 as benchmarked): within 0.5 m of a surface "
        f"| {100 * g['occupied_within_0.5m_of_a_surface']:.1f} % (nearest a facade: "
        f"{100 * g['occupied_within_0.5m_nearest_a_facade']:.1f} %; by class "
        f"{ {k: round(100 * v, 1) for k, v in g['occupied_within_0.5m_by_class'].items()} }) |",
        f"| ... >= 95 % of the driven path free | {100 * g['path_cells_free']:.1f} % |",
        "",
        "## Details",
        "",
        f"- 600-699 against the map run: mean {f(a['vs_map_run']['mean_m'])} m, p95 "
        f"{f(a['vs_map_run']['p95_m'])} m; localize summary: fps {a['summary']['fps']:.1f}, map "
        f"load {a['summary']['map_load_s']:.1f} s, relocalisations "
        f"{a['summary']['relocalisations']}.",
        f"- Jump run: {j['statuses']}; relocalisations {j['summary']['relocalisations']}, "
        f"attempts {j['summary']['relocalisation_attempts']}.",
        f"- Another sequence: {o['summary']['relocalisation_attempts']} relocalisation attempts, "
        f"{o['summary']['relocalise_ms_per_attempt']:.0f} ms each.",
        f"- Speed repeats (fps, ms/frame): localize {s['raw']['localize']}, odometry "
        f"{s['raw']['odometry']}.",
        f"- Occupancy of the full map: {g['cells'][0]} x {g['cells'][1]} cells of "
        f"{g['resolution_m']} m, {g['occupied']} occupied, {g['free']} free, "
        f"{g['export_occupancy_s']:.1f} s; each occupied cell is placed in the simulator's "
        f"world through the map keyframe nearest to it (the map run's ATE is "
        f"{f(g['map_run_ate_m'])} m over the whole drive). LAZ export: {g['laz_points']} points "
        f"in {g['export_laz_s']:.1f} s.",
        f"- Street of buildings only: {b['world_objects']} objects; {b['cells'][0]} x "
        f"{b['cells'][1]} cells, {b['occupied']} occupied, {b['free']} free, "
        f"{b['export_occupancy_s']:.1f} s; within 0.5 m of any surface other than the ground "
        f"{100 * b['occupied_within_0.5m_of_a_surface']:.1f} %; map run ATE "
        f"{f(b['map_run_ate_m'])} m.",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--sequence", default="07")
    ap.add_argument("--kitti-gt", type=Path, default=KITTI_GT)
    ap.add_argument("--other", type=Path, default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--report", type=Path, default=None)
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"load_start": os.getloadavg()[0], "date": time.strftime("%Y-%m-%d %H:%M")}
    from lidar_slam.provenance import git_commit

    res["commit"] = git_commit()
    print("1. map 0-799, localise 600-699", flush=True)
    res["slice"] = case_slice(args.seq, out)
    print("2. full map, jump", flush=True)
    res["jump"] = case_jump(args.seq, out)
    other = args.other
    if other is None:
        other = out / "other"
        if not (other / "poses.txt").is_file():
            cli("simulate", args.kitti_gt / "poses" / "00.txt", "--calib",
                args.kitti_gt / "calib" / "00.txt", "--out", other, "--n-scans", 100,
                "--overwrite")
    print("3. another sequence", flush=True)
    res["other"] = case_other(other, out)
    print("4. speed", flush=True)
    res["speed"] = case_speed(args.seq, out, args.repeats)
    print("5. occupancy, export", flush=True)
    res["occupancy"] = case_occupancy(args.seq, out, args.kitti_gt, args.sequence)
    print("6. occupancy on a street of buildings only", flush=True)
    res["occupancy_buildings"] = case_occupancy_buildings(args.seq, out, args.kitti_gt,
                                                          args.sequence)
    res["load_end"] = os.getloadavg()[0]
    (out / "bench_localize.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    cmd = "python tools/bench_localize.py " + " ".join(sys.argv[1:])
    report = args.report or out / "report.md"
    report.write_text(report_md(res, cmd))
    if args.report is not None:
        report.with_suffix(".json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    print(report.read_text())


if __name__ == "__main__":
    main()
