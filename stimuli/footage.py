"""Footage: reading frames + IMU + truth, streamed frame by frame, and writing synthetic runs.

:func:`open_footage` is the one entry point; it picks the layout reader (DESIGN.md, "Footage folder"):

* a **footage folder**: camera.json, frames/, frames.csv, imu.csv, optional truth.csv
  and depth/ (what :func:`write_footage` makes);
* the **D435i sample** of the FLIVVER track run as shipped in ``../shared/data``:
  frames named by raw frame number, ``velocity.csv`` with raw_frame = sample + 3
  and no IMU, so forward acceleration is derived from the smoothed ground truth
  (and every output says so);
* Middlebury ``.flo`` flow files (:func:`read_flo`), whose units depend on who wrote them;
* RealSense ROS1 bags as the RealSense Viewer up to librealsense 2.57 records them
  (:mod:`stimuli.realsense_bag`) and rosbag2 ``.db3`` as 2.58 and later do (:mod:`stimuli.rosbag2_db3`);
* the ASL/EuRoC folder layout (:mod:`stimuli.euroc`);
* video files with an IMU CSV and camera.json (:mod:`stimuli.video`).

The data classes (:class:`Footage`, :class:`IMU`, :class:`FootageError`) live in
:mod:`stimuli.footage_core`, which the layout readers import; this module imports the
readers only inside :func:`open_footage`, so there is no import circle.

Frames are decoded one at a time on iteration, so memory does not grow with length.
"""
from __future__ import annotations

import csv
import errno
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from lobula.camera import PinholeCamera

from .footage_core import (IMU, Footage, FootageError, check_times as _check_times, frame_gaps,  # noqa: F401
                           atomic_folder, imu_to_camera, nan_counts, numeric_column, read_camera_json,
                           read_csv_columns as _read_csv, read_frame, read_imu_csv, read_truth_csv, rotation_deg,
                           rotation_from_json, to_grey)


