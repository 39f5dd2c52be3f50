"""Scene families and the realistic IMU against exact, analytic truth."""
import csv
import json

import numpy as np

from lobula.camera import PinholeCamera
from stimuli.imu import IMUConfig, bias_random_walk, small_rotation, synthesize_imu
from stimuli.scene import SceneConfig, TrackScene
from stimuli.track import TrackRunConfig, make_track_run, random_profile
from stimuli.trajectory import trajectory_from_function

CAM = PinholeCamera().scaled(0.25)


def scene(v=0.5, duration=4.0, **kw):
    kw.setdefault("noise_grey", 0.0)
    return TrackScene(CAM, trajectory_from_function(lambda t: np.full_like(t, v), duration), SceneConfig(**kw))


def pixel_rays_world(sc, t):
    """Unit pixel rays (H, W, 3) in the track frame and their camera-frame forward components."""
    x, y = CAM.normalised_grid()
    d = np.stack([x, y, np.ones_like(x)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d, d @ sc.rotation(t).T


def test_corridor_depth_is_the_analytic_distance_to_the_nearest_wall():
    sc = scene(world="corridor", seed=3, rotation3_amp_deg=(5.0, 4.0, 5.0))
    t = 2.3
    floor, ceiling, left, right, end, back_wall = sc.surfaces
    w, fl, ce, z_end = right.offset, floor.offset, -ceiling.offset, end.offset
    assert 0.8 <= w <= 1.5 and 0.9 <= fl <= 1.4 and 0.9 <= ce <= 1.6
    d_cam, d = pixel_rays_world(sc, t)
    c = sc.position(t)
    with np.errstate(divide="ignore"):
        cand = np.stack([np.where(d[..., 1] > 0, (fl - c[1]) / d[..., 1], np.inf),
                         np.where(d[..., 1] < 0, (-ce - c[1]) / d[..., 1], np.inf),
                         np.where(d[..., 0] > 0, (w - c[0]) / d[..., 0], np.inf),
                         np.where(d[..., 0] < 0, (-w - c[0]) / d[..., 0], np.inf),
                         np.where(d[..., 2] > 0, (z_end - c[2]) / d[..., 2], np.inf)])
    rng = cand.min(0)  # a closed box: the nearest plane ahead is the one hit
    np.testing.assert_allclose(sc.depth(t), rng * d_cam[..., 2], rtol=1e-5)
    assert sc.depth(t).max() > 8 and sc.depth(t).min() < 2.5  # walls near, end wall far
    # Backward rays stay inside the closed corridor and end on the back wall or the sides.
    r_back, i_back, _, _ = sc.cast_rays(-d_cam, t)
    assert np.isfinite(r_back).all() and (i_back == 5).any() and not (i_back == 4).any()


def test_ground_plane_depth_is_h_over_sin_elevation_and_the_sky_is_empty():
    sc = scene(world="ground", seed=5, ground_objects=0)
    t = 1.0
    ground, backdrop = sc.surfaces
    h = ground.offset
    assert 0.8 <= h <= 1.6 and 50 <= backdrop.offset - sc.position_range[1] <= 200
    rng = np.random.default_rng(0)
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    r, idx, _, _ = sc.cast_rays(d, t)
    d_w = d @ sc.rotation(t).T
    below = d_w[:, 1] > 0  # y is down: elevation below the horizon
    on_ground = below & (idx == 0)
    np.testing.assert_allclose(r[on_ground], h / d_w[on_ground, 1], rtol=1e-9)
    # Every ray below the horizon meets the ground unless the backdrop is nearer.
    assert np.all(idx[below] >= 0)
    # Above the backdrop's top, nothing: infinite range and the sky's luminance.
    sky = d_w[:, 1] < -np.tan(np.arctan(40.0 / 50.0))
    assert sky.sum() > 300 and np.all(idx[sky] == -1) and np.all(np.isinf(r[sky]))
    np.testing.assert_allclose(sc.luminance(d[sky], t), sc.config.sky)
    # The frame: sky on top, ground (darker on average) below, no aliasing beyond the noise:
    # at the horizon the mip-mapped ground is near its mean grey.
    img = sc.render(t).astype(float)
    assert abs(img[:5].mean() - 255 * 0.8) < 2


def test_three_axis_rotation_gyro_integrates_to_the_scene_rotation():
    amp = (5.0, 4.0, 3.0)
    sc = scene(world="panels", seed=7, rotation3_amp_deg=amp)
    ang = np.degrees(sc.rotation3_angles(np.arange(0, 4, 0.005)))
    assert np.all(np.abs(ang) <= np.array(amp) + 1e-9)
    assert np.all(np.abs(ang).max(0) > 0.4 * np.array(amp))  # every axis moves
    freq = sc._rotation3[0]
    assert freq.min() >= 0.3 and freq.max() <= 1.5 and len(np.unique(freq)) == freq.size
    imu = synthesize_imu(sc, 4.0, IMUConfig(seed=1))
    # Integrate the exact body rate with the exponential map (midpoint rule).
    t, w = imu["time_s"], imu["gyro_true"]
    r = sc.rotation(0.0)
    for k in range(len(t) - 1):
        r = r @ small_rotation(0.5 * (w[k] + w[k + 1]) * (t[k + 1] - t[k]))
    err = r.T @ sc.rotation(t[-1])
    angle = np.degrees(np.arccos(np.clip((np.trace(err) - 1) / 2, -1, 1)))
    assert angle < 1e-3, angle
    # The written (noisy, biased) gyro integrates to within its bias x time.
    np.testing.assert_allclose(imu["gyro"] - imu["gyro_bias"], w, atol=6 * np.radians(0.014) * np.sqrt(125))
    # Another seed: another rotation.
    other = scene(world="panels", seed=8, rotation3_amp_deg=amp)
    assert not np.allclose(other.rotation(1.0), sc.rotation(1.0))


def test_random_profiles_reach_their_peak_and_start_as_asked():
    for seed in range(3):
        fast = random_profile(seed, 10.0, 2.0, "rest")
        t = np.arange(0, 10.0, 0.01)
        assert abs(np.abs(fast(t)).max() - 2.0) < 1e-9
        assert fast(np.array([0.0, 0.5])).tolist() == [0.0, 0.0]
        moving = random_profile(seed, 10.0, 0.6, "motion")
        assert abs(moving(0.0)) >= 0.24
    assert not np.allclose(random_profile(0, 10, 1, "rest")(t), random_profile(1, 10, 1, "rest")(t))


def test_dim_scene_scales_luminance_and_contrast():
    a, b = scene(seed=2), scene(seed=2, brightness=0.4, contrast=0.5)
    la, lb = a._render_clean(1.0), b._render_clean(1.0)
    hit = la > 0
    np.testing.assert_allclose(lb[hit].mean(), 0.4 * la[hit].mean(), rtol=0.02)
    assert 0.15 < lb[hit].std() / (0.4 * la[hit].std()) < 0.8


def test_bias_random_walk_has_the_stated_diffusion():
    rng = np.random.default_rng(0)
    walk, rate, T = 1e-3, 250.0, 20.0
    ends = np.array([bias_random_walk(rng, int(T * rate) + 1, rate, walk, np.zeros(3))[-1] for _ in range(300)])
    # std of the drift after T seconds is walk·√T (±10% for 900 draws).
    assert abs(ends.std() / (walk * np.sqrt(T)) - 1) < 0.1


def read_imu_csv(folder):
    with open(folder / "imu.csv") as fh:
        rows = list(csv.DictReader(fh))
    a = np.array([[float(r[f"accel_{k}"]) for k in "xyz"] for r in rows])
    g = np.array([[float(r[f"gyro_{k}"]) for k in "xyz"] for r in rows])
    return np.array([float(r["time_s"]) for r in rows]), a, g


def test_realistic_imu_scale_and_misalignment_are_recovered_from_the_written_data(tmp_path):
    cfg = TrackRunConfig(duration_s=12.0, scale=0.1, random_peak_m_s=1.0, random_start="motion", depth_every=0,
                         scene=SceneConfig(seed=4, rotation3_amp_deg=(5.0, 5.0, 5.0), noise_grey=0.0, supersample=1),
                         imu=IMUConfig.realistic(seed=4))
    out = make_track_run(tmp_path / "run", cfg, progress=False)
    t, acc, gyr = read_imu_csv(out)
    meta = json.loads((out / "scene.json").read_text())
    sc, imu = __import__("stimuli.track", fromlist=["build_track"]).build_track(cfg)
    for reading, true, key, tol in ((gyr, imu["gyro_true"], "gyro_matrix", 2e-3),
                                    (acc, imu["accel_true"], "accel_matrix", 3e-3)):
        # Least squares: reading = M·true + b (a constant bias; its slow walk is noise here).
        x = np.c_[true, np.ones(len(true))]
        coef = np.linalg.lstsq(x, reading, rcond=None)[0]
        m_fit, m_true = coef[:3].T, np.array(meta[key])
        assert np.abs(m_true - np.eye(3)).max() > 5e-3  # the errors are there to find
        # Gravity keeps the accelerometer's y input near -9.8 (±5° of tilt only), so its
        # column cannot be told from a bias: check x and z, and y·mean + bias together.
        cols = [0, 1, 2] if key == "gyro_matrix" else [0, 2]
        np.testing.assert_allclose(m_fit[:, cols], m_true[:, cols], atol=tol)
        if key == "accel_matrix":
            b_true = np.array(meta["accel_bias"]) + m_true[:, 1] * true[:, 1].mean()
            np.testing.assert_allclose(coef[3] + m_fit[:, 1] * true[:, 1].mean(), b_true, atol=0.01)
    # The biases drift: start and end differ by about walk·√T.
    drift = np.array(meta["gyro_bias_end"]) - np.array(meta["gyro_bias"])
    assert np.all(drift != 0) and np.abs(drift).max() < 6 * 4e-5 * np.sqrt(12)


def test_extrinsics_rotating_imu_back_gives_the_camera_frame_specific_force(tmp_path):
    cfg = TrackRunConfig(duration_s=2.0, scale=0.1, random_peak_m_s=0.8, depth_every=0,
                         scene=SceneConfig(seed=1, rotation3_amp_deg=(4.0, 3.0, 2.0), supersample=1),
                         imu=IMUConfig(seed=1, mount="rotated", accel_bias_std=0.0, gyro_bias_std=0.0,
                                       accel_noise_density=0.0, gyro_noise_density=0.0))
    out = make_track_run(tmp_path / "run", cfg, progress=False)
    r = np.array(json.loads((out / "camera.json").read_text())["imu_to_camera"])
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) > 0 and np.abs(r - np.eye(3)).max() > 0.5  # really rotated
    t, acc, gyr = read_imu_csv(out)
    sc, imu = __import__("stimuli.track", fromlist=["build_track"]).build_track(cfg)
    # Camera-frame specific force from the trajectory and rotation alone: Rᵀ(a ẑ − g).
    a_w = np.zeros((len(t), 3))
    a_w[:, 2] = sc.trajectory.acceleration(t)
    f_cam = np.einsum("nji,nj->ni", sc.rotation(t), a_w - sc.gravity_world)
    np.testing.assert_allclose(acc @ r.T, f_cam, atol=2e-6)
    np.testing.assert_allclose(gyr @ r.T, imu["gyro_true"], atol=2e-7)
    assert np.abs(acc - f_cam).max() > 1.0  # imu.csv itself is not in the camera frame
    from lobula.readers import open_footage
    fo = open_footage(out)
    np.testing.assert_allclose(fo.imu.accel, f_cam, atol=2e-6)
