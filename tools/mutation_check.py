"""Break the code on purpose and see whether the tests notice (issue 32).

Two modes, both on a temporary copy of the repository (the checkout is never touched): the
copy's source text is patched, and pytest runs there with PYTHONPATH on the copy, so the tests
and every process they start (`python -m lidar_slam.cli ...`, the loop worker, Ray) import the
broken code. Nothing in the package reads a switch for this: a break is a change of text.

  python tools/mutation_check.py                  every documented break, its tests, a table
  python tools/mutation_check.py --only NAME ...  some of them (--list names them)
  python tools/mutation_check.py --baseline       the same tests on the unbroken copy (all pass)
  python tools/mutation_check.py --random 40 --seed 0
      40 mutants drawn at random from lidar_slam/{frontend,backend,loop,io}: one operator or
      constant flipped each (< <=, == !=, + -, * /, and or, True False, a number n -> n + 1 or
      2n); each runs the test files that import its module (`-x`, not `slow`, 300 s cap); prints
      the survivors and the survival rate.

The documented breaks (BREAKS below) are listed in docs/design.md, "Breaks the tests must
catch", each beside the promise it breaks and the test that catches it. A break is caught when
pytest fails (a test failing or erroring). A timeout is not a catch, and a break whose text is
no longer in its file (or whose patched file does not compile) is reported as stale: the list
must follow the code. Exit status: 1 when a documented break was not caught.
"""

from __future__ import annotations

import argparse
import ast
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("frontend", "backend", "loop", "io")
IGNORE = shutil.ignore_patterns(".git", ".venv", "runs", "out", "__pycache__", ".pytest_cache",
                                ".hypothesis", "*.egg-info", "build", "*.rrd")


@dataclass(frozen=True)
class Break:
    name: str
    item: str  # the promise (issue 32's item number where it is one)
    path: str
    old: str  # must occur exactly once in path
    new: str
    tests: tuple[str, ...]


