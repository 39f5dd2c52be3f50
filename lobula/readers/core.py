"""The footage core: what every layout reader returns, and the checks they share.

:class:`Footage` is the streamed recording (camera, frame times, frames on demand, IMU,
truth), :class:`IMU` its inertial samples, :class:`FootageError` the one error a bad
input raises. The layout readers (:mod:`lobula.readers.folder`, :mod:`lobula.readers.realsense_bag`,
:mod:`lobula.readers.rosbag2_db3`, :mod:`lobula.readers.euroc`, :mod:`lobula.readers.video`,
:mod:`lobula.readers.gopro`) import this module; :func:`lobula.readers.open_footage` imports
them only when it opens their layout, so there is no import circle.

Conventions every reader keeps (COMMON contract 4):

* ``Footage.imu`` is in the camera optical frame (x right, y down, z forward), on the
  frames' clock, in seconds;
* ``frames()`` yields (index, time_s, grey float32 (H, W) in grey levels 0..255), decoding
  one frame at a time, so memory does not grow with the recording's length;
* with ``skip_bad_frames`` set, a frame that cannot be decoded is left out and its index
  kept in ``skipped_frames`` instead of stopping the run.
"""
from __future__ import annotations

import csv
import json
import math
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from lobula.camera import PinholeCamera


class FootageError(ValueError):
    """Bad or missing footage input; the message names the file and what to do."""


#: the fields every camera.json holds
CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "frame_rate_hz")


