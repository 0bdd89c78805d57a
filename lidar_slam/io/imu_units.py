"""The units of an imu.csv, told from its data (issue 30, item 6): what the file says it holds
(stamps in s, specific force in m/s^2) is checked against what the numbers can be, and a file
in another unit is converted with one warning saying what was assumed, or refused naming it.

- Stamps: an IMU samples at 10 Hz .. 5 kHz, so the median spacing of the stamps tells s from
  ms, us and ns (the plausible rates of two units are 1000x apart and the window is 500x wide:
  at most one unit fits). Whether the converted stamps are on the scans' clock is checked
  after (io.imu_gnss.check_overlap).
  gnss.csv's fixes may come milliseconds or hours apart: their unit is told by spacing and size
  together (gnss_stamps_in_s).
- Specific force: its median norm is ~9.81 m/s^2 on any recording not in free fall, ~1 in g
  (and then seldom far below 1: gravity dominates). Gravity removed (a median norm of 0..2
  m/s^2 that drops to ~0 at every pause) or anything else is refused (io.imu_gnss).
- The gyro's unit (rad/s or deg/s) is not told by its magnitude alone (a slow turn in deg/s
  looks like a fast one in rad/s): the front-end compares it with the lidar's own rotation
  (lidar_slam.frontend.imu_check).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError

log = logging.getLogger(__name__)

MIN_RATE_HZ, MAX_RATE_HZ = 10.0, 5000.0  # an IMU's sample rate, in any unit of its stamps
# gnss.csv stamps (gnss_stamps_in_s): a receiver's fixes come 1 ms to a day apart; stamps in s
# stay below 1e11 (year 5000); epoch seconds lie in 1e8..1e10 (1973..2286).
GNSS_SPACING_S = (1e-3, 86400.0)
GNSS_MAX_STAMP_S = 1e11
EPOCH_S = (1e8, 1e10)
STAMP_UNITS = ((1.0, "s"), (1e-3, "ms"), (1e-6, "us"), (1e-9, "ns"))
STANDARD_GRAVITY_MPS2 = 9.80665  # 1 g
G_RANGE = (0.5, 2.0)  # median norm of the specific force of a file in g (~1)


def stamp_scale(stamps: np.ndarray, source: str | Path,
                rates_hz: tuple[float, float] = (MIN_RATE_HZ, MAX_RATE_HZ), what: str = "an IMU"
                ) -> float:
    """Seconds per unit of the stamps (1, 1e-3, 1e-6 or 1e-9), from their median spacing;
    InputError when no unit gives a rate in rates_hz (an IMU's by default)."""
    lo_hz, hi_hz = rates_hz
    steps = np.diff(np.asarray(stamps, dtype=np.float64))
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if not len(steps):
        return 1.0  # no two increasing stamps: io.imu_gnss refuses the file
    spacing = float(np.median(steps))
    fits = [(scale, unit) for scale, unit in STAMP_UNITS
            if lo_hz <= 1.0 / (spacing * scale) <= hi_hz]
    if not fits:
        raise InputError(source, f"median stamp spacing {spacing:.6g} is not that of {what} at "
                                 f"{lo_hz:g}..{hi_hz:g} Hz in s, ms, us or ns")
    scale, unit = fits[0]
    if scale != 1.0:
        log.warning("%s: stamps read as %s (median spacing %.6g: %.4g Hz in %s, %.3g Hz in s); "
                    "converted to s", source, unit, spacing, 1.0 / (spacing * scale), unit,
                    1.0 / spacing)
    return scale


def gnss_stamps_in_s(rows: np.ndarray, source: str | Path) -> tuple[np.ndarray, dict[str, str]]:
    """gnss.csv rows with stamps in s, and {"stamps": unit} when they were in ms, us or ns.
    A receiver's fixes come every few ms to hours, so the spacing alone does not tell the
    unit: stamps whose spacing (GNSS_SPACING_S) and size (below GNSS_MAX_STAMP_S) both fit
    seconds stay as read; otherwise the unit that fits both, the one whose stamps look like
    epoch seconds (EPOCH_S) first, then the one whose fixes come closest to 1 Hz."""
    rows = np.asarray(rows, dtype=np.float64)
    if len(rows) < 2:
        return rows, {}
    stamps = rows[:, 0][np.isfinite(rows[:, 0])]
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    if not len(steps):
        return rows, {}
    spacing, size = float(np.median(steps)), float(np.median(np.abs(stamps)))

    def fits(scale: float) -> bool:
        return (GNSS_SPACING_S[0] <= spacing * scale <= GNSS_SPACING_S[1]
                and size * scale < GNSS_MAX_STAMP_S)

    if fits(1.0):
        return rows, {}
    units = [(scale, unit) for scale, unit in STAMP_UNITS[1:] if fits(scale)]
    if not units:
        return rows, {}  # the overlap with the scans' clock judges them
    scale, unit = min(units, key=lambda su: (not EPOCH_S[0] <= size * su[0] <= EPOCH_S[1],
                                             abs(np.log10(spacing * su[0]))))
    log.warning("%s: stamps read as %s (median spacing %.6g: a fix every %.3g s in %s); "
                "converted to s", source, unit, spacing, spacing * scale, unit)
    out = rows.copy()
    out[:, 0] *= scale
    return out, {"stamps": unit}


def accel_scale(accel: np.ndarray, source: str | Path) -> float:
    """m/s^2 per unit of the specific force: STANDARD_GRAVITY_MPS2 when its median norm is
    ~1 (a file in g, converted with one warning), else 1 (io.imu_gnss checks the range)."""
    norms = np.linalg.norm(np.asarray(accel, dtype=np.float64), axis=1)
    norms = norms[np.isfinite(norms)]
    if not len(norms):
        return 1.0
    median, p10 = (float(v) for v in np.percentile(norms, [50, 10]))
    # Gravity dominates a file in g: its norm seldom drops far below 1. With gravity removed the
    # norm of a moving sensor can also be ~1 m/s^2 in the median, but is near 0 at every pause.
    if G_RANGE[0] <= median <= G_RANGE[1] and p10 >= 0.5 * median:
        log.warning("%s: accelerations read as g (median specific force %.3g, 9.81 m/s^2 "
                    "expected); converted to m/s^2", source, median)
        return STANDARD_GRAVITY_MPS2
    return 1.0


def to_standard_units(rows: np.ndarray, source: str | Path) -> tuple[np.ndarray, dict[str, str]]:
    """imu.csv rows (N, 7) with stamps in s and specific force in m/s^2 (see the module doc),
    and the units the file was read in where they were not those (summary.json imu.read_as:
    {"stamps": "ns", "accel": "g"})."""
    rows = np.asarray(rows, dtype=np.float64)
    if len(rows) < 2:
        return rows, {}
    t_scale, a_scale = stamp_scale(rows[:, 0], source), accel_scale(rows[:, 4:7], source)
    read_as = {**({"stamps": dict(STAMP_UNITS)[t_scale]}
                  if t_scale != 1.0 else {}),
               **({"accel": "g"} if a_scale != 1.0 else {})}
    if not read_as:
        return rows, read_as
    out = rows.copy()
    out[:, 0] *= t_scale
    out[:, 4:7] *= a_scale
    return out, read_as
