"""The online/offline information bound (experiments.online_bound) against known answers."""
import json
from dataclasses import replace

import numpy as np
import pytest

from experiments.online_bound import (InformationModel, family_trajectory, filter_and_smoother, kappa_noise, main,
                                      online_offline, readout_latency_s, vision_kappa)

T = np.arange(300) / 30.0


def test_latency_is_the_causal_readouts():
    # 1.5σ of the 1 Hz Gaussian at 30 frames/s (σ = 5.6 frames: 9 frames) plus half the stagger of 4 (2 frames)
    assert round(readout_latency_s(1 / 30) * 30) == 11


def test_a_known_offset_and_a_deterministic_motion_measure_the_start_velocity_frame_by_frame():
    # With b known and no acceleration noise, v_k = v_0 + a·t_k is known up to v_0, and frame k measures v_0 with
    # variance (floor·v_k/a)²: the filter's variance is 1/(1/prior + Σ_{j≤k} info_j), the smoother's the sum
    # over all.
    a = 0.3
    v = 0.2 + a * T
    m = InformationModel(kappa_rel_error=0.0, kappa_abs_error=0.0, accel_floor=0.02, accel_noise=0.0,
                         bias_walk=0.0, bias_prior=1e-9, v_prior=1.0, latency_s=0.0)
    pf, ps, pl = filter_and_smoother(T, v, np.full_like(T, a), m)
    info = (a / (m.accel_floor * v)) ** 2
    expect_f = 1.0 / (1.0 / m.v_prior ** 2 + np.cumsum(info))
    expect_s = np.full_like(T, 1.0 / (1.0 / m.v_prior ** 2 + info.sum()))
    np.testing.assert_allclose(pf, expect_f, rtol=1e-5)
    np.testing.assert_allclose(ps, expect_s, rtol=1e-5)
    np.testing.assert_allclose(pl, pf)  # on time: the online estimate is the filter's


def test_a_random_walk_observed_each_frame_has_the_scalar_riccati_steady_states():
    # κ = a/v = 1 and b known: y = v + n each frame, v a random walk. Mid-record the filter and the smoother sit
    # at the scalar Riccati fixed points, and in the continuous limit (q·dt ≪ R) their ratio of variances is 2.
    v = np.exp(T)
    q, r = 0.01 ** 2, 0.02 ** 2
    m = InformationModel(kappa_rel_error=0.0, kappa_abs_error=0.0, accel_floor=np.sqrt(r), accel_noise=np.sqrt(q),
                         bias_walk=0.0, bias_prior=1e-9, latency_s=0.0)
    pf, ps, _ = filter_and_smoother(T, v, v, m)
    dt = T[1]
    qd = q * dt
    pminus = 0.5 * (qd + np.sqrt(qd ** 2 + 4 * qd * r))  # P⁻ = P + q·dt with P = P⁻·r/(P⁻ + r)
    p = pminus * r / (pminus + r)
    c = p / pminus
    p_s = (p - c ** 2 * pminus) / (1 - c ** 2)  # the RTS recursion's fixed point
    np.testing.assert_allclose(pf[150], p, rtol=1e-6)
    np.testing.assert_allclose(ps[150], p_s, rtol=1e-6)
    assert 1.85 < pf[150] / ps[150] < 2.0  # → 2 as q·dt/R → 0 (here 0.008)


def test_latency_only_adds_uncertainty_and_the_scale_error_is_common():
    t, v, a = T, 0.5 + 0.3 * np.sin(T), 0.3 * np.cos(T)
    on_time = online_offline(t, v, a, InformationModel(latency_s=0.0))
    late = online_offline(t, v, a, InformationModel(latency_s=0.4))
    assert on_time["online"] == pytest.approx(on_time["filter"])
    assert late["online"] > 1.05 * late["filter"]
    assert late["offline"] == pytest.approx(on_time["offline"])
    assert 1.0 < on_time["filter_ratio"] < late["online_ratio"]
    # a larger error common to both pulls the ratio toward 1
    big = online_offline(t, v, a, InformationModel(latency_s=0.4, scale_error=0.1))
    assert 1.0 < big["online_ratio"] < late["online_ratio"]


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="finite"):
        filter_and_smoother(T, np.full_like(T, np.nan), T, InformationModel())


@pytest.mark.parametrize("argv, words", [
    (["--families", "bogus"], "--families: unknown bogus"),
    (["--duration", "nan"], "the skip must lie in [0, duration)"),
    (["--skip", "5", "--duration", "3"], "the skip must lie in [0, duration)"),
    (["--plot", "ratios.txt"], "--plot ratios.txt: use a .png, .pdf or .svg file"),
    (["--out", "{file}/bound.json"], "is a file, not a folder"),
    (["--seeds", "0"], "--seeds must be a positive count"),
    (["--families", "rest", "--seeds", "7,", "--duration", "4", "--suite", "{file}"], "not a `lobula suite` suite.nc"),
])
def test_the_command_line_refuses_in_one_line_before_any_work(tmp_path, capsys, argv, words):
    import xarray as xr

    not_a_suite = tmp_path / "run.nc"
    xr.Dataset({"v_hat": ("time", np.zeros(3))}).to_netcdf(not_a_suite)
    argv = [a.replace("{file}", str(not_a_suite)) for a in argv]
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's refusal
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert rc == 2 and words in err and len(err.splitlines()) == 1, err


