"""The ``flicker`` protocol: full-field sinusoidal flicker and, for comparison, drum-grating motion at the same
temporal frequencies and contrast, through the lobula-plate chain (:mod:`.plate`).

It records the T4/T5 layers' responses (flicker drives preferred and null layers alike), the HS/VS
potentials, and the photoreceptor's and lamina's measured frequency responses beside
:func:`lobula.photoreceptor.photoreceptor_frequency_response`.
"""
from __future__ import annotations

import json
import math

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.photoreceptor import (PhotoreceptorConfig, photoreceptor_frequency_response, photoreceptor_init,
                                  photoreceptor_run)
from lobula.tangential_cells import tangential_fields
from stimuli.lattice_stimuli import GratingSource

from .edges import _image_angles
from .protocols import _specs
from .rig import EphysConfig, Rig, protocol
from .plate import (_check_common, _dataset, _describe, log_panel, noise_attrs, _noisy_config, plate_chain,
                    _plate_monitors, sine_fit, _suptitle, _time_mean, _trials, _window)

__all__ = ["flicker", "plot_flicker", "flicker_summary", "FLICKER_HZ"]

#: flicker's default temporal frequencies (Hz)
FLICKER_HZ = (1.0, 2.0, 4.0, 8.0, 16.0)


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
    # The two stages' gains coincide when the lamina's high-pass time constant equals the photoreceptor's
    # (both 0.25 s by default): the photoreceptor is drawn wide, solid, with large filled markers, the
    # lamina on top narrow, dashed, with small open markers, so that each stays visible on the other.
    for name, col, conf, line, mark in (
            ("photoreceptor", "C0", pc, dict(lw=3.0, ls="-", alpha=0.6), dict(marker="o", ms=9)),
            ("lamina", "C1", PhotoreceptorConfig(tau_s=pc.tau_s, tau_hp_s=cfg["on_off"]["tau_hp_on_s"]),
             dict(lw=1.2, ls="--"), dict(marker="s", ms=5, mfc="none", mew=1.3))):
        ax[0].plot(f, ds[f"{name}_gain"], ls="none", color=col, label=f"{name}, measured", **mark)
        ax[0].plot(ff, np.abs(photoreceptor_frequency_response(conf, dt, ff)), color=col,
                   label=f"{name}, exact discrete transfer", **line)
    ax[0].set_xscale("log")
    ax[0].set_xlabel("flicker frequency (Hz)")
    ax[0].set_ylabel("gain (output amplitude / luminance modulation)")
    same = np.allclose(ds.photoreceptor_gain, ds.lamina_gain, rtol=0.01)
    ax[0].set_title("Photoreceptor and lamina frequency response"
                    + ("\n(lamina: dashed, open squares, on the photoreceptor)" if same else ""),
                    fontsize=9)
    ax[0].legend(fontsize=7, frameon=False)
    for kind, ls in (("motion", "-"), ("flicker", "--")):
        r = ds.t4_mean_response.sel(stimulus=kind).mean("trial")
        # flicker's two layers coincide: the front-to-back layer's large open circles ring the other's dots
        for d, col, mark in (("front_to_back", "C2", dict(marker="o", ms=8, mfc="none", mew=1.3)),
                             ("back_to_front", "C3", dict(marker="o", ms=4))):
            ax[1].plot(f, r.sel(preferred_direction=d), ls=ls, color=col, label=f"{kind}: {d.replace('_', '-')} layer",
                       **mark)
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
    log_panel(ax[2], "temporal frequency (Hz)", "HS potential re rest (mV, cell mean)",
              "HS: flicker (dashed) against front-to-back motion (solid)")
    fig.suptitle(f"Flicker vs motion, contrast {json.loads(ds.attrs['parameters'])['contrast']:g}; "
                 + _suptitle(ds), fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)

