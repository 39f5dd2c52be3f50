"""The estimator on every scene family, short and small (320×240, 6 s; at 160×120 DIS cannot resolve the corridor), against baselines.

Each family's scene comes from `lobula suite`'s own definitions (experiments.suite.family_config,
realistic IMU on a rotated mount). The bounds are relative to baselines that know nothing
(the zero estimator v̂ = 0) or know too much (the constant mean of the truth): an estimator
that does not track velocity cannot beat both by the margins asked here.
"""
import numpy as np
import pytest

from experiments import suite
from lobula.velocity import estimate_velocity
from lobula.config import VelocityConfig
from lobula.readers import open_footage
from stimuli.track import make_track_run
from tests.imu_helpers import integrate_gyro

DURATION_S, SCALE, SKIP_S = 6.0, 0.5, 1.5


@pytest.fixture(scope="module")
def family_run(family_footage):
    return lambda family: family_footage(family, DURATION_S, SCALE)


_SCORED = {}  # (footage folder, filter, skip) -> scores: a footage is estimated once whatever tests ask


def _scores(fo, filt="zero-phase", skip_s=2.0, rest_depth_m=None):
    """The default estimator (filter ``filt``; ``rest_depth_m``: the scene depth given, None: learned) on
    footage fo, scored after ``skip_s`` against the truth and the baselines: RMSE over observable frames, the
    zero estimator's, the truth's std (the constant "mean of the truth"), ±2σ coverage, observable fraction
    and median σ (NaN where nothing is observable)."""
    key = (str(fo.path), filt, skip_s, rest_depth_m)
    if key not in _SCORED:
        _SCORED[key] = _estimate_and_score(fo, filt, skip_s, rest_depth_m)
    return dict(_SCORED[key])


def _estimate_and_score(fo, filt, skip_s, rest_depth_m=None):
    cfg = VelocityConfig()
    cfg.readout.filter = filt
    cfg.readout.rest_depth_max_m = rest_depth_m
    ds = estimate_velocity(fo, cfg, progress=False)
    t, v, vt, sd = ds.time.values, ds.v_hat.values, ds.v_true.values, ds.v_std.values
    m = t >= t[0] + skip_s
    ok = m & np.isfinite(v)
    return dict(rmse=float(np.sqrt(np.mean((v - vt)[ok] ** 2))), zero=float(np.sqrt(np.mean(vt[m] ** 2))),
                const=float(np.std(vt[m])), cover=float(np.mean(np.abs(v - vt)[ok] <= 2 * sd[ok])),
                observable=float(ok.sum() / m.sum()), median_sd=float(np.median(sd[ok])))


#: the families make test runs here: the walls, turning and held-out worlds; the panels (the turning family's
#: world without its turns), ground, dim, rest, moving, off-axis and fast ones, whose readout paths these share,
#: run under ``slow`` (every family is scored by ``lobula suite``; the off-axis heading's and the fast start's
#: paths by the streaming tests of those families)
BASELINE_FAMILIES = ("corridor", "rotation", "mixed")


@pytest.mark.parametrize("family", [
    pytest.param(f, marks=() if f in BASELINE_FAMILIES else pytest.mark.slow) for f in (
        "panels", "corridor",
        "rotation",  # 0.068 m/s against zero 0.314 and the truth's mean 0.138 (bound 0.069: the weakest family)
        "ground", "fast", "offaxis", "dim", "rest", "moving", "mixed")])
def test_family_beats_the_baselines(family_run, family):
    sc = _scores(family_run(family), skip_s=SKIP_S)
    print(f"\n{family}: RMSE {sc['rmse']:.3f} m/s (zero {sc['zero']:.3f}, mean of truth {sc['const']:.3f}), "
          f"observable {sc['observable']:.2f}, ±2σ {sc['cover']:.2f}")
    assert sc["observable"] >= 0.8
    assert sc["rmse"] <= 0.35 * sc["zero"]
    assert sc["rmse"] <= 0.5 * sc["const"]


@pytest.mark.parametrize("filt", [
    pytest.param("zero-phase", marks=pytest.mark.xfail(strict=True, reason=(
        "known limitation: the offline band is too wide on the corridor (RMSE 0.004 m/s against σ 0.016), "
        "so the truth lies inside ±2σ on 100 % of the frames, above the 99.5 % a calibrated band allows"))),
    pytest.param("causal", marks=pytest.mark.xfail(strict=True, reason=(
        "known limitation: the online band is too wide on the corridor (RMSE 0.016 m/s against σ 0.019), "
        "so the truth lies inside ±2σ on 100 % of the frames, above the 99.5 % a calibrated band allows")))])
