"""``lobula ephys current-injection``: current steps into the LC units with the eye at rest.

Known answers:
- A noise-free LIF unit fires periodically at 1/(t_ref + τ_m ln((RI + V_rest − V_reset)/(RI − (V_th − V_rest))))
  (:func:`lobula.neurons.lif_fi_curve`), I the step plus the synaptic current at rest, and not at all at or
  below its rheobase.
- With white membrane noise its rate is Siegert's (:func:`lobula.neurons.lif_rate`) within sampling error
  (plus the 1 ms step's small bias), and its ISI CV Brunel's (:func:`lobula.neurons.lif_isi_cv`).
- Rate units settle at the Naka–Rushton rate of their drive; Poisson units fire at it with ISI CV ≈ 1.
- A graded HS cell's membrane, τ_m dV/dt = −V − g_e(V − E_exc) − g_i(V − E_inh) + I/g_leak, settles at
  V∞ = (E_exc g_e + E_inh g_i + I/g_leak)/(1 + g_e + g_i) — I/g_leak at rest — with time constant
  τ_m/(1 + g_e + g_i).
Tiny rig (Δφ = 4°, 12 expansion units recorded): under a second per run.
"""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from experiments.cli import main as cli_main
from experiments.ephys.command import run_protocol
from experiments.ephys.injection import current_injection, interspike_intervals, synaptic_current
from experiments.ephys.rig import EphysConfig, Rig
from experiments.store import cf_problems
from lobula.lattice import LatticeConfig
from lobula.neurons import LIFConfig, lif_fi_curve, lif_isi_cv, lif_rate, lif_step, naka_rushton
from lobula.population import LCNeurons
from lobula.tangential_cells import TangentialConfig, hs_vs

TINY = EphysConfig(lattice=LatticeConfig(dphi_deg=4.0), trials=1)
NA = 1e-9


def test_noise_free_lif_follows_its_f_i_curve_and_is_silent_below_rheobase():
    amps = np.array([0.0, 0.3, 0.5, 0.55, 0.75, 1.0, 2.0, 3.0]) * NA
    ds = current_injection(TINY.with_neurons("lif"), amplitudes=amps, membrane_noise="none")
    lif = LIFConfig()                                      # the LC units' LIF, less its noise
    rest = float(ds.input_at_rest)
    assert rest == pytest.approx(1.0 * NA)                 # the eye at rest: the 1 nA bias alone
    assert float(ds.rheobase_theory) == pytest.approx(lif.rheobase - rest)      # 0.5 nA above the bias
    theory = lif_fi_curve(amps + rest, lif)
    np.testing.assert_allclose(ds.fi_rate_theory.values, theory)
    fires = amps > lif.rheobase - rest + 1e-15
    assert np.all(ds.fi_rate.values[~fires] == 0) and np.all(ds.lc_spikes.values[~fires] == 0)
    np.testing.assert_allclose(ds.fi_rate.values[fires], np.broadcast_to(theory[fires, None, None],
                                                                         ds.fi_rate.values[fires].shape), rtol=0.02)
    assert float(ds.rheobase) == pytest.approx(0.55 * NA)  # the first step above the noise-free rheobase
    assert ds.sizes["trial"] == 1 and "deterministic" in ds.attrs["trials_note"]
    # the membrane: at rest V∞ = V_rest + R·I (below threshold), reset after each spike
    v = ds.lc_v.sel(amplitude=0.3 * NA).isel(trial=0)
    assert float(v.sel(time=slice(0.9, 1.0)).mean()) == pytest.approx(lif.V_rest + lif.R * (rest + 0.3 * NA), abs=1e-4)
    assert cf_problems(ds) == []


def test_white_noise_lif_matches_siegert_rate_and_isi_cv():
    lif = LIFConfig(noise="white", noise_std=0.3 * NA)
    amps = np.array([0.0, 0.5, 1.0, 2.0]) * NA
    ds = current_injection(replace(TINY.with_neurons("lif"), trials=3), amplitudes=amps, membrane_noise="white",
                           noise_std_A=0.3 * NA, duration_s=2.0)
    rest = float(ds.input_at_rest)
    rate, cv = lif_rate(amps + rest, lif), lif_isi_cv(amps + rest, lif)
    np.testing.assert_allclose(ds.fi_rate_theory.values, rate)
    sim, sem = ds.fi_rate_mean.values, ds.fi_rate_sem.values
    assert np.all(np.abs(sim - rate) <= 3 * sem + 0.02 * rate), (sim, rate, sem)
    assert np.all(sim[1:] > sim[:-1])                                  # and rises with the current
    np.testing.assert_allclose(ds.isi_cv.values, cv, atol=0.1)
    assert ds.attrs["trials"] == 3 and ds.sizes["trial"] == 3


def test_trials_have_their_own_streams_independent_of_their_number():
    amps = np.array([0.75]) * NA
    one = current_injection(TINY.with_neurons("lif"), amplitudes=amps)          # the LC units' own OU noise
    three = current_injection(replace(TINY.with_neurons("lif"), trials=3), amplitudes=amps)
    np.testing.assert_array_equal(three.lc_spikes.isel(trial=0).values, one.lc_spikes.isel(trial=0).values)
    assert not np.array_equal(three.lc_spikes.isel(trial=1).values, three.lc_spikes.isel(trial=0).values)
    # OU noise has no closed form: the noise-free curve is drawn instead, and the CV theory is absent
    assert "no closed form" in three.attrs["theory"] and np.isnan(three.isi_cv_theory.values).all()


