"""Lobula-plate physiology with noise: the ``contrast`` and ``flicker`` protocols and their shared chain.

Chain (:func:`plate_chain`): the stimulus' luminance, with optional photon shot noise
(:func:`shot_noise`), through the photoreceptor's low-pass stage (the circuit's
:class:`~lobula.photoreceptor.PhotoreceptorConfig` without its high-pass: the lamina applies its
own, as in :func:`experiments.ephys.edges.lamina_input`), the lamina's ON/OFF split
(:func:`lobula.motion_pathways.lamina_on_off`, with the contrast gain of ``OnOffConfig.contrast_c50``
when set), T4/T5 (:func:`~lobula.motion_pathways.t4_t5`) and the HS/VS membranes
(:func:`~lobula.tangential_cells.hs_vs`, with channel noise and motion adaptation when set). The
photoreceptor signal keeps its luminance units here (the rig's circuit output has its adapted level
removed), which the contrast gain needs. Trial k's noise comes from one generator seeded
:func:`experiments.ephys.rig.trial_seed` (seed, k): photon noise first, then channel noise, condition
chunk by condition chunk (chunks fixed by the stimulus, not by the number of trials), so trial k is
the same whatever the number of trials.

Protocols:

- :func:`contrast`: a drum grating drifting front-to-back at the correlators' optimum 1/(2πτ) over a
  contrast series; Naka–Rushton fits (:func:`naka_rushton_fit`) to the T4 and T5 front-to-back layers,
  the HS conductance and the HS potential. With ``OnOffConfig.contrast_c50`` set, the T4/T5 fit returns
  c₅₀ (in stimulus contrast: c₅₀ over the optics' and filters' attenuation, ``c50_expected``), and the
  HS potential's half-maximum lies lower, at c₅₀/√(1 + γ) (γ the conductance the saturated drive opens;
  ``hs_v_c50_predicted``), because the shunting membrane saturates on top.
- :func:`flicker`: full-field sinusoidal flicker and, for comparison, drum-grating motion at the same
  temporal frequencies and contrast: the T4/T5 layers' responses (flicker drives preferred and null
  layers alike), the HS/VS potentials, and the photoreceptor's and lamina's measured frequency
  responses beside :func:`lobula.photoreceptor.photoreceptor_frequency_response`.

:func:`hs_tf_prediction` is the model's own discrete prediction of the HS cells' temporal-frequency
tuning. Shapes: luminance (B, T, n); the chain's outputs carry a trial dim after the conditions,
(B, K, T, …).
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.motion_pathways import DIRECTIONS, lamina_on_off, t4_t5
from lobula.photoreceptor import (PhotoreceptorConfig, photoreceptor_frequency_response, photoreceptor_init,
                                  photoreceptor_run)
from lobula.tangential_cells import conductances, shunting_potential, tangential_fields
from stimuli.lattice_stimuli import GratingSource

from .edges import _centre_columns, _image_angles, cell_coords, select
from .protocols import _specs
from .rig import (LAYER_RECORDS, PATHWAY_RECORDS, EphysConfig, Rig, cf_describe, monitors_for, protocol,
                  record_dataset, rig_attrs, trial_seed)

__all__ = ["shot_noise", "plate_chain", "naka_rushton", "naka_rushton_fit", "sine_fit", "hs_tf_prediction",
           "contrast", "flicker", "plot_contrast", "plot_flicker", "contrast_summary", "flicker_summary",
           "CONTRASTS", "FLICKER_HZ", "plate_config", "noise_attrs"]

#: contrast's default Michelson contrasts: 13 log-spaced from 0.01 to 1
CONTRASTS = np.geomspace(0.01, 1.0, 13)
#: flicker's default temporal frequencies (Hz)
FLICKER_HZ = (1.0, 2.0, 4.0, 8.0, 16.0)
#: luminance × time × ommatidia × trials per chunk of conditions (float32: about 100 MB per trial with the
#: T4/T5 gathers); fixed by the stimulus alone so trial k's noise does not depend on the number of trials
_CHUNK_ELEMENTS = 3_000_000


# =========================================================================== noise and the chain

def shot_noise(luminance, photon_rate_hz: float, dt: float, generator=None):
    """Photon shot noise on a luminance (..., T, n): Poisson photon counts per ommatidium and frame.

    Parameters
    ----------
    luminance : Tensor, (..., T, n)
        Relative luminance (≥ 0); 1 delivers ``photon_rate_hz`` photons per second to each ommatidium.
    photon_rate_hz : float
        Photons per ommatidium per second at luminance 1.
    dt : float
        Frame interval (s).
    generator : torch.Generator, optional
        The random stream (None: torch's global one).

    Returns
    -------
    Tensor, (..., T, n)
        ``N/(rate·dt)`` with N ~ Poisson(rate·dt·L): mean L, variance L/(rate·dt), in luminance units.
    """
    if not (photon_rate_hz > 0 and math.isfinite(photon_rate_hz)):
        raise ValueError(f"the photon rate must be a positive number of photons per ommatidium per second, "
                         f"got {photon_rate_hz}")
    per_frame = float(photon_rate_hz) * float(dt)
    lam = torch.clamp(luminance, min=0.0) * per_frame
    return torch.poisson(lam, generator=generator) / per_frame


def plate_config(rig: Rig) -> PhotoreceptorConfig:
    """The photoreceptor stages that feed the lamina: the circuit's, without its high-pass (the lamina's own
    high-pass replaces it). Refused with contrast gain control on (tau_gain_s), as in
    :func:`experiments.ephys.edges.lamina_input`."""
    pc = rig.config.circuit.photoreceptor
    if pc.tau_gain_s is not None:
        raise ValueError("the lobula plate needs the photoreceptor signal before its high-pass, and the photoreceptor's "
                         "RMS gain control (tau_gain_s) acts after it; record T4/T5/HS/VS with tau_gain_s None (use "
                         "OnOffConfig.contrast_c50 for the lamina's contrast gain)")
    return replace(pc, tau_hp_s=None)


def _chunks(n_cond: int, n_steps: int, n: int) -> list[tuple[int, int]]:
    size = max(1, _CHUNK_ELEMENTS // max(1, n_steps * n))
    return [(b, min(n_cond, b + size)) for b in range(0, n_cond, size)]


def plate_chain(rig: Rig, stimulus, n_cond: int, n_steps: int, monitors=(), *, trials: int = 1,
                photon_rate_hz: float | None = None, seed: int = 0, baseline: float = 1.0) -> dict:
    """The lobula plate's responses to a stimulus on ``trials`` trials (module docstring).

    Parameters
    ----------
    rig : Rig
        The rig (lattice, photoreceptor, ``on_off`` and ``tangential`` configurations, step dt).
    stimulus : callable
        ``stimulus(b0, b1)`` → luminance (b1 − b0, T, n) of conditions b0…b1−1.
    n_cond, n_steps : int
        Number of conditions B and of steps T.
    monitors : sequence of Monitor
        Lobula-plate monitors whose subsets to keep (:data:`experiments.ephys.rig.PATHWAY_RECORDS`).
    trials : int
        K; trial k's noise from :func:`trial_seed` (seed, k).
    photon_rate_hz : float, optional
        Photon shot noise (:func:`shot_noise`); None: none.
    seed : int
        The rig's seed.
    baseline : float
        The luminance the photoreceptor is adapted to before the first frame.

    Returns
    -------
    dict
        Each monitor's variable (B, K, T, X[, L]); ``hs.v``, ``vs.v`` (B, K, T, c) mV; ``t4_layers``,
        ``t5_layers`` (B, K, T, 4): each layer's mean over every ommatidium; ``g`` the HS/VS
        :class:`~lobula.tangential_cells.Conductances` (B, K, T, c); ``lamina`` (B, K, T): the ON minus
        OFF channel, mean over ommatidia (the lamina's signed output, in the photoreceptor signal's units,
        or normalised contrast with contrast gain on).
    """
    cfg, dt, lat = rig.config, rig.dt, rig.lattice
    pc = plate_config(rig)
    tc = cfg.tangential
    noisy = photon_rate_hz is not None or tc.channel_noise_mv > 0
    gens = []
    for k in range(trials if noisy else 0):
        g = torch.Generator(device=cfg.device)
        g.manual_seed(trial_seed(cfg.seed if seed is None else seed, k))
        gens.append(g)
    parts: dict = {}
    for b0, b1 in _chunks(n_cond, n_steps, lat.n):
        lum = stimulus(b0, b1).to(cfg.device)                                       # (b, T, n)
        if photon_rate_hz is not None:
            x = torch.stack([shot_noise(lum, photon_rate_hz, dt, g) for g in gens], dim=1)
        else:
            x = lum.unsqueeze(1).expand(-1, trials, -1, -1)                         # (b, K, T, n)
        noise = None
        if tc.channel_noise_mv > 0:
            b = b1 - b0
            draws = [(torch.randn((b, n_steps, tc.n_hs), generator=g, device=cfg.device),
                      torch.randn((b, n_steps, tc.n_vs), generator=g, device=cfg.device)) for g in gens]
            noise = tuple(torch.stack([d[i] for d in draws], dim=1) for i in range(2))
        state = photoreceptor_init(pc, torch.full(x.shape[:-2] + x.shape[-1:], float(baseline), dtype=x.dtype,
                                                  device=x.device))
        s, _ = photoreceptor_run(pc, dt, x, state)
        del x
        ch = lamina_on_off(s, dt, cfg.on_off)
        del s
        lamina = (ch.on - ch.off).mean(-1)
        layers = t4_t5(ch.on, ch.off, lat, cfg.on_off, dt)
        del ch
        from lobula.tangential_cells import hs_vs

        cells = hs_vs(layers.t4, layers.t5, lat, tc, dt, noise=noise)
        out = {"hs.v": cells.hs, "vs.v": cells.vs, "t4_layers": layers.t4.mean(-2), "t5_layers": layers.t5.mean(-2),
               "g": conductances(layers.t4, layers.t5, lat, tc, dt), "lamina": lamina}
        full = {"t4.response": layers.t4, "t5.response": layers.t5, "hs.v": cells.hs, "vs.v": cells.vs}
        for m in monitors:
            out[m.variable] = select(full[m.variable], m)
        del layers, full
        for k, v in out.items():
            parts.setdefault(k, []).append(v)
    res = {k: (type(v[0])(*(torch.cat(p) for p in zip(*v))) if k == "g" else torch.cat(v)) for k, v in parts.items()}
    return res


def _flat(x):
    """(B, K, T, …) → (B·K, T, …): conditions and trials as record_dataset's row-major conditions."""
    return x.reshape((-1,) + tuple(x.shape[2:]))


