"""RealSense ROS1 bags, as the RealSense Viewer (librealsense's recorder) writes them, as footage.

``open_realsense_bag(path)`` returns a :class:`BagFootage`, a :class:`~lobula.readers.core.Footage`
whose :meth:`~BagFootage.frames` streams grey images out of the bag one message at a
time (memory does not grow with the recording's length) and whose ``imu`` holds the
accelerometer and gyroscope on one time base in the camera optical frame.

What a Viewer bag holds (librealsense ``src/media/ros``, file format version 3)::

    /device_0/sensor_1/Color_0/image/data          sensor_msgs/Image (rgb8, bgr8, YUYV, ...)
    /device_0/sensor_1/Color_0/info/camera_info    sensor_msgs/CameraInfo (K: fx, cx, fy, cy)
    /device_0/sensor_1/Color_0/info                realsense_msgs/StreamInfo (fps, encoding)
    /device_0/sensor_1/Color_0/image/metadata      diagnostic_msgs/KeyValue (timestamp_domain, ...)
    /device_0/sensor_1/Color_0/tf/0                geometry_msgs/Transform (extrinsics)
    /device_0/sensor_2/Accel_0/imu/data            sensor_msgs/Imu (linear_acceleration only)
    /device_0/sensor_2/Gyro_0/imu/data             sensor_msgs/Imu (angular_velocity only)
    /device_0/sensor_0/Depth_0/image/data          sensor_msgs/Image (mono16 depth: never used as frames)

Topics are found by pattern and message type, not by sensor number; bags from the
``realsense-ros`` node (``/camera/color/image_raw``, ``/camera/accel/sample``, ...,
or one united ``/camera/imu``) are read by the same rules.

Choices, each also written into ``footage.notes``:

* **Times** are the messages' header stamps (the frame timestamps librealsense gives,
  the same clock for images and IMU when global time is on, as it is by default), in
  seconds relative to the first image's stamp; ``BagFootage.time_origin_s`` keeps the
  absolute origin. If the stamps are all zero (some converters) the bag's record times
  are used instead. Stamps must increase; IMU messages repeated verbatim (same stamp,
  same values) are dropped, anything else out of order is an error.
* **Grey** is ITU-R 601 luma as OpenCV computes it from rgb8/bgr8/rgba8/bgra8 (the same
  as reading a PNG of the frame with :func:`lobula.readers.core.read_frame`), the Y channel
  of YUYV/UYVY, mono8/8UC1 as is, mono16/16UC1 divided by 257.
* **IMU**: the accelerometer's times are the time base; the gyroscope (its own rate,
  200/400 Hz on the D435i) is linearly interpolated onto them, and accelerometer samples
  outside the gyroscope's span are dropped. librealsense already reports the D435i's
  motion data in the depth camera's optical convention (x right, y down, z forward);
  when the bag carries the extrinsics (``.../tf/<group>``: the transform from the
  group's reference stream to the stream, p_stream = R·p_ref + t) the small remaining
  rotation into the colour frame, R_colour·R_imuᵀ, is applied; the lever arm (the
  translation) is ignored.
* Lens distortion (CameraInfo ``D``) is ignored, as for the other footage kinds; the
  D435i colour stream reports zero coefficients.

Needs the ``rosbags`` package (pure Python) only when a bag is opened; its messages are parsed by
:mod:`lobula.readers.ros1_messages`.
"""
from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from lobula.camera import PinholeCamera

from .bag_frames import bag_frames
from .core import IMU, Footage, FootageError, rotation_deg as _rotation_deg
from .ros1_messages import (CAMERA_INFO_TYPE, IMAGE_TYPE, IMU_TYPE, KEY_VALUE_TYPE, STREAM_INFO_TYPE,
                            SUPPORTED_ENCODINGS, TRANSFORM_TYPE, _ENCODINGS, _header, _parse_camera_info,
                            _parse_image, _parse_imu, _parse_key_value, _parse_stream_info_fps, _parse_transform,
                            _to_grey)

# /device_<d>/sensor_<s>/<Stream>_<i>/image/data, as librealsense's ros_topic names them.
VIEWER_TOPIC = re.compile(r"^/device_(?P<device>\d+)/sensor_(?P<sensor>\d+)/(?P<stream>[A-Za-z]+)_(?P<index>\d+)/")

