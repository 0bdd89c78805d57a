"""The IMU's clock offset and mounting found from the data (issue 30, item 5), over a grid of
offsets and mountings on simulated hand-held walks.

    python tools/imu_calibration_grid.py SEQ [SEQ...] --out DIR [--cases 0:0,0.2:z90,...]
        [--json FILE]

SEQ: a simulated walk with an IMU (`lidar-slam simulate --motion handheld --imu --out SEQ`,
mounted as its lidar_slam.yaml says). Each case OFFSET:MOUNT rewrites imu.csv as an IMU on a
clock OFFSET s behind the lidar's (stamps minus OFFSET) and turned by MOUNT (none, x90, y90,
z90, x180, z180, xz90: 90 deg about x then z) against the simulated one, into DIR/<seq>/<case>/seq
(the scans linked, no lidar_slam.yaml), then runs `lidar-slam run` twice: with no config (the
offset and the mounting found from the data) and with the true values given (an overlay), and
scores both with `lidar-slam eval` (ATE RMSE). Prints one JSON row per case: the offset found
and its error (ms), the rotation error (deg), the sigmas, the rotation's error after the final
solve refined it, the calibration's window and cost, ATE auto and given, and a markdown table
at the end.

    --draws N  (N >= 2) runs each side N times: once as above, then N - 1 times with its values
    (the true ones; the auto run's estimate, with its refinement prior) given in an overlay,
    each jittered by at most JITTER_S and JITTER_DEG: far below any estimate's error, yet a
    hand-held walk's ATE moves by tens of per cent under such a jitter (a run is one draw of a
    chaotic process: docs/benchmarks/2026-12-05d-imu-calibration.md). The row then carries the
    median, min and max ATE of each side and the ratio of the medians.

    --variants V[,V...]  with --draws: more sides, drawn the same way, to tell what separates
    the two (docs/benchmarks/2026-12-05n-imu-calibration-draws.md): est (the estimate without
    the final solve's refinement), givenref (the true values with the auto run's refinement
    prior), off06 (the true rotation, the offset 0.6 ms off), rot01 (the true offset, the
    rotation 0.1 deg off); each row gains ate_V_median_m and ate_V_ratio (against given's).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

if __package__ in (None, ""):  # run as a script: `tools` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.bad_imu import HEADER, ate_m, cli, link_sequence  # noqa: E402

MOUNTS = {"none": [], "x90": [("x", 90)], "y90": [("y", 90)], "z90": [("z", 90)],
          "x180": [("x", 180)], "z180": [("z", 180)], "xz90": [("x", 90), ("z", 90)]}
DEFAULT_CASES = "0:none,0.2:none,-0.2:none,0.05:z90,-0.137:x180,1600:xz90,0:y90,0.1:z180"
# --draws: the jitter of the values each extra draw is given (s, deg): a fraction of the
# estimates' errors (0.02-0.7 ms, 0.06-0.5 deg on the walks) and of their sigmas.
JITTER_S, JITTER_DEG = 1e-4, 0.02
# --variants: how far off the true values off06 and rot01 are (s; rad, about a fixed axis).
OFF06_S = 6e-4
ROT01_ROTVEC = (0.0, 0.0010, 0.0015)  # 0.103 deg
VARIANTS = ("est", "givenref", "off06", "rot01")


def mount_rotation(name: str) -> np.ndarray:
    """R_new_old: the new IMU frame's axes in the simulated one (extrinsic rotations in order)."""
    R = np.eye(3)
    for axis, deg in MOUNTS[name]:
        R = Rotation.from_euler(axis, deg, degrees=True).as_matrix() @ R
    return R


def make_case(seq: Path, dest: Path, offset_s: float, mount: str) -> np.ndarray:
    """The walk with its IMU on a clock offset_s behind and turned by `mount`; returns the true
    T_lidar_imu of the new IMU (4x4)."""
    link_sequence(seq, dest, skip=("imu.csv", "lidar_slam.yaml"))
    overlay = yaml.safe_load((seq / "lidar_slam.yaml").read_text())["imu"]
    from lidar_slam.config import ImuConfig

    T_lidar_old = ImuConfig(T_lidar_imu=overlay["T_lidar_imu"]).T_lidar_imu_matrix()
    rows = np.loadtxt(seq / "imu.csv", delimiter=",", skiprows=1, ndmin=2)
    R = mount_rotation(mount)  # v_new = R^T v_old... the new frame is the old turned by R
    rows[:, 0] -= offset_s + float(overlay.get("time_offset_s", 0.0))
    rows[:, 1:4] = rows[:, 1:4] @ R  # (R^T w)^T = w^T R
    rows[:, 4:7] = rows[:, 4:7] @ R
    np.savetxt(dest / "imu.csv", rows, delimiter=",", header=HEADER, comments="",
               fmt=["%.9f"] + ["%.10g"] * 6)
    T = T_lidar_old.copy()
    T[:3, :3] = T_lidar_old[:3, :3] @ R
    return T


