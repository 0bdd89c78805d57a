"""How well a GNSS run sits on the Earth, against the simulator's truth, with no alignment at all.

    python tools/gnss_check.py RUN SIM [--json OUT.json]
        [--las MAP.las --kitti-gt ../shared/data/kitti_gt --sequence 07 [--start N] [--seed S]]

RUN: a `lidar-slam run` folder of a simulated sequence with gnss.csv (summary.json's geo section
has the datum and T_enu_map the back-end found; gnss_fixes.csv says what it did with each fix).
SIM: the `lidar-slam simulate --gnss` folder (poses.txt, calib.txt, T_world_seq.txt, whose world
is ENU at the datum of gnss_truth.csv). Prints the absolute position error of every frame (the
run's map-frame lidar positions through its geo-reference to WGS84, then to the simulator's ENU,
against the true lidar positions): RMS, horizontal and vertical RMS, max; and every multipath
jump of the simulator with what the run did with it (rejected x of y). The run's positions are
read from its poses_wgs84.csv when it wrote one (what a user gets), else placed by summary.json.
With --las (a `lidar-slam export RUN --out MAP.las` of the run): the distance of every LAS point,
read back through its own EPSG code to WGS84 and the simulator's ENU, to the nearest surface of
the simulated world (rebuilt from the KITTI trajectory the sequence was simulated along, with its
start scan and seed).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from lidar_slam.geo import GeoReference, LocalEnu
from lidar_slam.io.trajectory import camera_to_lidar_poses, read_kitti_calib_tr, read_kitti_poses


def sim_datum(sim: Path) -> LocalEnu:
    """The simulator's ENU datum, from gnss_truth.csv (true ENU and WGS84 of every epoch): the
    WGS84 point of ENU (0, 0, 0) seen from the epoch nearest to it, refined once over all."""
    t = np.loadtxt(sim / "gnss_truth.csv", delimiter=",", skiprows=1, ndmin=2)
    enu, llh = t[:, 1:4], t[:, 4:7]
    i = int(np.argmin(np.linalg.norm(enu, axis=1)))
    guess = LocalEnu(*LocalEnu(*llh[i]).to_wgs84(-enu[i:i + 1])[0])
    offset = (guess.from_wgs84(llh) - enu).mean(axis=0)  # the true datum in the guess's ENU
    datum = LocalEnu(*guess.to_wgs84(offset[None])[0])
    worst = float(np.abs(datum.from_wgs84(llh) - enu).max())
    if worst > 1e-3:
        raise SystemExit(f"{sim}: cannot recover the simulator's datum (off by {worst:.3g} m)")
    return datum


def true_lidar_enu(sim: Path) -> np.ndarray:
    """(n, 3) the true lidar position of every simulated scan in the simulator's ENU frame."""
    Tr = read_kitti_calib_tr(sim / "calib.txt")
    T_seq_lidar = camera_to_lidar_poses(read_kitti_poses(sim / "poses.txt"), Tr)
    T_world_seq = read_kitti_poses(sim / "T_world_seq.txt")[0]
    return (T_world_seq @ T_seq_lidar)[:, :3, 3]


def run_enu(run: Path, datum: LocalEnu) -> np.ndarray:
    """(n, 3) the run's lidar positions (poses_kitti.txt) placed by its geo-reference, in the
    ENU frame of `datum`."""
    summary = json.loads((run / "summary.json").read_text())
    if "geo" not in summary:
        why = (summary.get("gnss") or {}).get("reason", "no GNSS")
        raise SystemExit(f"{run}: no geo-reference in summary.json ({why})")
    if (run / "poses_wgs84.csv").is_file():
        llh = np.loadtxt(run / "poses_wgs84.csv", delimiter=",", skiprows=1, ndmin=2)[:, 2:5]
    else:
        geo = GeoReference.from_dict(summary["geo"])
        llh = geo.map_to_wgs84(read_kitti_poses(run / "poses_kitti.txt")[:, :3, 3])
    return datum.from_wgs84(llh)


def jumps(run: Path, sim: Path) -> list[dict]:
    """Every simulated multipath jump that reached gnss.csv, with the run's verdict on it."""
    truth = np.loadtxt(sim / "gnss_truth.csv", delimiter=",", skiprows=1, ndmin=2)
    with open(run / "gnss_fixes.csv", newline="") as fh:
        fixes = {round(float(r["stamp_s"]), 3): r for r in csv.DictReader(fh)}
    out = []
    for stamp, dropped, jump in truth[:, [0, 7, 8]]:
        if jump > 0 and not dropped:
            r = fixes.get(round(float(stamp), 3))
            out.append({"stamp_s": float(stamp), "jump_m": float(jump),
                        "status": r["status"] if r else "missing",
                        "residual_m": float(r["residual_m"]) if r else None})
    return out


