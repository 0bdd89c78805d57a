"""IMU and GNSS input: imu.csv / gnss.csv beside the scans (issue 22, item 1).

imu.csv: header `stamp_s,wx,wy,wz,ax,ay,az`; angular rate (rad/s) and specific force (m/s^2,
gravity included: ~+9.81 on z at rest with z up), both in the IMU frame.
gnss.csv: header `stamp_s,lat_deg,lon_deg,alt_m,sigma_h_m,sigma_v_m` (WGS84, 1-sigma in m).
Stamps are on the clock of times.txt. Stamps in ms, us or ns and accelerations in g are told
from the data and converted, with one warning (lidar_slam.io.imu_units). Rows that cannot be
used are dropped and counted (one warning per file, the counts in `dropped`): non-finite or
invalid values, a stamp equal to the previous kept one (duplicate), a stamp before it (out of
order). A file with a bad header, a row that is not numbers, or fewer than two usable rows is
refused (InputError, exit 2).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError

log = logging.getLogger(__name__)

IMU_FILE, GNSS_FILE = "imu.csv", "gnss.csv"
IMU_COLUMNS = ("stamp_s", "wx", "wy", "wz", "ax", "ay", "az")
GNSS_COLUMNS = ("stamp_s", "lat_deg", "lon_deg", "alt_m", "sigma_h_m", "sigma_v_m")
# A gap between IMU samples longer than this many median periods counts as missing samples.
GAP_PERIODS = 5.0
# The median norm of the specific force is ~9.81 m/s^2 on any recording that is not in free
# fall; outside this range the file is in g (~1) or has gravity removed (~0): refused.
MIN_MEDIAN_SPECIFIC_FORCE, MAX_MEDIAN_SPECIFIC_FORCE = 5.0, 20.0
# A sample beyond these is no reading of any IMU, in any of the units told from the data (a gyro
# in deg/s or rad/s, a specific force in m/s^2 or g): a glitch, dropped as a non-finite one is
# (one spike of 1e6 m/s^2 took the odometry 41 km away and the final solve to an internal error).
MAX_ABS_RATE = 1e4
MAX_ABS_SPECIFIC_FORCE = 1e4
# A glitch within range: a sample GLITCH_FACTOR x further from the median of its 5 neighbours
# (itself included) than 99 % of the samples within GLITCH_WINDOW_S of it are, and at least
# GLITCH_FACTOR x the floor: a body's motion through an IMU's filters does not jump so in one
# sample. Local, so that a robot standing still for minutes keeps the first foot strikes of its
# trot (a whole file's percentile dropped them), and floors that hold in both gyro units (the
# deg/s verdict comes later, lidar_slam.frontend.imu_check): 3 m/s^2 (a jump of 150 m/s^2, 15 g:
# the whole range of most consumer IMUs, so a 6 g foot strike after minutes of standing still is
# kept), 0.1 rad/s = 5.73 deg/s.
# The bank's 16 simulated IMUs drop nothing; one sample of 1000 m/s^2 is 10,000x (the final
# solve followed it to 3.4 m on a 60 s walk). Dropped and counted as the values out of range.
GLITCH_FACTOR = 50.0
GLITCH_WINDOW_S = 1.0
GLITCH_FLOOR = (3.0, 0.1 * 180.0 / np.pi)  # specific force (m/s^2), rate (rad/s or deg/s)


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples with strictly increasing stamps: stamp_s (N,), gyro_radps (N, 3) and
    accel_mps2 (N, 3) specific force, both in the IMU frame; `dropped` counts what the reader
    dropped and why."""

    stamp_s: np.ndarray
    gyro_radps: np.ndarray
    accel_mps2: np.ndarray
    source: str
    dropped: dict[str, int] = field(default_factory=dict)
    read_as: dict[str, str] = field(default_factory=dict)  # io.imu_units: units converted

    def __len__(self) -> int:
        return len(self.stamp_s)

    def shifted(self, offset_s: float) -> ImuSamples:
        """The same samples with offset_s added to every stamp (onto the lidar clock)."""
        return dataclasses.replace(self, stamp_s=self.stamp_s + offset_s)


@dataclass(frozen=True)
class GnssFixes:
    """GNSS fixes with strictly increasing stamps: stamp_s (N,), lat_deg / lon_deg / alt_m (N,)
    WGS84 (ellipsoidal height), sigma_h_m / sigma_v_m (N,) 1-sigma; `dropped` as ImuSamples."""

    stamp_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    sigma_h_m: np.ndarray
    sigma_v_m: np.ndarray
    source: str
    dropped: dict[str, int] = field(default_factory=dict)
    read_as: dict[str, str] = field(default_factory=dict)  # io.imu_units: units converted

    def __len__(self) -> int:
        return len(self.stamp_s)

    def shifted(self, offset_s: float) -> GnssFixes:
        """The same fixes with offset_s added to every stamp (onto the lidar clock)."""
        return dataclasses.replace(self, stamp_s=self.stamp_s + offset_s)


