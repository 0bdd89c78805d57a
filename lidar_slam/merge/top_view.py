"""The merged map from above (MAP/top_view.png): the map's point density, each kept session's
trajectory in its own colour, and the changed objects (appeared: green, disappeared: red),
numbered as in changes.csv. Drawn as `run`'s top view (lidar_slam.eval.evaluate)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_slam.merge.changes import ChangeCloud


def plot_merged_top_view(path: Path, trajectories: dict[int, np.ndarray],
                         map_points: np.ndarray, changes: ChangeCloud | None) -> None:
    """trajectories: session -> its frames' poses (F, 4, 4) in the merged frame; map_points
    (N, >=2) the merged map's points; changes: what merge found (None: not looked for)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lidar_slam.eval.evaluate import draw_map_density, save_png

    xy_all = np.concatenate([T[:, :2, 3] for T in trajectories.values()])
    fig = Figure(figsize=(8, 8))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_map_density(ax, map_points, xy_all)
    colours = [f"C{k}" for k in (0, 1, 4, 5, 6, 7, 8, 9)]  # no green or red: those are changes
    for n, (s, T) in enumerate(sorted(trajectories.items())):
        c = colours[n % len(colours)]
        ax.plot(T[:, 0, 3], T[:, 1, 3], "-", color=c, lw=1.0,
                label=f"session {s} ({len(T)} frames)")
        ax.plot(T[0, 0, 3], T[0, 1, 3], "o", color=c, ms=5)
    title = "merged map from above: sessions (o: start)"
    if changes is not None and len(changes.points):
        for appeared, colour, name in ((True, "tab:green", "appeared"),
                                       (False, "tab:red", "disappeared")):
            sel = (changes.appeared == appeared) & (changes.cluster >= 0)
            objects = sorted(set(changes.cluster[sel].tolist()))
            if not objects:
                continue
            ax.scatter(changes.points[sel, 0], changes.points[sel, 1], s=4, c=colour,
                       label=f"{name} ({len(objects)} objects)", zorder=3)
            for obj in objects:
                p = changes.points[changes.cluster == obj, :2]
                ax.annotate(str(obj), p.max(axis=0), color=colour, fontsize=8, zorder=4)
        title += ", changed objects (numbers: changes.csv)"
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    save_png(fig, path)
