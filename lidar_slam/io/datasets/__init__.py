"""Public dataset layouts, one module each (docs/datasets.md): each module's `detect(path)` says
whether a path is one of its sequences (the sequence folder, or None) and `open_sequence(root)`
reads it. DATASETS is the explicit table `open_source` asks, in this order."""

from __future__ import annotations

from pathlib import Path

from lidar_slam.io.datasets import boreas, kitti360, mulran, nclt, newer_college
from lidar_slam.io.datasets.common import DatasetSource

DATASETS = (newer_college, mulran, nclt, kitti360, boreas)


def open_dataset(path: Path) -> DatasetSource | None:
    """The dataset sequence at path, or None when path is none of DATASETS' layouts."""
    for module in DATASETS:
        root = module.detect(path)
        if root is not None:
            return module.open_sequence(root)
    return None