def _read_table(path: Path, columns: tuple[str, ...]) -> np.ndarray:
    """The rows of a CSV file with exactly this header, as an (N, len(columns)) float array."""
    try:
        with path.open(encoding="utf-8") as fh:
            header = fh.readline()
            if not header.strip():
                raise InputError(path, f"empty file (expected the header {','.join(columns)})")
            names = tuple(name.strip() for name in header.strip().split(","))
            if names != columns:
                raise InputError(path, f"header is {','.join(names)[:80]!r}, expected "
                                       f"{','.join(columns)}")
            body = fh.read()
            lines = [ln for ln in body.splitlines() if ln.partition("#")[0].strip()]
            try:
                rows = (np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=2)
                        if lines else np.empty((0, len(columns))))
            except ValueError:  # an empty field is a missing value, dropped as NaN is
                lines = [",".join(f if f.strip() else "nan"
                                  for f in ln.partition("#")[0].split(",")) for ln in lines]
                rows = np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=2)
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not a text file (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise InputError(path, f"cannot read the file ({exc.strerror or exc})") from None
    except ValueError:
        raise InputError(path, _first_bad_line(body, len(columns))) from None
    if rows.size == 0:  # only comments
        return np.empty((0, len(columns)))
    if rows.shape[1] != len(columns):
        raise InputError(path, f"{rows.shape[1]} columns per row, expected {len(columns)}")
    return rows


def _first_bad_line(body: str, n_columns: int) -> str:
    """What is wrong with the first row that is not n_columns numbers (file line numbers)."""
    for n, line in enumerate(body.splitlines(), 2):  # line 1 is the header
        fields = line.partition("#")[0].split(",")
        if not line.partition("#")[0].strip():
            continue
        if len(fields) != n_columns:
            return f"line {n}: {len(fields)} columns, expected {n_columns}"
        for value in fields:
            if not value.strip():
                continue  # an empty field is read as a missing value
            try:
                float(value)
            except ValueError:
                return f"line {n}: not a number ({value.strip()[:40]!r})"
    return "not a table of numbers"


def _clean(path: Path, rows: np.ndarray, bad: dict[str, np.ndarray], what: str
           ) -> tuple[np.ndarray, dict[str, int]]:
    """Rows kept (none of the masks in bad, each named for why its rows cannot be used, and
    each stamp after the last kept one) and the counts dropped; one warning naming the file and
    why when anything was dropped, InputError when fewer than 2 remain."""
    valid = ~np.any([np.asarray(m, dtype=bool) for m in bad.values()], axis=0)
    invalid = int((~valid).sum())
    whys, taken = [], np.zeros(len(rows), dtype=bool)
    for why, mask in bad.items():  # each row counted once, under its first reason
        n = int((mask & ~taken).sum())
        taken |= mask
        if n:
            whys.append(f"{n} {why}")
    stamps = rows[valid, 0]
    keep = np.zeros(len(stamps), dtype=bool)
    duplicate = backwards = 0
    last = -np.inf
    for i, stamp in enumerate(stamps):  # a running maximum: one pass, as the rosbag reader
        if stamp > last:
            keep[i], last = True, stamp
        elif stamp == last:
            duplicate += 1
        else:
            backwards += 1
    kept = rows[valid][keep]
    dropped = {"invalid": invalid, "duplicate_stamp": duplicate, "out_of_order": backwards}
    counts = ", ".join(whys + [f"{duplicate} duplicate stamps", f"{backwards} out of order"])
    if invalid or duplicate or backwards:
        log.warning("%s: dropped %d of %d %s (%s)", path, len(rows) - len(kept), len(rows), what,
                    counts)
    if len(kept) < 2:
        raise InputError(path, f"{len(kept)} usable {what} of {len(rows)} (need at least 2; "
                               f"{counts})")
    return kept, dropped


def read_imu_csv(path: str | Path) -> ImuSamples:
    """imu.csv (see the module docstring): rows with a non-finite value dropped, stamps made
    strictly increasing by dropping duplicates and steps back, gaps counted (warning)."""
    from lidar_slam.io.imu_units import to_standard_units

    p = Path(path)
    rows, read_as = to_standard_units(_read_table(p, IMU_COLUMNS), p)
    return imu_from_rows(p, rows, read_as=read_as)


RANK_BLOCK = 4096  # rows per block of running_rank (a block's windows: ~13 MB at 401 wide)


def running_rank(x: np.ndarray, size: int, rank: int, at: np.ndarray | None = None
                 ) -> np.ndarray:
    """scipy.ndimage.rank_filter(x, rank, size=(size, 1, ...), mode="nearest"): the rank-th
    smallest (0-based) of each centred window of `size` (odd) rows, per column, the ends
    repeated; at: only at these row indices (default every row). In NumPy (sliding windows,
    np.partition): importing scipy.ndimage costs ~0.2 s of every run with an IMU, a short
    walk's 4 %. tests/test_inertial.py checks it equals scipy's."""
    if size % 2 != 1 or not 0 <= rank < size:
        raise ValueError(f"running_rank: size {size} must be odd and rank {rank} in [0, size)")
    half = size // 2
    padded = np.pad(x, [(half, half)] + [(0, 0)] * (x.ndim - 1), mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, size, axis=0)  # a view
    rows = np.arange(len(x)) if at is None else np.asarray(at, dtype=np.int64)
    out = np.empty((len(rows),) + x.shape[1:], dtype=x.dtype)
    for start in range(0, len(rows), RANK_BLOCK):
        sel = rows[start:start + RANK_BLOCK]
        out[start:start + len(sel)] = np.partition(windows[sel], rank, axis=-1)[..., rank]
    return out


def _glitches(rows: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Rows (of those usable) whose specific force or rate is a glitch (GLITCH_FACTOR)."""
    out = np.zeros(len(rows), dtype=bool)
    index = np.flatnonzero(usable)
    if len(index) < 5:
        return out
    steps = np.diff(rows[index, 0])
    period = float(np.median(steps[steps > 0])) if (steps > 0).any() else 0.0
    half = int(min(GLITCH_WINDOW_S / period, len(index))) if period > 0 else len(index)
    for cols, floor in ((slice(4, 7), GLITCH_FLOOR[0]), (slice(1, 4), GLITCH_FLOOR[1])):
        x = rows[index, cols]
        # a 5-sample running median, and the 99th percentile within +-half (scipy.ndimage's
        # median_filter and percentile_filter, mode "nearest": rank int(size * 0.99))
        jump = np.linalg.norm(x - running_rank(x, 5, 2), axis=1)
        # a glitch clears GLITCH_FACTOR x the floor first: the percentile only where one does
        # (none in a clean stream; an hour at 200 Hz: 3 s for every sample's)
        cand = np.flatnonzero(jump > GLITCH_FACTOR * floor)
        if len(cand):
            size = 2 * half + 1
            local = running_rank(jump, size, int(size * 99 / 100), at=cand)
            out[index[cand[jump[cand] > GLITCH_FACTOR * np.maximum(local, floor)]]] = True
    return out


def imu_from_rows(source: str | Path, rows: np.ndarray, dropped: dict[str, int] | None = None,
                  read_as: dict[str, str] | None = None) -> ImuSamples:
    """ImuSamples from (N, 7) rows in the imu.csv column order, cleaned as read_imu_csv."""
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(rows).all(axis=1)
        in_range = ((np.abs(rows[:, 1:4]) <= MAX_ABS_RATE).all(axis=1)
                    & (np.abs(rows[:, 4:7]) <= MAX_ABS_SPECIFIC_FORCE).all(axis=1))
    bad = {"non-finite": ~finite,
           f"beyond {MAX_ABS_RATE:g} rad/s or {MAX_ABS_SPECIFIC_FORCE:g} m/s^2": ~in_range,
           f"glitches ({GLITCH_FACTOR:g}x further from their neighbours than 99 % of the "
           f"samples within {GLITCH_WINDOW_S:g} s)": _glitches(rows, finite & in_range)}
    kept, counts = _clean(Path(source), rows, bad, "IMU samples")
    dt = np.diff(kept[:, 0])
    gaps = int((dt > GAP_PERIODS * np.median(dt)).sum())
    if gaps:
        log.warning("%s: %d gaps longer than %g sample periods (%.4f s) in the IMU stream, the "
                    "longest %.3f s", source, gaps, GAP_PERIODS, float(np.median(dt)),
                    float(dt.max()))
    counts["gaps"] = gaps
    g_median = float(np.median(np.linalg.norm(kept[:, 4:7], axis=1)))
    if not MIN_MEDIAN_SPECIFIC_FORCE <= g_median <= MAX_MEDIAN_SPECIFIC_FORCE:
        w_median = float(np.median(np.linalg.norm(kept[:, 1:4], axis=1)))
        swapped = MIN_MEDIAN_SPECIFIC_FORCE <= w_median <= MAX_MEDIAN_SPECIFIC_FORCE
        raise InputError(source, f"median specific force {g_median:.3g} m/s^2 (expected about "
                                 f"9.81 with gravity included: " + (
                                     f"the rate columns read {w_median:.3g}: wx,wy,wz and "
                                     f"ax,ay,az swapped?)" if swapped
                                     else "in g, or gravity removed?)"))
    return ImuSamples(kept[:, 0], kept[:, 1:4].copy(), kept[:, 4:7].copy(), str(source),
                      {**counts, **(dropped or {})}, dict(read_as or {}))


def read_gnss_csv(path: str | Path) -> GnssFixes:
    """gnss.csv (see the module docstring): rows with a non-finite value, a latitude or
    longitude out of range or a sigma that is not positive dropped, stamps as read_imu_csv."""
    from lidar_slam.io.imu_units import gnss_stamps_in_s

    p = Path(path)
    rows, read_as = gnss_stamps_in_s(_read_table(p, GNSS_COLUMNS), p)
    return gnss_from_rows(p, rows, read_as=read_as)


def gnss_from_rows(source: str | Path, rows: np.ndarray, dropped: dict[str, int] | None = None,
                   read_as: dict[str, str] | None = None) -> GnssFixes:
    """GnssFixes from (N, 6) rows in the gnss.csv column order, cleaned as read_gnss_csv."""
    with np.errstate(invalid="ignore"):
        bad = {"non-finite": ~np.isfinite(rows).all(axis=1),
               "latitude or longitude out of range": ~((np.abs(rows[:, 1]) <= 90)
                                                       & (np.abs(rows[:, 2]) <= 180)),
               "sigma_h_m or sigma_v_m not positive": ~((rows[:, 4] > 0) & (rows[:, 5] > 0))}
    kept, counts = _clean(Path(source), rows, bad, "GNSS fixes")
    return GnssFixes(*(kept[:, i].copy() for i in range(6)), str(source),
                     {**counts, **(dropped or {})}, dict(read_as or {}))


def find_beside(folder: Path, name: str) -> Path | None:
    """name in the input folder, or in its scans/ subfolder; None when in neither."""
    for cand in (folder / name, folder / "scans" / name):
        if cand.is_file():
            return cand
    return None


def stream_info(stamp_s: np.ndarray, source: str, dropped: dict[str, int],
                time_offset_s: float, read_as: dict[str, str] | None = None) -> dict:
    """What summary.json says of an IMU or GNSS stream that was used (read_as: the units
    converted, io.imu_units)."""
    span = float(stamp_s[-1] - stamp_s[0])
    return {"source": source, "samples": int(len(stamp_s)),
            "rate_hz": round((len(stamp_s) - 1) / span, 3) if span > 0 else None,
            "first_stamp_s": float(stamp_s[0]), "last_stamp_s": float(stamp_s[-1]),
            "time_offset_s": time_offset_s, "dropped": dict(dropped),
            **({"read_as": dict(read_as)} if read_as else {})}


def overlap_problem(stamp_s: np.ndarray, scan_first_s: float, scan_last_s: float, what: str
                    ) -> str | None:
    """Why a stream cannot be used with the scans (its stamps do not overlap theirs at all:
    another clock), or None."""
    first, last = float(stamp_s[0]), float(stamp_s[-1])
    if last < scan_first_s or first > scan_last_s:
        return (f"{what} stamps {first:.6g}..{last:.6g} s do not overlap the scans' "
                f"{scan_first_s:.6g}..{scan_last_s:.6g} s (not the clock of the scan stamps? set "
                f"the time_offset_s of the config)")
    return None


def check_overlap(source: str, stamp_s: np.ndarray, scan_first_s: float, scan_last_s: float,
                  what: str, slack_s: float = 1.0) -> None:
    """Refuse a stream whose stamps do not overlap the scans' at all (another clock: nothing
    sensible can be done); warn when it misses more than slack_s at either end of them."""
    problem = overlap_problem(stamp_s, scan_first_s, scan_last_s, what)
    if problem is not None:
        raise InputError(source, problem)
    first, last = float(stamp_s[0]), float(stamp_s[-1])
    if first > scan_first_s + slack_s or last < scan_last_s - slack_s:
        log.warning("%s: %s stamps %.6g..%.6g s cover only part of the scans' %.6g..%.6g s",
                    source, what, first, last, scan_first_s, scan_last_s)
