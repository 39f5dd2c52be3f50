"""RealSense rosbag2 recordings (SQLite ``.db3``), as librealsense 2.58 and later write them, as footage.

``open_rosbag2(path)`` returns a :class:`Rosbag2Footage` whose :meth:`frames` streams grey
images out of the bag one message at a time (rosbags' rosbag2 Reader and its ROS 2
typestore; nothing is unpacked by hand) and whose ``imu`` holds accelerometer and
gyroscope on one time base in the camera optical frame.

What librealsense ≥ 2.58 writes (measured on files written by pyrealsense2 2.59)::

    /device_0/sensor_0/Color_0/image/data/compressed   sensor_msgs/CompressedImage, format
                                                       "rgb8; png compressed bgr8" (PNG)
    /device_0/sensor_0/Color_0/image/metadata          std_msgs/String "Frame number=..;
                                                       timestamp_domain=Global Time;..;timestamp=<ms>;"
    /device_0/sensor_0/Color_0/image/camera_info       sensor_msgs/CameraInfo (k: fx, cx, fy, cy; d)
    /device_0/sensor_0/Color_0/camera_info             std_msgs/String "width=..;fx=..;ppx=..;coeffs=.."
    /device_0/sensor_0/Color_0/info                    std_msgs/String "encoding=RGB8;fps=30"
    /device_0/sensor_0/Color_0/tf/ref_<k>              std_msgs/String "rotation=9 numbers;translation=3"
    /tf_static                                         tf2_msgs/TFMessage (parent ref_<k>, child Color)
    /device_0/sensor_1/Accel_0/imu/data (+ /metadata)  sensor_msgs/Imu (linear_acceleration)
    /device_0/sensor_1/Gyro_0/imu/data (+ /metadata)   sensor_msgs/Imu (angular_velocity)

Header stamps and record times count from the start of recording on the host; the
device's own time stamp of each frame and motion sample (ms) is in the metadata string.

Choices, each also written into ``footage.notes``:

* **clock** "device" (default): the metadata time stamps; "header": header stamps;
  "record": the bag's record times. Times are seconds relative to the first frame.
  A frame's metadata is the one recorded at the same record time (librealsense writes
  both together), else the one in the same position.
* **Grey** as for the other readers: OpenCV decodes the PNG (BGR order, as the format
  says) and ITU-R 601 luma is taken; raw ``sensor_msgs/Image`` topics are read too.
* **IMU**: accelerometer times are the time base, the gyroscope interpolated onto them.
  librealsense writes no transform for the motion streams in ``.db3``; the D435i's motion
  data are already in the depth camera's optical convention, so no rotation is applied
  unless the bag has IMU extrinsics (then R_image·R_imuᵀ, as for ``.bag``).
"""
from __future__ import annotations

import re
import sqlite3
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from lobula.camera import PinholeCamera

from .bag_frames import bag_frames
from .core import IMU, Footage, FootageError, opencv_quiet, rotation_deg, to_grey
from .realsense_bag import FramePlaceholders, choose_image_topic

COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPE = "sensor_msgs/msg/Image"
IMU_TYPE = "sensor_msgs/msg/Imu"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
STRING_TYPE = "std_msgs/msg/String"
TF_TYPE = "tf2_msgs/msg/TFMessage"
CLOCKS = ("device", "header", "record")

# What rosbags, sqlite3 and the decoders raise on damaged input.
_CORRUPT = (AssertionError, KeyError, IndexError, RuntimeError, OSError, EOFError, ValueError, UnicodeDecodeError,
            OverflowError, sqlite3.Error)


def _rosbags():
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.typesys import Stores, get_typestore
    return Reader, ReaderError, get_typestore(Stores.ROS2_HUMBLE)


def _kv(text: str) -> dict:
    """librealsense's "key=value;key=value;" strings as a dict."""
    out = {}
    for part in text.split(";"):
        if "=" in part:
            k, v = part.split("=", 1)
            out[k.strip()] = v.strip()
    return out


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _stream_name(topic: str) -> str:
    m = re.match(r"^/device_\d+/sensor_\d+/(?P<s>[A-Za-z]+_\d+)/", topic)
    return m.group("s") if m else topic


