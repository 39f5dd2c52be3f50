"""``--camera FILE`` in the calibration tools' own formats (lobula.readers.intrinsics): OpenCV FileStorage,
ROS camera_info, Kalibr camchains and Gyroflow lens profiles give the footage the camera, lens, IMU rotation
and clock their numbers say, as the equivalent camera.json would."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from experiments.cli import main
from lobula.readers import open_footage
from lobula.readers.core import FootageError
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run

RADTAN = [0.05, -0.02, 0.001, -0.0005, 0.003]
KB4 = [0.02, -0.01, 0.003, -0.001]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """2 s of a small (160×120) synthetic run in motion."""
    cfg = TrackRunConfig(profile=None, start_s=6.0, duration_s=2.0, scale=0.25, scene=SceneConfig(seed=2))
    return make_track_run(tmp_path_factory.mktemp("run") / "run", cfg, progress=False)


def pixels(cam) -> tuple:
    """A camera's geometry, without the nominal frame rate (the footage's own where a calibration has none)."""
    return cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy


def camera_of(run: Path) -> dict:
    return json.loads((run / "camera.json").read_text())


def k_matrix(c: dict, scale: float = 1.0) -> np.ndarray:
    return np.array([[c["fx"] * scale, 0, (c["cx"] + 0.5) * scale - 0.5],
                     [0, c["fy"] * scale, (c["cy"] + 0.5) * scale - 0.5], [0, 0, 1.0]])


def reference(run: Path, tmp_path: Path, **extra) -> Path:
    """The camera.json the other formats must amount to."""
    p = tmp_path / "reference.camera.json"
    p.write_text(json.dumps({**camera_of(run), **extra}))
    return p


@pytest.mark.parametrize("suffix", [".yaml", ".xml", ".json"])
def test_an_opencv_calibration_is_the_camera_json_it_says(run, tmp_path, suffix):
    c = camera_of(run)
    path = tmp_path / f"calib{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", c["width"])
    fs.write("image_height", c["height"])
    fs.write("camera_matrix", k_matrix(c))
    fs.write("distortion_coefficients", np.array([RADTAN]))
    fs.release()
    got = open_footage(run, camera=path)
    want = open_footage(run, camera=reference(run, tmp_path, distortion=dict(model="radtan", coeffs=RADTAN)))
    assert pixels(got.camera) == pixels(want.camera)  # the pinhole the lens is resampled onto
    assert got.distortion["coeffs"] == pytest.approx(RADTAN) and got.distortion["source"] == str(path)
    assert got.distortion["raw_camera"] == pytest.approx(want.distortion["raw_camera"])
    assert f"intrinsics from {path} (--camera, read as an OpenCV FileStorage file)" in got.notes[-1]


def test_opencvs_calibration_sample_marks_a_fisheye(run, tmp_path):
    """OpenCV's camera_calibration sample writes fisheye_model 1 and four coefficients for a fisheye."""
    c = camera_of(run)
    path = tmp_path / "out_camera_data.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in (("image_width", c["width"]), ("image_height", c["height"]), ("flags", 0), ("fisheye_model", 1),
                 ("camera_matrix", k_matrix(c)), ("distortion_coefficients", np.array(KB4)[:, None]),
                 ("avg_reprojection_error", 0.3)):
        fs.write(k, v)
    fs.release()
    got = open_footage(run, camera=path)
    assert got.distortion["model"] == "kannala-brandt" and got.distortion["coeffs"] == pytest.approx(KB4)


def test_velocity_with_an_opencv_calibration_equals_velocity_with_the_camera_json(run, tmp_path):
    from lobula.config import VelocityConfig
    from lobula.velocity import estimate_velocity

    c = camera_of(run)
    path = tmp_path / "calib.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in (("image_width", c["width"]), ("image_height", c["height"]), ("camera_matrix", k_matrix(c))):
        fs.write(k, v)
    fs.release()
    cfg = VelocityConfig()
    a = estimate_velocity(open_footage(run, camera=path), cfg, progress=False)
    b = estimate_velocity(open_footage(run), cfg, progress=False)
    np.testing.assert_array_equal(a.r.values, b.r.values)
    np.testing.assert_array_equal(a.v_hat.values, b.v_hat.values)