def _window(n_steps: int, dt: float, settle_s: float, freq_hz: float) -> slice:
    """Steps of the largest whole number of periods of ``freq_hz`` after ``settle_s`` (the whole rest if less
    than one period fits)."""
    start = int(math.ceil(settle_s / dt - 1e-9))
    span = n_steps - start
    periods = math.floor(span * dt * freq_hz + 1e-9) if freq_hz > 0 else 0
    length = int(round(periods / (freq_hz * dt))) if periods >= 1 else span
    return slice(start, start + min(length, span))


def _time_mean(x, win: slice) -> np.ndarray:
    """Mean over the time axis 2 of a (B, K, T, …) tensor within ``win``, as float64 numpy."""
    return x[:, :, win].double().mean(2).cpu().numpy()


# =========================================================================== fits and predictions

def naka_rushton(c, rmax, c50, n):
    """Naka–Rushton function ``R = Rmax·cⁿ/(cⁿ + c50ⁿ)`` (c, c50: contrast; R in Rmax's units)."""
    c = np.asarray(c, dtype=float)
    return rmax * c ** n / (c ** n + c50 ** n)


def naka_rushton_fit(contrasts, response) -> dict:
    """Least-squares Naka–Rushton fit (scipy.optimize.curve_fit) of ``response`` (C,) at ``contrasts`` (C,).

    Returns {"rmax", "c50", "n"} and their standard errors {"rmax_se", "c50_se", "n_se"} (square roots of
    the covariance's diagonal, scaled by the residuals); NaN when the fit fails or the response does not
    rise (a flat or negative response has no half-maximum).
    """
    from scipy.optimize import curve_fit

    c = np.asarray(contrasts, dtype=float)
    y = np.asarray(response, dtype=float)
    nan = {k: math.nan for k in ("rmax", "c50", "n", "rmax_se", "c50_se", "n_se")}
    ok = np.isfinite(y)
    if ok.sum() < 4 or not np.nanmax(y) > 0:
        return nan
    c, y = c[ok], y[ok]
    top = float(y.max())
    half = float(c[np.argmax(y >= 0.5 * top)])
    try:
        p, cov = curve_fit(naka_rushton, c, y, p0=(top, half, 2.0),
                           bounds=([0.0, 1e-4, 0.2], [np.inf, 100.0, 20.0]), maxfev=20000)
    except (RuntimeError, ValueError):
        return nan
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None)) if np.all(np.isfinite(cov)) else np.full(3, np.nan)
    return {"rmax": p[0], "c50": p[1], "n": p[2], "rmax_se": se[0], "c50_se": se[1], "n_se": se[2]}


def sine_fit(x: np.ndarray, t: np.ndarray, freq_hz: float) -> np.ndarray:
    """Complex amplitude Y of ``x ≈ a + Re(Y·e^{iωt})`` by least squares along the last axis (x (..., T), t (T,)
    in s): exact for a sinusoid plus a constant whatever the window."""
    w = 2.0 * math.pi * freq_hz * np.asarray(t, dtype=float)
    A = np.stack([np.ones_like(w), np.cos(w), np.sin(w)], axis=1)                     # (T, 3)
    coef, *_ = np.linalg.lstsq(A, np.moveaxis(np.asarray(x, dtype=float), -1, 0).reshape(len(w), -1), rcond=None)
    coef = coef.reshape((3,) + np.asarray(x).shape[:-1])
    return coef[1] - 1j * coef[2]


