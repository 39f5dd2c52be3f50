"""Neuron models against known answers (lobula.neurons).

Short runs only: the whole file should take a few seconds on two CPU cores.
"""
import math

import numpy as np
import pytest
import torch

from lobula.neurons import (
    LIFConfig, LIFNeuron, PoissonConfig, PoissonNeuron, RateNeuron, RateNeuronConfig,
    lif_current_for_rate, lif_fi_curve, lif_isi_cv, lif_rate, make_generator, naka_rushton, poisson_spikes,
)


def _first_spike_times(rec, dt):
    """Exact spike times (s) per neuron of trial 0 from spikes + spike_offset."""
    sp, off = rec["spikes"][:, 0].double(), rec["spike_offset"][:, 0].double()
    times = []
    for j in range(sp.shape[1]):
        k = torch.nonzero(sp[:, j]).flatten()
        times.append((k.double() * dt + off[k, j]).numpy())
    return times


# --------------------------------------------------------------------------- LIF

def test_lif_fi_curve_matches_analytic_within_2_percent():
    # dt = 1 ms is coarse (ISIs of 7-40 ms): the test relies on the exact in-step
    # threshold crossing, not on a small dt. Rate = (n-1)/(last - first spike).
    cfg = LIFConfig()
    dt, n_t = 1e-3, 1500
    currents = torch.linspace(1.55e-9, 4.0e-9, 12, dtype=torch.float64)
    rec = LIFNeuron(cfg).run(currents.expand(1, n_t, -1).float(), dt,
                             record=("v", "spikes", "spike_offset"))
    for I, ts in zip(currents.tolist(), _first_spike_times(rec, dt)):
        f_sim = (len(ts) - 1) / (ts[-1] - ts[0])
        f_ana = lif_fi_curve(I, cfg)
        assert f_ana > 15
        assert abs(f_sim - f_ana) / f_ana < 0.02, (I, f_sim, f_ana)
        # it is in fact exact to float32 precision
        assert abs(f_sim - f_ana) / f_ana < 1e-4, (I, f_sim, f_ana)
    assert rec["v"].max() < cfg.V_threshold          # reset, never left above threshold


def test_lif_fi_curve_formula_and_silence_below_rheobase():
    cfg = LIFConfig()
    I = 2.5e-9
    RI, gap = cfg.R * I, cfg.V_threshold - cfg.V_rest
    assert lif_fi_curve(I, cfg) == pytest.approx(1 / (cfg.t_ref + cfg.tau_m * math.log(RI / (RI - gap))))
    assert lif_fi_curve(0.99 * cfg.rheobase, cfg) == 0.0
    assert lif_fi_curve(np.array([0.0, I])).shape == (2,)
    assert torch.is_tensor(lif_fi_curve(torch.tensor([0.0, I], dtype=torch.float64)))
    # Below rheobase the membrane relaxes to V_rest + R I exactly and never spikes.
    rec = LIFNeuron(cfg).run(torch.full((2, 300, 3), 0.9 * cfg.rheobase, dtype=torch.float64), 1e-3)
    assert rec["spikes"].sum() == 0
    t = 1e-3 * torch.arange(1, 301, dtype=torch.float64)
    v_exact = cfg.V_rest + 0.9 * (cfg.V_threshold - cfg.V_rest) * (1 - torch.exp(-t / cfg.tau_m))
    torch.testing.assert_close(rec["v"][:, 1, 2], v_exact, rtol=0, atol=1e-14)


def test_lif_several_spikes_per_step_counted():
    # t_ref = 0 and dt = 20 ms ≫ ISI: each step holds several spikes; the count over a
    # long run must still match the analytic rate.
    cfg = LIFConfig(t_ref=0.0)
    I = 4e-9
    n_t, dt = 100, 0.02
    rec = LIFNeuron(cfg).run(torch.full((1, n_t, 1), I, dtype=torch.float64), dt)
    assert rec["spikes"].max() >= 2
    assert rec["spikes"].sum().item() / (n_t * dt) == pytest.approx(lif_fi_curve(I, cfg), abs=1 / (n_t * dt))


def test_lif_weak_white_noise_recovers_deterministic_rate():
    # The white-noise path times its crossings on the exponential path to the noisy V,
    # so as σ → 0 it must give the analytic rate even with a coarse dt and t_ref = 0.
    for cfg, dt in ((LIFConfig(noise="white", noise_std=1e-12), 1e-3),
                    (LIFConfig(t_ref=0.0, noise="white", noise_std=1e-12), 0.02)):
        n_t = int(round(1.0 / dt))
        rec = LIFNeuron(cfg).run(torch.full((4, n_t, 2), 3e-9, dtype=torch.float64), dt, seed=0)
        rate = rec["spikes"].sum(0) / (n_t * dt)
        assert torch.all((rate - lif_fi_curve(3e-9, cfg)).abs() <= 1.0)


