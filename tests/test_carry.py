"""v̂ carried beyond the frames vision answers (lobula.readout.carry)."""
import numpy as np
import pytest

from lobula.readout import ReadoutConfig, carried_std, readout, time_from_answer


def test_time_from_answer_counts_from_the_last_online_and_the_nearest_offline():
    t = np.arange(7.0)
    answered = np.array([0, 1, 0, 0, 0, 1, 0], bool)
    np.testing.assert_array_equal(time_from_answer(t, answered, causal=True), [np.inf, 0, 1, 2, 3, 0, 1])
    np.testing.assert_array_equal(time_from_answer(t, answered, causal=False), [1, 0, 1, 2, 1, 0, 1])
    assert np.all(np.isinf(time_from_answer(t, np.zeros(7, bool), causal=False)))


def test_carried_std_grows_with_the_offset_prior_and_is_nan_where_never_answered():
    out = carried_std(np.array([0.3, 0.3, 0.3]), np.array([0.0, 2.0, np.inf]), 0.2)
    np.testing.assert_allclose(out[:2], [0.3, 0.5])
    assert np.isnan(out[2])


@pytest.mark.parametrize("filt", ["zero-phase", "causal"])
def test_a_speed_seen_while_accelerating_is_carried_through_a_blind_cruise_with_an_honest_band(filt):
    """Vision fixes the speed while the camera accelerates, then the scene goes dark. The accelerometer's offset
    steps by 1.5 times its prior std in the dark (a tilt leaking gravity): the filter's own posterior, which
    learned the old offset, would hold the carried speed to centimetres per second; the carried band covers the
    drift it causes."""
    dt = 1 / 30
    t = np.arange(0, 14, dt)
    a = np.where(t < 4, 1.5 * np.sin(np.pi * t / 4) ** 2, 0.0)
    v = 1.0 + np.cumsum(a) * dt
    r = v[:, None] / np.linspace(4.0, 30.0, 30)  # fixed depths: ṙ = a/d, no r² term
    r[t >= 6.0] = np.nan
    cfg = ReadoutConfig(filter=filt)
    step = 1.5 * cfg.bias_prior_m_s2
    a_meas = a + np.where(t >= 8.0, step, 0.0)
    res = readout(t, r, np.where(np.isfinite(r), 0.0, np.nan), a_meas, cfg)
    assert res.observable[(t > 2) & (t < 5)].mean() > 0.9
    blind = t >= 8.0
    assert not res.observable[blind].any()
    # carried, not unknown: v̂ on every frame after vision first answered, its σ growing in the dark
    first = np.argmax(res.observable)
    assert np.all(np.isfinite(res.v_hat[first:])) and np.all(np.isfinite(res.v_std[first:]))
    # v̂ is the filter's posterior mean; only its std is not the posterior's
    np.testing.assert_array_equal(res.v_hat[first:], res.info["posterior_mean"][first:])
    assert np.all(res.v_std[first:] >= res.info["posterior_std"][first:])
    assert np.all(np.diff(res.v_std[blind]) >= -1e-12)
    err = res.v_hat - v
    assert np.abs(err[-1]) > 0.5 * step * (t[-1] - 8.0)  # the step did move the carried speed
    assert np.all(np.abs(err[blind]) <= 2 * res.v_std[blind])
    last = np.flatnonzero(res.observable)[-1]
    assert res.v_std[-1] >= cfg.bias_prior_m_s2 * (t[-1] - t[last])


def test_the_score_counts_the_carried_frames_and_the_band_over_every_frame():
    import xarray as xr

    from experiments.velocity import carried_line, score

    t = np.arange(10.0)
    v_true = np.full(10, 2.0)
    # skipped, never answered, observable ×3 (one outside its band), carried ×5 (one outside)
    v_hat = np.array([0.0, np.nan, 2.0, 2.1, 2.5, 2.0, 2.0, 3.0, 1.0, 5.0])
    v_std = np.array([1.0, np.nan, 0.1, 0.1, 0.1, 1.0, 1.0, 1.0, 1.0, 1.0])
    obs = np.array([0, 0, 1, 1, 1, 0, 0, 0, 0, 0], bool)
    ds = xr.Dataset(dict(v_hat=("time", v_hat), v_std=("time", v_std), observable=("time", obs),
                         v_true=("time", v_true)), coords=dict(time=t))
    sc = score(ds, skip_s=1.0)
    assert sc["n_frames"] == 9 and sc["observable_fraction"] == pytest.approx(3 / 9)
    assert sc["carried_fraction"] == pytest.approx(5 / 9)
    assert sc["coverage_2sigma_all"] == pytest.approx(6 / 9)   # the frame without v̂ counts outside
    assert sc["rmse_m_s"] == pytest.approx(np.sqrt((0.0 + 0.01 + 0.25) / 3))
    assert "55.6 %" in carried_line(sc) and "67 %" in carried_line(sc)
    ds["observable"] = ds.observable | True
    ds["v_hat"] = ds.v_hat.fillna(2.0)
    assert carried_line(score(ds, skip_s=1.0)) is None
