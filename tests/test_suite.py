"""`lobula suite` on tiny scenes: table, NetCDF and figure agree with what is stored and with truth."""
import csv
import json

import numpy as np
import pytest
import xarray as xr

from experiments import suite
from experiments.cli import main


def read_truth(folder):
    with open(folder / "truth.csv") as fh:
        rows = list(csv.DictReader(fh))
    return np.array([float(r["time_s"]) for r in rows]), np.array([float(r["v_forward_m_s"]) for r in rows])


def test_lock_on_time_needs_a_second_of_tracking_while_moving():
    t = np.arange(0, 6, 0.1)
    v = np.where(t < 2, 0.0, 0.5)
    err = np.where(t < 3, 0.3, 0.01)
    err[:20] = 0.0  # right about the still camera: does not count
    assert suite.lock_on_time(t, err, v) == pytest.approx(3.0)
    assert np.isnan(suite.lock_on_time(t, np.full_like(t, 0.2), v))
    e2 = np.where(t < 3, 0.3, 0.01)
    e2[35] = np.nan  # an unobservable frame (t = 3.5 s) restarts the hold
    assert suite.lock_on_time(t, e2, v) == pytest.approx(3.6)


def test_z95_tells_a_calibrated_band_from_one_too_wide_or_too_narrow():
    # Errors that are exactly Gaussian quantiles of σ = 0.01 m/s: |e|/σ's 95th percentile is 1.96.
    from scipy.stats import norm

    n = 4000
    err = 0.01 * norm.ppf((np.arange(n) + 0.5) / n)
    t, v_true = np.arange(n) / 30.0, np.full(n, 0.5)
    mask = np.ones(n, bool)
    for scale, z95, cov in ((1.0, 1.96, 0.954), (5.0, 1.96 / 5, 1.0), (0.5, 2 * 1.96, 0.683)):
        m = suite.window_metrics(t, v_true + err, np.full(n, 0.01 * scale), v_true, mask)
        assert m["z95"] == pytest.approx(z95, rel=0.01)
        assert m["coverage_2sigma"] == pytest.approx(cov, abs=0.01)
    # Coverage is 100 % for the calibrated band's 2x and 5x widenings alike; z95 is not.
    wide = [suite.window_metrics(t, v_true + err, np.full(n, 0.01 * k), v_true, mask) for k in (2.0, 5.0)]
    assert wide[0]["coverage_2sigma"] == wide[1]["coverage_2sigma"] > 0.999
    assert wide[0]["z95"] == pytest.approx(2.5 * wide[1]["z95"], rel=1e-9)
    # A frame without a std is an unbounded error; no std at all: NaN.
    sd = np.full(n, 0.01)
    sd[: n // 10] = np.nan
    assert suite.window_metrics(t, v_true + err, sd, v_true, mask)["z95"] == np.inf
    assert np.isnan(suite.window_metrics(t, v_true + err, None, v_true, mask)["z95"])
    # The figure's target band: a band whose ±2σ holds 99 % / 85 % of Gaussian errors has z95 at its ends.
    for lo_hi, cov in ((0, 0.99), (1, 0.85)):
        scale = norm.ppf(0.5 + cov / 2) / 2.0   # the σ stated, per unit of the errors' own
        m = suite.window_metrics(t, v_true + err, np.full(n, 0.01 * scale), v_true, mask)
        assert m["coverage_2sigma"] == pytest.approx(cov, abs=0.005)
        assert m["z95"] == pytest.approx(suite.Z95_TARGET[lo_hi], rel=0.01)


def test_every_frame_coverage_counts_carried_estimates_and_frames_without_one():
    """Ten frames: 4 answered inside ±2σ, 3 carried (2 inside, 1 outside), 3 unknown. Answered coverage is 4/4;
    over every frame it is 6/10 (an unknown frame counts outside), and the RMSE over every v̂ takes in the 7."""
    t = np.arange(10) / 10.0
    v_true = np.ones(10)
    v_all = np.array([1.01, 0.99, 1.0, 1.015, 1.1, 0.9, 1.5, np.nan, np.nan, np.nan])
    answered = np.where(np.arange(10) < 4, v_all, np.nan)
    sd = np.array([0.01] * 4 + [0.1] * 3 + [np.nan] * 3)
    m = suite.window_metrics(t, answered, sd, v_true, np.ones(10, bool), v_all)
    assert m["coverage_2sigma"] == 1.0 and m["observable_fraction"] == pytest.approx(0.4)
    assert m["coverage_2sigma_all"] == pytest.approx(0.6)
    e = v_all[:7] - 1.0
    assert m["rmse_all_m_s"] == pytest.approx(np.sqrt(np.mean(e ** 2)))
    assert m["rmse_m_s"] == pytest.approx(np.sqrt(np.mean(e[:4] ** 2)))
    # Without a carried series the answered one is every v̂; without a std there is no coverage.
    alone = suite.window_metrics(t, answered, sd, v_true, np.ones(10, bool))
    assert alone["rmse_all_m_s"] == alone["rmse_m_s"] and alone["coverage_2sigma_all"] == pytest.approx(0.4)
    assert np.isnan(suite.window_metrics(t, answered, None, v_true, np.ones(10, bool), v_all)["coverage_2sigma_all"])
    # An estimator that states a std but never gives a v̂ covers no frame.
    never = np.full(10, np.nan)
    assert suite.window_metrics(t, never, never, v_true, np.ones(10, bool), never)["coverage_2sigma_all"] == 0.0


def test_the_figure_says_none_where_a_configuration_ran_but_answered_nothing():
    """A configuration that ran and answered no frame of a family has no RMSE to draw: the figure marks that slot
    "none" (suite.unanswered), unlike one that answered on some seed or did not run at all."""
    metrics = ["rmse_m_s", "observable_fraction"]
    value = np.full((3, 2, 2, 1, 2), np.nan)   # family, seed, configuration, window, metric
    value[:, :, 0, 0, 1] = 0.0                 # "a" ran everywhere ...
    value[1, 0, 0, 0, :] = (0.1, 0.5)          # ... and answered on family q, seed 0 only
    value[0, :, 1, 0, :] = (0.2, 1.0)          # "b" ran on family p only, answering there
    ds = xr.Dataset({"value": (("family", "seed", "configuration", "window", "metric"), value)},
                    coords=dict(family=["p", "q", "r"], seed=[0, 1], configuration=["a", "b"],
                                window=["after_skip"], metric=metrics))
    assert suite.unanswered(ds, "a").tolist() == [True, False, True]
    assert suite.unanswered(ds, "b").tolist() == [False, False, False]


def test_a_configuration_path_the_estimator_lacks_fails_loudly(monkeypatch):
    monkeypatch.setitem(suite.CONFIGURATIONS, "bogus", ("lobula", "zero-phase", {"readout.no_such_field": 1}))
    with pytest.raises(ValueError, match="no field 'no_such_field'"):
        suite.velocity_config("bogus")
    assert suite.velocity_config("paper causal").readout.filter == "causal"


def test_suite_on_tiny_scenes_writes_consistent_files(tmp_path, capsys):
    out = tmp_path / "suite"
    argv = ["suite", "--out", str(out), "--families", "rest,ground", "--seeds", "1", "--duration", "3",
            "--scale", "0.2", "--skip", "1", "--imu", "ideal",
            "--configurations", "lobula zero-phase,zero,imu dead reckoning", "--quiet"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    ds = xr.load_dataset(out / "suite.nc")
    assert ds.value.dims == ("family", "seed", "configuration", "window", "metric")
    assert list(ds.family.values) == ["rest", "ground"] and ds.sizes["seed"] == 1
    assert "config" in ds.attrs and "suite" in ds.attrs
    # The table is the NetCDF's numbers (one seed: mean = the value).
    with open(out / "suite_table.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * 3 * 2
    for r in rows:
        for m in suite.METRICS:
            v = float(ds.value.sel(family=r["family"], seed=0, configuration=r["configuration"],
                                   window=r["window"], metric=m))
            assert np.isnan(v) and r[f"{m}_mean"] == "nan" or float(r[f"{m}_mean"]) == pytest.approx(v)
    # The zero estimator's RMSE is the RMS of the true velocity over the scored frames (from truth.csv).
    for fam in ("rest", "ground"):
        series = xr.load_dataset(out / "series" / f"{fam}-s0.nc")
        tt, vt = read_truth(out / "scenes" / f"{fam}-s0")
        t = series.time.values
        v = np.interp(t, tt, vt)
        after = t >= t[0] + 1.0
        rmse0 = float(ds.value.sel(family=fam, seed=0, configuration="zero", window="after_skip", metric="rmse_m_s"))
        assert rmse0 == pytest.approx(np.sqrt(np.mean(v[after] ** 2)), rel=1e-9)
        first = t < t[0] + 2.0
        r2 = float(ds.value.sel(family=fam, seed=0, configuration="zero", window="first_2s", metric="rmse_m_s"))
        assert r2 == pytest.approx(np.sqrt(np.mean(v[first] ** 2)), rel=1e-9)
        assert rmse0 > 0.05  # the scenes move
    # Dead reckoning from rest with the ideal IMU (constant bias, removed by the first second's mean)
    # stays close to the truth over 3 s; the vision estimate beats the zero estimator.
    dr = ds.value.sel(configuration="imu dead reckoning", window="after_skip", metric="rmse_m_s").isel(seed=0)
    zero = ds.value.sel(configuration="zero", window="after_skip", metric="rmse_m_s").isel(seed=0)
    assert float(dr.sel(family="rest")) < 0.2 * float(zero.sel(family="rest"))
    lob = ds.value.sel(configuration="lobula zero-phase", window="after_skip", metric="rmse_m_s").isel(seed=0)
    assert np.all(np.isfinite(lob)) and float(lob.sel(family="rest")) < float(zero.sel(family="rest"))
    assert (out / "suite.png").stat().st_size > 10_000 and (out / "series.png").stat().st_size > 10_000
    # The series file holds v̂ answered and answered-or-carried: equal where vision answers.
    s0 = xr.load_dataset(out / "series" / "ground-s0.nc")
    answered = np.isfinite(s0["v_hat__lobula_zero-phase"].values)
    assert answered.any()
    np.testing.assert_array_equal(s0["v_hat_all__lobula_zero-phase"].values[answered],
                                  s0["v_hat__lobula_zero-phase"].values[answered])
    assert "| rest | lobula zero-phase |" in printed
    # Resumable: a second run reuses the per-scene results and gives the same numbers.
    mtime = (out / "results" / "rest-s0.json").stat().st_mtime
    assert main(argv) == 0
    assert (out / "results" / "rest-s0.json").stat().st_mtime == mtime
    np.testing.assert_array_equal(xr.load_dataset(out / "suite.nc").value.values, ds.value.values)
    res = json.loads((out / "results" / "ground-s0.json").read_text())
    assert res["scene_config"]["scene"]["world"] == "ground"


def test_every_family_builds_a_distinct_seeded_world():
    from stimuli.track import build_track

    seen = set()
    for fam in suite.FAMILIES:
        cfg = suite.family_config(fam, 0, 4.0, 0.1)
        scene, imu = build_track(cfg)
        frame = scene.render(1.0)
        assert frame.std() > 5, fam  # textured, not blank
        v = scene.trajectory.velocity(np.arange(0, 4.0, 0.01))
        assert np.abs(v).max() <= {"fast": 2.0, "ground": 1.5, "corridor": 1.0, "mixed": 2.5}.get(fam, 0.7) + 1e-9, fam
        assert imu["accel_bias_t"].std(0).max() > 0, fam  # the realistic IMU's bias walks
        key = (cfg.scene.world, cfg.scene.seed)
        assert key not in seen
        seen.add(key)
        # Another seed index: another world.
        other = suite.family_config(fam, 1, 4.0, 0.1)
        assert other.scene.seed != cfg.scene.seed
    assert suite.family_config("rotation", 0, 4.0, 0.1).scene.rotation3_amp_deg != (0.0, 0.0, 0.0)
    assert abs(suite.family_config("fast", 2, 10.0, 0.1).random_peak_m_s - 2.0) < 1e-12
    off = suite.family_config("offaxis", 0, 4.0, 0.1).scene
    assert 5 <= abs(off.off_axis_yaw_deg) <= 9 and np.hypot(off.off_axis_yaw_deg, off.off_axis_pitch_deg) <= 10


@pytest.mark.parametrize("command", ["suite", "scene"])
def test_help_shows_every_option_with_its_default(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "(default:" in text
    for opt in {"suite": ["--families", "--seeds", "--duration", "--scale", "--workers", "--imu"],
                "scene": ["--world", "--rotation3", "--peak-speed", "--imu", "--imu-mount", "--brightness"]}[command]:
        assert opt in text


def test_seeds_are_a_count_or_an_explicit_list(tmp_path, capsys):
    assert suite.parse_seeds("3") == 3
    assert suite.parse_seeds("100,101") == [100, 101]
    assert suite.parse_seeds("7,") == [7]  # one seed alone; "7" is a count
    for bad in ("0", "-2", "a", "1,,2", ",", "7,,"):
        with pytest.raises(ValueError, match="--seeds"):
            suite.parse_seeds(bad)
    with pytest.raises(ValueError, match="distinct"):
        suite.run_suite(["rest"], [5, 5], 3.0, 0.2, tmp_path / "s")
    assert main(["suite", "--out", str(tmp_path / "s"), "--seeds", "x"]) == 2
    assert "--seeds" in capsys.readouterr().err


def test_suite_runs_the_emd_front_end_with_its_own_defaults():
    from experiments.suite import velocity_config
    from lobula.config import VelocityConfig

    cfg, want = velocity_config("emd causal"), VelocityConfig(front_end="emd")
    assert cfg.front_end == "emd" and cfg.readout.filter == "causal" and cfg.epipole == "principal"
    assert (cfg.readout.kappa_rel_error, cfg.emd.gaze) == (want.readout.kappa_rel_error, want.emd.gaze)
    assert velocity_config("lobula causal").front_end == "dis"


@pytest.mark.slow  # renders the scene again onto the eye at 500 Hz; the eye's readout runs in make test elsewhere
def test_suite_runs_the_fly_eye_on_the_same_world_and_keeps_it_out_of_all(tmp_path):
    # The eye is named, never part of "all" (each scene is rendered again onto the eye).
    assert not set(suite.EYE_CONFIGURATIONS) & set(suite.CONFIGURATIONS)
    cfg = suite.velocity_config("eye causal")
    assert (type(cfg).__name__, cfg.readout_kind, cfg.readout.filter) == ("EyeVelocityConfig", "spikes", "causal")
    with pytest.raises(ValueError, match="unknown configuration"):
        suite.run_suite(["rest"], [0], 3.0, 0.2, tmp_path / "bad", configurations=["eye zero-phase"])
    out = tmp_path / "suite"
    ds, _ = suite.run_suite(["rest"], [0], 2.5, 0.2, out, configurations=["eye rates causal", "eye rates zero-phase",
                                                                          "zero"], skip_s=1.0,
                            imu="ideal", progress=lambda *a: None)
    eye = out / "scenes" / "rest-s0-eye"
    assert (eye / "luminance.npy").exists() and (out / "scenes" / "rest-s0-eye.json").exists()
    pick = lambda c, m: float(ds.value.sel(family="rest", seed=0, configuration=c, window="after_skip", metric=m))
    # A known answer: the world moves (the zero estimator errs), the eye follows it far closer.
    assert pick("zero", "rmse_m_s") > 0.05
    assert pick("eye rates causal", "rmse_m_s") < 0.25 * pick("zero", "rmse_m_s")
    assert np.isfinite(pick("eye rates causal", "z95")) and pick("eye rates causal", "observable_fraction") > 0.5
    # The same rates offline: the readout's smoother, on the eye footage the causal run read (rendered once).
    zp = suite.velocity_config("eye rates zero-phase")
    assert (zp.readout_kind, zp.readout.filter) == ("kalman", "zero-phase")
    assert pick("eye rates zero-phase", "rmse_m_s") < 0.25 * pick("zero", "rmse_m_s")
    assert json.loads(ds.attrs["configurations"])["eye rates zero-phase"][:2] == ["eye", "zero-phase"]
    series = xr.open_dataset(out / "series" / "rest-s0.nc")
    assert not np.allclose(series["v_hat__eye_rates_zero-phase"], series["v_hat__eye_rates_causal"], equal_nan=True)
    assert json.loads(ds.attrs["eye_config"])["readout"]["filter"] == "causal"
    # The eye footage is rendered once: a second suite in the same folder reuses it.
    mtime = (eye / "luminance.npy").stat().st_mtime
    for f in (out / "results").glob("*.json"):
        f.unlink()
    suite.run_suite(["rest"], [0], 2.5, 0.2, out, configurations=["eye rates causal"], skip_s=1.0, imu="ideal",
                    progress=lambda *a: None)
    assert (eye / "luminance.npy").stat().st_mtime == mtime


def test_worlds_figure_shows_each_world_a_family_flew(tmp_path):
    """worlds.png holds one panel per world a family flew among the seeds (the saccadic family turns from world to
    world with the seed), the middle frame of the first seed in each; a scene not rendered is left out."""
    import cv2

    from experiments.suite import plot_worlds, world_frames

    for name, world in (("saccadic-s0", "panels"), ("saccadic-s1", "corridor"), ("saccadic-s3", "panels"),
                        ("saccadic-s2", "meadow"), ("rest-s0", "panels")):
        folder = tmp_path / "scenes" / name
        (folder / "frames").mkdir(parents=True)
        for k in range(3):
            cv2.imwrite(str(folder / "frames" / f"{k:06d}.png"), np.full((24, 32), 40 * k + 20, np.uint8))
        (folder / "scene.json").write_text(json.dumps({"config": {"scene": {"world": world}}}))
    found = world_frames(tmp_path, ["saccadic", "rest"], [0, 1, 2, 3, 4])
    assert [t for t, _ in found] == ["saccadic, seed 0 (panels)", "saccadic, seed 1 (corridor)",
                                     "saccadic, seed 2 (meadow)", "rest, seed 0 (panels)"]
    assert all(p.name == "000001.png" for _, p in found)
    assert plot_worlds(tmp_path, ["saccadic", "rest"], [0, 1, 2, 3, 4]).stat().st_size > 5_000


def test_a_kept_scene_is_reused_only_as_rendered(tmp_path):
    """A scene is rendered again when its settings differ, or when a file of it was cut short or removed since;
    otherwise reused as it is."""
    from experiments.suite_scene import ensure_rendered

    renders = []

    def render(folder):
        renders.append(folder)
        (folder / "frames").mkdir(parents=True)
        (folder / "frames" / "000000.png").write_bytes(b"x" * 100)
        (folder / "truth.csv").write_text("time_s,v_forward_m_s\n0,0\n0.1,0.1\n")

    scene = tmp_path / "scenes" / "rest-s0"
    for settings in ({"seed": 0}, {"seed": 0}, {"seed": 1}):
        ensure_rendered(scene, settings, render)
    assert len(renders) == 2  # reused once, then new settings
    (scene / "truth.csv").write_text("time_s,v_forward_m_s\n0,0\n")  # cut short
    ensure_rendered(scene, {"seed": 1}, render)
    (scene / "frames" / "000000.png").unlink()
    ensure_rendered(scene, {"seed": 1}, render)
    assert len(renders) == 4 and ensure_rendered(scene, {"seed": 1}, render) == scene and len(renders) == 4
    scene.with_name("rest-s0.json").write_text("{not json")
    ensure_rendered(scene, {"seed": 1}, render)
    assert len(renders) == 5
