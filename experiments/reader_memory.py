"""Memory of the footage readers on a long recording: is streaming flat in every layout?

``python -m experiments.reader_memory --frames 20000`` writes one synthetic recording per
layout (footage folder, EuRoC/ASL folder, MJPG video, ROS1 ``.bag`` and rosbag2 ``.db3``
written with rosbags) at a tiny resolution, opens each with :func:`lobula.readers.open_footage`
and streams every frame, printing the resident memory after opening, after the first
10% of frames and at the end. Flat streaming: the end and the 10% figures agree.
A measurement, not a test: it prints figures.
"""
from __future__ import annotations

import argparse
import gc
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def rss_mib() -> float:
    """Resident set size of this process (MiB), from /proc (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


W, H, FPS, IMU_HZ = 32, 24, 30.0, 200.0


def _picture(k: int) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W]
    return ((x * 7 + y * 3 + k) % 256).astype(np.uint8)


def _imu(n: int):
    t = np.arange(0, n / FPS + 0.1, 1 / IMU_HZ)
    acc = np.c_[np.zeros_like(t), -9.81 + 0 * t, 0.1 * np.sin(t)]
    return t, acc, np.zeros((len(t), 3))


def _camera() -> dict:
    return dict(width=W, height=H, fx=30.0, fy=30.0, cx=W / 2, cy=H / 2, frame_rate_hz=FPS)


def _imu_csv(path: Path, n: int) -> None:
    t, a, g = _imu(n)
    rows = ["time_s,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z"]
    rows += [f"{ti:.6f},{x:.5f},{y:.5f},{z:.5f},0,0,0" for ti, (x, y, z) in zip(t, a)]
    path.write_text("\n".join(rows) + "\n")


def make_folder(root: Path, n: int) -> Path:
    d = root / "folder"
    (d / "frames").mkdir(parents=True)
    (d / "camera.json").write_text(json.dumps(_camera()))
    rows = ["frame,time_s,file"]
    for k in range(n):
        cv2.imwrite(str(d / "frames" / f"{k:06d}.png"), _picture(k))
        rows.append(f"{k},{k / FPS:.6f},frames/{k:06d}.png")
    (d / "frames.csv").write_text("\n".join(rows) + "\n")
    _imu_csv(d / "imu.csv", n)
    return d


def make_euroc(root: Path, n: int) -> Path:
    mav = root / "euroc" / "mav0"
    (mav / "cam0" / "data").mkdir(parents=True)
    (mav / "imu0").mkdir(parents=True)
    ident = "T_BS:\n  cols: 4\n  rows: 4\n  data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n"
    (mav / "cam0" / "sensor.yaml").write_text(
        f"%YAML:1.0\n{ident}rate_hz: {FPS:g}\nresolution: [{W}, {H}]\ncamera_model: pinhole\n"
        f"intrinsics: [30.0, 30.0, {W / 2}, {H / 2}]\ndistortion_model: radial-tangential\n"
        f"distortion_coefficients: [-0.1, 0.01, 0.0, 0.0]\n")
    (mav / "imu0" / "sensor.yaml").write_text(f"%YAML:1.0\n{ident}rate_hz: {IMU_HZ:g}\n")
    ns0 = 1_400_000_000_000_000_000
    rows = ["#timestamp [ns],filename"]
    for k in range(n):
        ns = ns0 + round(k / FPS * 1e9)
        cv2.imwrite(str(mav / "cam0" / "data" / f"{ns}.png"), _picture(k))
        rows.append(f"{ns},{ns}.png")
    (mav / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    t, a, g = _imu(n)
    rows = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"]
    rows += [f"{ns0 + round(ti * 1e9)},0,0,0,{x:.5f},{y:.5f},{z:.5f}" for ti, (x, y, z) in zip(t, a)]
    (mav / "imu0" / "data.csv").write_text("\n".join(rows) + "\n")
    return root / "euroc"


def make_video(root: Path, n: int) -> Path:
    d = root / "video"
    d.mkdir()
    wr = cv2.VideoWriter(str(d / "rec.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    for k in range(n):
        wr.write(cv2.cvtColor(_picture(k), cv2.COLOR_GRAY2BGR))
    wr.release()
    (d / "camera.json").write_text(json.dumps(_camera()))
    _imu_csv(d / "imu.csv", n)
    return d / "rec.avi"


def _header(T, ns):
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    cls = T["std_msgs/msg/Header"]
    if "seq" in cls.__dataclass_fields__:    # ROS1
        return cls(seq=0, stamp=stamp, frame_id="1")
    return cls(stamp=stamp, frame_id="1")


def _imu_msg(T, ns, a=(0, 0, 0), w=(0, 0, 0)):
    v3 = T["geometry_msgs/msg/Vector3"]
    return T["sensor_msgs/msg/Imu"](header=_header(T, ns), orientation=T["geometry_msgs/msg/Quaternion"](
        x=0, y=0, z=0, w=1), orientation_covariance=np.zeros(9), angular_velocity=v3(x=w[0], y=w[1], z=w[2]),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=v3(x=a[0], y=a[1], z=a[2]),
        linear_acceleration_covariance=np.zeros(9))


def _info(T, ros1=False):
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    c = _camera()
    arrays = dict(d=np.zeros(5), k=np.array([c["fx"], 0, c["cx"], 0, c["fy"], c["cy"], 0, 0, 1.0]),
                  r=np.eye(3).ravel(), p=np.zeros(12))
    if ros1:
        arrays = {k.upper(): v for k, v in arrays.items()}
    return T["sensor_msgs/msg/CameraInfo"](header=_header(T, 0), height=H, width=W, distortion_model="",
                                           binning_x=0, binning_y=0, roi=roi, **arrays)


def make_bag(root: Path, n: int) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    path = root / "rec.bag"
    t, a, _ = _imu(n)
    pre = "/device_0/sensor_1/Color_0"
    with Writer(path) as w:
        ci = w.add_connection(f"{pre}/info/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        w.write(ci, 0, ts.serialize_ros1(_info(T, ros1=True), "sensor_msgs/msg/CameraInfo"))
        cimg = w.add_connection(f"{pre}/image/data", "sensor_msgs/msg/Image", typestore=ts)
        cacc = w.add_connection("/device_0/sensor_2/Accel_0/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
        events = sorted([(round(k / FPS * 1e9) + 1, 0, k) for k in range(n)]
                        + [(round(ti * 1e9) + 1, 1, j) for j, ti in enumerate(t)])
        for ns, kind, k in events:
            if kind == 0:
                msg = T["sensor_msgs/msg/Image"](header=_header(T, ns), height=H, width=W, encoding="mono8",
                                                 is_bigendian=0, step=W, data=_picture(k).ravel())
                w.write(cimg, ns, ts.serialize_ros1(msg, "sensor_msgs/msg/Image"))
            else:
                w.write(cacc, ns, ts.serialize_ros1(_imu_msg(T, ns, a[k]), "sensor_msgs/msg/Imu"))
    return path


def make_db3(root: Path, n: int) -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    folder = root / "db3"
    t, a, _ = _imu(n)
    pre = "/device_0/sensor_0/Color_0"
    with Writer(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        cc = w.add_connection(f"{pre}/image/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        w.write(cc, 1, ts.serialize_cdr(_info(T), "sensor_msgs/msg/CameraInfo"))
        ci = w.add_connection(f"{pre}/image/data/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        cm = w.add_connection(f"{pre}/image/metadata", "std_msgs/msg/String", typestore=ts)
        ca = w.add_connection("/device_0/sensor_1/Accel_0/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
        cam_ = w.add_connection("/device_0/sensor_1/Accel_0/imu/metadata", "std_msgs/msg/String", typestore=ts)
        events = sorted([(round(k / FPS * 1e9) + 2, 0, k) for k in range(n)]
                        + [(round(ti * 1e9) + 2, 1, j) for j, ti in enumerate(t)])
        for ns, kind, k in events:
            meta = T["std_msgs/msg/String"](data=f"timestamp_domain=Global Time;timestamp={ns / 1e6:.6f};")
            if kind == 0:
                png = np.frombuffer(cv2.imencode(".png", cv2.cvtColor(_picture(k), cv2.COLOR_GRAY2BGR))[1].tobytes(),
                                    np.uint8)
                msg = T["sensor_msgs/msg/CompressedImage"](header=_header(T, ns), format="rgb8; png compressed bgr8",
                                                           data=png)
                w.write(ci, ns, ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
                w.write(cm, ns, ts.serialize_cdr(meta, "std_msgs/msg/String"))
            else:
                w.write(ca, ns, ts.serialize_cdr(_imu_msg(T, ns, a[k]), "sensor_msgs/msg/Imu"))
                w.write(cam_, ns, ts.serialize_cdr(meta, "std_msgs/msg/String"))
    return next(folder.glob("*.db3"))


LAYOUTS = {"folder": make_folder, "euroc": make_euroc, "video": make_video, "bag": make_bag, "db3": make_db3}


def measure(path: Path) -> dict:
    """Open and stream every frame; resident memory (MiB) at each stage and the frames/s."""
    from lobula.readers import open_footage

    gc.collect()
    before = rss_mib()
    t0 = time.perf_counter()
    fo = open_footage(path)
    opened = rss_mib()
    n = len(fo)
    tenth, k = None, 0
    t1 = time.perf_counter()
    peak = opened
    for k, (_, _, img) in enumerate(fo.frames(), 1):
        if k == n // 10:
            tenth = rss_mib()
        if k % 500 == 0:
            peak = max(peak, rss_mib())
    end = rss_mib()
    return dict(frames=k, of=n, rss_before=before, rss_open=opened, rss_10pct=tenth, rss_end=end,
                rss_peak=max(peak, end), growth_after_10pct=end - tenth, open_s=t1 - t0,
                stream_fps=k / (time.perf_counter() - t1), kind=fo.kind)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--frames", type=int, default=20000, help="frames per recording")
    p.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=list(LAYOUTS), help="layouts to measure")
    p.add_argument("--dir", default=None, help="where to write the recordings (default: a temporary folder)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        print(f"{args.frames} frames of {W}x{H} per layout; resident memory in MiB")
        print(f"{'layout':<8} {'kind':<14} {'frames':>7} {'open':>7} {'at 10%':>7} {'end':>7} {'peak':>7} "
              f"{'growth':>7} {'open s':>7} {'frames/s':>9}")
        for name in args.layouts:
            path = LAYOUTS[name](Path(tmp), args.frames)
            m = measure(path)
            print(f"{name:<8} {m['kind']:<14} {m['frames']:>7} {m['rss_open']:>7.1f} {m['rss_10pct']:>7.1f} "
                  f"{m['rss_end']:>7.1f} {m['rss_peak']:>7.1f} {m['growth_after_10pct']:>+7.1f} {m['open_s']:>7.2f} "
                  f"{m['stream_fps']:>9.0f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