def _noisy(sd_mv):
    """A default LIF with white noise of free-membrane SD sd_mv (mV)."""
    return LIFConfig(noise="white", noise_std=sd_mv * 1e-3 * math.sqrt(2) / LIFConfig().R)


def test_siegert_rate_and_cv_limits():
    # Vanishing noise: Siegert's rate is the deterministic f-I curve and the ISI CV goes to 0
    # linearly in σ; far below threshold the neuron cannot fire (CV 1 by convention).
    I = np.array([1.6e-9, 2e-9, 3e-9])
    np.testing.assert_allclose(lif_rate(I, _noisy(1e-3)), lif_fi_curve(I), rtol=1e-4)
    cv_small, cv_smaller = lif_isi_cv(I, _noisy(1e-2)), lif_isi_cv(I, _noisy(1e-3))
    np.testing.assert_allclose(cv_small / cv_smaller, 10.0, rtol=0.02)
    assert np.all(cv_small < 0.01)
    # Far below threshold firing is a rare escape: a Poisson process (CV 1), at a vanishing rate.
    assert lif_rate(0.0, _noisy(0.5)) < 1e-20 and lif_isi_cv(0.0, _noisy(0.5)) == pytest.approx(1.0, abs=0.01)
    assert lif_isi_cv(0.0, _noisy(2.0)) == pytest.approx(1.0, abs=0.02)
    # Noise raises the rate most near rheobase and leaves strong drive almost unchanged.
    gain = lif_rate(I, _noisy(3.0)) / lif_fi_curve(I)
    assert gain[0] > 1.3 and gain[-1] < 1.02
    with pytest.raises(ValueError, match="white-noise"):
        lif_rate(I, LIFConfig(noise="ou", noise_std=1e-10))


def test_noisy_lif_simulation_matches_siegert_rate_and_cv_at_1ms():
    # 1 ms steps against τ_m = 10 ms: without the Brownian-bridge crossings the count ran
    # 20-30 % low in the noise-driven regime (1.3 nA, ν ≈ 7 Hz); with them within ~5 %.
    cfg = _noisy(1.0)
    I = np.array([1.3e-9, 1.6e-9, 3e-9])
    nu, cv = lif_rate(I, cfg), lif_isi_cv(I, cfg)
    dt, n_t, n = 1e-3, 3000, 300
    rec = LIFNeuron(cfg).run(torch.tensor(I).repeat(n, n_t, 1), dt, seed=4, record=("spikes", "spike_offset"))
    sp = rec["spikes"][500:]
    rate = sp.sum(0).mean(0).numpy() / ((n_t - 500) * dt)
    np.testing.assert_allclose(rate, nu, rtol=0.06)
    # ISI CV on the suprathreshold drives (spike times exact to the step at 3 nA: at most one per step).
    for j in (1, 2):
        isi = np.concatenate([np.diff(k * dt + rec["spike_offset"][500:, i, j][k].numpy())
                              for i in range(n) for k in [np.flatnonzero(sp[:, i, j].numpy())]])
        assert np.std(isi) / np.mean(isi) == pytest.approx(cv[j], rel=0.15)


def test_lif_current_for_rate_inverts_siegert():
    cfg = _noisy(1.0)
    rates = np.array([20.0, 60.0, 150.0, 400.0])
    np.testing.assert_allclose(lif_rate(lif_current_for_rate(rates, cfg), cfg), rates, rtol=2e-3)
    assert lif_current_for_rate(0.0, LIFConfig()) == pytest.approx(LIFConfig().rheobase)
    with pytest.raises(ValueError, match="rates must lie"):
        lif_current_for_rate(1.0 / cfg.t_ref, cfg)


def test_lif_refractory_clamp():
    cfg = LIFConfig(t_ref=0.005)
    dt = 1e-4
    rec = LIFNeuron(cfg).run(torch.full((1, 400, 1), 5e-9, dtype=torch.float64), dt,
                             record=("v", "spikes", "refractory"))
    v, sp = rec["v"][:, 0, 0], rec["spikes"][:, 0, 0]
    k = int(torch.nonzero(sp)[0])
    # V sits at V_reset for the whole refractory period after the spike
    n_ref = int(cfg.t_ref / dt) - 1
    assert torch.all(v[k:k + n_ref] == cfg.V_reset)
    assert v[k + n_ref + 2] > cfg.V_reset


