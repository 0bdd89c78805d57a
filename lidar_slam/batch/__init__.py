"""Many sequences at once: `lidar-slam batch` and a `simulate` of several sequences.

- jobs: a sequence as a job (BatchJob), the inputs and their folder names, run_job (a Ray task)
- fleet: the Ray fleet the jobs run on (the only module that imports ray)
- progress: progress of many jobs on stderr
- runner: fan_out (jobs to the fleet, outcomes back) and run_batch (with the results table)
- results: the results table (results.md, .json, .csv)
"""

from lidar_slam.batch.jobs import BatchJob, expand_inputs, run_job, sequence_names
from lidar_slam.batch.progress import JobProgress
from lidar_slam.batch.runner import BatchReport, fan_out, run_batch

__all__ = ["BatchJob", "BatchReport", "JobProgress", "expand_inputs", "fan_out", "run_batch",
           "run_job", "sequence_names"]