BREAKS = [
    # 1: IMU accuracy in the front-end
    Break("imu-prediction-off", "1", "lidar_slam/pipeline.py",
          "odom = self.odometry.step(deskewed, guess)", "odom = self.odometry.step(deskewed, None)",
          ("tests/test_imu_frontend.py::test_imu_deskew_and_prediction_track_a_fast_turning_walk"
           "_at_least_as_well_as_constant_velocity",)),
    Break("imu-deskew-off", "1", "lidar_slam/frontend/deskew.py",
          "        if self.motion is not None:\n            return self.motion.apply",
          "        if False:\n            return self.motion.apply",
          ("tests/test_imu_frontend.py::test_imu_deskew_and_prediction_track_a_fast_turning_walk"
           "_at_least_as_well_as_constant_velocity",)),
    # 2, 3: the final inertial solve
    Break("gravity-alignment-off", "2", "lidar_slam/pipeline.py",
          "        T_gravity_map[:3, :3] = gravity_rotation(T_S_map[:3, :3].T @ [0.0, 0.0, 1.0])",
          "        pass",
          ("tests/test_backend_inertial.py::test_a_run_without_loops_with_imu_and_gnss_is_gravity"
           "_aligned_and_geo_referenced",)),
    Break("imu-factors-off", "3", "lidar_slam/backend/inertial_graph.py",
          "    graph = gtsam.NonlinearFactorGraph()\n    values = gtsam.Values()\n",
          "    graph = gtsam.NonlinearFactorGraph()\n    values = gtsam.Values()\n"
          "    links = []\n",
          ("tests/test_backend_inertial.py::test_imu_factors_take_out_part_of_a_clean_runs_drift",)),
    Break("gnss-gate-open", "gnss", "lidar_slam/backend/gnss.py",
          "CHI2_3_GATE = 16.266", "CHI2_3_GATE = 1e12",
          ("tests/test_backend_inertial.py::test_a_40_m_multipath_jump_is_rejected_and_reported",)),
    # 4: readers on random and valid input
    Break("reader-refuses-every-cloud", "4", "lidar_slam/io/pointcloud.py",
          '    suffix = p.suffix.lower()\n    if suffix == ".bin":',
          '    suffix = p.suffix.lower()\n    raise InputError(p, "refused")\n'
          '    if suffix == ".bin":',
          ("tests/test_readers_properties.py::test_random_pcd_files_are_a_cloud_or_one_error",
           "tests/test_readers_properties.py::test_random_bytes_as_a_scan_file_are_a_cloud_or_one"
           "_error")),
    Break("calib-refuses-every-tr", "4", "lidar_slam/io/trajectory.py",
          "            if nums.size != 12:", "            if nums.size != 13:",
          ("tests/test_readers_properties.py::test_random_calib_files_give_a_rigid_tr_or_one"
           "_error",)),
    Break("times-refuse-two-stamps", "4", "lidar_slam/io/trajectory.py",
          "    if prev_s is not None and not stamp_s > prev_s:",
          "    if prev_s is not None:",
          ("tests/test_readers_properties.py::test_random_kitti_raw_timestamps_increase_or_are"
           "_one_error",
           "tests/test_readers_properties.py::test_random_times_files_give_increasing_stamps_or"
           "_one_error")),
    # 7: per-point time units
    Break("time-unit-us-as-ms", "7", "lidar_slam/io/point_times.py",
          "    return 1e-6 if 1e3 <= span <= 1e6 else 1e-9",
          "    return 1e-3 if 1e3 <= span <= 1e6 else 1e-9",
          ("tests/test_readers.py::test_offsets_written_in_s_us_and_ns_come_back_in_seconds",)),
    Break("time-unit-float-ns-as-us", "7", "lidar_slam/io/point_times.py",
          "        return 1.0 if span <= 2.0 else 1e-6 if span <= 2e6 else 1e-9",
          "        return 1.0 if span <= 2.0 else 1e-6 if span <= 2e9 else 1e-9",
          ("tests/test_readers.py::test_offsets_written_in_s_us_and_ns_come_back_in_seconds",)),
    Break("kitti-tr-not-applied", "kitti", "lidar_slam/io/trajectory.py",
          "    return np.linalg.inv(Tr) @ poses_cam @ Tr", "    return poses_cam",
          ("tests/test_readers.py::test_kitti_layout_reads_lidar_frame_ground_truth",)),
    # 5: covariances and their NEES
    Break("covariance-10x-overconfident", "5", "lidar_slam/frontend/edge_information.py",
          "    info = np.linalg.inv(cov)\n", "    info = 10.0 * np.linalg.inv(cov)\n",
          ("tests/test_covariances.py::test_keyframe_position_nees_on_sample_scans_stays_where"
           "_it_was_measured",)),
    Break("covariance-2.5x-overconfident", "5", "lidar_slam/frontend/edge_information.py",
          "    info = np.linalg.inv(cov)\n", "    info = 2.5 * np.linalg.inv(cov)\n",
          ("tests/test_covariances.py::test_keyframe_position_nees_on_sample_scans_stays_where"
           "_it_was_measured",)),
    Break("nees-without-the-covariance", "5", "tools/bank.py",
          "        out.append(float(e @ np.linalg.solve(P, e)))",
          "        out.append(float(e @ e))",
          ("tests/test_bank.py::test_position_nees_is_3_when_the_errors_follow_the_covariances",)),
    # the front-end's own promises
    Break("refinement-always-off", "refine", "lidar_slam/frontend/odometry.py",
          "        return limit > 0 and float(", "        return limit < 0 and float(",
          ("tests/test_odometry.py::test_slow_scans_refined_against_keyframes_keep_the_turn_kiss"
           "_icp_loses",)),
    Break("refinement-always-on", "refine", "lidar_slam/frontend/odometry.py",
          "        return limit > 0 and float(np.linalg.norm(self.last_delta[:3, 3])) < limit",
          "        return True or float(np.linalg.norm(self.last_delta[:3, 3])) < limit",
          ("tests/test_odometry.py::test_a_fast_car_is_not_refined_and_a_braking_one_is",)),
    Break("deskew-twice", "deskew", "lidar_slam/frontend/deskew.py",
          "        return deskew(points, times_rel_ref, self.T_prev_curr, self.period_s)",
          "        return deskew(deskew(points, times_rel_ref, self.T_prev_curr, self.period_s),"
          " times_rel_ref, self.T_prev_curr, self.period_s)",
          ("tests/test_frontend.py::test_a_scan_is_deskewed_once_by_the_motion_it_was_taken"
           "_in",)),
    Break("imu-mounting-ignored", "imu", "lidar_slam/frontend/imu_prediction.py",
          "        self.T_lidar_imu = cfg.T_lidar_imu_matrix()",
          "        self.T_lidar_imu = np.eye(4)",
          ("tests/test_imu_frontend.py::test_a_rotated_and_offset_imu_gives_the_poses_of_an_imu"
           "_at_the_lidar",)),
    # loops
    Break("loop-fitness-gate-open", "loops", "lidar_slam/loop/verify.py",
          "    if fitness < cfg.min_fitness:", "    if fitness < -1.0:",
          ("tests/test_verify.py::test_wrong_places_are_never_accepted_with_a_wrong_pose",)),
    Break("loops-never-accepted", "loops", "lidar_slam/loop/verify.py",
          "    if fitness < cfg.min_fitness:", "    if fitness < 2.0:",
          ("tests/test_verify.py::test_true_loops_are_accepted_with_the_reference_relative_pose",)),
    # 8: always-true asserts made real
    Break("loop-worker-outlives-its-run", "8", "lidar_slam/loop/worker.py",
          '    if sys.platform.startswith("linux"):\n        try:\n            libc',
          '    return\n    if sys.platform.startswith("linux"):\n        try:\n            libc',
          ("tests/test_signals.py::test_the_loop_worker_dies_with_a_killed_run",)),
    Break("sim-imu-without-bias", "8", "lidar_slam/sim/imu_gnss.py",
          "        return truth + bias + white, bias", "        return truth + white, bias",
          ("tests/test_sim_imu.py::test_simulate_imu_noise_has_the_bmi088_white_noise_and_a_slow"
           "_bias",)),
    Break("zero-range-refused", "8", "lidar_slam/config.py",
          "    min_range_m: NonNegative", "    min_range_m: Positive",
          ("tests/test_config.py::test_zero_where_zero_means_off_is_accepted",)),
    Break("shipped-config-ignored", "8", "lidar_slam/config.py",
          "    data = _read_overlay(Path(path)) if path is not None else {}", "    data = {}",
          ("tests/test_config.py::test_shipped_configs_load",)),
    Break("deskew-off", "8", "lidar_slam/config.py",
          "    deskew: bool = True", "    deskew: bool = False",
          ("tests/test_readme.py",)),
    # 9: reruns byte for byte
    Break("kiss-icp-on-every-thread", "9", "lidar_slam/config.py",
          "    max_num_threads: NonNegativeInt = 1", "    max_num_threads: NonNegativeInt = 0",
          ("tests/test_cli.py::test_two_runs_write_identical_files",)),
    Break("kiss-icp-on-every-thread-imu", "9", "lidar_slam/config.py",
          "    max_num_threads: NonNegativeInt = 1", "    max_num_threads: NonNegativeInt = 0",
          ("tests/test_cli.py::test_two_runs_with_an_imu_write_identical_files",)),
]