def test_posterior_std_is_calibrated_on_a_family_it_was_not_fitted_on(family_run, filt):
    """Truth inside ±2σ for 85–99.5 % of the frames on the corridor (floor, walls, ceiling).

    The readout's one calibration constant (ReadoutConfig.kappa_rel_error) is fitted on the
    "moving" family's dev seed 100 only; this is another world and seed. Both ends count: a
    band too narrow misses the truth, one too wide (or a v_std that says nothing) covers it always.
    """
    sc = _scores(family_run("corridor"), filt, skip_s=SKIP_S)
    print(f"\ncorridor {filt}: ±2σ {sc['cover']:.3f}, median σ {sc['median_sd']:.3f} m/s, RMSE {sc['rmse']:.3f}")
    assert sc["observable"] >= 0.8
    assert 0.85 <= sc["cover"] <= 0.995
    assert sc["median_sd"] <= 0.1 * sc["zero"]  # a band that says something


# ------------------------------------------------------------- footage beyond the suite
# Cases the suite's footage does not make (160×120, 8 s, one seed each).
def _small_run(tmp_path, family, seed, **imu):
    from dataclasses import replace

    cfg = suite.family_config(family, seed, 8.0, 0.25)
    cfg = replace(cfg, imu=replace(cfg.imu, **imu), depth_every=1000)
    make_track_run(tmp_path / "run", cfg, progress=False)
    return open_footage(tmp_path / "run")


# The smoother pairs κ with the low-passed velocity it multiplies, as the online filter does, so offline
# reads no worse than online here (zero-phase 0.0158, causal 0.0171 m/s).
def test_offline_is_not_worse_than_online_under_a_nearly_constant_acceleration(tmp_path):
    """The rotation family's seed 10 decelerates almost uniformly from 0.29 to −0.6 m/s. Then
    κ(t) = a/v = 1/(t − t₀) whatever a is, so an accelerometer offset δb and a velocity error
    δv₀ = −δb·v₀/a leave every κ unchanged: the offset is unobservable, and a posterior that
    claims it is known (±0.016 m/s², error 0.044) is confidently wrong. The smoother has every
    frame the filter has and more: it must do at least as well and keep its band honest."""
    fo = _small_run(tmp_path, "rotation", 10)
    zp, causal = _scores(fo, "zero-phase"), _scores(fo, "causal")
    print(f"\nzero-phase {zp}\ncausal {causal}")
    assert zp["rmse"] <= causal["rmse"]
    assert zp["cover"] >= 0.85


@pytest.fixture(scope="module")
def big_gyro_bias_run(tmp_path_factory):
    """The rotation family's seed 100 with a 1°/s gyro-bias draw — a consumer MEMS gyro's uncompensated
    zero-rate offset (the suite's realistic IMU draws 0.25°/s; the real EuRoC start reads 1.7 / 0.2 /
    4.7°/s), the data sheet's spread (lobula.imu.GYRO_BIAS_PRIOR) and 5× the heading fit's
    regulariser (lobula.imu.HEADING_FIT_BIAS_PRIOR). The camera turns from the first frame, so no
    still sample ever measures the bias: the flow's heading fit has to."""
    return _small_run(tmp_path_factory.mktemp("bias"), "rotation", 100, gyro_bias_std=np.radians(1.0))


def test_online_is_honest_with_a_gyro_bias_of_a_data_sheet_size(big_gyro_bias_run):
    """The heading fit learns the bias within ~3 s; the attitude integrated meanwhile lets gravity into
    the forward axis at up to |g|·1°/s ≈ 0.17 m/s² per second, which the readout's offset is allowed to
    follow (the drift bound from the bias prior, lobula.imu.gravity_drift_std, and the leak's walk,
    lobula.imu.leak_walk). Measured at 160×120 with the built-in and the recorded profile alike:
    causal RMSE 0.02–0.03 m/s against the zero estimator's 0.35, ±2σ 100 %. With the bias prior at the
    heading fit's 0.2°/s instead: 0.09 m/s, ±2σ 78 % — confidently wrong from the start."""
    causal = _scores(big_gyro_bias_run, "causal")
    print(f"\ncausal {causal}")
    assert causal["cover"] >= 0.85
    assert causal["rmse"] <= 0.35 * causal["zero"]
    assert causal["observable"] >= 0.5


