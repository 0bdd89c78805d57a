"""The localisation driver: scans of one input localised in a saved map, into one folder, as
`lidar-slam localize` does (the --out rules, signals, progress, the scan loop, the outputs)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from lidar_slam.errors import EXIT_BAD_INPUT, EXIT_INTERRUPTED, LidarSlamError, RunFailed
from lidar_slam.run.outdir import (
    prepare_out_dir,
    refuse_input_as_out,
    say_short_range,
    scan_range,
)
from lidar_slam.run.progress import progress as make_progress
from lidar_slam.run.signals import StopSignals

log = logging.getLogger(__name__)


def parse_initial_pose(text: str | None):
    """--initial-pose x,y,z,yaw (m, m, m, deg) -> T_map_scan, or None."""
    if text is None:
        return None
    from lidar_slam.localize import initial_pose_matrix

    try:
        x, y, z, yaw = (float(v) for v in text.split(","))
        if not all(abs(v) < float("inf") for v in (x, y, z, yaw)):  # nan ran unsaid
            raise ValueError
    except ValueError:
        raise RunFailed(f"--initial-pose: expected x,y,z,yaw, finite (metres, metres, metres, "
                        f"degrees), got {text!r}") from None
    return initial_pose_matrix(x, y, z, yaw)


@dataclass
class LocalizeOutcome:
    """What localize_sequence wrote: the summary, and the one-line error of a localisation that
    stopped early (its frames so far written)."""

    summary: dict
    failure: RunFailed | None = None


def _stats(loc, frames: list, wall_s: float, load_s: float, loop_s: float) -> dict:
    st, n = loc.stats, len(frames)
    return {"relocalisations": st.relocalisations,
            "relocalisation_attempts": st.relocalisation_attempts,
            "wall_s": wall_s, "fps": n / wall_s, "map_load_s": load_s,
            "fps_after_load": n / loop_s if loop_s > 0 else 0.0,
            "localize_ms_per_frame": 1e3 * st.compute_s() / n,
            "track_ms_per_frame": 1e3 * st.seconds["track"] / n,
            "relocalise_ms_per_attempt": (1e3 * st.seconds["relocalise"]
                                          / max(st.relocalisation_attempts, 1))}


def localize_sequence(data: Path, map_dir: Path, out: Path, *, config: Path | None = None,
                      start: int = 0, n_scans: int | None = None, topic: str | None = None,
                      initial_pose: str | None = None, overwrite: bool = False,
                      progress: bool = True) -> LocalizeOutcome:
    """Localise DATA in the map of the run folder map_dir and write poses, status.csv and the
    summary into out (LOCALIZE_OUTPUTS), without printing. Raises RunFailed when nothing was
    localised (nothing written)."""
    from lidar_slam import __version__
    from lidar_slam.io.sources import open_source, read_ahead
    from lidar_slam.localize import Localizer, Status
    from lidar_slam.map.saved import open_map
    from lidar_slam.provenance import git_commit
    from lidar_slam.run.outputs import LOCALIZE_OUTPUTS, write_localization

    refuse_input_as_out(out, {"map": map_dir, "input": data})
    T_init = parse_initial_pose(initial_pose)
    t0 = time.perf_counter()
    saved = open_map(map_dir, config)
    source = open_source(data, topic=topic,
                         kitti_vertical_correction=saved.cfg.data.kitti_vertical_correction)
    total = scan_range(data, start, n_scans, len(source))
    say_short_range(data, start, n_scans, len(source))
    prepare_out_dir(out, LOCALIZE_OUTPUTS, overwrite)
    loc = Localizer(saved, T_init)
    load_s = time.perf_counter() - t0
    frames: list = []
    error = None
    stop = StopSignals()
    with stop:
        bar = make_progress(f"localize {source.name}", total, shown=progress)
        t1 = time.perf_counter()
        try:
            for scan in read_ahead(source.scans(start, total)):
                if stop.received:
                    break
                frames += loc.step(scan)
                bar.tick()
        except KeyboardInterrupt:
            stop.received = True
        except LidarSlamError as exc:
            error = str(exc)
        finally:
            bar.close()
        frames += loc.finish()
        loop_s = time.perf_counter() - t1
        with stop.deferred():
            saved.close()
            if not frames:
                raise RunFailed(error or f"{data}: no scan localised; nothing written",
                                EXIT_INTERRUPTED if stop.received and not error
                                else EXIT_BAD_INPUT)
            lost = sum(f.status == Status.LOST for f in frames)
            located = lost < len(frames)
            if lost and located:
                log.warning("%d of %d frames lost (status.csv): their poses are the motion "
                            "model's prediction, or before the first localisation the initial "
                            "pose (the map origin without one)", lost, len(frames))
            # None localised: their poses would be the initial pose (or the map origin) repeated,
            # not a result; status.csv and the summary say what was tried.
            summary = write_localization(out, frames, poses=located, summary={
                **_stats(loc, frames, time.perf_counter() - t0, load_s, loop_s),
                "map": str(map_dir), "map_keyframes": len(saved),
                "input": str(data), "input_kind": source.kind,
                "topic": source.topic, "start": start, "initial_pose": initial_pose,
                "interrupted": stop.received, "stopped_by_error": error,
                "version": __version__, "git_commit": git_commit()})
    failure = None
    if not located and not stop.received and not error:
        failure = RunFailed(f"{data}: none of its {len(frames)} frames localised in the map "
                            f"{map_dir} (another place, or give --initial-pose); {out} holds "
                            f"status.csv and summary.json, no poses")
    elif error:
        failure = RunFailed(f"{error} (stopped there; frames so far written to {out})")
    elif stop.received:
        failure = RunFailed(f"interrupted; the {len(frames)} frames so far written to {out}",
                            EXIT_INTERRUPTED)
    return LocalizeOutcome(summary, failure)
