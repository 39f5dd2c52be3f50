"""Lobula-plate physiology: contrast gain, flicker, motion adaptation, noise and HS temporal-frequency tuning.

Known answers:
- The lamina's contrast gain makes each T4/T5 half-correlator answer a grating of lamina contrast C as
  C²/(C² + c50²): the Naka–Rushton fit to the T4 layer returns c50 in stimulus contrast, c50 over the
  optics' and the linear filters' attenuation (``c50_expected``), and the configured c50 within 10 %.
- The HS membrane V = (E_e g_e + E_i g_i)/(1 + g_e + g_i) with g = γ·R(c) is Naka–Rushton with c50/√(1 + γ):
  the HS potential's fit returns that; with the membrane in its linear range (γ ≪ 1) it returns c50.
- Photoreceptor and lamina gain and phase to flicker equal photoreceptor_frequency_response (exact discrete).
- Uniform flicker drives opposite T4/T5 layers alike: the HS opponent drive is 0.
- After motion stops, 1 − G of the adaptation gain decays as exp(−Δ/τa): the test conductance recovers with τa.
- Shot noise: variance L/(rate·dt) at the photoreceptor input, times (1 − a)/(1 + a) after its low-pass;
  channel noise: SD σ at rest.
- The HS cells' TF optimum lies at the optimum of the discrete opponent prediction (hs_tf_prediction).
Tiny rigs (Δφ = 4°, ~110 ommatidia; Δφ = 6° for adaptation's long runs): a few seconds per run.
"""
import math
from dataclasses import replace

import numpy as np
import pytest

from experiments.cli import main as cli_main
from experiments.ephys.adaptation import adaptation
from experiments.ephys.command import run_protocol
from experiments.ephys.contrast import contrast, hs_tf_prediction
from experiments.ephys.flicker import flicker
from experiments.ephys.plate import plate_chain, shot_noise
from experiments.ephys.edges import edges
from experiments.ephys.protocols import tf_tuning
from experiments.ephys.rig import EphysConfig, Rig, parse_monitor
from experiments.store import cf_problems
from lobula._optional import torch
from lobula.lattice import LatticeConfig
from lobula.motion_pathways import OnOffConfig, lamina_on_off
from lobula.photoreceptor import PhotoreceptorConfig, lowpass_scan, photoreceptor_run
from lobula.tangential_cells import TangentialConfig, hs_vs

TINY = EphysConfig(lattice=LatticeConfig(dphi_deg=4.0), trials=1)
SMALL = EphysConfig(lattice=LatticeConfig(dphi_deg=6.0), trials=1)
#: an HS membrane in its linear range: the saturated drive opens g_e + g_i ≈ 0.06
LINEAR = TangentialConfig(g_exc=0.1, g_inh=0.1)


def _c50(cfg, c50, **kw):
    return replace(cfg, on_off=replace(cfg.on_off, contrast_c50=c50), **kw)


@pytest.mark.parametrize("c50", [0.1, 0.3])
def test_contrast_fit_returns_the_configured_c50(c50):
    ds = contrast(_c50(TINY, c50))
    expected = float(ds.c50_expected)
    assert expected == pytest.approx(c50 / (ds.attrs["optics_attenuation"] * ds.attrs["lamina_gain"]))
    for cell in ("t4", "t5"):
        assert float(ds[f"{cell}_c50"]) == pytest.approx(expected, rel=0.03), cell
        assert float(ds[f"{cell}_c50"]) == pytest.approx(c50, rel=0.10), cell
        assert float(ds[f"{cell}_n"]) == pytest.approx(2.0, rel=0.03)
        assert 0 < float(ds[f"{cell}_c50_se"]) < 0.01 * c50 and np.isfinite(float(ds[f"{cell}_rmax_se"]))
    # the HS conductance follows the stage; the saturating membrane moves its potential's half-maximum to
    # c50/sqrt(1 + gamma), far below c50 with the default gains
    assert float(ds.hs_g_c50) == pytest.approx(expected, rel=0.03)
    assert float(ds.hs_v_c50) == pytest.approx(float(ds.hs_v_c50_predicted), rel=0.02)
    assert float(ds.hs_v_c50) < 0.3 * c50
    assert not cf_problems(ds)
    # with the membrane in its linear range, the HS potential's own fit returns the configured c50
    lin = contrast(_c50(TINY, c50, tangential=LINEAR))
    assert float(lin.hs_v_c50) == pytest.approx(c50, rel=0.10)
    assert float(lin.hs_v_c50) == pytest.approx(float(lin.hs_v_c50_predicted), rel=0.02)