def test_family_trajectory_is_the_rendered_truth(tmp_path):
    from experiments.suite import family_config
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    cfg = replace(family_config("rotation", 5, 1.0, scale=0.1), depth_every=0)
    folder = make_track_run(tmp_path / "rot", cfg, progress=False)
    truth = open_footage(folder).truth
    t, v, a = family_trajectory("rotation", 5, 1.0)
    np.testing.assert_allclose(t, truth["time_s"], atol=1e-6)
    np.testing.assert_allclose(v, truth["v_forward_m_s"], atol=2e-6)
    np.testing.assert_allclose(a, truth["a_forward_m_s2"], atol=2e-6)


def test_command_line_writes_rows_and_provenance(tmp_path, capsys):
    out = tmp_path / "bound.json"
    assert main(["--families", "rest", "--seeds", "7,", "--duration", "4", "--models", "measured",
                 "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    (row,) = doc["rows"]
    assert row["family"] == "rest" and row["seed"] == 7 and row["online_ratio"] > row["filter_ratio"] > 1.0
    assert {"git_commit", "command_line", "config", "lobula_version"} <= set(doc["provenance"])
    assert "| rest |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--models", "nonesuch"])


def test_kappa_noise_recovers_a_known_white_error_and_scales_a_correlated_one():
    rng = np.random.default_rng(3)
    t = np.arange(3000) / 30.0
    v = 0.6 + 0.4 * np.sin(0.7 * t)
    a = 0.3 * np.cos(1.9 * t + 1.0)  # not v's derivative: the fit needs a² and v² to vary apart
    # white errors in a_m = κ·v: 10 % of a and a 0.02 m/s² floor
    err = 0.1 * a * rng.standard_normal(len(t)) + 0.02 * rng.standard_normal(len(t))
    n = kappa_noise(t, (a + err) / v, v, a)
    assert n["kappa_rel_error"] == pytest.approx(0.1, rel=0.15)
    assert n["accel_floor"] == pytest.approx(0.02, rel=0.1)
    assert n["kappa_abs_error"] < 0.02 and n["correlation_s"] < 2 / 30
    assert n["gain"] == pytest.approx(1.0, abs=0.01)
    # the same floor through a 10-frame moving average: 10× the variance per frame of white errors, as much
    # information; and κ 5 % low reads as its gain
    smooth = np.convolve(0.02 * rng.standard_normal(len(t) + 9), np.ones(10) / np.sqrt(10), "valid")
    m = kappa_noise(t, 0.95 * a / v + smooth / v, v, a)
    # (the correlation time, summed over the lags that pass 2/√n, is itself noisy: ±50 % at 3,000 frames)
    assert m["correlation_s"] == pytest.approx(10 / 30, rel=0.5)
    assert m["accel_floor"] == pytest.approx(0.02 * np.sqrt(10), rel=0.25)
    assert m["gain"] == pytest.approx(0.95, abs=0.01)
    with pytest.raises(ValueError, match="need 20"):
        kappa_noise(t, np.full_like(t, np.nan), v, a)


def test_vision_kappa_of_exact_fields_is_a_over_v():
    from lobula.readout import ReadoutConfig

    # fields at depths D0 (1–4 m) approached at v(t): r = v/D, ṙ = a/D + r², r²̄ = r²
    t = np.arange(240) / 30.0
    v = 0.5 + 0.2 * np.sin(0.8 * t)
    a = 0.16 * np.cos(0.8 * t)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / 30.0)])
    depth = np.linspace(1.0, 4.0, 12)[None, :] + 3.0 - x[:, None]
    r = v[:, None] / depth
    kappa = vision_kappa(t, r, r ** 2, a, ReadoutConfig())
    inner = (t > 1) & (t < 7) & (np.abs(a) > 0.05)
    np.testing.assert_allclose(kappa[inner], (a / v)[inner], atol=0.02)


def test_footage_mode_measures_the_cameras_kappa(tmp_path, capsys):
    from stimuli.track import TrackRunConfig, make_track_run
    from stimuli.scene import SceneConfig

    cfg = TrackRunConfig(start_s=2.0, duration_s=4.0, scale=0.25, scene=SceneConfig(seed=3), depth_every=0)
    folder = make_track_run(tmp_path / "panels", cfg, progress=False)
    out = tmp_path / "kappa.json"
    assert main(["--footage", str(folder), "--out", str(out)]) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert row["front_end"] == "dis" and row["n_frames"] >= 40
    # DIS's κ on frontal panels: a_m = κ·v within a few hundredths of a m/s², its gain within 5 % of 1
    assert row["rms_m_s2"] < 0.05 and abs(row["gain"] - 1) < 0.05
    assert row["online"] > row["offline"] > 0
    assert "| panels | dis |" in capsys.readouterr().out


