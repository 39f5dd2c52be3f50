"""GoPro MP4s with their GPMF telemetry (lobula.readers.gopro): axes, timing, GPS truth, stabilisation, bad input.

Synthetic GoPro files are built here (GPMF written key by key, muxed with PyAV into a small MP4, the
camera's settings block appended to its index) and read back through ``open_footage``; the two
real clips in ../shared/data/gopro_walking (skipped with a reason where absent, never copied) are
checked against physics and against a second reader: GoPro's own MP4 reader (py-gpmf-parser's
mp4reader) for the packets and their times, and a KLV walk written here for the samples.
"""
from __future__ import annotations

import fractions
import json
import importlib.util
import re
import sys
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
import xarray as xr
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from experiments.cli import main
from lobula.readers import open_footage
from lobula.readers.core import FootageError
from lobula.readers.gopro import (GOPRO_TO_CAMERA, axis_order_matrix, has_gpmf_track, imu_axes_to_camera,
                                  packet_sample_times, quaternion_angle_deg)

GOPRO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "gopro_walking"
G = 9.80665
#: the GPMF decoder is a dependency only where py-gpmf-parser has wheels (Linux x86-64, CPython ≤ 3.12)
needs_gpmf = pytest.mark.skipif(importlib.util.find_spec("py_gpmf_parser") is None,
                                reason="py-gpmf-parser is not installed (wheels: Linux x86-64, CPython 3.8-3.12)")


def cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err.strip()


def one_line_error(code, err, *needles):
    assert code == 2 and "Traceback" not in err, err
    assert len(err.splitlines()) == 1, err
    for n in needles:
        assert n in err, err


# ------------------------------------------------------------------ GPMF written here
def klv(key: str, type_char: str | None, size: int, repeat: int, payload: bytes) -> bytes:
    """One GPMF KLV: 4-character key, type, struct size, repeat (big-endian), payload padded to 32 bits."""
    head = key.encode() + (type_char.encode() if type_char else b"\0") + bytes([size]) + repeat.to_bytes(2, "big")
    return head + payload + b"\0" * (-len(payload) % 4)


def nest(key: str, *children: bytes) -> bytes:
    body = b"".join(children)
    return klv(key, None, 1, len(body), body)


def text(key: str, s: str) -> bytes:
    return klv(key, "c", 1, len(s), s.encode("latin-1"))


def numbers(key: str, type_char: str, values) -> bytes:
    v = np.atleast_2d(np.asarray(values))
    dt = {"s": ">i2", "S": ">u2", "l": ">i4", "L": ">u4", "f": ">f4"}[type_char]
    return klv(key, type_char, v.shape[1] * np.dtype(dt).itemsize, v.shape[0], v.astype(dt).tobytes())


def gps9(samples) -> bytes:
    """GPS9 samples (lat, lon, alt, 2D speed, 3D speed, days, seconds, DOP, fix), a complex type."""
    scal = [10_000_000, 10_000_000, 1000, 1000, 100, 1, 1000, 100, 1]
    raw = b"".join(np.array([round(x * s) for x, s in zip(row[:7], scal)], ">i4").tobytes()
                   + np.array([round(row[7] * 100), row[8]], ">u2").tobytes() for row in samples)
    return (text("TYPE", "lllllllSS") + numbers("SCAL", "l", [[s] for s in scal])
            + klv("GPS9", "?", 32, len(samples), raw))


def write_gopro_mp4(path: Path, payloads: list[bytes], settings: bytes | None = None, seconds: float = 2.0,
                    ms_per_packet: int = 1000) -> Path:
    """An MP4 as a GoPro lays it out: 64×48 video at 30 frames/s and a gpmd track of one packet per
    ``ms_per_packet``; ``settings`` (GPMF) goes into moov/udta/GPMF, where the camera keeps it."""
    c = av.open(str(path), "w", format="mp4")
    v = c.add_stream("mpeg4", rate=30)
    v.width, v.height, v.pix_fmt = 64, 48, "yuv420p"
    d = c.add_data_stream(codec_name="bin_data")  # FFmpeg's mp4 muxer writes it as a 'gpmd' track
    d.time_base = fractions.Fraction(1, 1000)
    for k, p in enumerate(payloads):
        pk = av.Packet(p)
        pk.stream, pk.time_base = d, d.time_base
        pk.pts = pk.dts = k * ms_per_packet
        pk.duration = ms_per_packet
        c.mux(pk)
    for i in range(int(seconds * 30)):
        fr = av.VideoFrame.from_ndarray(np.full((48, 64, 3), (i * 4) % 255, np.uint8), format="rgb24")
        fr.pts = i
        for p in v.encode(fr):
            c.mux(p)
    for p in v.encode():
        c.mux(p)
    c.close()
    if settings is not None:
        data = bytearray(path.read_bytes())
        at = data.rfind(b"moov") - 4  # the muxer writes the index last
        assert int.from_bytes(data[at:at + 4], "big") == len(data) - at
        gpmf = len(settings) + 8
        udta = (gpmf + 8).to_bytes(4, "big") + b"udta" + gpmf.to_bytes(4, "big") + b"GPMF" + settings
        data += udta
        data[at:at + 4] = (len(data) - at).to_bytes(4, "big")
        path.write_bytes(bytes(data))
    return path


def camera_json(path: Path, w: int = 64, h: int = 48) -> Path:
    path.write_text(f'{{"width": {w}, "height": {h}, "fx": {w}, "fy": {w}, "cx": {(w - 1) / 2}, '
                    f'"cy": {(h - 1) / 2}, "frame_rate_hz": 30}}')
    return path