def test_contrast_gain_off_leaves_the_lamina_bit_identical_and_on_normalises():
    x = 1.0 + 0.4 * torch.sin(torch.linspace(0, 20, 500))[:, None].expand(500, 3).double()
    dt = 0.001
    ch = lamina_on_off(x, dt, OnOffConfig())
    hp = x - lowpass_scan(x, math.exp(-dt / 0.25))
    assert torch.equal(ch.on, torch.clamp(hp, min=0.0)) and torch.equal(ch.off, torch.clamp(-hp, min=0.0))
    # on: the Weber contrast over sqrt(2 LP(k^2) + c50^2)
    cfg = OnOffConfig(contrast_c50=0.2)
    mean = lowpass_scan(x, math.exp(-dt / 0.25))
    k = (x - mean) / mean
    want = k / torch.sqrt(lowpass_scan(2 * k * k, math.exp(-dt / cfg.contrast_tau_s)) + 0.04)
    got = lamina_on_off(x, dt, cfg)
    assert torch.allclose(got.on - got.off, want, atol=1e-12)
    with pytest.raises(ValueError, match="contrast_c50 must be a positive"):
        OnOffConfig(contrast_c50=0.0)


def test_contrast_gain_refused_where_the_luminance_level_is_lost():
    with pytest.raises(ValueError, match="lobula ephys contrast"):
        edges(_c50(TINY, 0.2), duration_s=0.05)


def test_plate_chain_is_the_rigs_lobula_plate():
    rig = Rig(TINY)
    lum = 1.0 + 0.5 * torch.sin(torch.arange(400)[:, None] * 0.03 + torch.arange(rig.lattice.n)[None, :] * 0.4)
    mons = [parse_monitor(s, rig) for s in ("t4.response", "hs.v")]
    mine = plate_chain(rig, lambda b0, b1: lum[None], 1, 400, mons, baseline=1.0)
    ref = rig.run(lum[None].float(), 400, mons, baseline=1.0)
    assert torch.allclose(mine["t4.response"][:, 0].float(), ref["t4.response"], rtol=1e-3, atol=1e-5)
    assert torch.allclose(mine["hs.v"][:, 0].float(), ref["hs.v"], rtol=1e-3, atol=1e-4)


def test_flicker_frequency_responses_and_the_null_opponent_drive():
    ds = flicker(TINY)
    for name in ("photoreceptor", "lamina"):
        np.testing.assert_allclose(ds[f"{name}_gain"], ds[f"{name}_gain_predicted"], rtol=2e-3)
        np.testing.assert_allclose(ds[f"{name}_phase_deg"], ds[f"{name}_phase_deg_predicted"], atol=0.2)
    # the default photoreceptor (10 ms low-pass, 0.25 s high-pass) is band-pass: its gain falls at both ends
    g = ds.photoreceptor_gain.values
    assert g[0] < g[2] > g[-1]
    t4 = ds.t4_mean_response.sel(stimulus="flicker")
    np.testing.assert_allclose(t4.sel(preferred_direction="front_to_back"),
                               t4.sel(preferred_direction="back_to_front"), rtol=1e-5)
    opp = ds.hs_opponent_drive.mean(("trial", "hs_cell"))
    assert np.all(np.abs(opp.sel(stimulus="flicker")) < 1e-3 * opp.sel(stimulus="motion"))
    assert np.all(ds.hs_flicker_motion_ratio.values < 0.6)
    assert not cf_problems(ds)


@pytest.mark.parametrize("tau", [1.0, 2.0])
def test_adaptation_recovers_with_the_configured_time_constant(tau):
    ds = adaptation(SMALL, adapt_tau_s=tau, adapter_s=2.0, gaps_s=(0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0))
    assert float(ds.hs_g_recovery_tau_s) == pytest.approx(tau, rel=0.02)
    assert float(ds.hs_g_test_ratio.isel(condition=0)) < 0.7               # the test's drop after the adapter
    assert float(ds.hs_v_test_ratio.isel(condition=0)) < 0.95
    r = ds.hs_g_test_ratio.values[:-1]
    assert np.all(np.diff(r[2:]) > 0)                                        # monotonic recovery after the transient
    assert not cf_problems(ds)