def check(run: Path, sim: Path) -> dict:
    """The figures printed by main()."""
    datum = sim_datum(sim)
    summary = json.loads((run / "summary.json").read_text())
    est = run_enu(run, datum)
    start = int(summary.get("start", 0))
    truth = true_lidar_enu(sim)[start:start + len(est)]
    err = est - truth
    with open(run / "gnss_fixes.csv", newline="") as fh:
        status = [r["status"] for r in csv.DictReader(fh)]
    j = jumps(run, sim)
    good_rejected = sum(s == "rejected" for s in status) - sum(x["status"] == "rejected"
                                                                for x in j)
    return {"frames": len(est),
            "abs_rmse_m": float(np.sqrt((err ** 2).sum(axis=1).mean())),
            "abs_rmse_horizontal_m": float(np.sqrt((err[:, :2] ** 2).sum(axis=1).mean())),
            "abs_rmse_vertical_m": float(np.sqrt((err[:, 2] ** 2).mean())),
            "abs_max_m": float(np.linalg.norm(err, axis=1).max()),
            "fixes_used": status.count("used"), "fixes_rejected": status.count("rejected"),
            "jumps": j, "jumps_rejected": sum(x["status"] == "rejected" for x in j),
            "good_fixes_rejected": good_rejected}


def las_distances(las_file: Path, sim: Path, kitti_gt: Path, sequence: str, start: int,
                  seed: int) -> np.ndarray:
    """Distance (m) of every point of las_file to the simulated world's nearest surface."""
    import laspy
    from pyproj import CRS, Transformer

    from lidar_slam.sim import load_kitti_truth, sequence_world

    las = laspy.read(las_file)
    crs = las.header.parse_crs()
    if crs is None or crs.to_epsg() is None:
        raise SystemExit(f"{las_file}: no EPSG code in the LAS header")
    lon, lat, h = Transformer.from_crs(crs, CRS.from_epsg(4979), always_xy=True).transform(
        np.asarray(las.x), np.asarray(las.y), np.asarray(las.z))
    world_xyz = sim_datum(sim).from_wgs84(np.c_[lat, lon, h])
    n = len(np.loadtxt(sim / "times.txt", ndmin=1))
    kt = load_kitti_truth(kitti_gt, int(sequence))
    world = sequence_world(kt.poses_world_lidar, start, start + n, seed=seed)
    dist, _ = world.closest(world_xyz)
    print(f"LAS {las_file}: EPSG {crs.to_epsg()}, {len(dist)} points; distance to the world's "
          f"surfaces median {np.median(dist):.3f} m, 99 % {np.quantile(dist, 0.99):.3f} m, "
          f"max {dist.max():.3f} m, over 0.5 m: {int((dist > 0.5).sum())}")
    return dist


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("sim", type=Path)
    ap.add_argument("--json", type=Path, help="Also write the figures as JSON.")
    ap.add_argument("--las", type=Path, help="A LAS/LAZ export of RUN to check on the world.")
    ap.add_argument("--kitti-gt", type=Path, help="The kitti_gt folder SIM was simulated from.")
    ap.add_argument("--sequence", default="07", help="Its KITTI sequence number.")
    ap.add_argument("--start", type=int, default=0, help="simulate's --start.")
    ap.add_argument("--seed", type=int, default=0, help="simulate's --seed.")
    a = ap.parse_args(argv)
    if a.las is not None and a.kitti_gt is None:
        ap.error("--las needs --kitti-gt")
    r = check(a.run, a.sim)
    print(f"absolute position error, no alignment ({r['frames']} frames): RMS "
          f"{r['abs_rmse_m']:.3f} m (horizontal {r['abs_rmse_horizontal_m']:.3f}, vertical "
          f"{r['abs_rmse_vertical_m']:.3f}), max {r['abs_max_m']:.3f} m")
    print(f"fixes: {r['fixes_used']} used, {r['fixes_rejected']} rejected "
          f"({r['good_fixes_rejected']} of them not a simulated jump)")
    print(f"multipath jumps rejected: {r['jumps_rejected']} of {len(r['jumps'])}")
    for x in r["jumps"]:
        res = "-" if x["residual_m"] is None else f"{x['residual_m']:.1f} m"
        print(f"  t {x['stamp_s']:9.3f} s  jump {x['jump_m']:5.1f} m  {x['status']:8s} "
              f"residual {res}")
    if a.las is not None:
        d = las_distances(a.las, a.sim, a.kitti_gt, a.sequence, a.start, a.seed)
        r["las"] = {"points": int(len(d)), "median_m": float(np.median(d)),
                    "max_m": float(d.max()), "over_0_5_m": int((d > 0.5).sum())}
    if a.json is not None:
        a.json.write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
