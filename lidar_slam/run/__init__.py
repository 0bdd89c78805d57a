"""The runner: one input into one run folder, with the --out rules, signals, progress, resume
from checkpoints and the outputs. `lidar-slam run`, `localize` and every `batch` task call it.

- runner.run_sequence: the one run driver (a RunOutcome; RunFailed when nothing was written)
- localize.localize_sequence: the same for localisation in a saved map
- outdir: the --out rules (prepare_out_dir, RUN_OUTPUTS) and the range of scans read
- signals, progress: Ctrl-C / SIGTERM handling, and progress on stderr
- checkpoint, outputs: the checkpoints a run resumes from, and the files it writes
"""

from lidar_slam.run.outdir import RUN_OUTPUTS, prepare_out_dir, scan_range
from lidar_slam.run.runner import RunOutcome, run_sequence

__all__ = ["RUN_OUTPUTS", "RunOutcome", "prepare_out_dir", "run_sequence", "scan_range"]
