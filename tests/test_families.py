"""The estimator on every scene family, short and small (320×240, 6 s; at 160×120 DIS cannot resolve the corridor), against baselines.

Each family's scene comes from `lobula suite`'s own definitions (experiments.suite.family_config,
realistic IMU on a rotated mount). The bounds are relative to baselines that know nothing
(the zero estimator v̂ = 0) or know too much (the constant mean of the truth): an estimator
that does not track velocity cannot beat both by the margins asked here.
"""
import numpy as np
import pytest

from experiments import suite
from experiments.velocity import estimate_velocity
from lobula.config import VelocityConfig
from stimuli.footage import open_footage
from stimuli.track import make_track_run

DURATION_S, SCALE, SKIP_S = 6.0, 0.5, 1.5


@pytest.fixture(scope="module")
def family_run(tmp_path_factory):
    cache = {}

    def make(family):
        if family not in cache:
            folder = tmp_path_factory.mktemp(family) / "run"
            make_track_run(folder, suite.family_config(family, 0, DURATION_S, SCALE), progress=False)
            cache[family] = open_footage(folder)
        return cache[family]

    return make


@pytest.mark.parametrize("family", [
    "panels", "corridor",
    "rotation",  # 0.068 m/s against zero 0.314 and the truth's mean 0.138 (bound 0.069: the weakest family)
    "ground", "fast", "offaxis", "dim", "rest", "moving", "mixed"])
def test_family_beats_the_baselines(family_run, family):
    fo = family_run(family)
    cfg = VelocityConfig()
    ds = estimate_velocity(fo, cfg, progress=False)
    t, v, vt, sd = ds.time.values, ds.v_hat.values, ds.v_true.values, ds.v_std.values
    m = t >= t[0] + SKIP_S
    ok = m & np.isfinite(v)
    rmse = float(np.sqrt(np.mean((v - vt)[ok] ** 2)))
    zero = float(np.sqrt(np.mean(vt[m] ** 2)))
    const = float(np.std(vt[m]))
    cover = float(np.mean(np.abs(v - vt)[ok] <= 2 * sd[ok]))
    print(f"\n{family}: RMSE {rmse:.3f} m/s (zero {zero:.3f}, mean of truth {const:.3f}), "
          f"observable {ok.sum() / m.sum():.2f}, ±2σ {cover:.2f}")
    assert ok.sum() >= 0.8 * m.sum()
    assert rmse <= 0.35 * zero
    assert rmse <= 0.5 * const


@pytest.mark.parametrize("filt", [
    pytest.param("zero-phase", marks=pytest.mark.xfail(strict=True, reason=(
        "band too wide here since the acceleration noise was measured (0.05 -> 0.01 m/s²/√Hz): "
        "RMSE 0.004 m/s but σ 0.016, truth inside ±2σ on 100 % (issue 10, open)"))),
    pytest.param("causal", marks=pytest.mark.xfail(strict=True, reason=(
        "online band too wide here since the 160-px flow grid: RMSE 0.016 m/s, σ 0.019, truth inside ±2σ "
        "on 100 % (73 % before; issue 10, open)")))])
def test_posterior_std_is_calibrated_on_a_family_it_was_not_fitted_on(family_run, filt):
    """Truth inside ±2σ for 85–99.5 % of the frames on the corridor (floor, walls, ceiling).

    The readout's one calibration constant (ReadoutConfig.kappa_rel_error) was fitted on the
    "moving" family's dev seed 100 only; this is another world and seed. Both ends count: a
    band too narrow misses the truth, one too wide (or a v_std that says nothing) covers it always.
    """
    fo = family_run("corridor")
    cfg = VelocityConfig()
    cfg.readout.filter = filt
    ds = estimate_velocity(fo, cfg, progress=False)
    t, v, vt, sd = ds.time.values, ds.v_hat.values, ds.v_true.values, ds.v_std.values
    m = (t >= t[0] + SKIP_S) & np.isfinite(v)
    cover = float(np.mean(np.abs(v - vt)[m] <= 2 * sd[m]))
    print(f"\ncorridor {filt}: ±2σ {cover:.3f}, median σ {np.median(sd[m]):.3f} m/s, "
          f"RMSE {np.sqrt(np.mean((v - vt)[m] ** 2)):.3f}")
    assert m.sum() >= 0.8 * (t >= t[0] + SKIP_S).sum()
    assert 0.85 <= cover <= 0.995
    assert np.median(sd[m]) <= 0.1 * np.sqrt(np.mean(vt[m] ** 2))  # a band that says something
