"""The --out rules of the commands that write a folder, and the range of scans a run reads."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from lidar_slam.errors import RunFailed

log = logging.getLogger("lidar_slam")

# Every file and folder `run` writes into --out: --overwrite deletes these and nothing else.
RUN_OUTPUTS = ("poses_kitti.txt", "poses_tum.txt", "odometry_kitti.txt", "map.ply", "loops.csv",
               "covariances.csv", "graph.g2o", "config.yaml", "summary.json",
                "error_traceback.txt", "keyframes", "checkpoint", "gnss_fixes.csv",
                "poses_enu.txt", "poses_wgs84.csv",  # with GNSS
               "top_view.png")


def prepare_out_dir(out: Path, ours: tuple[str, ...], overwrite: bool, resume: bool = False
                    ) -> bool:
    """The one rule for commands that write a folder: an --out that already holds files is
    refused unless --overwrite (our files are deleted first) or --resume. Returns True when
    there is a run to resume."""
    if overwrite and resume:
        raise RunFailed("--overwrite and --resume exclude each other")
    if out.exists() and not out.is_dir():
        raise RunFailed(f"{out}: --out is a file, not a folder")
    blocker = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise RunFailed(f"{out}: cannot create --out: {blocker} is a file, not a folder")
    held = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if held and resume:
        return True
    if held and not overwrite:
        flag = "--overwrite or --resume" if ours is RUN_OUTPUTS else "--overwrite"
        raise RunFailed(f"{out}: --out already holds files ({', '.join(held[:3])}"
                        f"{', ...' if len(held) > 3 else ''}); pass {flag}")
    doomed = [out / name for name in held if name in ours]
    locked = _undeletable(out, doomed)
    if locked is not None:  # found before anything is deleted: the old run stays whole
        raise RunFailed(f"{locked}: --overwrite cannot delete in it (no write permission); "
                        f"nothing was deleted")
    for path in doomed:
        try:  # a link is deleted, never followed
            path.unlink() if path.is_symlink() or not path.is_dir() else shutil.rmtree(path)
        except OSError as exc:  # rmtree names the entry alone: say where it is
            raise RunFailed(f"{path}: --overwrite could not delete it "
                            f"({exc.strerror or exc})") from None
    out.mkdir(parents=True, exist_ok=True)  # fail before the run, not after it
    return False


def _undeletable(out: Path, doomed: list[Path]) -> Path | None:
    """The first folder whose entries --overwrite must delete but cannot (no read, write or
    search permission: a read-only copy, another user's run), or None. Links are deleted, not
    followed."""
    import os

    folders = [out] if doomed else []

    def unlisted(err: OSError) -> None:  # a folder os.walk cannot list: rmtree cannot either
        folders.append(Path(err.filename))

    for path in doomed:
        if path.is_dir() and not path.is_symlink():
            folders += [Path(root) for root, _, _ in os.walk(path, onerror=unlisted)]
    return next((f for f in folders if not os.access(f, os.R_OK | os.W_OK | os.X_OK)), None)


def refuse_input_as_out(out: Path, inputs: dict[str, Path | None]) -> None:
    """--out may not be one of the command's inputs ({what: path}), nor hold one: --overwrite
    would delete the input's files before they are read, and the outputs written into an
    input folder would be read back as its data next time."""
    o = out.resolve()
    for what, path in inputs.items():
        if path is None:
            continue
        p = Path(path).resolve()
        if p == o:
            raise RunFailed(f"{out}: --out is the {what}; write the outputs to another folder")
        if o in p.parents and p.relative_to(o).parts[0] in RUN_OUTPUTS + ("run",):
            raise RunFailed(f"{out}: --out holds the {what} ({path}); write the outputs to "
                            f"another folder")


def refuse_out_among_scans(out: Path, files: list[Path] | None) -> None:
    """--out may not be a folder the input's scans are read from (a KITTI sequence's velodyne/,
    a folder's scans/): the outputs written there (map.ply) would be read back as scans next
    time. files: the input's scan files (None for a recording)."""
    if files is None or len(files) < 2:  # a recording, or one scan file: nothing read back
        return
    if out.resolve() in {p.resolve() for p in {Path(f).parent for f in files}}:
        raise RunFailed(f"{out}: --out is the folder the input's scans are read from; write the "
                        f"outputs to another folder")


def check_rrd(rrd: Path | None, out: Path, inputs: list[Path], overwrite: bool,
              resume: bool) -> None:
    """--rrd FILE: never an input (a scan, the input itself) nor a folder, and an existing file
    only with --overwrite (or --resume: the killed run's recording is made again), as --out."""
    if rrd is None:
        return
    r = rrd.resolve()
    if any(r == Path(p).resolve() for p in inputs):
        raise RunFailed(f"{rrd}: --rrd is an input of the run; record to another file")
    if rrd.is_dir():
        raise RunFailed(f"{rrd}: --rrd is a folder; give the recording's file name (run.rrd)")
    if out.resolve() in r.parents and r.relative_to(out.resolve()).parts[0] in RUN_OUTPUTS:
        raise RunFailed(f"{rrd}: --rrd is one of the run's own outputs; record to another file")
    if rrd.exists() and not (overwrite or resume):
        raise RunFailed(f"{rrd}: --rrd already exists; pass --overwrite to replace it")


def discard_run(out: Path, created: bool) -> None:
    """Remove what a run that produced no frame wrote (and --out itself if the run made it), so
    no 0-frame run folder is left behind."""
    for name in RUN_OUTPUTS:
        if name == "error_traceback.txt":
            continue
        path = out / name
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()
    if created and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def say_short_range(path: Path, start: int, n_scans: int | None, available: int) -> None:
    """One warning when --n-scans asks for more scans than there are from --start on."""
    if n_scans is not None and n_scans > available - start:
        log.warning("%s: --n-scans %d from --start %d: only %d scans there; reading those",
                    path, n_scans, start, available - start)


def scan_range(path: Path, start: int, n_scans: int | None, available: int,
               unit: str = "scan", count: str | None = None) -> int:
    """How many of the `available` scans (or poses) from --start on a command reads (all, or
    --n-scans at most); a --start past the last one is an error naming `path`."""
    if start >= available:
        raise RunFailed(f"{path}: --start {start} is past the last {unit} "
                        f"({f'{available} {unit}s' if count is None else count})")
    return available - start if n_scans is None else min(n_scans, available - start)