def test_lif_noise_stationary_statistics():
    # Known stationary moments of the exact discretisations (V_th far away: free membrane).
    dt, n_t = 1e-3, 300
    cfg_w = LIFConfig(V_threshold=10.0, noise="white", noise_std=0.2e-9)
    rec = LIFNeuron(cfg_w).run(torch.zeros(20, n_t, 100, dtype=torch.float64), dt, seed=3,
                               record=("v",))
    sd_v = rec["v"][100:].std().item()                       # after 10 τ_m
    assert sd_v == pytest.approx(cfg_w.R * cfg_w.noise_std / math.sqrt(2), rel=0.03)
    cfg_ou = LIFConfig(V_threshold=10.0, noise="ou", noise_std=0.3e-9, noise_tau=0.005)
    rec = LIFNeuron(cfg_ou).run(torch.zeros(20, n_t, 100, dtype=torch.float64), dt, seed=4,
                                record=("noise",))
    assert rec["noise"].std().item() == pytest.approx(cfg_ou.noise_std, rel=0.03)
    lag = 5                                                   # autocorrelation e^{-lag·dt/τ}
    x = rec["noise"]
    ac = (x[lag:] * x[:-lag]).mean() / (x * x).mean()
    assert ac.item() == pytest.approx(math.exp(-lag * dt / cfg_ou.noise_tau), abs=0.03)


def test_lif_bad_input_errors():
    with pytest.raises(ValueError, match="V_reset < V_threshold"):
        LIFConfig(V_reset=-0.04)
    with pytest.raises(ValueError, match="generator"):
        LIFNeuron(LIFConfig(noise="white", noise_std=1e-10)).step(None, torch.zeros(2, 3), 1e-3)
    with pytest.raises(ValueError, match="trials, time, neurons"):
        LIFNeuron().run(torch.zeros(5, 3), 1e-3)
    with pytest.raises(ValueError, match="dt"):
        LIFNeuron().run(torch.zeros(1, 5, 3), 0.0)
    st = LIFNeuron().init_state(2, 3)
    with pytest.raises(ValueError, match="shape"):
        LIFNeuron().step(st, torch.zeros(2, 4), 1e-3)


# --------------------------------------------------------------------------- rate neuron

@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-13), (torch.float32, 2e-6)])
def test_rate_step_response_is_exact_exponential(dtype, tol):
    cfg = RateNeuronConfig(tau_m=0.02)
    dt, n_t, u = 1e-3, 300, 1.7
    rec = RateNeuron(cfg).run(torch.full((3, n_t, 4), u, dtype=dtype), dt)
    t = dt * torch.arange(1, n_t + 1, dtype=torch.float64)
    expected = u * (1 - torch.exp(-t / cfg.tau_m))
    err = (rec["x"].double() - expected[:, None, None]).abs().max().item()
    assert err < tol * u
    # and the output is Naka-Rushton of the integrated drive throughout
    torch.testing.assert_close(rec["r"], naka_rushton(rec["x"], cfg.r_max, cfg.c50, cfg.n))


def test_rate_steady_state_is_naka_rushton():
    cfg = RateNeuronConfig(tau_m=0.01, r_max=80.0, c50=0.5, n=2.5)
    u = torch.tensor([-1.0, 0.0, 0.1, 0.5, 1.0, 3.0, 1e6], dtype=torch.float64)
    rec = RateNeuron(cfg).run(u.expand(2, 500, -1), 1e-3)    # 50 τ_m: e^-50 ≈ 2e-22
    up = u.clamp_min(0)
    expected = cfg.r_max * up ** cfg.n / (up ** cfg.n + cfg.c50 ** cfg.n)
    torch.testing.assert_close(rec["r"][-1, 0], expected, rtol=1e-12, atol=1e-12)
    assert rec["r"][-1, 0, 3].item() == pytest.approx(cfg.r_max / 2)  # half-max at c50
    # no overflow or NaN at extreme drives, in float32 too
    r32 = naka_rushton(torch.tensor([0.0, 1e-30, 1e30, float("inf")]), 100.0, 1.0, 2.0)
    assert torch.isfinite(r32).all() and r32[0] == 0 and r32[-1] == 100.0


def test_streaming_steps_equal_run():
    g_in = torch.Generator().manual_seed(0)
    drive = torch.rand(2, 50, 7, generator=g_in, dtype=torch.float64)
    neuron = RateNeuron()
    rec = neuron.run(drive, 1e-3)
    state = None
    for k in range(50):
        state = neuron.step(state, drive[:, k], 1e-3)
    assert torch.equal(state.r, rec["r"][-1])
    # LIF with noise: stream with the run's generator gives identical spikes
    cfg = LIFConfig(noise="ou", noise_std=0.5e-9)
    cur = 1.6e-9 + 0 * drive
    rec = LIFNeuron(cfg).run(cur, 1e-3, seed=7, record=("v", "spikes"))
    g = make_generator(7)
    lif = LIFNeuron(cfg)
    state = lif.init_state(2, 7, dtype=torch.float64, generator=g)
    for k in range(50):
        state = lif.step(state, cur[:, k], 1e-3, generator=g)
    assert torch.equal(state.v, rec["v"][-1])