# What rosbags and the decompressors raise on damaged bytes, besides ReaderError.
_CORRUPT = (AssertionError, KeyError, IndexError, RuntimeError, OSError, EOFError, struct.error, ValueError,
            UnicodeDecodeError)


# ---------------------------------------------------------------------- footage
class FramePlaceholders(Sequence):
    """Stand-ins for frame files: ``<bag>/<topic>/<index:06d>``, made on demand (no per-frame storage).

    The names end in the frame index so code that maps file stems to frames (the .flo
    reader) works; they are not files on disk. bag: the recording's path; topic: the image
    topic; n: the number of frames.
    """

    def __init__(self, bag: Path, topic: str, n: int):
        self._base, self._n = bag / topic.strip("/"), n

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self._n))]
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(i)
        return self._base / f"{i:06d}"


@dataclass
class BagFootage(Footage):
    """Footage streamed out of a RealSense ROS1 bag; see the module doc for the conventions.

    Extra fields: ``topic`` (the image topic read), ``encoding`` (its pixel encoding),
    ``time_origin_s`` (absolute time of ``times == 0``), ``time_source`` ("header" stamps
    or "bag" record times) and the per-frame bag record and source stamps (``bag_times_ns``,
    ``stamps_ns``: (n,) int64 ns) used to find and check frames while streaming.
    """

    topic: str = ""
    encoding: str = ""
    time_origin_s: float = 0.0
    time_source: str = "header"
    bag_times_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)

    def __len__(self) -> int:
        return len(self.times)

    def raw_frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """Yield (index, time_s, grey float32 (H, W)) for frames start..stop-1, one message at a time."""
        yield from bag_frames(self, self.topic, self.bag_times_ns, start, stop, open_bag=lambda: (*_rosbags(), None),
                              select=lambda c: c.topic == self.topic and c.msgtype == IMAGE_TYPE,
                              decode=lambda i, raw, bag_ns, _: self._decode_message(i, raw, bag_ns),
                              corrupt=_CORRUPT,
                              fix="the bag is damaged or changed: re-record it, or try `rosbag reindex`")

    def _decode_message(self, i: int, raw, bag_ns: int) -> np.ndarray | None:
        """Frame i's grey image, or None when it is undecodable and skip_bad_frames is set."""
        try:
            img = _parse_image(raw)
        except (ValueError, struct.error) as exc:
            self.bad_frame(i, FootageError(f"{self.path}: frame {i} on {self.topic} is corrupt ({exc}); "
                                           f"re-record, or read only frames before {i}"))
            return None
        got = img.stamp_ns if self.time_source == "header" else bag_ns
        if got != int(self.stamps_ns[i]):
            raise FootageError(f"{self.path}: frame {i} on {self.topic} has stamp {got} ns, "
                               f"{int(self.stamps_ns[i])} ns when opened; the bag changed, open it again")
        if img.encoding.lower() not in _ENCODINGS:
            raise FootageError(f"{self.path}: frame {i} on {self.topic} has encoding "
                               f"{img.encoding!r}; supported: {', '.join(SUPPORTED_ENCODINGS)}")
        try:
            if (img.width, img.height) != (self.camera.width, self.camera.height):
                raise FootageError(f"{self.path}: frame {i} on {self.topic} is {img.width}x{img.height}, "
                                   f"camera_info says {self.camera.width}x{self.camera.height}")
            try:
                return _to_grey(img)
            except ValueError as exc:
                raise FootageError(f"{self.path}: frame {i} on {self.topic}: {exc}; the message is "
                                   f"damaged, re-record") from None
        except FootageError as exc:
            self.bad_frame(i, exc)
            return None

    def depth_map(self, index: int) -> np.ndarray | None:
        """None: no depth is read from a bag."""
        return None


# ---------------------------------------------------------------------- opening
def _rosbags():
    try:
        from rosbags.rosbag1 import Reader, ReaderError
    except ImportError:  # pragma: no cover - rosbags is installed with the project
        raise FootageError("reading RealSense .bag files needs the rosbags package: pip install rosbags") from None
    return Reader, ReaderError


def _stream_name(topic: str) -> str:
    m = VIEWER_TOPIC.match(topic)
    return f"{m.group('stream')}_{m.group('index')}" if m else topic


