"""The EMD front end feeding the velocity readout: decoding against exact r, replay, real frames."""
import numpy as np
import pytest

from experiments.calibrate import calibrate_emd, exact_field_rates
from experiments.velocity import score
from lobula.velocity import estimate_velocity, field_rates
from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.readout import ReadoutConfig, readout
from lobula.emd_front_end import EMDFrontEnd, EMDFrontEndConfig, fit_calibration
from lobula.receptive_field import tile_fields
from lobula.readers import open_footage
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run


@pytest.fixture(scope="module")
def constant_run(tmp_path_factory):
    cfg = TrackRunConfig(constant_velocity_m_s=0.4, duration_s=3.0, scale=0.5, scene=SceneConfig(seed=5))
    return open_footage(make_track_run(tmp_path_factory.mktemp("emd") / "c", cfg, progress=False))


@pytest.mark.parametrize("surround", [0.0, 1.0])
def test_gradient_ratio_decoding_tracks_exact_expansion_rate(constant_run, surround):
    """Peripheral fields (where image motion is resolved) decode r = v/d to within tens of percent,
    with the mean removed in time (a 0.25 s high-pass) or in space (the LMC surround,
    ``EMDFrontEndConfig.surround``, the default, no high-pass)."""
    from lobula.photoreceptor import mean_removal

    cfg = VelocityConfig(front_end="emd")
    cfg.emd.surround, cfg.emd.photoreceptor = mean_removal("space" if surround else "time", cfg.emd.photoreceptor)
    idx, r_exact = exact_field_rates(constant_run, cfg)
    fields = tile_fields(constant_run.camera, cfg.fields)
    r_emd = np.array([r for _, r, _ in EMDFrontEnd(constant_run.camera, fields, cfg.emd).run(constant_run.frames())])
    ecc = np.hypot(*fields.centres_deg.T)
    late = idx >= 30  # photoreceptor high-pass settled
    e, x = r_emd[idx[late]][:, ecc > 12], r_exact[late][:, ecc > 12]
    ratio = np.median(e / x)
    corr = np.corrcoef(e.ravel(), x.ravel())[0, 1]
    print(f"\nEMD/exact r (fields > 12° out): median ratio {ratio:.3f}, correlation {corr:.3f}")
    # Measured 0.73 (high-pass) and 0.48 (surround: it whitens the image, moving contrast toward the
    # lattice's Nyquist limit, where the gradient ratio reads low — a gain κ = (ṙ − r²)/r is blind to
    # up to the r²-term); correlations 0.96 and 0.93.
    assert (0.6 < ratio < 1.4) if surround == 0 else (0.3 < ratio < 0.8)
    assert corr > 0.5
    assert np.all(np.sign(np.median(e, 0)) > 0)  # expansion everywhere


def test_the_columns_settling_after_a_start_reach_no_readout(constant_run):
    """The columns start at rest: their first frame reads no motion and the next climbs toward the moving level
    (at 30 frames/s with the 10 ms photoreceptor and delay filters: 0, then 70 %, then the level, measured on a
    braking camera), a ṙ the world never had. The frames within twice those time constants of the start are
    NaN; the first one kept reads the camera's expansion already (measured here, approaching at 0.4 m/s: 0.97 of
    the median of the next five frames, where the frame before it reads 0.70)."""
    cfg = VelocityConfig(front_end="emd")
    fields = tile_fields(constant_run.camera, cfg.fields)
    front = EMDFrontEnd(constant_run.camera, fields, cfg.emd)
    r = np.array([r for _, r, _ in front.run(constant_run.frames())])
    settling = np.arange(len(r)) * constant_run.camera.frame_interval_s < front.settle_s
    settling[0] = True
    assert settling.sum() == 2    # 0 and 33 ms at 30 frames/s; the settle time is 40 ms
    assert np.isnan(r[settling]).all() and np.isfinite(r[~settling]).any(axis=1).all()
    first = int(np.flatnonzero(~settling)[0])
    level = np.full(len(r), np.nan)
    level[first:] = np.nanmedian(r[first:], axis=1)
    steady = np.median(level[first + 1:first + 6])
    print(f"\nfirst kept frame / the next five frames' median r: {level[first] / steady:.3f}")
    assert abs(level[first] / steady - 1.0) < 0.05