def test_rate_and_poisson_units_follow_the_naka_rushton_rate_of_their_drive():
    amps = np.array([0.0, 0.5, 1.0, 2.0])
    r = TINY.circuit.population.neurons.rate
    nr = naka_rushton(torch.as_tensor(amps, dtype=torch.float64), r.r_max, r.c50, r.n).numpy()
    rate = current_injection(TINY, amplitudes=amps)
    np.testing.assert_allclose(rate.fi_rate_mean.values, nr, rtol=1e-3, atol=1e-6)
    assert "isi_cv" not in rate and float(rate.rheobase) == 0.5
    pois = current_injection(replace(TINY.with_neurons("poisson"), trials=2), amplitudes=amps, duration_s=2.0)
    assert np.all(np.abs(pois.fi_rate_mean.values - nr) <= 4 * pois.fi_rate_sem.values + 0.03 * nr)
    np.testing.assert_allclose(pois.isi_cv.values[1:], 1.0, atol=0.1)


def test_synaptic_current_is_the_lc_units_own_and_intervals_count_repeated_spikes():
    nc = replace(TINY.circuit.population.neurons, model="lif", lif=LIFConfig())
    neurons = LCNeurons(nc)
    drive = torch.tensor([[[-2.0, -0.3, 0.0, 0.4, 1.0, 7.0]]], dtype=torch.float64)
    state = neurons.init_state((1, 1, 6), "cpu", torch.float64)
    ref = neurons.step(state, drive, 0.001)
    own = lif_step(state, synaptic_current(nc, drive), 0.001, nc.lif)
    torch.testing.assert_close(own.v, ref.v, rtol=0, atol=0)
    assert [list(x) for x in interspike_intervals(np.array([[0, 1, 0, 2, 1]]), 0.5)] == [[1.0, 0.0, 0.5]]


@pytest.mark.parametrize("g_e,g_i", [(0.0, 0.0), (1.5, 0.0), (0.7, 2.0)])
def test_hs_cell_settles_at_its_membranes_steady_state_for_an_injected_current(g_e, g_i):
    """Constant T4 in the front-to-back (back-to-front) layer opens g_e (g_i) = g·T4 over HS's whole field."""
    rig_lat = Rig(TINY).lattice
    cfg = TangentialConfig()
    T, dt, i_mv = 400, 0.001, 6.0
    t4 = torch.zeros(T, rig_lat.n, 4, dtype=torch.float64)
    t4[..., 0], t4[..., 1] = g_e / cfg.g_exc, g_i / cfg.g_inh
    current = torch.zeros(T, cfg.n_hs, dtype=torch.float64)
    current[100:] = i_mv                                     # a step of I/g_leak = 6 mV at 0.1 s
    hs = hs_vs(t4, torch.zeros_like(t4), rig_lat, cfg, dt, hs_current_mv=current).hs
    g = 1.0 + g_e + g_i
    v0 = (cfg.e_exc_mv * g_e + cfg.e_inh_mv * g_i) / g
    v_inf = (cfg.e_exc_mv * g_e + cfg.e_inh_mv * g_i + i_mv) / g
    if g == 1.0:
        assert v_inf == i_mv                                 # at rest: V∞ = I/g_leak
    t = (np.arange(T) - 99) * dt                             # frame k holds V at the end of its step
    expect = np.where(t > 0, v_inf + (v0 - v_inf) * np.exp(-t * g / cfg.tau_m_s), v0)
    np.testing.assert_allclose(hs.numpy(), np.broadcast_to(expect[:, None], hs.shape), atol=1e-9)
    # no current: the cells' own membrane, bit for bit
    plain = hs_vs(t4, torch.zeros_like(t4), rig_lat, cfg, dt).hs
    torch.testing.assert_close(hs_vs(t4, torch.zeros_like(t4), rig_lat, cfg, dt, hs_current_mv=None).hs, plain,
                               rtol=0, atol=0)


def test_command_line_options_units_refusals_and_figure(tmp_path, capsys):
    ds = run_protocol("current-injection", {"neuron_model": "lif", "amplitudes": [0.0, 1.0],
                                            "membrane_noise": "none", "duration": 0.5, "trials": 1})
    np.testing.assert_allclose(ds.amplitude.values, [0.0, 1e-9])             # nA on the command line
    assert json.loads(ds.attrs["parameters"])["membrane_noise"] == "none" and ds.amplitude.attrs["units"] == "A"
    for opts, fix in (({"membrane_noise": "white"}, "use --neuron-model lif"),
                      ({"tau": 0.05}, "--tau does not apply to current-injection"),
                      ({"record": ["photoreceptor.v"]}, "the eye is at rest"),
                      ({"neuron_model": "lif", "record": ["lc.v"]}, "add it to --record"),
                      ({"neuron_model": "lif", "membrane_noise": "white", "noise_std": 0.0}, "--noise-std > 0"),
                      ({"amplitudes": [1.0, 0.5]}, "increasing order")):
        with pytest.raises(ValueError, match=fix):
            run_protocol("current-injection", {"duration": 0.3, **opts})
    out = tmp_path / "ci.nc"
    assert cli_main(["ephys", "current-injection", "--neuron-model", "lif", "--membrane-noise", "none",
                     "--amplitudes", "0", "0.75", "2", "--duration", "0.4", "--trials", "1", "--out", str(out),
                     "--plot", str(tmp_path / "ci.png")]) == 0
    text = capsys.readouterr().out
    assert "rheobase: 0.75 nA measured" in text and "0.5 nA noise-free theory" in text
    assert (tmp_path / "ci.png").stat().st_size > 10_000 and (tmp_path / "ci.pdf").exists()