def test_online_stays_observable_with_a_gyro_bias_of_a_data_sheet_size(big_gyro_bias_run):
    """Once the bias is learned the offset it let in is learned from vision too: v̂ is answered on most frames."""
    assert _scores(big_gyro_bias_run, "causal")["observable"] >= 0.8


@pytest.mark.slow  # make test runs the same scene and bias on the built-in profile (the data sheet's size, above)
def test_online_is_honest_with_a_gyro_bias_on_the_recorded_profile(tmp_path, real_profile, monkeypatch):
    """The same scene on a window of the recorded FLIVVER trajectory: 0.019 m/s, ±2σ 100 %, observable
    68 % (the offset the bias let in is learned again from vision while v̂ stays unanswered)."""
    monkeypatch.delenv("LOBULA_PROFILE")
    causal = _scores(_small_run(tmp_path, "rotation", 100, gyro_bias_std=np.radians(1.0)), "causal")
    print(f"\ncausal {causal}")
    assert causal["cover"] >= 0.85
    assert causal["rmse"] <= 0.35 * causal["zero"]
    assert causal["observable"] >= 0.5


def test_a_still_camera_that_turns_fast_is_known_still(tmp_path):
    """A hovering camera turning ±15° in yaw (±5° pitch and roll) at 0.3–1.5 Hz, up to ~80°/s, never
    translating. Over a 0.2 s flow pair a first-order derotation leaves ~ω²·dt of expansion at
    every pixel whichever way the camera turns (at 45°/s, r̄ ≈ +0.1 1/s: 0.3 m/s at 3 m), so with it the
    fields would show motion, the rest bound would never apply and offline v̂ would be NaN on every frame
    (320×240, seed 70000; online observable 58 % in the first 2 s). The fixed-pixel rates derotate exactly
    (lobula.receptive_field.pool_fields, ``turns``). The rest bound needs the scene's depth: given (5 m, the
    panels are 2-4 m away) the camera is known still. Never having moved, the camera has shown none; what
    it claims then (the expansion's sign changing, as v passing 0 would make it) still holds the truth."""
    from stimuli.imu import IMUConfig
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig

    seed = 70000
    cfg = TrackRunConfig(scene=SceneConfig(seed=seed, rotation3_amp_deg=(15.0, 5.0, 5.0)), constant_velocity_m_s=0.0,
                         imu=IMUConfig.model("realistic", seed=seed, mount="rotated"), duration_s=6.0, scale=0.25,
                         depth_every=1000)
    make_track_run(tmp_path / "run", cfg, progress=False)
    fo = open_footage(tmp_path / "run")
    for filt in ("zero-phase", "causal"):
        sc = _scores(fo, filt, skip_s=0.5, rest_depth_m=5.0)
        print(f"\n{filt}: {sc}")
        assert sc["observable"] >= 0.9, filt
        assert sc["rmse"] <= 0.01 and sc["cover"] >= 0.85, filt
        learned = _scores(fo, filt, skip_s=0.5)
        assert learned["observable"] == 0 or learned["cover"] >= 0.85, (filt, learned)


def test_the_saccadic_family_is_fly_flight_and_runs_only_when_named():
    """`--families saccadic` flies the fly's flight (the panels, corridor and meadow worlds in turn, seed mod 3);
    "all" keeps the ten families the results are reported on."""
    from experiments.families import ALL_FAMILIES, FAMILIES

    assert "saccadic" in ALL_FAMILIES and "saccadic" not in FAMILIES
    runs = [suite.family_config("saccadic", seed, 2.0, 0.25) for seed in range(4)]
    assert {run.flight for run in runs} == {"saccadic"}
    assert [run.scene.world for run in runs] == ["panels", "corridor", "meadow", "panels"]
    with pytest.raises(ValueError, match="unknown family"):
        suite.family_config("saccades", 0, 2.0, 0.25)


