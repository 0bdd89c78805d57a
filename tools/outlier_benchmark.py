"""Wrong loops against the back-end: add k wrong loop edges to a pose graph and compare the
solution with the clean graph's, for no kernel, Huber and GNC.

    python tools/outlier_benchmark.py GRAPH.g2o [--k 10 50 200] [--seeds 0 1 2 3 4] [--seed N]
        [--robust none huber gnc] [--init auto|file|chordal] [--markdown OUT.md] [--json OUT.json]

Each wrong loop joins a random pair of nodes (not neighbours, not already joined) with a random
relative pose (rotation uniform on SO(3) / SO(2), translation uniform in the box spanned by the
clean solution's positions) and the information matrix of the graph's median loop edge (median
log-determinant), so it is exactly as confident as a typical true loop. The reference is the
clean graph solved with the same --init and no kernel. Errors are node positions against that
reference, in the graph's units (m), RMS and max over all nodes; both solutions carry the same
prior on the first node, so no alignment is needed. "wrong rejected" counts the added loops the
solution does not keep (GNC weight 0; none / Huber: residual beyond the 99 % chi2 gate), "true
rejected" the original loops it drops.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lidar_slam.backend.g2o_optimize import PRIOR_SIGMAS
from lidar_slam.backend.pose_graph import PoseGraph
from lidar_slam.io.g2o import G2oEdge, G2oGraph, read_g2o, se2_matrix

log = logging.getLogger("outlier_benchmark")


def median_loop_information(g2o: G2oGraph) -> np.ndarray:
    """The information matrix of the loop edge (|i - j| != 1) with the median log-determinant
    (all edges when the graph has no loops)."""
    loops = [e for e in g2o.edges if abs(e.j - e.i) != 1] or g2o.edges
    logdet = np.array([np.linalg.slogdet(e.information)[1] for e in loops])
    return loops[int(np.argsort(logdet)[len(logdet) // 2])].information


def add_wrong_loops(g2o: G2oGraph, k: int, seed: int, extent_lo: np.ndarray,
                    extent_hi: np.ndarray) -> G2oGraph:
    """g2o with k wrong loop edges appended (see the module docstring); deterministic in seed."""
    rng = np.random.default_rng(seed)
    info = median_loop_information(g2o)
    keys = np.array(sorted(g2o.poses))
    joined = {(min(e.i, e.j), max(e.i, e.j)) for e in g2o.edges}
    wrong: list[G2oEdge] = []
    while len(wrong) < k:
        i, j = (int(v) for v in rng.choice(keys, 2, replace=False))
        pair = (min(i, j), max(i, j))
        if abs(i - j) == 1 or pair in joined:
            continue
        joined.add(pair)
        t = rng.uniform(extent_lo, extent_hi) - rng.uniform(extent_lo, extent_hi)
        if g2o.dims == 3:
            T = np.eye(4)
            T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
            T[:3, 3] = t
        else:
            T = se2_matrix(t[0], t[1], rng.uniform(-np.pi, np.pi))
        wrong.append(G2oEdge(i, j, T, info.copy()))
    return replace(g2o, edges=list(g2o.edges) + wrong)


def solve(g2o: G2oGraph, robust: str, init: str) -> PoseGraph:
    """The graph as `lidar-slam optimize` builds it (prior on the first node), solved."""
    graph = PoseGraph.from_g2o(g2o)
    first = min(g2o.poses)
    graph.add_prior(first, g2o.poses[first], *PRIOR_SIGMAS[g2o.dims])
    graph.solve(robust, init)
    return graph


def position_errors(poses: dict[int, np.ndarray], reference: dict[int, np.ndarray]
                    ) -> tuple[float, float]:
    """(RMS, max) of the position difference over all nodes."""
    keys = sorted(reference)
    d = np.array([poses[k][:-1, -1] - reference[k][:-1, -1] for k in keys])
    norms = np.linalg.norm(d, axis=1)
    return float(np.sqrt(np.mean(norms**2))), float(norms.max())


def run(g2o: G2oGraph, ks: list[int], seeds: list[int], kernels: list[str], init: str
        ) -> tuple[dict, list[dict]]:
    """The clean solution's summary and one row per (k, seed, kernel)."""
    t0 = time.perf_counter()
    clean = solve(g2o, "none", init)
    reference = clean.estimate
    pos = np.array([T[:-1, -1] for T in reference.values()])
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    n_edges = len(g2o.edges)
    clean_info = {"nodes": len(g2o.poses), "edges": n_edges,
                  "loop_edges": sum(abs(e.j - e.i) != 1 for e in g2o.edges),
                  "final_error": clean.summary.final_error, "init": clean.summary.init,
                  "seconds": time.perf_counter() - t0,
                  "extent": (hi - lo).tolist()}
    rows = []
    for k in ks:
        for seed in seeds:
            bad = add_wrong_loops(g2o, k, seed, lo, hi)
            for kernel in kernels:
                t0 = time.perf_counter()
                graph = solve(bad, kernel, init)
                seconds = time.perf_counter() - t0
                rms, worst = position_errors(graph.estimate, reference)
                keep = np.array(graph.summary.inlier)
                is_loop = np.array([e.is_loop for e in graph.edges])
                rows.append({"k": k, "seed": seed, "robust": kernel, "rms_m": rms, "max_m": worst,
                             "wrong_rejected": int((~keep[n_edges:]).sum()),
                             "true_rejected": int((~keep[:n_edges] & is_loop[:n_edges]).sum()),
                             "init": graph.summary.init, "seconds": seconds})
                log.info("k=%d seed=%d %s: RMS %.4f m, max %.4f m, wrong rejected %d/%d, "
                         "%.1f s", k, seed, kernel, rms, worst, rows[-1]["wrong_rejected"], k,
                         seconds)
    return clean_info, rows


