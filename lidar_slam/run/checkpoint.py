"""Checkpoints of a running pipeline in its run folder, and resuming from them.

RUN/checkpoint/ holds:
- `run.json`: what the run is (input, start, scan count, the effective config); a resume with
  other input or another config is refused.
- `state-<generation>.npz`: written every `checkpoint.every_keyframes` keyframes: the frames so
  far, the odometry (poses, kiss-icp's local map points), front-end and keyframe-selector state
  (with an IMU: the IMU front-end's, whose smoother is rebuilt by replaying its inputs),
  the loop records and constraints applied to the graph, and how many keyframes and threshold
  deviations are valid.
- `deviations.bin`: every model deviation fed to kiss-icp's adaptive threshold (append-only,
  float64 4x4), replayed on resume to rebuild the threshold exactly.
- `manifest.json`: the checkpoint itself: which state file it is, how many frames it holds,
  and the length and sha256 of every file it depends on (run.json and the state whole; of
  deviations.bin and the keyframe store's table.bin and points.bin, which grow after it, the
  prefix it covers), plus a sha256 of the manifest's own content. Written last, atomically
  (temporary file and rename): a kill at any instant leaves the previous manifest, whose state
  file is removed only after the new manifest is in place, and whose prefixes later appends do
  not touch. A resume checks every file against it first (check_same_run) and refuses a
  damaged, truncated or missing one with one line, before anything is read or cut back. Only
  the newest checkpoint is kept: there is no older one to fall back to.

The keyframe store (RUN/keyframes/) is flushed with every checkpoint; resuming cuts it back to
what the checkpoint vouches for. Loop detection for keyframes whose results were not yet applied
is redone, and the scan-context index is rebuilt from the stored clouds, so a resumed run makes
the same loop decisions as an uninterrupted one.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import weakref
from pathlib import Path

import numpy as np

from lidar_slam.config import SlamConfig
from lidar_slam.errors import InputError
from lidar_slam.io.atomic import write_atomic
from lidar_slam.pipeline import Pipeline
from lidar_slam.types import LoopConstraint

CHECKPOINT_VERSION = 1  # of the run's identity (run.json): a run made before is the same run
MANIFEST = "manifest.json"
MANIFEST_VERSION = 1
_RERUN = "cannot resume from this checkpoint; rerun with --overwrite to start again"
# Per pipeline, the running sha256 of each growing file up to its length at the last checkpoint,
# so a checkpoint hashes only what was appended since the one before.
_HASHES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _dir(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoint"


def describe_run(data: Path, start: int, n_scans: int | None, topic: str | None,
                 cfg: SlamConfig, imu_topic: str | None = None,
                 gnss_topic: str | None = None) -> dict:
    """What makes two runs the same run (for refusing a resume with other input or config);
    the IMU / GNSS topics only when named (a lidar-only run's identity is as before)."""
    named = {k: v for k, v in (("imu_topic", imu_topic), ("gnss_topic", gnss_topic)) if v}
    return {"version": CHECKPOINT_VERSION, "input": str(Path(data).resolve()), "start": start,
            "n_scans": n_scans, "topic": topic, "config": cfg.model_dump(mode="json"), **named}


def start_run(run_dir: Path, run: dict) -> None:
    """Record what this run is (a fresh run)."""
    d = _dir(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    for old in d.glob("state*.npz"):
        old.unlink()
    write_atomic(d / "run.json", json.dumps(run, indent=1) + "\n")
    (d / "deviations.bin").write_bytes(b"")
    _write_manifest(d, {"generation": 0, "state": None, "files": {}})


def has_checkpoint(run_dir: Path) -> bool:
    """Whether the run folder holds a checkpoint to resume from (or the remains of one, which
    check_same_run refuses): not a run killed before its first checkpoint."""
    d = _dir(run_dir)
    if not (d / MANIFEST).is_file():
        return any(d.glob("state*.npz"))  # a lost manifest, or one from before manifests
    try:
        return json.loads((d / MANIFEST).read_text()).get("state") is not None
    except (OSError, ValueError, AttributeError):
        return True  # damaged: check_same_run says so


def check_same_run(run_dir: Path, run: dict, *, verify_files: bool = True) -> None:
    """Refuse to resume a run folder made with other input, range or config, or (unless
    verify_files=False: only asking whether a finished run is this run) whose checkpoint is
    damaged (see verify)."""
    path = _dir(run_dir) / "run.json"
    try:
        old, problem = json.loads(path.read_text()), None
    except (OSError, ValueError) as exc:
        old, problem = {}, exc
    if verify_files and has_checkpoint(run_dir):
        verify(run_dir)
    if problem is not None:
        raise InputError(path, f"cannot read it to resume ({problem})")
    for key, what in (("version", "checkpoint version"), ("input", "input"),
                      ("start", "--start"), ("n_scans", "--n-scans"), ("topic", "--topic"),
                      ("config", "config"), ("imu_topic", "--imu-topic"),
                      ("gnss_topic", "--gnss-topic")):
        if old.get(key) != run.get(key):  # the IMU / GNSS topics only when named
            raise InputError(run_dir, f"cannot resume: the run was made with another {what} "
                             f"(use --overwrite to start again)")


def verify(run_dir: Path) -> dict:
    """Check every file the checkpoint depends on against its manifest (length and sha256;
    see the module doc); returns the manifest. Raises InputError naming the first file that is
    missing, truncated or damaged (or the manifest itself)."""
    d = _dir(run_dir)
    path = d / MANIFEST
    if not path.is_file():
        raise InputError(path, f"missing (or a checkpoint of a lidar-slam without checksums), "
                         f"so the checkpoint cannot be checked; {_RERUN}")
    try:
        manifest = json.loads(path.read_text())
        body = {k: v for k, v in manifest.items() if k != "sha256"}
        intact = manifest["sha256"] == _sha256_json(body)
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        intact = False
    if not intact:
        raise InputError(path, f"damaged (its content does not match its own sha256); {_RERUN}")
    if manifest.get("version") != MANIFEST_VERSION:
        raise InputError(path, f"version {manifest.get('version')}, this lidar-slam reads "
                         f"version {MANIFEST_VERSION}; {_RERUN}")
    for rel, want in manifest["files"].items():
        p = Path(run_dir) / rel
        if not p.is_file():
            raise InputError(p, f"missing; {_RERUN}")
        size = p.stat().st_size
        if size < want["bytes"]:
            raise InputError(p, f"truncated: {size} bytes, the checkpoint covers "
                             f"{want['bytes']}; {_RERUN}")
        if size != want["bytes"] and not want["grows"]:
            raise InputError(p, f"changed: {size} bytes, the checkpoint wrote {want['bytes']}; "
                             f"{_RERUN}")
        with open(p, "rb") as fh:
            if _sha256_prefix(fh, 0, want["bytes"]).hexdigest() != want["sha256"]:
                raise InputError(p, f"damaged: its first {want['bytes']} bytes do not match "
                                 f"the checkpoint's sha256; {_RERUN}")
    return manifest


def _sha256_json(body: dict) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _sha256_prefix(fh, start: int, end: int, h=None):
    """h (a new sha256 when None) updated with bytes start..end of the open file fh."""
    h = hashlib.sha256() if h is None else h
    fh.seek(start)
    while start < end:
        chunk = fh.read(min(1 << 20, end - start))
        if not chunk:
            break
        h.update(chunk)
        start += len(chunk)
    return h


def _write_manifest(d: Path, body: dict) -> None:
    body = {"version": MANIFEST_VERSION, **body}
    write_atomic(d / MANIFEST, json.dumps({**body, "sha256": _sha256_json(body)}, indent=1)
                 + "\n")


def _read_manifest(d: Path) -> dict:
    try:
        return json.loads((d / MANIFEST).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(d / MANIFEST, f"cannot read it ({exc}); {_RERUN}") from exc


def _growing_entry(pipe: Pipeline, run_dir: Path, rel: str) -> dict:
    """Manifest entry of a file that only grows: its length now and the sha256 of all of it,
    hashing only what was appended since the pipe's last checkpoint."""
    path = Path(run_dir) / rel
    hashes = _HASHES.setdefault(pipe, {})
    size = path.stat().st_size
    done, h = hashes.get(path, (0, None))
    if done > size:  # cut back since (cannot happen within one pipe): hash it all again
        done, h = 0, None
    with open(path, "rb") as fh:
        h = _sha256_prefix(fh, done, size, None if h is None else h.copy())
    hashes[path] = (size, h)
    return {"bytes": size, "sha256": h.hexdigest(), "grows": True}


def _whole_entry(data: bytes) -> dict:
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest(), "grows": False}


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
    anchors = pipe.odometry.anchors()
    constraints = pipe.backend.constraints if pipe.backend is not None else []
    meta = {"frames": len(r.indices), "keyframes": len(r.store), "deviations": n_dev,
            "loops_applied_upto": loops_applied_upto, "skipped_empty": r.skipped_empty,
            "skipped_small": r.skipped_small,
            "deskew": pipe.deskew.state(), "seconds": r.seconds, "adaptive": pipe.adaptive,
            "loop_records": [_record_json(x) for x in r.loops],
            "loop_split_edges": sorted(r.loop_split_edges)}
    arrays = {
        "indices": np.asarray(r.indices, np.int64), "stamps_s": np.asarray(r.stamps_s),
        "odom_poses": np.asarray(r.odom_poses).reshape(-1, 4, 4),
        "frame_kf": np.asarray(r.frame_kf, np.int64),
        "selector_last": (np.eye(4) if pipe.keyframes.last is None else pipe.keyframes.last),
        # keyframes due and waiting for a steady scan (SteadyWait), and the last registered
        # poses and miss they are judged by
        "steady_wait": np.array([float(pipe.steady_wait.pending), pipe.steady_wait.waited,
                                 pipe.steady_wait.last_miss, pipe.steady_wait.late,
                                 pipe.steady_wait.not_steady], np.float64),
        "steady_T": np.array(pipe.steady_wait.last, np.float64).reshape(-1, 4, 4),
        "steady_recent": np.array(pipe.steady_wait.recent, np.float64),
        "loop_ids": np.array([[c.query, c.match] for c in constraints], np.int64).reshape(-1, 2),
        "loop_T": np.array([c.T_match_query for c in constraints]).reshape(-1, 4, 4),
        "loop_info": np.array([c.information for c in constraints]).reshape(-1, 6, 6),
        "loop_fit": np.array([[c.fitness, c.rmse_m] for c in constraints]).reshape(-1, 2),
        "kf_up": np.array([[k, *u] for k, u in sorted(r.kf_up.items())]).reshape(-1, 4),
        "kf_node_dt": (np.full((1, 2), np.nan) if r.kf_node_dt is None else
                       np.array(sorted(r.kf_node_dt.items()), np.float64).reshape(-1, 2)),
        # the odometry's keyframe copies (refinement targets, failure watch) as the run has
        # them: without an IMU at the stamps, where the store's clouds are at mid-sweep
        "anchor_T": np.array([T for T, _ in anchors], np.float64).reshape(-1, 4, 4),
        "anchor_counts": np.array([len(p) for _, p in anchors], np.int64),
        "anchor_points": (np.concatenate([np.asarray(p, np.float32) for _, p in anchors])
                          if anchors else np.zeros((0, 3), np.float32)),
        # the last frame's registered pose when its stamp pose is still extrapolated
        # (Pipeline.unsettled): position, ref_s, T_world_ref
        "unsettled": (np.zeros((0, 18)) if pipe.unsettled is None else np.array(
            [[pipe.unsettled[0], pipe.unsettled[2], *np.ravel(pipe.unsettled[1][:4, :4])]])),
        "backend_live": (pipe.backend.state() if pipe.backend is not None
                         else np.empty((0, 4, 4))),
        **{f"odo_{k}": v for k, v in odo.items()},
        **({} if pipe.inertial is None
           else {f"imu_{k}": v for k, v in pipe.inertial.state().items()}),
        "meta": np.array(json.dumps(meta)),
    }
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    state = buf.getvalue()
    generation = _read_manifest(d)["generation"] + 1
    name = f"state-{generation:06d}.npz"
    write_atomic(d / name, state)
    kf = os.path.relpath(r.store.root, run_dir)
    files = {"checkpoint/run.json": _whole_entry((d / "run.json").read_bytes()),
             f"checkpoint/{name}": _whole_entry(state)}
    for rel in ("checkpoint/deviations.bin", f"{kf}/table.bin", f"{kf}/points.bin"):
        files[rel] = _growing_entry(pipe, run_dir, rel)
    _write_manifest(d, {"generation": generation, "state": name, "frames": meta["frames"],
                        "files": files})
    for old in d.glob("state*.npz"):  # only now: until here, the previous manifest held
        if old.name != name:
            old.unlink()


def _record_json(rec) -> dict:
    out = dict(rec.__dict__)
    T = out.pop("T_match_query")
    out["T_match_query"] = None if T is None else np.asarray(T).tolist()
    return out


def restore(run_dir: Path, pipe: Pipeline) -> int:
    """Load the checkpoint into a fresh pipe (made on the same run folder); returns the number
    of frames it already holds (the next scan to process is start + that)."""
    from lidar_slam.loop.detector import LoopRecord

    d = _dir(run_dir)
    state = d / _read_manifest(d)["state"]
    try:
        with np.load(state) as z:
            a = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as exc:  # verify() would have said which file
        raise InputError(state, f"cannot read it ({exc}); {_RERUN}") from exc
    meta = json.loads(str(a.pop("meta")))
    r = pipe.result
    r.indices = [int(i) for i in a["indices"]]
    r.stamps_s = [float(s) for s in a["stamps_s"]]
    r.odom_poses = list(a["odom_poses"])
    r.frame_kf = [int(k) for k in a["frame_kf"]]
    r.kf_up = {int(row[0]): np.array(row[1:]) for row in a.get("kf_up", np.zeros((0, 4)))}
    node_dt = a.get("kf_node_dt", np.full((1, 2), np.nan))  # NaN: not known (older checkpoint)
    r.kf_node_dt = (None if np.isnan(node_dt).any() else
                    {int(k): float(dt) for k, dt in node_dt})
    if "unsettled" not in a and pipe.inertial is None and meta["frames"]:
        # before 8d17648 a sweep-end scan's keyframe was at its stamp, now at mid-sweep: a run
        # continued across the change would mix the two. (A sweep-start one kept at its stamp
        # before a243844 continues: each node's cloud is in its own frame and covariances.csv
        # says each node's instant, and the odometry's copies are the store's clouds there.)
        raise InputError(state, f"made by an older lidar-slam (keyframes of runs without an "
                         f"IMU kept otherwise); {_RERUN}")
    for row in a.get("unsettled", np.zeros((0, 18))):
        pipe.unsettled = (int(row[0]), np.array(row[2:]).reshape(4, 4), float(row[1]))
    r.skipped_empty = meta["skipped_empty"]
    r.skipped_small = meta.get("skipped_small", 0)
    r.seconds = meta["seconds"]
    r.loop_split_edges = set(meta.get("loop_split_edges", ()))
    pipe.start(meta["adaptive"])
    if meta["frames"]:
        pipe.keyframes.last = a["selector_last"]
    if "steady_wait" in a:  # (always since 283818c; run.json's config check refuses older)
        # (283818c's had no counts)
        pending, waited, miss, late, not_steady = [*a["steady_wait"], 0.0, 0.0][:5]
        pipe.steady_wait.pending, pipe.steady_wait.waited = bool(pending), int(waited)
        pipe.steady_wait.late, pipe.steady_wait.not_steady = int(late), int(not_steady)
        pipe.steady_wait.last = [np.array(T) for T in a["steady_T"]]
        pipe.steady_wait.last_miss = float(miss)
        pipe.steady_wait.recent.extend(float(m) for m in a["steady_recent"])
    pipe.deskew.restore(meta["deskew"])
    deviations = np.fromfile(d / "deviations.bin", "<f8",
                             count=meta["deviations"] * 16).reshape(-1, 4, 4)
    with open(d / "deviations.bin", "r+b") as fh:
        fh.truncate(meta["deviations"] * 16 * 8)
    pipe.odometry.restore({k[4:]: v for k, v in a.items() if k.startswith("odo_")}, deviations)
    imu = {k[4:]: v for k, v in a.items() if k.startswith("imu_")}
    if (pipe.inertial is None) != (not imu):
        raise InputError(state, f"the checkpoint was made {'without' if not imu else 'with'} "
                         f"an IMU front-end and this run has {'one' if not imu else 'none'}; "
                         f"{_RERUN}")
    if imu:
        pipe.inertial.restore(imu)
    r.store.truncate(meta["keyframes"])
    if "anchor_T" in a:  # the odometry's keyframe copies, as the run had them
        ends = np.cumsum(a["anchor_counts"])
        for T, pts in zip(a["anchor_T"], np.split(a["anchor_points"], ends[:-1])):
            pipe.odometry.add_anchor(np.array(T), pts)
    else:  # older: the store's last non-empty keyframe clouds (what the odometry had then)
        anchors = []
        for kf_id in range(len(r.store) - 1, -1, -1):  # keyframe clouds, oldest first
            if len(anchors) == pipe.odometry.n_anchors:
                break
            kf = r.store.get(kf_id)
            if len(kf.points):
                anchors.insert(0, kf)
        for kf in anchors:
            pipe.odometry.add_anchor(kf.T_world_kf_odom, kf.points)
    for kf_id in range(len(r.store)):  # the odometry edges' information, as the run had it
        kf = r.store.get(kf_id)
        pipe.weigh_keyframe(kf_id, kf.T_world_kf_odom, kf.points)
    for row in meta["loop_records"]:
        T = row.pop("T_match_query")
        r.loops.append(LoopRecord(**row, T_match_query=None if T is None else np.array(T)))
    if pipe.backend is not None:
        upto = meta["loops_applied_upto"]
        loops = [LoopConstraint(int(q), int(m), T, info, float(f), float(e)) for (q, m), T, info,
                 (f, e) in zip(a["loop_ids"], a["loop_T"], a["loop_info"], a["loop_fit"])]
        by_query = {c.query: c for c in loops}
        # The graph holds the keyframes whose loop results were collected (the later ones join
        # it with their results, as in the run); a checkpoint from before 2026-12-05 held every
        # stored keyframe: its live estimate is cut to those.
        upto = min(upto, len(r.store) - 1)
        for kf_id in range(upto + 1):
            pipe.backend.add_keyframe(kf_id, r.store.T_world_kf_odom(kf_id),
                                      r.odom_information.get(kf_id))
            if kf_id in by_query:
                pipe.backend.add_loop(by_query[kf_id])
        if "backend_live" in a:
            pipe.backend.restore_live(a["backend_live"][:upto + 1])
        else:  # a checkpoint from before the windowed back-end: re-solve the newest window
            pipe.backend.update()
        pipe.loops.reindex(upto)
        pipe.loops_applied_upto = upto  # what a checkpoint before the next collection says
        for kf_id in range(max(upto + 1, 0), len(r.store)):
            pipe.loops.submit(kf_id)
    return meta["frames"]
