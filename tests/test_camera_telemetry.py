"""Videos with their camera's own motion log (lobula.readers.camera_telemetry): a Gyroflow .gcsv beside a
synthetic run's video gives back the run's IMU exactly, and the same velocity as the run's imu.csv; bad logs
are one clear line."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from experiments.cli import main
from lobula.readers import open_footage
from lobula.readers.core import FootageError
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run

pytest.importorskip("telemetry_parser", reason="telemetry-parser has wheels for CPython 3.8-3.12 only")
G = 9.80665


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """2 s of a small (160×120) synthetic run in motion, with exact truth."""
    cfg = TrackRunConfig(profile=None, start_s=6.0, duration_s=2.0, scale=0.25, scene=SceneConfig(seed=2))
    return make_track_run(tmp_path_factory.mktemp("run") / "run", cfg, progress=False)


def write_gcsv(path: Path, fo, ident="lobula_logger", accel=True) -> Path:
    """The run's IMU as a .gcsv as a logger writes it: integer µs, acceleration in g, and the camera-frame
    axes (x right, y down, z forward) named against Gyroflow's (x up, y left, z back): orientation "yxz"."""
    imu = fo.imu
    head = ["GYROFLOW IMU LOG", "version,1", f"id,{ident}", "orientation,yxz", "tscale,0.000001", "gscale,1",
            "ascale,1", "t,gx,gy,gz" + (",ax,ay,az" if accel else "")]
    rows = [",".join([str(int(round(t * 1e6))), *map(repr, g.tolist()), *(map(repr, (a / G).tolist()) if accel else [])])
            for t, g, a in zip(imu.time_s, imu.gyro, imu.accel)]
    path.write_text("\n".join(head + rows) + "\n")
    return path


