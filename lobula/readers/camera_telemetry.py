"""Video from cameras that log their own motion, read by Gyroflow's telemetry-parser.

Many cameras write their gyroscope and accelerometer into the video file (Sony, Insta360, DJI action
cameras, RunCam and other FPV cameras, Blackmagic, RED), and any logger or phone app can write
Gyroflow's ``.gcsv`` beside the video (``clip.mp4`` with ``clip.gcsv``). Gyroflow's own parser,
`telemetry-parser <https://github.com/AdrianEddy/telemetry-parser>`_, reads them all and turns each
model's axes into one frame, Gyroflow's: x up, y left, z backwards from the lens (for ``.gcsv`` its
``orientation`` line says how the logged axes map onto that frame). This reader rotates that frame into
the camera's (x right, y down, z forward; :data:`GYROFLOW_TO_CAMERA`), converts deg/s to rad/s, and
takes the samples' times as the parser gives them, as on the video's clock: the parser starts a
``.gcsv`` at 0, the video's start, whatever clock its logger kept (``--clock-offset auto`` estimates a
constant offset; a camera opened without intrinsics has its offset estimated anyway).

Intrinsics come from ``--camera FILE`` (a camera.json or a calibration tool's file,
:mod:`lobula.readers.intrinsics`) or a camera.json beside the video. Without one, an action camera (a wide
fisheye) is opened as GoPro MP4s are, as an equidistant lens of a nominal field of view, and any other camera
as a pinhole of a phone's field of view; the gyro then measures the focal length where the footage turns
enough (:mod:`lobula.readers.self_calibration`), and the output says which. A 360° camera's 2:1 picture is
refused without intrinsics. GoPro MP4s are read by :mod:`lobula.readers.gopro`; by this reader where GoPro's
own parser is not installed (it has Linux x86-64 wheels only): the IMU, the GPS truth (:func:`gopro_gps`) and the
camera and image orientations (:func:`gopro_orientations`, turning a stabilised clip's IMU into its image's frame),
both timed by the MP4's telemetry track (:func:`packet_times`), the settings and the stated field of view
(:func:`gopro_telemetry`), as the GoPro reader has them. A video with
an ``imu.csv`` beside it stays the ``video`` layout.
"""
from __future__ import annotations

import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .core import FootageError, IMU, imu_to_camera, read_camera_json, rotation_deg
from .video import VideoFootage, camera_file, check_presentation_times, container_times

#: Gyroflow's IMU frame (x up, y left, z backwards from the lens) into the camera's (x right, y down, z forward)
GYROFLOW_TO_CAMERA = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

#: makers of action and FPV cameras, whose lenses are wide fisheyes (matched at the start of the parser's
#: camera or model name, any case): opened without intrinsics as an equidistant lens the gyro calibrates
ACTION_CAMERAS = ("gopro", "insta360", "dji", "runcam", "caddx", "foxeer", "hawkeye", "akaso", "sjcam", "xtu",
                  "iflight", "walksnail")

#: degree: the diagonal field of view assumed for a camera that is not an action camera and comes without
#: intrinsics (a phone's main camera sees 70-85°), and the 1σ fraction of the focal length it implies, before the
#: gyro measures it
NOMINAL_PINHOLE_DIAGONAL_FOV_DEG = 75.0
NOMINAL_PINHOLE_FOV_REL_STD = 0.25

INSTALL_HINT = ("reading a camera's motion log needs telemetry-parser (Gyroflow's parser; wheels for Linux, macOS "
                "and Windows, CPython 3.8-3.12): pip install telemetry-parser")


class ParseFailure(Exception):
    """telemetry-parser failed on a file: raised an error, or its Rust code panicked."""


