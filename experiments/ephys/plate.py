"""Lobula-plate physiology with noise: the chain the ``contrast``, ``flicker`` and ``adaptation`` protocols share.

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

The protocols: :mod:`.contrast`, :mod:`.flicker`, :mod:`.adaptation`; :func:`run_plate_protocol` runs them
from the command line's options. Shapes: luminance (B, T, n); the chain's outputs carry a trial dim after
the conditions, (B, K, T, …).
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.motion_pathways import DIRECTIONS, lamina_on_off, t4_t5
from lobula.photoreceptor import PhotoreceptorConfig, photoreceptor_init, photoreceptor_run
from lobula.tangential_cells import conductances
from stimuli.lattice_stimuli import GratingSource

from .edges import _centre_columns, cell_coords, select
from .rig import (PATHWAY_RECORDS, EphysConfig, Rig, cf_describe, monitors_for, record_dataset, rig_attrs,
                  trial_seed)

__all__ = ["shot_noise", "plate_chain", "plate_config", "noise_attrs", "sine_fit", "run_plate_protocol", "PLATE_PROTOCOLS"]

#: luminance × time × ommatidia × trials per chunk of conditions (float32: about 100 MB per trial with the
#: T4/T5 gathers); fixed by the stimulus alone so trial k's noise does not depend on the number of trials
_CHUNK_ELEMENTS = 3_000_000


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


def sine_fit(x: np.ndarray, t: np.ndarray, freq_hz: float) -> np.ndarray:
    """Complex amplitude Y of ``x ≈ a + Re(Y·e^{iωt})`` by least squares along the last axis (x (..., T), t (T,)
    in s): exact for a sinusoid plus a constant whatever the window."""
    w = 2.0 * math.pi * freq_hz * np.asarray(t, dtype=float)
    A = np.stack([np.ones_like(w), np.cos(w), np.sin(w)], axis=1)                     # (T, 3)
    coef, *_ = np.linalg.lstsq(A, np.moveaxis(np.asarray(x, dtype=float), -1, 0).reshape(len(w), -1), rcond=None)
    coef = coef.reshape((3,) + np.asarray(x).shape[:-1])
    return coef[1] - 1j * coef[2]


def _phase_step(rig: Rig, wavelength_deg: float) -> float:
    """Δϕ (rad) between a column and its front-to-back neighbour for a drum grating of wavelength λ (degree)."""
    return 2.0 * math.pi * float(rig.lattice.dphi_deg) / float(wavelength_deg)


def _optics(src: GratingSource, mean_luminance: float, contrast: float) -> float:
    """Mean over ommatidia of the optics' attenuation of the grating of ``src``'s last condition (its
    modulation at the ommatidia over the stimulus' contrast ``contrast`` times ``mean_luminance``)."""
    amp = src._basis[-1].double().norm(dim=0).cpu().numpy()                        # (n,)
    return float(np.mean(amp) / (mean_luminance * contrast))


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


def _suptitle(ds: xr.Dataset) -> str:
    cfg = json.loads(ds.attrs["config"])["ephys"]
    noise = []
    if ds.attrs.get("photon_rate_hz", -1) > 0:
        noise.append(f"{ds.attrs['photon_rate_hz']:g} photons/s")
    if ds.attrs.get("channel_noise_mv", 0) > 0:
        noise.append(f"channel noise {ds.attrs['channel_noise_mv']:g} mV")
    return (f"Δφ = {cfg['lattice']['dphi_deg']:g}°, {ds.attrs.get('trials', 1)} trial(s)"
            + (f", {', '.join(noise)}" if noise else ", no noise"))


def log_panel(ax, xlabel: str, ylabel: str, title: str) -> None:
    """Finish a panel of the lobula-plate figures: a log x axis, its labels, a small title and a frameless legend."""
    ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, frameon=False)


#: the lobula-plate physiology protocols of ``lobula ephys`` (:mod:`.contrast`, :mod:`.flicker`, :mod:`.adaptation`)
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
    from importlib import import_module

    module = import_module(f".{protocol_name}", __package__)  # contrast, flicker, adaptation: one module each
    return getattr(module, protocol_name)(cfg, record=opts.get("record"), **kw)