def write_video(run: Path, dst: Path, *, gcsv=True, imu_csv=False, camera=True, **gcsv_kw) -> Path:
    dst.mkdir()
    fo = open_footage(run)
    video = dst / "clip.avi"
    wr = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (fo.camera.width, fo.camera.height))
    for _, _, img in fo.frames():
        wr.write(cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    wr.release()
    if camera:
        shutil.copy(run / "camera.json", dst / "clip.camera.json")
    if gcsv:
        write_gcsv(dst / "clip.gcsv", fo, **gcsv_kw)
    if imu_csv:
        shutil.copy(run / "imu.csv", dst / "imu.csv")
    shutil.copy(run / "truth.csv", dst / "truth.csv")
    return video


def cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err.strip()


def test_a_gcsv_beside_the_video_gives_back_the_runs_imu(run, tmp_path):
    video = write_video(run, tmp_path / "v")
    fo, ref = open_footage(video), open_footage(run)
    assert fo.kind == "camera-telemetry" and len(fo) == len(ref)
    np.testing.assert_allclose(fo.imu.time_s, ref.imu.time_s, rtol=0, atol=1e-6)  # written in whole µs
    np.testing.assert_allclose(fo.imu.accel, ref.imu.accel, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fo.imu.gyro, ref.imu.gyro, rtol=1e-12, atol=1e-15)
    assert fo.truth is not None and "clip.gcsv" in fo.imu.source


def test_a_loggers_own_clock_starts_at_the_videos_start(run, tmp_path):
    video = write_video(run, tmp_path / "v")
    log = tmp_path / "v" / "clip.gcsv"
    lines = log.read_text().splitlines()
    head, rows = lines[:8], lines[8:]
    shifted = [",".join([str(int(r.split(",")[0]) + 500_000_000)] + r.split(",")[1:]) for r in rows]  # 500 s on
    log.write_text("\n".join(head + shifted) + "\n")
    fo, ref = open_footage(video), open_footage(run)
    np.testing.assert_allclose(fo.imu.time_s, ref.imu.time_s - ref.imu.time_s[0], atol=1e-6)
    assert "first sample at the video's start" in " ".join(fo.notes)


def test_velocity_from_the_gcsv_equals_velocity_from_the_imu_csv(run, tmp_path, capsys):
    import xarray as xr

    gcsv = write_video(run, tmp_path / "g")
    plain = write_video(run, tmp_path / "p", gcsv=False, imu_csv=True)
    shutil.move(tmp_path / "p" / "clip.camera.json", tmp_path / "p" / "camera.json")
    assert open_footage(plain).kind == "video"
    out = {}
    for name, src in (("gcsv", gcsv), ("video", plain)):
        code, _, err = cli(capsys, "velocity", src, "--out", tmp_path / f"{name}.nc", "--quiet")
        assert code == 0, err
        out[name] = xr.load_dataset(tmp_path / f"{name}.nc")
    assert out["gcsv"].attrs["footage_layout"] == "camera-telemetry"
    # the same up to the log's whole microseconds
    for var in ("v_hat", "v_std", "accel", "r"):
        np.testing.assert_allclose(out["gcsv"][var].values, out["video"][var].values, rtol=1e-4, atol=1e-5,
                                   equal_nan=True)
    assert np.isfinite(out["gcsv"]["posterior_std"].values).any()


def test_a_video_with_its_own_imu_csv_stays_the_video_layout(run, tmp_path):
    video = write_video(run, tmp_path / "v", imu_csv=True)
    assert open_footage(video).kind == "video"


@pytest.mark.parametrize("content, needle", [
    ("GYROFLOW IMU LOG\nversion,1\nthis is not a log\n", "holds no samples"),
    ("\x00\x01garbage", "not a motion log"),
])
def test_a_broken_gcsv_is_one_clear_line(run, tmp_path, capsys, content, needle):
    video = write_video(run, tmp_path / "v")
    (tmp_path / "v" / "clip.gcsv").write_text(content)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", video, "--out", out)
    assert code == 2 and len(err.splitlines()) == 1 and needle in err and "clip.gcsv" in err, err
    assert not out.exists() and not list(tmp_path.glob(".o.nc*"))


def test_a_gyro_only_log_says_velocity_needs_an_accelerometer(run, tmp_path, capsys):
    video = write_video(run, tmp_path / "v", accel=False)
    code, _, err = cli(capsys, "velocity", video, "--out", tmp_path / "o.nc")
    assert code == 2 and "no accelerometer" in err and "clip.gcsv" in err, err
    fo = open_footage(video, require_imu=False)
    assert fo.imu is None


def test_without_intrinsics_an_action_camera_is_taken_for_a_fisheye_and_another_for_a_pinhole(run, tmp_path):
    video = write_video(run, tmp_path / "a", camera=False, ident="runcam_thumb_pro")
    fo = open_footage(video)
    assert fo.lens_guess["model"] == "kannala-brandt" and fo.distortion["removed"]
    assert fo.calibration["lens"].startswith("equidistant") and "focal_length_px" in fo.calibration
    video = write_video(run, tmp_path / "b", camera=False, ident="phone_logger")
    fo = open_footage(video)
    assert fo.lens_guess["model"] == "pinhole" and fo.lens_maps is None and fo.distortion is None
    # the run barely turns: the focal length stays the guess's, with the guess's uncertainty, and says why
    cal = fo.calibration
    assert cal["lens"].startswith("pinhole") and cal["focal_length_rel_std"] == 0.25
    assert "not measured: too little pan and tilt" in cal["focal_length_source"]
    assert cal["focal_length_px"] == pytest.approx(fo.camera.fx)


@pytest.fixture(scope="module")
def turning_run(tmp_path_factory) -> Path:
    """A 160×120 pinhole run turning on three axes (3 s)."""
    cfg = TrackRunConfig(start_s=3.0, duration_s=3.0, scale=0.25,
                         scene=SceneConfig(seed=2, rotation3_amp_deg=(5.0, 5.0, 5.0)))
    return make_track_run(tmp_path_factory.mktemp("turn") / "turn", cfg, progress=False)


def test_a_phone_video_that_turns_has_its_focal_length_measured(turning_run, tmp_path):
    """The turning run, its IMU as a phone app's .gcsv, no intrinsics: from the 75° guess (130 px) the gyro finds
    the focal length (154 px) within 6 %, inside twice its stated std; the IMU's axes, right, are left alone."""
    true_fx = json.loads((turning_run / "camera.json").read_text())["fx"]
    fo = open_footage(write_video(turning_run, tmp_path / "v", camera=False, ident="phone_logger"))
    cal = fo.calibration
    assert "measured against the gyro" in cal["focal_length_source"], cal
    err = cal["focal_length_px"] / true_fx - 1.0
    assert abs(err) < 0.06 and abs(err) <= 2 * cal["focal_length_rel_std"], cal
    assert fo.camera.fx == pytest.approx(cal["focal_length_px"], rel=1e-4) and abs(cal["clock_offset_s"]) < 0.01
    assert cal["imu_axes_source"].startswith("as read")
    assert cal["imu_axes_angle_deg"] < 2 * cal["imu_axes_angle_std_deg"]
    assert "imu_axes_rotation" not in cal and cal["projection_source"].startswith("the reader's guess, as the image")


def test_an_action_camera_that_films_through_a_wide_pinhole_is_found_out(tmp_path):
    """A 106° pinhole turning on three axes, logged by an action camera (opened as an equidistant fisheye for want of
    intrinsics): its edge turns 1.3× as fast as its centre read as a fisheye, 0.9× read as a pinhole, so it is read
    as a pinhole. Its focal length then reads 10 % long (the stated 4 % holds to about 70°; wider, the slope of the
    image's rates on the gyro's reads long)."""
    cam = tmp_path / "wide.json"
    cam.write_text(json.dumps(dict(width=320, height=240, fx=150.0, fy=150.0, cx=159.5, cy=119.5, frame_rate_hz=30.0)))
    cfg = TrackRunConfig(start_s=3.0, duration_s=3.0, scale=0.5, camera_json=str(cam),
                         scene=SceneConfig(seed=2, rotation3_amp_deg=(5.0, 5.0, 5.0)))
    run = make_track_run(tmp_path / "wide", cfg, progress=False)
    fo = open_footage(write_video(run, tmp_path / "v", camera=False, ident="runcam_thumb_pro"))
    cal = fo.calibration
    assert fo.lens_guess["model"] == "pinhole" and fo.distortion is None and fo.lens_maps is None, cal
    assert cal["lens"].startswith("pinhole") and cal["projection_source"].startswith("measured"), cal
    true_fx = json.loads((run / "camera.json").read_text())["fx"]
    assert abs(cal["focal_length_px"] / true_fx - 1.0) < 0.12, cal


def test_a_motion_log_in_other_axes_is_turned_onto_the_image(turning_run, tmp_path, capsys):
    """The same phone video, its motion logged in portrait while the picture is landscape (the log's axes 90°
    about the optical axis from the camera's): the gyro's rates no longer line up with the image's, so the clock
    offset cannot be found; the IMU is turned onto the image's rotation, within 2° of the truth (and its stated
    2σ), the clock found again, and the focal length measured as with the right axes."""
    from scipy.spatial.transform import Rotation

    portrait = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    video = write_video(turning_run, tmp_path / "v", camera=False, ident="phone_logger")
    fo = open_footage(turning_run)
    fo.imu = fo.imu.rotated(portrait.T)
    write_gcsv(video.with_suffix(".gcsv"), fo, ident="phone_logger")
    got, ref = open_footage(video), open_footage(turning_run).imu
    cal = got.calibration
    assert cal["imu_axes_source"].startswith("turned by"), cal
    k = min(len(ref.gyro), len(got.imu.gyro))
    r = np.asarray(cal["imu_axes_rotation"]) @ portrait.T          # what is left of the log's axes
    left = float(np.degrees(Rotation.from_matrix(r).magnitude()))
    print(f"\n{cal['imu_axes_source']}; {left:.2f}° left; focal length {cal['focal_length_px']:.1f} px")
    assert left < 2.0 and left < 2 * cal["imu_axes_angle_std_deg"], cal
    # the whole IMU turned by the rotation stated (rounded to 1e-6)
    assert np.allclose(got.imu.gyro[:k], ref.gyro[:k] @ r.T, atol=1e-5)
    assert np.allclose(got.imu.accel[:k], ref.accel[:k] @ r.T, atol=1e-4)
    assert cal["clock_offset_source"].startswith("estimated") and abs(cal["clock_offset_s"]) < 0.01, cal
    true_fx = json.loads((turning_run / "camera.json").read_text())["fx"]
    assert abs(cal["focal_length_px"] / true_fx - 1.0) <= 2 * cal["focal_length_rel_std"], cal
    assert json.loads(got.provenance()["camera_calibration"])["imu_axes_source"] == cal["imu_axes_source"]


def test_a_360_degree_picture_is_refused_without_intrinsics(run, tmp_path):
    dst = tmp_path / "s"
    dst.mkdir()
    wr = cv2.VideoWriter(str(dst / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (240, 120))
    for k in range(5):
        wr.write(np.full((120, 240, 3), 40 * k, np.uint8))
    wr.release()
    write_gcsv(dst / "clip.gcsv", open_footage(run), ident="insta360_x3")
    with pytest.raises(FootageError, match="240x120 frame is a 360° picture"):
        open_footage(dst / "clip.avi")


def test_a_panic_of_the_parser_is_one_clear_line(run, tmp_path, monkeypatch, capfd):
    """telemetry-parser's Rust code panics on some damaged files: the panic (a BaseException, its message and
    backtrace printed on the process's standard error) reads as "no motion log", with nothing else printed."""
    import os

    import telemetry_parser

    class Panic(BaseException):  # what pyo3 raises for a Rust panic
        pass

    def parser(path):
        os.write(2, b"thread '<unnamed>' panicked at src/gopro: range end index 88 out of range\nstack backtrace:\n")
        raise Panic("range end index 88 out of range for slice of length 84")

    monkeypatch.setattr(telemetry_parser, "Parser", parser)
    from lobula.readers.camera_telemetry import has_motion_log, read_motion_log

    video = write_video(run, tmp_path / "v", gcsv=False)
    capfd.readouterr()
    assert not has_motion_log(video)
    with pytest.raises(FootageError, match="finds no motion log"):
        read_motion_log(video)
    (tmp_path / "v" / "clip.gcsv").write_text("GYROFLOW IMU LOG\n")
    with pytest.raises(FootageError, match="clip.gcsv: not a motion log telemetry-parser can read"):
        open_footage(video)
    assert capfd.readouterr().err == ""

