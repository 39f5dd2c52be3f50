"""Rotation: flow under fast turns (gyro pre-warp) and what the gyro leaves to vision."""
import cv2
import numpy as np
import pytest
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
    from lobula.imu import vision_gyro_bias

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
    from lobula.imu import vision_gyro_bias

    t = np.linspace(0, 1, 11)
    b, s = vision_gyro_bias(np.zeros(0), np.zeros((0, 3)), t, np.array([1e-3, 0, 0]), 2e-3, causal=True)
    np.testing.assert_allclose(b, np.broadcast_to([1e-3, 0, 0], (11, 3)))
    np.testing.assert_allclose(s, 2e-3)


@pytest.mark.parametrize("from_residual", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_gyro_bias_from_vision_on_a_turning_scene_with_a_drifting_bias(tmp_path, from_residual):
    """The rotation family's scene (realistic IMU on a rotated mount, dev seed 9, not a suite
    seed) for 4 s, with the gyro bias walking 5× faster than the BMI055 figure so that it
    drifts through the record. The camera never stops turning, so the still-camera estimate
    (lobula.imu.gyro_bias) has nothing and leaves the whole bias; the flow must recover it to
    within half of that, with a std that covers its error — from its residual rotation
    (``gyro_bias_from_vision``) or, by default, from the heading and bias fit fused with the
    still-camera estimate. Gravity removed through that attitude then ramps less through the
    forward acceleration than through the still-camera one (which ramps at the whole bias)."""
    from dataclasses import replace

    from experiments import suite
    from lobula.velocity import estimate_velocity
    from lobula.velocity.inertial import forward_accel_at
    from lobula.config import VelocityConfig
    from lobula.imu import gyro_bias
    from lobula.readers import open_footage
    from stimuli.track import build_track, make_track_run

    cfg = suite.family_config("rotation", 9, 4.0, 0.5)
    cfg = replace(cfg, imu=replace(cfg.imu, gyro_bias_walk=2e-4), depth_every=1000)
    make_track_run(tmp_path / "run", cfg, progress=False)
    fo = open_footage(tmp_path / "run")
    _, imu = build_track(cfg)
    truth_imu = imu["gyro_bias_t"] @ imu["imu_to_camera"].T  # camera frame
    assert np.abs(gyro_bias(fo.imu.time_s, fo.imu.gyro)).max() == 0.0  # never still: nothing from the gyro alone
    for filt in ("zero-phase", "causal"):
        vc = VelocityConfig(gyro_bias_from_vision=from_residual)
        vc.readout.filter = filt
        ds = estimate_velocity(fo, vc, progress=False)
        t = ds.time.values
        truth = np.stack([np.interp(t, imu["time_s"], truth_imu[:, k]) for k in range(3)], -1)
        late = t > (1.0 if filt == "zero-phase" else 2.0)
        err = ds.gyro_bias.values[late] - truth[late]
        rms = np.sqrt(np.mean(err ** 2))
        still_only = np.sqrt(np.mean(truth[late] ** 2))
        cover = np.mean(np.abs(err) <= 2 * ds.gyro_bias_std.values[late])
        # The acceleration's error, its slow part: the offset the readout learns, and the ramp.
        a_true = np.interp(t, fo.truth["time_s"], fo.truth["a_forward_m_s2"])
        a_still, _ = forward_accel_at(fo, t, vc, bias=None)
        ramp = lambda a: abs(np.polyfit(t, a - a_true, 1)[0])  # noqa: E731  m/s² per s
        print(f"\n{filt}: bias error rms {1e3 * rms:.2f} mrad/s (still-only {1e3 * still_only:.2f}), ±2σ {cover:.2f}; "
              f"acceleration ramp {ramp(ds.accel.values):.3f} m/s²/s (still-only {ramp(a_still):.3f})")
        assert rms < 0.5 * still_only
        assert cover >= 0.8
        assert ramp(ds.accel.values) < 0.5 * ramp(a_still)


def test_gyro_bias_from_vision_option_reaches_the_config():
    import argparse

    from experiments.velocity import _velocity_config, add_parser

    p = argparse.ArgumentParser()
    add_parser(p.add_subparsers())
    on = _velocity_config(p.parse_args(["velocity", "x", "--out", "y.nc", "--gyro-bias-from-vision"]))
    off = _velocity_config(p.parse_args(["velocity", "x", "--out", "y.nc"]))
    assert on.gyro_bias_from_vision and not off.gyro_bias_from_vision
    assert off.flow.prewarp and not _velocity_config(p.parse_args(["velocity", "x", "--out", "y.nc", "--paper"])).flow.prewarp


# ---------------------------------------------------------------- gyro integration and the bias under rotation
def _turning_scene(cam, duration_s=4.0, speed=None, seed=5):
    from stimuli.scene import SceneConfig, TrackScene
    from stimuli.trajectory import trajectory_from_function

    speed = speed or (lambda t: np.zeros_like(t))
    return TrackScene(cam, trajectory_from_function(speed, duration_s),
                      SceneConfig(rotation3_amp_deg=(5.0, 4.0, 5.0), seed=seed, noise_grey=0))


def test_integrated_gyro_gives_each_pairs_rotation_exactly():
    """The rotation family's 3-axis turn (±4–5°, 0.3–1.5 Hz) read by a perfect 250 Hz gyro: each
    0.2 s pair's rotation from the integrated rates matches the scene's to 0.2 mrad/s. The
    rectangle rule (each sample's rate held over the step before it) runs half a sample late
    and misses by mrad/s — as much as a MEMS gyro's bias — which is what the trapezoid fixed."""
    from lobula.imu import orientation_from_gyro
    from stimuli.imu import angular_velocity

    scene = _turning_scene(PinholeCamera().scaled(0.25))
    t = np.arange(0.0, 4.0, 0.004)
    w = angular_velocity(scene.rotation, t)
    exact = scene.rotation(t)

    def pair_errors(q):
        i0 = np.arange(100, 900, 10)
        return np.array([np.linalg.norm(Rotation.from_matrix((exact[a].T @ exact[a + 50]).T @ (q[a].T @ q[a + 50]))
                                        .as_rotvec()) / 0.2 for a in i0])

    q = orientation_from_gyro(t, w, bias=np.zeros_like(w))
    steps = Rotation.from_rotvec(w * np.diff(t, prepend=t[0])[:, None]).as_matrix()
    rect = np.empty_like(q)
    r = np.eye(3)
    for k in range(len(t)):
        r = r @ steps[k]
        rect[k] = r
    new, old = pair_errors(q), pair_errors(rect)
    print(f"\npair rotation error: trapezoid {1e3 * new.max():.3f} mrad/s, rectangle {1e3 * np.median(old):.2f} (median)")
    assert new.max() < 2e-4
    assert np.median(old) > 1e-3


def test_gyro_attitude_is_causal_and_follows_a_changed_bias():
    """GyroAttitude integrates like orientation_from_gyro, never revises what it integrated, and
    says which correction (bias + E·rate) it removed over a stretch."""
    from lobula.imu import GyroAttitude, orientation_from_gyro

    t = np.arange(0.0, 2.0, 0.004)
    w = np.stack([0.3 * np.sin(6 * t), 0.2 * np.cos(4 * t), 0.1 + 0 * t], -1)
    b = np.array([0.01, -0.02, 0.005])
    q = orientation_from_gyro(t, w, bias=np.broadcast_to(b, w.shape))
    att = GyroAttitude(t, w, b)
    np.testing.assert_allclose(att(t[[10, 200, 499]]), q[[10, 200, 499]], atol=1e-12)
    att2 = GyroAttitude(t, w, b)
    first = att2(np.array([1.0]))
    att2.bias = np.zeros(3)
    att2.scale = np.eye(3) * 0.01
    np.testing.assert_allclose(att2(np.array([1.0])), first, atol=1e-12)  # what is integrated stays
    att2(np.array([1.6]))
    c, wbar = att2.applied_correction(1.2, 1.4)
    sel = (t >= 1.2) & (t < 1.4)
    np.testing.assert_allclose(c, 0.01 * w[sel].mean(0), atol=1e-12)
    np.testing.assert_allclose(wbar, w[sel].mean(0), atol=1e-12)


def test_heading_and_gyro_bias_from_exact_flow_of_a_turning_camera():
    """Exact flow (TrackScene.flow) of the rotation family's turn while flying at 0.05–0.55 m/s,
    read by a gyro with a 0.45 °/s bias and 1–2 % scale and misalignment errors. The plain
    epipole fit on that gyro's derotation is pulled by δω/r (degrees at low speed); fitted
    jointly (HeadingBiasEstimator, the attitude following its estimate) the bias comes out to
    within 25 % and the epipole to within a fraction of the plain one's error."""
    from lobula.epipole import EpipoleEstimator, HeadingBiasEstimator, derotate_finite
    from lobula.imu import GyroAttitude, orientation_from_gyro
    from stimuli.imu import angular_velocity

    cam = PinholeCamera().scaled(0.25)
    scene = _turning_scene(cam, 4.0, lambda t: 0.3 - 0.25 * np.cos(2 * np.pi * t / 3.0), seed=7)
    t = np.arange(0.0, 4.0, 0.004)
    bias = np.array([0.006, -0.005, 0.004])
    E = np.array([[0.015, 0.008, -0.005], [-0.006, -0.01, 0.007], [0.004, -0.008, 0.012]])
    gyro = angular_velocity(scene.rotation, t) @ (np.eye(3) + E).T + bias
    x, y = cam.normalised_grid()
    stride = 2
    joint = HeadingBiasEstimator(x, y, np.zeros(3), np.radians(0.2), stride=stride, scale_std=0.02)
    plain = EpipoleEstimator(x, y, stride=stride)
    att = GyroAttitude(t, gyro, np.zeros(3))
    q_plain = orientation_from_gyro(t, gyro, bias=np.zeros_like(gyro))
    from scipy.spatial.transform import Slerp
    plain_att = Slerp(t, Rotation.from_matrix(q_plain))
    R0 = scene.rotation(0.0)
    errs = {"joint": [], "plain": []}
    for t0 in np.arange(0.1, 3.7, 0.1):
        t1, tm = t0 + 0.2, t0 + 0.1
        flow = (scene.flow(t0, t1) / 0.2)[:, ::stride, ::stride].reshape(2, -1)
        for name in errs:
            if name == "joint":
                q = att(np.array([t0, t1, tm]))
                c, wbar = att.applied_correction(t0, t1)
            else:
                q = plain_att(np.array([t0, t1, tm])).as_matrix()
            pts = derotate_finite(joint.x, joint.y, flow, 0.2, q[2].T @ q[0], q[2].T @ q[1])
            if name == "joint":
                e = joint.update(None, points=pts, attitude=q[2], applied_bias=c, rate=wbar)
                att.bias, att.scale = joint.bias, joint.scale
            else:
                e = plain.update(None, points=pts, attitude=q[2])
            # The true heading seen in this (estimated) middle orientation.
            h = q[2].T @ R0.T @ scene.rotation(tm) @ np.array([*scene.epipole(tm), 1.0])
            errs[name].append(np.degrees(np.hypot(*(np.arctan(e) - np.arctan(h[:2] / h[2])))))
    joint_err, plain_err = np.median(errs["joint"][5:]), np.median(errs["plain"][5:])
    berr = np.linalg.norm(joint.bias - bias) / np.linalg.norm(bias)
    print(f"\nepipole error (median after 0.5 s): joint {joint_err:.2f}°, plain {plain_err:.2f}°; "
          f"bias error {100 * berr:.0f} % of |b|; E error {np.abs(joint.scale - E).max():.4f}")
    assert berr < 0.25
    assert joint_err < 0.5 * plain_err
    assert plain_err > 1.0


def test_gyro_attitude_at_the_first_sample_is_the_identity():
    """Asked first for a time at (or before) the first sample, nothing uninitialised is read."""
    from lobula.imu import GyroAttitude

    t = np.arange(0.0, 1.0, 0.004)
    att = GyroAttitude(t, np.tile([0.1, -0.2, 0.3], (t.size, 1)), np.zeros(3))
    np.testing.assert_allclose(att(np.array([-1.0, 0.0])), np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-12)


def test_fused_gyro_bias_weighs_by_inverse_variance_and_uses_only_what_is_known():
    from lobula.imu import fused_gyro_bias

    t = np.linspace(0.0, 2.0, 21)
    still_b, still_s = np.zeros((21, 3)), np.full(21, 2e-3)
    t_est = np.array([0.5, 1.5])
    est_b = np.array([[1e-3, 0, 0], [2e-3, 0, 0]])
    est_s = np.full((2, 3), 1e-4)           # ×2 below: 2e-4, a hundredth of the still variance
    b, s = fused_gyro_bias(t, still_b, still_s, t_est, est_b, est_s, causal=True, est_std_scale=2.0)
    w = (1 / 2e-4 ** 2) / (1 / 2e-4 ** 2 + 1 / 2e-3 ** 2)
    np.testing.assert_allclose(b[t < 0.5], 0.0)              # nothing from the flow yet
    np.testing.assert_allclose(s[t < 0.5], 2e-3)
    np.testing.assert_allclose(b[(t >= 0.5) & (t < 1.5), 0], w * 1e-3)
    np.testing.assert_allclose(b[t >= 1.5, 0], w * 2e-3)     # the newest estimate known by then
    np.testing.assert_allclose(s[t >= 0.5], 1 / np.sqrt(1 / 2e-4 ** 2 + 1 / 2e-3 ** 2))
    b_off, _ = fused_gyro_bias(t, still_b, still_s, t_est, est_b, est_s, causal=False, est_std_scale=2.0)
    np.testing.assert_allclose(b_off[:, 0], w * 2e-3)         # offline: the last, whole-record estimate


def test_attitude_leak_is_the_gravity_an_earlier_bias_estimate_let_in():
    """A still camera whose gyro reads a 1°/s bias about x; the online estimate is 0 until 2 s, then
    right. The attitude integrated meanwhile turned 2° that never happened, so the forward axis
    keeps |g|·sin 2° of gravity after 2 s: attitude_leak says so from the estimates alone, and
    leak_walk lets the offset move by that much within the second after the estimate moved."""
    from lobula.imu import G, attitude_leak, leak_walk, orientation_from_gyro

    t = np.arange(0.0, 5.0, 1 / 400)
    delta = np.radians(1.0)
    gyro = np.tile([delta, 0.0, 0.0], (len(t), 1))
    track = np.where((t >= 2.0)[:, None], gyro, 0.0)
    f = np.tile([0.0, -G, 0.0], (len(t), 1))               # specific force of a still camera, y down
    rot = orientation_from_gyro(t, gyro, causal=True, bias=track)
    forward_error = f[:, 2] - np.einsum("nji,j->ni", rot, f[0])[:, 2]  # what forward_acceleration keeps of g
    leak = attitude_leak(t, track, f)
    after = t > 2.01
    np.testing.assert_allclose(leak[after], forward_error[after], rtol=0.01)
    assert abs(leak[after].mean()) == pytest.approx(G * np.sin(2 * delta), rel=0.01)
    np.testing.assert_allclose(leak[t < 2.0], 0.0, atol=1e-12)   # the estimate had not moved yet
    walk = leak_walk(np.array([1.0, 2.5, 2.9, 3.5]), t, leak)
    np.testing.assert_allclose(walk, [0.0, abs(leak[-1]), abs(leak[-1]), 0.0], atol=1e-3)
    yaw = attitude_leak(t, np.where((t >= 2.0)[:, None], [0.0, delta, 0.0], 0.0), f)
    np.testing.assert_allclose(yaw, 0.0, atol=1e-12)         # a turn about gravity lets none in


def test_gyro_scale_error_is_fitted_on_a_camera_turning_fast(tmp_path):
    """A camera turning ±10°/±8°/±6° at 0.5–2 Hz (twice the suite's rotation family; up to ~2 rad/s)
    with a realistic IMU whose gyro has 2 % scale-factor and 1 % misalignment errors: E·ω is then a
    residual rotation of up to 0.04 rad/s, ten times the bias, which the derotation leaves in every
    pair. Fitted with the heading (VelocityConfig.gyro_scale_prior, the default 0.02) the speed is
    recovered; not fitted (0) v̂ reads slow. Measured on this scene (8 s at 160×120, zero-phase RMSE
    after 1 s): fitted 0.0063 m/s, not fitted 0.060, zero estimator 0.256 (6 s: 0.020 against 0.040:
    the fit needs seconds of turning)."""
    from dataclasses import replace

    from experiments import suite
    from experiments.velocity import score
    from lobula.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    cfg = suite.family_config("rotation", 9, 8.0, 0.25)
    cfg = replace(cfg, scene=replace(cfg.scene, rotation3_amp_deg=(10.0, 8.0, 6.0), rotation3_band_hz=(0.5, 2.0)),
                  imu=replace(cfg.imu, gyro_scale_std=0.02, gyro_misalign_std=0.01), depth_every=1000)
    make_track_run(tmp_path / "run", cfg, progress=False)
    fo = open_footage(tmp_path / "run")
    rmse = {}
    for prior in (0.02, 0.0):
        ds = estimate_velocity(fo, VelocityConfig(gyro_scale_prior=prior), progress=False)
        rmse[prior] = score(ds, skip_s=1.0)["rmse_m_s"]
    keep = ds.time.values >= ds.time.values[0] + 1.0
    zero = float(np.sqrt(np.mean(ds.v_true.values[keep] ** 2)))
    print(f"\nfitted {rmse[0.02]:.4f}, not fitted {rmse[0.0]:.4f}, zero {zero:.3f} m/s")
    assert rmse[0.02] < 0.5 * rmse[0.0], rmse
    assert rmse[0.02] < 0.2 * zero, (rmse, zero)


def test_an_attitude_integrated_once_serves_the_acceleration_and_the_axis():
    """forward_acceleration and forward_axis given orientation_from_gyro's rotations read exactly what
    they integrate themselves (the pipeline integrates the gyro once for both); a wrong shape is refused."""
    from lobula.imu import forward_acceleration, forward_axis, orientation_from_gyro

    t = np.arange(0, 4, 1 / 250)
    rng = np.random.default_rng(3)
    gyro = np.stack([0.3 * np.sin(2 * np.pi * 0.7 * t), 0.2 * np.cos(2 * np.pi * 0.4 * t), 0.1 * t / 4], -1)
    accel = np.array([0.1, -9.7, 0.4]) + 0.02 * rng.normal(size=(len(t), 3))
    for causal in (False, True):
        rot = orientation_from_gyro(t, gyro, causal)
        np.testing.assert_array_equal(forward_acceleration(t, accel, gyro, causal=causal, orientation=rot),
                                      forward_acceleration(t, accel, gyro, causal=causal))
        np.testing.assert_array_equal(forward_axis(t, gyro, causal, orientation=rot), forward_axis(t, gyro, causal))
    with pytest.raises(ValueError, match="orientation"):
        forward_acceleration(t, accel, gyro, orientation=rot[:-1])
