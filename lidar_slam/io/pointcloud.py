"""Single point-cloud files: .bin (KITTI float32 x,y,z,intensity), .pcd, .ply, .npy."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from tokenize import TokenError

import numpy as np

from lidar_slam.errors import InputError
from lidar_slam.io.ply import PLY_TYPE_CODES
from lidar_slam.io.point_times import relative_seconds
from lidar_slam.types import Scan

log = logging.getLogger(__name__)

SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")
TIME_FIELDS = ("t", "time", "timestamp", "timestamps", "offset_time")
INTENSITY_FIELDS = ("intensity", "intensities", "reflectivity", "remission")


@dataclass(frozen=True)
class CloudData:
    """Raw contents of one file: points (N,3) float64, times (N,) seconds or None, intensity or
    None."""

    points: np.ndarray
    times: np.ndarray | None
    intensity: np.ndarray | None


def read_bin(path: Path) -> CloudData:
    """KITTI .bin: float32 x, y, z, intensity per point."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc
    if size % 16 != 0:
        raise InputError(path, f"{size} bytes is not a multiple of 16 (float32 x,y,z,intensity)")
    try:
        data = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    except OSError as exc:  # e.g. permission denied: stat needs no read permission
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    # A file of garbage holds signalling NaNs, whose cast NumPy warns about: make_scan drops
    # the non-finite points and says so, naming the file.
    with np.errstate(invalid="ignore"):
        points = data[:, :3].astype(np.float64)
    if not _check_bin_layout(path, size, points, data[:, 3]):
        return CloudData(np.zeros((0, 3)), None, np.zeros(0, np.float32))
    return CloudData(points, None, data[:, 3].copy())


BIN_MAX_COORD_M = 1e5  # no lidar measures 100 km: a coordinate beyond is a misread number
BIN_MAX_SHARE = 0.01  # of the points with one: more is a file in another layout
BIN_CHECK_POINTS = 2048  # evenly spread points the layout check looks at


def _check_bin_layout(path: Path, size: int, points: np.ndarray, fourth: np.ndarray) -> bool:
    """Whether the .bin reads as float32 x, y, z, intensity (False: bytes that are not numbers,
    to be skipped with a warning); raises on the layouts that otherwise read as a cloud: float64
    numbers (each splits into two float32, one of them garbage: coordinates of 1e19 m) and
    float32 x, y, z only (the rows shift by a column: the 'intensity' is a coordinate, negative
    on about half the points). One point in a hundred may be out of range (a sensor's glitch,
    then cropped by data.max_range_m)."""
    if len(points) == 0:
        return True
    step = max(1, len(points) // BIN_CHECK_POINTS)  # shares: a sample says them (< 0.1 ms)
    sample, fourth = points[::step], fourth[::step]
    n = len(sample)
    with np.errstate(invalid="ignore"):
        far = int((np.abs(sample) > BIN_MAX_COORD_M).any(axis=1).sum())
        negative = int((fourth < 0).sum())
    if far > BIN_MAX_SHARE * n:
        for columns, layout in ((4, "float64 x, y, z, intensity"), (3, "float64 x, y, z")):
            if size % (8 * columns) == 0 and _plausible_float64(path, columns):
                raise InputError(path, f"holds {layout} (read as float32 x, y, z, intensity, "
                                 f"{100 * far / n:.0f} % of the points lie beyond "
                                 f"{BIN_MAX_COORD_M / 1e3:g} km); a .bin holds float32 x, y, "
                                 f"z, intensity")
        log.warning("%s: %.0f %% of its points lie beyond %g km: not float32 x, y, z, intensity "
                    "numbers; scan skipped", path, 100 * far / n, BIN_MAX_COORD_M / 1e3)
        return False
    if size % 12 == 0 and negative > 0.1 * n:
        raise InputError(path, f"the 4th column (intensity) is negative on {100 * negative / n:.0f}"
                         f" % of the points: float32 x, y, z without intensity? (a .bin holds "
                         f"float32 x, y, z, intensity)")
    return True


def _plausible_float64(path: Path, columns: int) -> bool:
    """Whether the file read as float64 rows of `columns` numbers is a cloud: finite, within
    BIN_MAX_COORD_M, a non-negative 4th column."""
    rows = np.fromfile(path, dtype="<f8").reshape(-1, columns)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(rows).all(axis=1) & (np.abs(rows[:, :3]) <= BIN_MAX_COORD_M).all(axis=1)
        if columns == 4:
            ok &= rows[:, 3] >= 0
    return bool(ok.mean() > 1 - BIN_MAX_SHARE)


# open3d's PCD and PLY readers allocate the point tensors the header asks for and, when the data
# is short, truncated or not numbers, leave the rest uninitialised (or zero) with only a printed
# warning: its output looks like a cloud. So the header and the size of the data are checked
# here first (a check, not a second decoder), and the cloud open3d returns must have the points
# the header declares.
_HEAD_BYTES = 1 << 16
_O3D_LINE_BYTES = 1023  # open3d reads PCD lines with fgets into a 1024-byte buffer
_NOT_TEXT = re.compile(rb"[^\t\r\n\x20-\x7e]")
_WORDS = re.compile(rb"[\t\r\n ]+")
_FLOAT = re.compile(r"[+-]?((\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|inf|infinity|nan)",
                    re.IGNORECASE | re.ASCII)
_INT = re.compile(r"[+-]?\d+", re.ASCII)
_DECIMAL = re.compile(r"[+-]?(0|[1-9]\d*)", re.ASCII)
_LEADING_ZERO = re.compile(rb"(?:^|\n)[+-]?0[0-9]")
_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT",
             "POINTS", "DATA")
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
_MAX_POINTS = 2**31 - 1  # open3d counts points in a C int
_LZF_MAX_RATIO = 100  # LZF expands at most ~88x (3 bytes back-reference 264)