def test_adaptation_off_by_default_leaves_hs_unchanged():
    rig = Rig(TINY)
    t4 = torch.rand(2, 300, rig.lattice.n, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.02
    t5 = torch.rand(2, 300, rig.lattice.n, 4, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 0.02
    a = hs_vs(t4, t5, rig.lattice, TangentialConfig(), 0.001)
    b = hs_vs(t4, t5, rig.lattice, TangentialConfig(channel_noise_mv=0.0), 0.001,
              noise=(torch.randn(2, 300, 3, dtype=torch.float64), torch.randn(2, 300, 6, dtype=torch.float64)))
    assert torch.equal(a.hs, b.hs) and torch.equal(a.vs, b.vs)
    c = hs_vs(t4, t5, rig.lattice, TangentialConfig(adapt_tau_s=1.0), 0.001)
    assert not torch.equal(a.hs, c.hs)


@pytest.mark.parametrize("lum", [1.0, 4.0])
def test_shot_noise_variance_is_luminance_over_rate_dt(lum):
    rate, dt = 2.0e4, 0.001
    gen = torch.Generator().manual_seed(3)
    x = shot_noise(torch.full((4000, 64), lum, dtype=torch.float64), rate, dt, gen)
    var = lum / (rate * dt)
    assert float(x.mean()) == pytest.approx(lum, rel=2e-3)
    assert float(x.var()) == pytest.approx(var, rel=0.03)
    # after the photoreceptor's first-order low-pass: var (1 - a)/(1 + a)
    a = math.exp(-dt / 0.01)
    y, _ = photoreceptor_run(PhotoreceptorConfig(tau_s=0.01), dt, x.T[:, :, None])
    assert float(y[:, 200:].var()) == pytest.approx(var * (1 - a) / (1 + a), rel=0.05)


def test_noise_trials_are_seeded_per_trial_and_zero_noise_is_deterministic():
    kw = dict(contrasts=(0.05, 0.1, 0.3, 1.0), duration_s=0.3, settle_s=0.1, photon_rate_hz=1e4)
    two = contrast(replace(TINY, trials=2), **kw)
    three = contrast(replace(TINY, trials=3), **kw)
    np.testing.assert_array_equal(two.hs_v.values, three.hs_v.isel(trial=slice(0, 2)).values)
    assert not np.array_equal(three.hs_v.isel(trial=0).values, three.hs_v.isel(trial=1).values)
    plain = contrast(TINY, contrasts=kw["contrasts"], duration_s=0.3, settle_s=0.1)
    zero = contrast(replace(TINY, trials=3), contrasts=kw["contrasts"], duration_s=0.3, settle_s=0.1,
                    channel_noise_mv=0.0)
    assert zero.sizes["trial"] == 1
    np.testing.assert_array_equal(plain.hs_v.values, zero.hs_v.values)
    np.testing.assert_array_equal(plain.t4_response.values, zero.t4_response.values)


def test_channel_noise_sd_at_rest():
    sigma = 2.0
    cfg = replace(TINY, trials=6, tangential=replace(TINY.tangential, channel_noise_mv=sigma))
    rig = Rig(cfg)
    res = plate_chain(rig, lambda b0, b1: torch.ones(b1 - b0, 1500, rig.lattice.n), 1, 1500, trials=6, seed=0)
    v = res["hs.v"][0]                                                      # (K, T, cells), the eye at rest
    assert float(v.mean()) == pytest.approx(0.0, abs=0.1)
    assert float(v.std()) == pytest.approx(sigma, rel=0.05)


def test_hs_tf_optimum_matches_the_discrete_prediction():
    tf = np.arange(2.5, 6.01, 0.25)
    ds = tf_tuning(TINY, temporal_frequencies_hz=tf, contrasts=(0.1,), stimulus="grating", wavelength_deg=20.0,
                   record=["hs.v"], duration_s=1.5, settle_s=0.75)
    peak = float(tf[np.argmax(ds.hs_v_tuning.sel(contrast=0.1).mean("hs_cell").values)])
    fine = np.arange(0.5, 15.0, 0.01)
    pred = fine[np.argmax(hs_tf_prediction(TINY, 0.001, fine, 2 * math.pi * 4.0 / 20.0))]
    assert abs(peak - pred) <= 0.2 * pred
    assert 3.0 < pred < 1.0 / (2 * math.pi * 0.035)          # below 1/(2πτ): the photoreceptor and lamina filters


def test_cli_runs_and_refuses(tmp_path):
    out = tmp_path / "c.nc"
    assert cli_main(["ephys", "contrast", "--dphi", "4", "--c50", "0.2", "--duration", "0.4", "--settle", "0.2",
                     "--contrast", "0.05", "0.1", "0.3", "1", "--out", str(out), "--plot",
                     str(tmp_path / "c.png")]) == 0
    assert out.exists() and (tmp_path / "c.png").exists() and (tmp_path / "c.pdf").exists()
    import xarray as xr
    with xr.open_dataset(out) as ds:
        assert ds.attrs["configured_c50"] == 0.2 and not cf_problems(ds)
    with pytest.raises(ValueError, match="add --photon-rate or --channel-noise"):
        run_protocol("contrast", {"trials": 3})
    with pytest.raises(ValueError, match="does not apply to flicker"):
        run_protocol("flicker", {"field_size": 5.0})
    with pytest.raises(ValueError, match="adaptation"):
        run_protocol("contrast", {"gaps": [0.0, 1.0]})