def run_and_score(data: Path, run_dir: Path, config: Path | None) -> dict:
    args = ["run", str(data), "--out", str(run_dir), "--overwrite"]
    if config is not None:
        args += ["--config", str(config)]
    t0 = time.perf_counter()
    proc = cli(*args)
    out = {"exit": proc.returncode, "wall_s": round(time.perf_counter() - t0, 1)}
    if proc.returncode != 0:
        out["stderr"] = proc.stderr.strip().splitlines()[-1:]
        return out
    out["summary"] = json.loads((run_dir / "summary.json").read_text())
    ate = ate_m(run_dir, data)
    if ate is not None:
        out["ate_m"] = ate
    return out


def jittered(T: np.ndarray, offset_s: float, k: int) -> tuple[np.ndarray, float]:
    """Draw k's values: T_lidar_imu's rotation turned by JITTER_DEG about axis k mod 3 (the
    sign alternating) and the offset moved by +-JITTER_S (alternating, halved every 3 draws)."""
    sign = 1.0 if k % 2 else -1.0
    axis = np.eye(3)[k % 3]
    T = T.copy()
    T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(sign * np.radians(JITTER_DEG) * axis).as_matrix()
    return T, offset_s + sign * JITTER_S / (1 + (k - 1) // 3)


def overlay(path: Path, T: np.ndarray, offset_s: float, sigma_deg: float | None = None) -> Path:
    imu = {"T_lidar_imu": [round(float(v), 12) + 0.0 for v in T.ravel()],
           "time_offset_s": float(offset_s)}
    if sigma_deg is not None:
        imu["T_lidar_imu_sigma_deg"] = float(sigma_deg)
    path.write_text(yaml.safe_dump({"imu": imu}))
    return path


def draws(data: Path, root: Path, side: str, T: np.ndarray, offset_s: float,
          sigma_deg: float | None, n: int, first: float | None) -> dict:
    """ATE median / min / max over `first` (the side's own run) and n - 1 jittered draws."""
    ates = [first]
    for k in range(1, n):
        Tk, dk = jittered(T, offset_s, k)
        cfg = overlay(root / f"{side}_draw{k}.yaml", Tk, dk, sigma_deg)
        ates.append(run_and_score(data, root / f"{side}_draw{k}", cfg).get("ate_m"))
    got = [a for a in ates if a is not None]
    if len(got) < len(ates):
        return {f"ate_{side}_draws_failed": len(ates) - len(got)}
    return {f"ate_{side}_median_m": round(float(np.median(got)), 4),
            f"ate_{side}_min_m": round(min(got), 4), f"ate_{side}_max_m": round(max(got), 4)}


def variant_values(name: str, T_true: np.ndarray, offset_s: float, T_est: np.ndarray,
                   est_offset_s: float, sigma_deg: float | None):
    """(T_lidar_imu, offset, refinement prior sigma) of a --variants side."""
    if name == "est":
        return T_est, est_offset_s, None
    if name == "givenref":
        return T_true, offset_s, sigma_deg
    if name == "off06":
        return T_true, offset_s + OFF06_S, None
    if name == "rot01":
        T = T_true.copy()
        T[:3, :3] = T_true[:3, :3] @ Rotation.from_rotvec(ROT01_ROTVEC).as_matrix()
        return T, offset_s, None
    raise ValueError(f"unknown variant {name!r} (one of {', '.join(VARIANTS)})")


def run_case(seq: Path, out: Path, case: str, n_draws: int = 1,
             variants: tuple[str, ...] = ()) -> dict:
    off_text, mount = case.split(":")
    offset_s = float(off_text)
    root = out / seq.name / case.replace(":", "_")
    data = root / "seq"
    T_true = make_case(seq, data, offset_s, mount)
    given = root / "given.yaml"
    given.write_text(yaml.safe_dump({"imu": {
        "T_lidar_imu": [round(float(v), 9) + 0.0 for v in T_true.ravel()],
        "time_offset_s": offset_s}}))
    auto = run_and_score(data, root / "auto", None)
    told = run_and_score(data, root / "given", given)
    row = {"seq": seq.name, "case": case, "offset_s": offset_s, "mount": mount,
           "ate_auto_m": auto.get("ate_m"), "ate_given_m": told.get("ate_m"),
           "wall_auto_s": auto["wall_s"], "wall_given_s": told["wall_s"]}
    imu = auto.get("summary", {}).get("imu", {})
    cal = imu.get("calibration", {})
    est = cal.get("estimate", {})
    row.update(imu_used=imu.get("used"), reason=imu.get("reason"),
               window_scans=cal.get("window_scans"), window_s=cal.get("window_seconds"))
    if est:
        R = np.array(est["R_lidar_imu"])
        err = Rotation.from_matrix(T_true[:3, :3].T @ R).magnitude()
        row.update(offset_found_s=est["time_offset_s"],
                   offset_error_ms=round(1e3 * (est["time_offset_s"] - offset_s), 3),
                   offset_sigma_ms=est["offset_sigma_ms"],
                   rotation_error_deg=round(float(np.degrees(err)), 3),
                   rotation_sigma_deg=est["rotation_sigma_deg"], correlation=est["correlation"])
    refined = imu.get("T_lidar_imu_refined")
    if refined:  # the final solve's refinement of the rotation found
        R = np.array(refined["T_lidar_imu"]).reshape(4, 4)[:3, :3]
        err = Rotation.from_matrix(T_true[:3, :3].T @ R).magnitude()
        row.update(refined_error_deg=round(float(np.degrees(err)), 3),
                   refine_prior_sigma_deg=refined["prior_sigma_deg"])
    if row["ate_auto_m"] and row["ate_given_m"]:
        row["ate_ratio"] = round(row["ate_auto_m"] / row["ate_given_m"], 3)
    if n_draws > 1 and row["ate_given_m"]:
        row.update(draws(data, root, "given", T_true, offset_s, None, n_draws,
                         row["ate_given_m"]))
    if n_draws > 1 and row["ate_auto_m"] and est:
        T_est = np.eye(4)
        T_est[:3, :3] = np.array(est["R_lidar_imu"])
        # the translation: the config's, none here (the auto run has no config): 0
        sigma = refined["prior_sigma_deg"] if refined else None
        row.update(draws(data, root, "auto", T_est, est["time_offset_s"], sigma, n_draws,
                         row["ate_auto_m"]))
        for name in variants:  # each side's first draw: its values unjittered
            T, off, sig = variant_values(name, T_true, offset_s, T_est, est["time_offset_s"],
                                         sigma)
            first = run_and_score(data, root / f"{name}_draw0",
                                  overlay(root / f"{name}_draw0.yaml", T, off, sig)).get("ate_m")
            row.update(draws(data, root, name, T, off, sig, n_draws, first))
            if row.get(f"ate_{name}_median_m") and row.get("ate_given_median_m"):
                row[f"ate_{name}_ratio"] = round(row[f"ate_{name}_median_m"]
                                                 / row["ate_given_median_m"], 3)
    if row.get("ate_auto_median_m") and row.get("ate_given_median_m"):
        row["ate_median_ratio"] = round(row["ate_auto_median_m"] / row["ate_given_median_m"], 3)
    return row


def markdown(rows: list[dict]) -> str:
    lines = ["| walk | offset (s) | mount | found (s) | error (ms) | sigma (ms) | rotation error "
             "(deg) | sigma (deg) | refined error (deg) | IMU used | window (scans, s) | "
             "ATE auto (m) | ATE given (m) | ratio |", "|---" * 14 + "|"]
    for r in rows:
        def f(key, fmt="{}", r=r):
            v = r.get(key)
            return "-" if v is None else fmt.format(v)
        lines.append(f"| {r['seq']} | {r['offset_s']:g} | {r['mount']} | {f('offset_found_s')} "
                     f"| {f('offset_error_ms')} | {f('offset_sigma_ms')} | "
                     f"{f('rotation_error_deg')} | {f('rotation_sigma_deg')} | "
                     f"{f('refined_error_deg')} | "
                     f"{f('imu_used')} | {f('window_scans')}, {f('window_s')} | "
                     f"{f('ate_auto_m', '{:.3f}')} | {f('ate_given_m', '{:.3f}')} | "
                     f"{f('ate_ratio')} |")
    drawn = [r for r in rows if r.get("ate_median_ratio") is not None]
    if drawn:
        lines += ["", "| walk | case | ATE given: median (min-max) (m) | ATE auto: median "
                  "(min-max) (m) | median ratio |", "|---" * 5 + "|"]
        lines += [f"| {r['seq']} | {r['case']} | {r['ate_given_median_m']:.3f} "
                  f"({r['ate_given_min_m']:.3f}-{r['ate_given_max_m']:.3f}) | "
                  f"{r['ate_auto_median_m']:.3f} ({r['ate_auto_min_m']:.3f}-"
                  f"{r['ate_auto_max_m']:.3f}) | {r['ate_median_ratio']} |" for r in drawn]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqs", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cases", default=DEFAULT_CASES)
    ap.add_argument("--json", type=Path, help="Write the rows here too.")
    ap.add_argument("--draws", type=int, default=1,
                    help="Runs per side (the first as without; the rest given jittered values).")
    ap.add_argument("--variants", default="",
                    help=f"With --draws: more sides, comma-separated ({', '.join(VARIANTS)}).")
    args = ap.parse_args()
    variants = tuple(v for v in args.variants.split(",") if v)
    if variants and args.draws < 2:
        ap.error("--variants needs --draws 2 or more (its sides are drawn as given's are)")
    for v in variants:
        if v not in VARIANTS:
            ap.error(f"unknown variant {v!r} (one of {', '.join(VARIANTS)})")
    rows = []
    for seq in args.seqs:
        for case in args.cases.split(","):
            row = run_case(seq, args.out, case, args.draws, variants)
            print(json.dumps(row), flush=True)
            rows.append(row)
    print(markdown(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
