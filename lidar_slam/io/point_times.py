"""Per-point times of a scan, in whatever unit a file or message stores them, to seconds
relative to the scan stamp. The one conversion every reader uses (files, KITTI, rosbags).

A sweep lasts 0.05-0.5 s, and a time field is either an offset from the scan stamp or an
absolute time (UNIX or sim clock):

- Unit, from the datatype and the span of the values: integers are microseconds when they span
  1e3..1e6 (1 ms .. 1 s), otherwise nanoseconds; floats are seconds when they span at most 2,
  microseconds up to 2e6, otherwise nanoseconds.
- Absolute times are recognised by being more than 1 s from zero and within 10 s of the stamp
  (in s, us or ns); the stamp is subtracted (in integer nanoseconds for integer fields).
- Offsets (values within 1 s of zero) are kept as they stand: [0, 0.1] for a scan stamped at the
  sweep's start, [-0.1, 0] for one stamped at its end. An absolute time within the first second
  of a clock that starts at zero is indistinguishable from an offset and is read as one.
- Anything else (absolute times with no stamp, or a stamp from another clock) is taken relative
  to the sweep's earliest point, with a warning.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

ABSOLUTE_TOL_S = 10.0  # absolute times lie within this of the scan stamp
OFFSET_MAX_S = 1.0  # offsets from the stamp lie within this of zero
_warned: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _warned:
        _warned.add(message)
        log.warning(message)


def time_unit_s(raw: np.ndarray) -> float:
    """Seconds per unit of a per-point time field (1, 1e-6 or 1e-9), from its datatype and span."""
    values = np.asarray(raw)
    span = float(values.max()) - float(values.min()) if values.size else 0.0
    return _unit_s(values.dtype.kind == "f", span)


def _unit_s(is_float: bool, span: float) -> float:
    if is_float:
        return 1.0 if span <= 2.0 else 1e-6 if span <= 2e6 else 1e-9
    return 1e-6 if 1e3 <= span <= 1e6 else 1e-9


def relative_seconds(raw: np.ndarray, stamp_ns: int | None = None) -> np.ndarray | None:
    """Per-point times (N,) in s, us or ns, offsets or absolute -> float64 seconds relative to
    the scan stamp (stamp_ns: integer nanoseconds, None when unknown). None when a value is
    NaN/inf (the scan is then used without times)."""
    raw = np.asarray(raw).ravel()
    if raw.size == 0:
        return np.zeros(0)
    with np.errstate(invalid="ignore"):  # signalling NaNs (a garbage file): caught below
        values = raw.astype(np.float64)
    if not np.isfinite(values).all():
        _warn_once("per-point time field has NaN/inf values; such scans are used without times")
        return None
    is_int = raw.dtype.kind in "iu"
    lo, hi = float(values.min()), float(values.max())
    mid = 0.5 * (lo + hi)
    if stamp_ns:
        stamp_s = stamp_ns * 1e-9
        for scale in (1e-9, 1e-6, 1.0) if is_int else (1.0, 1e-6, 1e-9):
            if abs(mid * scale) > OFFSET_MAX_S and abs(mid * scale - stamp_s) < ABSOLUTE_TOL_S:
                if is_int:
                    return (raw.astype(np.int64) * round(scale * 1e9) - stamp_ns) * 1e-9
                return values * scale - stamp_s
    # time_unit_s(raw) from the span already known (the float64 extremes are the raw ones,
    # converted: two passes over the times less per scan)
    scale = _unit_s(raw.dtype.kind == "f", hi - lo)
    if max(abs(lo), abs(hi)) * scale <= OFFSET_MAX_S:
        return values if scale == 1.0 else values * scale
    _warn_once("per-point times are neither offsets from the scan stamp nor near it; taken "
               "relative to each sweep's earliest point")
    if is_int:
        ints = raw.astype(np.int64)
        return (ints - ints.min()).astype(np.float64) * scale
    return (values - lo) * scale