def copy_repo(dest: Path) -> Path:
    """dest/<repo name> with the tracked tree (no venv, no runs); dest/shared -> the checkout's
    ../shared, which the tests read."""
    root = dest / REPO.name
    shutil.copytree(REPO, root, ignore=IGNORE, symlinks=True)
    shared = REPO.parent / "shared"
    if shared.exists():
        (dest / "shared").symlink_to(shared.resolve())
    return root


def apply(root: Path, path: str, old: str, new: str) -> str | None:
    """Patch root/path (old, exactly once, -> new); None, or why it could not be done."""
    f = root / path
    text = f.read_text()
    n = text.count(old)
    if n != 1:
        return f"{path}: the text to replace occurs {n} times (stale break)"
    text = text.replace(old, new)
    try:
        compile(text, str(f), "exec")
    except SyntaxError as exc:
        return f"{path}: the patched file does not compile ({exc.msg}, line {exc.lineno})"
    f.write_text(text)
    return None


def run_tests(root: Path, tests: list[str], timeout_s: float, extra: list[str] = ()
              ) -> tuple[str, float, str]:
    """pytest in the copy: ('failed' | 'passed' | 'timeout' | 'none', seconds, last line)."""
    env = dict(os.environ, PYTHONPATH=str(root), PYTHONDONTWRITEBYTECODE="1")
    env.pop("PYTEST_ADDOPTS", None)
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
           "-o", "addopts=", *extra, *tests]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # pytest and whatever it started
        proc.communicate()
        return "timeout", time.perf_counter() - t0, f"over {timeout_s:.0f} s"
    finally:
        try:  # a loop worker or Ray daemon left behind by a broken run
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    dt = time.perf_counter() - t0
    lines = [ln for ln in stdout.splitlines() if ln.strip()]
    last = lines[-1] if lines else stderr.strip()[-200:]
    if proc.returncode == 5:
        return "none", dt, last  # no test collected: the break's test names are stale
    return ("passed" if proc.returncode == 0 else "failed"), dt, last


