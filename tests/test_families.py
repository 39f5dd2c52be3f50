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
    "corridor",
    pytest.param("rotation", marks=pytest.mark.xfail(
        strict=True, reason="3-axis rotation with the realistic IMU: RMSE 0.16 m/s, ±2σ 10 % (issue 10, open)")),
    "ground", "fast", "moving"])
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
