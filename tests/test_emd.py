"""Hassenstein–Reichardt EMDs (and the photoreceptors feeding them) against the analytic theory.

Known answer: for a sine grating of contrast C, mean luminance L₀ and wavelength λ
drifting at temporal frequency TF across neighbours Δφ apart, each ommatidium's
signal is L₀ + L₀·C·M·sin(…) with M = exp(−(πΔρ/λ)²/(4 ln 2)) the Gaussian acceptance
function's transfer, and the opponent correlator's steady-state mean is

    R̄ = (L₀·C·M)² · sin(2πΔφ/λ) · ωτ / (1 + (ωτ)²),    ω = 2π·TF

(derivation: LP_τ has gain 1/√(1+(ωτ)²) and lag θ = atan ωτ, so the mean of
LP(A)·B − A·LP(B) is α²/2·|H|·[cos(θ−Δϕ) − cos(θ+Δϕ)] = α²·|H| sin θ · sin Δϕ). The mean
luminance cancels, M enters squared because R is a product of two signals.
"""
import math

import numpy as np
import pytest
import torch

from lobula.camera import PinholeCamera
from lobula.emd import (EMDArray, EMDConfig, emd_coefficients, emd_run, emd_sine_response,
                        emd_sine_response_discrete, emd_step)
from lobula.lattice import Lattice, LatticeConfig, acceptance_attenuation
from lobula.photoreceptor import (PhotoreceptorConfig, Photoreceptors, photoreceptor_frequency_response,
                                  photoreceptor_run)
from stimuli.gratings import drifting_grating_lattice, drum_coordinates

CAM = PinholeCamera().scaled(0.5)
TAU = 0.035


@pytest.fixture(scope="module")
def drum_eye():
    # azel rows are lines of constant elevation: horizontal neighbours are exactly Δφ
    # apart in drum longitude, so sin(2πΔφ/λ) is literal.
    return Lattice(CAM, LatticeConfig(dphi_deg=4.6, projection="azel"))


def _horizontal_prediction(lat, tf, lam, contrast, lum, fn):
    """Predicted R̄ for axis-0 pairs (trials, pairs) with the per-ommatidium attenuation M(λ cos β)."""
    a = lat.axis_pairs[0][0]
    _, beta = drum_coordinates(lat.directions[a], 0.0)
    M = acceptance_attenuation(lam[:, None] * np.cos(beta)[None], lat.drho_deg)
    amp = lum * contrast[:, None] * M
    return fn(tf[:, None], 2 * np.pi * lat.dphi_deg / lam[:, None], amp)


def _sweep_response(lat, fps, tf, lam, contrast, lum=2.0, seconds=3.0, settle=1.0, config=EMDConfig(TAU)):
    """Simulated steady-state mean R of axis-0 pairs, (trials, pairs); averages whole periods."""
    x = drifting_grating_lattice(lat, int(seconds * fps), temporal_freq_hz=tf, wavelength_deg=lam, contrast=contrast,
                                 mean_luminance=lum, acceptance=True, frame_rate_hz=fps)
    r, _ = emd_run(config, 1.0 / fps, x, lat.pairs_a, lat.pairs_b)
    return r[:, int(settle * fps):, torch.from_numpy(lat.pair_axis == 0)].double().mean(1).numpy()


def _grid():
    tf = np.array([0.5, 1.0, 2.0, 4.0, 8.0])
    lam = np.array([10.0, 20.0, 45.0, 90.0])
    c = np.array([0.2, 0.5, 1.0])
    return [a.ravel() for a in np.meshgrid(tf, lam, c, indexing="ij")]


def test_sweep_matches_exact_discrete_theory_at_camera_rate(drum_eye):
    """At 30 frames/s (τ ≈ one frame) the exact prediction of the discrete scheme holds to 0.1 %."""
    tf, lam, c = _grid()
    fps = CAM.frame_rate_hz
    m = _sweep_response(drum_eye, fps, tf, lam, c)
    cfg = EMDConfig(TAU)
    pred = _horizontal_prediction(drum_eye, tf, lam, c, 2.0,
                                  lambda f, dp, amp: emd_sine_response_discrete(cfg, 1 / fps, f, dp, amp))
    assert np.abs(m / pred - 1).max() < 1e-3


