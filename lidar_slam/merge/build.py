"""`lidar-slam merge` as a library call: sessions in, the merged map folder out.

MAP/ is a saved map as a run leaves one (lidar_slam.map.keyframes; `localize --map` and
`export` open it): keyframes/ with every kept session's keyframes in the merged frame (the
reference session's frame), config.yaml (the reference run's), summary.json, poses_kitti.txt /
poses_tum.txt (the reference session's frames in the merged frame: the platform's own motion,
which localisation measures its prediction on), loops.csv (the verified loops between
sessions: keyframe b of session b in keyframe a's frame, T_a_b as 12 numbers of its 3x4
row-major; distance: the Scan Context distance that proposed it, empty for a loop found where
the first solve put the sessions; kept by the final solve or not), and per session in the
order given, sessions/<i>/: poses_kitti.txt (every frame of the session in the merged frame,
rows as its run's) and summary.json (kept or left out and why, loops).
sessions/keyframes.csv says which session and keyframe each merged keyframe came from.
With GNSS in any kept session the merged frame is tied to the Earth: summary.json `geo` (as a
run's) from the reference's run, else from the first session that had GNSS
(`geo_from_session`); each GNSS session's summary says how far its own geo-reference puts its
keyframes from where the merged one does (`geo_disagreement_m`).
changes.ply / changes.csv: what changed between sessions (lidar_slam.merge.changes), point by
point (session, appeared or disappeared, object) and object by object. top_view.png: the map,
the sessions' trajectories and the changed objects from above (lidar_slam.merge.top_view).
Moving things (points seen in one scan only, lidar_slam.merge.moving) are left out.
"""

from __future__ import annotations

import csv
import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError, RunFailed
from lidar_slam.geo import GeoReference
from lidar_slam.geometry import inverse
from lidar_slam.io.atomic import atomic_path, write_text_atomic
from lidar_slam.io.trajectory import write_kitti_poses, write_tum
from lidar_slam.map.keyframes import DESCRIPTORS, KeyframeStore
from lidar_slam.merge.changes import ChangeCloud, detect_changes
from lidar_slam.merge.loops import (
    LoopSearch,
    SessionGrids,
    SessionLoop,
    find_loops,
    guided_loops,
)
from lidar_slam.merge.moving import moving_points
from lidar_slam.merge.session import Session, map_summary, open_session
from lidar_slam.merge.solve import Anchors, JointSolution, anchors, solve

log = logging.getLogger(__name__)

MERGE_OUTPUTS = ("keyframes", "sessions", "config.yaml", "summary.json", "poses_kitti.txt",
                 "poses_tum.txt", "loops.csv", "changes.ply", "changes.csv", "top_view.png")


@dataclass
class MergeResult:
    """What merge_runs wrote: per session (in the order given) its summary dict, the merged
    map's keyframe count, and the seconds it took."""

    sessions: list[dict]
    n_keyframes: int
    loops: int
    seconds: float
    changed_objects: int | None = None  # None: not looked for