def _stream_prefix(topic: str) -> str:
    m = re.match(r"^/device_\d+/sensor_\d+/[A-Za-z]+_\d+", topic)
    return m.group(0) if m else topic.rsplit("/", 1)[0]


class Rosbag2Footage(Footage):
    """Footage streamed out of a rosbag2 ``.db3``; see the module doc for the conventions.

    topic, msgtype: the image topic and its message type; record_ns (n,) int64 ns: each frame's
    record time in the bag; clock: the stamps ``times`` are on ("device", "header" or "record");
    time_origin_ns: the first frame's stamp (ns) on that clock, which ``times`` (s) count from.
    """

    def __init__(self, *args, topic: str = "", msgtype: str = "", record_ns=None, clock: str = "device",
                 time_origin_ns: int = 0, **kwargs):
        super().__init__(*args, **kwargs)
        self.topic, self.msgtype, self.clock = topic, msgtype, clock
        self.record_ns = np.asarray(record_ns if record_ns is not None else [], np.int64)
        self.time_origin_ns = time_origin_ns
        self.time_source = clock

    def __len__(self) -> int:
        return len(self.times)

    def raw_frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """Yield (index, time_s s, grey float32 (H, W)) for frames start..stop-1, one message at a time."""
        yield from bag_frames(self, self.topic, self.record_ns, start, stop, open_bag=_rosbags,
                              select=lambda c: c.topic == self.topic, decode=self._decode_recorded,
                              corrupt=_CORRUPT, fix="the bag is damaged or changed: re-record it")

    def _decode_recorded(self, i: int, raw, rec_ns: int, ts) -> np.ndarray | None:
        """Frame i's grey image, after checking its record time is the one seen when opening."""
        if rec_ns != int(self.record_ns[i]):
            raise FootageError(f"{self.path}: frame {i} on {self.topic} recorded at {rec_ns} ns, "
                               f"{int(self.record_ns[i])} ns when opened; the bag changed, open it again")
        return self._decode(i, raw, ts)

    def _decode(self, i: int, raw, ts) -> np.ndarray | None:
        try:
            try:
                msg = ts.deserialize_cdr(raw, self.msgtype)
            except Exception as exc:  # rosbags' SerdeError and the struct/numpy errors under it
                raise FootageError(f"{self.path}: frame {i} on {self.topic} is corrupt ({exc}); re-record") from None
            if self.msgtype == COMPRESSED_TYPE:
                data = np.asarray(msg.data, np.uint8)
                fix = "re-record, or pass --skip-bad-frames to leave such frames out"
                if data.size == 0:  # OpenCV asserts on an empty buffer instead of returning None
                    raise FootageError(f"{self.path}: frame {i} on {self.topic} is empty (0 bytes of "
                                       f"{msg.format!r} data); {fix}")
                try:
                    with opencv_quiet():
                        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
                except cv2.error:
                    img = None
                if img is None:
                    raise FootageError(f"{self.path}: frame {i} on {self.topic}: cannot decode its "
                                       f"{data.size} bytes of {msg.format!r} data (damaged); {fix}")
                grey = to_grey(img)
            else:
                grey = _raw_image_grey(msg)
            self.check_size(grey, f"{self.path}: frame {i} on {self.topic}")
            return grey
        except FootageError as exc:
            self.bad_frame(i, exc)
            return None

    def depth_map(self, index: int) -> np.ndarray | None:
        """None: no depth is read from a bag."""
        return None


def _raw_image_grey(msg) -> np.ndarray:
    """A sensor_msgs/Image (rgb8, bgr8, mono8, mono16) as grey float32."""
    enc = msg.encoding.lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    bpp = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1, "mono16": 2, "16uc1": 2}.get(enc)
    if bpp is None:
        raise FootageError(f"image encoding {msg.encoding!r} not supported (rgb8, bgr8, mono8, mono16)")
    data = np.asarray(msg.data, np.uint8)
    if data.size < step * h or step < w * bpp:
        raise FootageError(f"{w}x{h} {msg.encoding} image message is short ({data.size} bytes)")
    rows = data[:step * h].reshape(h, step)[:, :w * bpp]
    if bpp == 1:
        return rows.astype(np.float32)
    if bpp == 2:
        return np.ascontiguousarray(rows).view(">u2" if msg.is_bigendian else "<u2").astype(np.float32) / 257.0
    px = np.ascontiguousarray(rows).reshape(h, w, bpp)
    code = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY,
            "bgra8": cv2.COLOR_BGRA2GRAY}[enc]
    return cv2.cvtColor(px, code).astype(np.float32)