# --------------------------------------------------------------------------- Poisson

@pytest.mark.parametrize("rate_hz", [5.0, 40.0])
def test_poisson_counts_match_rate(rate_hz):
    # 1 s windows (1000 steps of 1 ms), 400 trials × 5 neurons = 2000 windows.
    dt, n_t, trials, neurons = 1e-3, 1000, 400, 5
    rec = PoissonNeuron().run(torch.full((trials, n_t, neurons), rate_hz), dt, seed=11)
    counts = rec["spikes"].sum(0).double().flatten()          # spikes per window
    m, lam = counts.numel(), rate_hz * n_t * dt
    z = (counts.sum() - m * lam) / math.sqrt(m * lam)         # total ~ Poisson(m λ)
    assert abs(z) < 3.5, z
    # dispersion test: Σ (c - λ)²/λ ~ χ²(m); normal approximation, 3.5 σ band
    d = ((counts - lam) ** 2 / lam).sum().item()
    assert abs(d - m) < 3.5 * math.sqrt(2 * m), d
    fano = counts.var().item() / counts.mean().item()
    assert fano == pytest.approx(1.0, abs=0.1)


def test_poisson_bernoulli_mode_binary_and_rate():
    dt, n_t = 1e-3, 1000
    rate = 50.0
    rec = PoissonNeuron(PoissonConfig(mode="bernoulli")).run(torch.full((200, n_t, 5), rate), dt, seed=5)
    sp = rec["spikes"]
    assert set(sp.unique().tolist()) <= {0.0, 1.0}
    p = -math.expm1(-rate * dt)                                # P(at least one event in a step)
    m = sp.numel()
    z = (sp.sum().item() - m * p) / math.sqrt(m * p * (1 - p))
    assert abs(z) < 3.5, z


def test_poisson_negative_rate_is_silent_and_needs_generator():
    assert poisson_spikes(torch.full((3, 4), -10.0), 1e-3, make_generator(0)).sum() == 0
    with pytest.raises(ValueError, match="generator"):
        poisson_spikes(torch.ones(3), 1e-3, None)


# --------------------------------------------------------------------------- seeds, devices

def test_same_seed_same_arrays_different_seed_different():
    rate = torch.full((4, 200, 6), 30.0)
    a = PoissonNeuron().run(rate, 1e-3, seed=1)["spikes"]
    b = PoissonNeuron().run(rate, 1e-3, seed=1)["spikes"]
    c = PoissonNeuron().run(rate, 1e-3, seed=2)["spikes"]
    assert torch.equal(a, b) and not torch.equal(a, c)
    for noise in ("white", "ou"):
        lif = LIFNeuron(LIFConfig(noise=noise, noise_std=0.5e-9))
        cur = torch.full((4, 200, 6), 1.5e-9)
        a, b, c = (lif.run(cur, 1e-3, seed=s, record=("v", "spikes")) for s in (1, 1, 2))
        assert torch.equal(a["v"], b["v"]) and torch.equal(a["spikes"], b["spikes"])
        assert not torch.equal(a["v"], c["v"])
        assert a["spikes"].sum() > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_matches_cpu():
    dev = "cuda"
    cfg = LIFConfig()
    cur = torch.linspace(1.6e-9, 4e-9, 8, dtype=torch.float64).expand(2, 500, -1).contiguous()
    cpu = LIFNeuron(cfg).run(cur, 1e-3, record=("v", "spikes"))
    gpu = LIFNeuron(cfg).run(cur.to(dev), 1e-3, record=("v", "spikes"))
    assert gpu["v"].device.type == "cuda"
    torch.testing.assert_close(gpu["v"].cpu(), cpu["v"], rtol=0, atol=1e-12)
    assert torch.equal(gpu["spikes"].cpu(), cpu["spikes"])
    drive = torch.rand(2, 100, 8, dtype=torch.float64)
    torch.testing.assert_close(RateNeuron().run(drive.to(dev), 1e-3)["r"].cpu(),
                               RateNeuron().run(drive, 1e-3)["r"])
    rate = torch.full((400, 1000, 5), 40.0, device=dev)
    a = PoissonNeuron().run(rate, 1e-3, seed=3)["spikes"]
    assert a.device.type == "cuda" and torch.equal(a, PoissonNeuron().run(rate, 1e-3, seed=3)["spikes"])
    counts = a.sum(0).double().flatten()
    assert abs(counts.mean().item() - 40.0) < 3.5 * math.sqrt(40.0 / counts.numel())
    noisy = LIFNeuron(LIFConfig(noise="ou", noise_std=0.5e-9))
    x = noisy.run(cur.to(dev), 1e-3, seed=1)["v"]
    assert torch.equal(x, noisy.run(cur.to(dev), 1e-3, seed=1)["v"])