def _suite_nc(path, seeds=(7,), skip=2.0, duration=4.0):
    import xarray as xr

    confs = ["lobula zero-phase", "lobula causal", "zero"]
    value = np.zeros((1, len(seeds), 3, 2, 1))
    value[0, :, 0, 0, 0] = 0.004  # zero-phase RMSE after the skip
    value[0, :, 1, 0, 0] = 0.010  # causal
    ds = xr.Dataset(dict(value=(("family", "seed", "configuration", "window", "metric"), value)),
                    coords=dict(family=["rest"], seed=list(seeds), configuration=confs,
                                window=["after_skip", "first_2s"], metric=["rmse_m_s"]),
                    attrs=dict(suite=json.dumps(dict(skip_s=skip, duration_s=duration))))
    ds.to_netcdf(path, engine="h5netcdf")
    return path


def test_the_pipelines_ratio_comes_from_a_suite_file_that_matches(tmp_path, capsys):
    from experiments.online_bound import suite_ratios

    nc = _suite_nc(tmp_path / "suite.nc")
    assert suite_ratios(nc, ["rest"], [7], 2.0, 4.0) == {("rest", 7): pytest.approx(2.5)}
    png = tmp_path / "bound.png"
    assert main(["--families", "rest", "--seeds", "7,", "--duration", "4", "--models", "measured",
                 "--suite", str(nc), "--plot", str(png)]) == 0
    assert png.stat().st_size > 10_000 and "| rest |" in capsys.readouterr().out
    for bad, match in (((["rest"], [8], 2.0, 4.0), "no seed 8"), ((["rest"], [7], 1.0, 4.0), "skip_s"),
                       ((["corridor"], [7], 2.0, 4.0), "no family corridor")):
        with pytest.raises(ValueError, match=match):
            suite_ratios(nc, *bad)
    with pytest.raises(SystemExit):  # refused on the command line too, not a traceback
        main(["--families", "rest", "--seeds", "8,", "--duration", "4", "--suite", str(nc)])


def test_the_readouts_priors_start_the_bound_where_the_readout_starts():
    # The readout starts v at 15 m/s and the offset with the gravity reference's error: offline the record's mean
    # acceleration (up to 15 m/s over its span), online the start's (0.3 g where the camera moves at the first
    # frame, 0.1 g at rest).
    from lobula.readout import ReadoutConfig
    from lobula.velocity.inertial import START_ACCEL_PRIOR_M_S2, START_ACCEL_PRIOR_MOVING_M_S2
    from experiments.online_bound import readout_priors

    rc = ReadoutConfig()
    moving = readout_priors(InformationModel(), T, np.full_like(T, 2.0))
    assert moving.v_prior == rc.v_prior_m_s
    assert moving.bias_prior == pytest.approx(np.hypot(rc.bias_prior_m_s2, rc.v_prior_m_s / (T[-1] - T[0])))
    assert moving.bias_prior_online == pytest.approx(np.hypot(rc.bias_prior_m_s2, START_ACCEL_PRIOR_MOVING_M_S2))
    at_rest = readout_priors(InformationModel(), T, 0.3 * T)
    assert at_rest.bias_prior_online == pytest.approx(np.hypot(rc.bias_prior_m_s2, START_ACCEL_PRIOR_M_S2))
    # Nothing vision sees tells v here (no acceleration: κ = 0 measures the offset alone), so v stays at its
    # prior, as wide as the readout's (widened by a few µm/s: the offset's first frames, integrated).
    t = np.arange(60) / 30.0
    _, ps, _ = filter_and_smoother(t, np.full_like(t, 2.0), np.zeros_like(t),
                                   replace(readout_priors(InformationModel(), t, np.full_like(t, 2.0)), accel_noise=0.0,
                                           bias_walk=0.0))
    np.testing.assert_allclose(np.sqrt(ps), rc.v_prior_m_s, rtol=1e-5)


def test_the_online_estimator_starts_from_its_own_offset_prior():
    # bias_prior_online changes the online figures alone: they are the model's with that offset prior, and the
    # offline figure stays the one with bias_prior.
    v = 0.2 + 0.3 * T
    a = np.full_like(T, 0.3)
    base = InformationModel(latency_s=0.2)
    split = online_offline(T, v, a, replace(base, bias_prior_online=2.0))
    assert split["offline"] == pytest.approx(online_offline(T, v, a, base)["offline"])
    wide = online_offline(T, v, a, replace(base, bias_prior=2.0))
    assert split["online"] == pytest.approx(wide["online"])
    assert split["filter"] == pytest.approx(wide["filter"])
    assert split["online"] > online_offline(T, v, a, base)["online"]
