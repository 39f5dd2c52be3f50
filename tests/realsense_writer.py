"""Write a genuine RealSense recording with librealsense itself (pyrealsense2's software_device + recorder).

``record(folder, out)`` feeds a footage folder's frames (as rgb8 colour) and IMU (accel at
its own rate, gyro at another) into a ``software_device`` recorded by ``rs.recorder``: the
installed librealsense decides the format (≤ 2.57: ROS1 ``.bag``; ≥ 2.58: rosbag2 ``.db3``).
Run as a script (``python tests/realsense_writer.py FOLDER OUT [GYRO_NPZ]``) so that a second
pyrealsense2 version can write the other format from a subprocess (PYTHONPATH).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

T0_MS = 1_700_000_000_000.0   # device (global) time of the first frame, ms


def librealsense_version() -> tuple[int, int]:
    import pyrealsense2 as rs
    v = getattr(rs, "__version__", None)
    if v is None:
        from pyrealsense2 import pyrealsense2 as _rs
        v = getattr(_rs, "__version__", "0.0")
    major, minor = (int(x) for x in v.split(".")[:2])
    return major, minor


def writes(suffix: str) -> bool:
    """Whether the installed librealsense records to this suffix (.bag up to 2.57, .db3 from 2.58)."""
    v = librealsense_version()
    return (v >= (2, 58)) == (suffix == ".db3")


def record(folder: str | Path, out: str | Path, gyro_t: np.ndarray, gyro: np.ndarray) -> None:
    import cv2
    import pyrealsense2 as rs

    from lobula.readers import open_footage

    fo = open_footage(folder)
    cam = fo.camera
    sd = rs.software_device()
    colour = sd.add_sensor("RGB Camera")
    motion = sd.add_sensor("Motion Module")
    intr = rs.intrinsics()
    intr.width, intr.height = cam.width, cam.height
    intr.fx, intr.fy, intr.ppx, intr.ppy = cam.fx, cam.fy, cam.cx, cam.cy
    intr.model, intr.coeffs = rs.distortion.brown_conrady, [0.0] * 5
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = rs.stream.color, 0, 0
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = cam.width, cam.height, int(round(cam.frame_rate_hz)), 3, rs.format.rgb8
    vs.intrinsics = intr
    cp = colour.add_video_stream(vs).as_video_stream_profile()
    mi = rs.motion_device_intrinsic()
    mi.data = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0]]
    mi.noise_variances, mi.bias_variances = [0.0] * 3, [0.0] * 3

    def motion_stream(kind, uid, fps):
        m = rs.motion_stream()
        m.type, m.index, m.uid, m.fps, m.fmt, m.intrinsics = kind, 0, uid, fps, rs.format.motion_xyz32f, mi
        return motion.add_motion_stream(m).as_motion_stream_profile()

    acc_rate = int(round(1 / np.median(np.diff(fo.imu.time_s))))
    gyro_rate = int(round(1 / np.median(np.diff(gyro_t))))
    ap, gp = motion_stream(rs.stream.accel, 1, acc_rate), motion_stream(rs.stream.gyro, 2, gyro_rate)
    recorder = rs.recorder(str(out), sd)
    colour.open(cp)
    colour.start(lambda f: None)
    motion.open([ap, gp])
    motion.start(lambda f: None)
    events = [(float(t), 0, k) for k, t in enumerate(fo.times)]
    events += [(float(t), 1, k) for k, t in enumerate(fo.imu.time_s)]
    events += [(float(t), 2, k) for k, t in enumerate(gyro_t)]
    events.sort()
    frames = fo.frames()
    keep = []   # librealsense reads the pixel buffers after on_video_frame returns
    for t, kind, k in events:
        ms = T0_MS + t * 1e3
        if kind == 0:
            _, _, grey = next(frames)
            rgb = np.ascontiguousarray(cv2.cvtColor(np.clip(np.round(grey), 0, 255).astype(np.uint8),
                                                    cv2.COLOR_GRAY2RGB))
            keep.append(rgb)
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride = rgb, 3, 3 * cam.width
            f.timestamp, f.domain, f.frame_number, f.profile = ms, rs.timestamp_domain.global_time, k, cp
            colour.on_video_frame(f)
        else:
            v = fo.imu.accel[k] if kind == 1 else gyro[k]
            vec = rs.vector()
            vec.x, vec.y, vec.z = (float(x) for x in v)
            f = rs.software_motion_frame()
            f.data, f.timestamp, f.domain, f.frame_number = vec, ms, rs.timestamp_domain.global_time, k
            f.profile = ap if kind == 1 else gp
            motion.on_motion_frame(f)
    colour.stop()
    colour.close()
    motion.stop()
    motion.close()
    recorder.pause()
    del recorder


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    d = np.load(sys.argv[3])
    record(sys.argv[1], sys.argv[2], d["t"], d["gyro"])