#: Fourier cosine coefficients b_k of the half-wave rectified cosine max(cos θ, 0) = Σ b_k cos kθ, k = 0…8
_RECTIFIED = np.array([1.0 / math.pi, 0.5] + [0.0 if k % 2 else 2.0 * (-1) ** (k // 2 + 1) / (math.pi * (k * k - 1))
                                              for k in range(2, 9)])


def hs_tf_prediction(config: EphysConfig, dt: float, temporal_freq_hz, phase_diff_rad: float) -> np.ndarray:
    """The model's own discrete prediction of the HS cells' opponent drive against temporal frequency.

    A drum grating of temporal frequency f (ω = 2πf) reaches two neighbouring columns A and B (B one step
    front-to-back, spatial phase Δϕ = ``phase_diff_rad`` behind A) through the same linear stages, sampled
    every dt: the photoreceptor's low-pass and the lamina's high-pass, whose exact discrete transfer is
    ``H(f) = photoreceptor_frequency_response(PhotoreceptorConfig(τ_pr, τ_hp), dt, f)``. So the lamina's
    signal in A is ``α·cos θ`` with α ∝ |H(f)| and θ = ωt + φ, and in B ``α·cos(θ − Δϕ)``. Rectified
    (ON: max(·, 0); OFF: max(−·, 0)), each channel is ``α·Σ_k b_k cos k(θ − …)`` with b_k the Fourier
    coefficients of the half-wave rectified cosine (b₀ = 1/π, b₁ = 1/2, b₂ = 2/(3π), b₄ = −2/(15π), odd
    k > 1 zero; OFF has the same |b_k|). The T4 preferred half-correlator is ``LP_τ(c_A)·c_B`` with the
    delay's discrete transfer ``L(f) = (1 − a)/(1 − a·e^{−iωdt})``, a = exp(−dt/τ); averaged over whole
    periods, harmonic k contributes ``α²·b_k²/2·Re(L(kf)·e^{ikΔϕ})`` (cross-harmonic products average to
    0), and the null half-correlator the same with −Δϕ. Preferred minus null, T4 and T5 alike:

        D(f) ∝ |H(f)|² · Σ_k b_k² · (−Im L(kf)) · sin(kΔϕ),

    the k = 1 term being :func:`lobula.emd.emd_sine_response_discrete`'s form for this correlator (a
    first-order delay sampled at the frame instants). HS cells are excited by the preferred layers and
    inhibited by the null ones, so their tuning peaks where D does; the shunting membrane is monotonic
    in the opponent drive, so it moves the peak little.

    Parameters
    ----------
    config : EphysConfig
        Photoreceptor τ (``circuit.photoreceptor.tau_s``), the lamina's high-pass (``on_off.tau_hp_on_s``)
        and T4's delay (``on_off.tau_delay_t4_s``).
    dt : float
        Step (s).
    temporal_freq_hz : array_like
        f (Hz).
    phase_diff_rad : float
        Δϕ = 2π·(column spacing)/λ (rad).

    Returns
    -------
    numpy.ndarray
        D(f) (f's shape), normalised to its maximum over the given frequencies.
    """
    f = np.asarray(temporal_freq_hz, dtype=float)
    pr = PhotoreceptorConfig(tau_s=config.circuit.photoreceptor.tau_s, tau_hp_s=config.on_off.tau_hp_on_s)
    h2 = np.abs(photoreceptor_frequency_response(pr, dt, f)) ** 2
    a = math.exp(-dt / config.on_off.tau_delay_t4_s)
    k = np.arange(len(_RECTIFIED))[:, None]
    lp = (1 - a) / (1 - a * np.exp(-2j * math.pi * k * f.ravel()[None, :] * dt))
    d = (_RECTIFIED[:, None] ** 2 * -np.imag(lp) * np.sin(k * phase_diff_rad)).sum(0).reshape(f.shape) * h2
    return d / np.max(d)


def _phase_step(rig: Rig, wavelength_deg: float) -> float:
    """Δϕ (rad) between a column and its front-to-back neighbour for a drum grating of wavelength λ (degree)."""
    return 2.0 * math.pi * float(rig.lattice.dphi_deg) / float(wavelength_deg)


def _optics(src: GratingSource, mean_luminance: float, contrast: float) -> float:
    """Mean over ommatidia of the optics' attenuation of the grating of ``src``'s last condition (its
    modulation at the ommatidia over the stimulus' contrast ``contrast`` times ``mean_luminance``)."""
    amp = src._basis[-1].double().norm(dim=0).cpu().numpy()                        # (n,)
    return float(np.mean(amp) / (mean_luminance * contrast))


# =========================================================================== shared protocol plumbing

#: units and long names of the coordinates made here
_DESCRIBE = {
    "stimulus": (None, "stimulus: flicker (full-field sinusoidal luminance) or motion (drum grating, "
                       "front-to-back)"),
    "condition": ("1", "condition index"),
    "gap_s": ("s", "blank interval between the adapter's end and the test's onset (NaN: no adapter)"),
    "adapter": (None, "adapter: motion (preferred-direction grating) or none (control)"),
}


def _plate_monitors(rig: Rig, record) -> list:
    """Monitors of the lobula plate (default: T4/T5 of the central column and its neighbours, HS, VS)."""
    cols = ",".join(map(str, _centre_columns(rig)))
    mons = monitors_for(rig, record, [f"t4.response[{cols}]", f"t5.response[{cols}]", "hs.v", "vs.v"])
    bad = [m.variable for m in mons if m.variable not in PATHWAY_RECORDS]
    if bad:
        raise ValueError(f"this protocol records the lobula plate only ({', '.join(PATHWAY_RECORDS)}), not "
                         f"{', '.join(bad)}; record those with tf-tuning, rf-map or looming")
    return mons


def _noisy_config(config: EphysConfig, channel_noise_mv) -> EphysConfig:
    cfg = config or EphysConfig()
    if channel_noise_mv is not None:
        cfg = replace(cfg, tangential=replace(cfg.tangential, channel_noise_mv=float(channel_noise_mv)))
    return cfg


def _trials(cfg: EphysConfig, photon_rate_hz) -> int:
    """Trials stored: the rig's when there is noise, else one (every trial would be identical)."""
    noisy = photon_rate_hz is not None or cfg.tangential.channel_noise_mv > 0
    return cfg.trials if noisy else 1


def noise_attrs(ds: xr.Dataset, cfg: EphysConfig, trials: int, photon_rate_hz) -> None:
    """The trials and noise settings, into ``ds.attrs`` (over the LC rig's own trial attributes)."""
    ds.attrs.update(trials=trials, trials_requested=cfg.trials,
                    trials_note="" if trials > 1 or cfg.trials == 1 else (
                        "no photon or channel noise: every trial would be identical, one is stored"),
                    photon_rate_hz=-1.0 if photon_rate_hz is None else float(photon_rate_hz),
                    channel_noise_mv=float(cfg.tangential.channel_noise_mv),
                    noise_note="photon_rate_hz -1: no photon noise; trial k's noise from trial_seed(seed, k)")


def _dataset(rig, res, monitors, cond: dict, trials: int, n_steps: int, name: str, params: dict) -> xr.Dataset:
    recs = {m.variable: _flat(res[m.variable]) for m in monitors}
    ds = record_dataset(rig, recs, monitors, {**cond, "trial": np.arange(trials)}, n_steps,
                        rig_attrs(rig, name, params))
    for dim in ("hs_cell", "vs_cell"):
        if dim not in ds.coords:
            ds.coords.update(cell_coords(rig, dim))
    if "preferred_direction" not in ds.coords:
        ds.coords["preferred_direction"] = np.array(DIRECTIONS)
    return ds


def _describe(ds: xr.Dataset) -> xr.Dataset:
    for name, (units, long_name) in _DESCRIBE.items():
        if name in ds.variables:
            ds[name].attrs.update({"long_name": long_name, **({"units": units} if units else {})})
    return cf_describe(ds)


def _check_common(name: str, *, duration_s, settle_s, mean_luminance, photon_rate_hz, wavelength_deg=None):
    if not (mean_luminance > 0 and math.isfinite(mean_luminance)):
        raise ValueError(f"{name} mean_luminance must be a positive number, got {mean_luminance}")
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ValueError(f"{name} duration must be a positive number of seconds, got {duration_s}")
    if not 0 <= settle_s < duration_s:
        raise ValueError(f"{name} settle_s must lie in [0, duration = {duration_s}) s, got {settle_s}; use a "
                         f"longer --duration or a shorter --settle")
    if photon_rate_hz is not None and not (photon_rate_hz > 0 and math.isfinite(photon_rate_hz)):
        raise ValueError(f"--photon-rate must be a positive number of photons per ommatidium per second, got "
                         f"{photon_rate_hz}")
    if wavelength_deg is not None and not (wavelength_deg > 0 and math.isfinite(wavelength_deg)):
        raise ValueError(f"{name} wavelength must be a positive number of degrees, got {wavelength_deg}")


def _store_fit(ds: xr.Dataset, prefix: str, fit: dict, units: str, what: str) -> None:
    """A Naka–Rushton fit's parameters and standard errors as scalar variables ``<prefix>_c50`` …"""
    for key, u, words in (("c50", "1", "semi-saturation contrast c50"), ("n", "1", "exponent n"),
                          ("rmax", units, "maximum response Rmax")):
        ds[f"{prefix}_{key}"] = ((), fit[key], {"units": u, "long_name": f"Naka-Rushton {words} of the {what}"})
        ds[f"{prefix}_{key}_se"] = ((), fit[f"{key}_se"], {
            "units": u, "long_name": f"standard error of the Naka-Rushton {words} of the {what}",
            "note": "square root of the fit covariance's diagonal (scipy.optimize.curve_fit)"})


# =========================================================================== contrast

def _contrast(config: EphysConfig, *, contrasts=None, temporal_frequency_hz: float | None = None,
              wavelength_deg: float = 60.0, duration_s: float = 2.0, settle_s: float = 1.0,
              mean_luminance: float = 1.0, photon_rate_hz: float | None = None,
              channel_noise_mv: float | None = None, record=None) -> xr.Dataset:
    """Contrast–response of the lobula plate: a drum grating drifting front-to-back over a contrast series.

    The grating (wavelength ``wavelength_deg``, degree; 60 by default, where the optics pass 98 % of
    its contrast) drifts at ``temporal_frequency_hz`` (default the
    correlators' optimum 1/(2π·τ_T4)) in the eye's front-to-back direction, one condition per
    Michelson contrast (default :data:`CONTRASTS`), for ``duration_s``; the eye starts adapted to the
    mean luminance. Responses are means over the largest whole number of periods after ``settle_s``.
    photon_rate_hz (photons per ommatidium per second at luminance 1) and channel_noise_mv (σ, mV)
    add noise; then ``config.trials`` trials are run and stored (dim ``trial``).

    Stores ``t4_mean_response``/``t5_mean_response`` (contrast, trial, preferred_direction: each layer's
    mean over every ommatidium), ``hs_v_mean``/``vs_v_mean`` (contrast, trial, cell, mV),
    ``hs_g_exc_mean``/``hs_g_inh_mean`` (conductances, units of g_leak), and Naka–Rushton fits
    (c50, n, Rmax and their standard errors) of the trial mean of: T4's and T5's front-to-back layer
    (``t4_c50`` …, the stage's measure), the HS cells' total conductance g_e + g_i (``hs_g_c50`` …) and
    the HS cells' potential (``hs_v_c50`` …, cell mean). With ``OnOffConfig.contrast_c50`` set,
    ``c50_expected`` is that c50 in stimulus contrast (over the optics' mean attenuation m and the
    photoreceptor's and lamina's gain |H(f)|: c50/(m·|H(f)|)), and ``hs_v_c50_predicted`` the HS
    potential's half-maximum the shunting membrane gives: hs_g_c50/√(1 + γ), γ = hs_g_rmax (the
    conductance the saturated drive opens), exact for a steady conductance with n = 2.
    """
    cfg = _noisy_config(config, channel_noise_mv)
    _check_common("contrast", duration_s=duration_s, settle_s=settle_s, mean_luminance=mean_luminance,
                  photon_rate_hz=photon_rate_hz, wavelength_deg=wavelength_deg)
    c = CONTRASTS if contrasts is None else np.atleast_1d(np.asarray(contrasts, dtype=float))
    if c.size < 4 or not np.all((c > 0) & (c <= 1)):
        raise ValueError(f"contrast needs at least 4 contrasts in (0, 1] for its Naka-Rushton fit, got {c.tolist()}")
    c = np.sort(c)
    tf = 1.0 / (2.0 * math.pi * cfg.on_off.tau_delay_t4_s) if temporal_frequency_hz is None \
        else float(temporal_frequency_hz)
    rig = Rig(cfg)
    if not 0 < tf < 0.5 / rig.dt:
        raise ValueError(f"contrast's temporal frequency must lie in (0, {0.5 / rig.dt:g}) Hz (the Nyquist limit), "
                         f"got {tf}")
    monitors = _plate_monitors(rig, record)
    K = _trials(cfg, photon_rate_hz)
    n_steps = int(round(duration_s / rig.dt))
    direction = float(_image_angles(cfg.on_off.eye)[0])
    src = GratingSource(rig.lattice, kind="drum", temporal_freq_hz=tf, contrast=c, wavelength_deg=wavelength_deg,
                        direction_deg=direction, mean_luminance=mean_luminance, frame_rate_hz=1.0 / rig.dt,
                        device=cfg.device)
    lum = src.render(n_steps)                                                         # (C, T, n)
    res = plate_chain(rig, lambda b0, b1: lum[b0:b1], len(c), n_steps, monitors, trials=K,
                      photon_rate_hz=photon_rate_hz, seed=cfg.seed, baseline=mean_luminance)
    params = dict(contrasts=c, temporal_frequency_hz=tf, wavelength_deg=wavelength_deg, direction_image_deg=direction,
                  duration_s=duration_s, settle_s=settle_s, mean_luminance=mean_luminance,
                  photon_rate_hz=photon_rate_hz, channel_noise_mv=cfg.tangential.channel_noise_mv,
                  monitors=_specs(monitors))
    ds = _dataset(rig, res, monitors, {"contrast": c}, K, n_steps, "contrast", params)
    win = _window(n_steps, rig.dt, settle_s, tf)
    lay = ("contrast", "trial", "preferred_direction")
    for cell in ("t4", "t5"):
        ds[f"{cell}_mean_response"] = (lay, _time_mean(res[f"{cell}_layers"], win), {
            "units": "1", "long_name": f"{cell.upper()} response of each layer, mean over every ommatidium and the "
                                       "steady state"})
    for cell in ("hs", "vs"):
        ds[f"{cell}_v_mean"] = (("contrast", "trial", f"{cell}_cell"), _time_mean(res[f"{cell}.v"], win), {
            "units": "mV", "long_name": f"{cell.upper()} membrane potential relative to rest, steady-state mean"})
    g = res["g"]
    for name, x, words in (("hs_g_exc_mean", g.hs_exc, "excitatory"), ("hs_g_inh_mean", g.hs_inh, "inhibitory")):
        ds[name] = (("contrast", "trial", "hs_cell"), _time_mean(x, win), {
            "units": "1", "long_name": f"HS {words} conductance in units of the leak conductance, steady-state mean"})
    ftb = DIRECTIONS.index("front_to_back")
    for cell in ("t4", "t5"):
        y = ds[f"{cell}_mean_response"].isel(preferred_direction=ftb).mean("trial").values
        _store_fit(ds, cell, naka_rushton_fit(c, y), "1", f"{cell.upper()} front-to-back layer's mean response")
    g_tot = (ds.hs_g_exc_mean + ds.hs_g_inh_mean).mean(("trial", "hs_cell")).values
    fit_g = naka_rushton_fit(c, g_tot)
    _store_fit(ds, "hs_g", fit_g, "1", "HS cells' total synaptic conductance g_e + g_i (cell mean, units of g_leak)")
    _store_fit(ds, "hs_v", naka_rushton_fit(c, ds.hs_v_mean.mean(("trial", "hs_cell")).values), "mV",
               "HS cells' potential (cell mean)")
    ds["hs_v_c50_predicted"] = ((), fit_g["c50"] / math.sqrt(1.0 + fit_g["rmax"]), {
        "units": "1", "long_name": "HS potential's semi-saturation contrast the shunting membrane gives: "
                                   "hs_g_c50/sqrt(1 + hs_g_rmax)",
        "note": "V = (E_exc g_e + E_inh g_i)/(1 + g_e + g_i) with g = gamma R(c), R = c^2/(c^2 + c50^2), is "
                "Naka-Rushton with c50/sqrt(1 + gamma)"})
    pr = PhotoreceptorConfig(tau_s=cfg.circuit.photoreceptor.tau_s, tau_hp_s=cfg.on_off.tau_hp_on_s)
    m = _optics(src, mean_luminance, float(c[-1]))
    h = float(np.abs(photoreceptor_frequency_response(pr, rig.dt, tf)))
    c50 = cfg.on_off.contrast_c50
    ds["c50_expected"] = ((), math.nan if c50 is None else c50 / (m * h), {
        "units": "1", "long_name": "the lamina's configured c50 in stimulus contrast: c50/(m |H(f)|) (NaN: "
                                   "contrast gain off)",
        "note": f"m = {m:.4f}, the optics' mean attenuation of the grating; |H(f)| = {h:.4f}, the photoreceptor's "
                f"low-pass and the lamina's high-pass at the grating's temporal frequency"})
    ds.attrs.update(configured_c50=-1.0 if c50 is None else float(c50), temporal_frequency_hz=tf,
                    optics_attenuation=m, lamina_gain=h)
    noise_attrs(ds, cfg, K, photon_rate_hz)
    return _describe(ds)


contrast = protocol(_contrast, EphysConfig)


# =========================================================================== flicker

def _flicker(config: EphysConfig, *, temporal_frequencies_hz=FLICKER_HZ, contrast: float = 0.5,
             wavelength_deg: float = 20.0, duration_s: float = 3.0, settle_s: float = 1.5,
             mean_luminance: float = 1.0, photon_rate_hz: float | None = None,
             channel_noise_mv: float | None = None, record=None) -> xr.Dataset:
    """Full-field sinusoidal flicker against motion at the same temporal frequencies.

    Conditions: ``stimulus`` (flicker: L₀(1 + C·sin 2πft) on every ommatidium; motion: a drum grating of
    ``wavelength_deg`` drifting front-to-back) × ``temporal_frequency_hz`` f × trial. Responses are means
    over the largest whole number of periods after ``settle_s``.

    Stores ``t4_mean_response``/``t5_mean_response`` (stimulus, f, trial, preferred_direction),
    ``hs_v_mean``/``vs_v_mean``, ``hs_opponent_drive`` (the HS field's preferred minus null T4 + T5,
    u²: 0 for flicker, which drives both layers alike), ``hs_flicker_motion_ratio`` (f), and the
    frequency responses: ``photoreceptor_gain``/``_phase_deg`` (the circuit's photoreceptor, noise-free,
    relative to the stimulus' modulation L₀·C) and ``lamina_gain``/``_phase_deg`` (the lamina's ON
    minus OFF output, mean over ommatidia and trials), each beside its ``_predicted`` value from
    :func:`lobula.photoreceptor.photoreceptor_frequency_response` (exact for the linear stages: the
    lamina's with no contrast gain and zero rectification thresholds).
    """
    cfg = _noisy_config(config, channel_noise_mv)
    _check_common("flicker", duration_s=duration_s, settle_s=settle_s, mean_luminance=mean_luminance,
                  photon_rate_hz=photon_rate_hz, wavelength_deg=wavelength_deg)
    f = np.atleast_1d(np.asarray(temporal_frequencies_hz, dtype=float))
    if not 0 < contrast <= 1:
        raise ValueError(f"flicker contrast must lie in (0, 1], got {contrast}")
    rig = Rig(cfg)
    if not np.all((f > 0) & (f < 0.5 / rig.dt)):
        raise ValueError(f"flicker frequencies must lie in (0, {0.5 / rig.dt:g}) Hz (the Nyquist limit), got "
                         f"{f.tolist()}")
    monitors = _plate_monitors(rig, record)
    K = _trials(cfg, photon_rate_hz)
    n_steps = int(round(duration_s / rig.dt))
    t = np.arange(n_steps) * rig.dt
    n, F = rig.lattice.n, len(f)
    wave = mean_luminance * (1.0 + contrast * np.sin(2.0 * math.pi * f[:, None] * t[None, :]))        # (F, T)
    flick = torch.as_tensor(wave, dtype=torch.float32, device=cfg.device)
    direction = float(_image_angles(cfg.on_off.eye)[0])
    src = GratingSource(rig.lattice, kind="drum", temporal_freq_hz=f, contrast=contrast, wavelength_deg=wavelength_deg,
                        direction_deg=direction, mean_luminance=mean_luminance, frame_rate_hz=1.0 / rig.dt,
                        device=cfg.device)

    def stimulus(b0, b1):
        parts = []
        if b0 < F:
            parts.append(flick[b0:min(b1, F), :, None].expand(-1, -1, n))
        if b1 > F:
            parts.append(src.render(n_steps)[max(b0, F) - F:b1 - F])
        return torch.cat(parts)

    res = plate_chain(rig, stimulus, 2 * F, n_steps, monitors, trials=K, photon_rate_hz=photon_rate_hz,
                      seed=cfg.seed, baseline=mean_luminance)
    kinds = np.array(["flicker", "motion"])
    params = dict(temporal_frequencies_hz=f, contrast=contrast, wavelength_deg=wavelength_deg,
                  direction_image_deg=direction, duration_s=duration_s, settle_s=settle_s,
                  mean_luminance=mean_luminance, photon_rate_hz=photon_rate_hz,
                  channel_noise_mv=cfg.tangential.channel_noise_mv, monitors=_specs(monitors))
    ds = _dataset(rig, res, monitors, {"stimulus": kinds, "temporal_frequency_hz": f}, K, n_steps, "flicker", params)
    w_hs, _ = tangential_fields(rig.lattice, cfg.tangential)
    t4l, t5l = res["t4_layers"], res["t5_layers"]
    means = {k: np.empty((2 * F, K) + tuple(res[k].shape[3:])) for k in ("t4_layers", "t5_layers", "hs.v", "vs.v")}
    opp = np.empty((2 * F, K, cfg.tangential.n_hs))
    g = res["g"]
    for i in range(F):                                    # each frequency its own whole periods
        win = _window(n_steps, rig.dt, settle_s, f[i])
        for b in (i, F + i):
            for k in means:
                means[k][b] = _time_mean(res[k][b:b + 1], win)[0]
            # the field's preferred minus null drive, from the conductances over their gains
            ge = _time_mean(g.hs_exc[b:b + 1], win)[0] / max(cfg.tangential.g_exc, 1e-300)
            gi = _time_mean(g.hs_inh[b:b + 1], win)[0] / max(cfg.tangential.g_inh, 1e-300)
            opp[b] = ge - gi
    shape = lambda a: a.reshape((2, F) + a.shape[1:])                                   # noqa: E731
    lay = ("stimulus", "temporal_frequency_hz", "trial", "preferred_direction")
    for cell, key in (("t4", "t4_layers"), ("t5", "t5_layers")):
        ds[f"{cell}_mean_response"] = (lay, shape(means[key]), {
            "units": "1", "long_name": f"{cell.upper()} response of each layer, mean over every ommatidium and whole "
                                       "periods of the steady state"})
    for cell in ("hs", "vs"):
        ds[f"{cell}_v_mean"] = (("stimulus", "temporal_frequency_hz", "trial", f"{cell}_cell"),
                                shape(means[f"{cell}.v"]), {
            "units": "mV", "long_name": f"{cell.upper()} membrane potential relative to rest, steady-state mean"})
    ds["hs_opponent_drive"] = (("stimulus", "temporal_frequency_hz", "trial", "hs_cell"), shape(opp), {
        "units": "1", "long_name": "HS field's preferred (front-to-back) minus null (back-to-front) T4 + T5 drive, "
                                   "steady-state mean (photoreceptor output squared)",
        "note": "the conductances over g_exc and g_inh; with motion adaptation on, after it"})
    hs = ds.hs_v_mean.mean(("trial", "hs_cell"))
    ds["hs_flicker_motion_ratio"] = ("temporal_frequency_hz", (hs.sel(stimulus="flicker") /
                                                               hs.sel(stimulus="motion")).values, {
        "units": "1", "long_name": "HS steady-state potential (cell and trial mean) to flicker over that to "
                                   "front-to-back motion at the same temporal frequency and contrast"})
    # Frequency responses against the stimulus' modulation, whose phasor is −i·L₀·C (a sine).
    x_in = -1j * mean_luminance * contrast
    pc = rig.config.circuit.photoreceptor
    y, _ = photoreceptor_run(pc, rig.dt, flick[:, :, None].double(),
                             photoreceptor_init(pc, torch.full((F, 1), float(mean_luminance), dtype=torch.float64)))
    lam = res["lamina"][:F].double().mean(1).cpu().numpy()                              # (F, T)
    yp = y[..., 0].cpu().numpy()
    h_pr = np.empty(F, complex)
    h_la = np.empty(F, complex)
    for i in range(F):
        win = _window(n_steps, rig.dt, settle_s, f[i])
        h_pr[i] = sine_fit(yp[i, win], t[win], f[i]) / x_in
        h_la[i] = sine_fit(lam[i, win], t[win], f[i]) / x_in
    pred_pr = photoreceptor_frequency_response(pc, rig.dt, f)
    pred_la = photoreceptor_frequency_response(
        PhotoreceptorConfig(tau_s=pc.tau_s, tau_hp_s=cfg.on_off.tau_hp_on_s), rig.dt, f)
    for name, val, words in (("photoreceptor", h_pr, "the circuit's photoreceptor output"),
                             ("lamina", h_la, "the lamina's ON minus OFF output (mean over ommatidia and trials)")):
        ds[f"{name}_gain"] = ("temporal_frequency_hz", np.abs(val), {
            "units": "1", "long_name": f"gain of {words} to full-field flicker (output amplitude over the "
                                       "luminance modulation)"})
        ds[f"{name}_phase_deg"] = ("temporal_frequency_hz", np.degrees(np.angle(val)), {
            "units": "degree", "long_name": f"phase of {words} relative to the flicker"})
    for name, val, words in (("photoreceptor", pred_pr, "photoreceptor (its linear stages)"),
                             ("lamina", pred_la, "lamina: photoreceptor low-pass times the lamina's high-pass")):
        ds[f"{name}_gain_predicted"] = ("temporal_frequency_hz", np.abs(val), {
            "units": "1", "long_name": f"exact discrete gain of the {words}",
            "note": "lobula.photoreceptor.photoreceptor_frequency_response"})
        ds[f"{name}_phase_deg_predicted"] = ("temporal_frequency_hz", np.degrees(np.angle(val)), {
            "units": "degree", "long_name": f"exact discrete phase of the {words}"})
    ds.attrs["lamina_prediction_valid"] = int(cfg.on_off.contrast_c50 is None and cfg.on_off.offset_on == 0
                                              and cfg.on_off.offset_off == 0 and photon_rate_hz is None)
    noise_attrs(ds, cfg, K, photon_rate_hz)
    return _describe(ds)


flicker = protocol(_flicker, EphysConfig)


# =========================================================================== summaries and figures

def contrast_summary(ds: xr.Dataset) -> list[str]:
    """Lines describing a stored ``contrast`` recording: the Naka–Rushton fits."""
    c50 = ds.attrs.get("configured_c50", -1.0)
    lines = [f"drum grating front-to-back at {ds.attrs['temporal_frequency_hz']:.3g} Hz; lamina contrast gain: "
             + (f"c50 {c50:g} (in stimulus contrast {float(ds.c50_expected):.3g})" if c50 > 0 else "off")]
    for p, words in (("t4", "T4 front-to-back layer"), ("t5", "T5 front-to-back layer"),
                     ("hs_g", "HS conductance"), ("hs_v", "HS potential")):
        lines.append(f"{words}: Naka-Rushton c50 {float(ds[f'{p}_c50']):.3g} ± {float(ds[f'{p}_c50_se']):.2g}, "
                     f"n {float(ds[f'{p}_n']):.3g} ± {float(ds[f'{p}_n_se']):.2g}, Rmax {float(ds[f'{p}_rmax']):.3g} "
                     f"{ds[f'{p}_rmax'].attrs['units']}")
    lines.append(f"HS potential's c50 predicted from its membrane: {float(ds.hs_v_c50_predicted):.3g}")
    return lines


def flicker_summary(ds: xr.Dataset) -> list[str]:
    """Lines describing a stored ``flicker`` recording."""
    opp = ds.hs_opponent_drive.mean(("trial", "hs_cell"))
    lines = ["HS potential to flicker over motion, per temporal frequency: " + ", ".join(
        f"{f:g} Hz {r:.2f}" for f, r in zip(ds.temporal_frequency_hz.values, ds.hs_flicker_motion_ratio.values))]
    lines.append("HS opponent drive (pref − null), flicker / motion: " + ", ".join(
        f"{f:g} Hz {float(opp.sel(stimulus='flicker', temporal_frequency_hz=f)):.2g} / "
        f"{float(opp.sel(stimulus='motion', temporal_frequency_hz=f)):.2g}" for f in ds.temporal_frequency_hz.values))
    for name in ("photoreceptor", "lamina"):
        err = np.max(np.abs(ds[f"{name}_gain"] / ds[f"{name}_gain_predicted"] - 1.0)).item()
        lines.append(f"{name} gain vs its exact discrete prediction: largest relative difference {err:.2g}")
    return lines


def _suptitle(ds: xr.Dataset) -> str:
    cfg = json.loads(ds.attrs["config"])["ephys"]
    noise = []
    if ds.attrs.get("photon_rate_hz", -1) > 0:
        noise.append(f"{ds.attrs['photon_rate_hz']:g} photons/s")
    if ds.attrs.get("channel_noise_mv", 0) > 0:
        noise.append(f"channel noise {ds.attrs['channel_noise_mv']:g} mV")
    return (f"Δφ = {cfg['lattice']['dphi_deg']:g}°, {ds.attrs.get('trials', 1)} trial(s)"
            + (f", {', '.join(noise)}" if noise else ", no noise"))


def plot_contrast(ds: xr.Dataset, path) -> list:
    """T4/T5 front-to-back layers and HS cells against contrast (log axis) with their Naka–Rushton fits and
    c50 marks; PNG and PDF."""
    from .figures import _plt, save_png_and_pdf, sem

    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(10.5, 4.3), layout="constrained")
    c = ds.contrast.values
    cc = np.geomspace(c.min(), c.max(), 200)
    ftb = "front_to_back"
    for cell, col in (("t4", "C0"), ("t5", "C1")):
        r = ds[f"{cell}_mean_response"].sel(preferred_direction=ftb)
        ax[0].errorbar(c, r.mean("trial"), yerr=sem(r.values, 1) if r.sizes["trial"] > 1 else None, fmt="o",
                       color=col, ms=4, label=f"{cell.upper()} front-to-back layer")
        if np.isfinite(float(ds[f"{cell}_c50"])):
            ax[0].plot(cc, naka_rushton(cc, float(ds[f"{cell}_rmax"]), float(ds[f"{cell}_c50"]),
                                        float(ds[f"{cell}_n"])), color=col, lw=1.2,
                       label=f"fit: c50 {float(ds[f'{cell}_c50']):.3g}, n {float(ds[f'{cell}_n']):.2g}")
    exp = float(ds.c50_expected)
    if np.isfinite(exp):
        ax[0].axvline(exp, color="0.4", ls="--", lw=1, label=f"configured c50 in stimulus contrast ({exp:.3g})")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("grating contrast (Michelson)")
    ax[0].set_ylabel("mean response (photoreceptor output squared)")
    ax[0].set_title("T4/T5: the motion detectors' contrast response", fontsize=9)
    ax[0].legend(fontsize=7, frameon=False)
    v = ds.hs_v_mean.mean("hs_cell")
    ax[1].errorbar(c, v.mean("trial"), yerr=sem(v.values, 1) if v.sizes["trial"] > 1 else None, fmt="o", color="C2",
                   ms=4, label="HS potential (cell mean)")
    if np.isfinite(float(ds.hs_v_c50)):
        ax[1].plot(cc, naka_rushton(cc, float(ds.hs_v_rmax), float(ds.hs_v_c50), float(ds.hs_v_n)), color="C2",
                   lw=1.2, label=f"fit: c50 {float(ds.hs_v_c50):.3g}, n {float(ds.hs_v_n):.2g}")
    pred = float(ds.hs_v_c50_predicted)
    if np.isfinite(pred):
        ax[1].axvline(pred, color="C2", ls=":", lw=1.2, label=f"c50 predicted by the shunting membrane ({pred:.3g})")
    if np.isfinite(exp):
        ax[1].axvline(exp, color="0.4", ls="--", lw=1, label=f"configured c50 in stimulus contrast ({exp:.3g})")
    ax[1].set_xscale("log")
    ax[1].set_xlabel("grating contrast (Michelson)")
    ax[1].set_ylabel("HS potential re rest (mV)")
    ax[1].set_title("HS cells: the shunting membrane saturates on top of the lamina", fontsize=9)
    ax[1].legend(fontsize=7, frameon=False)
    fig.suptitle(f"Contrast response: grating front-to-back at {ds.attrs['temporal_frequency_hz']:.3g} Hz; "
                 + _suptitle(ds), fontsize=10)
    return save_png_and_pdf(fig, path)