def test_a_ros_camera_info_with_an_equidistant_lens(run, tmp_path):
    c = camera_of(run)
    path = tmp_path / "head_camera.yaml"
    path.write_text(yaml.safe_dump(dict(
        image_width=c["width"], image_height=c["height"], camera_name="head_camera",
        camera_matrix=dict(rows=3, cols=3, data=k_matrix(c).ravel().tolist()), distortion_model="equidistant",
        distortion_coefficients=dict(rows=1, cols=4, data=KB4))))
    got = open_footage(run, camera=path)
    want = open_footage(run, camera=reference(run, tmp_path, distortion=dict(model="kannala-brandt", coeffs=KB4)))
    assert pixels(got.camera) == pixels(want.camera) and got.distortion["model"] == "kannala-brandt"


def test_a_kalibr_camchain_rotates_the_imu_and_shifts_its_clock(run, tmp_path, capsys):
    c = camera_of(run)
    r = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° about the optical axis
    t_cam_imu = np.eye(4)
    t_cam_imu[:3, :3] = r
    t_cam_imu[:3, 3] = [0.01, 0.02, 0.0]
    path = tmp_path / "camchain-imucam-run.yaml"
    path.write_text(yaml.safe_dump(dict(cam0=dict(
        camera_model="pinhole", intrinsics=[c["fx"], c["fy"], c["cx"], c["cy"]], distortion_model="radtan",
        distortion_coeffs=[0.0, 0.0, 0.0, 0.0], resolution=[c["width"], c["height"]], rostopic="/cam0/image_raw",
        T_cam_imu=t_cam_imu.tolist(), timeshift_cam_imu=0.012))))
    got, ref = open_footage(run, camera=path), open_footage(run)
    assert pixels(got.camera) == pixels(ref.camera) and got.distortion is None
    np.testing.assert_allclose(got.imu.accel, ref.imu.accel @ r.T, atol=1e-12)
    np.testing.assert_allclose(got.imu.gyro, ref.imu.gyro @ r.T, atol=1e-12)
    np.testing.assert_allclose(got.imu.time_s, ref.imu.time_s - 0.012, atol=1e-12)  # t_imu = t_cam + shift
    assert got.clock_offset_s == pytest.approx(-0.012) and str(path) in got.clock_offset_source
    # --clock-offset given: the user's number rules
    assert open_footage(run, camera=path, clock_offset=0.0).clock_offset_s == 0.0


def test_a_gyroflow_lens_profile_is_scaled_to_the_footage(run, tmp_path):
    c = camera_of(run)
    path = tmp_path / "GoPro_HERO_test.json"
    path.write_text(json.dumps(dict(
        name="test", camera_brand="GoPro", camera_model="HERO test", lens_model="Wide",
        calib_dimension=dict(w=2 * c["width"], h=2 * c["height"]),
        fisheye_params=dict(RMS_error=0.3, camera_matrix=k_matrix(c, 2.0).tolist(), distortion_coeffs=KB4))))
    got = open_footage(run, camera=path)
    raw = got.distortion["raw_camera"]
    assert (raw["width"], raw["height"]) == (c["width"], c["height"])
    assert raw["fx"] == pytest.approx(c["fx"]) and raw["cx"] == pytest.approx(c["cx"])
    assert raw["cy"] == pytest.approx(c["cy"]) and got.distortion["coeffs"] == pytest.approx(KB4)
    assert any("calibrated at 320x240, scaled by 0.5 to 160x120" in n for n in got.notes)


@pytest.mark.parametrize("content, needle", [
    ("this: is: not: yaml: [", "not a calibration file this reads"),
    ("just: some\nkeys: 1\n", "not a calibration file this reads"),
    (yaml.safe_dump(dict(cam0=dict(camera_model="omni", intrinsics=[1, 1, 1, 1, 1], resolution=[160, 120]))),
     "Kalibr camera model 'omni' is not supported"),
    (yaml.safe_dump(dict(image_width=160, image_height=120, camera_matrix=dict(data=[100, 0, 80, 0, 100, 60, 0, 0, 1]),
                         distortion_model="rational_polynomial", distortion_coefficients=dict(data=[0.1] * 8))),
     "not supported"),
    (json.dumps(dict(calib_dimension=dict(w=320, h=200), fisheye_params=dict(
        camera_matrix=[[200, 0, 160], [0, 200, 100], [0, 0, 1]], distortion_coeffs=[0, 0, 0, 0]))),
     "another aspect ratio"),
])
def test_a_bad_calibration_is_one_clear_line(run, tmp_path, capsys, content, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    out = tmp_path / "o.nc"
    code = main(["velocity", str(run), "--camera", str(path), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and needle in err and str(path) in err, err
    assert not out.exists()
    with pytest.raises(FootageError):
        open_footage(run, camera=path)