# ------------------------------------------------------------- real-world platforms
def _plan_and_world(family, seed, duration_s=10.0):
    """The family's seed: its run configuration, platform plan and world surfaces (no textures, no frames)."""
    from lobula.camera import PinholeCamera
    from stimuli.platforms import platform_plan
    from stimuli.worlds import world_surfaces

    cfg = suite.family_config(family, seed, duration_s, 0.25)
    plan = platform_plan(cfg.flight, cfg.scene.seed, duration_s, cfg.flight_config)
    surfaces = world_surfaces(cfg.scene, PinholeCamera().scaled(0.25), np.random.default_rng(cfg.scene.seed),
                              *plan.z_range())
    return cfg, plan, surfaces


def test_the_platform_families_are_drone_road_and_walking_and_run_only_when_named():
    from experiments.families import ALL_FAMILIES, EXTRA_FAMILIES, FAMILIES

    for family in ("drone", "road", "walking"):
        assert family in EXTRA_FAMILIES and family in ALL_FAMILIES and family not in FAMILIES
        assert "named only" in EXTRA_FAMILIES[family]
        assert suite.family_config(family, 0, 2.0, 0.25).flight == family
    assert [suite.family_config("walking", s, 2.0, 0.25).scene.world for s in range(4)] == ["ground", "corridor"] * 2
    assert {suite.family_config(f, 0, 2.0, 0.25).scene.world for f in ("drone", "road")} == {"ground"}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drone_accelerates_from_near_rest_to_its_cruise_over_the_ground(seed):
    """From ≤ 0.5 m/s to a cruise of 5-15 m/s, the change taking 2-6 s, then cruising within 3 %; 3-30 m
    above the ground, a backdrop 100-2,000 m beyond the farthest position, objects along the way; the
    gimbal leaves under 0.4° per axis; the IMU vibrates at 0.3-1 m/s² rms, 50-200 Hz."""
    cfg, plan, surfaces = _plan_and_world("drone", seed)
    t = np.arange(0.0, 10.0, 0.002)
    v = plan.speed(t)
    assert v[0] <= 0.5 and v.min() >= 0
    cruise = float(np.median(v[t > 8.0]))
    assert 5.0 * 0.97 <= cruise <= 15.0 * 1.03
    assert np.all(np.abs(v[t > 8.0] / cruise - 1) <= 0.03)
    dv = cruise - v[0]
    began, done = t[np.argmax(v > v[0] + 0.05 * dv)], t[np.argmax(v >= v[0] + 0.95 * dv)]
    assert 1.0 <= done - began <= 6.0  # 5 % to 95 % of a change taking 2-6 s
    assert v[t < began - 1.0].max() <= 0.5 * 1.03  # hovering before it sets off
    ground, backdrop = surfaces[0], surfaces[1]
    s_max = plan.z_range()[1]
    assert ground.axis == 1 and 3.0 <= ground.offset <= 30.0
    assert backdrop.axis == 2 and 100.0 <= backdrop.offset - s_max <= 2000.0
    s_min = plan.z_range()[0]
    along = surfaces[2 + 8:]  # beyond the ground world's 8 objects: those along the way, every ~30 m a side
    assert len(along) >= 2 * (s_max + 300.0 - s_min - 5.0) / 30.0 * 0.5
    assert min(s.offset for s in along) < s_max  # some the drone flies past
    assert np.degrees(np.abs(plan.angles(t)).max()) <= 0.4 + 1e-9
    assert 0.3 <= cfg.imu.vibration_rms_m_s2 <= 1.0 and 50.0 <= cfg.imu.vibration_hz <= 200.0