@contextmanager
def _parsing():
    """Run the parser with standard error silenced at the file descriptor (a panic of its Rust code prints its
    message and backtrace there before Python sees it, and a bad file must read as one line), any failure of it
    raised as :class:`ParseFailure` (pyo3's PanicException derives from BaseException, not Exception)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            try:
                yield
            except (KeyboardInterrupt, SystemExit, GeneratorExit):
                raise
            except BaseException as exc:  # noqa: B036: a Rust panic is no Exception
                raise ParseFailure(str(exc)) from None
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _parser(path: Path):
    """telemetry-parser's Parser on the ``.gcsv`` beside the video at ``path`` where there is one (the log the
    user put there), else on the video itself; None where it finds no motion log; FootageError where the
    package is missing or the ``.gcsv`` cannot be parsed."""
    try:
        import telemetry_parser
    except ImportError:
        raise FootageError(f"{path}: {INSTALL_HINT}") from None
    sidecar = path.with_suffix(".gcsv")
    try:
        with _parsing():
            return telemetry_parser.Parser(str(sidecar if sidecar.is_file() else path))
    except ParseFailure as exc:
        if sidecar.is_file():
            raise FootageError(f"{sidecar}: not a motion log telemetry-parser can read ({exc}); a .gcsv starts "
                               f"with 'GYROFLOW IMU LOG' or 'CAMERA IMU LOG', then version, id, orientation, "
                               f"tscale, gscale, ascale lines and a t,gx,gy,gz,ax,ay,az header") from None
        return None


def has_motion_log(path: Path) -> bool:
    """Whether ``path`` is a video whose motion log telemetry-parser reads (embedded, or a ``.gcsv`` beside it).
    False without telemetry-parser installed, so that other readers are asked."""
    try:
        import telemetry_parser  # noqa: F401
    except ImportError:
        return path.with_suffix(".gcsv").is_file()  # a sidecar is claimed, so the open names what to install
    if path.with_suffix(".gcsv").is_file():
        return True  # the user's log: a bad one is named when opened
    p = _parser(path)
    try:
        with _parsing():
            return p is not None and len(p.normalized_imu()) > 0
    except ParseFailure:
        return False


def read_motion_log(path: Path) -> dict:
    """The motion log of the video at ``path`` in the camera frame.

    Returns
    -------
    dict
        time_s (n,) s ascending; accel (n, 3) m/s² or None (no accelerometer); gyro (n, 3) rad/s or None;
        camera (the parser's camera type, e.g. "Sony", "Insta360", "gcsv") and model (str or None).
    """
    p = _parser(path)
    src = path.with_suffix(".gcsv") if path.with_suffix(".gcsv").is_file() else path  # what errors name
    if p is None:
        raise FootageError(f"{path}: telemetry-parser finds no motion log in it (no embedded gyro, no "
                           f"{path.with_suffix('.gcsv').name} beside it); give an imu.csv and camera.json beside "
                           f"the video instead")
    try:
        with _parsing():
            samples = p.normalized_imu()
    except ParseFailure as exc:
        raise FootageError(f"{src}: its motion log cannot be read ({exc}); copy the file again from the camera, "
                           f"or write the .gcsv again") from None
    if not samples:
        raise FootageError(f"{src}: the motion log holds no samples; a .gcsv needs its t,gx,gy,gz[,ax,ay,az] "
                           f"header and rows of numbers, a camera's file its motion track (copy it again)")
    t = np.array([s["timestamp_ms"] for s in samples], float) / 1e3

    def vectors(key, scale):
        if all(s.get(key) is None for s in samples):
            return None
        return np.array([s[key] if s.get(key) is not None else (np.nan,) * 3 for s in samples], float) * scale

    accel, gyro = vectors("accl", 1.0), vectors("gyro", np.pi / 180.0)
    order = np.argsort(t, kind="stable")
    keep = np.concatenate([[True], np.diff(t[order]) > 0])  # one sample per time stamp
    order = order[keep]
    rows = [x for x in (accel, gyro) if x is not None]
    good = np.isfinite(t[order]) & np.all([np.isfinite(x[order]).all(1) for x in rows], axis=0)
    order = order[good]
    if len(order) < 2:
        raise FootageError(f"{src}: the motion log has fewer than 2 samples with finite values and distinct times")
    rotate = lambda x: None if x is None else x[order] @ GYROFLOW_TO_CAMERA.T
    return dict(time_s=t[order], accel=rotate(accel), gyro=rotate(gyro), camera=str(p.camera or "unknown"),
                model=str(p.model) if p.model else None, dropped=int(len(t) - len(order)))


#: telemetry-parser's keys of a GoPro GPS group's packet fix (GPSF: 0 none, 2 2D, 3 3D) and precision (GPSP, DOP×100)
_GPSF, _GPSP = "0x47505346", "0x47505350"


def gopro_telemetry(path: Path, notes: list[str]) -> tuple[dict, list[dict]]:
    """(settings {FourCC: value}, one dict of streams per telemetry packet) of the GoPro MP4 at ``path`` as
    telemetry-parser reads them; empty, with a note, where it cannot."""
    p = _parser(path)
    try:
        with _parsing():
            groups = p.telemetry() if p is not None else []
    except ParseFailure as exc:
        notes.append(f"telemetry-parser cannot read the telemetry's packets ({exc}): no GPS, field of view or "
                     f"stabilisation settings")
        return {}, []
    settings = {}
    while groups and set(groups[0]) <= {"Default"}:   # the settings block before the track's packets
        settings.update({bytes.fromhex(k[2:]).decode("latin-1"): v for k, v in groups[0]["Default"].items()
                         if k.startswith("0x") and len(k) == 10})
        groups = groups[1:]
    return settings, groups


#: telemetry-parser's names of GoPro's per-frame camera and image orientations
_ORIENTATION_GROUPS = {"CORI": "CameraOrientation", "IORI": "ImageOrientation"}


def packet_times(path: Path, groups: list[dict], notes: list[str]) -> list[tuple[float, float]] | None:
    """Each of telemetry-parser's packets ``groups`` (:func:`gopro_telemetry`) of the GoPro MP4 at ``path`` timed by
    the MP4's telemetry track: their spans [t_in, t_out) s on the video's clock (demuxed once, not decoded); None
    where no packet holds GPS or orientations, or where the track cannot be read or its packets do not line up
    with telemetry-parser's, with a note saying which."""
    from .gopro_telemetry import packet_spans

    if not any("GPS" in g or name in g for g in groups for name in _ORIENTATION_GROUPS.values()):
        return None
    what = "GPS and camera and image orientations not read"
    try:
        spans = packet_spans(path)
    except FootageError as exc:
        notes.append(f"{what}: {exc}")
        return None
    if len(groups) != len(spans):
        notes.append(f"{what}: telemetry-parser gives {len(groups)} telemetry packets where the MP4's track has "
                     f"{len(spans)}, so their times are not known")
        return None
    return spans


def gopro_orientations(groups: list[dict], spans: list[tuple[float, float]] | None) -> dict:
    """The camera's and the image's orientations (CORI, IORI) in telemetry-parser's packets ``groups``
    (:func:`gopro_telemetry`), timed by their ``spans`` (:func:`packet_times`), as
    :class:`lobula.readers.gopro.GoProFootage`'s ``orientation`` holds them: {key: (time_s (n,) s on the video's
    clock, each packet's samples spread over its span, quaternions (n, 4) w, x, y, z)}; {} without spans or
    orientations."""
    from .gopro_telemetry import packet_sample_times

    out = {}
    for key, name in _ORIENTATION_GROUPS.items():
        times, quats = [], []
        for (t_in, t_out), g in zip(spans or [], groups):
            group = g.get(name) or {}
            q = np.array([[d["w"], d["x"], d["y"], d["z"]] for d in group.get("Data") or []], float)
            if len(q):
                times.append(packet_sample_times(t_in, t_out, len(q)))
                quats.append(q / float(group.get("Scale") or 32767))
        if quats:
            out[key] = (np.concatenate(times), np.concatenate(quats))
    return out


def gopro_gps(groups: list[dict], spans: list[tuple[float, float]] | None) -> dict | None:
    """The GPS samples in telemetry-parser's packets ``groups`` (:func:`gopro_telemetry`), timed by their ``spans``
    (:func:`packet_times`), as :func:`lobula.readers.gopro.gps_samples` gives them (time_s on the video's clock,
    each packet's samples spread over its span; lat_deg, lon_deg, alt_m, speed_2d_m_s, speed_3d_m_s, fix, dop);
    None without spans or GPS."""
    from .gopro_telemetry import packet_sample_times

    if spans is None:
        return None
    cols, gps9 = {k: [] for k in ("time_s", "data", "fix", "dop")}, False
    for (t_in, t_out), g in zip(spans, groups):
        gps = g.get("GPS") or {}
        data = np.asarray(gps.get("Data") or [], float)
        if data.ndim != 2 or data.shape[1] < 5:
            continue
        scale = np.atleast_1d(np.asarray(gps.get("Scale") or 1.0, float))
        data = data / (scale[: data.shape[1]] if len(scale) > 1 else scale[0])
        cols["time_s"].append(packet_sample_times(t_in, t_out, len(data)))
        cols["data"].append(data[:, :5])
        if data.shape[1] >= 9:    # GPS9: a fix and DOP per sample
            cols["fix"].append(data[:, 8])
            cols["dop"].append(data[:, 7])
            gps9 = True
        else:
            cols["fix"].append(np.full(len(data), float(gps.get(_GPSF, np.nan))))
            cols["dop"].append(np.full(len(data), float(gps.get(_GPSP, np.nan)) / 100.0))
    if not cols["data"]:
        return None
    d = np.concatenate(cols["data"])
    return dict(time_s=np.concatenate(cols["time_s"]), lat_deg=d[:, 0], lon_deg=d[:, 1], alt_m=d[:, 2],
                speed_2d_m_s=d[:, 3], speed_3d_m_s=d[:, 4], fix=np.concatenate(cols["fix"]),
                dop=np.concatenate(cols["dop"]), source=("GPS9" if gps9 else "GPS5") + ", telemetry-parser")


def is_action_camera(camera: str, model: str | None) -> bool:
    """Whether the parser's camera type or model names a maker of wide-fisheye action or FPV cameras."""
    names = [camera.lower(), (model or "").lower()]
    return any(n.startswith(m) for n in names for m in ACTION_CAMERAS)


def pinhole_camera(width: int, height: int, fps: float, diagonal_fov_deg: float):
    """A pinhole camera whose diagonal sees ``diagonal_fov_deg`` (deg): f = half the diagonal (px) / tan(half the
    angle); principal point at the centre."""
    import math

    from lobula.camera import PinholeCamera

    f = 0.5 * math.hypot(width, height) / math.tan(math.radians(0.5 * diagonal_fov_deg))
    return PinholeCamera(width, height, f, f, (width - 1) / 2, (height - 1) / 2, fps)


class CameraTelemetryFootage(VideoFootage):
    """A video with the camera's own motion log (module doc). ``lens_guess``: where no camera file was
    given, the lens assumed (an equidistant fisheye as :class:`lobula.readers.gopro.GoProFootage`'s, or model
    "pinhole"), else None;
    ``motion_log``: {camera, model, samples, rate_hz, source}."""

    lens_guess: dict | None
    motion_log: dict
    orientation: dict

    def provenance(self) -> dict:
        out = super().provenance()
        out["motion_log"] = json.dumps(self.motion_log)
        if getattr(self, "calibration", None):
            out["camera_calibration"] = json.dumps(self.calibration)
        return out


def open_camera_telemetry(path: str | Path, require_imu: bool = True, camera_json=None,
                          require_camera: bool = True) -> CameraTelemetryFootage:
    """Open a video with its camera's motion log (module doc).

    path: the video. camera_json: intrinsics (``--camera``); else ``CLIP.camera.json`` or ``camera.json`` beside
    it, whose optional imu_to_camera is applied after the parser's axis mapping, as a correction in the camera
    frame. require_imu: FootageError when the log has no accelerometer (False: opened with ``imu=None``).
    require_camera: FootageError for a 360° picture without intrinsics (False: ``camera=None``, for
    ``lobula info``). Every bad input is one FootageError naming the file and the fix.
    """
    from .gopro import (NOMINAL_DIAGONAL_FOV_DEG, NOMINAL_FOV_REL_STD, equidistant_camera, gps_truth, image_frame,
                        lens_guess_from_settings, stabilisation, stabilisation_notes)

    path = Path(path)
    if not path.is_file():
        raise FootageError(f"{path}: not found; give the video file itself")
    log = read_motion_log(path)
    times, w, h, fps, codec = container_times(path)
    if len(times) == 0:
        raise FootageError(f"{path}: no video frames could be read (empty or damaged file)")
    check_presentation_times(path, times)
    who = " ".join(x for x in (log["camera"], log["model"]) if x)
    sidecar = path.with_suffix(".gcsv")
    source = f"{sidecar} (.gcsv)" if log["camera"] == "gcsv" else f"{path} ({who} motion log)"
    cam_path = camera_file(path, camera_json)
    gopro, settings, packets, gopro_notes = (log["camera"] or "").lower() == "gopro", {}, [], []
    orientation, spans = {}, None
    if gopro:
        settings, packets = gopro_telemetry(path, gopro_notes)
        spans = packet_times(path, packets, gopro_notes)
        orientation = gopro_orientations(packets, spans)
    camera, lens_guess = None, None
    spherical = abs(w - 2 * h) <= 0.02 * w  # a 2:1 frame: a 360° camera's equirectangular or dual-fisheye picture
    if cam_path is not None:
        camera = read_camera_json(cam_path)
        if (w, h) != (camera.width, camera.height):
            raise FootageError(f"{path}: video is {w}x{h} but {cam_path} says {camera.width}x{camera.height}; give "
                               f"the intrinsics of this resolution")
    elif gopro and not spherical:
        camera, lens_guess = lens_guess_from_settings(w, h, fps, settings)
    elif is_action_camera(log["camera"], log["model"]) and not spherical:
        camera = equidistant_camera(w, h, fps, NOMINAL_DIAGONAL_FOV_DEG)
        lens_guess = dict(model="kannala-brandt", coeffs=[0.0, 0.0, 0.0, 0.0],
                          diagonal_fov_deg=NOMINAL_DIAGONAL_FOV_DEG,
                          source=f"a nominal {NOMINAL_DIAGONAL_FOV_DEG:g}° diagonal for a {who} action camera",
                          rel_std=NOMINAL_FOV_REL_STD)
    elif not spherical:
        # A phone's or a camera's own lens: a pinhole of a phone's main camera's field of view, the focal length
        # measured against the gyro where the footage turns enough (lobula.readers.self_calibration).
        camera = pinhole_camera(w, h, fps, NOMINAL_PINHOLE_DIAGONAL_FOV_DEG)
        lens_guess = dict(model="pinhole", coeffs=[], diagonal_fov_deg=NOMINAL_PINHOLE_DIAGONAL_FOV_DEG,
                          source=f"a nominal {NOMINAL_PINHOLE_DIAGONAL_FOV_DEG:g}° diagonal pinhole for a {who} camera",
                          rel_std=NOMINAL_PINHOLE_FOV_REL_STD)
    elif require_camera:
        raise FootageError(f"{path}: a {w}x{h} frame is a 360° picture (equirectangular, or two fisheyes side by "
                           f"side), not one lens's view; reframe it to one view and give that view's intrinsics "
                           f"with --camera FILE")
    notes = [f"video: {len(times)} frames ({w}x{h}, {codec}), frame times from the container's time stamps"]
    stab = stabilisation(settings, orientation["IORI"][1] if "IORI" in orientation else None)
    if gopro:
        notes.append("a GoPro MP4 read by telemetry-parser (GoPro's own parser is not installed here: py-gpmf-parser, "
                     "Linux x86-64 wheels): its IMU, GPS, camera and image orientations, settings and stated field "
                     "of view")
        notes.extend(gopro_notes)
    imu, r = None, None
    if log["accel"] is None:
        if require_imu:
            raise FootageError(f"{source}: the motion log has a gyroscope but no accelerometer; velocity needs one: "
                               f"log the accelerometer too, or pass --accel-from-truth with a truth.csv")
    else:
        imu = IMU(log["time_s"], log["accel"], log["gyro"], source=source)
        rate = (len(log["time_s"]) - 1) / max(float(log["time_s"][-1] - log["time_s"][0]), 1e-9)
        notes.append(f"IMU: {len(log['time_s'])} samples ({rate:.0f} Hz) from {source}, read by telemetry-parser and "
                     f"rotated from Gyroflow's axes (x up, y left, z back) into the camera frame (x right, y down, "
                     f"z forward); its times taken as on the video's clock"
                     + (" (a .gcsv's first sample at the video's start)" if log["camera"] == "gcsv" else "")
                     + (f"; {log['dropped']} samples without finite values or with a repeated time left out"
                        if log["dropped"] else ""))
        if cam_path is not None:
            r = imu_to_camera(cam_path)
            if r is not None:
                imu = imu.rotated(r)
                notes.append(f"IMU then rotated by {cam_path.name}'s imu_to_camera ({rotation_deg(r):.2f} deg)")
    if gopro and imu is not None and stab["electronic"]:
        imu = image_frame(imu, orientation, stab, notes)
    if gopro:
        notes.extend(stabilisation_notes(stab))
    truth = None
    tp = path.with_name("truth.csv")
    if tp.is_file():
        from .core import read_truth_csv
        truth, _ = read_truth_csv(tp, False)
    elif gopro:
        truth = gps_truth(gopro_gps(packets, spans), notes)
    streams = [dict(stream="video", codec=codec, frames=len(times), nominal_fps=round(fps, 3)),
               dict(stream="motion log", source=who, samples=len(log["time_s"]),
                    sensors=", ".join(n for n, x in (("accelerometer", log["accel"]), ("gyroscope", log["gyro"]))
                                      if x is not None))]
    footage = CameraTelemetryFootage(path, camera, times, [], imu, truth, kind="camera-telemetry", notes=notes,
                                     imu_to_camera=(GYROFLOW_TO_CAMERA if r is None else r @ GYROFLOW_TO_CAMERA)
                                     if imu is not None else None, camera_file_imu_rotation=r, streams=streams)
    footage.lens_guess, footage.orientation = lens_guess, orientation
    footage.motion_log = dict(camera=log["camera"], model=log["model"], samples=int(len(log["time_s"])),
                              source=source)
    return footage