def test_sweep_matches_continuous_formula(drum_eye):
    """C²·sin(2πΔφ/λ)·ωτ/(1+(ωτ)²)·M² within 3 % over TF × λ × C, no fitted constant."""
    tf, lam, c = _grid()
    fps = 200.0
    m = _sweep_response(drum_eye, fps, tf, lam, c)
    pred = _horizontal_prediction(drum_eye, tf, lam, c, 2.0, lambda f, dp, amp: emd_sine_response(TAU, f, dp, amp))
    assert np.abs(m / pred - 1).max() < 0.03
    # and one constant fitted to the whole sweep is 1 within 1 %
    k = float(np.sum(m * pred) / np.sum(pred * pred))
    assert abs(k - 1) < 0.01


def test_response_peaks_at_omega_tau_one(drum_eye):
    fps = 500.0
    tf = np.arange(2.0, 8.01, 0.5)                       # 1/(2πτ) = 4.55 Hz
    ones = np.ones_like(tf)
    m = _sweep_response(drum_eye, fps, tf, 20.0 * ones, 0.5 * ones, seconds=3.0).mean(1)
    assert tf[np.argmax(m)] == 4.5
    # a parabola through the top three points in log TF puts the peak at ωτ = 1 ± 2 %
    i = int(np.argmax(m))
    x = np.log(tf[i - 1:i + 2])
    p = np.polyfit(x, m[i - 1:i + 2], 2)
    f_peak = math.exp(-p[1] / (2 * p[0]))
    assert abs(2 * math.pi * f_peak * TAU - 1) < 0.02


def test_sign_flips_with_direction(drum_eye):
    lat = Lattice(CAM, LatticeConfig(dphi_deg=4.6))     # hexagonal, three axes
    fps = 30.0
    x = drifting_grating_lattice(lat, 90, temporal_freq_hz=2.0, wavelength_deg=25.0, contrast=0.6,
                                 direction_deg=[0.0, 180.0, 90.0, 270.0], acceptance=True, frame_rate_hz=fps)
    r, _ = emd_run(EMDConfig(TAU), 1 / fps, x, lat.pairs_a, lat.pairs_b)
    m = r[:, 30:].mean(1).numpy()                       # (4 directions, pairs)
    ax = lat.pair_axis
    assert (m[0, ax == 0] > 0).all() and (m[1, ax == 0] < 0).all()
    assert np.allclose(m[0], -m[1], rtol=1e-3, atol=1e-6)
    # Downward motion (90°) excites the two oblique axes (60°, 120° point down in the image).
    assert (m[2, ax == 1] > 0).all() and (m[2, ax == 2] > 0).all() and (m[3, ax != 0] < 0).all()
    # Horizontal pairs away from the centre are slightly oblique to the drum's meridians
    # (equidistant projection): small, antisymmetric left/right, zero on average.
    assert np.abs(m[2, ax == 0]).max() < 0.1 * np.abs(m[2, ax == 1]).mean()
    assert abs(m[2, ax == 0].mean()) < 1e-3 * np.abs(m[2, ax == 1]).mean()


def test_streaming_equals_whole_sequence(drum_eye):
    fps = 30.0
    x = drifting_grating_lattice(drum_eye, 40, temporal_freq_hz=[1.0, 3.0], wavelength_deg=20.0, contrast=0.5,
                                 frame_rate_hz=fps, dtype=torch.float64)
    whole, state = emd_run(EMDConfig(TAU), 1 / fps, x, drum_eye.pairs_a, drum_eye.pairs_b)
    assert whole.shape == (2, 40, drum_eye.n_pairs)
    a, _ = emd_run(EMDConfig(TAU), 1 / fps, x[:, :13], drum_eye.pairs_a, drum_eye.pairs_b)
    b, s2 = emd_run(EMDConfig(TAU), 1 / fps, x[:, 13:], drum_eye.pairs_a, drum_eye.pairs_b,
                    emd_run(EMDConfig(TAU), 1 / fps, x[:, :13], drum_eye.pairs_a, drum_eye.pairs_b)[1])
    assert torch.allclose(torch.cat([a, b], 1), whole, atol=1e-12)
    emds = EMDArray.from_lattice(drum_eye, EMDConfig(TAU))
    stepped = torch.stack([emds.step(x[:, t]) for t in range(40)], 1)
    assert torch.allclose(stepped, whole, atol=1e-12)
    st = None
    for t in range(40):
        r, st = emd_step(EMDConfig(TAU), 1 / fps, x[:, t], drum_eye.pairs_a, drum_eye.pairs_b, st)
    assert torch.allclose(r, whole[:, -1], atol=1e-12) and torch.allclose(st.lp, state.lp)
    assert whole[:, 0].abs().max() < 1e-12               # starts at rest on the first frame