def test_drone_vibration_is_in_the_accelerometer_at_its_rms_and_aliased_by_the_sample_rate():
    """The propellers shake the accelerometer at the drawn rms per axis; sampled at 250 Hz with no filter
    before it, a vibration at f Hz shows at |f − 250·round(f/250)| Hz; the camera's truth has none of it."""
    from dataclasses import replace

    from stimuli.imu import vibration

    cfg = suite.family_config("drone", 1, 10.0, 0.25).imu
    t = np.arange(0.0, 20.0, 1.0 / cfg.rate_hz)
    np.testing.assert_allclose(np.sqrt(np.mean(vibration(cfg, t) ** 2, axis=0)), cfg.vibration_rms_m_s2, rtol=0.05)
    vib = vibration(replace(cfg, vibration_hz=180.0, vibration_spread=0.0), t)  # one rate: one spectral line
    spectrum = np.abs(np.fft.rfft(vib[:, 0]))
    peak = np.fft.rfftfreq(len(t), 1.0 / cfg.rate_hz)[np.argmax(spectrum)]
    assert abs(peak - 70.0) <= 0.1  # 180 Hz folded about the 125 Hz Nyquist frequency
    # In the readings (the IMU frame), not in the camera's specific force.
    from stimuli.track import build_track

    run = suite.family_config("drone", 1, 2.0, 0.1)
    scene, imu = build_track(run)
    assert np.allclose(np.sqrt(np.mean(imu["accel_vibration"] ** 2, axis=0)), run.imu.vibration_rms_m_s2, rtol=0.15)
    reading = (imu["accel"] - imu["accel_bias_t"]) @ np.linalg.inv(imu["accel_matrix"]).T @ imu["imu_to_camera"].T
    resid = reading - imu["accel_true"]
    assert np.sqrt(np.mean(resid ** 2)) > 0.8 * run.imu.vibration_rms_m_s2
    assert np.sqrt(np.mean((resid - imu["accel_vibration"]) ** 2)) < 0.05  # what is left is white noise


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_road_vehicle_stops_and_goes_within_its_speeds(seed):
    """5-25 m/s, never backwards; within a 10 s run it brakes to ≤ 0.3 m/s before half the run and sets
    off again (and a 40 s run is back at a road speed); the camera rides 1-2 m above the road; objects line it."""
    cfg, plan, surfaces = _plan_and_world("road", seed)
    t = np.arange(0.0, 10.0, 0.002)
    v = plan.speed(t)
    assert v.min() >= -1e-9 and v.max() <= 25.0
    stop = int(np.argmax(v <= 0.3))
    assert v[stop] <= 0.3 and t[stop] <= 5.0 + 1e-9
    assert v[:stop].max() >= 5.0  # it was at a road speed before braking
    assert v[-1] >= v[stop:].min() + 1.5  # and is off again by the end
    assert np.abs(plan.speed(t, 1)).max() <= 8.0 + 1e-6  # braking no harder than a car brakes
    from stimuli.platforms import platform_plan

    v40 = platform_plan("road", cfg.scene.seed, 40.0).speed(np.arange(0.0, 40.0, 0.01))
    stop40 = int(np.argmax(v40 <= 0.3))
    assert 0 < stop40 and v40[stop40:].max() >= 5.0 and v40.max() <= 25.0  # back to a road speed after it
    ground = surfaces[0]
    assert ground.axis == 1 and 1.0 <= ground.offset <= 2.0
    s_min, s_max = plan.z_range()
    roadside = [s for s in surfaces[2 + 8:]]
    assert len(roadside) >= 2 * (s_max - s_min) / 15.0 * 0.5
    for s in roadside:
        assert min(abs(s.bounds[0][0]), abs(s.bounds[0][1])) >= 2.5 - 1e-9  # off the road
        assert s.bounds[1][1] == pytest.approx(ground.offset)  # standing on it


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_walking_has_a_gait_surge_bounce_sway_and_a_turning_hand(seed):
    """Walking at 1-2 m/s on average, the forward speed surging at the step rate (1.7-2.2 Hz), the camera
    bouncing 1.5-4 cm at the step rate and swaying 1-4 cm at half of it, the hand turning it at a few to
    tens of °/s."""
    cfg, plan, _ = _plan_and_world("walking", seed, 12.0)
    t = np.arange(6.0, 12.0, 0.002)  # in stride whether it started from rest or not
    v = plan.speed(t)
    assert 1.0 <= v.mean() <= 2.0
    f = np.fft.rfftfreq(len(t), 0.002)
    for signal, band in ((v - v.mean(), (1.7, 2.2)), (plan.offsets(t)[:, 1], (1.7, 2.2)),
                         (plan.offsets(t)[:, 0], (0.85, 1.1))):
        spectrum = np.abs(np.fft.rfft(signal - signal.mean()))
        peak = f[np.argmax(spectrum * (f > 0.5))]
        assert band[0] - 0.2 <= peak <= band[1] + 0.2
    bounce, sway = np.ptp(plan.offsets(t), axis=0)[::-1] / 2
    assert 0.015 * 0.95 <= bounce <= 0.04 * 1.05 and 0.01 * 0.9 <= sway <= 0.04 * 1.05
    rate = np.degrees(np.sqrt(np.mean(plan.angular_velocity(t) ** 2, axis=0)))
    assert np.all(rate >= 1.0) and rate.max() >= 3.0 and np.degrees(np.abs(plan.angular_velocity(t)).max()) <= 120.0