def table(rows: list[dict], kernels: list[str]) -> str:
    """Markdown: a row per k, per kernel RMS and max (median over seeds / worst seed), wrong
    loops rejected (mean over seeds) and seconds (median)."""
    cols = ["k"]
    for kernel in kernels:
        cols += [f"{kernel} RMS m", f"{kernel} max m", f"{kernel} wrong rejected",
                 f"{kernel} s"]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for k in sorted({r["k"] for r in rows}):
        cells = [str(k)]
        for kernel in kernels:
            sel = [r for r in rows if r["k"] == k and r["robust"] == kernel]
            rms = np.array([r["rms_m"] for r in sel])
            worst = np.array([r["max_m"] for r in sel])
            rej = np.mean([r["wrong_rejected"] for r in sel])
            secs = np.median([r["seconds"] for r in sel])
            cells += [f"{np.median(rms):.3g} / {rms.max():.3g}",
                      f"{np.median(worst):.3g} / {worst.max():.3g}", f"{rej:.1f} / {k}",
                      f"{secs:.1f}"]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("graph", type=Path)
    ap.add_argument("--k", type=int, nargs="+", default=[10, 50, 200])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--seed", type=int, action="append", default=[],
                    help="a further seed (repeatable)")
    ap.add_argument("--robust", nargs="+", choices=["none", "huber", "gnc"],
                    default=["none", "huber", "gnc"])
    ap.add_argument("--init", choices=["auto", "file", "chordal"], default="auto")
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="# %(message)s")
    g2o = read_g2o(args.graph)
    seeds = list(dict.fromkeys(args.seeds + args.seed))
    clean, rows = run(g2o, args.k, seeds, args.robust, args.init)
    text = (f"{args.graph.name}: {clean['nodes']} nodes, {clean['edges']} edges "
            f"({clean['loop_edges']} loops); clean solution error {clean['final_error']:.6g} "
            f"(init {clean['init']}); seeds {seeds}; cells: median over seeds / worst seed\n\n"
            + table(rows, args.robust))
    print(text)
    if args.markdown is not None:
        args.markdown.write_text(text)
    if args.json is not None:
        args.json.write_text(json.dumps({"graph": str(args.graph), "init": args.init,
                                         "seeds": seeds, "clean": clean, "rows": rows},
                                        indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