def plot_flicker(ds: xr.Dataset, path) -> list:
    """Photoreceptor and lamina gain against frequency (measured points, exact discrete lines); T4
    preferred and null layers and HS potentials to flicker and motion; PNG and PDF."""
    from .figures import _plt, save_png_and_pdf

    plt = _plt()
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.3), layout="constrained")
    f = ds.temporal_frequency_hz.values
    ff = np.geomspace(f.min(), f.max(), 200)
    cfg = json.loads(ds.attrs["config"])["ephys"]
    dt = float(cfg["circuit"]["dt_s"])
    pc = PhotoreceptorConfig(**cfg["circuit"]["photoreceptor"])
    for name, col, conf in (("photoreceptor", "C0", pc),
                            ("lamina", "C1", PhotoreceptorConfig(tau_s=pc.tau_s,
                                                                  tau_hp_s=cfg["on_off"]["tau_hp_on_s"]))):
        ax[0].plot(f, ds[f"{name}_gain"], "o", color=col, ms=5, label=f"{name}, measured")
        ax[0].plot(ff, np.abs(photoreceptor_frequency_response(conf, dt, ff)), color=col, lw=1.2,
                   label=f"{name}, exact discrete transfer")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("flicker frequency (Hz)")
    ax[0].set_ylabel("gain (output amplitude / luminance modulation)")
    ax[0].set_title("Photoreceptor and lamina frequency response", fontsize=9)
    ax[0].legend(fontsize=7, frameon=False)
    for kind, ls in (("motion", "-"), ("flicker", "--")):
        r = ds.t4_mean_response.sel(stimulus=kind).mean("trial")
        for d, col in (("front_to_back", "C2"), ("back_to_front", "C3")):
            ax[1].plot(f, r.sel(preferred_direction=d), ls=ls, marker="o", ms=4, color=col,
                       label=f"{kind}: {d.replace('_', '-')} layer")
    ax[1].set_xscale("log")
    ax[1].set_xlabel("temporal frequency (Hz)")
    ax[1].set_ylabel("T4 mean response (photoreceptor output squared)")
    ax[1].set_title("T4 (solid motion, dashed flicker): flicker drives preferred and null layers alike\n"
                    "(its two dashed lines coincide)", fontsize=9)
    ax[1].legend(fontsize=7, frameon=False)
    for kind, ls in (("motion", "-"), ("flicker", "--")):
        v = ds.hs_v_mean.sel(stimulus=kind).mean(("trial", "hs_cell"))
        ax[2].plot(f, v, ls=ls, marker="o", ms=4, color="C4", label=f"HS potential, {kind}")
        o = ds.hs_opponent_drive.sel(stimulus=kind).mean(("trial", "hs_cell"))
        ax[2].plot(f, o * (float(v.max()) / max(float(ds.hs_opponent_drive.max()), 1e-30)), ls=ls, marker="s",
                   ms=3, color="0.4", label=f"opponent drive (pref − null, scaled), {kind}")
    ax[2].axhline(0, color="0.7", lw=0.8)
    ax[2].set_xscale("log")
    ax[2].set_xlabel("temporal frequency (Hz)")
    ax[2].set_ylabel("HS potential re rest (mV, cell mean)")
    ax[2].set_title("HS: flicker (dashed) against front-to-back motion (solid)", fontsize=9)
    ax[2].legend(fontsize=7, frameon=False)
    fig.suptitle(f"Flicker vs motion, contrast {json.loads(ds.attrs['parameters'])['contrast']:g}; "
                 + _suptitle(ds), fontsize=10)
    return save_png_and_pdf(fig, path)