def merge_runs(runs: list[Path], out: Path, reference: int = 0, min_loops: int = 2,
               max_verify: int = 3, overwrite: bool = False, guided_radius_m: float = 3.0,
               detect: bool = True, max_links: int = 2) -> MergeResult:
    """Merge the run folders into out (the --out rule: refused when it holds files, unless
    overwrite); raises InputError for a folder that is not a finished run with keyframes,
    RunFailed for a reference out of range or an --out that is one of the runs. max_links: the
    other sessions a keyframe is linked to at most (merge.loops)."""
    from lidar_slam.run.outdir import prepare_out_dir

    t0 = time.perf_counter()
    if not 0 <= reference < len(runs):
        raise RunFailed(f"--reference {reference}: give 0..{len(runs) - 1} (one of the "
                        f"{len(runs)} runs)")
    seen: set[Path] = set()
    copies: dict[bytes, Path] = {}
    for run in runs:
        if run.resolve() in seen:
            raise InputError(run, "given twice")
        seen.add(run.resolve())
        digest = _run_digest(run)  # a copy merged as a second session doubled the map
        if digest is not None and digest in copies:
            raise InputError(run, f"the same run as {copies[digest]} (the same poses and "
                                  f"keyframes): give each session once")
        if digest is not None:
            copies[digest] = run
    if out.resolve() in seen:
        raise RunFailed(f"{out}: --out is one of the runs to merge")
    sessions: list[Session] = []
    try:
        for i, run in enumerate(runs):
            sessions.append(open_session(i, run))
        prepare_out_dir(out, MERGE_OUTPUTS, overwrite)
        cfg = sessions[reference].map.cfg
        loops, search = find_loops(sessions, cfg, max_verify, max_links)
        anc = anchors(sessions, loops, reference, min_loops)
        sol = solve(sessions, loops, anc, reference)
        if guided_radius_m > 0 and len(sol.T_merged_kf) > 1:
            more, n_verified = guided_loops(sessions, sol.T_merged_kf, _kept(loops, sol), cfg,
                                            guided_radius_m, max_links)
            search.verified += n_verified
            search.accepted += len(more)
            loops += more
            sol = solve(sessions, loops, anc, reference)
        # A session whose every link the solve rejected hangs on its weak prior alone: out.
        for s in sessions:
            if s.index != reference and s.index in sol.T_merged_kf and not any(
                    k and s.index in (lp.a, lp.b) for lp, k in zip(loops, sol.kept)):
                anc.left_out[s.index] = "the joint solve rejected every loop linking it"
                del anc.T_ref_session[s.index]
                sol = solve(sessions, loops, anc, reference)
        moving = moving_points(sessions, sol.T_merged_kf)
        changes = detect_changes(sessions, sol.T_merged_kf, moving=moving) if detect else None
        n = _write(out, sessions, loops, search, anc, sol, reference, moving)
        if changes is not None:
            _write_changes(out, changes)
            _add_changes_to_sessions(out, sessions, changes)
        _write_top_view(out, sessions, sol, changes)
        summaries = [json.loads((out / "sessions" / str(s.index) / "summary.json").read_text())
                     for s in sessions]
    finally:
        for s in sessions:
            s.close()
    objects = (None if changes is None
               else len(set(changes.cluster[changes.cluster >= 0].tolist())))
    return MergeResult(summaries, n, sum(bool(k) for k in sol.kept), time.perf_counter() - t0,
                       objects)


def _kept(loops: list[SessionLoop], sol: JointSolution) -> list[SessionLoop]:
    return [lp for lp, k in zip(loops, sol.kept) if k]


