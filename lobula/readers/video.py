"""Video files (mp4, mkv, avi, mov, ...) with an IMU CSV and a camera.json, as footage.

Layout: the video, and beside it ``<video stem>.camera.json`` or ``camera.json`` (the
footage folder's camera.json, optionally with "imu_to_camera"), ``<video stem>.imu.csv`` or
``imu.csv`` (time_s, accel_x..z, gyro_x..z; time_s on the video's clock: the container's
presentation time, pts × time base) and optionally ``truth.csv`` (time_s, v_forward_m_s).

Frame times are the container's presentation time stamps, read through PyAV (FFmpeg),
never an assumed frame rate: a variable-rate video or one with dropped frames keeps its
true times. Opening only demultiplexes — it reads each packet's time stamp without decoding
a picture, so opening an hour of 4K video costs seconds and no memory beyond the time
stamps; :meth:`VideoFootage.frames` decodes one packet at a time.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import av
import numpy as np

from .core import (Footage, FootageError, check_imu_csv, imu_to_camera, read_camera_json, read_imu_csv,
                   rotation_deg, to_grey)


def _beside(video: Path, name: str) -> Path:
    own = video.with_name(f"{video.stem}.{name}")
    return own if own.exists() else video.with_name(name)


def camera_file(video: Path, camera_json: str | Path | None) -> Path | None:
    """The camera.json of the video at ``video``: ``camera_json`` (``--camera``) where given, else
    ``<stem>.camera.json`` or ``camera.json`` beside it; None where there is none."""
    if camera_json is not None:
        return Path(camera_json)
    for p in (video.with_name(f"{video.stem}.camera.json"), video.with_name("camera.json")):
        if p.is_file():
            return p
    return None


def _open_container(path: Path):
    """(container, its first video stream); FootageError naming the file when FFmpeg cannot read it."""
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, UnicodeDecodeError) as exc:
        raise FootageError(f"{path}: FFmpeg cannot open it as a video ({exc.__class__.__name__}: not a video, an "
                           f"unknown container or codec, or a damaged file); re-encode it, e.g. to H.264 mp4 or MJPG "
                           f"avi") from None
    if not container.streams.video:
        container.close()
        raise FootageError(f"{path}: the file holds no video stream")
    return container, container.streams.video[0]


def _packet_time(packet, path: Path) -> float | None:
    """Presentation time (s) of a demultiplexed packet; None for the flush packet at the end."""
    if packet.size == 0:
        return None
    stamp = packet.pts if packet.pts is not None else packet.dts
    if stamp is None or packet.time_base is None:
        raise FootageError(f"{path}: a packet of the video has no time stamp; remux it (ffmpeg -i IN -c copy OUT.mkv)")
    return float(stamp * packet.time_base)


def check_video_file(path: Path) -> None:
    """A FootageError where the file at ``path`` is empty, holds text, or otherwise cannot be opened by FFmpeg as a
    video; it reads the container's header only."""
    if path.stat().st_size == 0:
        raise FootageError(f"{path}: the file is empty (0 bytes), not a video; copy it again from the camera or "
                           f"the recorder")
    try:
        container, _ = _open_container(path)
    except FootageError:
        text = _text_start(path)
        if text is None:
            raise
        raise FootageError(f"{path}: holds text ({text!r}), not a video; give the video file itself") from None
    container.close()


def _text_start(path: Path, n: int = 512) -> str | None:
    """The first line (up to 40 characters) of the file at ``path`` where its first ``n`` bytes are printable text,
    else None."""
    with path.open("rb") as fh:
        head = fh.read(n)
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return None
    if not all(c.isprintable() or c in "\t\r\n" for c in text):
        return None
    return text.strip().splitlines()[0][:40] if text.strip() else ""


def container_times(path: Path) -> tuple[np.ndarray, int, int, float, str]:
    """(frame times s (n,) ascending, width px, height px, nominal frames/s, codec) from the time stamps of
    the packets of the video at ``path``.

    Packets arrive in decoding order (B-frames come before the pictures they refer to), so
    the presentation times are sorted.
    """
    container, stream = _open_container(path)
    try:
        w, h = stream.codec_context.width, stream.codec_context.height
        fps = float(stream.average_rate or stream.guessed_rate or 0.0)
        times = []
        try:
            for packet in container.demux(stream):
                t = _packet_time(packet, path)
                if t is not None:
                    times.append(t)
        except av.error.FFmpegError as exc:
            raise FootageError(f"{path}: the container is damaged after {len(times)} packets ({exc}); "
                               f"re-encode or remux it") from None
        return np.sort(np.asarray(times, float)), w, h, fps, stream.codec_context.name
    finally:
        container.close()