def test_calibration_is_per_field_and_checked(constant_run):
    gains, latency, n = calibrate_emd(constant_run, VelocityConfig(front_end="emd"))
    assert 0.0 <= latency <= 0.3
    F = tile_fields(constant_run.camera).n_fields
    assert gains.shape == (F,) and n > 3 and np.all(np.isfinite(gains))
    assert fit_calibration(np.array([[1.0], [2.0]]), np.array([[2.0], [4.0]]), per_field=False) == 2.0
    with pytest.raises(ValueError, match="gains"):
        EMDFrontEnd(constant_run.camera, tile_fields(constant_run.camera),
                    EMDFrontEndConfig(calibration=[1.0, 2.0]))


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    """Gains and latency fitted on a different scene: built-in profile, texture seed 11, 8 s."""
    cfg = TrackRunConfig(profile=None, start_s=3.0, duration_s=8.0, scale=0.5, scene=SceneConfig(seed=11))
    fo = open_footage(make_track_run(tmp_path_factory.mktemp("calib") / "c", cfg, progress=False))
    gains, latency, _ = calibrate_emd(fo, VelocityConfig(front_end="emd"))
    return gains, latency


def _dis_on_the_replay(replay_rates) -> dict:
    """DIS's RMSE (m/s) and observable fraction on the 30 s replay after 2 s, the default readout."""
    rates, a, v_true, _ = replay_rates
    res = readout(rates.t, rates.r, rates.r2, a, ReadoutConfig())
    m = (rates.t >= rates.t[0] + 2.0)
    return dict(rmse_m_s=float(np.sqrt(np.mean((res.v_hat - v_true)[m & res.observable] ** 2))),
                observable_fraction=float(res.observable[m].mean()))


@pytest.mark.slow  # a 30 s EMD run; make test runs the EMD end to end on the constant run below
def test_emd_replay_beside_dis(replay_rates, emd_replay):
    """EMD and DIS on the same 30 s replay; the EMD's RMSE is reported beside DIS's.

    Measured: DIS 0.0039 m/s at fixed pixels, the EMD uncalibrated 0.0027 (0.68×); the bound is 3.5×.
    """
    emd, dis = score(emd_replay), _dis_on_the_replay(replay_rates)
    print(f"\nreplay: EMD RMSE {emd['rmse_m_s']:.4f} (observable {emd['observable_fraction']:.3f}), "
          f"DIS {dis['rmse_m_s']:.4f} ({dis['observable_fraction']:.3f}): {emd['rmse_m_s'] / dis['rmse_m_s']:.2f}x")
    assert emd["rmse_m_s"] < 0.08 and emd["observable_fraction"] > 0.9
    assert emd["rmse_m_s"] < 3.5 * dis["rmse_m_s"]


@pytest.mark.slow  # a second 30 s EMD run and a calibration scene; make test runs the calibration on its own above
def test_emd_calibrated_elsewhere_beside_dis(make_replay, replay_rates, calibration):
    """The EMD with gains and latency fitted on another scene, on the 30 s replay: measured 0.039 m/s, 2.5× DIS
    (against the project's target of 2×); the bound is 3×."""
    cal = VelocityConfig(front_end="emd")
    cal.emd.calibration, cal.emd.latency_s = list(calibration[0]), calibration[1]
    emd_cal = score(estimate_velocity(open_footage(make_replay(0.0, 30.0)), cal, progress=False))
    dis = _dis_on_the_replay(replay_rates)
    print(f"\ncalibrated elsewhere {emd_cal['rmse_m_s']:.4f}: {emd_cal['rmse_m_s'] / dis['rmse_m_s']:.2f}x DIS "
          f"(latency {1000 * calibration[1]:.0f} ms)")
    assert emd_cal["rmse_m_s"] < 3.0 * dis["rmse_m_s"] and emd_cal["observable_fraction"] > 0.9


def test_emd_and_dis_field_rates_agree_on_real_frames(d435i):
    """Real D435i frames: EMD r̄_f against DIS r̄_f (both about the principal point).

    Measured: correlation 0.35 over all (time, field) entries after the first 0.5 s
    (the photoreceptor high-pass settling), 0.77 between the fields' time means.
    """
    fo = open_footage(d435i)
    d = field_rates(fo, VelocityConfig(epipole="principal"), progress=False)
    e = field_rates(fo, VelocityConfig(front_end="emd"), progress=False)
    re = np.array([np.interp(d.t, e.t, e.r[:, f]) for f in range(e.r.shape[1])]).T
    late = d.t > e.t[0] + 0.5
    ok = np.isfinite(re) & np.isfinite(d.r) & late[:, None]
    corr = np.corrcoef(re[ok], d.r[ok])[0, 1]
    corr_mean = np.corrcoef(np.nanmean(re[late], 0), np.nanmean(d.r[late], 0))[0, 1]
    print(f"\nreal frames: EMD vs DIS r̄_f correlation {corr:.3f} (all), {corr_mean:.3f} (field means)")
    assert corr > 0.2 and corr_mean > 0.5