def test_substeps_resolve_a_fast_delay():
    """τ = 5 ms at 30 frames/s: the exact per-frame coefficients give the S→∞ limit smoothly."""
    fps = 30.0
    means = [emd_sine_response_discrete(EMDConfig(0.005, substeps=s), 1 / fps, 2.0, 0.5) for s in (64, 256, 1024)]
    assert abs(means[1] / means[2] - 1) < 1e-3 and abs(means[0] / means[2] - 1) < 1e-2
    c = emd_coefficients(EMDConfig(0.005), 1 / fps)
    assert c.substeps == 107 and math.isclose(c.decay, math.exp(-1 / fps / 0.005))


def test_photoreceptor_chain_feeds_the_theory(drum_eye):
    """Low-pass + LMC high-pass: R̄ scales by |H(ω)|² of the photoreceptor; the mean is removed."""
    fps = 100.0
    prc = PhotoreceptorConfig(tau_s=0.010, tau_hp_s=0.25)
    tf = np.array([0.5, 1.0, 2.0, 4.0, 8.0, 16.0])
    x = drifting_grating_lattice(drum_eye, 600, temporal_freq_hz=tf, wavelength_deg=30.0, contrast=0.5,
                                 mean_luminance=3.0, acceptance=True, frame_rate_hz=fps)
    y, _ = photoreceptor_run(prc, 1 / fps, x)
    assert abs(float(y[:, 200:].mean())) < 1e-4
    r, _ = emd_run(EMDConfig(TAU), 1 / fps, y, drum_eye.pairs_a, drum_eye.pairs_b)
    m = r[:, 200:, torch.from_numpy(drum_eye.pair_axis == 0)].double().mean(1).numpy()
    gain = np.abs(photoreceptor_frequency_response(prc, 1 / fps, tf))
    pred = _horizontal_prediction(drum_eye, tf, np.full_like(tf, 30.0), np.full_like(tf, 0.5), 3.0,
                                  lambda f, dp, amp: emd_sine_response_discrete(EMDConfig(TAU), 1 / fps, f, dp, amp))
    assert np.abs(m / (pred * gain[:, None] ** 2) - 1).max() < 1e-3


def test_photoreceptor_step_response_and_streaming():
    dt = 0.01
    prc = PhotoreceptorConfig(tau_s=0.02, tau_hp_s=0.1, tau_adapt_s=0.5, eps=1e-9)
    x = torch.ones(2, 50, 4, dtype=torch.float64)
    x[:, 10:] = 5.0
    lp_only, _ = photoreceptor_run(PhotoreceptorConfig(tau_s=0.02), dt, x)
    k = np.arange(40) + 1
    assert np.allclose(lp_only[0, 10:, 0].numpy(), 5 - 4 * np.exp(-k * dt / 0.02))   # exact exponential
    whole, _ = photoreceptor_run(prc, dt, x)
    pr = Photoreceptors(prc, dt)
    stepped = torch.stack([pr.step(x[:, t]) for t in range(50)], 1)
    assert torch.allclose(stepped, whole, atol=1e-12)
    assert torch.allclose(whole[:, :10], torch.zeros(2, 10, 4, dtype=torch.float64))  # settled at start
    # Weber adaptation: the same step at 10× the luminance gives the same output.
    bright, _ = photoreceptor_run(prc, dt, 10 * x)
    assert torch.allclose(bright, whole, atol=1e-6)
    gain, _ = photoreceptor_run(PhotoreceptorConfig(tau_s=0.0, tau_hp_s=0.1, tau_gain_s=0.2), dt,
                                torch.sin(torch.arange(400.0) * 0.3)[None, :, None] * torch.tensor([0.1, 1.0])[:, None, None])
    assert torch.allclose(gain[0, 300:], gain[1, 300:], atol=0.02)   # contrast-invariant amplitude


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_matches_cpu(drum_eye):
    x = drifting_grating_lattice(drum_eye, 60, temporal_freq_hz=[1.0, 4.0], wavelength_deg=20.0, contrast=0.5)
    cpu, _ = emd_run(EMDConfig(TAU), 1 / 30, x, drum_eye.pairs_a, drum_eye.pairs_b)
    gpu, _ = emd_run(EMDConfig(TAU), 1 / 30, x.cuda(), drum_eye.pairs_a, drum_eye.pairs_b)
    assert gpu.device.type == "cuda" and torch.allclose(gpu.cpu(), cpu, atol=1e-5)


