"""Run optimize_g2o (plain LM, prior on the first node) over every se-sync g2o file; print a table
next to the gtsam_err@LM column of ../shared/data/posegraphs/README.txt.

    python tools/bench_posegraphs.py [--data DIR] [--robust huber|none] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
import time
from pathlib import Path

from lidar_slam.backend.g2o_optimize import optimize_g2o

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraphs"


def readme_errors(readme: Path) -> dict[str, float]:
    """gtsam_err@LM per file stem, from the sanity-check table of the posegraphs README."""
    out: dict[str, float] = {}
    text = readme.read_text()
    block = text.split("gtsam_err@LM", 1)[1] if "gtsam_err@LM" in text else ""
    for line in block.splitlines()[1:]:
        m = re.match(r"\s+([\w-]+)\s+([\d.]+)\s+[\d.]+\s+[\d.]+", line)
        if not m:
            break
        out[m.group(1)] = float(m.group(2))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--robust", choices=["none", "huber"], default="none")
    ap.add_argument("--only", nargs="*", default=None, help="file stems to run")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="# %(levelname)s %(message)s")
    ref = readme_errors(args.data / "README.txt")
    files = sorted((args.data / "se-sync").glob("*.g2o"), key=lambda p: p.stat().st_size)
    if args.only:
        files = [f for f in files if f.stem in args.only]
    cols = ["file", "dims", "vertices", "edges", "initial_error", "final_error", "README_LM",
            "rel_diff_%", "iters", "lm_s", "total_s"]
    print("\t".join(cols), flush=True)
    total = 0.0
    for f in files:
        t0 = time.perf_counter()
        r = optimize_g2o(f, None, robust=args.robust)
        wall = time.perf_counter() - t0
        total += wall
        readme = ref.get(f.stem)
        diff = "" if readme is None else f"{100 * (r.final_error - readme) / readme:+.3f}"
        print("\t".join([f.name, str(r.dims), str(r.n_vertices), str(r.n_edges),
                         f"{r.initial_error:.6g}", f"{r.final_error:.6g}",
                         "" if readme is None else f"{readme:g}", diff, str(r.iterations),
                         f"{r.seconds:.2f}", f"{wall:.2f}"]), flush=True)
    print(f"# {len(files)} files, {total:.1f} s total", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