def test_emd_front_end_records_what_it_runs(constant_run):
    """The EMD path neither estimates an epipole nor derotates its responses: its configuration and
    attributes say so, and asking it for an epipole estimate fails instead of running without one."""
    import json

    emd_run = estimate_velocity(constant_run, VelocityConfig(front_end="emd"), progress=False)

    assert VelocityConfig(front_end="emd").epipole == "principal"
    assert VelocityConfig().epipole == "estimate"                       # the flow front ends estimate it
    assert VelocityConfig().for_front_end("emd").epipole == "principal"
    assert VelocityConfig(epipole="principal").for_front_end("dis").epipole == "principal"
    assert json.loads(emd_run.attrs["config"])["epipole"] == "principal"
    assert emd_run.attrs["epipole"] == "principal"
    assert emd_run.attrs["derotation"].startswith("gaze stabilised" if VelocityConfig().derotate else "none")

    cfg = VelocityConfig(front_end="emd")
    cfg.epipole = "estimate"                                            # as --epipole estimate sets it
    with pytest.raises(ValueError, match="no epipole estimate"):
        estimate_velocity(constant_run, cfg, progress=False)


def test_pooled_sums_at_any_epipole_equal_the_fixed_epipole_weights(constant_run):
    """The pooled numerator and denominator are linear and quadratic in the epipole, so nine sums per
    field give :func:`pair_pooling_weights`' exactly, wherever the epipole moves."""
    from lobula.emd_front_end import epipole_pooling_weights, pair_pooling_weights, pooled_at_epipole
    from lobula.lattice import Lattice, LatticeConfig

    cam = constant_run.camera
    lat = Lattice(cam, LatticeConfig(dphi_deg=1.5))
    fields = tile_fields(cam)
    rng = np.random.default_rng(0)
    R, G = rng.normal(size=(4, lat.n_pairs)), rng.uniform(size=(4, lat.n_pairs))
    wn, wd = epipole_pooling_weights(lat, fields, 0.01)
    e = np.array([[0.0, 0.0], [0.1, -0.05], [-0.2, 0.15], [0.03, 0.3]])
    num, den = pooled_at_epipole(R @ wn, G @ wd, e)
    for k in range(len(e)):
        n, d = pair_pooling_weights(lat, fields, e[k], 0.01)
        np.testing.assert_allclose(num[k], n @ R[k], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(den[k], d @ G[k], rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def turning_still_run(tmp_path_factory):
    """A camera that only turns (3-axis, up to 5°, 0.5–1.5 Hz) in front of panels: every field's true r = 0."""
    cfg = TrackRunConfig(constant_velocity_m_s=0.0, duration_s=3.0, scale=0.5,
                         scene=SceneConfig(seed=11, rotation3_amp_deg=(5.0, 4.0, 3.0), rotation3_band_hz=(0.5, 1.5)))
    return open_footage(make_track_run(tmp_path_factory.mktemp("turn") / "t", cfg, progress=False))


def test_stabilised_gaze_removes_the_turns_aliased_expansion(turning_still_run):
    """A still camera turning at up to ~45°/s moves its image up to 1.5° per frame, twice Δφ: the
    unstabilised EMD fields read large spurious expansion; warped into the fixated gaze (the default
    with a gyro) they read a fraction of it, and say which output it was."""
    fo = turning_still_run
    out = {}
    for gaze in ("none", "fixate"):
        cfg = VelocityConfig(front_end="emd")
        cfg.emd.gaze = gaze
        rates = field_rates(fo, cfg, progress=False)
        out[gaze] = np.nanmedian(np.abs(rates.r[15:]))
    print(f"\nturning still camera, median |r̄| (true 0): unstabilised {out['none']:.3f}, fixated {out['fixate']:.3f} 1/s")
    assert out["fixate"] < 0.3 * out["none"]
    ds = estimate_velocity(fo, VelocityConfig(front_end="emd"), progress=False)
    assert ds.attrs["derotation"].startswith("gaze stabilised")
    import json
    from lobula.emd_front_end import EMDFrontEndConfig
    old = json.loads(json.dumps(EMDFrontEndConfig().to_dict()))
    old.pop("gaze")
    assert EMDFrontEndConfig.from_dict(old).gaze == "none"     # stored without a gaze: the camera's image


def test_emd_gaze_option_sets_the_gaze_and_is_refused_elsewhere():
    import argparse

    from experiments.velocity import apply_velocity_options

    cfg = apply_velocity_options(VelocityConfig(front_end="emd"), argparse.Namespace(emd_gaze="none"))
    assert cfg.emd.gaze == "none" and VelocityConfig(front_end="emd").emd.gaze == "fixate"
    with pytest.raises(ValueError, match="--emd-gaze"):
        apply_velocity_options(VelocityConfig(front_end="dis"), argparse.Namespace(emd_gaze="fixate"))