def _image_rank(topic: str, stream_name=None) -> int | None:
    """Preference for an image topic as footage: colour, then infrared, then others; never depth."""
    name = (stream_name or _stream_name)(topic).lower()
    if any(w in name for w in ("depth", "confidence", "disparity")):
        return None
    if "color" in name or "colour" in name or "rgb" in name:
        return 0
    if "infra" in name or re.search(r"(^|[/_])ir($|[/_])", name):
        return 1
    if "fisheye" in name:
        return 2
    return 3


def choose_image_topic(path, image_topics: list[str], stream: str | None, stream_name=None) -> str:
    """The image topic to read as footage: the one ``stream`` names ("Color_0", "Infrared_1" or part of
    a topic), else colour, then infrared; never depth. ``stream_name`` maps a topic to its stream's
    name (the ROS1 Viewer layout by default). image_topics: the recording's image topics; ``path``
    is named in errors. Raises FootageError naming the topics there are."""
    name = stream_name or _stream_name
    if stream is not None:
        chosen = [t for t in image_topics if name(t).lower() == stream.lower() or stream in t]
        if not chosen:
            raise FootageError(f"{path}: no image stream matches {stream!r}; image topics here: "
                               f"{', '.join(sorted(image_topics)) or 'none'}")
        return sorted(chosen)[0]
    ranked = sorted((r, t) for t in image_topics if (r := _image_rank(t, name)) is not None)
    if not ranked:
        raise FootageError(f"{path}: no colour or infrared image topic"
                           f"{' (only ' + ', '.join(sorted(image_topics)) + ')' if image_topics else ''}; "
                           f"record the Color (or Infrared) stream")
    return ranked[0][1]


def _common_prefix(a: str, b: str) -> int:
    n = 0
    for x, y in zip(a.split("/"), b.split("/")):
        if x != y:
            break
        n += 1
    return n


def _closest(topics: list[str], ref: str) -> str | None:
    """The topic sharing the longest path prefix with ``ref`` (ties: alphabetical)."""
    return min(topics, key=lambda t: (-_common_prefix(t, ref), t)) if topics else None


def _stream_prefix(topic: str) -> str:
    """/device_0/sensor_1/Color_0 for a Viewer topic; the parent namespace otherwise."""
    m = VIEWER_TOPIC.match(topic)
    return m.group(0).rstrip("/") if m else topic.rsplit("/", 1)[0]


def _first(reader, conns, parse):
    for _, _, raw in reader.messages(connections=conns):
        return parse(raw)
    return None


def _check_increasing(path: Path, topic: str, stamps: np.ndarray, what: str) -> None:
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        k = int(bad[0])
        raise FootageError(f"{path}: {what} time stamps on {topic} do not increase: message {k + 1} (counting "
                           f"from 0) is stamped {stamps[k + 1] / 1e9:.9f} s, not after message {k}'s "
                           f"{stamps[k] / 1e9:.9f} s; the bag was merged or damaged: re-record, or re-export it "
                           f"with sorted stamps")


def _timestamp_domain(reader, topics: dict, prefix: str, kind: str) -> str | None:
    conns = [c for c in topics.get(f"{prefix}/{kind}/metadata", []) if c.msgtype == KEY_VALUE_TYPE]
    if not conns:
        return None
    for k, (_, _, raw) in enumerate(reader.messages(connections=conns)):
        key, value = _parse_key_value(raw)
        if key == "timestamp_domain":
            return value
        if k > 200:
            break
    return None


def _extrinsics(reader, topics: dict, prefix: str) -> tuple[str, np.ndarray] | None:
    """(group, R) of a stream's .../tf/<group> transform (p_stream = R·p_ref + t), if the bag has it."""
    for topic in sorted(t for t in topics if t.startswith(prefix + "/tf/")):
        conns = [c for c in topics[topic] if c.msgtype == TRANSFORM_TYPE]
        got = _first(reader, conns, _parse_transform) if conns else None
        if got is not None:
            return topic.rsplit("/", 1)[1], got[1]
    return None


