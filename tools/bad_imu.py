"""An imu.csv changed the ways users get it wrong (issue 30, item 6), each run as a new user would.

    python tools/bad_imu.py SEQ --out DIR [--cases ns,deg,...] [--markdown FILE]

SEQ: a simulated sequence with an IMU (`lidar-slam simulate --motion handheld --imu --out SEQ`).
For each case a copy of SEQ (the scans linked, imu.csv rewritten) goes to DIR/<case>/seq, then
`lidar-slam run` (its lidar_slam.yaml as --config; --no-imu for the `no-imu` case) and
`lidar-slam eval` against its poses.txt. Prints one row per case: exit code, ATE (m), whether
summary.json says the IMU was used, the IMU check's verdict, the IMU factors in the final solve
and the accelerometer's disagreement with the odometry (lidar_slam.frontend.imu_check), the
number of warning lines and the last line on stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CASES = {
    "imu": "imu.csv as simulated",
    "no-imu": "--no-imu",
    "ns": "stamps in ns",
    "deg": "gyro in deg/s",
    "g": "accelerations in g",
    "mount90z": "IMU mounted 90 deg about z, config not told",
    "clock50ms": "clock 0.05 s off",
    "half": "covering half the scans",
    "accflip": "accelerometer's sign flipped",
    "acc90z": "accelerometer's axes turned 90 deg about z, gyro not",
    "accspike": "one accelerometer sample of 1000 m/s^2",
    "two": "two samples only",
    "acc108": "accelerometer's scale x1.08",
    "accdelay": "accelerometer 0.2 s behind the gyro",
}
HEADER = "stamp_s,wx,wy,wz,ax,ay,az"


def rotated_about_z(rows: np.ndarray, deg: float) -> np.ndarray:
    """The samples of an IMU turned by deg about its z axis against the one simulated (the
    measurements in the new frame: R^T v)."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = rows.copy()
    out[:, 1:4] = rows[:, 1:4] @ R
    out[:, 4:7] = rows[:, 4:7] @ R
    return out


def corrupt(rows: np.ndarray, case: str) -> tuple[np.ndarray, str]:
    """The imu.csv rows of a case and the stamp format to write them with."""
    r = rows.copy()
    if case == "ns":
        r[:, 0] = np.round(r[:, 0] * 1e9)
        return r, "%d"
    if case == "deg":
        r[:, 1:4] = np.degrees(r[:, 1:4])
    elif case == "g":
        r[:, 4:7] = r[:, 4:7] / 9.81
    elif case == "mount90z":
        r = rotated_about_z(r, 90.0)
    elif case == "clock50ms":
        r[:, 0] += 0.05
    elif case == "half":
        mid = 0.5 * (r[0, 0] + r[-1, 0])
        r = r[r[:, 0] <= mid]
    elif case == "accflip":
        r[:, 4:7] = -r[:, 4:7]
    elif case == "acc90z":
        r[:, 4:7] = rotated_about_z(rows, 90.0)[:, 4:7]
    elif case == "accspike":
        r[len(r) // 2, 6] = 1000.0
    elif case == "two":
        r = r[:2]
    elif case == "acc108":
        r[:, 4:7] *= 1.08
    elif case == "accdelay":
        r[:, 4:7] = np.roll(rows[:, 4:7], 40, axis=0)  # 200 Hz: each row holds the one 40 back
    return r, "%.9f"


def link_sequence(seq: Path, dest: Path, skip: tuple[str, ...]) -> None:
    """dest: seq's files as symbolic links, but for those named in skip (written by the caller)."""
    dest.mkdir(parents=True, exist_ok=True)
    for item in seq.iterdir():
        if item.name in skip or (dest / item.name).exists():
            continue
        os.symlink(item.resolve(), dest / item.name)


def ate_m(run_dir: Path, data: Path) -> float | None:
    """The run's ATE RMSE (m) against the sequence's truth, as `lidar-slam eval` prints it."""
    ev = cli("eval", str(run_dir / "poses_kitti.txt"), str(data / "poses.txt"), "--calib",
             str(data / "calib.txt"))
    for line in ev.stdout.splitlines():
        if line.startswith("ATE RMSE"):
            return float(line.split()[2])
    return None


def make_case(seq: Path, dest: Path, case: str) -> Path:
    """A copy of seq whose scans are links and whose imu.csv is the case's."""
    link_sequence(seq, dest, skip=("imu.csv",))
    rows = np.loadtxt(seq / "imu.csv", delimiter=",", skiprows=1, ndmin=2)
    rows, stamp_fmt = corrupt(rows, case)
    np.savetxt(dest / "imu.csv", rows, delimiter=",", header=HEADER, comments="",
               fmt=[stamp_fmt] + ["%.10g"] * 6)
    return dest


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *args], capture_output=True,
                          text=True, check=False)


def run_case(seq: Path, out: Path, case: str) -> dict:
    data = make_case(seq, out / case / "seq", case)
    run_dir = out / case / "run"
    args = ["run", str(data), "--out", str(run_dir), "--overwrite"]
    if (data / "lidar_slam.yaml").exists():
        args += ["--config", str(data / "lidar_slam.yaml")]
    if case == "no-imu":
        args.append("--no-imu")
    t0 = time.perf_counter()
    proc = cli(*args)
    row = {"case": case, "what": CASES[case], "exit": proc.returncode,
           "wall_s": round(time.perf_counter() - t0, 1)}
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    row["warnings"] = sum(ln.startswith("WARNING") for ln in err)
    row["last_line"] = err[-1][:200] if err else ""
    row["imu_lines"] = [ln[:240] for ln in err if "imu.csv" in ln or "IMU" in ln][:3]
    summary = run_dir / "summary.json"
    if proc.returncode in (0, 1) and summary.exists():
        s = json.loads(summary.read_text())
        row["imu_used"] = s.get("imu", {}).get("used")
        row["imu_rate_hz"] = s.get("imu", {}).get("rate_hz")
        row["imu_check"] = s.get("imu_check")
        row["imu_final_factors"] = s.get("imu", {}).get("factors")  # IMU factors, final solve
        row["acceleration_disagreement"] = s.get("imu", {}).get("acceleration_disagreement")
        ate = ate_m(run_dir, data)
        if ate is not None:
            row["ate_m"] = ate
    return row


def markdown(rows: list[dict]) -> str:
    lines = ["| imu.csv | exit | ATE (m) | imu.used | verdict | IMU factors in the final solve "
             "| acceleration disagreement | warnings | last line on stderr |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        check = r.get("imu_check") or {}
        verdict = check.get("verdict", "") if isinstance(check, dict) else ""
        ate = f"{r['ate_m']:.3f}" if "ate_m" in r else "-"
        last = r["last_line"].replace("|", "/")
        dis = r.get("acceleration_disagreement")
        lines.append(f"| {r['what']} | {r['exit']} | {ate} | {r.get('imu_used', '-')} | "
                     f"{verdict} | {r.get('imu_final_factors', '-')} | "
                     f"{'-' if dis is None else f'{dis:.3g}'} | {r['warnings']} | {last} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--json", type=Path, help="Write the rows here too.")
    args = ap.parse_args()
    rows = []
    for case in args.cases.split(","):
        row = run_case(args.seq, args.out, case)
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(markdown(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
