"""`lidar-slam merge`: several runs (sessions) into one saved map (lidar_slam.merge)."""

from __future__ import annotations

from pathlib import Path

import typer

from lidar_slam.cli.common import app, reports_errors


@app.command()
@reports_errors
def merge(
    runs: list[Path] = typer.Argument(..., help="Run folders (finished `run`s, each with its "
                                      "keyframes/ map), one per session, in any frames."),
    out: Path = typer.Option(..., "--out", "-o", help="Merged map folder to write."),
    reference: int = typer.Option(0, "--reference", min=0,
                                  help="The session (0-based, in the order given) whose frame "
                                       "the merged map is in."),
    min_loops: int = typer.Option(2, "--min-loops", min=1,
                                  help="Verified loops that must agree to link two sessions."),
    changes: bool = typer.Option(True, "--changes/--no-changes",
                                 help="Find what appeared and disappeared between sessions "
                                      "(MAP/changes.ply, changes.csv)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the files in --out."),
) -> None:
    """Merge sessions recorded at different times into one map that `localize` and `export`
    open. No shared origin is needed: loops between sessions (Scan Context, the loop-closure
    ICP gates) place them, one robust (GNC) solve joins them; a session with no verified
    overlap is reported and left out.
    """
    from lidar_slam.merge.build import merge_runs

    result = merge_runs(runs, out, reference, min_loops, overwrite=overwrite, detect=changes)
    for i, s in enumerate(result.sessions):
        loops = sum(v["kept"] for v in s["loops_with_sessions"].values())
        typer.echo(f"session {i}: {'kept' if s['kept'] else 'LEFT OUT'} ({s['why']}), "
                   f"{s['keyframes']} keyframes, {loops} loops with other sessions kept")
    changed = ("" if result.changed_objects is None
               else f", {result.changed_objects} changed objects")
    typer.echo(f"wrote {out}: {result.n_keyframes} keyframes, {result.loops} loops between "
               f"sessions{changed}, {result.seconds:.1f} s")