def open_realsense_bag(path: str | Path, stream: str | None = None, camera: PinholeCamera | None = None,
                       require_imu: bool = True, time_source: str | None = None) -> BagFootage:
    """Open a RealSense ROS1 bag (RealSense Viewer recording) as streamed footage.

    stream: which image stream to read, as a Viewer stream name ("Color_0", "Infrared_1")
    or any part of a topic; default: colour, else infrared (never depth).
    camera: intrinsics to use instead of the bag's CameraInfo (needed when it has none).
    require_imu: raise when the bag has no accelerometer (True, as velocity needs it);
    with False such a bag opens with ``imu=None``.
    time_source: "header" (the messages' header stamps: the device's frame timestamps) or
    "bag" (the bag's record times); default: header stamps unless they are all zero.

    Reads the image stamps (only the message headers) and the IMU once, up front; images
    are decoded only by :meth:`BagFootage.frames`. Raises :class:`FootageError` with the
    file and what to do for anything unreadable.
    """
    path = Path(path)
    if not path.exists():
        raise FootageError(f"{path}: file not found; give a .bag recorded by the RealSense Viewer")
    if path.is_dir():
        raise FootageError(f"{path}: is a folder, not a ROS1 .bag file (a ROS 2 bag? convert it with "
                           f"`rosbags-convert`); RealSense Viewer recordings are single .bag files")
    Reader, ReaderError = _rosbags()
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, *_CORRUPT) as exc:
        raise FootageError(f"{path}: not a readable ROS1 bag ({exc}); give a .bag recorded by the RealSense "
                           f"Viewer (an interrupted recording may need `rosbag reindex`)") from exc
    try:
        return _open(path, reader, stream, camera, require_imu, time_source)
    except FootageError:
        raise
    except (ReaderError, *_CORRUPT) as exc:
        raise FootageError(f"{path}: the bag is damaged ({type(exc).__name__}: {exc}); re-record it "
                           f"(`rosbag check` / `rosbag reindex` may rescue part of it)") from exc
    finally:
        reader.close()


def _open(path: Path, reader, stream: str | None, camera: PinholeCamera | None, require_imu: bool,
          time_source: str | None = None) -> BagFootage:
    topics: dict[str, list] = {}
    for c in reader.connections:
        topics.setdefault(c.topic, []).append(c)
    types = {t: {c.msgtype for c in cs} for t, cs in topics.items()}
    counts = {t: sum(c.msgcount for c in cs) for t, cs in topics.items()}

    # ---- image topic
    image_topics = [t for t, ty in types.items() if IMAGE_TYPE in ty and counts[t] > 0]
    topic = choose_image_topic(path, image_topics, stream)
    img_conns = [c for c in topics[topic] if c.msgtype == IMAGE_TYPE]
    prefix = _stream_prefix(topic)

    # ---- image stamps: only the first 12 bytes of each message are parsed
    bag_ns, hdr_ns = [], []
    first = None
    for _, t_bag, raw in reader.messages(connections=img_conns):
        if first is None:
            first = _parse_image(raw)
        bag_ns.append(t_bag)
        hdr_ns.append(_header(raw)[0])
    bag_ns, hdr_ns = np.array(bag_ns, np.int64), np.array(hdr_ns, np.int64)
    if first.encoding.lower() not in _ENCODINGS:
        raise FootageError(f"{path}: {topic} has encoding {first.encoding!r}; supported: "
                           f"{', '.join(SUPPORTED_ENCODINGS)}; record colour as RGB8/BGR8/YUYV or infrared Y8")

    # ---- IMU topics (before the time check, which depends on the IMU's stamps too)
    accel_topic, gyro_topic, united, imu_raw = _imu_messages(path, reader, topics, types, counts, topic,
                                                             require_imu)

    # ---- time source: header stamps unless they are missing (all zero) somewhere
    notes = []
    if time_source not in (None, "header", "bag"):
        raise ValueError(f"unknown time source {time_source!r}; choose header or bag")
    use_header = np.any(hdr_ns != 0) and all(np.any(v[0] != 0) for v in imu_raw.values())
    if time_source is not None:
        use_header = time_source == "header"
    source = "header" if use_header else "bag"
    stamps = hdr_ns if use_header else bag_ns
    _check_increasing(path, topic, stamps, "image")
    origin = int(stamps[0])
    times = (stamps - origin) / 1e9

    # ---- camera
    camera, distortion = _camera(path, reader, topics, types, counts, topic, prefix, first, times, camera, notes)
    dom_img = _timestamp_domain(reader, topics, prefix, "image")
    notes.insert(0, f"RealSense bag: {len(times)} frames from {topic} ({first.encoding} -> grey), "
                    f"{camera.frame_rate_hz:g} Hz; times are {'header stamps' if use_header else 'bag record times (header stamps are zero)'}"
                    f"{' (' + dom_img + ')' if dom_img else ''} relative to the first frame's, "
                    f"origin {origin / 1e9:.6f} s")

    # ---- IMU: accel time base, gyro interpolated, rotated into the colour optical frame
    imu, r_imu = _bag_imu(path, reader, topics, prefix, accel_topic, gyro_topic, united, imu_raw, use_header,
                          origin, dom_img, notes)

    return BagFootage(path=path, camera=camera, times=times, files=FramePlaceholders(path, topic, len(times)),
                      imu=imu, truth=None, kind="realsense-bag", notes=notes, topic=topic, distortion=distortion,
                      imu_to_camera=r_imu,
                      encoding=first.encoding, time_origin_s=origin / 1e9, time_source=source,
                      bag_times_ns=bag_ns, stamps_ns=stamps,
                      streams=[dict(topic=t, type=", ".join(sorted(types[t])), messages=int(counts[t]))
                               for t in sorted(topics)])


