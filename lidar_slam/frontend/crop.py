"""Range crop."""

from __future__ import annotations

import numpy as np


def range_mask(points: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """Boolean mask of points whose distance from the sensor lies in [min_range_m, max_range_m]."""
    r2 = np.einsum("ij,ij->i", points, points)
    return (r2 >= min_range_m * min_range_m) & (r2 <= max_range_m * max_range_m)
