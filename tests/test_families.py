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

DURATION_S, SCALE, SKIP_S = 6.0, 0.5, 1.5


@pytest.fixture(scope="module")
def family_run(family_footage):
    return lambda family: family_footage(family, DURATION_S, SCALE)


_SCORED = {}  # (footage folder, filter, skip) -> scores: a footage is estimated once whatever tests ask


def _scores(fo, filt="zero-phase", skip_s=2.0):
    """The default estimator (filter ``filt``) on footage fo, scored after ``skip_s`` against the truth
    and the baselines: RMSE over observable frames, the zero estimator's, the truth's std (the
    constant "mean of the truth"), ±2σ coverage, observable fraction and median σ."""
    key = (str(fo.path), filt, skip_s)
    if key not in _SCORED:
        _SCORED[key] = _estimate_and_score(fo, filt, skip_s)
    return dict(_SCORED[key])


def _estimate_and_score(fo, filt, skip_s):
    cfg = VelocityConfig()
    cfg.readout.filter = filt
    ds = estimate_velocity(fo, cfg, progress=False)
    t, v, vt, sd = ds.time.values, ds.v_hat.values, ds.v_true.values, ds.v_std.values
    m = t >= t[0] + skip_s
    ok = m & np.isfinite(v)
    return dict(rmse=float(np.sqrt(np.mean((v - vt)[ok] ** 2))), zero=float(np.sqrt(np.mean(vt[m] ** 2))),
                const=float(np.std(vt[m])), cover=float(np.mean(np.abs(v - vt)[ok] <= 2 * sd[ok])),
                observable=float(ok.sum() / m.sum()), median_sd=float(np.median(sd[ok])))


@pytest.mark.parametrize("family", [
    "panels", "corridor",
    "rotation",  # 0.068 m/s against zero 0.314 and the truth's mean 0.138 (bound 0.069: the weakest family)
    "ground", "fast", "offaxis", "dim", "rest", "moving", "mixed"])
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
    (lobula.receptive_field.pool_fields, ``turns``)."""
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
        sc = _scores(fo, filt, skip_s=0.5)
        print(f"\n{filt}: {sc}")
        assert sc["observable"] >= 0.9, filt
        assert sc["rmse"] <= 0.01 and sc["cover"] >= 0.85, filt


def test_the_saccadic_family_is_fly_flight_and_runs_only_when_named():
    """`--families saccadic` flies the fly's flight (panels on even seeds, the corridor on odd ones); "all"
    keeps the ten families the results are reported on."""
    from experiments.families import ALL_FAMILIES, FAMILIES

    assert "saccadic" in ALL_FAMILIES and "saccadic" not in FAMILIES
    even, odd = suite.family_config("saccadic", 0, 2.0, 0.25), suite.family_config("saccadic", 1, 2.0, 0.25)
    assert even.flight == odd.flight == "saccadic"
    assert (even.scene.world, odd.scene.world) == ("panels", "corridor")
    with pytest.raises(ValueError, match="unknown family"):
        suite.family_config("saccades", 0, 2.0, 0.25)
