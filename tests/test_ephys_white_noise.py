"""``lobula ephys white-noise``: spatiotemporal white noise and reverse correlation.

Known answers:
- The photoreceptor (a 10 ms low-pass and a 0.25 s high-pass, linear) recorded directly: with frames of
  one step its STRF at offset 0 is its impulse response per step (the response-weighted average over
  the contrast variance), and 0 at every other offset; with frames of m steps, the impulse response
  convolved with the frames' autocorrelation, a triangle of half-width m.
- A T4 (T5) cell, LP_τ(c[A])·c[B] with B its neighbour along the preferred direction, sees B through the
  fast arm and A through the 35 ms delay: its STRF tilts in space-time (the response follows a stimulus
  at B sooner than one at A), toward its preferred direction — opposite tilts for opposite layers.
  T4's (ON) STRF is positive, T5's (OFF) negative.
- Trial k's noise comes from trial_seed(seed, k) alone.
Tiny rig (Δφ = 4°): a few seconds per run.
"""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from experiments.ephys.command import run_protocol
from experiments.ephys.rig import EphysConfig, Rig, trial_seed
from experiments.ephys.white_noise import _tilt, white_noise, white_noise_stimulus
from experiments.store import cf_problems
from lobula.lattice import LatticeConfig
from lobula.photoreceptor import photoreceptor_run

TINY = EphysConfig(lattice=LatticeConfig(dphi_deg=4.0), trials=2)
CENTRE = "photoreceptor.v[45,46,56,57,58,68,69]"


def _impulse_response(n: int) -> np.ndarray:
    """The circuit's photoreceptor response per step to a one-step unit pulse on a mean of 1 (n steps)."""
    x = torch.ones(1, n + 1, 1, dtype=torch.float64)
    x[0, 1, 0] = 2.0
    y, _ = photoreceptor_run(TINY.circuit.photoreceptor, TINY.circuit.dt_s, x)
    return (y[0, 1:, 0] - y[0, 0, 0]).numpy()


@pytest.fixture(scope="module")
def plate():
    """T4 and T5 of the central column and its neighbours (the default monitors), 4 × 3 s."""
    return white_noise(replace(TINY, trials=4), duration_s=3.0)


def test_photoreceptor_strf_is_its_impulse_response():
    ds = white_noise(TINY, duration_s=2.0, record=[CENTRE])
    strf = ds.photoreceptor_v_strf.mean("ommatidium")
    h = _impulse_response(ds.sizes["lag_s"])
    k = strf.sel(offset_deg=0.0).values
    assert np.corrcoef(k, h)[0, 1] > 0.95
    assert float(k[:20].sum() / h[:20].sum()) == pytest.approx(1.0, abs=0.1)   # the amplitude too, per unit contrast
    others = strf.where(strf.offset_deg != 0).values
    assert np.nanmax(np.abs(others)) < 0.1 * h.max()
    assert ds.photoreceptor_v_strf.dims == ("lag_s", "offset_deg", "ommatidium")
    assert ds.lag_s.attrs["units"] == "s" and ds.offset_deg.attrs["units"] == "degree"
    assert cf_problems(ds) == []


def test_frames_of_several_steps_smooth_the_kernel_with_their_triangle():
    m = 5
    ds = white_noise(TINY, duration_s=3.0, frame_s=m * 0.001, record=[CENTRE])
    k = ds.photoreceptor_v_strf.mean("ommatidium").sel(offset_deg=0.0).values
    h = _impulse_response(len(k) + m)
    tri = 1.0 - np.abs(np.arange(-m + 1, m)) / m                      # P(two steps u apart share a frame)
    expect = np.convolve(h, tri)[m - 1:m - 1 + len(k)]
    assert np.corrcoef(k, expect)[0, 1] > 0.95
    assert np.corrcoef(k, h[:len(k)])[0, 1] < np.corrcoef(k, expect)[0, 1]