def check_imports_copy(root: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(root))
    out = subprocess.run([sys.executable, "-c", "import lidar_slam; print(lidar_slam.__file__)"],
                         cwd=root, env=env, capture_output=True, text=True, check=True)
    if not out.stdout.strip().startswith(str(root)):
        sys.exit(f"mutation_check: the copy's lidar_slam is not the one imported "
                 f"({out.stdout.strip()})")


def documented(names: list[str], baseline: bool, timeout_s: float) -> int:
    chosen = [b for b in BREAKS if not names or b.name in names]
    unknown = set(names) - {b.name for b in BREAKS}
    if unknown:
        sys.exit(f"mutation_check: no break named {', '.join(sorted(unknown))} (--list)")
    survived = []
    print(f"{'break':32s} {'item':7s} {'result':9s} {'s':>6s}  tests")
    for b in chosen:
        with tempfile.TemporaryDirectory(prefix="mutation-") as tmp:
            root = copy_repo(Path(tmp))
            check_imports_copy(root)
            why = None if baseline else apply(root, b.path, b.old, b.new)
            if why:
                result, dt, last = "STALE", 0.0, why
            else:
                state, dt, last = run_tests(root, list(b.tests), timeout_s)
                if baseline:
                    result = {"passed": "passes", "failed": "FAILS"}.get(state, state.upper())
                else:
                    result = {"failed": "caught", "passed": "SURVIVED", "timeout": "TIMEOUT",
                              "none": "STALE"}[state]
        if result not in ("caught", "passes"):
            survived.append(b.name)
        names = ", ".join(t.split("::")[-1] for t in b.tests)
        print(f"{b.name:32s} {b.item:7s} {result:9s} {dt:6.0f}  {names}\n{'':50s}({last[:110]})",
              flush=True)
    what = "not passing unbroken" if baseline else "survived or stale"
    print(f"\n{len(chosen) - len(survived)} of {len(chosen)} "
          f"{'pass unbroken' if baseline else 'caught'}; {what}: {', '.join(survived) or 'none'}")
    return 1 if survived else 0


# ---------------------------------------------------------------------------- random mutants
FLIPS = {ast.Lt: "<=", ast.LtE: "<", ast.Gt: ">=", ast.GtE: ">", ast.Eq: "!=", ast.NotEq: "==",
         ast.Add: "-", ast.Sub: "+", ast.Mult: "/", ast.Div: "*", ast.And: "or", ast.Or: "and"}
SYMBOL = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!=",
          ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.And: "and", ast.Or: "or"}


@dataclass(frozen=True)
class Mutant:
    path: str
    line: int
    col: int  # 0-based offset of `old` in the line
    old: str
    new: str

    def describe(self) -> str:
        return f"{self.path}:{self.line}: {self.old!r} -> {self.new!r}"


