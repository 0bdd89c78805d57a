"""How much a run's ATE moves when the IMU's true clock offset and mounting, given in the
config, are off by a tenth of a millisecond or a tenth of a degree: the yardstick for "ATE within
10 % of the run given the true values" (issue 30, Done-when).

    python tools/imu_calibration_sensitivity.py SEQ [SEQ...] --out DIR [--case 0.05:z90]
        [--json FILE]

SEQ: a simulated walk with an IMU (`lidar-slam simulate --motion handheld --imu --out SEQ`).
The case OFFSET:MOUNT is made as tools/imu_calibration_grid.py makes it (imu.csv on a clock
OFFSET s behind, turned by MOUNT); then `lidar-slam run` with the true values given, and again
with the offset 0.1 ms later / earlier, and with the rotation turned by 0.1 deg about the
lidar's x, y and z; each scored with `lidar-slam eval` (ATE RMSE). Prints one JSON row per run
and a markdown table (ATE, ratio to the true values' run, the front-end's odometry ATE and the
final solve's odometry variance factors).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

if __package__ in (None, ""):  # run as a script: `tools` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.imu_calibration_grid import make_case, run_and_score  # noqa: E402

OFFSET_S = 1e-4
ANGLE_DEG = 0.1
PERTURBATIONS = {"true values": (0.0, None), "offset +0.1 ms": (OFFSET_S, None),
                 "offset -0.1 ms": (-OFFSET_S, None), "rotation x 0.1 deg": (0.0, "x"),
                 "rotation y 0.1 deg": (0.0, "y"), "rotation z 0.1 deg": (0.0, "z")}


def run_perturbed(data: Path, root: Path, T_true: np.ndarray, offset_s: float, name: str,
                  d_offset_s: float, axis: str | None) -> dict:
    T = T_true.copy()
    if axis is not None:  # turned about the lidar's axis
        T[:3, :3] = Rotation.from_euler(axis, ANGLE_DEG, degrees=True).as_matrix() @ T[:3, :3]
    tag = name.replace(" ", "_").replace("+", "p").replace("-", "m")
    cfg = root / f"{tag}.yaml"
    cfg.write_text(yaml.safe_dump({"imu": {
        "T_lidar_imu": [round(float(v), 9) + 0.0 for v in T.ravel()],
        "time_offset_s": offset_s + d_offset_s}}))
    out = run_and_score(data, root / tag, cfg)
    summary = out.get("summary", {})
    return {"perturbation": name, "ate_m": out.get("ate_m"),
            "odometry_ate_m": summary.get("odometry_ate_rmse_m"),
            "odometry_variance_factor": summary.get("imu", {}).get("odometry_variance_factor"),
            "exit": out["exit"]}


def markdown(rows: list[dict]) -> str:
    lines = ["| walk | perturbation | ATE (m) | / true values | odometry ATE (m) | odometry "
             "variance factor (rot, trans) |", "|---" * 6 + "|"]
    for r in rows:
        ratio = "-" if r.get("ratio") is None else f"{r['ratio']:.3f}"
        odo = "-" if r["odometry_ate_m"] is None else f"{r['odometry_ate_m']:.4f}"
        lines.append(f"| {r['seq']} | {r['perturbation']} | {r['ate_m']} | {ratio} | {odo} | "
                     f"{r['odometry_variance_factor']} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqs", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--case", default="0.05:z90")
    ap.add_argument("--json", type=Path, help="Write the rows here too.")
    args = ap.parse_args()
    off_text, mount = args.case.split(":")
    rows = []
    for seq in args.seqs:
        root = args.out / seq.name / args.case.replace(":", "_")
        T_true = make_case(seq, root / "seq", float(off_text), mount)
        base = None
        for name, (d_offset, axis) in PERTURBATIONS.items():
            row = {"seq": seq.name, "case": args.case, **run_perturbed(
                root / "seq", root, T_true, float(off_text), name, d_offset, axis)}
            if name == "true values":
                base = row["ate_m"]
            row["ratio"] = round(row["ate_m"] / base, 3) if base and row["ate_m"] else None
            print(json.dumps(row), flush=True)
            rows.append(row)
    print(markdown(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