def body_to_stored(xyz: np.ndarray, orin: str) -> np.ndarray:
    """GoPro body-axis vectors (X, Y, Z columns) as a sensor storing channels in ``orin`` writes them."""
    col = {"X": 0, "Y": 1, "Z": 2}
    return np.stack([xyz[:, col[c.upper()]] * (1 if c.isupper() else -1) for c in orin], -1)


# Known motion in GoPro's documented body axes (X left, Y out of the back, Z up): a camera pitched
# 10° down, turning right at 0.5 rad/s and pitching up at 0.3 rad/s.
PITCH = np.radians(10.0)
ACCEL_BODY = np.array([0.0, G * np.sin(PITCH), G * np.cos(PITCH)])   # specific force: up
GYRO_BODY = np.array([-0.3, 0.0, -0.5])  # about −X (= right): nose up; about −Z (= down): turning right
# The same in the camera optical frame (x right, y down, z forward, lobula.camera):
ACCEL_CAM = np.array([0.0, -G * np.cos(PITCH), -G * np.sin(PITCH)])
GYRO_CAM = np.array([0.3, 0.5, 0.0])    # ω_x > 0 tilts the optical axis up, ω_y > 0 turns it right


def imu_strm(key: str, vec_body: np.ndarray, n: int, scal: int, orin: str | None, orio: bool = True) -> bytes:
    raw = np.round(body_to_stored(np.tile(vec_body, (n, 1)), orin or "YxZ") * scal)
    props = [text("ORIN", orin)] + ([text("ORIO", "ZXY")] if orio else []) if orin else []
    return nest("STRM", numbers("TSMP", "L", [[n]]), text("STNM", key.title()), *props,
                text("SIUN", "m/s\xb2" if key == "ACCL" else "rad/s"), numbers("SCAL", "s", [[scal]]),
                numbers(key, "s", raw))


def gps5_strm(speeds, fix: int, dop: float) -> bytes:
    rows = [[33.1267700 * 1e7, -117.3273436 * 1e7, -22.959 * 1e3, v * 1000, v * 100] for v in speeds]
    return nest("STRM", text("STNM", "GPS (Lat., Long., Alt., 2D speed, 3D speed)"), numbers("GPSF", "L", [[fix]]),
                numbers("GPSP", "S", [[round(dop * 100)]]),
                numbers("SCAL", "l", [[10_000_000], [10_000_000], [1000], [1000], [100]]),
                numbers("GPS5", "l", np.round(rows)))


def payload(*streams: bytes, name: str = "Camera") -> bytes:
    return nest("DEVC", numbers("DVID", "L", [[1]]), text("DVNM", name), *streams)


def settings_block(model: str, eise: str = "Y", eisa: str = "HS EIS") -> bytes:
    return nest("DEVC", numbers("DVID", "L", [[1]]), text("MINF", model), text("EISE", eise), text("EISA", eisa),
                text("VFOV", "W"))


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    """Two 1 s packets of a camera writing ORIN/ORIO (200 then 198 IMU samples, 18 GPS5 samples each:
    the second without a fix), HyperSmooth on in the settings, and a camera.json beside it."""
    d = tmp_path_factory.mktemp("gopro")
    speeds = [np.linspace(1.10, 1.44, 18), np.linspace(1.5, 1.6, 18)]
    pl = [payload(imu_strm("ACCL", ACCEL_BODY, n, 418, "YxZ"), imu_strm("GYRO", GYRO_BODY, n, 939, "YxZ"),
                  gps5_strm(speeds[k], fix=(3, 0)[k], dop=1.54))
          for k, n in enumerate((200, 198))]
    clip = write_gopro_mp4(d / "clip.mp4", pl, settings_block("HERO7 Black"))
    camera_json(d / "clip.camera.json")
    return clip