def read_camera_json(path: str | Path) -> PinholeCamera:
    """The intrinsics of the camera.json at ``path`` (width, height, fx, fy, cx, cy in pixels; frame_rate_hz
    in Hz; optionally rolling_shutter_s in s), each field checked: a FootageError names the file, the field, what
    it must be and what it is."""
    path = Path(path)
    need = ", ".join(CAMERA_FIELDS)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise FootageError(f"{path}: not found; write a camera.json with {need}, or give one with --camera FILE"
                           ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FootageError(f"{path}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    except json.JSONDecodeError as exc:
        raise FootageError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno}); "
                           f"a camera.json is one object with {need}") from None
    if not isinstance(d, dict):
        raise FootageError(f"{path}: must be one JSON object with {need}")
    missing = [k for k in CAMERA_FIELDS if k not in d]
    if missing:
        raise FootageError(f"{path}: missing {', '.join(missing)}; a camera.json needs {need}")
    vals = {}
    for k in CAMERA_FIELDS:
        v = d[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise FootageError(f"{path}: {k} must be a finite number, got {json.dumps(v)}")
        if k in ("width", "height") and v != int(v):
            raise FootageError(f"{path}: {k} must be a whole number of pixels, got {v:g}")
        if k in ("width", "height", "fx", "fy", "frame_rate_hz") and v <= 0:
            raise FootageError(f"{path}: {k} must be > 0, got {v:g}")
        vals[k] = int(v) if k in ("width", "height") else float(v)
    if "rolling_shutter_s" in d:  # optional: a rolling shutter's readout (lobula.rolling_shutter)
        v = d["rolling_shutter_s"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0 / vals["frame_rate_hz"]:
            raise FootageError(f"{path}: rolling_shutter_s (s, the first row's exposure to the last's) must be a "
                               f"number from 0 to the frame interval {1.0 / vals['frame_rate_hz']:.4f} s, got "
                               f"{json.dumps(v)}")
        vals["rolling_shutter_s"] = float(v)
    return PinholeCamera(**vals)


def read_csv_columns(path: Path, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The CSV at ``path`` (a header row) as {column: (n,) array} (float where every value parses);
    clear errors, among them a missing column of ``required`` (names) and a row cut short
    (:func:`read_csv_table`, which also gives each row's line number)."""
    return read_csv_table(path, required)[0]


def read_csv_table(path: Path, required: tuple[str, ...]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The CSV at ``path`` (a header row) as ({column: (n,) array}, each row's line number in the file (n,)).

    A column is float where every value parses, text otherwise. A FootageError names the file
    where it is missing or unreadable, lacks a column of ``required`` (names), has no rows, or
    has a row with fewer values than the header names (a file cut off mid-row).
    """
    try:
        with open(path, newline="") as fh:
            reader = csv.reader(fh)
            cols = next(reader, [])
            rows, lines = [], []
            for row in reader:
                if row:  # a blank line is no row
                    rows.append(row)
                    lines.append(reader.line_num)
    except FileNotFoundError:
        raise FootageError(f"{path}: file not found") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise FootageError(f"{path}: not a readable CSV ({exc})") from None
    missing = [c for c in required if c not in cols]
    if missing:
        raise FootageError(f"{path}: missing column(s) {missing}; expected {list(required)}")
    if not rows:
        raise FootageError(f"{path}: no rows")
    check_row_lengths(path, rows, lines, len(cols))
    out = {}
    for k, c in enumerate(cols):
        try:
            out[c] = np.array([float(r[k]) for r in rows])
        except ValueError:
            out[c] = np.array([r[k] for r in rows])
    return out, np.asarray(lines, int)


def check_row_lengths(path: Path, rows: list[list[str]], lines: list[int], needed: int) -> None:
    """FootageError naming the first of ``rows`` (lists of values; ``lines``, their line numbers in the file at
    ``path``) with fewer than ``needed`` values: a row cut short, as a copy or a recording stopped mid-row leaves
    the last one."""
    for row, line in zip(rows, lines):
        if len(row) < needed:
            raise FootageError(f"{path}: row {line} has {len(row)} column{'s' * (len(row) != 1)}, {needed} needed "
                               f"(cut short?); complete or remove that row")


def row_of(lines: np.ndarray | None, index: int) -> int:
    """The file's line number of data row ``index`` (0-based): from ``lines`` (each row's line number) where
    given, else counted after one header line."""
    return int(lines[index]) if lines is not None else index + 2


def check_times(path: Path, t: np.ndarray, what: str = "time_s", lines: np.ndarray | None = None) -> None:
    """Times ``t`` (n,) s must be finite and strictly increasing; the FootageError names ``path``, the
    column ``what`` and the first bad row by its line number in the file (``lines`` (n,), each row's; default
    one header line and no blank lines)."""
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise FootageError(f"{path}: {what} has NaN or infinite values (first at row {row_of(lines, bad[0])}); "
                           f"remove those rows")
    bad = np.flatnonzero(np.diff(t) <= 0) + 1  # the row that fails to come after the one before it
    if bad.size:
        k = int(bad[0])
        raise FootageError(f"{path}: {what} does not increase at row {row_of(lines, k)} "
                           f"({t[k]} after {t[k - 1]}); sort the rows and drop duplicates")


@contextmanager
def opencv_quiet() -> Iterator[None]:
    """OpenCV's own log off while the block runs: a damaged image is reported once, by the reader's
    FootageError (or counted by --skip-bad-frames), not also by OpenCV's "[ERROR…] readHeader" lines."""
    try:
        before = cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # an OpenCV build without the logging module
        yield
        return
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(before)


def read_frame(path: Path) -> np.ndarray:
    """Decode the image file at ``path`` as grey float32 (H, W) in grey levels 0..255; clear error if corrupt."""
    if not path.exists():
        raise FootageError(f"{path}: frame file is missing")
    with opencv_quiet():
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FootageError(f"{path}: cannot decode this image (corrupt or not an image); replace or remove it")
    return to_grey(img)


def to_grey(img: np.ndarray) -> np.ndarray:
    """OpenCV-decoded image ``img`` ((H, W) grey, or (H, W, 1|3|4) grey, BGR or BGRA; 8 or 16 bit) -> grey
    float32 (H, W) in 0..255."""
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 257.0
    return img.astype(np.float32)


def frame_gaps(times: np.ndarray, nominal_dt: float | None = None) -> dict:
    """Dropped frames judged from the time stamps ``times`` (n,) s: intervals over 1.5 nominal frame intervals.

    nominal_dt: the frame interval (s); default the median interval. Returns
    {"gaps": number of long intervals, "missing": frames missing in them (each interval
    counts round(Δt/dt) − 1), "largest_s": the longest interval (s), "first_at_s": time (s) of the
    first gap or None}.
    """
    t = np.asarray(times, float)
    if t.size < 2:
        return dict(gaps=0, missing=0, largest_s=0.0, first_at_s=None)
    d = np.diff(t)
    dt = float(nominal_dt or np.median(d))
    long = d > 1.5 * dt
    return dict(gaps=int(long.sum()), missing=int(np.sum(np.round(d[long] / dt) - 1)),
                largest_s=float(d.max()), first_at_s=float(t[np.flatnonzero(long)[0]]) if long.any() else None)


def rotation_from_json(value, where: str) -> np.ndarray:
    """A rotation matrix (3, 3) from ``value``, a list of 3 lists of 3 numbers; a FootageError naming
    ``where`` unless it is orthonormal with det +1."""
    try:
        r = np.asarray(value, float)
    except (TypeError, ValueError):
        r = np.zeros(0)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise FootageError(f"{where}: imu_to_camera must be a 3x3 rotation matrix (list of 3 lists of 3 numbers)")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0:
        raise FootageError(f"{where}: imu_to_camera is not a rotation (R Rᵀ ≠ I or det < 0); give R with "
                           f"v_cam = R @ v_imu")
    return r


def rotation_deg(r: np.ndarray) -> float:
    """Angle (degrees) of the rotation matrix ``r`` (3, 3)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


@dataclass
class IMU:
    """IMU samples in the camera optical frame: time_s (n,) s, accel (n, 3) m/s², gyro (n, 3) rad/s or None;
    source: where they were read from (a path, or path:topic).

    nan_counts: {column of the file: rows with NaN or no value there}, filled only where the
    samples were read keeping such rows (``lobula info``, which reports them); empty otherwise.
    """

    time_s: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray | None
    source: str
    nan_counts: dict[str, int] = field(default_factory=dict)

    def rotated(self, r: np.ndarray) -> "IMU":
        """The same samples with every vector rotated by r (3, 3) (v' = r @ v)."""
        return IMU(self.time_s, self.accel @ r.T, None if self.gyro is None else self.gyro @ r.T, self.source,
                   self.nan_counts)

    def shifted(self, offset_s: float) -> "IMU":
        """The same samples on a clock ``offset_s`` (s) later (t' = t + offset)."""
        return IMU(self.time_s + offset_s, self.accel, self.gyro, self.source, self.nan_counts)


@dataclass
class Footage:
    """A streamed recording: camera intrinsics, frame times and files, IMU and truth.

    Iterate :meth:`frames` for (index, time_s, image (H, W) float32 grey levels).
    ``path``: the recording; ``kind``: its layout's name; ``times`` (n,) s and ``files`` (n): each
    frame's time and file (placeholders where frames live inside a container); ``notes``: what the
    reader chose, one line each. ``imu`` may be None (then velocity needs ``accel_from_truth``); ``truth`` maps
    column name -> array at ``truth['time_s']``. ``distortion`` describes lens distortion
    the reader removed or ignored (None: none reported); ``imu_to_camera`` the rotation
    applied to the IMU on reading (None: none needed or known), and ``camera_file_imu_rotation`` the part of it
    the camera file's "imu_to_camera" gave (the whole rotation for a footage folder or a video, a correction after
    the reader's own axes for a GoPro or camera-telemetry file; None where the file gave none). ``skip_bad_frames``,
    ``skipped_frames`` and the clock offset fields (``clock_offset_s``, s added to the IMU's times;
    ``clock_offset_source``, where it came from) are filled by :func:`lobula.readers.open_footage`;
    ``streams`` lists what the recording holds (one dict per topic or sensor: name, type, count, ...);
    ``truth_nan_counts`` the truth log's NaN or empty values per column (filled where counted);
    ``lens_maps`` the remap that takes a distorted lens's frames onto ``camera``, a pinhole
    (:func:`lobula.readers.open_footage` sets it from a camera.json's "distortion").
    """

    path: Path
    camera: PinholeCamera
    times: np.ndarray
    files: list[Path]
    imu: IMU | None = None
    truth: dict[str, np.ndarray] | None = None
    kind: str = "folder"
    notes: list[str] = field(default_factory=list)
    distortion: dict | None = None
    imu_to_camera: np.ndarray | None = None
    camera_file_imu_rotation: np.ndarray | None = None
    skip_bad_frames: bool = False
    skipped_frames: list[int] = field(default_factory=list)
    clock_offset_s: float = 0.0
    clock_offset_source: str = "none"
    streams: list[dict] = field(default_factory=list)
    truth_nan_counts: dict[str, int] = field(default_factory=dict)
    lens_maps: tuple | None = None

    def __len__(self) -> int:
        return len(self.files)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """(index, time s, image (H, W) float32 grey levels) of frames start..stop − 1, the lens's distortion
        removed where the footage has one (:attr:`lens_maps`, :func:`lobula.lens.undistortion_maps`)."""
        if self.lens_maps is None:
            yield from self.raw_frames(start, stop)
            return
        from lobula.lens import undistort

        for i, t, img in self.raw_frames(start, stop):
            yield i, t, undistort(img, self.lens_maps)

    def raw_frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """(index, time s, image (H, W) float32 grey levels) of frames start..stop − 1 as the recording
        holds them (a reader's own frame loop overrides this)."""
        stop = len(self) if stop is None else min(stop, len(self))
        for i in range(start, stop):
            try:
                img = self.decode(i)
            except FootageError as exc:
                self.bad_frame(i, exc)
                continue
            yield i, float(self.times[i]), img

    def decode(self, i: int) -> np.ndarray:
        """Frame i as grey float32 (H, W); FootageError if it cannot be decoded or has the wrong size."""
        img = read_frame(self.files[i])
        self.check_size(img, self.files[i])
        return img

    def check_size(self, img: np.ndarray, where) -> None:
        """FootageError naming ``where`` unless ``img`` is (H, W) as the camera says."""
        if img.shape != (self.camera.height, self.camera.width):
            raise FootageError(f"{where}: image is {img.shape[1]}x{img.shape[0]}, the intrinsics say "
                               f"{self.camera.width}x{self.camera.height}")

    def bad_frame(self, i: int, exc: Exception) -> None:
        """Frame i could not be decoded (``exc``, why): raise, or (skip_bad_frames) remember it and go on."""
        if not self.skip_bad_frames:
            raise exc if isinstance(exc, FootageError) else FootageError(str(exc))
        if i not in self.skipped_frames:
            self.skipped_frames.append(i)

    def depth_map(self, index: int) -> np.ndarray | None:
        """Frame ``index``'s forward depth (H, W), camera z in m, from ``depth/<index>.npy``, or None."""
        p = self.path / "depth" / f"{index:06d}.npy"
        return np.load(p) if p.exists() else None

    def provenance(self) -> dict:
        """What an output's attrs say about how this footage was read (call after streaming it)."""
        gaps = frame_gaps(self.times)
        return dict(footage_layout=self.kind,
                    frames_skipped=len(self.skipped_frames),
                    frames_skipped_indices=json.dumps(self.skipped_frames[:100]),
                    frames_dropped=gaps["missing"], frame_gaps=gaps["gaps"],
                    clock_offset_s=float(self.clock_offset_s), clock_offset_source=self.clock_offset_source,
                    camera_intrinsics=json.dumps(self.camera.to_dict()),
                    lens_distortion=json.dumps(self.distortion) if self.distortion else "none",
                    imu_to_camera=json.dumps(np.round(self.imu_to_camera, 9).tolist())
                    if self.imu_to_camera is not None else "none")


def imu_to_camera(path: Path) -> np.ndarray | None:
    """The optional "imu_to_camera" rotation (3, 3) of the camera.json at ``path`` (v_cam = R @ v_imu),
    checked; None where it has none."""
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if "imu_to_camera" not in d:
        return None
    return rotation_from_json(d["imu_to_camera"], str(path))


def numeric_column(values: np.ndarray) -> np.ndarray:
    """A CSV column ``values`` (n,) as float (n,), empty cells and "nan" as NaN; ValueError on any other text."""
    if values.dtype.kind == "f":
        return values
    return np.array([float(v) if str(v).strip() else np.nan for v in values], float)


def nan_counts(columns: dict[str, np.ndarray]) -> dict[str, int]:
    """{column: rows that are NaN, infinite or empty}, for the columns that have any."""
    out = {}
    for name, v in columns.items():
        try:
            n = int(np.count_nonzero(~np.isfinite(numeric_column(np.asarray(v)))))
        except ValueError:
            continue
        if n:
            out[name] = n
    return out


def read_imu_csv(imu_path: Path, rotation: np.ndarray | None = None, keep_nan: bool = False) -> IMU:
    """The imu.csv at ``imu_path`` (time_s s, accel_x..z m/s², gyro_x..z rad/s) as an IMU, rotated by
    ``rotation`` (3, 3) if given.

    A NaN, infinite or empty value is a FootageError naming its row, unless ``keep_nan``: then
    rows without a time are left out, other such values kept, and every column's count of them is in
    the IMU's ``nan_counts`` (what ``lobula info`` reports).
    """
    cols = ("time_s", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
    d, lines = read_csv_table(imu_path, cols)
    try:
        v = {c: numeric_column(d[c]) for c in cols}
    except ValueError:
        raise FootageError(f"{imu_path}: non-numeric values; every IMU column must be a number") from None
    acc = np.stack([v["accel_x"], v["accel_y"], v["accel_z"]], -1)
    gyr = np.stack([v["gyro_x"], v["gyro_y"], v["gyro_z"]], -1)
    t = v["time_s"]
    counts = nan_counts(v)
    if counts and not keep_nan:
        raise FootageError(f"{imu_path}: {not_finite_values(v, lines)}; repair or remove those rows "
                           f"(`lobula info` counts them)")
    if keep_nan:
        timed = np.isfinite(t)
        t, acc, gyr, lines = t[timed], acc[timed], gyr[timed], lines[timed]
    check_times(imu_path, t, lines=lines)
    imu = IMU(t, acc, gyr, source=str(imu_path), nan_counts=counts)
    return imu.rotated(rotation) if rotation is not None else imu


def not_finite_values(columns: dict[str, np.ndarray], lines: np.ndarray) -> str:
    """What is wrong with the float ``columns`` ({name: (n,)}, at least one value not finite) in words: which
    kind of value (NaN or missing, infinite), in which columns, first at which row (``lines`` (n,), each row's
    line number in the file)."""
    bad = {c: ~np.isfinite(v) for c, v in columns.items() if not np.isfinite(v).all()}
    first = int(np.flatnonzero(np.any(list(bad.values()), axis=0))[0])
    values = np.concatenate([columns[c][m] for c, m in bad.items()])
    infinite, nan = np.isinf(values).any(), np.isnan(values).any()
    kind = ("NaN, missing or infinite values" if infinite and nan
            else "values that are not finite (inf)" if infinite else "NaN or missing values")
    return f"{kind} in {', '.join(bad)} (first at row {row_of(lines, first)})"


#: gravity, m/s²
GRAVITY_M_S2 = 9.80665
#: m/s²: below this median |specific force| an accelerometer reads no gravity. A camera is not in free fall for
#: most of a recording, so a working accelerometer's median |a| stays within a few m/s² of gravity's 9.81 (a
#: walk, a car, a hovering drone); a dead sensor reads 0, gravity-removed acceleration well under 1 g, and the
#: same readings in g about 1.
MIN_MEDIAN_SPECIFIC_FORCE_M_S2 = 3.0
#: Hz: the sample rates an IMU can have; a time_s outside them is not in seconds (an IMU in ms reads 1000 times
#: slower: 250 Hz as 0.25 Hz)
IMU_RATE_RANGE_HZ = (1.0, 1e5)
#: the time units a time_s column is mistakenly written in, and how many of them make a second
TIME_UNITS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))
#: an IMU spanning this many times the frames' span at a rate this slow (Hz) is a fast IMU's time_s in
#: milliseconds (a 1 kHz IMU reads 1 Hz); an IMU log that truly runs on beyond the video samples faster
MS_SPAN_RATIO, MS_MAX_RATE_HZ = 300.0, 20.0
#: what an imu.csv whose time_s is not in seconds is told to do
TIME_FIX = "write time_s in seconds, on the frames' clock"


def check_imu_csv(imu: IMU, frame_times: np.ndarray, notes: list[str], keep_nan: bool = False) -> None:
    """A FootageError where the IMU read from an imu.csv cannot be the one the layout documents (accelerometer in
    m/s², gravity included; time_s in s on the frames' clock, ``frame_times`` (n,) s); with ``keep_nan``
    (``lobula info``) the same said in ``notes`` instead, the footage opened."""
    problem = gravity_problem(imu) or rate_problem(imu) or span_problem(imu, frame_times)
    if problem is None:
        return
    if not keep_nan:
        raise FootageError(problem)
    notes.append(f"{problem} (lobula velocity refuses this IMU)")


def gravity_problem(imu: IMU) -> str | None:
    """Why ``imu``'s accelerometer (m/s²) reads no gravity, or None where it does (its median |a| at least
    :data:`MIN_MEDIAN_SPECIFIC_FORCE_M_S2`)."""
    norm = np.linalg.norm(imu.accel, axis=1)
    norm = norm[np.isfinite(norm)]
    if not norm.size or np.median(norm) >= MIN_MEDIAN_SPECIFIC_FORCE_M_S2:
        return None
    median, top = float(np.median(norm)), float(norm.max())
    if round(top, 3) == 0:
        seen, cause = "|a| 0.000 m/s² throughout", "a dead or unconnected sensor"
    else:
        seen = f"median |a| {median:.3f} m/s², at most {top:.3f}"
        cause = ("readings in g? (multiply them by 9.81)" if 0.8 <= median <= 1.25
                 else "a dead sensor, or acceleration with gravity removed")
    return (f"{imu.source}: the accelerometer reads no gravity: {seen}, where a working one reads about "
            f"{GRAVITY_M_S2:.2f} m/s² at rest ({cause}); accel_x..z must be the specific force in m/s², "
            f"gravity included")


def imu_rate(imu: IMU) -> tuple[float, float] | None:
    """(span s, mean sample rate Hz) of ``imu``'s time_s, or None where it has fewer than 2 samples."""
    t = imu.time_s
    if len(t) < 2:
        return None
    span = float(t[-1] - t[0])
    return span, (len(t) - 1) / span


def rate_problem(imu: IMU) -> str | None:
    """Why ``imu``'s time_s is not in seconds where its sample rate is one no IMU has (outside
    :data:`IMU_RATE_RANGE_HZ`), naming the likeliest unit it is in; else None."""
    low, high = IMU_RATE_RANGE_HZ
    span_rate = imu_rate(imu)
    if span_rate is None or low <= span_rate[1] <= high:
        return None
    span, rate = span_rate
    said = f"{len(imu.time_s)} samples over {span:.6g} s is a rate of {rate:.3g} Hz"
    rates = f"where an IMU samples at {low:g} Hz to {high / 1e3:g} kHz"
    fits = [(unit, rate * k) for unit, k in TIME_UNITS if low <= rate * k <= high]
    if not fits:
        return f"{imu.source}: time_s is not in seconds: {said}, {rates}; {TIME_FIX}"
    unit, real = min(fits, key=lambda f: abs(np.log10(f[1] / 200.0)))  # the likeliest: nearest a common 200 Hz
    return f"{imu.source}: time_s looks like {unit}, not seconds: {said} ({real:.0f} Hz in {unit}), {rates}; {TIME_FIX}"


def span_problem(imu: IMU, frame_times: np.ndarray) -> str | None:
    """Why ``imu``'s time_s is in milliseconds where it spans :data:`MS_SPAN_RATIO` times the frames' span
    (``frame_times`` (n,) s) or more at :data:`MS_MAX_RATE_HZ` or slower; else None."""
    span_rate = imu_rate(imu)
    frames = float(frame_times[-1] - frame_times[0]) if len(frame_times) > 1 else 0.0
    if span_rate is None or frames <= 0:
        return None
    span, rate = span_rate
    if span < MS_SPAN_RATIO * frames or rate > MS_MAX_RATE_HZ:
        return None
    return (f"{imu.source}: time_s looks like milliseconds, not seconds: the IMU spans {span:.6g} s, "
            f"{span / frames:.0f} times the frames' {frames:.3g} s, at a rate of {rate:.3g} Hz ({rate * 1e3:.0f} Hz "
            f"in milliseconds); {TIME_FIX}")


def read_truth_csv(path: Path, keep_nan: bool = False) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """The truth.csv at ``path`` (time_s s, v_forward_m_s m/s, other columns; each (n,)) and its NaN count per
    column.

    Rows without a time are a FootageError naming the file, unless ``keep_nan`` (then they are
    left out and counted); NaN velocities are kept either way (counted).
    """
    truth, lines = read_csv_table(path, ("time_s", "v_forward_m_s"))
    counts = nan_counts(truth)
    for k, v in truth.items():
        try:
            truth[k] = numeric_column(v)
        except ValueError:  # a text column (a label) stays text; time and velocity must be numbers
            if k in ("time_s", "v_forward_m_s"):
                raise FootageError(f"{path}: {k} has values that are not numbers; repair those rows") from None
    if keep_nan:
        keep = np.isfinite(truth["time_s"])
        truth = {k: v[keep] for k, v in truth.items()}
        lines = lines[keep]
    check_times(path, truth["time_s"], lines=lines)
    return truth, counts


def footage_provenance(footage) -> dict:
    """The attrs an output carries about its footage (works on wrappers without the method too)."""
    fn = getattr(footage, "provenance", None)
    if fn is None and hasattr(footage, "_footage"):
        fn = getattr(footage._footage, "provenance", None)
    return fn() if fn is not None else {}


def acceleration_from_truth(truth: dict[str, np.ndarray], smoothing_s: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Forward acceleration (m/s²) as the derivative of Gaussian-smoothed ground-truth velocity.

    truth: {"time_s": (n,) s, "v_forward_m_s": (n,) m/s, optionally "a_forward_m_s2"};
    smoothing_s: the Gaussian's std, s. Returns (time_s (n,) s, a (n,) m/s²).
    Used where a recording has no accelerometer (the D435i sample),
    and always labelled as such in outputs.
    """
    from scipy.ndimage import gaussian_filter1d  # here: SciPy is slow to load, and only this needs it

    t, v = truth["time_s"], truth["v_forward_m_s"]
    if "a_forward_m_s2" in truth:
        return t, truth["a_forward_m_s2"]
    dt = float(np.median(np.diff(t)))
    return t, gaussian_filter1d(v, smoothing_s / dt, order=1, mode="nearest") / dt