def _bad(path: Path, kind: str, problem: str) -> InputError:
    return InputError(path, f"not a valid {kind} file ({problem})")


def _shown(word: bytes) -> str:
    return repr(word[:20].decode("latin-1"))


def _count(path: Path, kind: str, word: str, what: str) -> int:
    if not _INT.fullmatch(word) or word.startswith(("-", "+")) or int(word) > _MAX_POINTS:
        raise _bad(path, kind, f"{what} {word[:20]!r} is not a count up to {_MAX_POINTS}")
    return int(word)


def _number_ok(word: bytes, code: str, strict: bool) -> bool:
    """Whether a word of ASCII data is a number of numpy type code as the C reader takes it:
    rply (strict) refuses anything else and out-of-range values, with only a printed warning;
    open3d's PCD reader takes junk as 0 and wraps integers (a leading 0 is octal there)."""
    text = word.decode("latin-1")
    if len(text) > 255:
        return False
    if code[0] == "f":
        if not _FLOAT.fullmatch(text):
            return False
        value = float(text)
        return not strict or np.isnan(value) or abs(value) <= np.finfo(code).max
    if not (_INT if strict else _DECIMAL).fullmatch(text):
        return False
    info = np.iinfo(code)
    return info.min <= int(text) <= info.max


def _header_lines(head: bytes, path: Path, kind: str, last: bytes):
    """(line words, offset after the line) of a text header up to the line that starts with
    `last` (inclusive); only printable ASCII."""
    pos = 0
    while True:
        end = head.find(b"\n", pos)
        if end < 0:
            raise _bad(path, kind, f"no {last.decode()} line in the first "
                                   f"{_HEAD_BYTES // 1024} KiB")
        line = head[pos:end + 1]
        if _NOT_TEXT.search(line):
            raise _bad(path, kind, "the header has bytes that are not text")
        if kind == "PCD" and len(line) > _O3D_LINE_BYTES:
            raise _bad(path, kind, f"header line longer than {_O3D_LINE_BYTES} bytes")
        pos = end + 1
        words = [w.decode() for w in _WORDS.split(line.strip(b"\t\r\n ")) if w]
        yield words, pos, line
        if words and words[0].encode() == last:
            return