def _imu_messages(path: Path, reader, topics: dict, types: dict, counts: dict, topic: str, require_imu: bool):
    """The accelerometer and gyroscope topics nearest the image ``topic`` (one united IMU topic where the bag
    has no separate ones) and their messages: (accel_topic, gyro_topic, united, {role: (header stamps ns,
    record times ns, values (n, 6): linear acceleration then angular velocity)})."""
    imu_topics = [t for t, ty in types.items() if IMU_TYPE in ty and counts[t] > 0]
    accel_topic = _closest([t for t in imu_topics if "accel" in t.lower()], topic)
    gyro_topic = _closest([t for t in imu_topics if "gyro" in t.lower()], topic)
    united = False
    if accel_topic is None and gyro_topic is None and imu_topics:
        accel_topic = gyro_topic = _closest(imu_topics, topic)  # realsense-ros unite_imu_method
        united = True
    if accel_topic is None and require_imu:
        raise FootageError(f"{path}: no accelerometer topic (sensor_msgs/Imu, e.g. /device_0/sensor_2/Accel_0/"
                           f"imu/data){' (gyroscope only: ' + gyro_topic + ')' if gyro_topic else ''}; velocity "
                           f"needs forward acceleration and a bag has no ground truth, so --accel-from-truth "
                           f"cannot stand in. Record with the Motion Module (Accel + Gyro) enabled (D435i)")
    imu_raw = {}
    for role, t in (("accel", accel_topic), ("gyro", gyro_topic)):
        if t is None or (role == "gyro" and united):
            continue
        conns = [c for c in topics[t] if c.msgtype == IMU_TYPE]
        st, bt, vals = [], [], []
        for _, t_bag, raw in reader.messages(connections=conns):
            s, ang, lin = _parse_imu(raw)
            st.append(s)
            bt.append(t_bag)
            vals.append(np.concatenate([lin, ang]))
        imu_raw[role] = (np.array(st, np.int64), np.array(bt, np.int64), np.array(vals))
    if united:
        imu_raw["gyro"] = imu_raw["accel"]
    return accel_topic, gyro_topic, united, imu_raw


