"""Saccadic suppression in the eye's velocity circuit: the haltere's rate gates the circuit's learning and the
readout's visual update during body saccades (lobula.eye_circuit, experiments.eye_velocity)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from lobula.compound_eye import CompoundEye, CompoundEyeConfig
from lobula.eye_circuit import EyeCircuit, EyeCircuitConfig, EyeFieldConfig

RATE = 500.0


def _saccade_gyro(n: int, start: int, length: int, peak_deg_s: float, wobble_deg_s: float = 40.0) -> np.ndarray:
    """(n, 3) rad/s: a yaw wobble of ``wobble_deg_s`` at 3 Hz and one raised-cosine saccade about y."""
    t = np.arange(n) / RATE
    g = np.zeros((n, 3))
    g[:, 1] = math.radians(wobble_deg_s) * np.sin(2 * math.pi * 3.0 * t)
    x = np.arange(length) / length
    g[start:start + length, 1] += math.radians(peak_deg_s) * 0.5 * (1 - np.cos(2 * math.pi * x))
    return g


def test_the_hold_is_three_of_the_circuits_time_constants_and_old_configurations_have_no_gate():
    cfg = EyeCircuitConfig()
    # photoreceptor 10 ms + EMD 35 ms + the per-pair decoding's 35 ms, to e^-3
    assert cfg.saccade_hold_s() == pytest.approx(3 * (0.010 + 0.035 + 0.035))
    assert EyeCircuitConfig(normaliser="delayed").saccade_hold_s() == pytest.approx(3 * (0.010 + 0.035))
    assert cfg.saccade_gate_deg_s == 300.0
    assert EyeCircuitConfig.from_dict(cfg.to_dict()).saccade_gate_deg_s == 300.0
    stored = cfg.to_dict()
    stored.pop("saccade_gate_deg_s")
    assert EyeCircuitConfig.from_dict(stored).saccade_gate_deg_s is None
    with pytest.raises(ValueError, match="saccade_gate_deg_s"):
        EyeCircuitConfig(saccade_gate_deg_s=0.0)


def test_the_gate_flags_the_saccade_and_its_hold_across_chunks():
    eye = CompoundEye(CompoundEyeConfig(dphi_deg=12.0, rings=1))
    n, start, length = 1000, 300, 40                        # an 80 ms saccade from 0.6 s
    gyro = _saccade_gyro(n, start, length, peak_deg_s=800.0)
    fast = np.linalg.norm(gyro, axis=1) > math.radians(300.0)
    first, last = np.flatnonzero(fast)[[0, -1]]
    hold = int(round(EyeCircuitConfig().saccade_hold_s() * RATE))
    expect = np.zeros(n, bool)
    expect[first:last + hold + 1] = True
    whole = EyeCircuit(eye, RATE).saccade_samples(gyro)
    np.testing.assert_array_equal(whole, expect)
    circ = EyeCircuit(eye, RATE)
    parts = []
    for i in range(0, n, 170):                              # chunks that split the saccade and the hold
        parts.append(circ.saccade_samples(gyro[i:i + 170]))
        circ._n_steps += len(gyro[i:i + 170])               # as process() advances the clock
    np.testing.assert_array_equal(np.concatenate(parts), expect)
    # the wobble alone (40 deg/s) never reaches the gate; without a gate nothing is flagged
    assert not EyeCircuit(eye, RATE).saccade_samples(_saccade_gyro(n, 0, 0, 0.0)).any()
    assert not EyeCircuit(eye, RATE, EyeCircuitConfig(saccade_gate_deg_s=None)).saccade_samples(gyro).any()


def _run(eye, cfg, lum, gyro, chunk=250):
    circ = EyeCircuit(eye, RATE, cfg)
    outs = [circ.process(lum[i:i + chunk], gyro[i:i + chunk]) for i in range(0, len(lum), chunk)] + [circ.finish()]
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def test_gated_steps_teach_the_haltere_gain_nothing_and_flight_below_the_gate_is_unchanged():
    eye = CompoundEye(CompoundEyeConfig(dphi_deg=12.0, rings=1))
    rng = np.random.default_rng(0)
    n = 1500
    # a pattern drifting across the lattice: the LC fields see motion, the haltere a turn
    lum = 0.5 + 0.2 * rng.standard_normal((n, eye.n)).cumsum(0) / np.sqrt(np.arange(1, n + 1))[:, None]
    lum = lum.astype(np.float32)
    fields = EyeFieldConfig(size_deg=60.0)
    calm = _saccade_gyro(n, 0, 0, 0.0, wobble_deg_s=120.0)
    on, off = (_run(eye, EyeCircuitConfig(fields=fields, saccade_gate_deg_s=g), lum, calm) for g in (300.0, None))
    for k in ("rho", "grad", "r2_eff", "haltere_gain"):        # below the gate: bit-identical
        np.testing.assert_array_equal(on[k], off[k])
    assert not on["saccade"].any()
    gyro = _saccade_gyro(n, 900, 40, peak_deg_s=900.0, wobble_deg_s=120.0)
    on = _run(eye, EyeCircuitConfig(fields=fields), lum, gyro)
    sac = on["saccade"]
    steps = np.flatnonzero(sac)
    # the flagged steps: the saccade's blocks and the hold after (0.24 s = 12 steps at 50 Hz), contiguous
    assert len(steps) == steps[-1] - steps[0] + 1 and 13 <= len(steps) <= 18, steps
    g = on["haltere_gain"]
    # α is learned once its running means have settled (50 steps) and holds through the gated steps: the gain
    # at each gated step and the first after is the one before the saccade
    assert np.isfinite(g).all() and np.ptp(g[steps[0] - 5:steps[0]], axis=0).max() > 0   # it was learning
    np.testing.assert_array_equal(g[steps[0]:steps[-1] + 2], np.broadcast_to(g[steps[0]], (len(steps) + 1,
                                                                                            g.shape[1])))
    ungated = _run(eye, EyeCircuitConfig(fields=fields, saccade_gate_deg_s=None), lum, gyro)["haltere_gain"]
    assert np.abs(ungated[steps[-1] + 1] - g[steps[0]]).max() > 1e-6   # without the gate the saccade teaches it


def test_the_gyro_bias_leaves_the_saccades_out():
    from experiments.eye_velocity import causal_gyro

    ti = np.arange(0, 4.0, 1 / 250)
    bias = np.array([0.002, -0.004, 0.003])
    g = np.tile(bias, (len(ti), 1))
    sac = (ti >= 0.3) & (ti < 0.38)                      # a 60 deg saccade in 80 ms, then straight flight
    g[sac, 1] += math.radians(60.0) / 0.08
    imu = SimpleNamespace(time_s=ti, gyro=g)
    times = np.array([1.0, 3.9])
    plain = causal_gyro(imu, times)
    gated = causal_gyro(imu, times, 300.0, 0.24)
    # the running mean takes the saccade for bias: 60 deg over the first second is ~1 rad/s
    assert abs(plain[0, 1]) > 0.9
    np.testing.assert_allclose(gated, 0.0, atol=1e-12)     # the samples' bias removed exactly, the turn none of it


def _wall_flight(n=400, dt=0.02, fields=12, seed=0):
    """Exact LC rates of a frontal wall approached at a varying speed, with 2 % noise: (t, r, r2, a, v)."""
    t = np.arange(n) * dt
    v = 0.5 + 0.2 * np.sin(2 * math.pi * 0.25 * t)
    a = 0.2 * 2 * math.pi * 0.25 * np.cos(2 * math.pi * 0.25 * t)
    D = 10.0 - np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    rng = np.random.default_rng(seed)
    r = (v / D)[:, None] * (1 + 0.02 * rng.standard_normal((n, fields)))
    return t, r, r ** 2, a, v


def test_the_suppressed_readout_predicts_through_a_saccade_and_is_the_readout_without_one():
    from experiments.eye_velocity import EyeVelocityConfig, suppressed_readout
    from lobula.readout import readout

    t, r, r2, a, v = _wall_flight()
    rcfg = EyeVelocityConfig().readout
    plain = readout(t, r, r2, a, rcfg)
    same = suppressed_readout(t, r, r2, a, rcfg, np.zeros(len(t), bool))
    np.testing.assert_array_equal(plain.v_hat, same.v_hat)
    np.testing.assert_array_equal(plain.v_std, same.v_std)
    # a saccade at 5 s: the fields turn onto other surfaces, the rates jump threefold for 0.3 s
    sac = (t >= 5.0) & (t < 5.3)
    bad_r = np.where(sac[:, None], 3 * r, r)
    corrupt = readout(t, bad_r, bad_r ** 2, a, rcfg)
    sup = suppressed_readout(t, np.where(sac[:, None], np.nan, bad_r), np.where(sac[:, None], np.nan, bad_r ** 2),
                             a, rcfg, sac)
    after = (t >= 5.0) & (t < 7.0)
    err_sup = np.sqrt(np.nanmean((sup.v_hat - v)[after] ** 2))
    err_bad = np.sqrt(np.nanmean((corrupt.v_hat - v)[after] ** 2))
    assert err_sup < 0.02 and err_bad > 3 * err_sup, (err_sup, err_bad)
    assert np.isfinite(sup.v_hat[after]).all()                 # answered throughout
    # predict-only while the measurements' centre lies in the saccade: σ grows there
    lag = int(round(sup.info["measurement_delay_s"] / 0.02))
    gap = np.flatnonzero(np.roll(sac, lag))
    assert np.all(np.diff(sup.v_std[gap[1:]]) > 0)