# =========================================================================== command line

#: the lobula-plate physiology protocols of ``lobula ephys`` (this module and :mod:`.adaptation`)
PLATE_PROTOCOLS = ("contrast", "flicker", "adaptation")
#: command-line option → protocol keyword, per protocol
PLATE_OPTIONS = {
    "contrast": (("contrast", "contrasts"), ("tf", "temporal_frequency_hz"), ("wavelength", "wavelength_deg"),
                 ("duration", "duration_s"), ("settle", "settle_s"), ("photon_rate", "photon_rate_hz"),
                 ("channel_noise", "channel_noise_mv")),
    "flicker": (("tf", "temporal_frequencies_hz"), ("contrast", "contrast"), ("wavelength", "wavelength_deg"),
                ("duration", "duration_s"), ("settle", "settle_s"), ("photon_rate", "photon_rate_hz"),
                ("channel_noise", "channel_noise_mv")),
    "adaptation": (("tf", "temporal_frequency_hz"), ("contrast", "contrast"), ("wavelength", "wavelength_deg"),
                   ("adapter", "adapter_s"), ("gaps", "gaps_s"), ("test_duration", "test_s"),
                   ("adapt_tau", "adapt_tau_s"), ("adapt_half_g", "adapt_half_g"), ("photon_rate", "photon_rate_hz"),
                   ("channel_noise", "channel_noise_mv")),
}
#: options that take one value on the command line (nargs "+") but one keyword value here
_SCALAR = {("contrast", "flicker"), ("contrast", "adaptation"), ("tf", "contrast"), ("tf", "adaptation")}


