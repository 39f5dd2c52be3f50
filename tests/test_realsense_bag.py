"""RealSense ROS1 bags (RealSense Viewer layout) as footage: synthetic bags written with rosbags.

Every bag here is written the way librealsense's recorder writes one: static info
(StreamInfo, CameraInfo, extrinsics) at bag time 0, frames on
/device_0/sensor_1/Color_0/image/data with the trailing float32 depth_units that
librealsense appends to each Image, a mono16 depth stream beside it, and the
accelerometer and gyroscope on their own topics at their own rates.
"""
import inspect
import itertools
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from lobula.camera import PinholeCamera  # noqa: E402
from lobula.readers import open_footage, realsense_bag  # noqa: E402
from lobula.readers.core import Footage, FootageError, read_frame  # noqa: E402
from lobula.readers.realsense_bag import BagFootage, open_realsense_bag  # noqa: E402

TS = get_typestore(Stores.ROS1_NOETIC)
TS.register(get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended\n", "realsense_msgs/msg/StreamInfo"))
T = TS.types
T0 = 1_700_000_000_123_456_789          # first frame's header stamp (ns), global time
K = dict(fx=61.5, fy=61.75, cx=31.6, cy=24.2)
COLOR = "/device_0/sensor_1/Color_0"
ACCEL = "/device_0/sensor_2/Accel_0"
GYRO = "/device_0/sensor_2/Gyro_0"
DEPTH = "/device_0/sensor_0/Depth_0"


def accel_fn(t):
    t = np.asarray(t, float)
    return np.stack([0.1 * np.sin(2 * np.pi * t), -9.81 + 0.05 * t, 0.3 * np.cos(2 * np.pi * t)], -1)


def gyro_fn(t):   # linear in t, so linear interpolation is exact
    t = np.asarray(t, float)
    return np.stack([0.01 + 0.02 * t, -0.03 * t, 0.5 * t], -1)


def pattern(k, h=48, w=64):
    """A known RGB test image for frame k."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(4 * x + 7 * k) % 256, (5 * y + 3 * k) % 256, (x * y + 11 * k) % 256], -1).astype(np.uint8)


def rot(axis, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def quat(r):
    w = np.sqrt(1 + np.trace(r)) / 2
    return T["geometry_msgs/msg/Quaternion"](x=(r[2, 1] - r[1, 2]) / (4 * w), y=(r[0, 2] - r[2, 0]) / (4 * w),
                                              z=(r[1, 0] - r[0, 1]) / (4 * w), w=w)


def header(ns, seq=0, frame_id="1"):
    return T["std_msgs/msg/Header"](seq=seq, stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame_id)


def encode(rgb, encoding, pad=0):
    """(bytes, step, is_bigendian) of an RGB test image in a RealSense/ROS encoding, rows padded by `pad` bytes."""
    h, w, _ = rgb.shape
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    e = encoding.lower()
    big = 0
    if e == "rgb8":
        px = rgb
    elif e == "bgr8":
        px = rgb[..., ::-1]
    elif e in ("rgba8", "bgra8"):
        px = np.concatenate([rgb if e == "rgba8" else rgb[..., ::-1], np.full((h, w, 1), 200, np.uint8)], -1)
    elif e in ("mono8", "8uc1"):
        px = rgb[..., 1]
    elif e in ("mono16", "16uc1", "mono16be"):
        v = rgb[..., 1].astype(np.uint16) * 257 + (rgb[..., 0] % 7)
        big = int(e == "mono16be")
        px = v.astype(">u2" if big else "<u2").view(np.uint8).reshape(h, w * 2)
    elif e in ("yuyv", "uyvy", "yuv422"):
        chroma = np.where(np.arange(w) % 2 == 0, 90, 170).astype(np.uint8)[None, :].repeat(h, 0)
        pair = (grey, chroma) if e == "yuyv" else (chroma, grey)
        px = np.stack(pair, -1)
    else:  # unsupported encodings: any bytes
        px = rgb[..., 0]
    rows = px.reshape(h, -1)
    if pad:
        rows = np.concatenate([rows, np.full((h, pad), 255, np.uint8)], 1)
    return rows.tobytes(), rows.shape[1], big


def expected_grey(rgb, encoding):
    e = encoding.lower()
    if e in ("mono8", "8uc1"):
        return rgb[..., 1].astype(np.float32)
    if e in ("mono16", "16uc1", "mono16be"):
        return (rgb[..., 1].astype(np.float32) * 257 + (rgb[..., 0] % 7)) / 257.0
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)


def image_raw(ns, seq, rgb, encoding, pad=0, depth_units=True):
    """A serialised sensor_msgs/Image as librealsense writes it (frame_id "1" + trailing float32 depth_units)."""
    data, step, big = encode(rgb, encoding, pad)
    h, w, _ = rgb.shape
    msg = T["sensor_msgs/msg/Image"](header=header(ns, seq), height=h, width=w,
                                     encoding="mono16" if encoding.lower() == "mono16be" else encoding,
                                     is_bigendian=big, step=step, data=np.frombuffer(data, np.uint8))
    raw = bytes(TS.serialize_ros1(msg, "sensor_msgs/msg/Image"))
    return raw + struct.pack("<f", 0.001) if depth_units else raw


def imu_raw(ns, seq, lin=(0, 0, 0), ang=(0, 0, 0)):
    v3 = T["geometry_msgs/msg/Vector3"]
    msg = T["sensor_msgs/msg/Imu"](header=header(ns, seq), orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
                                   orientation_covariance=np.zeros(9), angular_velocity=v3(x=ang[0], y=ang[1], z=ang[2]),
                                   angular_velocity_covariance=np.zeros(9),
                                   linear_acceleration=v3(x=lin[0], y=lin[1], z=lin[2]),
                                   linear_acceleration_covariance=np.zeros(9))
    return bytes(TS.serialize_ros1(msg, "sensor_msgs/msg/Imu"))


def ser(msg, typename):
    return bytes(TS.serialize_ros1(msg, typename))


def write_bag(path, n=30, fps=30, h=48, w=64, encoding="rgb8", pad=0, images=None, frame_ns=None,
              accel_hz=250.0, gyro_hz=400.0, accel_span=(-0.05, None), gyro_span=(-0.03, None), accel_ns=None,
              with_image=True, with_accel=True, with_gyro=True, with_info=True, info_size=None, tf=None,
              depth=True, compression=None, layout="viewer", extra_accel=()):
    """Write a RealSense-style bag; returns what was written (stamps in ns, values)."""
    path = Path(path)
    if images is None:
        images = [pattern(k, h, w) for k in range(n)]
    n = len(images)
    if frame_ns is None:
        frame_ns = T0 + np.round(np.arange(n) / fps * 1e9).astype(np.int64)
    dur = n / fps
    out = dict(frame_ns=np.asarray(frame_ns, np.int64), images=images)
    msgs = []   # (bag time ns, topic, msgtype, raw)
    bag0 = T0 - 200_000_000   # the Viewer's bag clock: capture time since the recording started

    def at(ns):
        return int(ns - bag0)

    img_topic = f"{COLOR}/image/data" if layout == "viewer" else "/camera/color/image_raw"
    info_topic = f"{COLOR}/info/camera_info" if layout == "viewer" else "/camera/color/camera_info"
    if with_image:
        for k, (ns, img) in enumerate(zip(frame_ns, images)):
            # bag record time: arrival order (nominal frame time + 2 ms), whatever the header stamp says
            arrival = at(T0) + round(k / fps * 1e9) + 2_000_000
            msgs.append((arrival, img_topic, "sensor_msgs/msg/Image", image_raw(int(ns), k, img, encoding, pad)))
            if layout == "viewer" and k < 3:
                kv = T["diagnostic_msgs/msg/KeyValue"](key="timestamp_domain", value="Global Time")
                msgs.append((arrival, f"{COLOR}/image/metadata", "diagnostic_msgs/msg/KeyValue",
                             ser(kv, "diagnostic_msgs/msg/KeyValue")))
    if with_info and layout == "viewer":
        msgs.append((0, f"{COLOR}/info", "realsense_msgs/msg/StreamInfo",
                     ser(T["realsense_msgs/msg/StreamInfo"](fps=fps, encoding=encoding, is_recommended=True),
                         "realsense_msgs/msg/StreamInfo")))
    if with_info:
        ih, iw = info_size or (h, w)
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        info = T["sensor_msgs/msg/CameraInfo"](
            header=header(0), height=ih, width=iw, distortion_model="Inverse Brown Conrady", D=np.zeros(5),
            K=np.array([K["fx"], 0, K["cx"], 0, K["fy"], K["cy"], 0, 0, 1.0]), R=np.zeros(9), P=np.zeros(12),
            binning_x=0, binning_y=0, roi=roi)
        msgs.append((0, info_topic, "sensor_msgs/msg/CameraInfo", ser(info, "sensor_msgs/msg/CameraInfo")))
    if depth and layout == "viewer":
        for k in range(3):
            d = np.full((h, w), 1000 + k, np.uint16)
            msg = T["sensor_msgs/msg/Image"](header=header(T0 + k * 33_000_000, k), height=h, width=w,
                                             encoding="mono16", is_bigendian=0, step=2 * w,
                                             data=d.view(np.uint8).ravel())
            msgs.append((at(T0) + k * 1000 + 1, f"{DEPTH}/image/data", "sensor_msgs/msg/Image",
                         ser(msg, "sensor_msgs/msg/Image") + struct.pack("<f", 0.001)))
    if layout == "viewer":
        msgs.append((0, "/file_version", "std_msgs/msg/UInt32", ser(T["std_msgs/msg/UInt32"](data=3),
                                                                  "std_msgs/msg/UInt32")))
    if tf:
        for prefix, r in tf.items():
            tr = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=0.01, y=-0.005, z=0.02),
                                                  rotation=quat(r))
            msgs.append((0, f"{prefix}/tf/0", "geometry_msgs/msg/Transform", ser(tr, "geometry_msgs/msg/Transform")))
    united = layout == "ros"
    if with_accel:
        if accel_ns is None:
            a0, a1 = accel_span
            accel_ns = T0 + np.round(np.arange(a0, (dur if a1 is None else a1), 1 / accel_hz) * 1e9).astype(np.int64)
        t = (np.asarray(accel_ns) - T0) / 1e9
        out.update(accel_ns=np.asarray(accel_ns, np.int64), accel=accel_fn(t))
        topic = "/camera/imu" if united else f"{ACCEL}/imu/data"
        # bag record times in arrival order, even where a header stamp goes back
        arrival = np.maximum.accumulate([at(int(ns)) for ns in accel_ns]) + np.arange(len(accel_ns))
        for k, (ns, a) in enumerate(zip(accel_ns, out["accel"])):
            g = gyro_fn((ns - T0) / 1e9) if united else (0, 0, 0)
            msgs.append((int(arrival[k]), topic, "sensor_msgs/msg/Imu", imu_raw(int(ns), k, a, g)))
        for ns, a in extra_accel:
            msgs.append((at(int(ns)), topic, "sensor_msgs/msg/Imu", imu_raw(int(ns), 0, a)))
    if with_gyro and not united:
        g0, g1 = gyro_span
        gyro_ns = T0 + np.round(np.arange(g0, (dur if g1 is None else g1), 1 / gyro_hz) * 1e9).astype(np.int64)
        out.update(gyro_ns=gyro_ns, gyro=gyro_fn((gyro_ns - T0) / 1e9))
        for k, (ns, g) in enumerate(zip(gyro_ns, out["gyro"])):
            msgs.append((at(int(ns)), f"{GYRO}/imu/data", "sensor_msgs/msg/Imu", imu_raw(int(ns), k, ang=g)))
    if layout == "ros" and depth:
        msg = T["sensor_msgs/msg/Image"](header=header(T0), height=h, width=w, encoding="16UC1", is_bigendian=0,
                                         step=2 * w, data=np.zeros(2 * h * w, np.uint8))
        msgs.append((at(T0), "/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", ser(msg, "sensor_msgs/msg/Image")))

    msgs.sort(key=lambda m: m[0])
    writer = Writer(path)
    if compression:
        writer.set_compression(Writer.CompressionFormat[compression])
    writer.open()
    conns = {}
    for t_bag, topic, typ, raw in msgs:
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, typ, typestore=TS)
        writer.write(conns[topic], max(0, t_bag), raw)
    writer.close()
    return out


# ------------------------------------------------------------------ reading
def test_viewer_bag_gives_intrinsics_frame_count_and_header_times(tmp_path):
    bag = tmp_path / "rec.bag"
    w = write_bag(bag)
    fo = open_realsense_bag(bag)
    assert isinstance(fo, BagFootage) and isinstance(fo, Footage) and fo.kind == "realsense-bag"
    assert fo.topic == f"{COLOR}/image/data" and fo.encoding == "rgb8"    # colour, not the depth stream
    assert fo.camera == PinholeCamera(64, 48, K["fx"], K["fy"], K["cx"], K["cy"], 30.0)
    assert len(fo) == 30 and len(fo.files) == 30 and fo.files[7].stem == "000007" and fo.files[-1].stem == "000029"
    np.testing.assert_array_equal(fo.times, (w["frame_ns"] - T0) / 1e9)
    assert fo.times[0] == 0.0 and fo.time_origin_s == pytest.approx(T0 / 1e9)
    assert fo.truth is None and fo.depth_map(0) is None
    assert "Global Time" in fo.notes[0] and "header stamps" in fo.notes[0]
    # Each image carries librealsense's trailing depth_units, which a strict deserialiser refuses.
    with pytest.raises(Exception):
        TS.deserialize_ros1(image_raw(T0, 0, pattern(0), "rgb8"), "sensor_msgs/msg/Image")


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1", "mono16", "16UC1",
                                      "mono16be", "YUYV", "uyvy", "yuv422"])
def test_every_encoding_decodes_to_the_expected_grey(tmp_path, encoding):
    images = [pattern(k) for k in range(3)]
    bag = tmp_path / "enc.bag"
    write_bag(bag, images=images, encoding=encoding, pad=6, with_gyro=False)   # padded rows too
    got = list(open_realsense_bag(bag).frames())
    assert [i for i, _, _ in got] == [0, 1, 2]
    for (_, _, img), rgb in zip(got, images):
        assert img.dtype == np.float32 and img.shape == (48, 64)
        np.testing.assert_array_equal(img, expected_grey(rgb, encoding))
        if encoding in ("rgb8", "bgr8"):
            luma = rgb.astype(float) @ [0.299, 0.587, 0.114]
            assert np.abs(img - luma).max() <= 0.51


def test_rgb_frames_match_the_folder_reader(tmp_path):
    """Grey from an rgb8 bag equals read_frame on a PNG of the same picture."""
    rgb = pattern(5)
    bag = tmp_path / "one.bag"
    write_bag(bag, images=[rgb, pattern(6)])
    cv2.imwrite(str(tmp_path / "f.png"), rgb[..., ::-1])
    _, _, img = next(open_realsense_bag(bag).frames())
    np.testing.assert_array_equal(img, read_frame(tmp_path / "f.png"))


def test_frames_stream_decoding_only_what_is_read(tmp_path, monkeypatch):
    bag = tmp_path / "s.bag"
    w = write_bag(bag, n=40)
    fo = open_realsense_bag(bag)
    decoded = []
    real = realsense_bag._to_grey
    monkeypatch.setattr(realsense_bag, "_to_grey", lambda img: decoded.append(img.stamp_ns) or real(img))
    assert not decoded                                       # opening decodes no image
    gen = fo.frames()
    assert inspect.isgenerator(gen)
    first5 = list(itertools.islice(gen, 5))
    assert len(decoded) == 5 and [i for i, _, _ in first5] == list(range(5))
    gen.close()
    part = list(fo.frames(10, 13))
    assert [i for i, _, _ in part] == [10, 11, 12] and len(decoded) == 8
    assert decoded[-3:] == list(w["frame_ns"][10:13])
    every = list(fo.frames())
    assert len(every) == 40 and len(decoded) == 48
    for i, t, img in part:
        assert t == fo.times[i]
        np.testing.assert_array_equal(img, every[i][2])
        np.testing.assert_array_equal(img, expected_grey(pattern(i), "rgb8"))
    assert list(fo.frames(38, 99))[-1][0] == 39 and list(fo.frames(5, 5)) == []


@pytest.mark.parametrize("accel_hz,gyro_hz", [(250.0, 400.0), (63.0, 200.0)])
def test_imu_is_what_was_written_on_the_accel_time_base(tmp_path, accel_hz, gyro_hz):
    bag = tmp_path / "imu.bag"
    # gyro starts 20 ms after the accelerometer and stops 0.1 s before it: those accel samples go
    w = write_bag(bag, accel_hz=accel_hz, gyro_hz=gyro_hz, accel_span=(-0.05, 1.0), gyro_span=(-0.03, 0.9))
    fo = open_realsense_bag(bag)
    imu = fo.imu
    keep = (w["accel_ns"] >= w["gyro_ns"][0]) & (w["accel_ns"] <= w["gyro_ns"][-1])
    assert 0 < (~keep).sum() and imu.time_s.shape == (keep.sum(),)
    np.testing.assert_array_equal(imu.time_s, (w["accel_ns"][keep] - T0) / 1e9)   # same clock as the frames
    np.testing.assert_array_equal(imu.accel, w["accel"][keep])                     # exactly as written
    np.testing.assert_allclose(imu.gyro, gyro_fn(imu.time_s), atol=1e-12)            # interpolated (exact: linear)
    assert imu.accel.shape == imu.gyro.shape == (keep.sum(), 3)
    note = fo.notes[1]
    assert f"({accel_hz:.0f} Hz) is the time base" in note and f"({gyro_hz:.0f} Hz) linearly interpolated" in note
    assert f"{(~keep).sum()} accelerometer samples outside its span dropped" in note
    assert "librealsense reports" in note and "x right, y down, z forward" in note
    assert ACCEL in imu.source and GYRO in imu.source


def test_imu_extrinsics_rotate_into_the_colour_frame(tmp_path):
    bag = tmp_path / "tf.bag"
    r_col, r_imu = rot(0, 2.0), rot(2, 90.0)   # reference -> stream rotations (p_stream = R p_ref + t)
    w = write_bag(bag, tf={COLOR: r_col, ACCEL: r_imu, GYRO: r_imu}, gyro_span=(-0.06, 1.05))
    imu = open_realsense_bag(bag).imu
    r = r_col @ r_imu.T                           # imu -> reference -> colour
    np.testing.assert_allclose(open_realsense_bag(bag).imu_to_camera, r, atol=1e-12)
    np.testing.assert_allclose(imu.accel, w["accel"] @ r.T, atol=1e-12)
    np.testing.assert_allclose(imu.gyro, gyro_fn(imu.time_s) @ r.T, atol=1e-12)
    # gravity's reading (−9.81 on the IMU's y) lands on the colour frame's x after the 90° turn about z
    assert np.all(imu.accel[:, 0] < -9.7)
    note = open_realsense_bag(bag).notes[1]
    assert "accelerometer rotated 90.02 deg" in note or "accelerometer rotated 89.98 deg" in note


def test_realsense_ros_layout_with_one_united_imu_topic(tmp_path):
    bag = tmp_path / "ros.bag"
    w = write_bag(bag, layout="ros", encoding="bgr8", n=12)
    fo = open_realsense_bag(bag)
    assert fo.topic == "/camera/color/image_raw" and len(fo) == 12
    assert fo.camera.fx == K["fx"] and fo.camera.frame_rate_hz == pytest.approx(30.0, rel=1e-6)
    np.testing.assert_array_equal(fo.imu.accel, w["accel"])
    np.testing.assert_allclose(fo.imu.gyro, gyro_fn((w["accel_ns"] - T0) / 1e9), atol=1e-15)
    np.testing.assert_array_equal(next(fo.frames(3))[2], expected_grey(pattern(3), "bgr8"))


def test_lz4_compressed_bag_and_a_chosen_stream(tmp_path):
    bag = tmp_path / "lz4.bag"
    write_bag(bag, n=8, compression="LZ4")
    fo = open_realsense_bag(bag, stream="Color_0")
    assert len(list(fo.frames())) == 8
    with pytest.raises(FootageError, match=r"no image stream matches 'Infrared_1'.*Color_0"):
        open_realsense_bag(bag, stream="Infrared_1")


def test_verbatim_repeated_imu_messages_are_dropped(tmp_path):
    bag = tmp_path / "dup.bag"
    t = (T0 + 8_000_000 - T0) / 1e9
    w = write_bag(bag, accel_span=(0.0, None), gyro_span=(-0.01, 1.05), extra_accel=[(T0 + 8_000_000, accel_fn(t))])
    imu = open_realsense_bag(bag).imu
    np.testing.assert_array_equal(imu.time_s, (w["accel_ns"] - T0) / 1e9)


def test_zero_header_stamps_fall_back_to_bag_record_times(tmp_path):
    bag = tmp_path / "zero.bag"
    write_bag(bag, n=6, frame_ns=np.zeros(6, np.int64), with_accel=False, with_gyro=False)
    fo = open_realsense_bag(bag, require_imu=False)
    assert fo.time_source == "bag" and "bag record times" in fo.notes[0]
    np.testing.assert_allclose(fo.times, np.arange(6) / 30, atol=1e-9)
    assert [i for i, _, _ in fo.frames(2)] == [2, 3, 4, 5]


# ------------------------------------------------------------------ errors
def test_missing_not_a_bag_and_corrupt_files_are_clear_errors(tmp_path):
    with pytest.raises(FootageError, match=r"absent\.bag: file not found"):
        open_realsense_bag(tmp_path / "absent.bag")
    txt = tmp_path / "notes.bag"
    txt.write_text("frame,time_s,file\n")
    with pytest.raises(FootageError, match=r"notes\.bag: not a readable ROS1 bag"):
        open_realsense_bag(txt)
    with pytest.raises(FootageError, match=r"is a folder"):
        open_realsense_bag(tmp_path)
    good = tmp_path / "good.bag"
    write_bag(good, n=10)
    data = good.read_bytes()
    for frac in (0.5, 0.97):
        cut = tmp_path / f"cut{frac}.bag"
        cut.write_bytes(data[:int(len(data) * frac)])
        with pytest.raises(FootageError, match=rf"cut{frac}\.bag: .*(re-record|reindex)"):
            open_realsense_bag(cut)
    # damaged bytes inside a compressed chunk: the decompressor's own error becomes a FootageError
    bz2 = tmp_path / "bz2.bag"
    write_bag(bz2, n=10, compression="BZ2")
    data = bytearray(bz2.read_bytes())
    at = int(len(data) * 0.4)
    data[at:at + 64] = b"\xaa" * 64
    bz2.write_bytes(bytes(data))
    with pytest.raises(FootageError, match=r"bz2\.bag: the bag is damaged .*re-record"):
        open_realsense_bag(bz2)


def test_no_image_topic(tmp_path):
    bag = tmp_path / "imu_only.bag"
    write_bag(bag, with_image=False)
    with pytest.raises(FootageError, match=r"imu_only\.bag: no colour or infrared image topic.*only "
                                           r"/device_0/sensor_0/Depth_0/image/data.*record the Color"):
        open_realsense_bag(bag)


def test_no_imu_topics(tmp_path):
    bag = tmp_path / "no_imu.bag"
    write_bag(bag, with_accel=False, with_gyro=False)
    with pytest.raises(FootageError, match=r"no_imu\.bag: no accelerometer topic.*velocity needs forward "
                                           r"acceleration.*--accel-from-truth cannot stand in"):
        open_realsense_bag(bag)
    fo = open_realsense_bag(bag, require_imu=False)
    assert fo.imu is None and len(fo) == 30
    gyro_only = tmp_path / "gyro_only.bag"
    write_bag(gyro_only, with_accel=False)
    with pytest.raises(FootageError, match=r"no accelerometer topic.*gyroscope only"):
        open_realsense_bag(gyro_only)


def test_non_increasing_stamps(tmp_path):
    ns = T0 + np.round(np.arange(10) / 30 * 1e9).astype(np.int64)
    ns[[4, 5]] = ns[[5, 4]]
    bag = tmp_path / "swap.bag"
    write_bag(bag, n=10, frame_ns=ns)
    with pytest.raises(FootageError, match=r"swap\.bag: image time stamps on .*Color_0/image/data do not "
                                           r"increase: message 5 \(counting from 0\) is stamped 1700000000\.256"):
        open_realsense_bag(bag)
    acc = T0 + np.round(np.arange(0, 0.3, 0.004) * 1e9).astype(np.int64)
    acc[20] = acc[19] - 1_000_000                  # 1 ms before its predecessor
    bag = tmp_path / "acc.bag"
    write_bag(bag, n=9, accel_ns=acc)
    with pytest.raises(FootageError, match=r"accelerometer time stamps on .*Accel_0/imu/data do not increase: message 20 "):
        open_realsense_bag(bag)


def test_missing_or_mismatched_intrinsics_and_unsupported_encoding(tmp_path):
    bag = tmp_path / "noinfo.bag"
    write_bag(bag, n=5, with_info=False)
    with pytest.raises(FootageError, match=r"no sensor_msgs/CameraInfo .* give them with --camera FILE"):
        open_realsense_bag(bag)
    cam = PinholeCamera(64, 48, 60.0, 60.0, 32.0, 24.0, 30.0)
    assert open_realsense_bag(bag, camera=cam).camera == cam
    bag = tmp_path / "size.bag"
    write_bag(bag, n=5, info_size=(480, 640))
    with pytest.raises(FootageError, match=r"images are 64x48 but the intrinsics .* are for 640x480"):
        open_realsense_bag(bag)
    bag = tmp_path / "bayer.bag"
    write_bag(bag, n=3, encoding="bayer_rggb8")
    with pytest.raises(FootageError, match=r"encoding 'bayer_rggb8'; supported: rgb8"):
        open_realsense_bag(bag)


# ------------------------------------------------------------------ the velocity pipeline
def test_velocity_on_a_bag_equals_velocity_on_its_folder(tmp_path):
    """A synthetic track run written into a Viewer-style bag gives the folder's v̂."""
    from lobula.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from stimuli.track import TrackRunConfig, make_track_run

    folder = make_track_run(tmp_path / "run", TrackRunConfig(profile=None, start_s=5, duration_s=2, scale=0.25),
                            progress=False)
    ff = open_footage(folder)
    cam = ff.camera
    images = [np.repeat(img.astype(np.uint8)[..., None], 3, -1) for _, _, img in ff.frames()]   # grey as rgb8
    frame_ns = T0 + np.round(ff.times * 1e9).astype(np.int64)
    bag = tmp_path / "run.bag"
    imu_ns = T0 + np.round(ff.imu.time_s * 1e9).astype(np.int64)
    # write the folder's IMU as the Viewer would: accel and gyro topics (here at the same 250 Hz)
    msgs = []
    for k, (ns, a, g) in enumerate(zip(imu_ns, ff.imu.accel, ff.imu.gyro)):
        msgs.append((int(ns), f"{ACCEL}/imu/data", imu_raw(int(ns), k, a)))
        msgs.append((int(ns) + 1, f"{GYRO}/imu/data", imu_raw(int(ns), k, ang=g)))
    for k, (ns, img) in enumerate(zip(frame_ns, images)):
        msgs.append((int(ns), f"{COLOR}/image/data", image_raw(int(ns), k, img, "rgb8")))
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    info = T["sensor_msgs/msg/CameraInfo"](header=header(0), height=cam.height, width=cam.width, distortion_model="",
                                           D=np.zeros(0), K=np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1]),
                                           R=np.zeros(9), P=np.zeros(12), binning_x=0, binning_y=0, roi=roi)
    with Writer(bag) as writer:
        c_info = writer.add_connection(f"{COLOR}/info/camera_info", "sensor_msgs/msg/CameraInfo", typestore=TS)
        c_si = writer.add_connection(f"{COLOR}/info", "realsense_msgs/msg/StreamInfo", typestore=TS)
        writer.write(c_info, 0, ser(info, "sensor_msgs/msg/CameraInfo"))
        writer.write(c_si, 0, ser(T["realsense_msgs/msg/StreamInfo"](fps=int(cam.frame_rate_hz), encoding="rgb8",
                                                                     is_recommended=True),
                                  "realsense_msgs/msg/StreamInfo"))
        conns = {}
        for t_bag, topic, raw in sorted(msgs, key=lambda m: m[0]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, "sensor_msgs/msg/Imu" if "imu" in topic
                                                     else "sensor_msgs/msg/Image", typestore=TS)
            writer.write(conns[topic], t_bag - T0 + 1_000_000, raw)
    fb = open_realsense_bag(bag)
    assert fb.camera == cam and len(fb) == len(ff)
    np.testing.assert_array_equal(fb.times, ff.times)
    np.testing.assert_array_equal(fb.imu.time_s, ff.imu.time_s)
    np.testing.assert_array_equal(fb.imu.accel, ff.imu.accel)
    np.testing.assert_array_equal(fb.imu.gyro, ff.imu.gyro)

    cfg = VelocityConfig()
    v_folder = estimate_velocity(ff, cfg, progress=False)
    v_bag = estimate_velocity(fb, VelocityConfig(), progress=False)
    assert v_bag.attrs["footage_kind"] == "realsense-bag" and "RealSense bag" in v_bag.attrs["notes"]
    assert np.isfinite(v_bag.v_hat.values).sum() > 10
    np.testing.assert_array_equal(v_bag.time.values, v_folder.time.values)
    np.testing.assert_array_equal(v_bag.r.values, v_folder.r.values)
    np.testing.assert_array_equal(v_bag.v_hat.values, v_folder.v_hat.values)


def test_open_footage_and_the_cli_take_a_bag(tmp_path, capsys):
    from experiments.cli import main
    from lobula.readers import open_footage

    bag = tmp_path / "rec.bag"
    write_bag(bag)
    fo = open_footage(bag)
    assert fo.kind == "realsense-bag" and len(fo) == 30
    assert main(["velocity", str(tmp_path / "missing.bag"), "--out", str(tmp_path / "o.nc"), "--quiet"]) == 2
    assert "missing.bag" in capsys.readouterr().err


def test_calibrate_camera_on_a_bag_without_imu_names_the_gyro(tmp_path, capsys):
    from experiments.cli import main

    bag = tmp_path / "no_imu.bag"
    write_bag(bag, with_accel=False, with_gyro=False)
    assert main(["calibrate-camera", str(bag), "--out", str(tmp_path / "camera.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no_imu.bag: calibrate-camera measures the focal length against the gyro" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "camera.json").exists()
