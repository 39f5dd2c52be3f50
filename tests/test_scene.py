"""The synthetic world: geometry of the renderer, reproducibility, IMU physics."""
import filecmp

import cv2
import numpy as np

from lobula.camera import PinholeCamera
from lobula.flow import FlowConfig, make_flow_fn, pixel_to_angular
from lobula.imu import forward_acceleration
from lobula.receptive_field import gap_correction, pool_fields, tile_fields
from lobula.readers import open_footage
from stimuli.imu import IMUConfig, synthesize_imu
from stimuli.scene import SceneConfig, TrackScene
from stimuli.track import TrackRunConfig, make_track_run
from stimuli.trajectory import trajectory_from_function

CAM = PinholeCamera().scaled(0.5)


def constant_scene(v=0.4, duration=3.0, **kw):
    kw.setdefault("noise_grey", 0.0)
    return TrackScene(CAM, trajectory_from_function(lambda t: np.full_like(t, v), duration), SceneConfig(**kw))


def warp_back(frame1, disp, cam):
    """Sample frame1 at p + displacement (normalised) for every pixel of frame 0."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float32), np.arange(cam.height, dtype=np.float32))
    mu, mv = (u + disp[0] * cam.fx).astype(np.float32), (v + disp[1] * cam.fy).astype(np.float32)
    return cv2.remap(frame1.astype(np.float32), mu, mv, cv2.INTER_LINEAR)


def test_exact_flow_warps_the_next_frame_onto_this_one():
    scene = constant_scene(v=0.5, rotation_amp_deg=2.0)
    t0, t1 = 1.0, 1.1
    f0, f1 = scene.render(t0).astype(float), scene.render(t1).astype(float)
    disp = scene.flow(t0, t1)
    warped = warp_back(f1, disp, CAM)
    m = np.zeros_like(f0, bool)
    m[8:-8, 8:-8] = True  # leave out pixels that flow in from outside the frame
    before = np.abs(f1 - f0)[m].mean()
    after = np.abs(warped - f0)[m].mean()
    assert before > 5 * after, (before, after)


def test_depth_and_r_are_consistent_with_the_trajectory():
    scene = constant_scene(v=0.4)
    d0, d1 = scene.depth(1.0), scene.depth(1.05)
    # A static point straight ahead (principal ray) gets closer by v·Δt.
    c = (int(round(CAM.cy)), int(round(CAM.cx)))
    np.testing.assert_allclose(d0[c] - d1[c], 0.4 * 0.05, rtol=1e-3)
    np.testing.assert_allclose(scene.r_exact(1.0), 0.4 / d0, rtol=1e-6)


def test_dis_field_rates_match_exact_v_over_d():
    """On a constant-velocity scene, r̄_f from DIS matches each field's exact v/d within 10%."""
    scene = constant_scene(v=0.5, noise_grey=1.0)
    fields = tile_fields(CAM)
    t0, t1 = 1.0, 1.2  # the default 6-frame pair at 30 frames/s
    flow = pixel_to_angular(make_flow_fn(FlowConfig())(scene.render(t0), scene.render(t1)), CAM, t1 - t0)
    r, r2 = gap_correction(*pool_fields(flow * 0.2, fields), 1.0)
    r_dis = r / 0.2
    # Exact mean rate over the pair, pooled the same way from the exact displacement.
    r_ex, _ = gap_correction(*pool_fields(scene.flow(t0, t1), fields), 1.0)
    r_ex = r_ex / 0.2
    rel = np.abs(r_dis - r_ex) / np.abs(r_ex)
    assert np.median(rel) < 0.10, np.median(rel)
    # ... and the exact pooled rate is the mean of v/d over the interval.
    ts = np.linspace(t0, t1, 11)
    w = fields.weights.toarray()
    dx2 = (fields.x ** 2 + fields.y ** 2).ravel()
    inv_d = np.mean([1 / scene.depth(t).ravel() for t in ts], axis=0)
    r_true = (w @ (0.5 * inv_d * dx2)) / (w @ dx2)
    np.testing.assert_allclose(np.median(r_ex / r_true), 1.0, atol=0.02)


def test_same_seed_gives_the_same_bytes(tmp_path):
    cfg = TrackRunConfig(profile=None, duration_s=0.3, scale=0.25, scene=SceneConfig(seed=3))
    a = make_track_run(tmp_path / "a", cfg, progress=False)
    b = make_track_run(tmp_path / "b", cfg, progress=False)
    names = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(names) > 10
    for n in names:
        assert filecmp.cmp(a / n, b / n, shallow=False), n
    c = make_track_run(tmp_path / "c", TrackRunConfig(profile=None, duration_s=0.3, scale=0.25,
                                                      scene=SceneConfig(seed=4)), progress=False)
    assert not filecmp.cmp(a / "frames/000000.png", c / "frames/000000.png", shallow=False)
    fo = open_footage(a)
    assert len(fo) == 9 and fo.imu is not None and fo.truth is not None


