"""`lidar-slam optimize`: a g2o pose graph optimised with GTSAM (lidar_slam.backend)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path

import typer

from lidar_slam.cli.common import app, fail, log, reports_errors


class Robust(str, Enum):
    huber = "huber"
    gnc = "gnc"
    none = "none"


class Init(str, Enum):
    auto = "auto"
    file = "file"
    chordal = "chordal"


class Certify(str, Enum):
    auto = "auto"
    on = "on"
    off = "off"


class Weights(str, Enum):
    file = "file"
    sesync = "sesync"


@app.command()
@reports_errors
def optimize(
    graph: Path = typer.Argument(..., help="Input g2o (2D SE2 or 3D SE3:QUAT)."),
    out: Path = typer.Option(..., "--out", "-o", help="Optimised g2o to write."),
    robust: Robust = typer.Option(Robust.none, "--robust",
                                  help="Kernel on loop edges; gnc: graduated non-convexity "
                                       "(truncated least squares), odometry edges known inliers."),
    huber_k: float = typer.Option(1.345, "--huber-k", help="Huber threshold (whitened)."),
    init: Init = typer.Option(Init.auto, "--init",
                              help="Start: the file's poses, a global initialisation (chordal in "
                                   "3D, LAGO in 2D), or auto: both, the lower final error kept "
                                   "(with --robust gnc: the odometry chain)."),
    certify: Certify = typer.Option(Certify.auto, "--certify",
                                    help="Shonan rotation certificate (auto: graphs up to "
                                         "6000 nodes)."),
    weights: Weights = typer.Option(Weights.file, "--weights",
                                    help="sesync: SE-Sync's isotropic weights instead of the "
                                         "file's information (its optimum is SE-Sync's p*)."),
    max_iterations: int = typer.Option(100, "--max-iterations", min=1,
                                       help="Levenberg-Marquardt iterations at most."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out."),
) -> None:
    """Optimise a pose graph with GTSAM (prior on the first pose): LM, Huber or GNC."""
    from lidar_slam.backend.g2o_optimize import optimize_g2o

    if robust == Robust.huber and not huber_k > 0:
        raise fail(f"--huber-k must be positive, got {huber_k}")
    if not out.parent.is_dir():
        raise fail(f"{out}: cannot write it, {out.parent} is not a folder")
    if not graph.is_file():
        raise fail(f"{graph}: {'a folder, not a g2o file' if graph.is_dir() else 'does not exist'}")
    if out.exists() and out.resolve() == graph.resolve():
        raise fail(f"{out}: --out is the input graph; write the optimised one elsewhere")
    if out.is_dir():
        raise fail(f"{out}: --out is a folder, not a file")
    if out.exists() and not overwrite:
        raise fail(f"{out}: already exists; pass --overwrite")
    if robust != Robust.huber and huber_k != 1.345:
        log.warning("--huber-k: not used without --robust huber")
    rep = optimize_g2o(graph, out, robust=robust.value, huber_k=huber_k,
                       max_iterations=max_iterations, init=init.value, certify=certify.value,
                       weights=weights.value)
    typer.echo(f"graph={graph} dims={rep.dims} vertices={rep.n_vertices} edges={rep.n_edges} "
               f"loop_edges={rep.n_loop_edges} robust={rep.robust} "
               f"repaired_information={rep.n_repaired} weights={weights.value}")
    tried = ", ".join(f"{name}={'skipped (starts higher)' if err is None else f'{err:.6g}'}"
                      for name, err in rep.candidates)
    typer.echo(f"init={rep.init} ({tried})")
    typer.echo(f"initial_error={rep.initial_error:.6g}")
    typer.echo(f"final_error={rep.final_error:.6g}")
    typer.echo(f"sesync_objective={rep.sesync_objective:.6g}")
    label = "rejected" if rep.robust == "gnc" else "outside_99pct_gate"
    typer.echo(f"loops: {label}={rep.n_loops_rejected} of {rep.n_loop_edges}")
    cert = rep.certificate
    if cert is None:
        typer.echo("rotations_certified=not_run")
    elif cert.certified:
        typer.echo(f"rotations_certified=yes (ShonanAveraging{rep.dims}: rotation-only problem at "
                   f"its global optimum, lambda_min={cert.lambda_min:.3g}, "
                   f"{cert.seconds:.2f} s)")
    else:
        why = cert.note or f"lambda_min={cert.lambda_min:.3g}"
        typer.echo(f"rotations_certified=no ({why}, {cert.seconds:.2f} s)")
    iterations = "-" if rep.iterations is None else rep.iterations
    typer.echo(f"iterations={iterations} seconds={rep.seconds:.3f} "
               f"cpu_seconds={rep.cpu_seconds:.3f} load_seconds={rep.load_seconds:.3f}")
    typer.echo(f"wrote {out}")