def open_footage(path: str | Path, *, stream: str | None = None, clock: str | None = None,
                 require_imu: bool = True, skip_bad_frames: bool = False,
                 clock_offset: float | str | None = None, undistort: str = "same-k",
                 camera: str | Path | None = None, keep_nan: bool = False, require_camera: bool = True) -> Footage:
    """Open any footage the project reads, checking everything cheap up front.

    path: a footage folder, the D435i sample folder, a RealSense ``.bag`` (ROS1) or ``.db3``
    (rosbag2), an ASL/EuRoC folder (``mav0/``), or a video file (mp4, mkv, avi, mov) with
    ``camera.json`` and ``imu.csv`` beside it (or a folder holding those and one video), or a
    GoPro MP4 as the camera wrote it, with its GPMF telemetry track (:mod:`stimuli.gopro`).
    stream: RealSense recordings: image stream ("Color_0", "Infrared_1", or part of a topic;
    default colour, else infrared). clock: RealSense recordings: "device" (the frames' own
    time stamps, default), "header" (message header stamps) or "record" (the bag's record
    times). require_imu: bags, EuRoC and video stop when there is no accelerometer (False:
    open with ``imu=None``, as ``lobula info`` does). skip_bad_frames: leave undecodable
    frames out (counted in ``skipped_frames``) instead of stopping. clock_offset: seconds
    added to the IMU's times to put them on the frames' clock, or "auto" to estimate it
    (:mod:`stimuli.clock_offset`). undistort: EuRoC: "same-k" (undistort onto the same
    pinhole K) or "optimal" (onto OpenCV's optimal new K, all pixels valid). camera: a
    camera.json (width, height, fx, fy, cx, cy, frame_rate_hz; optionally imu_to_camera) to use
    instead of the recording's own intrinsics, on every layout (``--camera FILE``): for a folder
    or a video it stands for the camera.json beside the frames (its imu_to_camera too); for
    RealSense bags and EuRoC it replaces the recorded intrinsics (EuRoC's distortion is still
    removed with them). keep_nan: open IMU and truth logs with NaN or empty values, counting
    them per column (IMU.nan_counts, ``truth_nan_counts``) instead of stopping (``lobula info``).
    require_camera: a GoPro MP4 carries no intrinsics: without ``camera`` or a camera.json beside
    it, stop (True) or open it with ``camera=None`` (False, ``lobula info``).
    """
    path = Path(path)
    if clock not in (None, "device", "header", "record"):
        raise ValueError(f"unknown clock {clock!r}; choose device, header or record")
    suffix = path.suffix.lower()
    if not path.exists():
        raise FootageError(f"{path}: not found (not a folder or a file); give a footage folder, a RealSense "
                           f".bag/.db3, an EuRoC folder or a video file")
    cam_json = None if camera is None else Path(camera)
    intrinsics = None if cam_json is None else read_camera_json(cam_json)
    if path.is_file() and suffix == ".bag":
        from .realsense_bag import open_realsense_bag
        footage = open_realsense_bag(path, stream=stream, require_imu=require_imu, camera=intrinsics,
                                     time_source={"record": "bag", "header": "header", "device": "header"}.get(clock))
    elif suffix == ".db3" or (path.is_dir() and (path / "metadata.yaml").exists()):
        from .rosbag2_db3 import open_rosbag2
        footage = open_rosbag2(path, stream=stream, clock=clock or "device", require_imu=require_imu,
                               camera=intrinsics)
    elif path.is_file() and suffix in VIDEO_SUFFIXES:
        footage = _open_video_file(path, require_imu, cam_json, keep_nan, require_camera)
    elif not path.is_dir():
        raise FootageError(f"{path}: not a footage folder, a RealSense .bag/.db3 or a video "
                           f"({', '.join(VIDEO_SUFFIXES)}); give one of those")
    elif (path / "frames.csv").exists():
        footage = _open_folder(path, cam_json, keep_nan)
    elif (path / "velocity.csv").exists() and (path / "frames").is_dir():
        footage = _open_d435i_sample(path, cam_json)
    elif (path / "mav0").is_dir() or (path / "cam0" / "data.csv").exists():
        from .euroc import open_euroc
        footage = open_euroc(path, require_imu=require_imu, undistort=undistort, intrinsics=intrinsics)
    elif videos := sorted(p for p in path.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES):
        if len(videos) > 1:
            raise FootageError(f"{path}: holds {len(videos)} videos ({videos[0].name}, {videos[1].name}, ...); "
                               f"give the video file itself")
        footage = _open_video_file(videos[0], require_imu, cam_json, keep_nan, require_camera)
    else:
        raise FootageError(f"{path}: neither a footage folder (frames.csv), the D435i sample layout "
                           f"(frames/ + velocity.csv), an EuRoC folder (mav0/cam0) nor a folder with a video")
    if cam_json is not None:
        footage.notes.append(f"intrinsics from {cam_json} (--camera), not the recording's own")
    _refuse_options_for_layout(footage, stream, clock, undistort)
    footage.skip_bad_frames = skip_bad_frames
    if clock_offset not in (None, 0, 0.0, "0"):
        _apply_clock_offset(footage, clock_offset)
    return footage


def _refuse_options_for_layout(footage: Footage, stream, clock, undistort) -> None:
    """FootageError for a reader option the opened layout has no use for: it would be silently ignored."""
    realsense = "only RealSense .bag/.db3 recordings"
    unused = []
    if not footage.kind.startswith("realsense"):
        unused += [f"--stream ({realsense})"] * (stream is not None)
        unused += [f"--clock ({realsense})"] * (clock not in (None, "device"))
    if footage.kind != "euroc" and undistort != "same-k":
        unused.append("--undistort (only EuRoC/ASL folders)")
    if unused:
        raise FootageError(f"{footage.path}: {'; '.join(unused)} — this is a {footage.kind} footage; drop "
                           f"{'it' if len(unused) == 1 else 'them'}")


VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov", ".m4v", ".webm")


def _open_video_file(path: Path, require_imu: bool, cam_json: Path | None, keep_nan: bool,
                     require_camera: bool) -> Footage:
    """A video file: a GoPro MP4 with its GPMF track (stimuli.gopro), else the video reader (camera.json + imu.csv)."""
    if path.suffix.lower() in (".mp4", ".mov", ".m4v"):
        from .gopro import has_gpmf_track, open_gopro
        if has_gpmf_track(path):
            return open_gopro(path, require_imu=require_imu, camera_json=cam_json, require_camera=require_camera)
    from .video import open_video
    return open_video(path, require_imu=require_imu, camera_json=cam_json, keep_nan=keep_nan)