def test_t4_and_t5_receptive_fields_tilt_toward_their_preferred_direction(plate):
    ds = plate
    assert ds.t4_response_strf.dims == ("lag_s", "offset_deg", "ommatidium", "preferred_direction")
    lags, off = ds.lag_s.values, ds.offset_deg.values
    for cell, sign in (("t4", 1.0), ("t5", -1.0)):
        mean = ds[f"{cell}_response_strf"].mean("ommatidium")
        tilt = _tilt(mean.values, lags, off)
        # negative tilt: tuned to motion toward +offset (front-to-back on the horizontal axis, downward on the vertical)
        expect = {"front_to_back": -1, "back_to_front": 1, "upward": 1, "downward": -1}
        assert [np.sign(t) for t in tilt] == [expect[d] for d in ds.preferred_direction.values], (cell, tilt)
        # the polarity: ON cells correlate with brightening, OFF cells with darkening
        peak = mean.values.reshape(-1, 4)[np.abs(mean.values.reshape(-1, 4)).argmax(0), range(4)]
        assert np.all(np.sign(peak) == sign)
        # most recorded cells read their own preferred direction from their own STRF
        hits = ds[f"{cell}_response_strf_motion"].values == ds.preferred_direction.values[None, :]
        assert hits.mean() >= 0.85, hits
    # the fast arm's neighbour: front-to-back T4 sees its strongest early response one column front-to-back
    ftb = ds.t4_response_strf.mean("ommatidium").sel(preferred_direction="front_to_back")
    early = ftb.sel(lag_s=slice(0.0, 0.01)).mean("lag_s")
    g = float(ds.offset_deg[1] - ds.offset_deg[0])              # the grid: the lattice's row spacing, Δφ·√3/2
    assert float(early.offset_deg[int(np.argmax(early.values))]) == pytest.approx(4.0, abs=g / 2)
    assert list(ds.strf_axis.values) == ["front_to_back", "front_to_back", "downward", "downward"]
    assert cf_problems(ds) == []


def test_trial_noise_comes_from_its_own_seed():
    rig = Rig(TINY)
    lum, con = white_noise_stimulus(rig, 50, trial_seed(3, 1), contrast=0.4)
    again, _ = white_noise_stimulus(rig, 50, trial_seed(3, 1), contrast=0.4)
    np.testing.assert_array_equal(lum, again)
    assert set(np.round(np.unique(con).astype(float), 6).tolist()) == {-0.4, 0.4}
    one = white_noise(replace(TINY, trials=1, seed=3), duration_s=1.7, record=[CENTRE])
    two = white_noise(replace(TINY, seed=3), duration_s=1.7, record=[CENTRE])
    np.testing.assert_array_equal(two.photoreceptor_v.isel(trial=0).values, one.photoreceptor_v.isel(trial=0).values)
    assert not np.array_equal(two.photoreceptor_v.isel(trial=1).values, two.photoreceptor_v.isel(trial=0).values)
    assert list(two.trial_seed.values) == [trial_seed(3, 0), trial_seed(3, 1)]
    # pixels of 2 Δφ: ommatidia in one pixel see the same noise
    _, px = white_noise_stimulus(rig, 20, 0, pixel_deg=8.0)
    assert len(np.unique(px[0])) == 2 and 1 < len({tuple(c) for c in px.T}) < rig.lattice.n


def test_options_and_refusals_name_the_fix():
    ds = run_protocol("white-noise", {"dphi": 4.0, "duration": 1.7, "trials": 1, "noise": "gaussian",
                                      "contrast": [0.3], "max_lag": 0.05, "strf_extent": 8.0, "record": [CENTRE]})
    p = json.loads(ds.attrs["parameters"])
    assert (p["noise"], p["contrast"], p["max_lag_s"], p["extent_deg"]) == ("gaussian", 0.3, 0.05, 8.0)
    assert ds.sizes["lag_s"] == 51 and ds.attrs["trials"] == 1
    for opts, fix in (({"noise": "gaussian", "contrast": [0.5]}, "--contrast ≤ 0.33 or --noise binary"),
                      ({"frame": 0.0015}, "whole number of the 0.001 s model steps"),
                      ({"duration": 0.5}, "longer --duration or a shorter --max-lag"),
                      ({"record": ["lc.rate"]}, "white-noise maps the receptive fields of photoreceptor.v"),
                      ({"neuron_model": "lif"}, "--neuron-model does not apply to white-noise"),
                      ({"field_size": 20.0}, "--field-size does not apply to white-noise"),
                      ({"contrast": [0.2, 0.4]}, "one --contrast value")):
        with pytest.raises(ValueError, match=fix):
            run_protocol("white-noise", {"dphi": 4.0, "duration": 1.7, "trials": 1, **opts})
