"""`lidar-slam batch` (many sequences on Ray, one results table) and `simulate` with several
pose files. Five tiny sequences (three slices of sample_scans, a simulated one, a corrupt one)
keep Ray's start-up the main cost: one batch with Ray embedded; the same batch on a separate
local cluster (`ray start --head`, stopped at the end by process id), interrupted with SIGINT
and run again."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
from conftest import SHARED_DATA, require_ray, shared_path

from lidar_slam.batch.results import COLUMNS

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_scans"
SLICES = {"a": (0, 20), "b": (25, 45), "c": (50, 71)}
OK_NAMES = ["a", "b", "c", "sim"]
# The same thread count as a batch task (--cpus-per-run 1): the same poses, bit for bit.
SAME_FILES = ("poses_kitti.txt", "poses_tum.txt", "odometry_kitti.txt", "loops.csv", "graph.g2o")


def lidar_slam(*args, env=None, timeout=600):
    full = {**os.environ, "LIDAR_SLAM_PROGRESS_S": "1", **(env or {})}
    return subprocess.run([sys.executable, "-m", "lidar_slam.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=full)


def kitti_slice(dst: Path, first: int, stop: int, copy: bool = False) -> Path:
    """Scans first..stop-1 of sample_scans as a KITTI-layout sequence of their own."""
    for sub in ("velodyne", "velodyne_times"):
        (dst / sub).mkdir(parents=True)
        for k, i in enumerate(range(first, stop)):
            src, out = SAMPLE / sub / f"{i:06d}.bin", dst / sub / f"{k:06d}.bin"
            shutil.copyfile(src, out) if copy else out.symlink_to(src)
    for name in ("times.txt", "poses.txt"):
        lines = (SAMPLE / name).read_text().splitlines()[first:stop]
        (dst / name).write_text("\n".join(lines) + "\n")
    shutil.copyfile(SAMPLE / "calib.txt", dst / "calib.txt")
    return dst


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> list[Path]:
    """a, b, c: slices of sample_scans; sim: 20 simulated VLP-16 scans along its poses;
    corrupt: a slice whose 7th scan is cut short (the run stops there: an error row)."""
    root = tmp_path_factory.mktemp("inputs")
    seqs = [kitti_slice(root / name, *span) for name, span in SLICES.items()]
    sim = lidar_slam("simulate", SAMPLE / "poses.txt", "--calib", SAMPLE / "calib.txt",
                     "--times", SAMPLE / "times.txt", "--out", root / "sim", "--start", 10,
                     "--n-scans", 20, "--sensor", "vlp16")
    assert sim.returncode == 0, sim.stderr
    corrupt = kitti_slice(root / "corrupt", 0, 12, copy=True)
    scan = corrupt / "velodyne" / "000006.bin"
    scan.write_bytes(scan.read_bytes()[:1000])
    return [*seqs, root / "sim", corrupt]


def read_table(out: Path) -> list[dict]:
    with (out / "results.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(COLUMNS)
    return rows


@pytest.fixture(scope="module")
def embedded(inputs, tmp_path_factory) -> dict:
    """The five sequences with Ray embedded (no --address), no terminal."""
    require_ray()
    out = tmp_path_factory.mktemp("batch") / "B"
    proc = lidar_slam("batch", *inputs, "--out", out, "--workers", 2, env={"CI": "true"})
    return {"out": out, "proc": proc, "table": read_table(out)}


@pytest.mark.cluster
def test_batch_rows_and_run_folders_match_run(embedded, inputs, tmp_path):
    """Four rows with metrics, one error row, exit code 1 with a one-line summary; each run
    folder holds what `lidar-slam run` writes at the same thread count, the same poses, loops
    and graph."""
    proc, out = embedded["proc"], embedded["out"]
    assert proc.returncode == 1, proc.stderr
    table = embedded["table"]
    assert [r["sequence"] for r in table] == ["a", "b", "c", "sim", "corrupt", "TOTAL"]
    rows = {r["sequence"]: r for r in table}
    for name in OK_NAMES:
        row = rows[name]
        assert row["status"] == "ok" and row["message"] == "" and int(row["frames"]) > 0, row
        # < 100 m of path each: ATE, no KITTI drift
        assert 0.0 < float(row["ate_m"]) < 1.0 and row["t_err_pct"] == "", row
        assert float(row["fps"]) > 0 and float(row["peak_rss_mb"]) > 50, row
    bad = rows["corrupt"]
    assert bad["status"] == "error" and "000006.bin" in bad["message"], bad
    assert bad["frames"] == "6" and bad["ate_m"] == ""  # the frames before the bad scan
    total = rows["TOTAL"]
    assert total["status"] == "error" and total["message"] == "4 ok, 1 failed"
    assert int(total["frames"]) == 81 and float(total["fps"]) > 0
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("lidar-slam: error")]
    assert errors == ["lidar-slam: error: 1 of 5 sequences failed, 4 ok (see "
                      f"{out / 'results.md'})"], proc.stderr
    assert "Traceback" not in proc.stderr
    # progress without a terminal: done / running / failed and frames/s, as lines
    assert re.search(r"batch: \d/5 done, \d failed, \d running, \d queued; \d+ frames, "
                     r"[\d.]+ frames/s", proc.stderr), proc.stderr
    assert "batch: sim: ok, 20 frames" in proc.stderr
    assert "| sequence | status | message |" in proc.stdout
    md = (out / "results.md").read_text()
    assert md.startswith("| " + " | ".join(COLUMNS) + " |")
    doc = json.loads((out / "results.json").read_text())
    assert doc["columns"] == list(COLUMNS) and doc["rows"][-1]["sequence"] == "TOTAL"

    config = tmp_path / "threads.yaml"
    config.write_text("odometry:\n  max_num_threads: 1\n")
    runs = {data: subprocess.Popen(  # the four at once: the machine has idle time to fill
        [sys.executable, "-m", "lidar_slam.cli", "run", str(data), "--out",
         str(tmp_path / data.name), "--config", str(config)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for data in inputs[:4]}
    for data, run in runs.items():
        assert run.wait(timeout=600) == 0, run.stderr.read()
        ref, got = tmp_path / data.name, out / data.name
        files = sorted(str(p.relative_to(ref)) for p in ref.rglob("*"))
        assert files == sorted(str(p.relative_to(got)) for p in got.rglob("*"))
        for name in SAME_FILES:
            assert (got / name).read_bytes() == (ref / name).read_bytes(), (data.name, name)


def _stop_cluster(temp_dir: str, gcs: str | None) -> None:
    """Stop every process of the test's cluster, found by its temp dir or GCS address in the
    command line, and their children: by process id (`ray stop` would stop every Ray on the
    machine)."""
    me = {os.getpid(), *(p.pid for p in psutil.Process().parents())}
    keys = [k for k in (temp_dir, gcs) if k]
    found = set()
    for p in psutil.process_iter(["cmdline"]):
        try:
            if p.pid not in me and any(k in a for k in keys for a in p.info["cmdline"] or ()):
                found.add(p)
                found.update(p.children(recursive=True))
        except psutil.Error:
            pass
    for p in found:
        try:
            p.terminate()
        except psutil.Error:
            pass
    _, alive = psutil.wait_procs(list(found), timeout=5)
    for p in alive:
        try:
            p.kill()
        except psutil.Error:
            pass


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def ray_cluster():
    """A separate one-node cluster on this machine, as `ray start --head` makes it; yields
    its address."""
    require_ray()
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths are limited
    gcs = None
    try:
        # Free ports for the two that Ray fixes by default, so that a second cluster on the
        # machine (another test run) does not stop this one from starting.
        client_port, agent_port = free_port(), free_port()
        proc = subprocess.run(
            [str(Path(sys.executable).with_name("ray")), "start", "--head", "--num-cpus", "2",
             "--node-ip-address", "127.0.0.1", "--port", "0", "--include-dashboard", "false",
             "--ray-client-server-port", str(client_port), "--dashboard-agent-listen-port",
             str(agent_port), "--temp-dir", temp, "--disable-usage-stats"],
            capture_output=True, text=True, timeout=300)
        found = re.search(r"ray start --address='([^']+)'", proc.stdout + proc.stderr)
        gcs = found.group(1) if found else None
        assert proc.returncode == 0 and gcs, proc.stdout + proc.stderr
        yield gcs
    finally:
        _stop_cluster(temp, gcs)
        shutil.rmtree(temp, ignore_errors=True)


def pinned(gcs: str) -> dict:
    """Environment that makes `--address auto` mean this test's cluster even where another
    one runs on the machine (RAY_ADDRESS comes first; with an address given, Ray reads its
    token only with RAY_AUTH_MODE=token)."""
    return {"RAY_ADDRESS": gcs, "RAY_AUTH_MODE": "token"}


def launch_batch(args: list, out: Path, env: dict) -> subprocess.Popen:
    """A batch in a session of its own, SIGINT not ignored: as a command in a terminal."""
    return subprocess.Popen(
        [sys.executable, "-m", "lidar_slam.cli", "batch", *map(str, args), "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, "LIDAR_SLAM_PROGRESS_S": "1", **env},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _finished(summary: Path) -> bool:
    """A run that ended at its input's end: a run stopped by the Ctrl-C writes its summary.json
    too, saying so (it made this test fail whenever the signal caught a second job mid-run)."""
    if not summary.is_file():
        return False
    doc = json.loads(summary.read_text())
    return not (doc.get("interrupted") or doc.get("stopped_by_error"))


@pytest.fixture(scope="module")
def on_cluster(inputs, ray_cluster, tmp_path_factory) -> dict:
    """The same batch on the separate cluster (--address auto): Ctrl-C (SIGINT to the
    command's process group, as a terminal sends it) once a sequence has finished, then the
    same command again."""
    out = tmp_path_factory.mktemp("cluster") / "C"
    args = [*inputs, "--address", "auto"]
    proc = launch_batch(args, out, pinned(ray_cluster))
    try:
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            if any((out / n / "summary.json").is_file() for n in OK_NAMES):
                break
            time.sleep(0.1)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert (out / "results.csv").is_file(), stderr
    first = {"returncode": proc.returncode, "stdout": stdout, "stderr": stderr,
             "table": read_table(out),
             "mtimes": {n: (out / n / "summary.json").stat().st_mtime_ns for n in OK_NAMES
                        if _finished(out / n / "summary.json")}}
    again = lidar_slam("batch", *args, "--out", out, env=pinned(ray_cluster))
    return {"out": out, "first": first, "again": again, "table": read_table(out)}


@pytest.mark.cluster
def test_sigint_stops_the_batch_and_keeps_finished_runs(on_cluster):
    first = on_cluster["first"]
    assert first["returncode"] == 130, first["stderr"]
    assert "Traceback" not in first["stderr"]
    last = first["stderr"].strip().splitlines()[-1]
    assert last.startswith("lidar-slam: error: interrupted;") and "re-run" in last, last
    rows = {r["sequence"]: r for r in first["table"]}
    finished = sorted(n for n in OK_NAMES if rows[n]["status"] == "ok")
    # every run the table calls ok finished; one may finish as the signal lands, its result
    # not back yet (its row "interrupted"): the rerun skips it all the same (next test)
    assert finished and set(finished) <= set(first["mtimes"]), rows
    assert any("interrupted" in r["message"] for r in rows.values()), rows


@pytest.mark.cluster
def test_rerun_skips_finished_runs_and_totals_count_them(on_cluster):
    first, again = on_cluster["first"], on_cluster["again"]
    assert again.returncode == 1, again.stderr
    rows = {r["sequence"]: r for r in on_cluster["table"]}
    skipped = [n for n in OK_NAMES if rows[n]["message"] == "finished earlier: skipped"]
    assert sorted(skipped) == sorted(first["mtimes"]), rows
    for name in skipped:  # not run again: summary.json untouched
        assert (on_cluster["out"] / name / "summary.json").stat().st_mtime_ns == \
            first["mtimes"][name]
    total = rows["TOTAL"]
    assert int(total["frames"]) == sum(int(rows[n]["frames"]) for n in OK_NAMES) == 81
    assert total["message"] == f"4 ok ({len(skipped)} finished earlier), 1 failed"
    assert int(total["loops_accepted"]) == sum(int(rows[n]["loops_accepted"]) for n in OK_NAMES)


@pytest.mark.cluster
def test_batch_on_a_separate_cluster_gives_the_same_table(on_cluster, embedded):
    table, out = on_cluster["table"], on_cluster["out"]
    same = [c for c in COLUMNS if c not in ("message", "fps", "peak_rss_mb")]
    assert [{c: r[c] for c in same} for r in table] == \
        [{c: r[c] for c in same} for r in embedded["table"]]
    assert table[4]["message"].replace(str(out), "DIR") == \
        embedded["table"][4]["message"].replace(str(embedded["out"]), "DIR")
    for name in OK_NAMES:
        assert (out / name / "poses_kitti.txt").read_bytes() == \
            (embedded["out"] / name / "poses_kitti.txt").read_bytes()


@pytest.mark.cluster
def test_simulate_several_pose_files_in_one_call(ray_cluster, tmp_path):
    """Two trajectories in one `simulate` call (jobs on Ray) give the same scans as two calls;
    each finds its calib and times beside its pose file, as KITTI lays them out."""
    root = tmp_path / "kitti"
    poses = np.loadtxt(SAMPLE / "poses.txt")
    for sub, text in (("poses", None), ("calib", (SAMPLE / "calib.txt").read_text()),
                      ("times", (SAMPLE / "times.txt").read_text())):
        (root / sub).mkdir(parents=True)
        for name, rows in (("x", poses), ("y", poses[::-1])):
            path = root / sub / f"{name}.txt"
            path.write_text(text) if text else np.savetxt(path, rows, fmt="%.9e")
    common = ["--n-scans", "3", "--start", "5", "--sensor", "vlp16"]
    cli = [sys.executable, "-m", "lidar_slam.cli", "simulate"]
    procs = [subprocess.Popen([*cli, str(root / "poses" / f"{n}.txt"), "--out",
                               str(tmp_path / n), *common], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for n in ("x", "y")]
    both = lidar_slam("simulate", root / "poses" / "x.txt", root / "poses" / "y.txt", "--out",
                      tmp_path / "both", *common, "--address", "auto",
                      env=pinned(ray_cluster))
    assert both.returncode == 0, both.stderr
    assert both.stdout.count("simulated 3 scans") == 2
    for name, proc in zip(("x", "y"), procs):
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        files = sorted(p.relative_to(tmp_path / name) for p in (tmp_path / name).rglob("*"))
        assert len(files) > 8
        for rel in files:
            a, b = tmp_path / name / rel, tmp_path / "both" / name / rel
            assert a.is_dir() or a.read_bytes() == b.read_bytes(), rel


def test_batch_without_ray_says_what_to_install(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; sys.modules['ray'] = None; "
         "from lidar_slam.cli import app; app()", "batch", str(SAMPLE), "--out",
         str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'lidar-slam[cluster]'" in lines[0], proc.stderr
    assert not (tmp_path / "o").exists()


def test_batch_task_names_a_node_that_cannot_read_an_input(tmp_path):
    """On a cluster a path one node sees and another does not is an error row saying so."""
    from lidar_slam.batch import BatchJob, run_job

    job = BatchJob("x", str(tmp_path / "not_here"), str(tmp_path / "x"), cluster=True)
    res = run_job(job)
    assert res.row["status"] == "error"
    assert "does not exist on node" in res.row["message"]
    assert "shared file system" in res.row["message"]
    job = BatchJob("x", str(SAMPLE), str(tmp_path / "gone" / "x"), cluster=True)
    assert "--out is not visible on node" in run_job(job).row["message"]


def test_sequence_names_and_globs(tmp_path):
    from lidar_slam.batch import expand_inputs, sequence_names

    for d in ("a/07", "b/07", "c/x2", "c/x10"):
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "drive.bag").write_bytes(b"")
    paths = expand_inputs([str(tmp_path / "a" / "07"), str(tmp_path / "*" / "07"),
                           str(tmp_path / "c" / "x*"), str(tmp_path / "drive.bag")])
    assert sequence_names(paths) == ["a_07", "b_07", "x2", "x10", "drive"]
    from lidar_slam.errors import InputError

    with pytest.raises(InputError, match="no input matches"):
        expand_inputs([str(tmp_path / "nothing*")])


def test_total_row_pools_drift_over_segments_and_ate_over_frames():
    from lidar_slam.batch.results import SequenceResult, error_row, total_row

    def ok(name, frames, t_err, segs, ate, computed):
        row = dict.fromkeys(COLUMNS)
        row.update(sequence=name, status="ok", message="", frames=frames, path_length_m=100.0,
                   t_err_pct=t_err, r_err_deg_100m=t_err, ate_m=ate, loops_accepted=2,
                   fps=10.0, peak_rss_mb=300.0)
        return SequenceResult(row, {"kitti_segments": segs, "computed_now": computed,
                                    "frames_computed": frames if computed else 0})

    rows = [ok("a", 100, 1.0, 10, 1.0, True), ok("b", 300, 2.0, 30, 2.0, False),
            error_row("c", "bad\n  file")]
    total = total_row(rows, wall_s=10.0)
    assert total["frames"] == 400 and total["loops_accepted"] == 4
    assert total["t_err_pct"] == pytest.approx(1.75)  # (10 x 1 + 30 x 2) / 40 segments
    assert total["ate_m"] == pytest.approx(np.sqrt((100 * 1 + 300 * 4) / 400))
    assert total["fps"] == pytest.approx(10.0)  # 100 frames computed now in 10 s
    assert total["status"] == "error" and total["message"] == "2 ok (1 finished earlier), 1 failed"
    assert rows[2].row["message"] == "bad file"  # one line


@pytest.mark.cluster
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_to_the_group_stops_an_embedded_batch_and_keeps_its_table(inputs, tmp_path,
                                                                         sig):
    """`timeout -s TERM` / Ctrl-C on `batch` with Ray inside it: the signal reaches Ray's
    processes too. The batch writes its table (finished runs ok, the others to re-run) and
    exits 130; the same command then finishes the rest. SIGTERM used to kill the batch with
    no table."""
    require_ray()
    out = tmp_path / "B"
    args = [*inputs[:3], "--workers", 1]
    proc = launch_batch(args, out, {})
    try:
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            if (out / "a" / "summary.json").is_file():
                break
            time.sleep(0.05)
        os.killpg(proc.pid, sig)
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("lidar-slam: error: interrupted;") and "re-run" in last, last
    rows = {r["sequence"]: r for r in read_table(out)}
    assert rows["a"]["status"] == "ok", rows
    assert any("interrupted" in r["message"] for r in rows.values()), rows
    for name in ("results.md", "results.json"):
        assert (out / name).is_file(), name
    again = lidar_slam("batch", *args, "--out", out)
    assert again.returncode == 0, again.stderr
    assert [r["status"] for r in read_table(out)] == ["ok"] * 4


OUSTER_BAG = SHARED_DATA / "rosbags" / "ouster_os1_64_points_ros1_profile.mcap"
OUSTER_IMU = "/os1_cloud_node/imu"


@pytest.fixture(scope="module")
def ouster_imu_offset() -> float:
    """The Ouster sample's IMU is stamped by the sensor's clock: the offset onto the clouds'."""
    from lidar_slam.io import rosbag
    from lidar_slam.io.sources import open_source

    shared_path("rosbags", OUSTER_BAG.name)  # skips, or fails under LIDAR_SLAM_REQUIRE_SHARED
    imu, _ = rosbag.read_imu_topic(OUSTER_BAG, OUSTER_IMU)
    return float(open_source(OUSTER_BAG).stamps[0] - imu.stamp_s[0])


def test_batch_jobs_read_the_imu_topic_and_switches_as_run_does(ouster_imu_offset, tmp_path):
    """A job names the IMU topic of its bag as `run --imu-topic` does (the clock offset from
    the config), is skipped as finished when re-run with it, and --no-imu switches it off."""
    from lidar_slam.batch import BatchJob, run_job
    from lidar_slam.cli.run import run_overrides

    cfg = tmp_path / "offset.yaml"
    # Two clouds cannot calibrate an IMU (lidar_slam.imu_calibration): the config gives it all.
    cfg.write_text(f"imu:\n  time_offset_s: {ouster_imu_offset!r}\n  T_lidar_imu: [0, 0, 0, 0, "
                   f"0, 0]\n")
    job = BatchJob("bag", str(OUSTER_BAG), str(tmp_path / "bag"), str(cfg),
                   imu_topic=OUSTER_IMU)
    res = run_job(job)
    assert res.row["status"] == "ok", res.row
    imu = json.loads((tmp_path / "bag" / "summary.json").read_text())["imu"]
    assert OUSTER_IMU in imu["source"] and imu["samples"] == 17, imu
    # read, but two clouds are too short for either end to use it: said so
    assert imu["used"] is False and "need 1.0 s" in imu["reason"], imu
    assert run_job(job).row["message"] == "finished earlier: skipped"
    # another IMU topic is another run: not skipped (here: no such topic, an error row)
    res = run_job(BatchJob("bag", str(OUSTER_BAG), str(tmp_path / "bag"), str(cfg),
                           imu_topic="/no/such/imu"))
    assert res.row["status"] == "error" and "/no/such/imu" in res.row["message"], res.row
    # the topic named without the offset: to be found from the data, which two clouds cannot:
    # lidar-only, as the run says
    res = run_job(BatchJob("bag", str(OUSTER_BAG), str(tmp_path / "bad"), imu_topic=OUSTER_IMU))
    assert res.row["status"] == "ok", res.row
    imu = json.loads((tmp_path / "bad" / "summary.json").read_text())["imu"]
    assert not imu["used"] and "cannot be found from the data" in imu["reason"], imu
    off = BatchJob("bag", str(OUSTER_BAG), str(tmp_path / "off"), str(cfg),
                   overrides=run_overrides(False, False, no_imu=True, no_gnss=True))
    assert run_job(off).row["status"] == "ok"
    summary = json.loads((tmp_path / "off" / "summary.json").read_text())
    assert not summary["imu"]["used"] and not summary["gnss"]["used"]


def test_batch_command_gives_every_job_the_imu_and_gnss_options(monkeypatch, tmp_path):
    """`batch --imu-topic T --gnss-topic G --no-gnss` reaches every job like `run`'s flags."""
    from typer.testing import CliRunner

    import lidar_slam.batch
    from lidar_slam.batch.runner import BatchReport
    from lidar_slam.cli import app

    require_ray()
    seen = []

    def capture(jobs, out_dir, fleet, interval_s, meta=None):  # the jobs, not run (no Ray)
        seen.extend(jobs)
        return BatchReport([], [], 0.0, False)

    monkeypatch.setattr(lidar_slam.batch, "run_batch", capture)
    monkeypatch.setattr("lidar_slam.batch.results.as_markdown", lambda rows: "")
    res = CliRunner().invoke(app, ["batch", str(SAMPLE), str(OUSTER_BAG), "--out",
                                   str(tmp_path / "o"), "--imu-topic", OUSTER_IMU,
                                   "--gnss-topic", "/fix", "--no-gnss"])
    assert res.exit_code == 0, res.output
    assert len(seen) == 2
    for job in seen:
        assert (job.imu_topic, job.gnss_topic) == (OUSTER_IMU, "/fix")
        assert job.overrides["gnss"] == {"enabled": False} and "imu" not in job.overrides
