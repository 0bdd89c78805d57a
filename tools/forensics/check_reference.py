"""How consistent is a reference trajectory with its own scans?

For chosen scan pairs, start four independent registrations at the reference relative pose and
print how far each one moves away from it. Where the reference is right, every method stays
within its noise (a centimetre or two); where every method moves the same way by the same amount,
the reference is what is off there.

Pairs come in two kinds so that drift can be told from a registration bias:
  loop    - far apart along the path, close in space (where loop closure acts);
  control - a few frames apart, with a comparable heading change and distance (same viewpoint
            change, almost no path in between, so almost no room for odometry drift).

Methods (all start at the reference relative pose, scans at full resolution unless stated):
  p2plane  open3d point-to-plane ICP, 0.1 m voxels
  gicp     open3d generalized ICP, 0.1 m voxels
  kiss     kiss-icp's own robust point-to-point registration against a voxel map of the match
  submap   point-to-plane between submaps of +-2 scans placed with the reference poses

    python tools/forensics/check_reference.py ../shared/data/ouster_os0_loop_balm \
        --loop 172:106 --loop 169:112 --control 133:128
    (without --loop/--control: loop pairs are found from the reference poses)

Validated on simulated KITTI 00 (exact truth, scans deskewed with the truth's motion): on 6 loop
pairs submap, p2plane and GICP move 0.1-0.3 cm, so they carry no loop-pair bias of their own;
kiss-icp's registration is noisier there (0.4-8.7 cm on loops, 1.0-3.1 cm on controls).

--corrected OUT.txt also writes the reference with its own loop closed: a pose graph of the
reference's consecutive relative poses (1 cm / 0.05 deg) plus the submap registrations of the loop
pairs (2 cm / 0.1 deg), none of it from lidar_slam's pipeline. --est runs are then also scored
(ATE) against it. It is a diagnostic, not a ground truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lidar_slam.backend.factors import sigmas_to_information
from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.eval.metrics import ate
from lidar_slam.frontend.deskew import deskew
from lidar_slam.geometry import inverse, rotation_angle_deg, transform_points
from lidar_slam.io.sources import open_source
from lidar_slam.io.trajectory import read_kitti_poses, write_kitti_poses
from lidar_slam.o3d import o3d

reg = o3d.pipelines.registration


def _pcd(points: np.ndarray, voxel_m: float):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pcd = pcd.voxel_down_sample(voxel_m)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel_m, max_nn=20))
    return pcd


def _o3d(src: np.ndarray, tgt: np.ndarray, T0: np.ndarray, gicp: bool, voxel_m: float = 0.1):
    s, t = _pcd(src, voxel_m), _pcd(tgt, voxel_m)
    crit = reg.ICPConvergenceCriteria(1e-7, 1e-7, 100)
    T = T0
    for max_corr in (0.5, 0.25):  # coarse to fine
        if gicp:
            T = reg.registration_generalized_icp(
                s, t, max_corr, T, reg.TransformationEstimationForGeneralizedICP(), crit
            ).transformation
        else:
            T = reg.registration_icp(
                s, t, max_corr, T, reg.TransformationEstimationPointToPlane(), crit
            ).transformation
    return np.asarray(T)


def _kiss(src: np.ndarray, tgt: np.ndarray, T0: np.ndarray, voxel_m: float = 0.3):
    from kiss_icp.pybind import kiss_icp_pybind as kp

    vmap = kp._VoxelHashMap(voxel_size=voxel_m, max_distance=100.0, max_points_per_voxel=20)
    vmap._update(kp._voxel_down_sample(kp._Vector3dVector(tgt.astype(np.float64)), voxel_m * 0.5),
                 np.eye(4))
    source = kp._voxel_down_sample(kp._Vector3dVector(src.astype(np.float64)), voxel_m * 1.5)
    regn = kp._Registration(max_num_iterations=500, convergence_criterion=1e-5, max_num_threads=0)
    T = T0
    for sigma in (0.3, 0.1):
        T = regn._align_points_to_map(points=source, voxel_map=vmap, initial_guess=T,
                                      max_correspondance_distance=3 * sigma, kernel=sigma)
    return np.asarray(T)


class ScanCache:
    """Scans loaded when first needed (a 1200-scan HDL-64 sequence does not fit in memory). Scans
    with per-point times are deskewed to their stamp with the *reference's* own motion to the next
    scan, so that the reference is tested on scans consistent with it."""

    def __init__(self, source, ref: np.ndarray, keep: int = 64):
        self.source, self.ref, self.keep = source, ref, keep
        self._cache: dict[int, np.ndarray] = {}
        self.deskewed = 0

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, i: int) -> np.ndarray:
        if i not in self._cache:
            scan = next(iter(self.source.scans(i, 1)))
            pts = scan.points[:, :3].astype(np.float64)
            if scan.point_times is not None and len(self) > 1:
                j = i + 1 if i + 1 < len(self) else i - 1
                T = inverse(self.ref[min(i, j)]) @ self.ref[max(i, j)]
                dt = abs(float(self.source.stamps[max(i, j)] - self.source.stamps[min(i, j)]))
                pts = deskew(pts, scan.point_times, T, dt if dt > 0 else 0.1)
                self.deskewed += 1
            if len(self._cache) >= self.keep:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = pts
        return self._cache[i]


def _submap(scans: list[np.ndarray], ref: np.ndarray, centre: int, radius: int = 2) -> np.ndarray:
    parts = [transform_points(inverse(ref[centre]) @ ref[j], scans[j])
             for j in range(max(0, centre - radius), min(len(scans), centre + radius + 1))]
    return np.concatenate(parts)


def register_pair(scans: list[np.ndarray], ref: np.ndarray, q: int, m: int,
                  methods: tuple[str, ...] = ("p2plane", "gicp", "kiss", "submap")
                  ) -> dict[str, np.ndarray]:
    """T_match_query from each method, every one started at the reference relative pose."""
    T_ref = inverse(ref[m]) @ ref[q]
    run = {
        "p2plane": lambda: _o3d(scans[q], scans[m], T_ref, gicp=False),
        "gicp": lambda: _o3d(scans[q], scans[m], T_ref, gicp=True),
        "kiss": lambda: _kiss(scans[q], scans[m], T_ref),
        "submap": lambda: _o3d(_submap(scans, ref, q), _submap(scans, ref, m), T_ref, gicp=False),
    }
    return {name: run[name]() for name in methods}


def orthonormalize(poses: np.ndarray) -> np.ndarray:
    """Text poses are orthonormal only to their printed digits (kiss-icp checks it)."""
    out = poses.copy()
    for T in out:
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def _move(T_ref: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    d = inverse(T_ref) @ T
    return float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d))


def _auto_loops(ref: np.ndarray, min_gap: int, max_dist_m: float) -> list[tuple[int, int]]:
    """For each late frame, the closest earlier frame at least min_gap frames back."""
    pairs = []
    for q in range(min_gap, len(ref)):
        d = np.linalg.norm(ref[: q - min_gap + 1, :3, 3] - ref[q, :3, 3], axis=1)
        m = int(np.argmin(d))
        if d[m] < max_dist_m:
            pairs.append((q, m))
    return pairs


def _pair(text: str, first_index: int) -> tuple[int, int]:
    q, m = text.split(":")
    return int(q) - first_index, int(m) - first_index


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("data", type=Path, help="folder with scans/ and poses.txt (T_world_sensor)")
    ap.add_argument("--poses", type=Path,
                    help="reference poses, KITTI format T_world_sensor (default: the data's own "
                         "poses.txt / ground truth, in the lidar frame)")
    ap.add_argument("--first-index", type=int, default=0,
                    help="file number of the first scan, so pairs can be named by file number")
    ap.add_argument("--loop", action="append", default=[], help="QUERY:MATCH (file numbers)")
    ap.add_argument("--control", action="append", default=[], help="QUERY:MATCH (file numbers)")
    ap.add_argument("--est", type=Path, action="append", default=[],
                    help="also report an estimated trajectory's relative pose (KITTI format)")
    ap.add_argument("--corrected", type=Path,
                    help="write the reference with its loop closed by the submap registrations")
    args = ap.parse_args(argv)

    source = open_source(args.data)
    if args.poses:
        ref = read_kitti_poses(args.poses)
    elif source.ground_truth is not None:  # KITTI layouts: already moved to the lidar frame
        ref = source.ground_truth
    else:
        print(f"error: {args.data}: no reference poses (give --poses)", file=sys.stderr)
        return 2
    ref = orthonormalize(ref)
    scans = ScanCache(source, ref)
    if len(scans) != len(ref):
        print(f"error: {len(scans)} scans but {len(ref)} poses", file=sys.stderr)
        return 2
    loops = [_pair(p, args.first_index) for p in args.loop] or _auto_loops(ref, 40, 4.0)[:12]
    controls = [_pair(p, args.first_index) for p in args.control]
    ests = [(p.parent.name + "/" + p.name, read_kitti_poses(p)) for p in args.est]

    methods = ("p2plane", "gicp", "kiss", "submap")
    head = f"{'kind':8s} {'pair':>9s} {'dist':>5s} {'dyaw':>5s} " + " ".join(
        f"{m:>13s}" for m in methods) + "".join(f" {n[-24:]:>24s}" for n, _ in ests)
    print("Each cell: how far the method moved from the reference relative pose, cm / deg")
    print(head)
    rows = []
    loop_edges: list[tuple[int, int, np.ndarray]] = []
    for kind, pairs in (("loop", loops), ("control", controls)):
        for q, m in pairs:
            T_ref = inverse(ref[m]) @ ref[q]
            yaw = np.degrees(np.arctan2(T_ref[1, 0], T_ref[0, 0]))
            res = register_pair(scans, ref, q, m)
            moves = {k: _move(T_ref, T) for k, T in res.items()}
            spread = max(_move(res[a], res[b])[0] for a in methods for b in methods)
            line = (f"{kind:8s} {q + args.first_index:4d}:{m + args.first_index:<4d} "
                    f"{np.linalg.norm(T_ref[:3, 3]):5.2f} {yaw:5.0f} "
                    + " ".join(f"{100 * t:7.1f}/{r:5.2f}" for t, r in moves.values()))
            for _, P in ests:
                t, r = _move(T_ref, inverse(P[m]) @ P[q])
                line += f" {100 * t:18.1f}/{r:5.2f}"
            print(line + f"   spread {100 * spread:.1f} cm", flush=True)
            rows.append((kind, {k: t for k, (t, _) in moves.items()}))
            if kind == "loop":
                loop_edges.append((m, q, res["submap"]))
    for kind in ("loop", "control"):
        v = [r for k, r in rows if k == kind]
        if v:
            print(f"{kind} ({len(v)} pairs), median move per method: " + ", ".join(
                f"{m} {100 * np.median([r[m] for r in v]):.1f} cm" for m in methods))
    if args.corrected:
        corrected = close_reference_loop(ref, loop_edges)
        write_kitti_poses(args.corrected, corrected)
        print(f"wrote {args.corrected}: the reference moved by up to "
              f"{100 * max(_move(a, b)[0] for a, b in zip(ref, corrected)):.1f} cm")
        for name, P in ests:
            print(f"ATE {name}: vs reference {ate(P, ref).rmse_m:.4f} m, "
                  f"vs loop-closed reference {ate(P, corrected).rmse_m:.4f} m")
    return 0


def close_reference_loop(ref: np.ndarray, loops: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    graph = PoseGraph()
    graph.add_prior(0, ref[0], 1e-3, 1e-3)
    for i in range(len(ref)):
        graph.set_initial(i, ref[i])
        if i:
            graph.add_odometry(i - 1, i, inverse(ref[i - 1]) @ ref[i], rot_sigma_deg=0.05,
                               trans_sigma_m=0.01)
    for m, q, T in loops:
        graph.add_loop(m, q, T, sigmas_to_information(0.1, 0.02, 3))
    est = graph.optimize()
    return np.stack([est[i] for i in range(len(ref))])


if __name__ == "__main__":
    sys.exit(main())
