"""Video files (mp4, mkv, avi, mov, ...) with an IMU CSV and a camera.json, as footage.

Layout: the video, and beside it ``<video stem>.camera.json`` or ``camera.json`` (the
footage folder's camera.json, optionally with "imu_to_camera"), ``<video stem>.imu.csv`` or
``imu.csv`` (time_s, accel_x..z, gyro_x..z; time_s on the video's clock: 0 = the
container's time 0) and optionally ``truth.csv`` (time_s, v_forward_m_s).

Frame times are the container's presentation time stamps, read through OpenCV
(``CAP_PROP_POS_MSEC`` after each grab), never an assumed frame rate: a variable-rate
video or one with dropped frames keeps its true times. Opening grabs every frame once
to read its time (decoding but not converting; memory flat); :meth:`VideoFootage.frames`
decodes again, one frame at a time.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from lobula.camera import PinholeCamera

from .footage_core import (check_times, Footage, FootageError, imu_to_camera, read_csv_columns, read_imu_csv,
                           rotation_deg, to_grey)


def _beside(video: Path, name: str) -> Path:
    own = video.with_name(f"{video.stem}.{name}")
    return own if own.exists() else video.with_name(name)


def _open_capture(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        cap.release()
        raise FootageError(f"{path}: OpenCV cannot open this video (unknown container or codec, or a damaged "
                           f"file); re-encode it, e.g. to H.264 mp4 or MJPG avi")
    return cap


def container_times(path: Path) -> tuple[np.ndarray, int, int, float]:
    """(frame times s (n,), width, height, nominal fps) from the container's time stamps."""
    cap = _open_capture(path)
    try:
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        times = []
        while cap.grab():
            times.append(cap.get(cv2.CAP_PROP_POS_MSEC) / 1e3)
    finally:
        cap.release()
    return np.asarray(times, float), w, h, fps


class VideoFootage(Footage):
    """Footage decoded from a video file, one frame at a time."""

    def __len__(self) -> int:
        return len(self.times)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        n = len(self)
        start, stop = max(0, int(start)), (n if stop is None else min(int(stop), n))
        if start >= stop:
            return
        cap = _open_capture(self.path)
        try:
            i = 0
            while i < stop:
                ok = cap.grab()
                if not ok:
                    break
                t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1e3
                if abs(t - self.times[i]) > 1e-4:
                    raise FootageError(f"{self.path}: frame {i} has time {t:.6f} s, {self.times[i]:.6f} s when "
                                       f"opened; the file changed, open it again")
                if i >= start:
                    ok, img = cap.retrieve()
                    try:
                        if not ok or img is None:
                            raise FootageError(f"{self.path}: frame {i} (t = {t:.3f} s) cannot be decoded; "
                                               f"re-encode the video, or pass --skip-bad-frames")
                        grey = to_grey(img)
                        self.check_size(grey, f"{self.path}: frame {i}")
                    except FootageError as exc:
                        self.bad_frame(i, exc)
                    else:
                        yield i, float(self.times[i]), grey
                i += 1
        finally:
            cap.release()
        if i < stop:
            if self.skip_bad_frames:
                for k in range(i, stop):
                    self.bad_frame(k, FootageError(""))
            else:
                raise FootageError(f"{self.path}: the video ended after frame {i - 1}, {n} frames when opened; "
                                   f"the file changed or is damaged, or pass --skip-bad-frames")

    def depth_map(self, index: int) -> np.ndarray | None:
        return None


def open_video(path: str | Path, require_imu: bool = True) -> VideoFootage:
    """Open a video with its camera.json and imu.csv (see the module doc); clear errors for anything missing."""
    path = Path(path)
    if not path.is_file():
        raise FootageError(f"{path}: video file not found")
    cam_path = _beside(path, "camera.json")
    camera = PinholeCamera.from_json(cam_path)
    times, w, h, fps = container_times(path)
    if len(times) == 0:
        raise FootageError(f"{path}: no frames could be read (empty or damaged video)")
    check_times(path, times, "container time stamp")
    if (w, h) != (camera.width, camera.height):
        raise FootageError(f"{path}: video is {w}x{h} but {cam_path.name} says {camera.width}x{camera.height}")
    r = imu_to_camera(cam_path)
    notes = [f"video: {len(times)} frames ({w}x{h}), frame times from the container's time stamps "
             f"(nominal {fps:g} frames/s in the container, {camera.frame_rate_hz:g} in {cam_path.name})"]
    imu_path = _beside(path, "imu.csv")
    imu = None
    if imu_path.exists():
        imu = read_imu_csv(imu_path, r)
        if r is not None:
            notes.append(f"IMU rotated into the camera frame by imu_to_camera ({rotation_deg(r):.2f} deg)")
    elif require_imu:
        raise FootageError(f"{imu_path}: missing; velocity needs an IMU log beside the video ({path.stem}.imu.csv "
                           f"or imu.csv: time_s, accel_x..z, gyro_x..z on the video's clock)")
    truth = None
    tp = _beside(path, "truth.csv")
    if tp.exists():
        truth = read_csv_columns(tp, ("time_s", "v_forward_m_s"))
        check_times(tp, truth["time_s"])
    streams = [dict(stream="video", codec=_fourcc(path), frames=len(times), nominal_fps=fps)]
    return VideoFootage(path, camera, times, [path] * 0, imu, truth, kind="video", notes=notes,
                        imu_to_camera=r, streams=streams)


def _fourcc(path: Path) -> str:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        code = int(cap.get(cv2.CAP_PROP_FOURCC))
    finally:
        cap.release()
    return "".join(chr((code >> 8 * k) & 0xFF) for k in range(4)).strip("\x00") or "?"
