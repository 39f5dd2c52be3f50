"""Readers of real footage: one module per layout and a registry that picks the reader for a path.

:func:`open_footage` is the one entry point. It walks :data:`READERS`, a list of :class:`Reader`
entries in priority order, and opens the path with the first whose ``recognise`` says yes:

* RealSense ROS1 ``.bag`` as the RealSense Viewer up to librealsense 2.57 records them
  (:mod:`lobula.readers.realsense_bag`) and rosbag2 ``.db3`` as 2.58 and later do
  (:mod:`lobula.readers.rosbag2_db3`);
* GoPro MP4s as the camera wrote them, with their GPMF telemetry (:mod:`lobula.readers.gopro`);
* videos whose camera logs its own motion (Sony, Insta360, DJI, RunCam, ...) or with a Gyroflow ``.gcsv``
  beside them, read by Gyroflow's telemetry-parser (:mod:`lobula.readers.camera_telemetry`);
* video files with an IMU CSV and camera.json beside them (:mod:`lobula.readers.video`);
* the footage folder and the D435i sample folder (:mod:`lobula.readers.folder`);
* the ASL/EuRoC folder layout (:mod:`lobula.readers.euroc`);
* a folder holding one video (opened as that video).

Adding a format is one module and one entry (:func:`register_reader`). Every reader returns a
:class:`~lobula.readers.core.Footage` (:mod:`lobula.readers.core`: the data classes and the checks
the readers share). This package imports nothing heavy until a reader opens a path, so the
command line's parsers stay fast; the readers import :mod:`lobula.readers.core`, never this module.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .core import Footage

#: the suffixes a video file may have (lower case)
VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov", ".m4v", ".webm")


@dataclass(frozen=True)
class Reader:
    """One footage layout that :func:`open_footage` can open.

    name: short name, shown in messages (the opened footage's ``kind`` says the same where it can).
    recognise: ``recognise(path) -> bool`` for an existing path: whether it is this layout. It must be
    cheap (look at names, read a few bytes) and import nothing heavy, since every path asks the
    readers before it in turn. open: ``open(path, **options) -> Footage``; the options are those of
    :func:`open_footage` that a reader may use (stream, clock, require_imu, undistort, camera: a
    camera.json path or None, keep_nan, require_camera); a reader takes the ones it knows and ignores
    the rest (``**_``). layout: what the reader recognises in a few words, for the message naming
    the known layouts when none recognises a path.
    """

    name: str
    recognise: Callable[[Path], bool]
    open: Callable[..., "Footage"]
    layout: str = ""

    def describe(self) -> str:
        """The reader's name and, where given, its layout, for messages."""
        return f"{self.name} ({self.layout})" if self.layout else self.name


def _intrinsics(camera):
    """The PinholeCamera of a camera.json path, or None."""
    from .core import read_camera_json
    return None if camera is None else read_camera_json(camera)


def _open_realsense_bag(path, *, stream=None, clock=None, require_imu=True, camera=None, **_):
    from .realsense_bag import open_realsense_bag
    return open_realsense_bag(path, stream=stream, require_imu=require_imu, camera=_intrinsics(camera),
                              time_source={"record": "bag", "header": "header", "device": "header"}.get(clock))


def _open_rosbag2(path, *, stream=None, clock=None, require_imu=True, camera=None, **_):
    from .rosbag2_db3 import open_rosbag2
    return open_rosbag2(path, stream=stream, clock=clock or "device", require_imu=require_imu,
                        camera=_intrinsics(camera))


def _is_gopro(path: Path) -> bool:
    if not (path.is_file() and path.suffix.lower() in (".mp4", ".mov", ".m4v")):
        return False
    from .gopro import has_gpmf_track  # reads the MP4's box index only: no decoder is started
    if not has_gpmf_track(path):
        return False
    if gpmf_parser_installed():
        return True
    # Without GoPro's own parser, telemetry-parser reads the IMU where it can (camera-telemetry); where it cannot,
    # the GoPro reader claims the file and names what to install.
    from .camera_telemetry import has_motion_log
    return not has_motion_log(path)


def gpmf_parser_installed() -> bool:
    """Whether GoPro's own parser (py-gpmf-parser, Linux x86-64 wheels only) is installed."""
    import importlib.util
    return importlib.util.find_spec("py_gpmf_parser") is not None


def _open_gopro(path, *, require_imu=True, camera=None, require_camera=True, **_):
    from .gopro import open_gopro
    return open_gopro(path, require_imu=require_imu, camera_json=camera, require_camera=require_camera)


def _is_camera_telemetry(path: Path) -> bool:
    if not (path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES):
        return False
    if path.with_name(f"{path.stem}.imu.csv").exists() or path.with_name("imu.csv").exists():
        return False  # the video layout: its own IMU log rules
    from .camera_telemetry import has_motion_log
    return has_motion_log(path)


def _open_camera_telemetry(path, *, require_imu=True, camera=None, require_camera=True, **_):
    from .camera_telemetry import open_camera_telemetry
    return open_camera_telemetry(path, require_imu=require_imu, camera_json=camera, require_camera=require_camera)


def _open_video(path, *, require_imu=True, camera=None, keep_nan=False, **_):
    from .video import open_video
    return open_video(path, require_imu=require_imu, camera_json=camera, keep_nan=keep_nan)


def _open_folder(path, *, camera=None, keep_nan=False, **_):
    from .folder import open_folder
    return open_folder(path, camera, keep_nan)


def _open_d435i_sample(path, *, camera=None, **_):
    from .folder import open_d435i_sample
    return open_d435i_sample(path, camera)


def _open_euroc(path, *, require_imu=True, undistort="same-k", camera=None, **_):
    from .euroc import open_euroc
    return open_euroc(path, require_imu=require_imu, undistort=undistort, intrinsics=_intrinsics(camera))


def _videos_in(path: Path) -> list[Path]:
    return sorted(p for p in path.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES) if path.is_dir() else []


def _open_video_folder(path, **options):
    from .core import FootageError
    videos = _videos_in(path)
    if len(videos) > 1:
        raise FootageError(f"{path}: holds {len(videos)} videos ({videos[0].name}, {videos[1].name}, ...); "
                           f"give the video file itself")
    return _reader_for(videos[0]).open(videos[0], **options)


#: the readers :func:`open_footage` asks, first to last; the first that recognises a path opens it
READERS: list[Reader] = [
    Reader("realsense-bag", lambda p: p.is_file() and p.suffix.lower() == ".bag", _open_realsense_bag,
           "a RealSense ROS1 .bag"),
    Reader("rosbag2", lambda p: p.suffix.lower() == ".db3" or (p.is_dir() and (p / "metadata.yaml").exists()),
           _open_rosbag2, "a rosbag2 .db3, or its folder with metadata.yaml"),
    Reader("gopro", _is_gopro, _open_gopro, "a GoPro MP4 with its GPMF telemetry track"),
    Reader("camera-telemetry", _is_camera_telemetry, _open_camera_telemetry,
           "a video with its camera's own motion log (Sony, Insta360, DJI, RunCam, ...) or a Gyroflow .gcsv beside it"),
    Reader("video", lambda p: p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES, _open_video,
           f"a video file, {'/'.join(VIDEO_SUFFIXES)}, with camera.json and imu.csv beside it"),
    Reader("folder", lambda p: p.is_dir() and (p / "frames.csv").exists(), _open_folder,
           "a footage folder: frames.csv, frames/, camera.json, imu.csv"),
    Reader("d435i-sample", lambda p: p.is_dir() and (p / "velocity.csv").exists() and (p / "frames").is_dir(),
           _open_d435i_sample, "the D435i sample: frames/ and velocity.csv"),
    Reader("euroc", lambda p: p.is_dir() and ((p / "mav0").is_dir() or (p / "cam0" / "data.csv").exists()),
           _open_euroc, "an ASL/EuRoC folder: mav0/ or cam0/data.csv"),
    Reader("video-folder", lambda p: bool(_videos_in(p)), _open_video_folder, "a folder holding one video"),
]


def register_reader(reader: Reader, *, before: str | None = None) -> Reader:
    """Add ``reader`` to :data:`READERS`: last, or just before the reader named ``before``.

    A reader of the same name is replaced in place (``before`` is then ignored). Returns the reader.
    """
    names = [r.name for r in READERS]
    if reader.name in names:
        READERS[names.index(reader.name)] = reader
    elif before is None:
        READERS.append(reader)
    elif before in names:
        READERS.insert(names.index(before), reader)
    else:
        raise ValueError(f"no reader named {before!r} to insert {reader.name!r} before; known: {', '.join(names)}")
    return reader


def known_layouts() -> str:
    """The layouts the registered readers recognise, in priority order, as one line."""
    return "; ".join(r.describe() for r in READERS)


def _reader_for(path: Path) -> Reader:
    """The first registered reader that recognises ``path`` (which exists); FootageError naming the path and
    the known layouts when none does."""
    from .core import FootageError
    for reader in READERS:
        if reader.recognise(path):
            return reader
    if path.is_dir() and (path / "eye.json").is_file():  # a compound eye's samples (stimuli.eye): no camera images
        raise FootageError(f"{path}: compound-eye footage (eye.json), which has no camera images for this command; "
                           f"read it with `lobula velocity --front-end emd`, `lobula eye-velocity` or `lobula info`")
    raise FootageError(f"{path}: no reader recognises it; the layouts known: {known_layouts()}")


def open_footage(path: str | Path, *, stream: str | None = None, clock: str | None = None,
                 require_imu: bool = True, skip_bad_frames: bool = False,
                 clock_offset: float | str | None = None, undistort: str = "same-k",
                 camera: str | Path | None = None, keep_nan: bool = False, require_camera: bool = True,
                 rolling_shutter: float | None = None) -> Footage:
    """Open any footage the registered readers know, checking everything cheap up front.

    path: a footage folder, the D435i sample folder, a RealSense ``.bag`` (ROS1) or ``.db3``
    (rosbag2), an ASL/EuRoC folder (``mav0/``), or a video file (mp4, mkv, avi, mov) with
    ``camera.json`` and ``imu.csv`` beside it (or a folder holding those and one video), or a
    GoPro MP4 as the camera wrote it, with its GPMF telemetry track (:mod:`lobula.readers.gopro`), or a video
    with its camera's own motion log or a Gyroflow ``.gcsv`` beside it (:mod:`lobula.readers.camera_telemetry`);
    whatever else :func:`register_reader` added. The first reader of :data:`READERS` that
    recognises it opens it; when none does, a FootageError names the path and the known layouts.
    stream: RealSense recordings: image stream ("Color_0", "Infrared_1", or part of a topic;
    default colour, else infrared). clock: RealSense recordings: "device" (the frames' own
    time stamps, default), "header" (message header stamps) or "record" (the bag's record
    times). require_imu: bags, EuRoC and video stop when there is no accelerometer (False:
    open with ``imu=None``, as ``lobula info`` does). skip_bad_frames: leave undecodable
    frames out (counted in ``skipped_frames``) instead of stopping. clock_offset: seconds
    added to the IMU's times to put them on the frames' clock, or "auto" to estimate it
    (:mod:`lobula.readers.clock_offset`). undistort: EuRoC, and any footage whose camera.json (or
    ``camera``) gives a lens "distortion" ({"model": "kannala-brandt" | "radtan", "coeffs": [...]},
    :mod:`lobula.lens`): "same-k" (undistort onto the same pinhole K) or "optimal" (EuRoC: onto
    OpenCV's optimal new K, all pixels valid; a lens: a focal length that keeps the whole width's view,
    up to 150°). camera: a
    camera.json (width, height, fx, fy, cx, cy, frame_rate_hz; optionally imu_to_camera), or a calibration
    tool's file (:mod:`lobula.readers.intrinsics`: OpenCV, ROS camera_info, Kalibr, Gyroflow), to use
    instead of the recording's own intrinsics, on every layout (``--camera FILE``): for a folder
    or a video it stands for the camera.json beside the frames (its imu_to_camera too); for
    RealSense bags and EuRoC it replaces the recorded intrinsics (EuRoC's distortion is still
    removed with them). keep_nan: open IMU and truth logs with NaN or empty values, counting
    them per column (IMU.nan_counts, ``truth_nan_counts``), and an imu.csv that cannot be an IMU's (no gravity,
    a time_s not in seconds) said in the notes, instead of stopping (``lobula info``).
    require_camera: a GoPro MP4 carries no intrinsics: without ``camera`` or a camera.json beside
    it, stop (True) or open it with ``camera=None`` (False, ``lobula info``).
    rolling_shutter: the sensor's readout, its first row's exposure to its last's (s), in place of
    the camera's own ``rolling_shutter_s`` (:mod:`lobula.rolling_shutter`; before any self-calibration, which then
    times the image's rotation at its rows' mean exposure).
    """
    path = Path(path)
    if clock not in (None, "device", "header", "record"):
        raise ValueError(f"unknown clock {clock!r}; choose device, header or record")
    if not path.exists():
        from .core import FootageError
        raise FootageError(f"{path}: not found (not a folder or a file); give one of: {known_layouts()}")
    cam_json = None if camera is None else Path(camera)
    intr = None
    if cam_json is not None:
        from .intrinsics import read_intrinsics
        intr = read_intrinsics(cam_json)  # a bad --camera is named before the footage is looked at
    import tempfile
    with tempfile.TemporaryDirectory(prefix="lobula-camera-") as tmp:
        given = cam_json
        if intr is not None and intr.format != "camera.json":
            # Another tool's calibration: the readers take it as the camera.json it amounts to.
            cam_json, intr = _converted_camera_json(intr, cam_json, path, Path(tmp))
        reader = _reader_for(path)
        footage = reader.open(path, stream=stream, clock=clock, require_imu=require_imu, undistort=undistort,
                              camera=cam_json, keep_nan=keep_nan, require_camera=require_camera)
        lensed = _remove_lens(footage, path, cam_json, undistort)
        if given is not None:
            _refuse_an_ignored_rotation(footage, cam_json, given)
    if given is not None:
        _name_the_given_file(footage, cam_json, given, intr)
    _refuse_options_for_layout(footage, stream, clock, undistort if not lensed else "same-k")
    footage.skip_bad_frames = skip_bad_frames
    if clock_offset is None and intr is not None and intr.imu_clock_offset_s and footage.imu is not None:
        footage.imu = footage.imu.shifted(intr.imu_clock_offset_s)
        footage.clock_offset_s = float(intr.imu_clock_offset_s)
        footage.clock_offset_source = f"from {given} ({intr.format})"
        footage.notes.append(f"IMU clock shifted by {intr.imu_clock_offset_s * 1e3:+.1f} ms onto the frames' clock "
                             f"(from {given})")
    elif clock_offset not in (None, 0, 0.0, "0"):
        _apply_clock_offset(footage, clock_offset)
    if rolling_shutter is not None and footage.camera is not None:
        _apply_rolling_shutter(footage, rolling_shutter)
    if getattr(footage, "lens_guess", None) is not None and footage.imu is not None:
        from .self_calibration import self_calibrate
        self_calibrate(footage, clock=clock_offset is None)
    return footage


def _apply_rolling_shutter(footage: "Footage", readout_s: float) -> None:
    """Give ``footage``'s camera (and the raw camera behind a resampled lens) a rolling shutter's readout (s, the
    ``rolling_shutter`` option), said in its notes; FootageError where it is negative or exceeds the frame
    interval."""
    from dataclasses import replace

    from .core import FootageError
    try:
        footage.camera = replace(footage.camera, rolling_shutter_s=float(readout_s))
    except ValueError as exc:
        raise FootageError(f"{footage.path}: --rolling-shutter {readout_s:g}: {exc}") from None
    if isinstance(footage.distortion, dict) and "raw_camera" in footage.distortion:
        footage.distortion["raw_camera"]["rolling_shutter_s"] = float(readout_s)
    footage.notes.append(f"rolling shutter: {1e3 * readout_s:.1f} ms readout, first row to last (--rolling-shutter); "
                         f"each row's flow is put back on the frames' times for the rotation")


def _footage_size_and_rate(path: Path) -> tuple[tuple[int, int] | None, float | None]:
    """((width, height) px, nominal frames/s) of a video file, a folder holding one, or a footage folder
    (frames.csv and its first frame); (None, None) for anything else. Reads no picture of a video."""
    import numpy as np

    videos = [path] if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES else _videos_in(path)
    if len(videos) == 1:
        import av
        try:
            with av.open(str(videos[0])) as c:
                s = c.streams.video[0]
                rate = float(s.average_rate) if s.average_rate else None
                return (s.codec_context.width, s.codec_context.height), rate
        except (av.error.FFmpegError, IndexError):
            return None, None
    if path.is_dir() and (path / "frames.csv").exists():
        import cv2

        from .core import read_csv_columns
        cols = read_csv_columns(path / "frames.csv", ("time_s", "file"))
        img = cv2.imread(str(path / str(cols["file"][0])), cv2.IMREAD_UNCHANGED)
        t = np.asarray(cols["time_s"], float)
        rate = round(1.0 / float(np.median(np.diff(t))), 3) if len(t) > 1 else None
        return (None if img is None else (img.shape[1], img.shape[0])), rate
    return None, None


def _converted_camera_json(intr, given: Path, path: Path, tmp: Path):
    """(the camera.json written in ``tmp``, the calibration it holds) of the calibration ``intr`` read from
    ``given``: scaled to the footage at ``path`` where its size is known and differs, its frame rate the
    footage's where the calibration has none."""
    import json

    from .intrinsics import camera_json_of
    size, rate = _footage_size_and_rate(path)
    if size is not None:
        intr = intr.scaled_to(size[0], size[1], given)
    out = tmp / f"{given.stem}.camera.json"
    d = camera_json_of(intr, rate or 30.0)
    if d.get("rolling_shutter_s", 0.0) > 1.0 / d["frame_rate_hz"]:
        from .core import FootageError
        raise FootageError(f"{given}: its readout, {1e3 * d['rolling_shutter_s']:.1f} ms, is longer than the "
                           f"footage's frame interval ({1e3 / d['frame_rate_hz']:.1f} ms): a profile of another "
                           f"frame rate; give this mode's")
    out.write_text(json.dumps(d))
    return out, intr


def _name_the_given_file(footage: "Footage", used: Path, given: Path, intr) -> None:
    """Notes and the lens's source name the user's ``--camera`` file, not the camera.json it was turned into."""
    what = "" if intr is None or intr.format == "camera.json" else f", read as {intr.format}" + "".join(
        f"; {n}" for n in intr.notes)
    footage.notes = [n.replace(str(used), str(given)).replace(used.name, given.name) for n in footage.notes]
    footage.notes.append(f"intrinsics from {given} (--camera{what}), not the recording's own")
    if isinstance(footage.distortion, dict) and footage.distortion.get("source") == str(used):
        footage.distortion["source"] = str(given)


#: layouts whose IMU the recording's own extrinsics put into the camera frame: a --camera file's rotation has no place
OWN_EXTRINSICS = ("realsense-bag", "realsense-db3", "euroc")


def _refuse_an_ignored_rotation(footage: "Footage", used: Path, given: Path) -> None:
    """FootageError where the ``--camera`` file (as the readers took it, ``used``) carries an IMU rotation that the
    layout does not apply (its own extrinsics rule): silently dropped it would not do what it says."""
    from .core import FootageError, imu_to_camera
    if footage.kind in OWN_EXTRINSICS and imu_to_camera(used) is not None:
        raise FootageError(f"{given}: its IMU rotation (imu_to_camera, or a camchain's T_cam_imu) is not applied to a "
                           f"{footage.kind} recording, whose own extrinsics put the IMU in the camera frame; give "
                           f"the intrinsics without it")


def _lens_file(path: Path, cam_json: Path | None) -> Path | None:
    """The camera.json that describes the footage's lens: ``--camera``'s, else the one in or beside ``path``."""
    beside = ([path / "camera.json"] if path.is_dir()
              else [path.parent / f"{path.stem}.camera.json", path.parent / "camera.json"])
    for p in (cam_json, *beside):
        if p is not None and p.is_file():
            return p
    return None


def _remove_lens(footage: Footage, path: Path, cam_json: Path | None, undistort: str) -> bool:
    """Where the camera.json gives a lens "distortion" (and the reader has not removed one itself, as EuRoC's
    does), resample every frame onto a pinhole camera (``undistort``: "same-k" or "optimal",
    :func:`lobula.lens.undistortion_maps`); returns whether it did."""
    from lobula.lens import read_lens, undistortion_maps

    from .core import FootageError
    src = _lens_file(path, cam_json)
    guess = getattr(footage, "lens_guess", None)
    if (src is None and (guess is None or guess["model"] == "pinhole")) or footage.camera is None \
            or footage.kind == "euroc":
        return False
    if src is None:
        from lobula.lens import LensDistortion
        lens, src = LensDistortion(guess["model"], tuple(guess["coeffs"])), guess["source"]
    else:
        try:
            lens = read_lens(src)
        except ValueError as exc:
            raise FootageError(str(exc)) from None
    if lens is None:
        return False
    footage.lens_maps, pinhole = undistortion_maps(footage.camera, lens, undistort)
    footage.distortion = dict(model=lens.model, coeffs=list(lens.coeffs), removed=True, target_k=undistort,
                              raw_camera=footage.camera.to_dict(), source=str(src))
    footage.notes.append(f"lens distortion ({lens.model}, {list(lens.coeffs)}) from {src} removed: every frame "
                         f"resampled onto a pinhole camera ({undistort}: fx {pinhole.fx:.2f}, fy {pinhole.fy:.2f} px)")
    footage.camera = pinhole
    return True


def _refuse_options_for_layout(footage: Footage, stream, clock, undistort) -> None:
    """FootageError for a reader option the opened layout has no use for: it would be silently ignored."""
    from .core import FootageError
    realsense = "only RealSense .bag/.db3 recordings"
    unused = []
    if not footage.kind.startswith("realsense"):
        unused += [f"--stream ({realsense})"] * (stream is not None)
        unused += [f"--clock ({realsense})"] * (clock not in (None, "device"))
    if footage.kind != "euroc" and undistort != "same-k":
        unused.append("--undistort (only EuRoC/ASL folders and a camera.json with a lens \"distortion\")")
    if unused:
        raise FootageError(f"{footage.path}: {'; '.join(unused)} — this is a {footage.kind} footage; drop "
                           f"{'it' if len(unused) == 1 else 'them'}")


def _apply_clock_offset(footage: Footage, clock_offset) -> None:
    """Shift the IMU onto the frames' clock by a given or estimated constant offset (s)."""
    import numpy as np

    from .core import FootageError
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


#: the data classes, loaded on first use (PEP 562) so that importing this package stays light
_CORE = ("Footage", "FootageError", "IMU")
__all__ = ["READERS", "Reader", "VIDEO_SUFFIXES", "known_layouts", "open_footage", "register_reader", *_CORE]


def __getattr__(name: str):
    if name in _CORE:
        return getattr(importlib.import_module(".core", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