class VideoFootage(Footage):
    """Footage decoded from a video file, one packet at a time."""

    def __len__(self) -> int:
        return len(self.times)

    def raw_frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """Yield (index, time_s s, grey float32 (H, W)) for frames start..stop-1, decoding one packet at a time."""
        n = len(self)
        start, stop = max(0, int(start)), (n if stop is None else min(int(stop), n))
        if start >= stop:
            return
        container, stream = _open_container(self.path)
        done = np.zeros(n, bool)  # yielded, or reported bad
        try:
            for packet in container.demux(stream):  # the last, empty packet flushes the decoder's delayed pictures
                t = _packet_time(packet, self.path)
                i = None if t is None else self._index(t)
                try:
                    pictures = packet.decode()
                except av.error.FFmpegError as exc:
                    if i is not None and start <= i < stop:
                        done[i] = True
                        self.bad_frame(i, FootageError(f"{self.path}: frame {i} (t = {t:.3f} s) cannot be decoded "
                                                       f"({exc}); re-encode the video, or pass --skip-bad-frames"))
                    continue
                for picture in pictures:  # in presentation order, possibly some packets later
                    k = i if picture.time is None else self._index(float(picture.time))
                    if k is None or not start <= k < stop or done[k]:
                        continue
                    done[k] = True
                    grey = to_grey(picture.to_ndarray(format="bgr24"))  # the same grey as every reader
                    try:
                        self.check_size(grey, f"{self.path}: frame {k}")
                    except FootageError as exc:
                        self.bad_frame(k, exc)
                    else:
                        yield k, float(self.times[k]), grey
                if done[start:stop].all():
                    break
        finally:
            container.close()
        missing = np.flatnonzero(~done[start:stop]) + start
        if len(missing):
            if not self.skip_bad_frames:
                raise FootageError(f"{self.path}: the video ended before frame {missing[0]}, {n} frames when "
                                   f"opened; the file changed or is damaged, or pass --skip-bad-frames")
            for k in missing:
                self.bad_frame(int(k), FootageError(""))

    def _index(self, t: float) -> int:
        """The frame whose time stamp is t (s); FootageError if none is (the file changed since opening)."""
        i = int(np.searchsorted(self.times, t - 1e-7))
        if i >= len(self.times) or abs(self.times[i] - t) > 1e-6:
            raise FootageError(f"{self.path}: a picture has time {t:.6f} s, unknown when the video was opened; "
                               f"the file changed, open it again")
        return i

    def depth_map(self, index: int) -> np.ndarray | None:
        """None: a video has no depth maps."""
        return None


def check_presentation_times(path: Path, times: np.ndarray) -> None:
    """FootageError naming the video, the frames and the fix where two frames share a presentation
    time stamp (``times`` (n,) sorted, s): each frame's time then is not known."""
    if not np.all(np.isfinite(times)):
        raise FootageError(f"{path}: some packets have no usable presentation time stamp; remux the video with "
                           f"fresh time stamps (ffmpeg -i IN -c copy OUT.mkv)")
    same = np.flatnonzero(np.diff(times) <= 0)
    if same.size:
        k = int(same[0])
        raise FootageError(
            f"{path}: the video's time stamps are broken: {same.size} frame(s) repeat the presentation time of the "
            f"frame before (first: frames {k} and {k + 1}, both at {times[k]:.6f} s), so when each frame was taken "
            f"is not known (the container was written without proper time stamps); "
            f"re-encode it with one time stamp per frame at its true rate, e.g. ffmpeg -i IN -vf "
            f"setpts=N/(FPS*TB) -r FPS OUT.mp4, and check that the IMU log's time_s is on the same clock")


def open_video(path: str | Path, require_imu: bool = True, camera_json: str | Path | None = None,
               keep_nan: bool = False) -> VideoFootage:
    """Open a video with its camera.json and imu.csv (see the module doc); clear errors for anything missing.

    path: the video file; require_imu: stop when there is no imu.csv beside it (False: ``imu=None``);
    camera_json: a camera.json to use instead of the one beside the video (``--camera``);
    keep_nan: open what ``lobula info`` reports rather than stops at: NaN IMU and truth values (counted), and
    an IMU that cannot be one (said in the notes)."""
    from .core import read_truth_csv

    path = Path(path)
    if not path.is_file():
        raise FootageError(f"{path}: video file not found")
    check_video_file(path)  # before its camera.json: an empty file or a text file is no video, with one or without
    cam_path = Path(camera_json) if camera_json is not None else _beside(path, "camera.json")
    camera = read_camera_json(cam_path)
    times, w, h, fps, codec = container_times(path)
    if len(times) == 0:
        raise FootageError(f"{path}: no frames could be read (empty or damaged video)")
    check_presentation_times(path, times)
    if (w, h) != (camera.width, camera.height):
        raise FootageError(f"{path}: video is {w}x{h} but {cam_path.name} says {camera.width}x{camera.height}")
    r = imu_to_camera(cam_path)
    notes = [f"video: {len(times)} frames ({w}x{h}), frame times from the container's time stamps "
             f"(nominal {fps:g} frames/s in the container, {camera.frame_rate_hz:g} in {cam_path.name})"]
    imu_path = _beside(path, "imu.csv")
    imu = None
    if imu_path.exists():
        imu = read_imu_csv(imu_path, r, keep_nan=keep_nan)
        check_imu_csv(imu, times, notes, keep_nan)
        if r is not None:
            notes.append(f"IMU rotated into the camera frame by imu_to_camera ({rotation_deg(r):.2f} deg)")
    elif require_imu:
        raise FootageError(f"{imu_path}: missing; velocity needs an IMU log beside the video ({path.stem}.gcsv, or {path.stem}.imu.csv "
                           f"or imu.csv: time_s, accel_x..z, gyro_x..z on the video's clock)")
    truth, truth_nan = None, {}
    tp = _beside(path, "truth.csv")
    if tp.exists():
        truth, truth_nan = read_truth_csv(tp, keep_nan)
    streams = [dict(stream="video", codec=codec, frames=len(times), nominal_fps=fps)]
    return VideoFootage(path, camera, times, [path] * 0, imu, truth, kind="video", notes=notes,
                        imu_to_camera=r, camera_file_imu_rotation=r, streams=streams, truth_nan_counts=truth_nan)