def _docstring_lines(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            body = getattr(node, "body", [])
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.update(range(body[0].lineno, body[0].end_lineno + 1))
    return out


def mutants_of(path: Path) -> list[Mutant]:
    """Every single-token flip in the file (operators between their operands, True/False,
    numbers) outside docstrings, log calls and annotations."""
    rel = str(path.relative_to(REPO))
    text = path.read_text()
    lines = text.splitlines()
    tree = ast.parse(text)
    skip = _docstring_lines(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                node.func.attr in ("debug", "info", "warning", "error", "exception"):
            skip.update(range(node.lineno, node.end_lineno + 1))
        if isinstance(node, (ast.AnnAssign, ast.arg)) and getattr(node, "annotation", None):
            a = node.annotation
            skip.update(range(a.lineno, a.end_lineno + 1))
    out: list[Mutant] = []

    def token_between(left: ast.AST, right: ast.AST, sym: str, new: str) -> None:
        if left.end_lineno != right.lineno or left.end_lineno in skip:
            return
        line = lines[left.end_lineno - 1]
        seg = line[left.end_col_offset:right.col_offset]
        # the operator alone between its operands (brackets and spaces around it)
        m = re.fullmatch(r"[\s)]*(" + re.escape(sym) + r")[\s(]*", seg)
        if m and not (sym in "<>" and "=" in seg):
            out.append(Mutant(rel, left.end_lineno, left.end_col_offset + m.start(1), sym, new))

    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            ops = [node.left, *node.comparators]
            for op, a, b in zip(node.ops, ops, ops[1:]):
                if type(op) in FLIPS:
                    token_between(a, b, SYMBOL[type(op)], FLIPS[type(op)])
        elif isinstance(node, ast.BinOp) and type(node.op) in FLIPS:
            token_between(node.left, node.right, SYMBOL[type(node.op)], FLIPS[type(node.op)])
        elif isinstance(node, ast.BoolOp) and type(node.op) in FLIPS:
            for a, b in zip(node.values, node.values[1:]):
                token_between(a, b, SYMBOL[type(node.op)], FLIPS[type(node.op)])
        elif isinstance(node, ast.Constant) and node.lineno not in skip and \
                node.lineno == node.end_lineno:
            src = lines[node.lineno - 1][node.col_offset:node.end_col_offset]
            if isinstance(node.value, bool):
                out.append(Mutant(rel, node.lineno, node.col_offset, src, str(not node.value)))
            elif isinstance(node.value, (int, float)) and re.fullmatch(r"[\d._eE+-]+", src):
                v = node.value
                new = repr(v + 1) if isinstance(v, int) else repr(2.0 * v if v else 1.0)
                out.append(Mutant(rel, node.lineno, node.col_offset, src, new))
    return out


def tests_importing(path: Path) -> list[str]:
    """Test files that import the mutated module by name."""
    mod = ".".join(path.relative_to(REPO).with_suffix("").parts)
    pkg, name = mod.rsplit(".", 1)
    pat = re.compile(rf"\b{re.escape(mod)}\b|from {re.escape(pkg)} import [^\n]*\b{name}\b")
    return sorted(str(p.relative_to(REPO)) for p in (REPO / "tests").glob("test_*.py")
                  if pat.search(p.read_text()))


def random_mode(n: int, seed: int, timeout_s: float) -> int:
    files = sorted(p for pkg in PACKAGES for p in (REPO / "lidar_slam" / pkg).rglob("*.py"))
    pool = [(m, f) for f in files for m in mutants_of(f) if tests_importing(f)]
    rng = random.Random(seed)
    sample = rng.sample(pool, min(n, len(pool)))
    print(f"{len(pool)} mutants in lidar_slam/{{{','.join(PACKAGES)}}} (modules some test "
          f"imports); {len(sample)} drawn with seed {seed}")
    survived, undecided, counted = [], [], 0
    for i, (m, f) in enumerate(sample, 1):
        tests = tests_importing(f)
        with tempfile.TemporaryDirectory(prefix="mutation-") as tmp:
            root = copy_repo(Path(tmp))
            target = root / m.path
            lines = target.read_text().splitlines(keepends=True)
            ln = lines[m.line - 1]
            lines[m.line - 1] = ln[:m.col] + m.new + ln[m.col + len(m.old):]
            target.write_text("".join(lines))
            try:
                compile(target.read_text(), str(target), "exec")
            except SyntaxError:
                print(f"[{i}] skipped (does not compile): {m.describe()}")
                continue
            state, dt, last = run_tests(root, tests, timeout_s, ["-m", "not slow"])
        verdict = {"failed": "killed", "passed": "SURVIVED", "timeout": "undecided",
                   "none": "no tests"}[state]
        if state == "timeout":
            undecided.append(m)
        elif state in ("passed", "failed"):
            counted += 1
            if state == "passed":
                survived.append(m)
        print(f"[{i}] {verdict:10s} {dt:5.0f} s  {m.describe()}  ({len(tests)} test files)",
              flush=True)
    rate = len(survived) / counted if counted else 0.0
    print(f"\nsurvived {len(survived)} of {counted} decided ({100 * rate:.0f} %); "
          f"{len(undecided)} undecided (their tests ran over {timeout_s:.0f} s):")
    for m in survived:
        print("  survived   " + m.describe())
    for m in undecided:
        print("  undecided  " + m.describe())
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", default=[], metavar="NAME")
    ap.add_argument("--list", action="store_true", help="name the documented breaks")
    ap.add_argument("--baseline", action="store_true",
                    help="run each break's tests on the unbroken copy (they must pass)")
    ap.add_argument("--random", type=int, default=0, metavar="N",
                    help="N random mutants instead of the documented breaks")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout-s", type=float, default=600.0)
    a = ap.parse_args(argv)
    if a.list:
        for b in BREAKS:
            print(f"{b.name:32s} {b.item:7s} {b.path}")
        return 0
    if a.random:
        return random_mode(a.random, a.seed, min(a.timeout_s, 300.0))
    return documented(a.only, a.baseline, a.timeout_s)


if __name__ == "__main__":
    sys.exit(main())