def run_plate_protocol(protocol_name: str, opts: dict):
    """``lobula ephys contrast|flicker|adaptation`` from a dict of given (already applicability-checked) options."""
    from .command import rig_config

    noisy = "photon_rate" in opts or opts.get("channel_noise", 0) > 0
    trials = opts.get("trials", 4 if noisy else 1)
    if trials != 1 and not noisy:
        raise ValueError(f"--trials {trials}: without noise every trial would be identical; use --trials 1, or add "
                         f"--photon-rate or --channel-noise for trial-to-trial variability")
    cfg = rig_config(protocol_name, {k: v for k, v in opts.items() if k not in ("trials", "tau")})
    cfg = replace(cfg, trials=trials)
    if "tau" in opts:
        cfg = replace(cfg, on_off=replace(cfg.on_off, tau_delay_t4_s=float(opts["tau"]),
                                          tau_delay_t5_s=float(opts["tau"])))
    if "c50" in opts:
        cfg = replace(cfg, on_off=replace(cfg.on_off, contrast_c50=float(opts["c50"])))
    kw = {}
    for opt, key in PLATE_OPTIONS[protocol_name]:
        if opt in opts:
            v = opts[opt]
            if (opt, protocol_name) in _SCALAR:
                if len(v) != 1:
                    raise ValueError(f"{protocol_name} takes one --{opt.replace('_', '-')} value, got {v}")
                v = v[0]
            kw[key] = v
    run = {"contrast": contrast, "flicker": flicker}.get(protocol_name)
    if run is None:
        from .adaptation import adaptation as run
    return run(cfg, record=opts.get("record"), **kw)
