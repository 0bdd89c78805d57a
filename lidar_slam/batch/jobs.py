"""The jobs of `lidar-slam batch`: one per sequence, each run by a Ray worker (run_job).

Every job runs the same code as `lidar-slam run` (lidar_slam.run.run_sequence) into
DIR/<name>/, with `--resume` semantics: a sequence whose run folder holds a finished run of the
same input, range and config is skipped (its row is read back), a partial one (killed,
interrupted) resumes from its checkpoint. A failing sequence becomes an error row; the others go
on. Nothing here imports typer: a worker imports this module and the runner only.
"""

from __future__ import annotations

import glob
import json
import socket
from dataclasses import dataclass, field
from pathlib import Path

from lidar_slam.batch.results import SequenceResult, error_row, run_row
from lidar_slam.errors import InputError, LidarSlamError

SHARED_FS = ("every node of the cluster must read the inputs and write --out at the same paths "
             "(a shared file system)")
SKIPPED = "finished earlier: skipped"


@dataclass(frozen=True)
class BatchJob:
    """One sequence of a batch: absolute paths (Ray workers do not start in the caller's
    folder) and the options every run of the batch shares."""

    name: str
    data: str
    out: str
    config: str | None = None
    start: int = 0
    n_scans: int | None = None
    topic: str | None = None
    overrides: dict = field(default_factory=dict)
    overwrite: bool = False
    cluster: bool = False
    imu_topic: str | None = None  # as `run --imu-topic` / `--gnss-topic` (bags only)
    gnss_topic: str | None = None


def expand_inputs(patterns: list[str]) -> list[Path]:
    """Inputs in the given order, each glob (quoted, so the shell left it) replaced by its
    matches in natural order; a path named twice is run once. A glob without a match is an
    error; a plain path that does not exist becomes that sequence's error row."""
    from lidar_slam.io.sources import natural_key

    out: list[Path] = []
    for pattern in patterns:
        if any(c in pattern for c in "*?["):
            found = sorted(glob.glob(pattern), key=natural_key)
            if not found:
                raise InputError(pattern, "no input matches this pattern")
            paths = [Path(p) for p in found]
        else:
            paths = [Path(pattern)]
        for p in paths:
            p = p.absolute()
            if p not in out:
                out.append(p)
    return out


def sequence_names(paths: list[Path]) -> list[str]:
    """A folder name per input (a file's name without its suffix), made unique by prefixing
    the parent folders' names where two inputs share one: /a/07 and /b/07 are a_07 and b_07."""

    def name(p: Path, depth: int) -> str:
        parts = list(p.parts[-depth:])
        if p.suffix and not p.is_dir():
            parts[-1] = p.stem
        return "_".join(x.strip("/") or "root" for x in parts)

    depth = [1] * len(paths)
    while True:
        names = [name(p, d) for p, d in zip(paths, depth)]
        clash = [i for i, n in enumerate(names) if names.count(n) > 1]
        if not clash or all(depth[i] >= len(paths[i].parts) for i in clash):
            break
        for i in clash:
            depth[i] += 1
    seen: dict[str, int] = {}
    for i, n in enumerate(names):  # the same path twice was removed; this is a last resort
        seen[n] = seen.get(n, 0) + 1
        names[i] = n if seen[n] == 1 else f"{n}-{seen[n]}"
    return names


def finished_run(out: Path, identity: dict) -> bool:
    """Whether out holds a run that ended normally (not interrupted, not stopped by an error)
    of the same input, range and config (checkpoint/run.json)."""
    from lidar_slam.run import checkpoint

    summary_path = out / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
    except (OSError, ValueError):
        return False
    if summary.get("interrupted") or summary.get("stopped_by_error"):
        return False
    traceback = out / "error_traceback.txt"  # an internal error, written after the summary
    if traceback.is_file() and traceback.stat().st_mtime >= summary_path.stat().st_mtime:
        return False
    try:
        checkpoint.check_same_run(out, identity, verify_files=False)
    except InputError:
        return False
    return True


def run_job(job: BatchJob) -> SequenceResult:
    """One sequence, in a Ray worker: skip it when finished, else run (or resume) it as `run`
    does; its row, or an error row with the one-line message. The details say on which node
    and with which lidar_slam it ran."""
    import lidar_slam
    from lidar_slam.runtime import tune_process

    tune_process()  # a fresh worker process per job (max_calls=1): it starts a run here
    res = _run_job(job)
    res.details.update(node=socket.gethostname(), code=str(Path(lidar_slam.__file__).parent))
    return res


def finished_result(job: BatchJob, since: float | None = None) -> SequenceResult | None:
    """The row of job's run folder when it holds a finished run of this job (None otherwise);
    it counts as computed by this batch when summary.json is newer than `since` (a time)."""
    from lidar_slam.config import load_config
    from lidar_slam.io.sources import open_source
    from lidar_slam.run import checkpoint

    data, out = Path(job.data), Path(job.out)
    cfg = load_config(job.config, job.overrides)
    if not finished_run(out, checkpoint.describe_run(data, job.start, job.n_scans, job.topic,
                                                     cfg, job.imu_topic, job.gnss_topic)):
        return None
    now = since is not None and (out / "summary.json").stat().st_mtime >= since
    source = open_source(data, topic=job.topic,
                         kitti_vertical_correction=cfg.data.kitti_vertical_correction)
    return run_row(job.name, out, source.ground_truth, "" if now else SKIPPED, computed_now=now)


def _run_job(job: BatchJob) -> SequenceResult:
    from lidar_slam.run.runner import run_sequence

    data, out = Path(job.data), Path(job.out)
    node = socket.gethostname()
    try:
        if not out.parent.is_dir():
            raise InputError(out.parent, f"--out is not visible on node {node}: {SHARED_FS}")
        if job.cluster and not data.exists():
            raise InputError(data, f"does not exist on node {node}: {SHARED_FS}")
        found = None if job.overwrite else finished_result(job)
        if found is not None:
            return found
        outcome = run_sequence(
            data, out, config=Path(job.config) if job.config else None, start=job.start,
            n_scans=job.n_scans, topic=job.topic, imu_topic=job.imu_topic,
            gnss_topic=job.gnss_topic, overrides=job.overrides,
            overwrite=job.overwrite, resume=not job.overwrite, progress=False)
    except LidarSlamError as exc:
        return error_row(job.name, str(exc))
    except OSError as exc:  # e.g. a run folder that cannot be written
        return error_row(job.name, f"{exc.filename or out}: {exc.strerror or exc}")
    if outcome.failure is not None:
        return error_row(job.name, str(outcome.failure), outcome.summary)
    resumed = outcome.summary.get("resumed_at_frame", 0)
    return run_row(job.name, out, outcome.ground_truth,
                   f"resumed at frame {resumed}" if resumed else "")