def _check_pcd(path: Path, head: bytes, size: int) -> int:
    """Points of a PCD file open3d can read in full (0 for an empty one), else an InputError."""
    kind = "PCD"
    values: dict[str, list[str]] = {}
    data_at = 0
    for words, pos, _ in _header_lines(head, path, kind, b"DATA"):
        if not words or words[0].startswith("#"):
            continue
        key = words[0]
        if key not in _PCD_KEYS:
            raise _bad(path, kind, f"unknown header line {key[:20]!r}")
        if key in values:
            raise _bad(path, kind, f"two {key} lines")
        if key in ("SIZE", "TYPE", "COUNT") and "FIELDS" not in values:
            raise _bad(path, kind, f"{key} before FIELDS")
        if key == "COUNT" and "SIZE" not in values:
            raise _bad(path, kind, "COUNT before SIZE")
        values[key], data_at = words[1:], pos
    names = values.get("FIELDS") or []
    if not names or "SIZE" not in values or "TYPE" not in values:
        raise _bad(path, kind, "FIELDS, SIZE and TYPE lines are needed")
    counts = values.get("COUNT", ["1"] * len(names))
    for key, row in (("SIZE", values["SIZE"]), ("TYPE", values["TYPE"]), ("COUNT", counts)):
        if len(row) != len(names):
            raise _bad(path, kind, f"{len(row)} {key} values for {len(names)} FIELDS")
    if len(set(names)) != len(names) or {"positions", "normals", "colors"} & set(names):
        raise _bad(path, kind, f"field names repeated or reserved ({' '.join(names)[:60]})")
    codes = []
    for name, sz, tp, ct in zip(names, values["SIZE"], values["TYPE"], counts):
        code = _PCD_TYPES.get((tp.upper(), int(sz) if sz.isdigit() else 0)) if len(tp) == 1 \
            else None
        if code is None:
            raise _bad(path, kind, f"field {name!r}: SIZE {sz[:10]} TYPE {tp[:10]} is not a "
                                   "supported type")
        if _count(path, kind, ct, f"field {name!r}: COUNT") < 1:
            raise _bad(path, kind, f"field {name!r}: COUNT 0")
        codes.append(code)
    field = {n: (c, int(k)) for n, c, k in zip(names, codes, counts)}
    if not {"x", "y", "z"} <= set(field):
        raise _bad(path, kind, "no x, y, z fields")
    for group in (("x", "y", "z"), ("normal_x", "normal_y", "normal_z")):
        found = {field[n] for n in group if n in field}
        if len(found) > 1 or (group[0] == "x" and found != {(field["x"][0], 1)}):
            raise _bad(path, kind, f"{', '.join(group)} need one type and COUNT 1")
    for key in ("WIDTH", "HEIGHT", "POINTS", "DATA"):
        if key in values and len(values[key]) != 1:
            raise _bad(path, kind, f"{key} needs one value")
    if "POINTS" not in values and not {"WIDTH", "HEIGHT"} <= set(values):
        raise _bad(path, kind, "no POINTS line")
    dims = [_count(path, kind, values[k][0], k) for k in ("WIDTH", "HEIGHT") if k in values]
    points = _count(path, kind, values["POINTS"][0], "POINTS") if "POINTS" in values \
        else dims[0] * dims[1]
    if len(dims) == 2 and dims[0] * dims[1] != points:
        raise _bad(path, kind, f"WIDTH x HEIGHT = {dims[0] * dims[1]} but POINTS {points}")
    data = values["DATA"][0]
    if data not in ("ascii", "binary", "binary_compressed"):
        raise _bad(path, kind, f"DATA {data[:20]!r} (ascii, binary or binary_compressed)")
    if points == 0:
        return 0
    point_bytes = sum(np.dtype(c).itemsize * k for c, k in field.values())
    if data == "binary" and size - data_at < points * point_bytes:
        raise _bad(path, kind, f"binary data is {size - data_at} bytes, {points} points of "
                               f"{point_bytes} bytes need {points * point_bytes}")
    if data == "binary_compressed":
        with open(path, "rb") as fh:
            fh.seek(data_at)
            sizes = np.frombuffer(fh.read(8), "<u4")
        if len(sizes) < 2 or sizes[1] != points * point_bytes or \
                sizes[0] > size - data_at - 8 or sizes[1] > _LZF_MAX_RATIO * int(sizes[0]):
            raise _bad(path, kind, f"compressed data does not hold {points} points of "
                                   f"{point_bytes} bytes")
    if data == "ascii":
        used = {"x", "y", "z", next((n for n in TIME_FIELDS if n in field), ""),
                next((n for n in INTENSITY_FIELDS if n in field), "")}
        _check_pcd_ascii(path, data_at, points, [(*field[n], n in used) for n in names])
    return points


