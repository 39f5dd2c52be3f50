"""Issue 10's rotation: flow under fast turns (gyro pre-warp) and what the gyro leaves to vision."""
import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from lobula.camera import PinholeCamera
from lobula.flow import FlowConfig, make_flow_fn, prewarp_flow, rotation_warp


def _textured(cam, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur((rng.random((cam.height, cam.width)) * 255).astype(np.uint8), (0, 0), 2)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)


def test_prewarp_recovers_a_fast_turn_that_plain_dis_loses():
    """A pure rotation of 0.13 rad (0.65 rad/s over a 0.2 s pair) moves the 320×240 image up to
    ~60 px; DIS alone misses it, with the gyro's rotation pre-warped the raw flow is exact."""
    cam = PinholeCamera().scaled(0.5)
    a = _textured(cam)
    r01 = Rotation.from_rotvec([0.05, -0.12, 0.04]).as_matrix()
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    iu, iv = rotation_warp(cam, r01.T)(u, v)  # b(q) = a(W⁻¹ q): what the turned camera sees
    b = cv2.remap(a, iu.astype(np.float32), iv.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    wu, wv = rotation_warp(cam, r01)(u, v)
    true = np.stack([wu - u, wv - v])
    fn = make_flow_fn(FlowConfig())
    inner = (slice(None), slice(30, -30), slice(40, -40))
    pre = prewarp_flow(fn, a, b, cam, r01)
    err_pre = np.nanmedian(np.abs(pre - true)[inner])
    err_raw = np.median(np.abs(fn(a, b) - true)[inner])
    assert np.abs(true).max() > 40
    # NaN exactly where the point leaves the view (to within a pixel of the edge).
    gone = (wu < -1) | (wu > cam.width) | (wv < -1) | (wv > cam.height)
    stays = (wu > 1) & (wu < cam.width - 2) & (wv > 1) & (wv < cam.height - 2)
    assert np.isnan(pre[0][gone]).all() and gone.sum() > 1000
    assert np.isfinite(pre[0][stays]).mean() > 0.99
    assert err_pre < 0.05, err_pre
    assert err_raw > 20 * err_pre, (err_raw, err_pre)


def test_prewarp_of_no_rotation_is_the_plain_flow():
    cam = PinholeCamera().scaled(0.5)
    a = _textured(cam, 1)
    b = np.roll(a, 3, axis=1)
    fn = make_flow_fn(FlowConfig())
    np.testing.assert_array_equal(prewarp_flow(fn, a, b, cam, np.eye(3)), fn(a, b))


def test_vision_gyro_bias_tracks_a_drifting_bias_from_noisy_residuals():
    """Residual rates = a random-walk bias + noise 10 mrad/s (what a 320×240 flow pair gives)
    + a few wild pairs: the filter follows the bias to well within the prior, its std covers
    the error, and the causal estimate converges too."""
    from lobula.haltere import vision_gyro_bias

    rng = np.random.default_rng(3)
    t_imu = np.arange(0.0, 20.0, 0.004)
    walk = 3e-4  # rad/s²/√Hz: three times the filter's own assumption (haltere.GYRO_BIAS_WALK)
    bias = np.radians([0.2, -0.25, 0.1]) + np.cumsum(rng.normal(0, walk * np.sqrt(0.004), (t_imu.size, 3)), 0)
    t_m = np.arange(0.1, 20.0, 0.2)
    z = np.stack([np.interp(t_m, t_imu, bias[:, k]) for k in range(3)], -1) + rng.normal(0, 0.01, (t_m.size, 3))
    z[::17] += rng.normal(0, 0.1, z[::17].shape)  # outlying pairs (flow failures)
    for causal in (False, True):
        b, s = vision_gyro_bias(t_m, z, t_imu, np.zeros(3), np.radians(0.2), causal)
        late = t_imu > 5.0
        err = b[late] - bias[late]
        rms = np.sqrt(np.mean(err ** 2, 0))
        still_only = np.sqrt(np.mean(bias[late] ** 2, 0))  # gyro_bias gives 0 for a camera that never stops
        assert np.all(rms < 0.5 * still_only), (causal, rms, still_only)
        assert np.all(rms < 2e-3), (causal, rms)
        cover = np.mean(np.abs(err) <= 2 * s[late])
        print(causal, rms, still_only, cover)
        assert 0.8 <= cover, (causal, cover)
        assert np.all(s[late] < np.radians(0.2))


def test_vision_gyro_bias_without_measurements_is_the_prior():
    from lobula.haltere import vision_gyro_bias

    t = np.linspace(0, 1, 11)
    b, s = vision_gyro_bias(np.zeros(0), np.zeros((0, 3)), t, np.array([1e-3, 0, 0]), 2e-3, causal=True)
    np.testing.assert_allclose(b, np.broadcast_to([1e-3, 0, 0], (11, 3)))
    np.testing.assert_allclose(s, 2e-3)


def test_gyro_bias_from_vision_on_a_turning_scene_with_a_drifting_bias(tmp_path):
    """The rotation family's scene (realistic IMU on a rotated mount, dev seed 9, not a suite
    seed) for 4 s, with the gyro bias walking 5× faster than the BMI055 figure so that it
    drifts through the record. The camera never stops turning, so the still-camera estimate
    (lobula.haltere.gyro_bias) has nothing and leaves the whole bias; the flow's residual
    rotation must recover it to within half of that, with a std that covers its error."""
    from dataclasses import replace

    from experiments import suite
    from experiments.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from lobula.haltere import gyro_bias
    from stimuli.footage import open_footage
    from stimuli.track import build_track, make_track_run

    cfg = suite.family_config("rotation", 9, 4.0, 0.5)
    cfg = replace(cfg, imu=replace(cfg.imu, gyro_bias_walk=2e-4), depth_every=1000)
    make_track_run(tmp_path / "run", cfg, progress=False)
    fo = open_footage(tmp_path / "run")
    _, imu = build_track(cfg)
    truth_imu = imu["gyro_bias_t"] @ imu["imu_to_camera"].T  # camera frame
    assert np.abs(gyro_bias(fo.imu.time_s, fo.imu.gyro)).max() == 0.0  # never still: nothing from the gyro alone
    for filt in ("zero-phase", "causal"):
        vc = VelocityConfig(gyro_bias_from_vision=True)
        vc.readout.filter = filt
        ds = estimate_velocity(fo, vc, progress=False)
        t = ds.time.values
        truth = np.stack([np.interp(t, imu["time_s"], truth_imu[:, k]) for k in range(3)], -1)
        late = t > (1.0 if filt == "zero-phase" else 2.0)
        err = ds.gyro_bias.values[late] - truth[late]
        rms = np.sqrt(np.mean(err ** 2))
        still_only = np.sqrt(np.mean(truth[late] ** 2))
        cover = np.mean(np.abs(err) <= 2 * ds.gyro_bias_std.values[late])
        print(f"\n{filt}: bias error rms {1e3 * rms:.2f} mrad/s (still-only {1e3 * still_only:.2f}), ±2σ {cover:.2f}")
        assert rms < 0.5 * still_only
        assert cover >= 0.8


def test_gyro_bias_from_vision_option_reaches_the_config():
    import argparse

    from experiments.velocity import _velocity_config, add_parser

    p = argparse.ArgumentParser()
    add_parser(p.add_subparsers())
    on = _velocity_config(p.parse_args(["velocity", "x", "--out", "y.nc", "--gyro-bias-from-vision"]))
    off = _velocity_config(p.parse_args(["velocity", "x", "--out", "y.nc"]))
    assert on.gyro_bias_from_vision and not off.gyro_bias_from_vision
    assert off.flow.prewarp and not _velocity_config(p.parse_args(["velocity", "x", "--out", "y.nc", "--paper"])).flow.prewarp
