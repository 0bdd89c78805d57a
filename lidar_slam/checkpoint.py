"""Checkpoints of a running pipeline in its run folder, and resuming from them.

RUN/checkpoint/ holds:
- `run.json`: what the run is (input, start, scan count, the effective config); a resume with
  other input or another config is refused.
- `state.npz`: written every `checkpoint.every_keyframes` keyframes via a temporary file and a
  rename, so a kill at any instant leaves the previous checkpoint whole: the frames so far, the
  odometry (poses, kiss-icp's local map points), front-end and keyframe-selector state, the loop
  records and constraints applied to the graph, and how many keyframes and threshold deviations
  are valid.
- `deviations.bin`: every model deviation fed to kiss-icp's adaptive threshold (append-only,
  float64 4x4), replayed on resume to rebuild the threshold exactly.

The keyframe store (RUN/keyframes/) is flushed with every checkpoint; resuming cuts it back to
what the checkpoint vouches for. Loop detection for keyframes whose results were not yet applied
is redone, and the scan-context index is rebuilt from the stored clouds, so a resumed run makes
the same loop decisions as an uninterrupted one.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.errors import InputError
from lidar_slam.keyframes import write_atomic
from lidar_slam.pipeline import Pipeline
from lidar_slam.types import LoopConstraint

CHECKPOINT_VERSION = 1


def _dir(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoint"


def describe_run(data: Path, start: int, n_scans: int | None, topic: str | None,
                 cfg: SlamConfig) -> dict:
    """What makes two runs the same run (for refusing a resume with other input or config)."""
    return {"version": CHECKPOINT_VERSION, "input": str(Path(data).resolve()), "start": start,
            "n_scans": n_scans, "topic": topic, "config": cfg.model_dump(mode="json")}


def start_run(run_dir: Path, run: dict) -> None:
    """Record what this run is (a fresh run)."""
    d = _dir(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    write_atomic(d / "run.json", json.dumps(run, indent=1) + "\n")
    (d / "deviations.bin").write_bytes(b"")


def has_checkpoint(run_dir: Path) -> bool:
    return (_dir(run_dir) / "state.npz").is_file()


def check_same_run(run_dir: Path, run: dict) -> None:
    """Refuse to resume a run folder made with other input, range or config."""
    path = _dir(run_dir) / "run.json"
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read it to resume ({exc})") from exc
    for key, what in (("version", "checkpoint version"), ("input", "input"),
                      ("start", "--start"), ("n_scans", "--n-scans"), ("topic", "--topic"),
                      ("config", "config")):
        if old.get(key) != run[key]:
            raise InputError(run_dir, f"cannot resume: the run was made with another {what} "
                             f"(use --overwrite to start again)")


def save(run_dir: Path, pipe: Pipeline, loops_applied_upto: int) -> None:
    """Write a checkpoint of pipe after its last scan; loop results of keyframes <= the given
    id are in the graph, later ones will be recomputed on resume."""
    d = _dir(run_dir)
    r = pipe.result
    r.store.flush()  # before the state that vouches for it
    deviations = pipe.odometry.take_deviations()
    with open(d / "deviations.bin", "ab") as fh:
        fh.write(np.ascontiguousarray(deviations, "<f8").tobytes())
        fh.flush()
        os.fsync(fh.fileno())
    n_dev = (d / "deviations.bin").stat().st_size // (16 * 8)
    odo = pipe.odometry.state()
    constraints = pipe.backend.constraints if pipe.backend is not None else []
    meta = {"frames": len(r.indices), "keyframes": len(r.store), "deviations": n_dev,
            "loops_applied_upto": loops_applied_upto, "skipped_empty": r.skipped_empty,
            "skipped_small": r.skipped_small,
            "deskew": pipe.deskew.state(), "seconds": r.seconds, "adaptive": pipe.adaptive,
            "loop_records": [_record_json(x) for x in r.loops]}
    arrays = {
        "indices": np.asarray(r.indices, np.int64), "stamps_s": np.asarray(r.stamps_s),
        "odom_poses": np.asarray(r.odom_poses).reshape(-1, 4, 4),
        "frame_kf": np.asarray(r.frame_kf, np.int64),
        "selector_last": (np.eye(4) if pipe.keyframes.last is None else pipe.keyframes.last),
        "loop_ids": np.array([[c.query, c.match] for c in constraints], np.int64).reshape(-1, 2),
        "loop_T": np.array([c.T_match_query for c in constraints]).reshape(-1, 4, 4),
        "loop_info": np.array([c.information for c in constraints]).reshape(-1, 6, 6),
        "loop_fit": np.array([[c.fitness, c.rmse_m] for c in constraints]).reshape(-1, 2),
        "backend_live": (pipe.backend.state() if pipe.backend is not None
                         else np.empty((0, 4, 4))),
        **{f"odo_{k}": v for k, v in odo.items()},
        "meta": np.array(json.dumps(meta)),
    }
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    write_atomic(d / "state.npz", buf.getvalue())


def _record_json(rec) -> dict:
    out = dict(rec.__dict__)
    T = out.pop("T_match_query")
    out["T_match_query"] = None if T is None else np.asarray(T).tolist()
    return out


def restore(run_dir: Path, pipe: Pipeline) -> int:
    """Load the checkpoint into a fresh pipe (made on the same run folder); returns the number
    of frames it already holds (the next scan to process is start + that)."""
    from lidar_slam.loop.closer import LoopRecord

    d = _dir(run_dir)
    with np.load(d / "state.npz") as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(str(a.pop("meta")))
    r = pipe.result
    r.indices = [int(i) for i in a["indices"]]
    r.stamps_s = [float(s) for s in a["stamps_s"]]
    r.odom_poses = list(a["odom_poses"])
    r.frame_kf = [int(k) for k in a["frame_kf"]]
    r.skipped_empty = meta["skipped_empty"]
    r.skipped_small = meta.get("skipped_small", 0)
    r.seconds = meta["seconds"]
    pipe.start(meta["adaptive"])
    if meta["frames"]:
        pipe.keyframes.last = a["selector_last"]
    pipe.deskew.restore(meta["deskew"])
    deviations = np.fromfile(d / "deviations.bin", "<f8",
                             count=meta["deviations"] * 16).reshape(-1, 4, 4)
    with open(d / "deviations.bin", "r+b") as fh:
        fh.truncate(meta["deviations"] * 16 * 8)
    pipe.odometry.restore({k[4:]: v for k, v in a.items() if k.startswith("odo_")}, deviations)
    r.store.truncate(meta["keyframes"])
    anchors = []  # the slow-scan refinement's target, as the run had it: the last non-empty
    for kf_id in range(len(r.store) - 1, -1, -1):  # keyframe clouds, oldest first
        if len(anchors) == pipe.cfg.odometry.refine_keyframes:
            break
        kf = r.store.get(kf_id)
        if len(kf.points):
            anchors.insert(0, kf)
    for kf in anchors:
        pipe.odometry.add_anchor(kf.T_world_kf_odom, kf.points)
    for row in meta["loop_records"]:
        T = row.pop("T_match_query")
        r.loops.append(LoopRecord(**row, T_match_query=None if T is None else np.array(T)))
    if pipe.backend is not None:
        upto = meta["loops_applied_upto"]
        loops = [LoopConstraint(int(q), int(m), T, info, float(f), float(e)) for (q, m), T, info,
                 (f, e) in zip(a["loop_ids"], a["loop_T"], a["loop_info"], a["loop_fit"])]
        by_query = {c.query: c for c in loops}
        for kf_id in range(len(r.store)):
            pipe.backend.add_keyframe(kf_id, r.store.T_world_kf_odom(kf_id))
            if kf_id in by_query:
                pipe.backend.add_loop(by_query[kf_id])
        if "backend_live" in a:
            pipe.backend.restore_live(a["backend_live"])
        else:  # a checkpoint from before the windowed back-end: re-solve the newest window
            pipe.backend.update()
        upto = min(upto, len(r.store) - 1)
        applied = [c for c in loops if c.query <= upto]
        pipe.loops.reindex(upto, max(applied, key=lambda c: c.query) if applied else None)
        for kf_id in range(max(upto + 1, 0), len(r.store)):
            pipe.loops.submit(kf_id)
    return meta["frames"]
