"""Does the held-out evidence tell, scan by scan, whether the slow-scan refinement helps?

    python tools/forensics/refine_evidence.py SEQ [--n-scans N] [--keep kiss|refined]

Runs the pipeline lidar-only (loops off); on every slow scan it computes both kiss-icp's pose
and the refinement's, and the evidence (lidar_slam.frontend.odometry.plane_evidence) before
the ICP (one Gauss-Newton step on the held-out points) and after it; the run goes on with
--keep's pose. Against the truth, each candidate's motion from the previous scan's pose is
scored (translation mm, rotation mdeg); prints how often the refined motion was the better
one, by what the evidence said.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from lidar_slam import pipeline
from lidar_slam.config import load_config
from lidar_slam.frontend import odometry
from lidar_slam.geometry import inverse, rotation_angle_deg
from lidar_slam.io.sources import open_source


def _error(P_prev, S, G_prev, G) -> tuple[float, float]:
    E = inverse(inverse(P_prev) @ S) @ (inverse(G_prev) @ G)
    return 1e3 * float(np.linalg.norm(E[:3, 3])), 1e3 * float(rotation_angle_deg(E))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--n-scans", type=int, default=None)
    ap.add_argument("--keep", choices=("kiss", "refined"), default="refined")
    ap.add_argument("--z", type=float, default=load_config().odometry.refine_evidence_z)
    args = ap.parse_args()
    records: list[dict] = []

    def traced(self, frame_down, T0, *_args, **_kwargs):  # _refine's other arguments unused
        o = self.cfg.odometry
        target = self._targets.get(False)  # the slow scans' target (Odometry._refine)
        if target is None:
            target = self._targets[False] = odometry.PlaneTarget(
                np.concatenate([odometry.transform_points(T, p) for T, p in self._recent()]),
                self.cfg.keyframes.cloud_voxel_m, odometry.REFINE_ITERATIONS,
                o.refine_max_correspondence_m)
        pts = np.asarray(frame_down)
        step = max(2, math.ceil(len(pts) / o.refine_max_points))
        source, held = pts[::step], pts[step // 2::step]
        T1 = target.align(source, T0, o.refine_max_correspondence_m)
        c = o.refine_max_correspondence_m
        records.append({"T0": T0, "T1": T1,
                        "early": odometry.plane_evidence(target, held, T0, None, c),
                        "post": odometry.plane_evidence(target, held, T0, T1, c)})
        return T1 if args.keep == "refined" else T0

    odometry.Odometry._refine = traced
    src = open_source(args.data)
    truth = src.ground_truth
    cfg = load_config(overrides={"loop": {"enabled": False}, "imu": {"enabled": False},
                                 "odometry": {"max_num_threads": 1}})
    pipe = pipeline.Pipeline(cfg)
    rows = []
    for i, scan in enumerate(src.scans(0, args.n_scans)):
        n = len(records)
        pipe.process(scan)
        if len(records) == n + 1 and i > 0:
            rec = records[-1]
            P = pipe.result.odom_poses
            T_used = rec["T1"] if args.keep == "refined" else rec["T0"]
            T_ref_stamp = inverse(T_used) @ P[-1]
            e0 = _error(P[-2], rec["T0"] @ T_ref_stamp, truth[i - 1], truth[i])
            e1 = _error(P[-2], rec["T1"] @ T_ref_stamp, truth[i - 1], truth[i])
            C = inverse(rec["T0"]) @ rec["T1"]
            rows.append((e0, e1, rec["early"], rec["post"],
                         (1e3 * float(np.linalg.norm(C[:3, 3])), 1e3 * rotation_angle_deg(C))))
    pipe.close()
    corr = np.array([r[4] for r in rows]).reshape(-1, 2)
    print(f"{args.data}: {len(rows)} slow scans, z {args.z}; the refinement's correction: "
          f"median {np.median(corr[:, 0]):.1f} mm, {np.median(corr[:, 1]):.0f} mdeg")
    groups = {"all": lambda r: True,
              "early proven": lambda r: r[2].proven(args.z),
              "early not": lambda r: not r[2].proven(args.z),
              "post proven": lambda r: r[3].proven(args.z),
              "post not": lambda r: not r[3].proven(args.z),
              "both proven": lambda r: r[2].proven(args.z) and r[3].proven(args.z)}
    refused = [r for r in rows if not r[3].proven(args.z)]
    if refused:
        z = np.array([r[3].gain_m / max(r[3].stderr_m, 1e-12) for r in refused])
        print("refused after the ICP: z quartiles " + " ".join(f"{q:.2f}" for q in
              np.percentile(z, [0, 25, 50, 75, 100])) + "; gain mm quartiles " + " ".join(
              f"{1e3 * q:.2f}" for q in np.percentile([r[3].gain_m for r in refused],
                                                       [0, 25, 50, 75, 100])))
    print("group           n  refined better (t)  (r)  mean e0-e1 mm  mdeg   median e0 mm  e1 mm")
    for name, f in groups.items():
        g = [r for r in rows if f(r)]
        if not g:
            print(f"{name:14s} {0:3d}")
            continue
        e0 = np.array([r[0] for r in g])
        e1 = np.array([r[1] for r in g])
        print(f"{name:14s} {len(g):4d}  {np.mean(e1[:, 0] < e0[:, 0]):17.2f} "
              f"{np.mean(e1[:, 1] < e0[:, 1]):5.2f}  {np.mean(e0[:, 0] - e1[:, 0]):12.2f} "
              f"{np.mean(e0[:, 1] - e1[:, 1]):6.1f}   {np.median(e0[:, 0]):11.2f} "
              f"{np.median(e1[:, 0]):6.2f}")


if __name__ == "__main__":
    main()
