"""The ROS1 messages of a RealSense bag, parsed, and its image messages decoded to grey.

Messages go through rosbags' Noetic typestore with librealsense's ``realsense_msgs/StreamInfo``
registered; :func:`_to_grey` turns an image message into grey levels as
:mod:`lobula.readers.realsense_bag` describes (its module doc: **Grey**). Needs the ``rosbags``
package only when a message is parsed.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

IMAGE_TYPE = "sensor_msgs/msg/Image"
IMU_TYPE = "sensor_msgs/msg/Imu"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TRANSFORM_TYPE = "geometry_msgs/msg/Transform"
KEY_VALUE_TYPE = "diagnostic_msgs/msg/KeyValue"
STREAM_INFO_TYPE = "realsense_msgs/msg/StreamInfo"

# encoding -> (bytes per pixel, how to make grey)
_ENCODINGS = {
    "rgb8": (3, "rgb"), "bgr8": (3, "bgr"), "rgba8": (4, "rgba"), "bgra8": (4, "bgra"),
    "mono8": (1, "mono8"), "8uc1": (1, "mono8"), "y8": (1, "mono8"),
    "mono16": (2, "mono16"), "16uc1": (2, "mono16"), "y16": (2, "mono16"),
    "yuyv": (2, "yuyv"), "yuy2": (2, "yuyv"), "yuv422_yuy2": (2, "yuyv"),
    "uyvy": (2, "uyvy"), "yuv422": (2, "uyvy"),
}
_CV_CODES = {"rgb": cv2.COLOR_RGB2GRAY, "bgr": cv2.COLOR_BGR2GRAY,
             "rgba": cv2.COLOR_RGBA2GRAY, "bgra": cv2.COLOR_BGRA2GRAY}
SUPPORTED_ENCODINGS = tuple(_ENCODINGS)


# ROS1 wire format through rosbags' Noetic typestore. librealsense appends a float32
# depth_units to every sensor_msgs/Image whose header frame_id is "1" (all Viewer
# recordings since 2.3x), which the typestore's strict ``deserialize_ros1`` rejects as
# a size mismatch; :func:`_deserialize` runs the same message definition but accepts
# trailing bytes after a complete message (never a message cut short).
def _typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended\n", STREAM_INFO_TYPE))
    return ts


_TS = None


def _deserialize(raw, typename: str):
    """A ROS1 message through the typestore, allowing trailing bytes (see above)."""
    global _TS
    if _TS is None:
        _TS = _typestore()
    msgdef = _TS.get_msgdef(typename)
    try:
        msg, pos = msgdef.deserialize_ros1(memoryview(raw), 0, msgdef.cls, _TS)
    except (struct.error, UnicodeDecodeError, IndexError) as exc:
        raise ValueError(f"{typename} message is truncated or damaged ({exc})") from None
    if pos > len(raw):
        raise ValueError(f"{typename} message runs past its end")
    return msg


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _header(raw) -> tuple[int, None]:
    """(stamp in ns, None) of the std_msgs/Header that every stamped message starts with."""
    return _stamp_ns(_deserialize(raw, "std_msgs/msg/Header")), None


@dataclass(frozen=True)
class _Image:
    stamp_ns: int
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: np.ndarray


def _parse_image(raw) -> _Image:
    m = _deserialize(raw, IMAGE_TYPE)
    return _Image(_stamp_ns(m.header), int(m.height), int(m.width), m.encoding, int(m.is_bigendian),
                  int(m.step), m.data)


def _parse_imu(raw) -> tuple[int, np.ndarray, np.ndarray]:
    """(stamp ns, angular_velocity (3,), linear_acceleration (3,)) of a sensor_msgs/Imu."""
    m = _deserialize(raw, IMU_TYPE)
    w, a = m.angular_velocity, m.linear_acceleration
    return _stamp_ns(m.header), np.array([w.x, w.y, w.z]), np.array([a.x, a.y, a.z])


def _parse_camera_info(raw) -> dict:
    m = _deserialize(raw, CAMERA_INFO_TYPE)
    return dict(height=int(m.height), width=int(m.width), distortion_model=m.distortion_model,
                D=np.asarray(m.D, float).copy(), K=np.asarray(m.K, float).copy())


def _parse_transform(raw) -> tuple[np.ndarray, np.ndarray]:
    """(translation (3,), rotation matrix (3, 3)) of a geometry_msgs/Transform."""
    m = _deserialize(raw, TRANSFORM_TYPE)
    t, q = m.translation, m.rotation
    return np.array([t.x, t.y, t.z]), _quat_to_matrix(q.x, q.y, q.z, q.w)


def _parse_key_value(raw) -> tuple[str, str]:
    m = _deserialize(raw, KEY_VALUE_TYPE)
    return m.key, m.value


def _parse_stream_info_fps(raw) -> int:
    return int(_deserialize(raw, STREAM_INFO_TYPE).fps)


def _quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError("zero or non-finite quaternion")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _to_grey(img: _Image) -> np.ndarray:
    """Decode one image message to grey float32 (H, W) in grey levels 0..255."""
    bpp, kind = _ENCODINGS[img.encoding.lower()]
    h, w, step = img.height, img.width, img.step
    if step < w * bpp or len(img.data) < step * h:
        raise ValueError(f"{w}x{h} {img.encoding} needs {w * bpp} bytes a row and {step * h} in all, "
                         f"message has step {step} and {len(img.data)} bytes")
    rows = np.frombuffer(img.data, np.uint8, count=step * h).reshape(h, step)[:, :w * bpp]
    if kind == "mono8":
        return rows.astype(np.float32)
    if kind == "mono16":
        px = np.ascontiguousarray(rows).view(">u2" if img.is_bigendian else "<u2")
        return px.astype(np.float32) / 257.0
    if kind in ("yuyv", "uyvy"):
        return rows.reshape(h, w, 2)[..., 0 if kind == "yuyv" else 1].astype(np.float32)
    return cv2.cvtColor(np.ascontiguousarray(rows).reshape(h, w, bpp), _CV_CODES[kind]).astype(np.float32)