def _check_pcd_ascii(path: Path, data_at: int, points: int, fields: list) -> None:
    """open3d reads one point per line of at least sum(COUNT) words (shorter lines skipped),
    each field from its first word, with strtod / strtol and no check. fields: (numpy type
    code, COUNT, whether the reader uses it)."""
    columns, offset = [], 0
    for code, count, used in fields:  # only the fields read into the cloud are checked
        if used:
            columns.append((offset, code))
        offset += count
    with open(path, "rb") as fh:
        fh.seek(data_at)
        data = fh.read()
    # open3d splits words at tab, CR, LF and space only; bytes.split() (fast) also at VT, FF
    other_space = b"\x0b" in data or b"\x0c" in data
    rows: list[list[bytes]] = []
    for n, line in enumerate(data.split(b"\n"), 1):
        if len(line) >= _O3D_LINE_BYTES or b"\0" in line:
            raise _bad(path, "PCD", f"data line {n} is longer than {_O3D_LINE_BYTES - 1} "
                                    "bytes or has a NUL byte")
        words = [w for w in _WORDS.split(line) if w] if other_space else line.split()
        if len(words) >= offset:
            rows.append(words)
            if len(rows) == points:
                break
    if len(rows) < points:
        raise _bad(path, "PCD", f"POINTS {points} but the ascii data has {len(rows)} point "
                                "lines")
    for col, code in columns:  # one regex pass per column; word by word only to name the bad one
        words = [r[col] for r in rows]
        if _all_numbers(words, code):
            continue
        for n, word in enumerate(words, 1):
            if not _number_ok(word, code, strict=False):
                raise _bad(path, "PCD", f"point {n}: {_shown(word)} is not a number of "
                                        f"type {code}")


def _all_numbers(words: list[bytes], code: str) -> bool:
    """Every word a number of type code, by the rules of _number_ok (PCD ascii), checked in
    bulk by numpy; False sends the caller word by word (numpy reads 1_0 as 10 and 010 as 10
    where strtod / strtol read 1 and 8: those go that way too)."""
    joined = b"\n".join(words)
    if b"_" in joined or (code[0] != "f" and _LEADING_ZERO.search(joined)):
        return False
    try:
        values = np.array(words).astype(np.float64 if code[0] == "f" else np.int64)
    except (ValueError, OverflowError):
        return False
    if code[0] == "f":
        return True
    info = np.iinfo(code)
    return bool(((values >= info.min) & (values <= min(info.max, 2**63 - 1))).all())


def _check_ply(path: Path, head: bytes, size: int) -> int:
    """Vertices of a PLY file open3d can read in full (0 for none), else an InputError."""
    kind = "PLY"
    if not (head[:3] == b"ply" and head[3:4] in (b"\n", b"\r")):
        raise _bad(path, kind, "does not start with 'ply'")
    crlf = head[3:5] == b"\r\n"
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
    for n, (words, pos, line) in enumerate(_header_lines(head, path, kind, b"end_header")):
        if n == 0 or not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and fmt is None and len(words) == 3 and words[2] == "1.0" \
                and words[1] in ("ascii", "binary_little_endian", "binary_big_endian"):
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append((words[1], _count(path, kind, words[2], "element count"), []))
        elif words[0] == "property" and elements and len(words) == 3 \
                and words[1] in PLY_TYPE_CODES:
            elements[-1][2].append((words[2], PLY_TYPE_CODES[words[1]]))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list" \
                and words[2] in PLY_TYPE_CODES and words[3] in PLY_TYPE_CODES:
            elements[-1][2].append((words[4], None))
        elif words[0] == "end_header" and len(words) == 1:
            if fmt is None:
                raise _bad(path, kind, "no 'format' line")
            if line != (b"end_header\r\n" if crlf else b"end_header\n"):
                raise _bad(path, kind, "end_header line ends unlike the 'ply' line")
            return _check_ply_data(path, fmt, elements, pos, size)
        else:
            raise _bad(path, kind, f"header line {n + 1}: {' '.join(words)[:40]!r}")
    raise AssertionError("unreachable")  # _header_lines ends at end_header or raises