def _messages(reader, conns, ts, typename):
    if not conns:   # rosbags reads every topic when given no connections
        return
    for _, rec_ns, raw in reader.messages(connections=conns):
        yield rec_ns, ts.deserialize_cdr(raw, typename)


def _device_times(reader, topics, prefix: str, kind: str, ts) -> dict:
    """{record ns: (device ms, position)} from a stream's metadata strings, plus the timestamp domain."""
    conns = [c for c in topics.get(f"{prefix}/{kind}/metadata", []) if c.msgtype == STRING_TYPE]
    by_rec, order, domain = {}, [], None
    for rec_ns, msg in _messages(reader, conns, ts, STRING_TYPE):
        kv = _kv(msg.data)
        if "timestamp" in kv:
            ms = float(kv["timestamp"])
            by_rec.setdefault(rec_ns, ms)
            order.append(ms)
        domain = domain or kv.get("timestamp_domain")
    return dict(by_rec=by_rec, order=order, domain=domain)


def _pick_times(path, topic, clock, rec, hdr, meta) -> np.ndarray:
    """Per-message times (ns, int64) on the chosen clock."""
    if clock == "record":
        return np.asarray(rec, np.int64)
    if clock == "header":
        return np.asarray(hdr, np.int64)
    if not meta["order"]:
        raise FootageError(f"{path}: {topic} has no metadata with device time stamps; use --clock header")
    if all(r in meta["by_rec"] for r in rec):
        ms = np.array([meta["by_rec"][r] for r in rec])
    elif len(meta["order"]) == len(rec):
        ms = np.asarray(meta["order"])
    else:
        raise FootageError(f"{path}: {topic} has {len(rec)} messages but {len(meta['order'])} metadata time "
                           f"stamps that do not pair up; use --clock header")
    return np.round(ms * 1e6).astype(np.int64)


def _check_increasing(path, topic, stamps, what):
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        k = int(bad[0])
        raise FootageError(f"{path}: {what} time stamps on {topic} do not increase: message {k + 1} is stamped "
                           f"{stamps[k + 1] / 1e9:.9f} s, not after message {k}'s {stamps[k] / 1e9:.9f} s; "
                           f"try another --clock, or re-record")


def _rotation_from_string(text: str) -> np.ndarray | None:
    """librealsense's extrinsics string "rotation=r0,..,r8;translation=..": rs2_extrinsics is column-major."""
    kv = _kv(text)
    try:
        r = np.array([float(x) for x in kv["rotation"].split(",")]).reshape(3, 3).T
    except (KeyError, ValueError):
        return None
    return r if np.abs(r @ r.T - np.eye(3)).max() < 1e-3 else None


def _extrinsics(reader, topics, prefix, ts):
    for topic in sorted(t for t in topics if t.startswith(prefix + "/tf/")):
        conns = [c for c in topics[topic] if c.msgtype == STRING_TYPE]
        for _, msg in _messages(reader, conns, ts, STRING_TYPE):
            r = _rotation_from_string(msg.data)
            if r is not None:
                return topic.rsplit("/", 1)[1], r
    return None


