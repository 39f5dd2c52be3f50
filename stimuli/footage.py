"""Footage: reading frames + IMU + truth, streamed frame by frame, and writing synthetic runs.

Three layouts are read (DESIGN.md, "Footage folder"):

* a **footage folder**: camera.json, frames/, frames.csv, imu.csv, optional truth.csv
  and depth/ (what :func:`write_footage` makes);
* the **D435i sample** of the FLIVVER track run as shipped in ``../shared/data``:
  frames named by raw frame number, ``velocity.csv`` with raw_frame = sample + 3
  and no IMU, so forward acceleration is derived from the smoothed ground truth
  (and every output says so);
* Middlebury ``.flo`` flow files (:func:`read_flo`), whose units depend on who wrote them;
* RealSense ROS bags as the RealSense Viewer records them (:mod:`stimuli.realsense_bag`).

Frames are decoded one at a time on iteration, so memory does not grow with length.
"""
from __future__ import annotations

import csv
import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from lobula.camera import PinholeCamera


class FootageError(ValueError):
    """Bad or missing footage input; the message names the file and what to do."""


def _read_csv(path: Path, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            cols = reader.fieldnames or []
    except FileNotFoundError:
        raise FootageError(f"{path}: file not found") from None
    missing = [c for c in required if c not in cols]
    if missing:
        raise FootageError(f"{path}: missing column(s) {missing}; expected {list(required)}")
    if not rows:
        raise FootageError(f"{path}: no rows")
    out = {}
    for c in cols:
        try:
            out[c] = np.array([float(r[c]) for r in rows])
        except (TypeError, ValueError):
            out[c] = np.array([r[c] for r in rows])
    return out


def _check_times(path: Path, t: np.ndarray, what: str = "time_s") -> None:
    if not np.all(np.isfinite(t)):
        raise FootageError(f"{path}: {what} has NaN or infinite values; remove those rows")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise FootageError(f"{path}: {what} does not increase at row {bad[0] + 2} "
                           f"({t[bad[0]]} then {t[bad[0] + 1]}); sort the rows and drop duplicates")


def read_frame(path: Path) -> np.ndarray:
    """Decode one frame as grey float32 (H, W) in grey levels 0..255; clear error if corrupt."""
    if not path.exists():
        raise FootageError(f"{path}: frame file is missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FootageError(f"{path}: cannot decode this image (corrupt or not an image); replace or remove it")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 257.0
    return img.astype(np.float32)


@dataclass
class IMU:
    """IMU samples in the camera optical frame: time_s (n,), accel (n, 3) m/s², gyro (n, 3) rad/s or None."""

    time_s: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray | None
    source: str


@dataclass
class Footage:
    """A streamed recording: camera intrinsics, frame times and files, IMU and truth.

    Iterate :meth:`frames` for (index, time_s, image (H, W) float32 grey levels).
    ``imu`` may be None (then velocity needs ``accel_from_truth``); ``truth`` maps
    column name -> array at ``truth['time_s']``; ``accel_source`` says where forward
    acceleration comes from.
    """

    path: Path
    camera: PinholeCamera
    times: np.ndarray
    files: list[Path]
    imu: IMU | None = None
    truth: dict[str, np.ndarray] | None = None
    kind: str = "folder"
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.files)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        stop = len(self) if stop is None else min(stop, len(self))
        for i in range(start, stop):
            img = read_frame(self.files[i])
            if img.shape != (self.camera.height, self.camera.width):
                raise FootageError(f"{self.files[i]}: image is {img.shape[1]}x{img.shape[0]}, camera.json says "
                                   f"{self.camera.width}x{self.camera.height}")
            yield i, float(self.times[i]), img

    def depth_map(self, index: int) -> np.ndarray | None:
        p = self.path / "depth" / f"{index:06d}.npy"
        return np.load(p) if p.exists() else None


def open_footage(path: str | Path) -> Footage:
    """Open a footage folder or the D435i sample layout, checking everything cheap up front."""
    path = Path(path)
    if path.is_file() and path.suffix == ".bag":
        from .realsense_bag import open_realsense_bag
        return open_realsense_bag(path)
    if not path.is_dir():
        raise FootageError(f"{path}: not a folder or a .bag; give a footage folder (camera.json, frames/, "
                           f"frames.csv, imu.csv) or a RealSense Viewer recording (.bag)")
    if (path / "frames.csv").exists():
        return _open_folder(path)
    if (path / "velocity.csv").exists() and (path / "frames").is_dir():
        return _open_d435i_sample(path)
    raise FootageError(f"{path}: neither a footage folder (frames.csv) nor the D435i sample layout "
                       f"(frames/ + velocity.csv)")


def _open_folder(path: Path) -> Footage:
    camera = PinholeCamera.from_json(path / "camera.json")
    fr = _read_csv(path / "frames.csv", ("frame", "time_s", "file"))
    _check_times(path / "frames.csv", fr["time_s"])
    files = [path / str(f) for f in fr["file"]]
    missing = [f for f in files if not f.exists()]
    if missing:
        raise FootageError(f"{path / 'frames.csv'}: names {len(missing)} missing frame file(s), first "
                           f"{missing[0].relative_to(path)}; restore them or drop their rows")
    imu = None
    imu_path = path / "imu.csv"
    if imu_path.exists():
        cols = ("time_s", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
        d = _read_csv(imu_path, cols)
        acc = np.stack([d["accel_x"], d["accel_y"], d["accel_z"]], -1)
        gyr = np.stack([d["gyro_x"], d["gyro_y"], d["gyro_z"]], -1)
        if not (np.all(np.isfinite(acc)) and np.all(np.isfinite(gyr))):
            row = int(np.flatnonzero(~np.isfinite(np.c_[acc, gyr]).all(1))[0]) + 2
            raise FootageError(f"{imu_path}: NaN or missing values (first at row {row}); "
                               f"repair or remove those rows")
        _check_times(imu_path, d["time_s"])
        imu = IMU(d["time_s"], acc, gyr, source=str(imu_path))
    truth = None
    if (path / "truth.csv").exists():
        truth = _read_csv(path / "truth.csv", ("time_s", "v_forward_m_s"))
        _check_times(path / "truth.csv", truth["time_s"])
    return Footage(path, camera, fr["time_s"], files, imu, truth, kind="folder")


def _open_d435i_sample(path: Path) -> Footage:
    camera = PinholeCamera.from_json(path / "camera.json")
    vel = _read_csv(path / "velocity.csv", ("sample", "raw_frame", "time_s", "v_true_m_s"))
    _check_times(path / "velocity.csv", vel["time_s"])
    files = sorted((p for p in (path / "frames").iterdir() if re.fullmatch(r"\d+\.(png|jpg)", p.name)),
                   key=lambda p: int(p.stem))
    if not files:
        raise FootageError(f"{path / 'frames'}: no frames named by raw frame number (e.g. 0705.png)")
    raw = np.array([int(p.stem) for p in files])
    lookup = dict(zip(vel["raw_frame"].astype(int), vel["time_s"]))
    absent = [r for r in raw if r not in lookup]
    if absent:
        raise FootageError(f"{path / 'velocity.csv'}: no raw_frame {absent[0]} for frames/{files[0].name}")
    times = np.array([lookup[r] for r in raw])
    truth = {"time_s": vel["time_s"], "v_forward_m_s": vel["v_true_m_s"]}
    if "v_flivver_published_m_s" in vel:
        truth["v_published_m_s"] = vel["v_flivver_published_m_s"]
    note = ("D435i sample: no IMU recorded; forward acceleration derived from the ground-truth "
            "velocity (Gaussian-smoothed derivative); frame times from velocity.csv with "
            "raw_frame = sample + 3 (the authors' alignment, uncertain by about 3 frames)")
    return Footage(path, camera, times, files, None, truth, kind="d435i-sample", notes=[note])


def acceleration_from_truth(truth: dict[str, np.ndarray], smoothing_s: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Forward acceleration (m/s²) as the derivative of Gaussian-smoothed ground-truth velocity.

    Returns (time_s, a). Used where a recording has no accelerometer (the D435i sample),
    and always labelled as such in outputs.
    """
    t, v = truth["time_s"], truth["v_forward_m_s"]
    if "a_forward_m_s2" in truth:
        return t, truth["a_forward_m_s2"]
    dt = float(np.median(np.diff(t)))
    return t, gaussian_filter1d(v, smoothing_s / dt, order=1, mode="nearest") / dt


# ---------------------------------------------------------------------- .flo files
FLO_TAG = 202021.25


def read_flo(path: str | Path) -> np.ndarray:
    """Read a Middlebury .flo file: returns (2, H, W) float32 (u, v) in the file's own units."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(12)
        if len(head) < 12:
            raise FootageError(f"{path}: too short to be a .flo file")
        tag = np.frombuffer(head[:4], "<f4")[0]
        w, h = np.frombuffer(head[4:], "<i4")
        if tag != FLO_TAG or w <= 0 or h <= 0 or w * h > 1 << 28:
            raise FootageError(f"{path}: not a Middlebury .flo file (tag {tag}, size {w}x{h})")
        data = np.frombuffer(fh.read(), "<f4")
    if data.size != 2 * w * h:
        raise FootageError(f"{path}: truncated .flo file ({data.size} of {2 * w * h} values)")
    return data.reshape(h, w, 2).transpose(2, 0, 1).copy()


@dataclass(frozen=True)
class FloUnits:
    """What a .flo file's numbers mean.

    units: "rad/s" (pixel displacement / (fx_ref·gap_s): the FLIVVER files) or
    "px" (pixel displacement over the frame pair: FlowNet2's raw output).
    gap_s: time between the two frames (s). ref_width/ref_height: image size the flow
    was computed at (the FLIVVER files: 640×448, resized from 480 rows). In "rad/s" the
    FLIVVER convention divides both components by the *original* fx, so pixels of the
    resized image are value·gap·fx on both axes.
    """

    units: str = "rad/s"
    gap_s: float = 0.2
    ref_width: int = 640
    ref_height: int = 448


def flo_to_normalised(flow: np.ndarray, camera: PinholeCamera, units: FloUnits) -> np.ndarray:
    """Convert a .flo field to normalised flow (1/s) on the camera's full-size pixel grid, (2, H, W).

    The flow is resized to the camera image, its vectors rescaled by the change of pixel
    size, and divided by the focal lengths and the frame gap.
    """
    _, h, w = flow.shape
    if (w, h) != (units.ref_width, units.ref_height):
        raise FootageError(f".flo field is {w}x{h} but its units say {units.ref_width}x{units.ref_height}")
    sx, sy = camera.width / w, camera.height / h
    if units.units == "rad/s":
        # The FLIVVER convention: pixel displacement of the resized image = value·gap·fx.
        du = flow[0] * units.gap_s * camera.fx
        dv = flow[1] * units.gap_s * camera.fx
    elif units.units == "px":
        du, dv = flow[0], flow[1]
    else:
        raise ValueError(f"unknown .flo units {units.units!r}; use 'rad/s' or 'px'")
    du = cv2.resize(du.astype(np.float32), (camera.width, camera.height), interpolation=cv2.INTER_LINEAR) * sx
    dv = cv2.resize(dv.astype(np.float32), (camera.width, camera.height), interpolation=cv2.INTER_LINEAR) * sy
    return np.stack(camera.flow_px_to_normalised(du, dv, units.gap_s)).astype(np.float32)


# ---------------------------------------------------------------------- writing
def write_footage(folder: str | Path, scene, imu: dict, times: np.ndarray, metadata: dict,
                  depth_every: int = 10, progress=None) -> Path:
    """Render ``scene`` at ``times`` into a footage folder, atomically.

    Everything is written to a hidden sibling folder that is renamed into place only
    when complete, so an interrupted run leaves no folder that looks finished.
    """
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise FileExistsError(f"{folder}: exists and is not empty; choose a new folder or delete it")
    tmp = folder.parent / f".{folder.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "frames").mkdir(parents=True)
    (tmp / "depth").mkdir()
    try:
        cam = scene.camera
        (tmp / "camera.json").write_text(json.dumps(cam.to_dict(), indent=1))
        with open(tmp / "frames.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["frame", "time_s", "file"])
            for i, t in enumerate(times):
                name = f"frames/{i:06d}.png"
                cv2.imwrite(str(tmp / name), scene.render(float(t), i))
                if depth_every and i % depth_every == 0:
                    np.save(tmp / "depth" / f"{i:06d}.npy", scene.depth(float(t)))
                wr.writerow([i, f"{t:.6f}", name])
                if progress is not None:
                    progress(1)
        with open(tmp / "imu.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["time_s", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z"])
            for t, a, g in zip(imu["time_s"], imu["accel"], imu["gyro"]):
                wr.writerow([f"{t:.6f}", *(f"{x:.6f}" for x in a), *(f"{x:.7f}" for x in g)])
        vel = scene.camera_velocity(times)
        with open(tmp / "truth.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["time_s", "v_forward_m_s", "a_forward_m_s2", "position_m"])
            acc = scene.trajectory.acceleration(times)
            # Forward (optical-axis) acceleration: the track acceleration projected on z_cam.
            a_fwd = acc * np.einsum("nji,j->ni", scene.rotation(times), np.array([0, 0, 1.0]))[:, 2]
            for t, v, a, s in zip(times, vel[:, 2], a_fwd, scene.trajectory.position(times)):
                wr.writerow([f"{t:.6f}", f"{v:.6f}", f"{a:.6f}", f"{s:.6f}"])
        (tmp / "scene.json").write_text(json.dumps(metadata, indent=1, default=str))
        if folder.exists():
            folder.rmdir()
        tmp.rename(folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder
