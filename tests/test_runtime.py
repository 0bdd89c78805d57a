"""Process tuning: importing the package changes nothing; tune_process() does, on request."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _python(code: str) -> str:
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "LIDAR_SLAM_MALLOC_DEFAULTS")}
    env["PYTHONPATH"] = str(REPO)
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True,
                         text=True, check=True, timeout=60)
    return out.stdout.strip()


def test_importing_lidar_slam_leaves_the_environment_alone():
    code = ("import os\nbefore = dict(os.environ)\nimport lidar_slam\n"
            "print(dict(os.environ) == before)\n")
    assert _python(code) == "True"


def test_tune_process_asks_for_one_openblas_thread_unless_the_user_chose():
    code = ("import os\nfrom lidar_slam.runtime import tune_process\ntune_process()\n"
            "print(os.environ['OPENBLAS_NUM_THREADS'])\n"
            "os.environ['OPENBLAS_NUM_THREADS'] = '3'\ntune_process()\n"
            "print(os.environ['OPENBLAS_NUM_THREADS'])\n")
    assert _python(code).split() == ["1", "3"]