def test_accelerometer_reads_gravity_and_forward_acceleration_is_recovered():
    # Starts in motion (v = 0.3 m/s at t = 0): nothing may assume an initial rest.
    traj = trajectory_from_function(lambda t: 0.3 + 0.25 * np.sin(2 * np.pi * t / 4), 16.0)
    scene = TrackScene(CAM, traj, SceneConfig(gravity_pitch_deg=4.0, gravity_roll_deg=2.0))
    imu = synthesize_imu(scene, 16.0, IMUConfig(seed=5))
    g = np.linalg.norm(imu["accel"].mean(0))
    assert abs(g - 9.81) < 0.05
    assert imu["accel"][:, 1].mean() < -9.7  # y is down: gravity reads negative on y
    a = forward_acceleration(imu["time_s"], imu["accel"], imu["gyro"])
    truth = traj.acceleration(imu["time_s"])
    # Compare 1/30 s means: the accelerometer's white noise averages down, a bias does not.
    k = 250 // 30
    n = len(a) // k * k
    err = (a[:n] - truth[:n]).reshape(-1, k).mean(1)
    assert np.sqrt(np.mean(err ** 2)) < 0.04
    # A naive reading that ignores the tilt would be off by g·sin(4°) ≈ 0.68 m/s².
    assert abs(np.mean(imu["accel"][:, 2] - truth)) > 0.5


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_cast_rays_ranges_are_analytic_all_around_the_sphere():
    """Rays anywhere on the sphere (backward too) hit the floor and walls at their analytic range."""
    scene = constant_scene(v=0.4, side_walls=True)
    t = 1.3
    rng = np.random.default_rng(1)
    # Backward and sideways rays that go down: the floor (y = +0.6) or a side wall (x = ±1.5) first.
    d = unit(rng.normal(size=(400, 3)) * [1, 1, 1] + [0, 0.2, 0])
    d = d[(d[:, 2] < 0) & (d[:, 1] > 0.05)]
    assert len(d) > 50
    rng_m, idx, a, b = scene.cast_rays(d, t)
    expect = np.minimum(0.6 / d[:, 1], 1.5 / np.abs(d[:, 0]))
    np.testing.assert_allclose(rng_m, expect, rtol=1e-9)
    floor = [i for i, s in enumerate(scene.surfaces) if s.axis == 1][0]
    np.testing.assert_array_equal(idx == floor, 0.6 / d[:, 1] < 1.5 / np.abs(d[:, 0]))
    # Straight back, level: parallel to the floor, between the walls' ends: nothing is hit.
    r0, i0, _, _ = scene.cast_rays(np.array([0.0, -0.3, -1.0]) / np.hypot(0.3, 1.0), t)
    assert i0 == -1 and np.isinf(r0)
    assert scene.luminance(np.array([0.0, -0.3, -1.0]) / np.hypot(0.3, 1.0), t) == 0.0
    # Forward pixel rays: range = forward depth x |(x, y, 1)|, the same hits as the depth map.
    x, y = CAM.normalised_grid()
    dirs = unit(np.stack([x, y, np.ones_like(x)], -1))
    rng_m, idx, _, _ = scene.cast_rays(dirs, t)
    np.testing.assert_allclose(rng_m, scene.depth(t) * np.sqrt(x ** 2 + y ** 2 + 1), rtol=1e-6)


def test_pinhole_frames_are_the_ray_luminance_averaged_over_sub_pixel_rays():
    scene = constant_scene(v=0.4, rotation_amp_deg=2.0, side_walls=True)
    t, ss = 0.7, scene.config.supersample
    x, y = scene._rays
    lum = scene.luminance(unit(np.stack([x, y, np.ones_like(x)], -1)), t)
    img = lum.reshape(CAM.height, ss, CAM.width, ss).mean(axis=(1, 3))
    np.testing.assert_allclose(img, scene._render_clean(t), atol=1e-5)
    frame = scene.render(t)
    assert np.abs(frame - np.clip(np.round(255 * img), 0, 255)).max() <= 1
    # Any shape of directions, e.g. a flat list of 10,000 rays (cv2's 2-D map limits do not apply).
    flat = unit(np.random.default_rng(2).normal(size=(10000, 3)))
    l_flat = scene.luminance(flat, t)
    np.testing.assert_allclose(l_flat[:100], scene.luminance(flat[:100].reshape(10, 10, 3), t).ravel(), atol=1e-6)


def test_culling_each_surface_to_its_image_block_changes_no_hit():
    """The renderer tests each surface only on the block of rays its image can cover (clipped to the
    half-space in front of the camera), a band of rows at a time: every hit, depth and texture
    coordinate is the one every ray tested against every surface gives, in a panels world turning on
    three axes and off its axis, in a corridor whose walls reach behind the camera and on a ground
    plane with its sky."""
    from stimuli.scene import _grid_window

    worlds = [dict(world="panels", rotation3_amp_deg=(5.0, 3.0, 2.0), off_axis_yaw_deg=8.0),
              dict(world="corridor"), dict(world="ground")]
    culled = 0
    for kw in worlds:
        sc = constant_scene(v=1.0, duration=4.0, **kw)
        x, y = sc._rays
        for t in (0.0, 1.7, 3.9):
            rot, pos = sc.rotation(t), sc.position(t)
            d = np.stack([x, y, np.ones_like(x)], -1) @ rot.T
            full = sc._intersect(d, pos)
            for band_rows in (len(y), 7):  # the whole grid; bands whose edges fall anywhere
                bands = list(sc._cast_bands(x, y, t, band_rows=band_rows))
                for k, a in enumerate(full):
                    assert np.array_equal(a, np.concatenate([band[1 + k] for band in bands]))
            for s in sc.surfaces:
                w = _grid_window(s, x[0], y[:, 0], rot, pos)
                culled += w is None or (w != (Ellipsis,) and x[w].size < x.size)
    assert culled > 0  # the blocks are smaller than the image: the test compares two different computations