# --------------------------------------------------------------------------- fast paths vs a plain reference

def _reference_emd(config, dt, x, A, B):
    """The correlator written out frame by frame in float64 with plain pair indexing: (..., T, n) → (..., T, P)."""
    c = emd_coefficients(config, dt)
    x = x.double()
    lp, xp = x[..., 0, :].clone(), x[..., 0, :].clone()
    out = []
    for t in range(x.shape[-2]):
        xc = x[..., t, :]
        w = c.n_lp * xp + c.n_lc * xc
        out.append(lp[..., A] * w[..., B] - w[..., A] * lp[..., B]
                   + c.n_pc * (xp[..., A] * xc[..., B] - xc[..., A] * xp[..., B]))
        lp = c.decay * lp + c.beta * xp + c.gamma * xc
        xp = xc
    return torch.stack(out, dim=-2)


def _grid_pairs(rows, cols):
    """Right and down neighbours of a rows×cols grid numbered row by row (runs of pairs), plus the diagonal."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    a = np.concatenate([idx[:, :-1].ravel(), idx[:-1].ravel(), idx[:-1, :-1].ravel()])
    b = np.concatenate([idx[:, 1:].ravel(), idx[1:].ravel(), idx[1:, 1:].ravel()])
    return a, b


@pytest.mark.parametrize("layout", ["runs", "gather", "irregular"])
def test_fast_correlator_equals_plain_reference(layout):
    from lobula.emd import pair_runs
    rng = np.random.default_rng(3)
    a, b = _grid_pairs(9, 20)
    n = 180
    if layout == "irregular":  # random pairs: no runs, the gather path
        a, b = rng.integers(0, n, 300), rng.integers(0, n, 300)
        assert pair_runs(a, b) is None
    else:
        assert pair_runs(a, b) is not None and len(pair_runs(a, b)) == 9 + 1 + 8  # rows; one for "down"; rows − 1
    x = torch.as_tensor(1.0 + 0.3 * rng.standard_normal((2, 3, 23, n)), dtype=torch.float32)
    cfg, dt = EMDConfig(TAU), 1 / 200
    ref = _reference_emd(cfg, dt, x, a, b)
    runs = None if layout == "gather" else "auto"
    # A small max_chunk splits the sequence into time pieces; the state carries across them.
    for max_chunk in (4_000_000, 2 * n * 6 * 4):
        r, state = emd_run(cfg, dt, x, a, b, runs=runs, max_chunk=max_chunk)
        assert r.shape == (2, 3, 23, len(a))
        torch.testing.assert_close(r.double(), ref, rtol=1e-5, atol=1e-6)
    # Streaming: a split run and frame-by-frame steps give the same outputs.
    r1, s1 = emd_run(cfg, dt, x[..., :10, :], a, b, runs=runs)
    buf = torch.empty(len(a), 13, 6)
    r2, s2 = emd_run(cfg, dt, x[..., 10:, :], a, b, state=s1, runs=runs, out=buf)
    assert r2.data_ptr() == buf.data_ptr()
    torch.testing.assert_close(torch.cat([r1, r2], dim=-2).double(), ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(s2.lp, state.lp)
    emds = EMDArray(a, b, cfg, dt)
    steps = torch.stack([emds.step(x[..., t, :]) for t in range(x.shape[-2])], dim=-2)
    torch.testing.assert_close(steps.double(), ref, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="out must be"):
        emd_run(cfg, dt, x, a, b, out=torch.empty(3, 3))
