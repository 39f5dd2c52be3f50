"""The fly-flight figures' flights and scores (experiments.fly_flight_figures): known answers, no rendering."""
from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr

from experiments.fly_flight_figures import FLIGHTS, flight_run_config, flight_scores
from stimuli.flight import saccadic_flight


def _plan(flight, seed=0, duration=8.0):
    cfg = flight_run_config(flight, seed, duration)
    assert cfg.flight == "saccadic"
    return saccadic_flight(cfg.scene.seed, cfg.duration_s, cfg.flight_config)


def test_flights_differ_only_where_they_say():
    """The no-wobble flight has the saccadic flight's segments and saccades and no wobble; the turning flight
    never turns faster than the saccade gate (300 °/s) while the saccadic one does; the gaze flight is the
    saccadic flight's configuration (the head is the only difference)."""
    sac, calm, turn = _plan("saccadic"), _plan("saccadic, no wobble"), _plan("turning")
    np.testing.assert_array_equal(sac.saccades, calm.saccades)
    np.testing.assert_array_equal(sac.segments, calm.segments)
    t = np.arange(0.0, 8.0, 0.001)
    assert np.abs(calm.wobble(t, 1)).max() == 0.0
    assert np.degrees(np.abs(sac.wobble(t, 1)).max()) > 10.0
    peak = lambda p: np.degrees(np.abs(p.heading(t, 1)).max())
    assert peak(sac) > 300.0 > peak(turn) > 50.0
    assert flight_run_config("saccadic, gaze", 1) == flight_run_config("saccadic", 1)
    assert FLIGHTS["saccadic, gaze"][1] and not FLIGHTS["saccadic"][1]


def test_flight_scores_count_answered_frames_outside_saccades():
    """On a series with a known error: 0.02 m/s off from 3.6 s on, 0.3 before, answered from 4 s on, a saccade
    whose frames are left out: the RMSE where answered, the answered fraction, the RMSE on every frame and the
    lock-on times (answered frames: 4 s; every frame: 3.6 s) come out as constructed."""
    t = np.arange(0.0, 8.0, 0.02)
    v_true = np.full(len(t), 0.5)
    answered = (t >= 4.0)
    sac = (t >= 3.0) & (t < 3.5)
    err = np.where(t >= 3.6 - 1e-9, 0.02, 0.3)
    ds = xr.Dataset(dict(v_hat=("time", v_true + err), v_true=("time", v_true),
                         observable=("time", answered), saccade=("time", sac),
                         v_std=("time", np.full(len(t), 0.1))), coords=dict(time=t))
    s = flight_scores(ds, skip_s=2.0)
    keep = (t >= 2.0) & ~sac
    assert s["rmse_answered"] == pytest.approx(0.02)
    assert s["answered"] == pytest.approx(answered[keep].mean())
    assert s["rmse_all"] == pytest.approx(math.sqrt(np.mean(err[keep] ** 2)))
    assert s["coverage_2sigma"] == pytest.approx((t[keep] >= 3.6 - 1e-9).mean())   # 0.02 inside ±0.2, 0.3 out
    assert s["lock_on_s"] == pytest.approx(4.0)       # within 0.05 + 10 %·0.5, answered, from 4 s on
    assert s["lock_on_all_s"] == pytest.approx(3.6)
    assert s["zero"] == pytest.approx(0.5)