def _check_ply_data(path: Path, fmt: str, elements: list, data_at: int, size: int) -> int:
    kind = "PLY"
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise _bad(path, kind, "no 'vertex' element")
    upto = elements[:names.index("vertex") + 1]
    vertex = upto[-1]
    props = [p[0] for p in vertex[2]]
    if not {"x", "y", "z"} <= set(props) or len(set(props)) != len(props):
        raise _bad(path, kind, "vertex properties need x, y, z once each")
    if any(code is None for _, _, plist in upto for _, code in plist):
        raise _bad(path, kind, "list properties in or before 'vertex' are not supported")
    if vertex[1] == 0:
        return 0
    if fmt != "ascii":
        need = sum(count * sum(np.dtype(c).itemsize for _, c in plist)
                   for _, count, plist in upto)
        if size - data_at < need:
            raise _bad(path, kind, f"binary data is {size - data_at} bytes, the header needs "
                                   f"{need} up to the last vertex")
        return vertex[1]
    codes = [c for _, count, plist in upto for _ in range(count) for _, c in plist]
    with open(path, "rb") as fh:
        fh.seek(data_at)
        words = [w for w in re.split(rb"[ \n\r\t]+", fh.read()) if w]
    if len(words) < len(codes):
        raise _bad(path, kind, f"ascii data has {len(words)} values, the header needs "
                               f"{len(codes)} up to the last vertex")
    for i, (word, code) in enumerate(zip(words, codes)):
        if not _number_ok(word, code, strict=True):
            raise _bad(path, kind, f"ascii value {i + 1} {_shown(word)} is not a number of "
                                   f"type {code}")
    return vertex[1]


def _o3d_message(exc: Exception) -> str:
    """The problem in an open3d RuntimeError ('[Open3D Error] (function) file:line: problem')."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).strip().splitlines()
    return re.sub(r"^.*?\.cpp:\d+: ", "", text[0] if text else "error")[:120]


def read_o3d(path: Path, stamp_ns: int | None = None) -> CloudData:
    """A .pcd or .ply file, read by open3d once its header and data size are checked."""
    from lidar_slam.o3d import o3d

    kind = path.suffix.lower()[1:].upper()
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(_HEAD_BYTES)
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror})") from exc
    n = _check_pcd(path, head, size) if kind == "PCD" else _check_ply(path, head, size)
    if n == 0:
        return CloudData(np.zeros((0, 3)), None, None)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        try:
            pcd = o3d.t.io.read_point_cloud(str(path))
        except RuntimeError as exc:
            raise InputError(path, f"open3d cannot read it: {_o3d_message(exc)}") from None
    got = len(pcd.point.positions) if "positions" in pcd.point else 0
    if got != n:
        raise InputError(path, f"unreadable {kind} file (open3d decoded {got} of its {n} "
                               "points)")
    pts = pcd.point.positions.numpy().astype(np.float64).reshape(-1, 3)
    times = intensity = None
    for name in TIME_FIELDS:
        if name in pcd.point:
            times = relative_seconds(_column(path, pcd.point[name].numpy(), name, n), stamp_ns)
            break
    for name in INTENSITY_FIELDS:
        if name in pcd.point:
            intensity = _float32(_column(path, pcd.point[name].numpy(), name, n))
            break
    return CloudData(pts, times, intensity)


def _float32(values: np.ndarray) -> np.ndarray:
    """Intensities as float32 (a value beyond float32 becomes inf, without a warning)."""
    with np.errstate(over="ignore"):
        return values.astype(np.float32)


def _column(path: Path, values: np.ndarray, name: str, n: int) -> np.ndarray:
    if values.shape not in ((n,), (n, 1)) or values.dtype.kind not in "iuf":
        raise InputError(path, f"field {name!r} is {values.dtype} {values.shape}, expected one "
                               f"number per point ({n})")
    return values.reshape(n)


def _numeric_field(path: Path, arr: np.ndarray, name: str) -> np.ndarray:
    """One number per point from a structured .npy's field."""
    dtype = arr.dtype[name]
    if dtype.kind not in "iuf" or dtype.shape != ():
        raise InputError(path, f"field {name!r} is {dtype}, expected one number per point")
    return arr[name]