def _camera(path: Path, reader, topics: dict, types: dict, counts: dict, topic: str, prefix: str, first,
            times: np.ndarray, camera: PinholeCamera | None, notes: list[str]):
    """(camera, distortion): ``camera`` as given, else the intrinsics of the image stream's CameraInfo at its
    StreamInfo frame rate (else the frames' median rate); the distortion the CameraInfo reports (ignored),
    or None. FootageError where there are no intrinsics or they disagree with the frames' size."""
    distortion = None
    info_topics = [t for t, ty in types.items() if CAMERA_INFO_TYPE in ty and counts[t] > 0]
    info_topic = f"{prefix}/info/camera_info" if f"{prefix}/info/camera_info" in info_topics else \
        _closest([t for t in info_topics if _image_rank(t) == _image_rank(topic)] or info_topics, topic)
    fps = None
    si = [c for c in topics.get(f"{prefix}/info", []) if c.msgtype == STREAM_INFO_TYPE]
    if si:
        fps = _first(reader, si, _parse_stream_info_fps) or None
    if fps is None and len(times) > 1:
        fps = 1.0 / float(np.median(np.diff(times)))
    if fps is None:
        fps = 30.0
        notes.append("one frame only: frame rate taken as 30 Hz")
    intrinsics_from = "--camera" if camera is not None else info_topic
    if camera is None:
        if info_topic is None:
            raise FootageError(f"{path}: no sensor_msgs/CameraInfo for {topic}, so no intrinsics; give them with "
                               f"--camera FILE, a camera.json with width, height, fx, fy, cx, cy, frame_rate_hz "
                               f"of this stream")
        info = _first(reader, [c for c in topics[info_topic] if c.msgtype == CAMERA_INFO_TYPE], _parse_camera_info)
        k = info["K"]
        w, h = (info["width"] or first.width), (info["height"] or first.height)
        if k[0] <= 0 or k[4] <= 0:
            raise FootageError(f"{path}: {info_topic} has no intrinsics (K = {k.tolist()}); give them with "
                               f"--camera FILE, a camera.json with width, height, fx, fy, cx, cy, frame_rate_hz "
                               f"of this stream")
        camera = PinholeCamera(width=int(w), height=int(h), fx=float(k[0]), fy=float(k[4]), cx=float(k[2]),
                               cy=float(k[5]), frame_rate_hz=float(fps))
        if np.any(np.abs(info["D"]) > 1e-9):
            distortion = dict(model=info["distortion_model"], coeffs=info["D"].tolist(), removed=False)
            notes.append(f"lens distortion ({info['distortion_model']}, D = {np.round(info['D'], 5).tolist()}) "
                         f"ignored: pinhole model")
    if (first.width, first.height) != (camera.width, camera.height):
        raise FootageError(f"{path}: {topic} images are {first.width}x{first.height} but the intrinsics "
                           f"({intrinsics_from}) are for {camera.width}x{camera.height}")
    return camera, distortion


def _bag_imu(path: Path, reader, topics: dict, prefix: str, accel_topic, gyro_topic, united: bool, imu_raw: dict,
             use_header: bool, origin: int, dom_img: str | None, notes: list[str]):
    """(IMU or None, the rotation applied to it or None): the accelerometer's times as the time base (s from
    ``origin``, ns), the gyroscope interpolated onto them, both rotated into the image stream's optical
    frame. Appends what it did to ``notes``."""
    imu, r_imu = None, None
    if "accel" in imu_raw:
        pick = 0 if use_header else 1
        if united:
            acc_t, both = _dedupe_check(path, accel_topic, imu_raw["accel"][pick], imu_raw["accel"][2], "IMU")
            acc, gyro = both[:, :3], both[:, 3:]
        else:
            acc_t, acc = _dedupe_check(path, accel_topic, imu_raw["accel"][pick], imu_raw["accel"][2][:, :3],
                                       "accelerometer")
            gyro = None
        rate_a = (len(acc_t) - 1) / ((acc_t[-1] - acc_t[0]) / 1e9) if len(acc_t) > 1 else float("nan")
        imu_note = f"IMU: accelerometer {accel_topic} ({rate_a:.0f} Hz) is the time base"
        if "gyro" in imu_raw:
            if united:
                imu_note += " (one united IMU topic: gyroscope at the same times)"
            else:
                gyr_t, gyr = _dedupe_check(path, gyro_topic, imu_raw["gyro"][pick], imu_raw["gyro"][2][:, 3:],
                                           "gyroscope")
                keep = (acc_t >= gyr_t[0]) & (acc_t <= gyr_t[-1])
                if keep.sum() < 2:
                    raise FootageError(f"{path}: accelerometer ({accel_topic}) and gyroscope ({gyro_topic}) "
                                       f"stamps do not overlap; their clocks differ: re-record with global "
                                       f"time enabled")
                acc_t, acc = acc_t[keep], acc[keep]
                tg = (gyr_t - gyr_t[0]) / 1e9
                ta = (acc_t - gyr_t[0]) / 1e9
                gyro = np.stack([np.interp(ta, tg, gyr[:, j]) for j in range(3)], -1)
                rate_g = (len(gyr_t) - 1) / ((gyr_t[-1] - gyr_t[0]) / 1e9) if len(gyr_t) > 1 else float("nan")
                imu_note += (f"; gyroscope {gyro_topic} ({rate_g:.0f} Hz) linearly interpolated onto it"
                             f"{f', {int((~keep).sum())} accelerometer samples outside its span dropped' if (~keep).any() else ''}")
        else:
            imu_note += "; no gyroscope topic (no derotation possible)"
        acc, gyro, axes = _to_colour_frame(reader, topics, prefix, accel_topic, gyro_topic, acc, gyro)
        r_imu = _applied_rotation(reader, topics, prefix, accel_topic)
        notes.append(f"{imu_note}; {axes}")
        dom_imu = _timestamp_domain(reader, topics, _stream_prefix(accel_topic), "imu")
        if dom_img and dom_imu and dom_img != dom_imu:
            notes.append(f"warning: image stamps are {dom_img} but IMU stamps are {dom_imu}; the two clocks "
                         f"may be offset")
        imu = IMU((acc_t - origin) / 1e9, acc, gyro, source=f"{path}:{accel_topic}"
                  + (f" + {gyro_topic}" if gyro_topic and not united else ""))
    else:
        notes.append("no IMU in this bag: velocity cannot be estimated from it")
    return imu, r_imu


