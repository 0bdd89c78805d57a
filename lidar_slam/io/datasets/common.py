"""What the public-dataset readers share: a source over scan files with their stamps, the ground
truth moved to the lidar frame at those stamps, and the IMU / GNSS a layout carries with the
mounting its calibration gives (docs/datasets.md says where each transform comes from)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.geometry import interpolate
from lidar_slam.io.inertial_input import Carried, CarriedStreams
from lidar_slam.io.pointcloud import CloudData, make_scan
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

# A ground-truth stamp within this of a scan stamp is that scan's pose (no interpolation).
SAME_STAMP_S = 1e-6


def require(path: Path, what: str) -> Path:
    """path, or one InputError naming the missing file of a partial layout."""
    if not path.exists():
        raise InputError(path, f"missing: {what}")
    return path


# A lidar's scan period is more than this: stamps read from file names closer in the median are
# numbers (000000.bin read as 0, 1, 2 ns / us). No upper bound: a sequence may keep every 100th
# scan.
MIN_SCAN_PERIOD_S = 1e-3


def stamped_files(folder: Path, suffix: str, stamp_s: Callable[[str], float],
                  what: str) -> tuple[list[Path], np.ndarray]:
    """The files of a folder named by their stamps, in time order, with the stamps (s); one
    InputError naming the folder when it holds none or a name is not a stamp."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix == suffix] \
        if folder.is_dir() else []
    if not files:
        raise InputError(folder, f"no {suffix} scans found ({what})")
    stamps = np.empty(len(files), dtype=np.float64)
    for k, p in enumerate(files):
        try:
            stamps[k] = stamp_s(p.stem)
        except ValueError:
            raise InputError(p, f"the scan file name is not a stamp (expected {what})") from None
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    if len(stamps) > 1 and not (np.diff(stamps) > 0).all():
        k = int(np.flatnonzero(np.diff(stamps) <= 0)[0])
        raise InputError(folder, f"two scans with the stamp {stamps[k]:.6f} s")
    check_scan_period(folder, stamps, what)
    return [files[i] for i in order], stamps


def check_scan_period(folder: Path, stamps_s: np.ndarray, what: str) -> None:
    """InputError naming the folder when the stamps read from its file names are closer than a
    lidar scans (MIN_SCAN_PERIOD_S in the median: 000000.bin read as 0 ns)."""
    if len(stamps_s) > 1:
        spacing = float(np.median(np.diff(stamps_s)))
        if spacing < MIN_SCAN_PERIOD_S:
            raise InputError(folder, f"the file names read as stamps {spacing:.3g} s apart (a "
                                     f"lidar scans every {MIN_SCAN_PERIOD_S:g} s or more): are "
                                     f"they numbered, not stamped? (expected {what})")


def poses_at(gt_stamps_s: np.ndarray, gt_poses: np.ndarray, stamps_s: np.ndarray) -> np.ndarray:
    """Ground-truth poses (M, 4, 4) at stamps (K,): a pose within SAME_STAMP_S, else slerp / lerp
    between the two around it; NaN where the ground truth does not reach (before its first or
    after its last stamp)."""
    order = np.argsort(gt_stamps_s, kind="stable")
    ts, Ts = gt_stamps_s[order], gt_poses[order]
    out = np.full((len(stamps_s), 4, 4), np.nan)
    if not len(ts):
        return out
    hi = np.searchsorted(ts, stamps_s)
    for k, (t, j) in enumerate(zip(stamps_s, hi)):
        if j < len(ts) and abs(ts[j] - t) <= SAME_STAMP_S:
            out[k] = Ts[j]
        elif j > 0 and abs(ts[j - 1] - t) <= SAME_STAMP_S:
            out[k] = Ts[j - 1]
        elif 0 < j < len(ts):
            s = (t - ts[j - 1]) / (ts[j] - ts[j - 1])
            out[k] = interpolate(Ts[j - 1], Ts[j], float(s))
    missing = int(np.isnan(out[:, 0, 0]).sum())
    if missing:
        log.warning("ground truth covers %d of %d scans (stamps %.3f..%.3f s); the others are "
                    "left out of the metrics", len(stamps_s) - missing, len(stamps_s),
                    float(ts[0]), float(ts[-1]))
    return out


def rigid(R: np.ndarray, t) -> np.ndarray:
    """4x4 from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rpy_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (rad): the x-y-z extrinsic (z-y-x intrinsic) convention."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def load_rows(path: Path, columns: int, what: str, skip_header: bool = False,
              delimiter: str = ",") -> np.ndarray:
    """A numeric table with `columns` columns (or more), as float64; one InputError naming the
    file when it is not."""
    try:
        with path.open(encoding="utf-8") as fh:
            lines = fh.read().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the {what} ({exc})") from None
    if skip_header and lines:
        lines = lines[1:]
    lines = [ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    try:
        rows = np.loadtxt(lines, delimiter=delimiter, ndmin=2, dtype=np.float64) if lines \
            else np.empty((0, columns))
    except ValueError as exc:
        raise InputError(path, f"not a table of numbers ({what}): {exc}") from None
    if rows.shape[1] < columns:
        raise InputError(path, f"{rows.shape[1]} columns, expected {columns} ({what})")
    return rows


class DatasetSource(CarriedStreams):
    """A public dataset's sequence: scans from stamped files (read by `read(path, stamp_s)`), the
    ground truth T_world_lidar at every scan stamp (NaN rows where it does not reach) or None,
    and the streams it carries (`carried`)."""

    topic = None

    def __init__(self, kind: str, name: str, files: list[Path], stamps: np.ndarray,
                 read: Callable[[Path, float], CloudData], ground_truth: np.ndarray | None,
                 carried: Carried | None = None):
        self.kind, self.name, self.files, self.stamps = kind, name, files, stamps
        self._read = read
        self.ground_truth = ground_truth
        self.carried = carried or Carried()
        self.path = files[0].parent  # open_source sets the folder given

    @property
    def sensor_streams(self) -> Carried:
        """The IMU / GNSS / mounting the layout carries (the ScanSource protocol's name)."""
        return self.carried

    @property
    def input_notes(self) -> dict[str, int]:
        """Nothing dropped or recovered: bad files are refused, not dropped."""
        return {}

    def __len__(self) -> int:
        return len(self.files)

    def scans(self, start: int = 0, count: int | None = None) -> Iterator[Scan]:
        stop = len(self.files) if count is None else min(len(self.files), start + count)
        for i in range(start, stop):
            cloud = self._read(self.files[i], float(self.stamps[i]))
            yield make_scan(i, self.stamps[i], cloud, str(self.files[i]))