def read_npy(path: Path, stamp_ns: int | None = None) -> CloudData:
    """.npy: (N,3|4|5) numbers [x y z (intensity) (time)], or a structured array with fields
    x, y, z (and a time / intensity field)."""
    try:  # memory-mapped: a header that claims more data than the file has is refused here
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "Python objects" in str(exc):  # not numbers: no pickle
            raise InputError(path, "a .npy of Python objects (pickled), not of numbers; save "
                                   "the points as a numeric array") from None
        raise InputError(path, f"unreadable .npy ({str(exc).splitlines()[0][:120]})") from None
    except (OSError, EOFError, SyntaxError, TokenError) as exc:
        # NumPy parses the header with ast / tokenize: a damaged one raises their errors
        raise InputError(path, f"unreadable .npy ({str(exc).splitlines()[0][:120]})") from None
    if arr.dtype.names:
        arr = arr.reshape(-1)
        names = arr.dtype.names
        if not {"x", "y", "z"} <= set(names):
            raise InputError(path, f"structured .npy needs x, y, z fields (has "
                                   f"{', '.join(names)[:80]})")
        pts = np.stack([_numeric_field(path, arr, a) for a in "xyz"], axis=1)
        tname = next((n for n in TIME_FIELDS if n in names), None)
        iname = next((n for n in INTENSITY_FIELDS if n in names), None)
        times = relative_seconds(_numeric_field(path, arr, tname), stamp_ns) if tname else None
        inten = _float32(_numeric_field(path, arr, iname)) if iname else None
        return CloudData(pts.astype(np.float64), times, inten)
    if arr.ndim != 2 or arr.shape[1] not in (3, 4, 5) or arr.dtype.kind not in "iuf":
        raise InputError(path, f"expected an (N,3|4|5) array of numbers [x y z (intensity) "
                               f"(time_s)], got {arr.dtype} {arr.shape}")
    pts = arr[:, :3].astype(np.float64)
    inten = _float32(arr[:, 3]) if arr.shape[1] >= 4 else None
    times = relative_seconds(np.array(arr[:, 4]), stamp_ns) if arr.shape[1] == 5 else None
    return CloudData(pts, times, inten)


def read_cloud(path: str | Path, stamp_ns: int | None = None) -> CloudData:
    """Read one scan file, by suffix; per-point times in seconds relative to the scan stamp
    (stamp_ns, when known, recognises absolute times; see lidar_slam.io.point_times)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".bin":
        return read_bin(p)
    if suffix in (".pcd", ".ply"):
        return read_o3d(p, stamp_ns)
    if suffix == ".npy":
        return read_npy(p, stamp_ns)
    raise InputError(p, f"unsupported scan format '{suffix}' (use {', '.join(SCAN_SUFFIXES)})")


def make_scan(index: int, stamp_s: float, cloud: CloudData, source: str) -> Scan:
    """Build a Scan, dropping points with NaN/inf coordinates (counted in the log)."""
    points, times, inten = cloud.points, cloud.times, cloud.intensity
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf: NaN, no warning
        # One contiguous sum: a NaN/inf anywhere makes it non-finite (3x faster than per row).
        suspect = not np.isfinite(np.add.reduce(points.ravel()))
    finite = np.isfinite(points).all(axis=1) if suspect else None
    if finite is not None and not finite.all():  # (an overflowing finite sum lands here too)
        log.warning("%s: dropped %d points with NaN/inf coordinates", source, int((~finite).sum()))
        points = points[finite]
        times = times[finite] if times is not None else None
        inten = inten[finite] if inten is not None else None
    if times is not None and not np.isfinite(times).all():
        times = None
    bad = None if inten is None else ~np.isfinite(inten)
    if bad is not None and bad.any():
        log.warning("%s: %d NaN/inf intensities set to 0", source, int(bad.sum()))
        inten = np.where(bad, 0, inten).astype(inten.dtype)
    return Scan(index, float(stamp_s), points, times, inten, source)