def _dedupe_check(path: Path, topic: str, stamps: np.ndarray, values: np.ndarray, what: str):
    """Drop IMU messages repeated verbatim (same stamp and values); then stamps must increase."""
    if len(stamps) > 1:
        dup = np.r_[False, (np.diff(stamps) == 0) & np.all(np.diff(values, axis=0) == 0, axis=1)]
        stamps, values = stamps[~dup], values[~dup]
    if not np.all(np.isfinite(values)):
        row = int(np.flatnonzero(~np.isfinite(values).all(1))[0])
        raise FootageError(f"{path}: {what} message {row} on {topic} has NaN or infinite values; re-record")
    _check_increasing(path, topic, stamps, what)
    return stamps, values


def _applied_rotation(reader, topics, prefix, accel_topic) -> np.ndarray | None:
    """The accelerometer-to-image rotation _to_colour_frame applied (None when none was)."""
    cam = _extrinsics(reader, topics, prefix)
    ext = _extrinsics(reader, topics, _stream_prefix(accel_topic))
    if ext is None or (cam is not None and cam[0] != ext[0]):
        return None
    return (cam[1] if cam else np.eye(3)) @ ext[1].T


def _to_colour_frame(reader, topics, prefix, accel_topic, gyro_topic, acc, gyro):
    """Rotate IMU vectors into the image stream's optical frame with the bag's extrinsics, if any."""
    cam = _extrinsics(reader, topics, prefix)
    ext_a = _extrinsics(reader, topics, _stream_prefix(accel_topic))
    ext_g = _extrinsics(reader, topics, _stream_prefix(gyro_topic)) if gyro is not None else None
    if ext_a is None and ext_g is None:
        return acc, gyro, ("no IMU extrinsics in the bag: axes used as librealsense reports them for the "
                           "D435i, already in the camera optical convention (x right, y down, z forward); "
                           "no rotation applied (IMU to colour is typically well under a degree on a D435i)")
    r_cam = cam[1] if cam else np.eye(3)
    said = []
    out = []
    for name, vec, ext in (("accelerometer", acc, ext_a), ("gyroscope", gyro, ext_g)):
        if vec is None:
            out.append(None)
            continue
        if ext is None:
            out.append(vec)
            said.append(f"{name}: no extrinsics, unrotated")
            continue
        if cam is not None and cam[0] != ext[0]:
            out.append(vec)
            said.append(f"{name}: extrinsics in group {ext[0]}, image in group {cam[0]}, cannot compose, unrotated")
            continue
        r = r_cam @ ext[1].T  # imu -> reference -> image stream
        out.append(vec @ r.T)
        said.append(f"{name} rotated {_rotation_deg(r):.2f} deg")
    return out[0], out[1], ("axes put in the image stream's optical frame (x right, y down, z forward) with "
                            "the bag's extrinsics: " + ", ".join(said) + "; lever arm ignored")
