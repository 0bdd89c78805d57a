"""Kill a run anywhere, resume it, and check it ends as if never killed.

Usage: python tools/kill_anywhere.py --out DIR [--data sample_scans] [--kills 10] [--seed 0]
                                     [--every 5]

1. `lidar-slam run DATA` once uninterrupted (DIR/full), with `odometry.max_num_threads: 1`
   (every byte reproducible) and a checkpoint every --every keyframes (DIR/config.yaml). Its
   wall time T is measured, and when it had streamed each odometry line.
2. The same run in DIR/killed-1, started with --resume (which starts afresh in an empty
   folder), SIGKILLed, resumed with --resume and killed again, --kills times, then resumed to
   the end. The kill points are --kills seeded uniform times t_1 < ... < t_N in (0, T) of the
   uninterrupted run, so they fall in start-up, processing, checkpoint writes and the final
   outputs alike. A point is turned into progress, robust to the machine's speed: the
   uninterrupted run had streamed f odometry lines at t_k, t_k - tau(f) s before; attempt k is
   killed that long after it has streamed f lines (a resumed run first rewrites the lines of
   its checkpoint, so a point at or before the checkpoint lands in its restore; a point before
   the first line, that long after the attempt started). The whole
   process group is killed (the loop worker process too), and checked to be gone.
   An attempt that ends before its kill must exit 0 and finishes the run; the point is then
   tried again (its delay halved) in another run from scratch (DIR/killed-2, ...).
3. Every finished killed run is compared with the uninterrupted one: the largest position
   difference of poses_kitti.txt over all frames (must be <= --tol-m, default 1e-6 m) and
   loops.csv (the same candidates with the same decisions).

Prints one line per attempt and the comparison, writes DIR/kill_anywhere.json, and exits 1 on
a mismatch (or an attempt that failed on its own). No process of the runs is left afterwards.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidar_slam.io.trajectory import read_kitti_poses  # noqa: E402 (after the sys.path line)


def _members(pgid: int) -> list[int]:
    """Live (not zombie) processes of process group pgid."""
    out = []
    for p in psutil.process_iter(["status"]):
        try:
            if os.getpgid(p.pid) == pgid and p.info["status"] != psutil.STATUS_ZOMBIE:
                out.append(p.pid)
        except (ProcessLookupError, psutil.Error):
            pass
    return out


def _kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL the run's whole process group and wait until none of it is left."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()
    deadline = time.monotonic() + 10
    while (left := _members(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    if left:
        raise RuntimeError(f"processes {left} of the killed run outlived SIGKILL")


class Attempts:
    """Starts `lidar-slam run` attempts in process groups of their own, logs kept in DIR/logs."""

    def __init__(self, data: Path, config: Path, logs: Path):
        self.data, self.config, self.logs = data, config, logs
        logs.mkdir(parents=True, exist_ok=True)
        self.n = 0
        self.running: subprocess.Popen | None = None

    def start(self, out: Path, *flags: str) -> subprocess.Popen:
        self.n += 1
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
        with open(self.logs / f"attempt-{self.n:02d}.txt", "w") as log:
            self.running = subprocess.Popen(
                [sys.executable, "-m", "lidar_slam.cli", "run", str(self.data), "--out",
                 str(out), "--config", str(self.config), *flags], stdout=log,
                stderr=subprocess.STDOUT, env=env, start_new_session=True)
        return self.running

    def last_line(self) -> str:
        lines = (self.logs / f"attempt-{self.n:02d}.txt").read_text().strip().splitlines()
        return lines[-1] if lines else ""

    def close(self) -> None:
        if self.running is not None:
            _kill_group(self.running)
            self.running = None


def _checkpoint_frames(run: Path) -> int:
    """Frames the run's checkpoint holds (0 without one)."""
    try:
        return int(json.loads((run / "checkpoint" / "manifest.json").read_text())
                   .get("frames") or 0)
    except (OSError, ValueError):
        return 0


def _loops(run: Path) -> list[list[str]]:
    """loops.csv rows without the measured numbers: frames, decision and reason."""
    rows = [r.split(",") for r in (run / "loops.csv").read_text().splitlines()[1:]]
    return [[r[0], r[1], r[6], r[7], r[-1]] for r in rows]


def compare(full: Path, run: Path) -> dict:
    """The killed run against the uninterrupted one."""
    A, B = read_kitti_poses(full / "poses_kitti.txt"), read_kitti_poses(run / "poses_kitti.txt")
    same_frames = len(A) == len(B)
    dp = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1) if same_frames else np.array([np.inf])
    la, lb = _loops(full), _loops(run)
    return {"frames": [len(A), len(B)], "max_position_diff_m": float(dp.max()),
            "worst_frame": int(dp.argmax()), "loops": [len(la), len(lb)],
            "loops_accepted": [sum(r[2] == "1" for r in la), sum(r[2] == "1" for r in lb)],
            "same_loops": la == lb,
            "loops_only_full": [r for r in la if r not in lb][:5],
            "loops_only_killed": [r for r in lb if r not in la][:5]}


def _lines(path: Path, stale_ns: int | None) -> int:
    """Odometry lines in path, or -1 while it is absent or still the file of an earlier attempt
    (modified at stale_ns; an attempt truncates it when it opens it)."""
    try:
        if path.stat().st_mtime_ns == stale_ns:
            return -1
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return -1