# ------------------------------------------------------------------ axes and timing as pure functions
def test_axis_order_matrix_is_gopros_mtrx():
    # the MTRX the MAX and the HERO7 Black write beside their ORIN (gopro_walking clips)
    assert np.array_equal(axis_order_matrix("XzY"), [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert np.array_equal(axis_order_matrix("YxZ"), [[0, 0, 1], [0, -1, 0], [1, 0, 0]])
    assert np.array_equal(axis_order_matrix("ZXY"), np.eye(3))
    assert np.array_equal(axis_order_matrix("zxy", "ZXY"), -np.eye(3))
    for bad in ("XXY", "XY", "ABC"):
        with pytest.raises(ValueError, match="X, Y and Z"):
            axis_order_matrix(bad)


@pytest.mark.parametrize("orin", ["ZXY", "YxZ", "yXZ", "XzY", "xYz"])
def test_every_stored_order_reaches_the_camera_frame(orin):
    r = imu_axes_to_camera(orin)
    assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
    stored = body_to_stored(np.array([ACCEL_BODY, GYRO_BODY]), orin)
    assert np.allclose(stored @ r.T, [ACCEL_CAM, GYRO_CAM])


def test_a_mirrored_axis_order_is_refused():
    with pytest.raises(ValueError, match="mirror"):
        imu_axes_to_camera("xZy")


def test_standard_order_to_camera_is_a_rotation_with_gravity_on_minus_y():
    assert np.isclose(np.linalg.det(GOPRO_TO_CAMERA), 1.0)
    # upright and level at rest: specific force on +Z (up) reads −g on the camera's y (down)
    assert np.allclose(GOPRO_TO_CAMERA @ [G, 0, 0], [0, -G, 0])


def test_packet_sample_times_spread_over_each_span():
    t = packet_sample_times(1.001, 2.002, 4)
    assert np.allclose(t, [1.001, 1.25125, 1.5015, 1.75175])
    both = np.concatenate([packet_sample_times(0.0, 1.001, 197), packet_sample_times(1.001, 2.002, 199)])
    assert np.all(np.diff(both) > 0) and both[197] == 1.001
    assert packet_sample_times(0, 1, 0).size == 0


def test_quaternion_angle():
    half = np.radians(20.0) / 2
    assert np.allclose(quaternion_angle_deg(np.array([[1, 0, 0, 0], [np.cos(half), 0, 0, np.sin(half)],
                                                      [-np.cos(half), np.sin(half), 0, 0]]) * 32767), [0, 20, 20])


# ------------------------------------------------------------------ a synthetic GoPro file
@needs_gpmf
def test_synthetic_gopro_opens_with_imu_in_the_camera_frame(synthetic):
    assert has_gpmf_track(synthetic)
    fo = open_footage(synthetic)
    assert fo.kind == "gopro" and len(fo) == 60 and (fo.camera.width, fo.camera.height) == (64, 48)
    imu = fo.imu
    assert len(imu.time_s) == 398
    assert np.allclose(imu.accel, ACCEL_CAM, atol=0.5 / 418) and np.allclose(imu.gyro, GYRO_CAM, atol=0.5 / 939)
    assert np.allclose(imu.time_s[:200], np.arange(200) / 200)
    assert np.allclose(imu.time_s[200:], 1 + np.arange(198) / 198)
    assert fo.telemetry["streams"]["ACCL"]["axes"] == "ORIN YxZ -> ZXY -> camera"
    frames = list(fo.frames(0, 3))
    assert [i for i, _, _ in frames] == [0, 1, 2] and frames[2][2].shape == (48, 64)


def orientation_strm(key: str, rotvecs: np.ndarray) -> bytes:
    """CORI or IORI: unit quaternions (w, x, y, z) of rotation vectors (n, 3) rad in the camera's axes, as int16
    over SCAL 32767."""
    q = Rotation.from_rotvec(rotvecs).as_quat()
    wxyz = np.c_[q[:, 3:], q[:, :3]]
    return nest("STRM", text("STNM", {"CORI": "CameraOrientation", "IORI": "ImageOrientation"}[key]),
                numbers("SCAL", "s", [[32767]]), numbers(key, "s", np.round(wxyz * 32767)))


@needs_gpmf
def test_a_stabilised_clip_with_its_image_orientation_has_the_images_imu(tmp_path):
    """A camera turning at ω while its stabiliser lets the image turn at half of it writes CORI = B⁻¹ and
    IORI = S⁻¹ (B = exp(ω t), S = B⁻¹·V = exp(−ω t / 2)): its IMU comes out in the image's frame, the gyro at ω/2
    and the specific force turned by S⁻¹ (to the int16 quaternions' 0.003 rad/s); asked not to, the body's."""
    from lobula.readers.gopro import open_gopro

    pl = []
    for k in range(2):
        t = k + np.arange(30) / 30
        pl.append(payload(imu_strm("ACCL", ACCEL_BODY, 200, 418, "YxZ"), imu_strm("GYRO", GYRO_BODY, 200, 939, "YxZ"),
                          orientation_strm("CORI", -np.outer(t, GYRO_CAM)),
                          orientation_strm("IORI", np.outer(t, GYRO_CAM) / 2)))
    clip = write_gopro_mp4(tmp_path / "clip.mp4", pl, settings_block("HERO9 Black"))
    cam = camera_json(tmp_path / "clip.camera.json")
    fo = open_gopro(clip, camera_json=cam)
    assert fo.telemetry["stabilisation"]["imu_frame"] == "image"
    inside = (fo.imu.time_s > 0.05) & (fo.imu.time_s < 1.9)
    np.testing.assert_allclose(fo.imu.gyro[inside], np.tile(GYRO_CAM / 2, (inside.sum(), 1)), atol=5e-3)
    s = Rotation.from_rotvec(-np.outer(fo.imu.time_s[inside], GYRO_CAM) / 2)  # image → body
    np.testing.assert_allclose(fo.imu.accel[inside], s.inv().apply(np.tile(ACCEL_CAM, (inside.sum(), 1))),
                               atol=0.02)
    np.testing.assert_allclose(fo.body_imu.gyro, np.tile(GYRO_CAM, (len(fo.imu.time_s), 1)), atol=0.5 / 939)
    kept = open_gopro(clip, camera_json=cam, image_orientation=False)
    assert kept.telemetry["stabilisation"]["imu_frame"] == "body" and kept.imu is kept.body_imu


@needs_gpmf
def test_orientations_that_do_not_follow_the_gyro_are_not_used(tmp_path):
    """CORI written the other way round (B, not B⁻¹) turns against the gyro: the IMU stays the body's, and a note
    says why."""
    pl = [payload(imu_strm("ACCL", ACCEL_BODY, 200, 418, "YxZ"), imu_strm("GYRO", GYRO_BODY, 200, 939, "YxZ"),
                  orientation_strm("CORI", np.outer(k + np.arange(30) / 30, GYRO_CAM)),
                  orientation_strm("IORI", np.zeros((30, 3)) + 0.01)) for k in range(2)]
    clip = write_gopro_mp4(tmp_path / "clip.mp4", pl, settings_block("HERO9 Black"))
    fo = open_footage(clip, camera=camera_json(tmp_path / "camera.json"))
    assert fo.telemetry["stabilisation"]["imu_frame"] == "body" and fo.imu is fo.body_imu
    assert any(n.startswith("the file's camera and image orientations (CORI, IORI) are not used: CORI's rates")
               for n in fo.notes), fo.notes


@needs_gpmf
def test_synthetic_gps_truth_skips_samples_without_a_fix(synthetic):
    fo = open_footage(synthetic)
    tr = fo.truth
    # packet 0 has a 3D fix (18 samples over 0..1 s), packet 1 none
    assert len(tr["time_s"]) == 18 and np.allclose(tr["time_s"], np.arange(18) / 18)
    assert np.allclose(tr["v_forward_m_s"], np.linspace(1.10, 1.44, 18), atol=1e-3)
    assert set(tr["gps_fix"]) == {3} and np.allclose(tr["gps_dop"], 1.54)
    assert len(fo.gps["time_s"]) == 36 and fo.telemetry["gps"]["with_fix"] == 18
    prov = fo.provenance()
    assert prov["truth_source"] == "GPS (GPS5 2D ground speed)" and prov["gopro_model"] == "HERO7 Black"
    assert prov["electronic_stabilisation"].startswith("on (HS EIS)")
    assert any("truth is GPS" in n for n in fo.notes)


@needs_gpmf
def test_model_default_axis_order_without_orin(tmp_path):
    # a HERO6 writes no ORIN: GoPro documents its order as Y, −X, Z
    pl = [payload(imu_strm("ACCL", ACCEL_BODY, 200, 418, None), imu_strm("GYRO", GYRO_BODY, 200, 939, None))]
    clip = write_gopro_mp4(tmp_path / "h6.mp4", pl, settings_block("HERO6 Black", "N", "N/A"), seconds=1.0)
    fo = open_footage(clip, camera=camera_json(tmp_path / "cam.json"))
    assert np.allclose(fo.imu.accel, ACCEL_CAM, atol=0.01) and np.allclose(fo.imu.gyro, GYRO_CAM, atol=0.01)
    assert fo.telemetry["stabilisation"]["electronic"] is False
    assert "documented for the model" in fo.telemetry["streams"]["ACCL"]["axes"]
    # an unknown model without ORIN is refused rather than guessed
    clip = write_gopro_mp4(tmp_path / "x.mp4", pl, settings_block("HERO99"), seconds=1.0)
    with pytest.raises(FootageError, match=r"x\.mp4: the ACCL stream does not say its axis order"):
        open_footage(clip, camera=tmp_path / "cam.json")


@needs_gpmf
def test_gps9_per_sample_fix_and_dop(tmp_path):
    rows = [[33.12677, -117.32734, -22.9, 1.0 + k / 100, 1.1, 9000, 3600 + k / 10, 1.2, 3 if k % 3 else 0]
            for k in range(10)]
    pl = [payload(imu_strm("ACCL", ACCEL_BODY, 200, 418, "YxZ"), nest("STRM", text("STNM", "GPS9"), gps9(rows)))]
    clip = write_gopro_mp4(tmp_path / "h11.mp4", pl, settings_block("HERO11 Black"), seconds=1.0)
    fo = open_footage(clip, camera=camera_json(tmp_path / "cam.json"))
    keep = [k for k in range(10) if k % 3]
    assert fo.gps["source"] == "GPS9" and np.allclose(fo.truth["time_s"], np.array(keep) / 10)
    assert np.allclose(fo.truth["v_forward_m_s"], [1.0 + k / 100 for k in keep])
    assert np.allclose(fo.truth["gps_dop"], 1.2) and set(fo.truth["gps_fix"]) == {3}
    assert fo.imu.gyro is None


@needs_gpmf
def test_info_prints_the_telemetry(synthetic, capsys):
    code, out, _ = cli(capsys, "info", synthetic)
    assert code == 0
    assert "[gopro]" in out and "gopro:      HERO7 Black" in out
    assert "gps:      GPS5, 18 of 36 samples with a 2D/3D fix (fix [0, 3]" in out
    assert "stabilisation: electronic on (HS EIS), from camera settings" in out
    assert "truth:    GPS (GPS5 2D ground speed)" in out


# ------------------------------------------------------------------ bad input: one line, no output
@needs_gpmf
def test_without_a_camera_file_the_lens_is_assumed_measured_and_said(synthetic, tmp_path, capsys):
    """No camera file and no stated field of view: an equidistant fisheye of the nominal diagonal, whose focal length
    and clock offset the gyro cannot measure on a clip that does not turn — said, and stored."""
    from lobula.readers.gopro import NOMINAL_DIAGONAL_FOV_DEG, equidistant_camera

    clip = tmp_path / "bare.mp4"
    clip.write_bytes(synthetic.read_bytes())
    fo = open_footage(clip)
    cal = fo.calibration
    raw = fo.distortion["raw_camera"]
    guess = equidistant_camera(raw["width"], raw["height"], 30.0, NOMINAL_DIAGONAL_FOV_DEG)
    assert raw["fx"] == pytest.approx(guess.fx) and cal["focal_length_px"] == pytest.approx(guess.fx)
    assert "nominal" in cal["focal_length_source"] and "not measured" in cal["focal_length_source"]
    assert cal["clock_offset_s"] == 0.0 and "not identifiable" in cal["clock_offset_source"]
    assert fo.distortion["model"] == "kannala-brandt" and fo.distortion["removed"]
    assert json.loads(fo.provenance()["camera_calibration"]) == cal
    # and info does not ask for the camera file velocity goes without
    code, out, _ = cli(capsys, "info", clip)
    assert code == 0 and "intrinsics: none in the recording; velocity measures them from the gyro" in out


@needs_gpmf
def test_mp4_without_telemetry(tmp_path, capsys):
    from lobula.readers.gopro import open_gopro
    clip = write_gopro_mp4(tmp_path / "plain.mp4", [], seconds=0.5)
    assert not has_gpmf_track(clip)
    with pytest.raises(FootageError, match=r"plain\.mp4: no GPMF telemetry track \(gpmd\).*camera's original file"):
        open_gopro(clip)
    code, _, err = cli(capsys, "velocity", clip, "--out", tmp_path / "v.nc", "--quiet")
    one_line_error(code, err, "camera.json")  # not a GoPro file: the video reader's own message


def test_truncated_file(synthetic, tmp_path, capsys):
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(synthetic.read_bytes()[: synthetic.stat().st_size * 2 // 3])
    o = tmp_path / "v.nc"
    for cmd in (("info", cut), ("velocity", cut, "--out", o, "--quiet")):
        code, _, err = cli(capsys, *cmd)
        one_line_error(code, err, "cut.mp4: the MP4 has no index (moov", "copy the whole file again")
    assert not o.exists()


@needs_gpmf
def test_no_accelerometer_and_gps_without_a_fix(tmp_path, capsys):
    pl = [payload(gps5_strm(np.full(18, 1.3), fix=0, dop=99.0))]
    clip = write_gopro_mp4(tmp_path / "gpsonly.mp4", pl, seconds=1.0)
    camera_json(tmp_path / "gpsonly.camera.json")
    o = tmp_path / "v.nc"
    code, _, err = cli(capsys, "velocity", clip, "--out", o, "--quiet")
    one_line_error(code, err, "gpsonly.mp4: the GPMF telemetry has no accelerometer (ACCL)", "--accel-from-truth")
    assert not o.exists()
    fo = open_footage(clip, require_imu=False)
    assert fo.imu is None and fo.truth is None  # no fix: no truth, and it says so
    assert any("0 of 18 samples with a 2D/3D fix: no truth" in n for n in fo.notes)


@needs_gpmf
def test_damaged_telemetry_packet(tmp_path, capsys):
    good = payload(imu_strm("ACCL", ACCEL_BODY, 200, 418, "YxZ"))
    bad = good[:40] + b"\xff" * 8 + good[48:]  # a KLV header whose sizes run past its nest
    clip = write_gopro_mp4(tmp_path / "bad.mp4", [good, bad])
    camera_json(tmp_path / "bad.camera.json")
    code, _, err = cli(capsys, "velocity", clip, "--out", tmp_path / "v.nc", "--quiet")
    one_line_error(code, err, "bad.mp4: telemetry packet 1 (1.000–2.000 s) is damaged", "copy the file again")


def test_without_the_gpmf_parser_the_error_says_what_to_install(synthetic, monkeypatch):
    monkeypatch.setitem(sys.modules, "py_gpmf_parser", None)  # import fails as where it is not installed
    with pytest.raises(FootageError, match=r"needs py-gpmf-parser .*pip install 'py-gpmf-parser>=0\.1\.1,<1'"):
        open_footage(synthetic)


# ------------------------------------------------------------------ the real clips
CLIPS = {"gopro_max_walk.mp4": dict(speed=1.21, model="GoPro Max", orin="XzY", iori=True),
         "gopro_hero7_walk.mp4": dict(speed=1.78, model="HERO7 Black", orin="YxZ", iori=False)}


@pytest.fixture(scope="module", params=sorted(CLIPS))
def clip(request, tmp_path_factory):
    path = GOPRO / request.param
    if not path.exists():
        pytest.skip(f"GoPro clip not found at {path} (../shared/data is beside the repo in CI)")
    # only the image size matters to these tests: the flow is measured in pixels
    cam = camera_json(tmp_path_factory.mktemp("cam") / "camera.json", 848, 480)
    return path, CLIPS[request.param], open_footage(path, camera=cam)


@needs_gpmf
def test_real_clip_streams_gravity_and_gps(clip):
    path, want, fo = clip
    assert fo.kind == "gopro" and fo.telemetry["model"] == want["model"]
    imu, t = fo.imu, fo.imu.time_s
    rate = (len(t) - 1) / (t[-1] - t[0])
    assert 190 < rate < 205 and fo.telemetry["streams"]["GYRO"]["samples"] == len(t)
    assert np.all(np.diff(t) > 0) and abs(t[0] - fo.times[0]) < 0.01
    # the telemetry spans the video (the HERO7's track ends with its last whole packet, 0.7 s early)
    assert t[-1] - t[0] > 0.9 * (fo.times[-1] - fo.times[0])
    # averaged over whole strides the accelerometer reads gravity, pointing up: −y in the camera frame
    g = imu.accel.mean(0)
    assert abs(np.linalg.norm(g) / G - 1) < 0.03 and g[1] < -0.95 * np.linalg.norm(g)
    gps_t = fo.gps["time_s"]
    assert 17.5 < (len(gps_t) - 1) / (gps_t[-1] - gps_t[0]) < 18.5 and np.all(np.diff(gps_t) > 0)
    assert abs(np.mean(fo.truth["v_forward_m_s"]) - want["speed"]) < 0.01
    assert set(fo.truth["gps_fix"]) == {3}
    st = fo.telemetry["stabilisation"]
    assert st["electronic"] is True and st["source"].startswith("camera settings")
    assert (st["image_orientation_max_deg"] is not None) == want["iori"]
    assert want["orin"] in fo.telemetry["streams"]["ACCL"]["axes"]


@needs_gpmf
def test_real_clip_frames_stop_where_the_telemetry_does(clip):
    """The HERO7's telemetry ends 0.7 s before its video: those frames are left out with a note, and the rest
    all have IMU samples around them (the MAX's telemetry spans its video: nothing left out)."""
    path, want, fo = clip
    left = [n for n in fo.notes if "left out (no IMU samples around them)" in n]
    assert fo.times[-1] <= fo.imu.time_s[-1] + 1 / 29.97
    assert (len(left) == 1) == (want["model"] == "HERO7 Black")
    if left:
        assert len(fo) == len(list(fo.frames())) < 351


def _payloads_by_gopros_reader(path: Path):
    """(t_in, t_out, bytes) of every GPMF packet through GoPro's own MP4 reader (not FFmpeg)."""
    pg = pytest.importorskip("py_gpmf_parser")
    h = pg.OpenMP4Source(str(path), pg.MOV_GPMF_TRAK_TYPE, pg.MOV_GPMF_TRAK_SUBTYPE, 0)
    assert h
    try:
        out = []
        for i in range(pg.GetNumberPayloads(h)):
            size = pg.GetPayloadSize(h, i)
            words = pg.GetPayload(h, pg.GetPayloadResource(h, 0, size), i, size)
            _, t_in, t_out = pg.GetPayloadTime(h, i)
            out.append((t_in, t_out, np.asarray(words, np.uint32).tobytes()[:size]))
        return out
    finally:
        pg.CloseSource(h)


def _klv_walk(buf: bytes):
    """(key, type, struct size, repeat, payload) of every KLV, nests entered (a STRM is yielded before its contents)."""
    pos = 0
    while pos + 8 <= len(buf):
        key, tc, size, rep = buf[pos:pos + 4].decode("latin-1"), buf[pos + 4], buf[pos + 5], \
            int.from_bytes(buf[pos + 6:pos + 8], "big")
        body = buf[pos + 8:pos + 8 + size * rep]
        yield key, chr(tc), size, rep, body
        if tc == 0:
            yield from _klv_walk(body)
        pos += 8 + size * rep + (-(size * rep) % 4)


def _second_reader(path: Path, key: str):
    """(times, samples in the camera frame) of ACCL or GYRO: GoPro's MP4 reader + the KLV walk above,
    SCAL applied here and ORIN's order mapped by imu_axes_to_camera."""
    ts, vs = [], []
    for t_in, t_out, buf in _payloads_by_gopros_reader(path):
        scal = orin = None
        for k, tc, size, rep, body in _klv_walk(buf):
            if k == "STRM":
                scal = orin = None
            elif k == "SCAL":
                scal = np.frombuffer(body, ">i2" if tc == "s" else ">i4").astype(float)
            elif k == "ORIN":
                orin = body.decode("latin-1")
            elif k == key:
                raw = np.frombuffer(body, ">i2").reshape(rep, size // 2) / scal
                vs.append(raw @ imu_axes_to_camera(orin).T)
                ts.append(t_in + np.arange(rep) * (t_out - t_in) / rep)
    return np.concatenate(ts), np.concatenate(vs)


@needs_gpmf
def test_real_clip_matches_a_second_reader(clip):
    path, _, fo = clip
    t2, a2 = _second_reader(path, "ACCL")
    _, g2 = _second_reader(path, "GYRO")
    assert len(t2) == len(fo.body_imu.time_s)
    assert np.max(np.abs(t2 - fo.body_imu.time_s)) < 1e-3
    assert np.allclose(a2, fo.body_imu.accel, rtol=0, atol=1e-9) and np.allclose(g2, fo.body_imu.gyro, rtol=0, atol=1e-9)


@needs_gpmf
def test_real_clip_matches_telemetry_parser(clip):
    tp = pytest.importorskip("telemetry_parser", reason="gyroflow's telemetry-parser is an optional cross-check")
    path, _, fo = clip
    acc = []
    for group in tp.Parser(str(path)).telemetry():
        a = group.get("Accelerometer")
        if a and a.get("Data"):
            raw = np.array([[s["x"], s["y"], s["z"]] for s in a["Data"]], float)
            m = np.asarray(a["Matrix"][0], float).reshape(3, 3)
            acc.append(raw @ m.T / float(a["Scale"]) @ GOPRO_TO_CAMERA.T)
    assert np.allclose(np.concatenate(acc), fo.body_imu.accel, atol=1e-6)


@needs_gpmf
def test_real_clip_through_gyroflows_axes_is_the_same_imu(clip):
    """telemetry-parser's samples in Gyroflow's frame (x up, y left, z back), turned into the camera's by
    lobula.readers.camera_telemetry, are this reader's sample for sample: the axis map other cameras' logs
    take is right. Its times spread the samples evenly over the whole clip, this reader's over each packet's
    span: on the HERO7 they part by up to 0.14 s mid-clip, on the MAX by 4 ms."""
    pytest.importorskip("telemetry_parser", reason="telemetry-parser has wheels for CPython 3.8-3.12 only")
    from lobula.readers.camera_telemetry import read_motion_log

    path, _, fo = clip
    log = read_motion_log(path)
    assert log["camera"] == "GoPro" and len(log["time_s"]) == len(fo.body_imu.time_s)
    np.testing.assert_allclose(log["accel"], fo.body_imu.accel, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log["gyro"], fo.body_imu.gyro, rtol=0, atol=1e-9)
    assert np.max(np.abs(log["time_s"] - fo.body_imu.time_s)) < 0.2


@needs_gpmf
def test_real_clip_without_gopros_parser_is_read_by_telemetry_parser(clip, monkeypatch):
    """Where py-gpmf-parser is not installed (it has Linux x86-64 wheels only), a GoPro MP4 opens as
    camera-telemetry: the same IMU samples, the same GPS truth (times, speeds, fixes, DOPs) from telemetry-parser's
    decoding timed by the MP4's telemetry track, the same camera and image orientations (CORI, IORI) and so the same
    IMU turned into the stabilised image's frame (to the parsers' 4 ms apart in timing the IMU), the same lens guess
    (the stated field of view, where there is one), the stabilisation said, and a note that says which parser read
    it and why."""
    pytest.importorskip("telemetry_parser", reason="telemetry-parser has wheels for CPython 3.8-3.12 only")
    import lobula.readers as readers
    from lobula.readers.camera_telemetry import open_camera_telemetry

    path, want, fo = clip
    monkeypatch.setattr(readers, "gpmf_parser_installed", lambda: False)
    assert readers._reader_for(path).name == "camera-telemetry"
    got = open_camera_telemetry(path)
    assert got.kind == "camera-telemetry" and got.truth is not None and fo.truth is not None
    assert any("py-gpmf-parser" in n and "image orientations" in n for n in got.notes), got.notes
    assert any(n.startswith("truth is GPS (GPS5, telemetry-parser)") for n in got.notes), got.notes
    assert any(n.startswith("electronic stabilisation on (HS ") for n in got.notes), got.notes
    stated = fo.telemetry["lens"]["diagonal_fov_deg"]       # the GPMF reader's reading of ZFOV (the MAX's 137.4°)
    assert got.lens_guess["diagonal_fov_deg"] == round(stated or 135.0, 3), got.lens_guess
    assert ("ZFOV" in got.lens_guess["source"]) == (stated is not None)
    assert sorted(got.orientation) == sorted(k for k in fo.orientation if k != "GRAV")
    for key, (t, q) in got.orientation.items():
        np.testing.assert_allclose(t, fo.orientation[key][0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(q, fo.orientation[key][1][:, :4], rtol=0, atol=1e-9)
    turned = any(n.startswith("IMU turned into the stabilised image's frame") for n in got.notes)
    assert turned == want["iori"] == (fo.telemetry["stabilisation"]["imu_frame"] == "image")
    if turned:
        assert min(np.corrcoef(got.imu.gyro[:, j], fo.imu.gyro[:, j])[0, 1] for j in range(3)) > 0.99
    else:
        np.testing.assert_allclose(got.imu.gyro, fo.body_imu.gyro, rtol=0, atol=1e-9)
    for key in ("time_s", "v_forward_m_s", "gps_speed_3d_m_s", "gps_fix", "gps_dop"):
        np.testing.assert_allclose(got.truth[key], fo.truth[key], rtol=0, atol=1e-9, err_msg=key)


def test_a_gopro_file_neither_parser_reads_names_what_to_install(synthetic, monkeypatch):
    """telemetry-parser cannot read the synthetic MP4 either: without GoPro's parser it is one line saying how to
    install it."""
    import sys

    import lobula.readers as readers

    monkeypatch.setattr(readers, "gpmf_parser_installed", lambda: False)
    monkeypatch.setitem(sys.modules, "py_gpmf_parser", None)   # its import fails as where it is not installed
    assert readers._reader_for(synthetic).name == "gopro"
    with pytest.raises(FootageError, match="needs py-gpmf-parser"):
        open_footage(synthetic)


@needs_gpmf
def test_real_clip_gyro_turns_the_image_the_right_way(clip):
    """The body's gyro, in the camera frame, against the image's mean flow (DIS at quarter size): turning right
    (ω_y > 0) moves the image left (u < 0), tilting up (ω_x > 0) moves it down (v > 0). HyperSmooth takes
    out most of the fast rotation (the HERO7's nearly all of it), so the slow part (1 s) carries the sign."""
    path, want, fo = clip
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
    prev, rows = None, []
    for _, t, img in fo.frames():
        small = cv2.resize(img, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA).astype(np.uint8)
        if prev is not None and t <= fo.body_imu.time_s[-1]:
            flow = dis.calc(prev[1], small, None)
            rows.append((prev[0], t, flow[..., 0].mean() * 4, flow[..., 1].mean() * 4))
        prev = (t, small)
    t0, t1, u, v = np.array(rows).T
    ti = fo.body_imu.time_s
    w = np.array([fo.body_imu.gyro[(ti >= a) & (ti < b)].mean(0) for a, b in zip(t0, t1)])
    slow = lambda x: uniform_filter1d(x, 31, mode="nearest")  # noqa: E731
    yaw, pitch = np.corrcoef(slow(w[:, 1]), slow(u))[0, 1], np.corrcoef(slow(w[:, 0]), slow(v))[0, 1]
    assert yaw < 0 and pitch > 0.5, (yaw, pitch)
    if want["iori"]:  # the MAX's image follows the turns frame by frame as well
        assert np.corrcoef(w[:, 1], u)[0, 1] < -0.5


def _pair_mean(imu, t0, t1):
    """(n, 3) rad/s: ``imu``'s gyro averaged over each interval [t0, t1) (s)."""
    ti = imu.time_s
    return np.array([imu.gyro[(ti >= a) & (ti < b)].mean(0) for a, b in zip(t0, t1)])


@needs_gpmf
def test_real_clip_imu_follows_the_stabilised_image(clip, tmp_path):
    """The MAX writes its body's and its image's orientations (CORI, IORI): its IMU is turned into the stabilised
    image's frame, where the image's own rotation rates follow the gyro's, as the body's gyro does not. The
    HERO7 writes no IORI: its IMU stays the body's. Asked not to, the reader keeps the body's."""
    from lobula.readers.clock_offset import image_rotation_rates
    from lobula.readers.gopro import open_gopro

    path, want, fo = clip
    st = fo.telemetry["stabilisation"]
    if not want["iori"]:
        assert st["imu_frame"] == "body" and fo.imu is fo.body_imu
        return
    assert st["imu_frame"] == "image" and st["orientation_gyro_agreement"] > 0.8
    assert any(n.startswith("IMU turned into the stabilised image's frame") for n in fo.notes), fo.notes
    t, w_img = image_rotation_rates(fo, width=160)
    dt = np.diff(fo.times)[:len(t)]
    t0, t1 = t - dt / 2, t + dt / 2
    corr = lambda w: [np.corrcoef(w_img[:, j], w[:, j])[0, 1] for j in range(3)]  # noqa: E731
    image, body = corr(_pair_mean(fo.imu, t0, t1)), corr(_pair_mean(fo.body_imu, t0, t1))
    assert image[0] > 0.9 and image[1] > 0.9 and image[2] > 0.7, image
    assert max(body) < 0.7, body
    kept = open_gopro(path, camera_json=camera_json(tmp_path / "camera.json", 848, 480), image_orientation=False)
    assert kept.telemetry["stabilisation"]["imu_frame"] == "body"
    np.testing.assert_array_equal(kept.imu.gyro, fo.body_imu.gyro)


@needs_gpmf
def test_real_clip_info(clip, capsys):
    path, want, _ = clip
    code, out, _ = cli(capsys, "info", path)
    assert code == 0 and f"gopro:      {want['model']}" in out
    speed = float(re.search(r"mean 2D speed ([0-9.]+) m/s", out).group(1))
    assert abs(speed - want["speed"]) < 0.01 and "stabilisation: electronic on" in out
    assert ("IMU in the stabilised image's frame" in out) == want["iori"]


@needs_gpmf
@pytest.mark.slow  # the whole MAX clip through every self-calibration (36 s); the reader's tests above run in make test
def test_real_clip_without_a_camera_file_says_it_cannot_know(tmp_path, capsys):
    """`lobula velocity CLIP.mp4` with nothing else: the lens from the stated field of view (the gyro cannot measure it
    through the stabilised image), the clock offset said, and — vision's expansion not following the accelerometer
    on a walk — no speed claimed, with the reason."""
    path = GOPRO / "gopro_max_walk.mp4"
    if not path.exists():
        pytest.skip(f"GoPro clip not found at {path} (../shared/data is beside the repo in CI)")
    o = tmp_path / "run.nc"
    code, out, _ = cli(capsys, "velocity", path, "--out", o, "--quiet")
    assert code == 0
    assert "lens: equidistant fisheye" in out and "ZFOV 137.4" in out and "clock offset:" in out
    assert "never observable: the image's expansion never followed the accelerometer" in out
    ds = xr.open_dataset(o)
    assert not ds.observable.values.any() and not ds.vision_locked.values.any()
    assert ds.vision_coupling.max() < 3.0
    assert "camera_calibration" in ds.attrs


@needs_gpmf
@pytest.mark.parametrize("name, filt, front", [
    pytest.param("gopro_hero7_walk", "zero-phase", "dis", marks=pytest.mark.slow),
    pytest.param("gopro_max_walk", "causal", "dis", marks=pytest.mark.slow),
    pytest.param("gopro_hero7_walk", "causal", "dis", marks=pytest.mark.slow),
    pytest.param("gopro_hero7_walk", "causal", "emd", marks=pytest.mark.slow)])
def test_real_clip_is_never_confidently_wrong(tmp_path, capsys, name, filt, front):
    """On both walks, offline and online, with nothing but the clip: where a speed is claimed, the GPS speed lies
    inside ±2σ on at least 80 % of those frames; a flow whose expansion reverses its sign on a steady walk (the
    HERO7's) does not lock vision on. The EMD front end online on the HERO7 reads the walker's bob as two sign
    changes of the expansion within 0.2 s and a κ of the wrong sign in its first second: taken in, they held
    v̂ near 0 ± 0.1 m/s while the GPS read 1.7-2.1. The MAX offline is the test above; all run under ``slow``."""
    path = GOPRO / f"{name}.mp4"
    if not path.exists():
        pytest.skip(f"GoPro clip not found at {path} (../shared/data is beside the repo in CI)")
    o = tmp_path / "run.nc"
    code, out, _ = cli(capsys, "velocity", path, "--out", o, "--filter", filt, "--front-end", front, "--quiet")
    assert code == 0
    ds = xr.open_dataset(o)
    obs = ds.observable.values.astype(bool)
    if obs.any():
        e = np.abs(ds.v_hat.values[obs] - ds.v_true.values[obs])
        assert np.mean(e <= 2 * ds.v_std.values[obs]) >= 0.8
    else:
        assert "never observable" in out


@needs_gpmf
def test_real_clip_gravity_follows_the_cameras_own(tmp_path):
    """The MAX writes its own gravity direction once per frame (GRAV, in the camera's axes). The pipeline's
    gravity, the gyro-tracked mean specific force (lobula.imu.gravity_free_acceleration), lies within 0.8° of it at
    the median and 2.9° at the 95th percentile; the specific force itself, which holds the walk's accelerations,
    strays 3.3° at the median (9.0° at the 95th percentile)."""
    from lobula.imu.gravity import gravity_free_acceleration

    path = GOPRO / "gopro_max_walk.mp4"
    if not path.exists():
        pytest.skip(f"GoPro clip not found at {path} (../shared/data is beside the repo in CI)")
    fo = open_footage(path, camera=camera_json(tmp_path / "camera.json", 848, 480))
    imu = fo.body_imu
    t, grav = fo.orientation["GRAV"]

    def angles(v):
        at = np.stack([np.interp(t, imu.time_s, v[:, j]) for j in range(3)], 1)
        cos = np.sum(at * grav[:, :3], 1) / np.linalg.norm(at, axis=1) / np.linalg.norm(grav[:, :3], axis=1)
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    ours = angles(gravity_free_acceleration(imu.time_s, imu.accel, imu.gyro) - imu.accel)
    raw = angles(-imu.accel)
    assert np.median(ours) < 1.5 and np.percentile(ours, 95) < 4.0, (np.median(ours), np.percentile(ours, 95))
    assert np.median(raw) > 2 * np.median(ours)
