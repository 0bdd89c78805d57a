"""Run optimize_g2o over every se-sync g2o file and print one table: gtsam errors, the start kept,
SE-Sync's objective next to its certified optimum p*, Shonan's rotation certificate, seconds.

    python tools/bench_posegraphs.py [--data DIR] [--init auto|file|chordal]
        [--robust none|huber|gnc] [--certify auto|on|off] [--weights file|sesync]
        [--compare-file] [--only NAME ...] [--markdown OUT.md] [--json OUT.json]

--compare-file also runs plain LM from the file's guess (the regression bar: auto must not end
higher). p* comes from ../shared/data/posegraphs/reference_costs.tsv; gtsam_err@LM of its README
is shown where it lists one.
"""

from __future__ import annotations

import argparse
import csv
import json
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


def reference_optima(tsv: Path) -> dict[str, float]:
    """SE-Sync's certified optimum p* per file stem, from reference_costs.tsv."""
    lines = [ln for ln in tsv.read_text().splitlines() if ln and not ln.startswith("#")]
    out = {}
    for row in csv.DictReader(lines, delimiter="\t"):
        if row["present_here"] == "yes":
            out[Path(row["file"]).stem] = float(row["optimal_objective"])
    return out


def _fmt(value, spec: str = ".6g") -> str:
    return "" if value is None else format(value, spec)


def run_one(path: Path, args, p_star: float | None, readme: float | None) -> dict:
    t0 = time.perf_counter()
    r = optimize_g2o(path, None, robust=args.robust, init=args.init, certify=args.certify,
                     weights=args.weights)
    row = {"file": path.stem, "dims": r.dims, "vertices": r.n_vertices, "edges": r.n_edges,
           "repaired": r.n_repaired, "init": r.init,
           "tried": {name: err for name, err in r.candidates},
           "initial_error": r.initial_error, "final_error": r.final_error,
           "sesync_objective": r.sesync_objective, "p_star": p_star,
           "F_over_p_star": None if p_star is None else r.sesync_objective / p_star,
           "seconds": r.seconds, "cpu_seconds": r.cpu_seconds, "load_seconds": r.load_seconds,
           "certified": None if r.certificate is None else r.certificate.certified,
           "certify_seconds": r.certify_seconds, "readme_lm": readme,
           "wall_s": time.perf_counter() - t0}
    if args.compare_file:
        f = optimize_g2o(path, None, robust=args.robust, init="file", weights=args.weights)
        row["file_lm_final_error"] = f.final_error
        row["file_lm_seconds"] = f.seconds
    return row


def markdown(rows: list[dict], compare_file: bool) -> str:
    cols = ["graph", "dims", "nodes", "edges", "init", "initial_error", "final_error"]
    if compare_file:
        cols += ["LM from file", "LM from file s"]
    cols += ["sesync_objective", "p*", "F / p*", "seconds", "rotations certified (Shonan s)"]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cert = ("not run" if r["certified"] is None else
                f"{'yes' if r['certified'] else 'no'} ({r['certify_seconds']:.1f})")
        vals = [r["file"], r["dims"], r["vertices"], r["edges"], r["init"],
                _fmt(r["initial_error"]), _fmt(r["final_error"])]
        if compare_file:
            vals += [_fmt(r["file_lm_final_error"]), _fmt(r["file_lm_seconds"], ".2f")]
        vals += [_fmt(r["sesync_objective"]), _fmt(r["p_star"], ".4g"),
                 _fmt(r["F_over_p_star"], ".4f"), f"{r['seconds']:.2f}", cert]
        out.append("| " + " | ".join(str(v) for v in vals) + " |")
    return "\n".join(out) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--init", choices=["auto", "file", "chordal"], default="auto")
    ap.add_argument("--robust", choices=["none", "huber", "gnc"], default="none")
    ap.add_argument("--certify", choices=["auto", "on", "off"], default="auto")
    ap.add_argument("--weights", choices=["file", "sesync"], default="file",
                    help="sesync: solve SE-Sync's own problem (isotropic weights)")
    ap.add_argument("--compare-file", action="store_true",
                    help="also run plain LM from the file's guess")
    ap.add_argument("--only", nargs="*", default=None, help="file stems to run")
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="# %(levelname)s %(message)s")
    readme = readme_errors(args.data / "README.txt")
    optima = reference_optima(args.data / "reference_costs.tsv")
    files = sorted((args.data / "se-sync").glob("*.g2o"), key=lambda p: p.stat().st_size)
    if args.only:
        files = [f for f in files if f.stem in args.only]
    rows = []
    for f in files:
        row = run_one(f, args, optima.get(f.stem), readme.get(f.stem))
        rows.append(row)
        print("\t".join(f"{k}={_fmt(v) if isinstance(v, float) else v}" for k, v in row.items()),
              flush=True)
    table = markdown(rows, args.compare_file)
    print(table)
    if args.markdown is not None:
        args.markdown.write_text(table)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    print(f"# {len(rows)} files, {sum(r['wall_s'] for r in rows):.1f} s total", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