@pytest.mark.parametrize("family", ["drone", "road", "walking"])
def test_platform_families_are_reproducible_from_the_seed(family):
    a, b, c = (suite.family_config(family, s, 10.0, 0.25) for s in (0, 0, 1))
    assert a.to_dict() == b.to_dict()
    from stimuli.platforms import platform_plan

    t = np.linspace(0.0, 10.0, 501)
    pa, pb, pc = (platform_plan(x.flight, x.scene.seed, 10.0) for x in (a, b, c))
    assert np.array_equal(pa.position(t), pb.position(t)) and np.array_equal(pa.rotation(t), pb.rotation(t))
    assert not np.allclose(pa.speed(t), pc.speed(t))


@pytest.mark.parametrize("family", ["drone", "road", "walking"])
def test_platform_families_render_through_a_fisheye_with_exact_truth(tmp_path, family):
    """Each family's seed through a 131° equidistant fisheye: the footage opens with the lens, and the
    truth is the camera-frame velocity of the platform's motion."""
    import json
    from dataclasses import replace

    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(dict(width=640, height=480, fx=280.0, fy=280.0, cx=319.5, cy=239.5, frame_rate_hz=30.0)))
    cfg = replace(suite.family_config(family, 0, 0.5, 0.2), camera_json=str(cam), lens="kannala-brandt:0,0,0,0",
                  depth_every=1000)
    make_track_run(tmp_path / "run", cfg, progress=False)
    fo = open_footage(tmp_path / "run")
    assert json.loads((tmp_path / "run" / "camera.json").read_text())["distortion"]["model"] == "kannala-brandt"
    frames = [img for _, _, img in fo.frames()]
    assert len(frames) == 15 and all(f.std() > 5 for f in frames)
    from stimuli.platforms import platform_plan

    plan = platform_plan(family, cfg.scene.seed, 0.5)
    tt = fo.truth["time_s"]
    scene_rot = plan.rotation(tt) @ np.asarray(
        __import__("stimuli.scene", fromlist=["TrackScene"]).rotation_x(-np.radians(cfg.scene.off_axis_pitch_deg)))
    v_cam = np.einsum("nji,nj->ni", scene_rot, plan.velocity_world(tt))[:, 2]
    np.testing.assert_allclose(fo.truth["v_forward_m_s"], v_cam, atol=2e-6)


@pytest.mark.parametrize("family", ["drone", "road", "walking"])
def test_platform_imu_integrates_to_the_motion_the_frames_are_rendered_from(family):
    """An ideal, noiseless IMU (camera axes, 2 kHz, no vibration) on each family's seed 0: the gyro
    integrated from the true start attitude stays on the scene's rotation and the specific force, rotated
    into the track frame with gravity added back, integrates to the world velocity (bounce, sway and
    hand turns included) within 2 mm/s over 3 s."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    from stimuli.imu import IMUConfig
    from stimuli.track import build_track

    ideal = IMUConfig(rate_hz=2000.0, accel_noise_density=0.0, gyro_noise_density=0.0, accel_bias_std=0.0,
                      gyro_bias_std=0.0)
    cfg = replace(suite.family_config(family, 0, 3.0, 0.1), imu=ideal)
    scene, imu = build_track(cfg)
    t, g, f = imu["time_s"], imu["gyro"], imu["accel"]
    dt = np.diff(t)
    r = integrate_gyro(t, g, scene.rotation(t[0]))
    assert Rotation.from_matrix(np.einsum("nji,njk->nik", scene.rotation(t), r)).magnitude().max() < 1e-4
    a_world = np.einsum("nij,nj->ni", r, f) + scene.gravity_world
    v = scene.world_velocity(t[:1]) + np.concatenate([np.zeros((1, 3)),
                                                      np.cumsum(0.5 * (a_world[1:] + a_world[:-1]) * dt[:, None], 0)])
    v_true = scene.world_velocity(t)
    assert np.abs(v - v_true).max() < 2e-3
    # and the position the frames are cast from is that velocity's integral
    p = scene.position(t)
    np.testing.assert_allclose(np.diff(p, axis=0) / dt[:, None], 0.5 * (v_true[1:] + v_true[:-1]), atol=1e-4)