def _apply_clock_offset(footage: Footage, clock_offset) -> None:
    """Shift the IMU onto the frames' clock by a given or estimated constant offset (s)."""
    if footage.imu is None:
        raise FootageError(f"{footage.path}: --clock-offset needs an IMU, and this footage has none")
    if isinstance(clock_offset, str) and clock_offset.strip().lower() == "auto":
        from .clock_offset import estimate_clock_offset
        est = estimate_clock_offset(footage)
        offset, source = est.offset_s, (f"estimated: gyro vs image rotation, correlation {est.correlation:.2f} "
                                        f"over {est.n_pairs} frame pairs")
    else:
        try:
            offset = float(clock_offset)
        except (TypeError, ValueError):
            raise ValueError(f"--clock-offset {clock_offset!r}: give seconds (e.g. 0.012) or 'auto'") from None
        if not np.isfinite(offset):
            raise ValueError(f"--clock-offset {clock_offset!r}: must be finite")
        source = "given"
    footage.imu = footage.imu.shifted(offset)
    footage.clock_offset_s, footage.clock_offset_source = float(offset), source
    footage.notes.append(f"IMU clock shifted by {offset * 1e3:+.1f} ms onto the frames' clock ({source})")


def footage_provenance(footage) -> dict:
    """The attrs an output carries about its footage (works on wrappers without the method too)."""
    fn = getattr(footage, "provenance", None)
    if fn is None and hasattr(footage, "_footage"):
        fn = getattr(footage._footage, "provenance", None)
    return fn() if fn is not None else {}


def _open_folder(path: Path, cam_json: Path | None = None, keep_nan: bool = False) -> Footage:
    cam_json = cam_json or path / "camera.json"
    camera = read_camera_json(cam_json)
    fr = _read_csv(path / "frames.csv", ("frame", "time_s", "file"))
    _check_times(path / "frames.csv", fr["time_s"])
    files = [path / str(f) for f in fr["file"]]
    missing = [f for f in files if not f.exists()]
    if missing:
        raise FootageError(f"{path / 'frames.csv'}: names {len(missing)} missing frame file(s), first "
                           f"{missing[0].relative_to(path)}; restore them or drop their rows")
    imu = None
    imu_path = path / "imu.csv"
    r = imu_to_camera(cam_json)
    notes = []
    if imu_path.exists():
        imu = read_imu_csv(imu_path, r, keep_nan=keep_nan)
        if r is not None:
            notes.append(f"IMU rotated into the camera frame by {cam_json.name}'s imu_to_camera "
                         f"({rotation_deg(r):.2f} deg)")
    truth, truth_nan = read_truth_csv(path / "truth.csv", keep_nan) if (path / "truth.csv").exists() else (None, {})
    return Footage(path, camera, fr["time_s"], files, imu, truth, kind="folder", notes=notes, imu_to_camera=r,
                   truth_nan_counts=truth_nan)


def _open_d435i_sample(path: Path, cam_json: Path | None = None) -> Footage:
    camera = read_camera_json(cam_json or path / "camera.json")
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
def _no_space(folder: Path) -> bool:
    """Whether the file system holding ``folder`` has no space left for an ordinary user."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < 1 << 16


def write_footage(folder: str | Path, scene, imu: dict, times: np.ndarray, metadata: dict,
                  depth_every: int = 10, progress=None) -> Path:
    """Render ``scene`` at ``times`` into a footage folder, atomically.

    Everything is written to a hidden sibling folder that is renamed into place only
    when complete, so an interrupted run leaves no folder that looks finished.
    """
    folder = Path(folder)
    with atomic_folder(folder) as tmp:
        (tmp / "frames").mkdir()
        (tmp / "depth").mkdir()
        cam = scene.camera
        (tmp / "camera.json").write_text(json.dumps(cam.to_dict(), indent=1))
        with open(tmp / "frames.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["frame", "time_s", "file"])
            for i, t in enumerate(times):
                name = f"frames/{i:06d}.png"
                if not cv2.imwrite(str(tmp / name), scene.render(float(t), i)):  # OpenCV reports a failed write so
                    raise OSError(errno.ENOSPC if _no_space(tmp) else errno.EIO, f"cannot write {name}", str(folder))
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
    return folder