def _mtime_ns(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return None


def _attempt(proc: subprocess.Popen, odo: Path, stale_ns: int | None, lines: int,
             delay_s: float, timeout_s: float) -> bool:
    """Wait until the attempt has streamed `lines` odometry lines (from its start when 0), then
    delay_s more; True when it is still running then (to be killed), False when it ended
    first."""
    deadline = time.monotonic() + timeout_s
    while lines and proc.poll() is None and _lines(odo, stale_ns) < lines:  # 0: from the start
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {lines} odometry lines in {odo} after {timeout_s:.0f} s")
        time.sleep(0.002)
    if proc.poll() is not None:
        return False
    try:
        proc.wait(timeout=delay_s)
        return False
    except subprocess.TimeoutExpired:
        return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO / "sample_scans")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=int, default=5, help="checkpoint every this many keyframes")
    ap.add_argument("--tol-m", type=float, default=1e-6)
    ap.add_argument("--timeout-s", type=float, default=600, help="per attempt")
    args = ap.parse_args(argv)

    args.out.mkdir(parents=True, exist_ok=True)
    config = args.out / "config.yaml"
    config.write_text(f"odometry:\n  max_num_threads: 1\ncheckpoint:\n  every_keyframes: "
                      f"{args.every}\n")
    attempts = Attempts(args.data.resolve(), config, args.out / "logs")
    rng = np.random.default_rng(args.seed)
    report: dict = {"seed": args.seed, "kills": [], "runs": []}
    try:
        full = args.out / "full"
        shutil.rmtree(full, ignore_errors=True)
        t0 = time.monotonic()
        proc = attempts.start(full, "--overwrite")
        odo, reached = full / "odometry_kitti.txt", [0.0]  # reached[f]: f lines streamed (s)
        while proc.poll() is None:
            n = _lines(odo, None)
            reached += [time.monotonic() - t0] * (n + 1 - len(reached))
            time.sleep(0.002)
        total_s = time.monotonic() - t0
        attempts.close()
        if proc.returncode != 0:
            print(f"uninterrupted run failed: {attempts.last_line()}")
            return 1
        n_frames = len(read_kitti_poses(full / "poses_kitti.txt"))
        reached = reached[: n_frames + 1] + [total_s] * (n_frames + 1 - len(reached))
        report.update(uninterrupted_s=round(total_s, 3), first_line_s=round(reached[1], 3),
                      last_line_s=round(reached[-1], 3), frames=n_frames)
        print(f"uninterrupted: {n_frames} frames in {total_s:.2f} s (odometry lines from "
              f"{reached[1]:.2f} s to {reached[-1]:.2f} s)")
        points = [float(t) for t in sorted(rng.uniform(0, total_s, args.kills))]
        report["kill_points_s"] = [round(t, 3) for t in points]

        ok, chain, halved = True, 0, 0
        while len(report["kills"]) < args.kills:
            chain += 1
            run = args.out / f"killed-{chain}"
            shutil.rmtree(run, ignore_errors=True)
            odo = run / "odometry_kitti.txt"
            while True:
                frames = _checkpoint_frames(run)
                k = len(report["kills"])
                kill = k < args.kills
                t = points[k] if kill else total_s
                lines = max(f for f in range(n_frames + 1) if reached[f] <= t)
                delay_s = (t - reached[lines]) / 2 ** halved
                stale = _mtime_ns(odo)
                proc = attempts.start(run, "--resume")
                if kill and _attempt(proc, odo, stale, lines, delay_s, args.timeout_s):
                    attempts.close()
                    after = _checkpoint_frames(run)
                    report["kills"].append({"run": chain, "attempt": attempts.n, "point_s":
                                            round(t, 3), "from_frame": frames, "after_lines":
                                            lines, "delay_s": round(delay_s, 3),
                                            "checkpoint_frame_after": after})
                    print(f"attempt {attempts.n}: point {t:.2f} s: resumed from frame {frames}, "
                          f"SIGKILL {delay_s:.3f} s after odometry line {lines}; checkpoint "
                          f"now at frame {after}")
                    halved = 0
                    continue
                try:
                    proc.wait(timeout=args.timeout_s)
                except subprocess.TimeoutExpired:
                    print(f"attempt {attempts.n}: still running after {args.timeout_s:.0f} s")
                    return 1
                attempts.close()
                if proc.returncode != 0:
                    print(f"attempt {attempts.n} (resumed from frame {frames}) failed with exit "
                          f"code {proc.returncode}: {attempts.last_line()}")
                    return 1
                if kill:
                    halved += 1
                    print(f"attempt {attempts.n}: point {t:.2f} s: resumed from frame {frames}, "
                          f"finished before its kill; the point again in a new run")
                else:
                    print(f"attempt {attempts.n}: resumed from frame {frames}, finished")
                break
            result = compare(full, run)
            result["run"] = chain
            report["runs"].append(result)
            good = (result["max_position_diff_m"] <= args.tol_m and result["same_loops"]
                    and result["frames"][0] == result["frames"][1])
            ok &= good
            print(f"{run.name}: {result['frames'][1]} frames, largest position difference "
                  f"{result['max_position_diff_m']:.3g} m (frame {result['worst_frame']}), loops "
                  f"{result['loops'][1]} ({result['loops_accepted'][1]} accepted) vs "
                  f"{result['loops'][0]} ({result['loops_accepted'][0]}): "
                  f"{'same' if result['same_loops'] else 'DIFFERENT'} -> "
                  f"{'ok' if good else 'MISMATCH'}")
            if not result["same_loops"]:
                print(f"  only uninterrupted: {result['loops_only_full']}; "
                      f"only killed: {result['loops_only_killed']}")
        report["ok"] = ok
        (args.out / "kill_anywhere.json").write_text(json.dumps(report, indent=1) + "\n")
        print(f"{len(report['kills'])} kills in {chain} run(s): {'ok' if ok else 'MISMATCH'}")
        return 0 if ok else 1
    finally:
        attempts.close()


if __name__ == "__main__":
    sys.exit(main())
