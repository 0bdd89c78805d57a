"""`lidar-slam export`: a run's map as points (PLY/PCD/LAS/LAZ) or an occupancy grid."""

from __future__ import annotations

import math
from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from lidar_slam.cli.common import app, fail, log, reports_errors
from lidar_slam.run.outdir import prepare_out_dir

MIN_CELL_M = 1e-3  # --voxel / --resolution: a millimetre, below any lidar's noise


def _parse_band(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise fail(f"--band: expected LOW,HIGH in metres above the ground, got {text!r}"
                    ) from None
    if not 0 <= lo < hi < math.inf:
        raise fail(f"--band: need 0 <= LOW < HIGH, both finite, got {text!r}")
    return lo, hi


class PointFormatOption(str, Enum):
    ply = "ply"
    pcd = "pcd"
    las = "las"
    laz = "laz"


OCCUPANCY_OUTPUTS = ("map.png", "map.yaml")


@app.command()
@reports_errors
def export(
    run_dir: Path = typer.Argument(..., help="Run folder (a finished `run`)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o",
                                       help="Point file to write; with --occupancy the folder "
                                            "for map.png / map.yaml (default: RUN_DIR)."),
    fmt: Optional[PointFormatOption] = typer.Option(None, "--format",
                                                    help="Point format (default: --out's "
                                                         "suffix)."),
    voxel: Optional[float] = typer.Option(None, "--voxel",
                                          help="Keep one point per voxel of this size (m)."),
    occupancy: bool = typer.Option(False, "--occupancy",
                                   help="Write a 2-D occupancy grid (ROS map_server format)."),
    resolution: float = typer.Option(0.1, "--resolution", help="Occupancy cell size (m)."),
    band: str = typer.Option("0.3,2.0", "--band",
                             help="Heights above the ground that are obstacles (m, LOW,HIGH)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output."),
) -> None:
    """Export a run's map: points as PLY / PCD / LAS / LAZ, or an occupancy grid.

    Points are the keyframe clouds placed with the final poses (the frame of poses_kitti.txt),
    with intensity and the id of their keyframe. A run with GNSS gives LAS / LAZ in UTM
    (easting, northing, ellipsoidal height) with the CRS, and a map.yaml with its geo origin.
    """
    from lidar_slam.map.saved import open_map

    unused = ([n for n, v in (("--voxel", voxel), ("--format", fmt)) if v is not None]
              if occupancy else [n for n, v, d in (("--resolution", resolution, 0.1),
                                                    ("--band", band, "0.3,2.0")) if v != d])
    if unused:  # taken quietly before, as if they had done something
        log.warning("%s: not used %s --occupancy", ", ".join(unused),
                    "with" if occupancy else "without")
    for name, value in (("--voxel", voxel), ("--resolution", resolution)):
        if value is not None and not value > 0:
            raise fail(f"{name} must be positive, got {value:g}")
        if value is not None and not MIN_CELL_M <= value < math.inf:
            # 1e-20 overflowed the voxel indices (2214 of 99,659 points kept), inf kept one
            raise fail(f"{name} must be a finite size of at least {MIN_CELL_M:g} m, got "
                       f"{value:g}")
    if occupancy:
        from lidar_slam.map.occupancy import OccupancyParams, build_grid, write_map_server

        params = OccupancyParams(resolution_m=resolution, band_m=_parse_band(band))
        folder = out if out is not None else run_dir
        saved = open_map(run_dir)
        if folder == run_dir or out is None:
            held = [n for n in OCCUPANCY_OUTPUTS if (folder / n).exists()]
            if held and not overwrite:
                raise fail(f"{folder}: already holds {', '.join(held)}; pass --overwrite")
        else:
            prepare_out_dir(folder, OCCUPANCY_OUTPUTS, overwrite)
        try:
            grid = build_grid(saved, params)
        finally:
            saved.close()
        png, yaml_path = write_map_server(grid, folder, params)
        h, w = grid.state.shape
        typer.echo(f"wrote {png} and {yaml_path} ({w} x {h} cells of {resolution:g} m)")
        return
    from lidar_slam.map.export import (
        PointFormat,
        format_of,
        map_points,
        require_laspy,
        write_points,
    )

    if out is None:
        raise fail("--out FILE is needed (or --occupancy)")
    kind = format_of(out, None if fmt is None else PointFormat(fmt.value))
    if out.is_dir():
        raise fail(f"{out}: --out is a folder, not a file")
    own = _run_file(run_dir, out)
    if own is not None:
        raise fail(f"{out}: --out is the run's own {own}; export elsewhere")
    if out.exists() and not overwrite:
        raise fail(f"{out}: already exists; pass --overwrite")
    if kind in (PointFormat.las, PointFormat.laz):
        require_laspy()  # before reading the map
    saved = open_map(run_dir)
    try:
        points = map_points(saved, voxel)
    finally:
        saved.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    n = write_points(out, kind, points)
    typer.echo(f"wrote {n} points to {out}")


def _run_file(run_dir: Path, out: Path) -> str | None:
    """The name of the file or folder of the run (run.outdir.RUN_OUTPUTS: its poses, its
    keyframes the map is read from, ...) that out is or lies in, else None: an export never
    replaces what it reads or what the run wrote."""
    from lidar_slam.run.outdir import RUN_OUTPUTS

    try:
        rel = out.resolve().relative_to(run_dir.resolve())
    except ValueError:
        return None
    return rel.parts[0] if rel.parts and rel.parts[0] in RUN_OUTPUTS else None