def open_rosbag2(path: str | Path, stream: str | None = None, clock: str = "device", require_imu: bool = True,
                 camera: PinholeCamera | None = None) -> Rosbag2Footage:
    """Open a RealSense rosbag2 recording (``.db3`` file, or a rosbag2 folder) as streamed footage.

    stream: image stream ("Color_0", "Infrared_1" or part of a topic; default colour, else
    infrared, never depth). clock: "device", "header" or "record" (module doc).
    require_imu: stop when there is no accelerometer. camera: intrinsics to use instead of
    the bag's. Raises :class:`FootageError` naming the file and what to do.
    """
    path = Path(path)
    if clock not in CLOCKS:
        raise ValueError(f"unknown clock {clock!r}; choose {', '.join(CLOCKS)}")
    if not path.exists():
        raise FootageError(f"{path}: file not found; give a .db3 recorded by librealsense ≥ 2.58")
    Reader, ReaderError, ts = _rosbags()
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, *_CORRUPT) as exc:
        raise FootageError(f"{path}: not a readable rosbag2 .db3 ({type(exc).__name__}: {exc}); give a .db3 "
                           f"recorded by librealsense ≥ 2.58 (a truncated or damaged file cannot be read: "
                           f"re-record it)") from exc
    try:
        return _open(path, reader, ts, stream, clock, require_imu, camera)
    except FootageError:
        raise
    except (ReaderError, *_CORRUPT) as exc:
        raise FootageError(f"{path}: the bag is damaged ({type(exc).__name__}: {exc}); re-record it") from exc
    except Exception as exc:  # rosbags' SerdeError on a damaged message
        if type(exc).__name__ != "SerdeError":
            raise
        raise FootageError(f"{path}: a message is damaged ({exc}); re-record it") from exc
    finally:
        reader.close()


def _open(path, reader, ts, stream, clock, require_imu, camera) -> Rosbag2Footage:
    topics: dict[str, list] = {}
    for c in reader.connections:
        topics.setdefault(c.topic, []).append(c)
    types = {t: {c.msgtype for c in cs} for t, cs in topics.items()}
    counts = {t: sum(c.msgcount for c in cs) for t, cs in topics.items()}
    streams = [dict(topic=t, type=", ".join(sorted(types[t])), messages=int(counts[t])) for t in sorted(topics)]

    topic, msgtype, prefix, rec, fmt, meta, stamps = _image_stream(path, reader, ts, topics, types, counts,
                                                                   stream, clock)
    origin = int(stamps[0])
    times = (stamps - origin) / 1e9

    notes, distortion = [], None
    fps = _stream_fps(reader, topics, prefix, ts, times)
    if camera is None:
        camera, distortion, note = _bag_camera(path, reader, topics, prefix, ts, topic, fps)
        if note:
            notes.append(note)

    accel_topic, gyro_topic, raw = _imu_streams(path, reader, ts, topics, types, counts, clock, require_imu)
    imu, r = _bag_imu(path, reader, ts, topics, raw, accel_topic, gyro_topic, clock, topic, prefix, meta,
                      origin, notes)
    clock_word = {"device": f"device time stamps from the metadata ({meta['domain'] or 'domain not given'})",
                  "header": "message header stamps", "record": "bag record times"}[clock]
    notes.insert(0, f"rosbag2 .db3: {len(times)} frames from {topic} ({fmt} -> grey), {camera.frame_rate_hz:g} Hz; "
                    f"times are {clock_word}, relative to the first frame's ({origin / 1e9:.6f} s)")
    return Rosbag2Footage(path, camera, times, FramePlaceholders(path, topic, len(times)),
                          imu, None, kind="realsense-db3", notes=notes, distortion=distortion, imu_to_camera=r,
                          streams=streams, topic=topic, msgtype=msgtype, record_ns=rec, clock=clock,
                          time_origin_ns=origin)


def _image_stream(path, reader, ts, topics, types, counts, stream, clock):
    """The image topic, its message type and stream prefix, its record times (ns), its format, its
    metadata times and its stamps (ns, int64) on ``clock``."""
    image_topics = [t for t, ty in types.items() if ty & {COMPRESSED_TYPE, IMAGE_TYPE} and counts[t] > 0]
    topic = choose_image_topic(path, image_topics, stream, _stream_name)
    msgtype = COMPRESSED_TYPE if COMPRESSED_TYPE in types[topic] else IMAGE_TYPE
    img_conns = [c for c in topics[topic] if c.msgtype == msgtype]
    prefix = _stream_prefix(topic)

    rec, hdr, fmt = [], [], None
    for rec_ns, msg in _messages(reader, img_conns, ts, msgtype):
        rec.append(rec_ns)
        hdr.append(_stamp_ns(msg.header))
        fmt = fmt or (msg.format if msgtype == COMPRESSED_TYPE else msg.encoding)
    meta = _device_times(reader, topics, prefix, "image", ts)
    stamps = _pick_times(path, topic, clock, rec, hdr, meta)
    _check_increasing(path, topic, stamps, "image")
    return topic, msgtype, prefix, rec, fmt, meta, stamps


def _stream_fps(reader, topics, prefix, ts, times) -> float:
    """The stream's frame rate (Hz): its info string's fps, else from the frame times (s)."""
    fps = None
    for t in (f"{prefix}/info",):
        for _, msg in _messages(reader, [c for c in topics.get(t, []) if c.msgtype == STRING_TYPE], ts, STRING_TYPE):
            fps = float(_kv(msg.data).get("fps", 0)) or None
            break
    if fps is None:
        fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 30.0
    return fps


def _bag_camera(path, reader, topics, prefix, ts, topic, fps):
    """(camera, distortion or None, note or None) from the bag's intrinsics: CameraInfo, else
    librealsense's camera_info string."""
    info = None
    for t in (f"{prefix}/image/camera_info", f"{prefix}/info/camera_info"):
        conns = [c for c in topics.get(t, []) if c.msgtype == CAMERA_INFO_TYPE]
        for _, msg in _messages(reader, conns, ts, CAMERA_INFO_TYPE):
            info = dict(w=int(msg.width), h=int(msg.height), fx=float(msg.k[0]), fy=float(msg.k[4]),
                        cx=float(msg.k[2]), cy=float(msg.k[5]), model=msg.distortion_model,
                        coeffs=np.asarray(msg.d, float).tolist(), source=t)
            break
        if info:
            break
    if info is None:
        conns = [c for c in topics.get(f"{prefix}/camera_info", []) if c.msgtype == STRING_TYPE]
        for _, msg in _messages(reader, conns, ts, STRING_TYPE):
            kv = _kv(msg.data)
            try:
                info = dict(w=int(kv["width"]), h=int(kv["height"]), fx=float(kv["fx"]), fy=float(kv["fy"]),
                            cx=float(kv["ppx"]), cy=float(kv["ppy"]), model=kv.get("model", ""),
                            coeffs=[float(x) for x in kv.get("coeffs", "").split(",") if x],
                            source=f"{prefix}/camera_info")
            except (KeyError, ValueError):
                info = None
            break
    if info is None or info["fx"] <= 0 or info["fy"] <= 0 or info["w"] <= 0 or info["h"] <= 0:
        what = ("no intrinsics (no CameraInfo or camera_info string)" if info is None else
                f"unusable intrinsics in {info['source']} ({info['w']}x{info['h']}, fx {info['fx']:g}, "
                f"fy {info['fy']:g})")
        raise FootageError(f"{path}: {topic} has {what}; give them with --camera FILE, a camera.json with "
                           f"width, height, fx, fy, cx, cy, frame_rate_hz of this stream")
    camera = PinholeCamera(width=info["w"], height=info["h"], fx=info["fx"], fy=info["fy"], cx=info["cx"],
                           cy=info["cy"], frame_rate_hz=float(fps))
    distortion, note = None, None
    if any(abs(x) > 1e-9 for x in info["coeffs"]):
        distortion = dict(model=info["model"], coeffs=info["coeffs"], removed=False)
        note = (f"lens distortion ({info['model']}, {np.round(info['coeffs'], 5).tolist()}) ignored: "
                f"pinhole model")
    return camera, distortion, note


def _imu_streams(path, reader, ts, topics, types, counts, clock, require_imu):
    """(accelerometer topic, gyroscope topic, {role: (stamps ns, values (n, 3), time domain)})."""
    imu_topics = [t for t, ty in types.items() if IMU_TYPE in ty and counts[t] > 0]
    accel_topic = next((t for t in sorted(imu_topics) if "accel" in t.lower()), None)
    gyro_topic = next((t for t in sorted(imu_topics) if "gyro" in t.lower()), None)
    if accel_topic is None and require_imu:
        raise FootageError(f"{path}: no accelerometer topic (sensor_msgs/Imu, e.g. /device_0/sensor_1/Accel_0/"
                           f"imu/data){' (gyroscope only)' if gyro_topic else ''}; velocity needs forward "
                           f"acceleration: record with the Motion Module (Accel + Gyro) enabled (D435i)")
    raw = {}
    for role, t in (("accel", accel_topic), ("gyro", gyro_topic)):
        if t is None:
            continue
        rec_i, hdr_i, vals = [], [], []
        for rec_ns, msg in _messages(reader, [c for c in topics[t] if c.msgtype == IMU_TYPE], ts, IMU_TYPE):
            rec_i.append(rec_ns)
            hdr_i.append(_stamp_ns(msg.header))
            v = msg.linear_acceleration if role == "accel" else msg.angular_velocity
            vals.append((v.x, v.y, v.z))
        m = _device_times(reader, topics, _stream_prefix(t), "imu", ts)
        st = _pick_times(path, t, clock, rec_i, hdr_i, m)
        vals = np.asarray(vals, float)
        if len(st) > 1:   # librealsense may repeat a sample verbatim
            dup = np.r_[False, (np.diff(st) == 0) & np.all(np.diff(vals, axis=0) == 0, axis=1)]
            st, vals = st[~dup], vals[~dup]
        if not np.all(np.isfinite(vals)):
            raise FootageError(f"{path}: NaN or infinite values on {t}; re-record")
        _check_increasing(path, t, st, role)
        raw[role] = (st, vals, m["domain"])
    return accel_topic, gyro_topic, raw


def _bag_imu(path, reader, ts, topics, raw, accel_topic, gyro_topic, clock, topic, prefix, meta, origin, notes):
    """(IMU or None, IMU-to-camera rotation (3, 3) or None): the gyroscope onto the accelerometer's
    times, both into the image's optical frame where the bag has the extrinsics; notes appended."""
    if "accel" not in raw:
        notes.append("no IMU in this bag: velocity cannot be estimated from it")
        return None, None
    acc_t, acc, _ = raw["accel"]
    gyro = None
    note = f"IMU: accelerometer {accel_topic} is the time base"
    if "gyro" in raw:
        g_t, g, _ = raw["gyro"]
        keep = (acc_t >= g_t[0]) & (acc_t <= g_t[-1])
        if keep.sum() < 2:
            raise FootageError(f"{path}: accelerometer and gyroscope stamps do not overlap on the {clock} "
                               f"clock; try --clock header")
        acc_t, acc = acc_t[keep], acc[keep]
        gyro = np.stack([np.interp((acc_t - g_t[0]) / 1e9, (g_t - g_t[0]) / 1e9, g[:, j]) for j in range(3)], -1)
        note += f"; gyroscope {gyro_topic} linearly interpolated onto it"
        if (~keep).any():
            note += f", {int((~keep).sum())} accelerometer samples outside its span dropped"
    ext_img = _extrinsics(reader, topics, prefix, ts)
    ext_acc = _extrinsics(reader, topics, _stream_prefix(accel_topic), ts)
    r = None
    if ext_img and ext_acc and ext_img[0] == ext_acc[0]:
        r = ext_img[1] @ ext_acc[1].T
        acc, gyro = acc @ r.T, (None if gyro is None else gyro @ r.T)
        note += f"; rotated {rotation_deg(r):.2f} deg into {topic}'s optical frame with the bag's extrinsics"
    else:
        note += ("; no IMU extrinsics in the bag (librealsense ≥ 2.58 writes none for motion streams): axes "
                 "as librealsense reports them for the D435i, already in the camera optical convention "
                 "(x right, y down, z forward); no rotation applied")
    notes.append(note)
    if meta["domain"] and raw["accel"][2] and meta["domain"] != raw["accel"][2] and clock == "device":
        notes.append(f"warning: image stamps are {meta['domain']} but IMU stamps are {raw['accel'][2]}; "
                     f"the clocks may be offset (see --clock-offset)")
    imu = IMU((acc_t - origin) / 1e9, acc, gyro, source=f"{path}:{accel_topic}"
              + (f" + {gyro_topic}" if gyro_topic else ""))
    return imu, r