def _write(out: Path, sessions: list[Session], loops: list[SessionLoop], search: LoopSearch,
           anc: Anchors, sol: JointSolution, reference: int,
           moving: dict[tuple[int, int], np.ndarray]) -> int:
    """The merged map folder (see the module doc), each keyframe's cloud without its moving
    points (merge.moving); returns its keyframe count."""
    ref = sessions[reference]
    store = KeyframeStore(out / "keyframes")
    poses, grids, origin = [], [], []
    try:
        for s in sessions:
            if s.index not in sol.T_merged_kf:
                continue
            T = sol.T_merged_kf[s.index]
            grids.append(SessionGrids(s, ref.map.cfg).grids)  # the merged map's one shape
            for k in range(len(s)):
                kf = s.map.keyframe(k)
                static = ~moving[(s.index, k)]
                store.add(int(s.map.frame_index[k]), T[k], kf.points[static],
                          None if kf.intensity is None else kf.intensity[static],
                          float(s.kf_stamps_s[k]))
                poses.append(T[k])
                origin.append((len(origin), s.index, k, int(s.map.frame_index[k])))
        if grids:
            np.concatenate(grids).astype("<f4").tofile(out / "keyframes" / DESCRIPTORS)
        store.flush(np.stack(poses), sum(len(g) for g in grids))
    finally:
        store.close()
    shutil.copyfile(ref.run_dir / "config.yaml", out / "config.yaml")
    (out / "sessions").mkdir(exist_ok=True)
    with atomic_path(out / "sessions" / "keyframes.csv") as tmp, open(tmp, "w", newline="") as fh:
        rows = csv.writer(fh)
        rows.writerow(["keyframe", "session", "session_keyframe", "frame"])
        rows.writerows(origin)
    _write_loops(out / "loops.csv", loops, sol)
    geo, _ = merged_geo(sessions, sol.T_merged_kf, reference)
    for s in sessions:
        _write_session(out / "sessions" / str(s.index), s, loops, anc, sol, reference,
                       sum(int(m.sum()) for (i, _), m in moving.items() if i == s.index), geo)
    frames = sol.T_merged_kf[reference]
    T_ref = ref.frames_in(frames)
    write_kitti_poses(out / "poses_kitti.txt", T_ref)
    write_tum(out / "poses_tum.txt", ref.stamps_s, T_ref)
    try:
        ref_summary = json.loads((ref.run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        ref_summary = {}
    summary = {"merged_from": [str(s.run_dir.resolve()) for s in sessions],
               "reference": reference,
               "keyframes": len(poses), "sessions_kept": sorted(sol.T_merged_kf),
               "loops_between_sessions": {"queries": search.queries,
                                          "candidates": search.candidates,
                                          "verified": search.verified,
                                          "accepted": search.accepted,
                                          "kept_by_solve": sum(bool(k) for k in sol.kept)},
               "loops_within_sessions": {"given": sol.intra_total, "kept": sol.intra_kept},
               "solve_s": sol.seconds}
    if isinstance(ref_summary, dict) and "auto_settings" in ref_summary:
        summary["auto_settings"] = ref_summary["auto_settings"]
    geo, geo_from = merged_geo(sessions, sol.T_merged_kf, reference)
    if geo is not None:
        summary["geo"] = geo.to_dict()
        summary["geo_from_session"] = geo_from
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    return len(poses)


def merged_geo(sessions: list[Session], T_merged_kf: dict[int, np.ndarray], reference: int
               ) -> tuple[GeoReference | None, int | None]:
    """Where the merged frame lies on the Earth, and which session says so: the reference's
    geo-reference when its run had GNSS, else the first kept session's that had (its T_enu_map
    carried by T_merged_session); (None, None) when no kept session had GNSS."""
    order = [reference] + [s.index for s in sessions if s.index != reference]
    for i in order:
        s = sessions[i]
        if s.index not in T_merged_kf or s.map.geo is None:
            continue
        T_merged_run = T_merged_kf[i][0] @ inverse(s.map.T_map_kf[0])
        return GeoReference(s.map.geo.enu, s.map.geo.T_enu_map @ inverse(T_merged_run)), i
    return None, None


def geo_disagreement_m(s: Session, geo: GeoReference, T_merged_kf: np.ndarray) -> np.ndarray:
    """How far (m) the merged geo-reference puts each keyframe of a session with its own GNSS
    from where that session's own geo-reference puts it (0 for the session it came from)."""
    own = s.map.geo.map_to_wgs84(s.map.T_map_kf[:, :3, 3])
    return np.linalg.norm(geo.enu.from_wgs84(own) - geo.map_to_enu(T_merged_kf[:, :3, 3]),
                          axis=1)


def _write_top_view(out: Path, sessions: list[Session], sol: JointSolution,
                    changes: ChangeCloud | None) -> None:
    """top_view.png: the merged map, the kept sessions' trajectories, the changed objects."""
    from lidar_slam.map.saved import open_map
    from lidar_slam.merge.top_view import plot_merged_top_view

    saved = open_map(out)
    try:
        points = saved.all_points_map()
    finally:
        saved.close()
    plot_merged_top_view(out / "top_view.png",
                         {s.index: s.frames_in(sol.T_merged_kf[s.index]) for s in sessions
                          if s.index in sol.T_merged_kf}, points, changes)


def _write_changes(out: Path, changes: ChangeCloud) -> None:
    """changes.ply (every changed point: x, y, z in the merged frame, session, appeared 1 /
    disappeared 0, object or -1) and changes.csv (one row per changed object)."""
    from lidar_slam.io.ply import write_ply

    write_ply(out / "changes.ply", {"x": changes.points[:, 0].astype(np.float32),
                                    "y": changes.points[:, 1].astype(np.float32),
                                    "z": changes.points[:, 2].astype(np.float32),
                                    "session": changes.session.astype(np.int32),
                                    "appeared": changes.appeared.astype(np.int32),
                                    "object": changes.cluster.astype(np.int32)})
    with atomic_path(out / "changes.csv") as tmp, open(tmp, "w", newline="") as fh:
        rows = csv.writer(fh)
        rows.writerow(["object", "change", "sessions", "points", "x", "y", "z", "size_x",
                       "size_y", "size_z"])
        for obj in sorted(set(changes.cluster[changes.cluster >= 0].tolist())):
            sel = changes.cluster == obj
            p = changes.points[sel]
            lo, hi = p.min(axis=0), p.max(axis=0)
            rows.writerow([obj, "appeared" if changes.appeared[sel][0] else "disappeared",
                           " ".join(map(str, sorted(set(changes.session[sel].tolist())))),
                           int(sel.sum()), *(f"{v:.3f}" for v in (lo + hi) / 2),
                           *(f"{v:.3f}" for v in hi - lo)])


def _add_changes_to_sessions(out: Path, sessions: list[Session], changes: ChangeCloud) -> None:
    """Each session's summary.json gets its changed points and objects (an object counts for
    the sessions whose points it holds)."""
    for s in sessions:
        path = out / "sessions" / str(s.index) / "summary.json"
        doc = json.loads(path.read_text())
        mine = changes.session == s.index
        counts = {}
        for kind, sel in (("appeared", mine & changes.appeared),
                          ("disappeared", mine & ~changes.appeared)):
            objects = set(changes.cluster[sel & (changes.cluster >= 0)].tolist())
            counts[f"{kind}_points"] = int(sel.sum())
            counts[f"{kind}_objects"] = len(objects)
        doc["changes"] = counts
        write_text_atomic(path, json.dumps(doc, indent=1) + "\n")


def _write_loops(path: Path, loops: list[SessionLoop], sol: JointSolution) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        rows = csv.writer(fh)
        rows.writerow(["session_a", "keyframe_a", "session_b", "keyframe_b", "distance",
                       "fitness", "rmse_m", "kept", "T_a_b"])
        for lp, kept in zip(loops, sol.kept):
            dist = "" if np.isnan(lp.distance) else f"{lp.distance:.4f}"
            rows.writerow([lp.a, lp.match, lp.b, lp.query, dist,
                           f"{lp.fitness:.4f}", f"{lp.rmse_m:.4f}",
                           "" if kept is None else int(kept),
                           " ".join(f"{v:.9g}" for v in lp.T_match_query[:3].ravel())])


def _write_session(folder: Path, s: Session, loops: list[SessionLoop], anc: Anchors,
                   sol: JointSolution, reference: int, n_moving: int,
                   geo: GeoReference | None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    mine = [(lp, k) for lp, k in zip(loops, sol.kept) if s.index in (lp.a, lp.b)]
    with_other: dict[str, dict[str, int]] = {}
    for lp, k in mine:
        other = str(lp.b if lp.a == s.index else lp.a)
        entry = with_other.setdefault(other, {"verified": 0, "kept": 0})
        entry["verified"] += 1
        entry["kept"] += bool(k)
    kept = s.index in sol.T_merged_kf
    doc = {"run": str(s.run_dir), "kept": kept, "reference": s.index == reference,
           "why": anc.left_out.get(s.index, "reference" if s.index == reference else
                                   "linked by verified loops"),
           "keyframes": len(s), "frames": len(s.T_run_frame),
           "loops_with_sessions": with_other,
           "loops_within": len(s.loops)}
    if kept:
        doc["moving_points_left_out"] = n_moving
        doc["gnss"] = s.map.geo is not None
        if geo is not None and s.map.geo is not None:
            d = geo_disagreement_m(s, geo, sol.T_merged_kf[s.index])
            doc["geo_disagreement_m"] = {"mean": round(float(d.mean()), 4),
                                         "max": round(float(d.max()), 4)}
        frames = s.frames_in(sol.T_merged_kf[s.index])
        write_kitti_poses(folder / "poses_kitti.txt", frames)
        doc["T_merged_session"] = np.round(sol.T_merged_kf[s.index][0]
                                           @ np.linalg.inv(s.map.T_map_kf[0]), 9).tolist()
    write_text_atomic(folder / "summary.json", json.dumps(doc, indent=1) + "\n")



def _run_digest(run: Path) -> bytes | None:
    """A hash of a run's poses and keyframe table (None when either is missing: open_session
    says what is wrong with it)."""
    import hashlib

    h = hashlib.sha256()
    for path in (run / "poses_kitti.txt", run / "keyframes" / "table.bin"):
        try:
            h.update(path.read_bytes())
        except OSError:
            return None
    return h.digest()


def sessions_of(map_dir: Path) -> tuple[list[Path], int]:
    """The run folders a saved map is made of and its reference: a merged map's (its
    summary.json `merged_from`, each still there), else the run itself (reference 0). What
    `run --extend MAP` merges the new run with."""
    summary = map_summary(map_dir)
    runs = summary.get("merged_from")
    if not runs:
        if not (map_dir / "keyframes" / "manifest.json").is_file():
            raise InputError(map_dir, "not a saved map (no keyframes/manifest.json)")
        return [map_dir], 0
    for run in runs:
        if not Path(run).is_dir():
            raise InputError(map_dir, f"merged from {run}, which is no longer there: "
                             "--extend merges the map's runs again")
    return [Path(r) for r in runs], int(summary.get("reference", 0))


def extend_map(map_dir: Path, new_run: Path, out: Path) -> MergeResult:
    """`run --extend`: the new run (already written) merged with the map's sessions into out,
    in the map's reference frame (the new run is the last session)."""
    runs, reference = sessions_of(map_dir)
    return merge_runs([*runs, new_run], out, reference, overwrite=True)
