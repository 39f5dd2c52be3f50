"""The synthetic world: geometry of the renderer, reproducibility, IMU physics."""
import filecmp
import json

import cv2
import numpy as np
import pytest

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
        if n.name != "scene.json":
            assert filecmp.cmp(a / n, b / n, shallow=False), n
    # scene.json: the same but for when it was made (its provenance's time)
    meta_a, meta_b = (json.loads((x / "scene.json").read_text()) for x in (a, b))
    assert meta_a.pop("created") and meta_b.pop("created") and meta_a == meta_b
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


# ------------------------------------------------------------- rolling shutter
def test_rolling_shutter_rows_are_the_global_frames_at_their_row_times():
    """Row r of a frame stamped t under a readout of T seconds is row r of the global-shutter frame at
    t + r/height·T, and so is its depth: here a camera moving at 2 m/s and turning on three axes."""
    from dataclasses import replace

    kw = dict(v=2.0, duration=2.0, rotation3_amp_deg=(5.0, 4.0, 3.0), rotation3_band_hz=(2.0, 4.0))
    glob, rolling = constant_scene(**kw), constant_scene(rolling_shutter_s=0.03, **kw)
    assert replace(rolling.config, rolling_shutter_s=0.0) == glob.config
    t, h = 0.7, CAM.height
    img, dep = rolling._render_clean(t), rolling.depth(t)
    assert not np.allclose(img, glob._render_clean(t), atol=1e-3)  # the rows do differ from the frame at t
    for r in (0, 37, h // 2, h - 1):
        tr = t + r / h * 0.03
        np.testing.assert_allclose(img[r], glob._render_clean(tr)[r], rtol=0, atol=1e-9)
        np.testing.assert_allclose(dep[r], glob.depth(tr)[r], rtol=1e-6)
    np.testing.assert_allclose(rolling.row_times(t), t + np.arange(h) / h * 0.03)


def _yawing_edge_scene(readout_s: float, rate_rad_s: float):
    """A still camera (160×120) yawing right at a constant rate (rad/s) before a vertical edge straight
    ahead at t = 0: a dark surface right of it, a lighter wall behind (no texture, no noise)."""
    from dataclasses import replace

    from stimuli.scene import _rot_stack

    class Yawing(TrackScene):
        def _mount_rotation(self, t):
            return _rot_stack(rate_rad_s * np.asarray(t, dtype=float), 1)

    cam = PinholeCamera().scaled(0.25)
    scene = Yawing(cam, trajectory_from_function(np.zeros_like, 1.0),
                   SceneConfig(seed=0, n_panels=1, floor=False, contrast=0.0, noise_grey=0.0, supersample=8,
                               rolling_shutter_s=readout_s))
    # The one panel made a half-plane x ≥ 0 from top to bottom, darker than the backdrop (gain 0.8).
    scene.surfaces[0] = replace(scene.surfaces[0], bounds=((0.0, 50.0), (-50.0, 50.0)), gain=0.5)
    return scene, cam


def _edge_columns(lum: np.ndarray) -> np.ndarray:
    """The column (px) of a vertical light-to-dark edge in each row of lum (H, W): where the box-filtered
    pixels say the lighter side ends (pixel j spans j − ½ .. j + ½)."""
    light, dark = lum[:, 0:1], lum[:, -1:]
    return ((lum - dark) / (light - dark)).sum(axis=1) - 0.5


def test_rolling_shutter_shears_vertical_edges_by_the_rate_times_the_readout():
    """Yawing at 1 rad/s with a 30 ms readout, the edge in row r is where the camera points at
    t + r/H·30 ms: u = cx − fx·tan(ω·t_r), a shear of fx·tan(ω·T·(H−1)/H) ≈ 4.6 px from top to bottom;
    with a global shutter every row shows it at u = cx − fx·tan(ω·t)."""
    rate, readout, t = 1.0, 0.03, 0.01
    for t_read in (readout, 0.0):
        scene, cam = _yawing_edge_scene(t_read, rate)
        cols = _edge_columns(scene._render_clean(t))
        tr = t + np.arange(cam.height) / cam.height * t_read
        np.testing.assert_allclose(cols, cam.cx - cam.fx * np.tan(rate * tr), atol=0.08)
    scene, cam = _yawing_edge_scene(readout, rate)
    cols = _edge_columns(scene._render_clean(0.0))
    shear = cols[0] - cols[-1]
    assert abs(shear - cam.fx * np.tan(rate * readout * (cam.height - 1) / cam.height)) < 0.1
    assert shear > 4.0


def test_rolling_shutter_is_recorded_in_camera_json_and_set_from_the_command_line(tmp_path):
    import json

    from experiments.cli import build_parser
    from experiments.render import scene_config_from_args

    parser = build_parser(["scene"])
    cfg = scene_config_from_args(parser.parse_args(["scene", "out", "--builtin-profile", "--rolling-shutter", "0.02"]))
    assert cfg.scene.rolling_shutter_s == 0.02
    assert scene_config_from_args(parser.parse_args(["scene", "out", "--builtin-profile"])).scene.rolling_shutter_s == 0
    from experiments.render import run_scene

    with pytest.raises(ValueError, match="--rolling-shutter .* compound eye"):  # it has no rows to read out
        run_scene(parser.parse_args(["scene", str(tmp_path / "eye"), "--eye", "fly", "--rolling-shutter", "0.03"]))
    assert not (tmp_path / "eye").exists()
    cfg = TrackRunConfig(duration_s=0.2, scale=0.1, imu=IMUConfig(), scene=SceneConfig(rolling_shutter_s=0.02))
    cam = json.loads((make_track_run(tmp_path / "rs", cfg, progress=False) / "camera.json").read_text())
    assert cam["rolling_shutter_s"] == 0.02
    glob = TrackRunConfig(duration_s=0.2, scale=0.1, imu=IMUConfig())
    assert "rolling_shutter_s" not in json.loads((make_track_run(tmp_path / "gs", glob, progress=False)
                                                  / "camera.json").read_text())
    assert "rolling_shutter_s" not in glob.to_dict()["scene"]  # a global shutter's scene reads as before


# ------------------------------------------------------------- kilometres away
def test_a_backdrop_two_kilometres_away_is_rendered_at_its_depth():
    """No far clip and no fighting where the ground meets the backdrop: a drone 25 m up before a backdrop
    1,990-2,000 m beyond its farthest position sees, down a column of the image, the sky, the backdrop
    and the ground each at its analytic depth (float32), and the backdrop's face rendered, not the sky."""
    from dataclasses import replace

    from experiments.suite_scene import family_config
    from stimuli.track import build_track

    cfg = family_config("drone", 0, 2.0, 0.25)
    cfg = replace(cfg, scene=replace(cfg.scene, ground_height_m=(25.0, 25.0), ground_backdrop_m=(1990.0, 2000.0),
                                     ground_backdrop_height_m=(300.0, 300.0), noise_grey=0.0, roadside_spacing_m=0.0,
                                     ground_objects=0))
    scene, _ = build_track(cfg)
    ground, back = scene.surfaces
    assert ground.axis == 1 and back.axis == 2 and back.offset > 1990
    t, cam = 1.0, scene.camera
    pos, rot = scene.position(t), scene.rotation(t)
    c = int(round(cam.cx))
    y = (np.arange(cam.height) - cam.cy) / cam.fy
    d = np.stack([np.full_like(y, (c - cam.cx) / cam.fx), y, np.ones_like(y)], -1) @ rot.T  # track frame
    with np.errstate(divide="ignore"):
        lam_g = np.where(d[:, 1] > 0, (ground.offset - pos[1]) / d[:, 1], np.inf)
        lam_b = (back.offset - pos[2]) / d[:, 2]
    y_b = pos[1] + lam_b * d[:, 1]
    lam_b = np.where((y_b >= back.bounds[1][0]) & (y_b <= back.bounds[1][1]), lam_b, np.inf)
    lam_g = np.where(pos[2] + lam_g * d[:, 2] <= back.offset, lam_g, np.inf)
    expected = np.minimum(lam_g, lam_b)
    on_back = np.isfinite(lam_b) & (lam_b < lam_g)
    assert on_back.sum() >= 3 and np.isfinite(lam_g).sum() >= 3 and np.isinf(expected).sum() >= 3
    depth = scene.depth(t)[:, c]
    np.testing.assert_allclose(depth, expected, rtol=2e-6)
    assert expected[on_back].min() > 1900
    sky = 255 * scene.config.sky
    assert np.all(np.abs(scene.render(t)[on_back, c].astype(float) - sky) > 40)


# ------------------------------------------------------------- the meadow: outdoors at a fly's scale
def test_a_fly_in_the_meadow_never_flies_through_a_stem_and_sees_surfaces_from_centimetres_to_metres():
    """The saccadic family's meadow seeds: the ground 0.1-0.4 m below, every stem standing on it with its inner
    edge beyond the flight's reach (the whole flight's |x| is less than the nearest stem's), a hedge beyond the
    farthest position; rendered, the camera sees surfaces under 2 m on most of each image, the sky as well, and
    nothing nearer than the flight allows."""
    from experiments.suite_scene import family_config
    from stimuli.flight import FlightConfig
    from stimuli.track import build_track

    for seed in (2, 5):
        scene, _ = build_track(family_config("saccadic", seed, 4.0, 0.25))
        assert scene.config.world == "meadow"
        ground, hedge, *stems = scene.surfaces
        h = ground.offset
        assert ground.axis == 1 and 0.1 <= h <= 0.4
        assert hedge.axis == 2 and all(hedge.offset > s.offset for s in stems) and len(stems) > 50
        inner = np.array([min(abs(a) for a in s.bounds[0]) for s in stems])
        assert np.all(inner >= 0.45) and all(s.bounds[1][1] == h for s in stems)
        t = np.linspace(0.0, 4.0, 401)
        reach = np.abs(scene.position(t)[:, 0]).max()
        assert reach <= FlightConfig().lateral_limit_m + 0.01 < inner.min()
        for tk in (0.5, 2.0, 3.5):
            depth = scene.depth(tk)
            near = np.isfinite(depth) & (depth <= 2.0)
            assert near.mean() > 0.3 and np.isinf(depth).mean() > 0.02  # stems and ground near, sky beyond
            assert np.nanmin(depth) > 0.05


def test_the_meadow_leaves_the_other_worlds_and_their_stored_configuration_as_they_are():
    """The meadow's parameters are written for the meadow (scene.json) and not for a world that does not use them
    (scene.json and the caches keyed by it stay as they are)."""
    assert not [k for k in SceneConfig(world="ground").to_dict() if k.startswith("meadow")]
    meadow = SceneConfig(world="meadow").to_dict()
    assert meadow["meadow_spacing_m"] == 0.1 and SceneConfig(**meadow) == SceneConfig(world="meadow")
    with np.testing.assert_raises(ValueError):
        SceneConfig(world="meadow", meadow_spacing_m=0.0)


def test_a_scene_folder_says_what_made_it(tmp_path):
    """scene.json carries the version, the commit, the command line and the time that made the footage."""
    import json

    from stimuli.track import TrackRunConfig, make_track_run

    out = make_track_run(tmp_path / "s", TrackRunConfig(profile=None, duration_s=0.2, scale=0.25), progress=False)
    meta = json.loads((out / "scene.json").read_text())
    for key in ("lobula_version", "git_commit", "command_line", "created", "config"):
        assert meta[key], key


@pytest.mark.parametrize("option, words", [(["--lens", "kannala-brandt:0.1,0,0,0"], "--lens shapes"),
                                           (["--exposure", "0.01", "--noise", "0.05"], "--exposure, --noise shape")])
def test_camera_options_the_compound_eye_cannot_use_are_refused(tmp_path, option, words):
    from experiments.cli import build_parser
    from experiments.render import run_scene

    args = build_parser(["scene"]).parse_args(["scene", str(tmp_path / "eye"), "--eye", "fly", *option])
    with pytest.raises(ValueError, match=f"{words} the camera's frames; the compound eye"):
        run_scene(args)
    assert not (tmp_path / "eye").exists()


def test_a_camera_file_is_read_from_its_folder_too(tmp_path):
    from lobula.camera import PinholeCamera

    cam = PinholeCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, frame_rate_hz=30.0)
    (tmp_path / "camera.json").write_text(json.dumps(cam.to_dict()))
    assert PinholeCamera.from_json(tmp_path) == cam
    (tmp_path / "camera.json").write_bytes(b"\x89PNG\x00\xff")
    with pytest.raises(ValueError, match="camera.json: not a valid camera.json"):
        PinholeCamera.from_json(tmp_path)
