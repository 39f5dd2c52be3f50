"""Motion adaptation of the tangential cells: the ``adaptation`` protocol.

An adapter (a drum grating drifting in the HS cells' preferred, front-to-back direction for
``adapter_s``) is followed, after a blank gap Δ at the mean luminance, by a short test grating; one
condition per gap, and a control with no adapter. The adaptation is
:class:`lobula.tangential_cells.TangentialConfig`'s: a divisive gain G = LP_τa(1/(1 + g/g½)) on each
cell's excitatory and inhibitory conductance. During the gap the drive stops, so 1 − G decays as
exp(−Δ/τa); the gain's recursion is linear in G given the (unadapted) drive, so the test's mean
adapted conductance is an affine function of G at the test's onset and recovers toward the control's
as ``R(Δ) = R_control − B·exp(−Δ/τa)`` once the lamina's own transient at the adapter's end has died
away (gaps ≥ ``fit_from_s``, default four lamina high-pass time constants). The fit of that form to the
HS conductance returns τa (the known answer); the HS potential, a saturating function of the
conductances, recovers with about the same time constant (stored, not exact).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from stimuli.lattice_stimuli import GratingSource

from .plate import (_check_common, _dataset, _describe, _noisy_config, _plate_monitors, _suptitle, _trials,
                       noise_attrs, plate_chain)
from .edges import _image_angles
from .protocols import _specs
from .rig import EphysConfig, Rig, protocol

__all__ = ["adaptation", "recovery_fit", "plot_adaptation", "adaptation_summary", "GAPS_S"]

#: adaptation's default gaps between the adapter's end and the test (s)
GAPS_S = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)


def recovery_fit(gaps_s, response, control: float) -> dict:
    """Fit ``R(Δ) = control − B·exp(−Δ/τ)`` (scipy.optimize.curve_fit) to ``response`` (G,) at ``gaps_s`` (G,).

    Returns {"tau_s", "tau_s_se", "amplitude", "amplitude_se"} (τ in s, B in the response's units; standard
    errors from the covariance); NaN when the fit fails or there is no deficit to recover from.
    """
    from scipy.optimize import curve_fit

    g = np.asarray(gaps_s, dtype=float)
    y = np.asarray(response, dtype=float)
    nan = {"tau_s": math.nan, "tau_s_se": math.nan, "amplitude": math.nan, "amplitude_se": math.nan}
    deficit = control - y
    if len(g) < 3 or not np.all(np.isfinite(y)) or not deficit[0] > 0:
        return nan
    pos = deficit > 0
    tau0 = float(np.ptp(g)) / max(1.0, math.log(deficit[pos][0] / deficit[pos][-1])) if pos.sum() > 1 else 1.0
    try:
        p, cov = curve_fit(lambda d, b, tau: control - b * np.exp(-d / tau), g, y,
                           p0=(deficit[0] * math.exp(g[0] / max(tau0, 1e-3)), max(tau0, 1e-3)),
                           bounds=([0.0, 1e-4], [np.inf, 1e4]), maxfev=20000)
    except (RuntimeError, ValueError):
        return nan
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None)) if np.all(np.isfinite(cov)) else np.full(2, np.nan)
    return {"tau_s": p[1], "tau_s_se": se[1], "amplitude": p[0], "amplitude_se": se[0]}


def _adaptation(config: EphysConfig, *, adapter_s: float = 3.0, gaps_s=GAPS_S, test_s: float = 0.3,
                contrast: float = 0.5, temporal_frequency_hz: float | None = None, wavelength_deg: float = 40.0,
                lead_s: float = 0.2, mean_luminance: float = 1.0, adapt_tau_s: float | None = None,
                adapt_half_g: float | None = None, fit_from_s: float | None = None,
                photon_rate_hz: float | None = None, channel_noise_mv: float | None = None,
                record=None) -> xr.Dataset:
    """Adapter, blank gap, test: the tangential cells' motion adaptation and its recovery.

    Conditions (dim ``condition``): one per gap Δ in ``gaps_s`` (s, coordinate ``gap_s``) and a control
    with no adapter (``adapter`` "none", gap NaN), × trial. Timeline, the same for every condition so the
    tests coincide: blank until the adapter (``adapter_s`` of a front-to-back drum grating of
    ``contrast``, ``wavelength_deg`` and ``temporal_frequency_hz``, default 1/(2π·τ_T4)), blank for Δ,
    then the same grating for ``test_s``; the earliest adapter starts at ``lead_s``. Time 0 is the
    stimulus' start; the test starts at ``test_onset_s``.

    adapt_tau_s, adapt_half_g: the adaptation's τa (s) and g½ (units of g_leak), overriding the rig's
    :class:`~lobula.tangential_cells.TangentialConfig` (adaptation off there and no adapt_tau_s: 1.5 s).
    fit_from_s: the shortest gap the recovery fit uses (default 4 × the lamina's high-pass τ).

    Stores ``hs_g_exc_test`` and ``hs_v_test`` (condition, trial, hs_cell): the HS excitatory conductance
    (after adaptation) and potential, mean over the test; ``hs_g_exc_adapter_end``; and the recovery fits
    ``hs_g_recovery_tau_s`` (the known answer τa) and ``hs_v_recovery_tau_s`` with their standard errors
    (:func:`recovery_fit` on the trial and cell means against the control).
    """
    cfg = _noisy_config(config, channel_noise_mv)
    tc = cfg.tangential
    tau = adapt_tau_s if adapt_tau_s is not None else (tc.adapt_tau_s if tc.adapt_tau_s is not None else 1.5)
    cfg = replace(cfg, tangential=replace(tc, adapt_tau_s=float(tau), adapt_half_g=float(
        tc.adapt_half_g if adapt_half_g is None else adapt_half_g)))
    gaps = np.sort(np.atleast_1d(np.asarray(gaps_s, dtype=float)))
    for name, val in (("adapter_s", adapter_s), ("test_s", test_s)):
        if not (val > 0 and math.isfinite(val)):
            raise ValueError(f"adaptation {name} must be a positive number of seconds, got {val}")
    if not (lead_s >= 0 and math.isfinite(lead_s)):
        raise ValueError(f"adaptation lead_s must be a non-negative number of seconds, got {lead_s}")
    if gaps.size < 3 or not np.all((gaps >= 0) & np.isfinite(gaps)):
        raise ValueError(f"adaptation needs at least 3 non-negative gaps (s) for its recovery fit, got {gaps.tolist()}")
    if not 0 < contrast <= 1:
        raise ValueError(f"adaptation contrast must lie in (0, 1], got {contrast}")
    fit_from = 4.0 * max(cfg.on_off.tau_hp_on_s, cfg.on_off.tau_hp_off_s) if fit_from_s is None else float(fit_from_s)
    if (gaps >= fit_from).sum() < 3:
        raise ValueError(f"the recovery fit uses gaps ≥ {fit_from:g} s (after the lamina's transient) and needs 3 of "
                         f"them; got {gaps.tolist()}: add longer --gaps")
    onset = lead_s + adapter_s + float(gaps.max())
    duration = onset + test_s
    _check_common("adaptation", duration_s=duration, settle_s=0.0, mean_luminance=mean_luminance,
                  photon_rate_hz=photon_rate_hz, wavelength_deg=wavelength_deg)
    tf = 1.0 / (2.0 * math.pi * cfg.on_off.tau_delay_t4_s) if temporal_frequency_hz is None \
        else float(temporal_frequency_hz)
    rig = Rig(cfg)
    if not 0 < tf < 0.5 / rig.dt:
        raise ValueError(f"adaptation's temporal frequency must lie in (0, {0.5 / rig.dt:g}) Hz, got {tf}")
    monitors = _plate_monitors(rig, record)
    K = _trials(cfg, photon_rate_hz)
    dt = rig.dt
    n_steps = int(round(duration / dt))
    i_test = int(round(onset / dt))
    G = len(gaps)
    on = np.zeros((G + 1, n_steps), dtype=bool)                                     # the grating's on-times
    for j, gap in enumerate(gaps):
        start = int(round((onset - gap - adapter_s) / dt))
        on[j, start:int(round((onset - gap) / dt))] = True
    on[:, i_test:] = True
    direction = float(_image_angles(cfg.on_off.eye)[0])
    src = GratingSource(rig.lattice, kind="drum", temporal_freq_hz=tf, contrast=contrast, wavelength_deg=wavelength_deg,
                        direction_deg=direction, mean_luminance=mean_luminance, frame_rate_hz=1.0 / dt,
                        device=cfg.device)
    grating = src.render(n_steps) - mean_luminance                                  # (T, n) modulation
    mask = torch.as_tensor(on, dtype=grating.dtype, device=grating.device)

    def stimulus(b0, b1):
        return mean_luminance + mask[b0:b1, :, None] * grating[None]

    res = plate_chain(rig, stimulus, G + 1, n_steps, monitors, trials=K, photon_rate_hz=photon_rate_hz,
                      seed=cfg.seed, baseline=mean_luminance)
    params = dict(adapter_s=adapter_s, gaps_s=gaps, test_s=test_s, contrast=contrast, temporal_frequency_hz=tf,
                  wavelength_deg=wavelength_deg, direction_image_deg=direction, lead_s=lead_s,
                  mean_luminance=mean_luminance, adapt_tau_s=cfg.tangential.adapt_tau_s,
                  adapt_half_g=cfg.tangential.adapt_half_g, fit_from_s=fit_from, photon_rate_hz=photon_rate_hz,
                  channel_noise_mv=cfg.tangential.channel_noise_mv, monitors=_specs(monitors))
    ds = _dataset(rig, res, monitors, {"condition": np.arange(G + 1)}, K, n_steps, "adaptation", params)
    ds.coords["gap_s"] = ("condition", np.append(gaps, np.nan))
    ds.coords["adapter"] = ("condition", np.array(["motion"] * G + ["none"]))
    win = slice(i_test, n_steps)
    g_exc = res["g"].hs_exc
    test_g = g_exc[:, :, win].double().mean(2).cpu().numpy()                        # (G+1, K, c)
    test_v = res["hs.v"][:, :, win].double().mean(2).cpu().numpy()
    dims = ("condition", "trial", "hs_cell")
    ds["hs_g_exc_test"] = (dims, test_g, {"units": "1", "long_name": "HS excitatory conductance after adaptation, "
                                                                      "units of the leak conductance, mean over the test"})
    ds["hs_v_test"] = (dims, test_v, {"units": "mV", "long_name": "HS membrane potential relative to rest, mean over "
                                                                   "the test"})
    ends = [int(round((onset - gap) / dt)) - 1 for gap in gaps]
    end_g = np.full_like(test_g, np.nan)
    end_g[:G] = g_exc[torch.arange(G), :, torch.as_tensor(ends)].double().cpu().numpy()
    ds["hs_g_exc_adapter_end"] = (dims, end_g, {
        "units": "1", "long_name": "HS excitatory conductance (after adaptation) in the adapter's last step (NaN: "
                                   "no adapter)"})
    use = gaps >= fit_from
    for name, data, units in (("hs_g", test_g, "1"), ("hs_v", test_v, "mV")):
        y = data.mean(axis=(1, 2))
        fit = recovery_fit(gaps[use], y[:G][use], float(y[G]))
        what = "HS excitatory conductance" if name == "hs_g" else "HS potential"
        ds[f"{name}_recovery_tau_s"] = ((), fit["tau_s"], {
            "units": "s", "long_name": f"time constant of the {what}'s recovery from adaptation (test response "
                                       f"against the gap, gaps of at least {fit_from:g} s)"})
        ds[f"{name}_recovery_tau_s_se"] = ((), fit["tau_s_se"], {
            "units": "s", "long_name": f"standard error of the {what}'s recovery time constant"})
        ds[f"{name}_recovery_amplitude"] = ((), fit["amplitude"], {
            "units": units, "long_name": f"{what}'s deficit B at gap 0 of the recovery fit control - B exp(-gap/tau)"})
        ds[f"{name}_test_ratio"] = ("condition", y / y[G], {
            "units": "1", "long_name": f"{what} to the test over the control's (no adapter)"})
    ds.attrs.update(adapt_tau_s=float(cfg.tangential.adapt_tau_s), adapt_half_g=float(cfg.tangential.adapt_half_g),
                    test_onset_s=float(i_test * dt), fit_from_s=fit_from)
    noise_attrs(ds, cfg, K, photon_rate_hz)
    return _describe(ds)


adaptation = protocol(_adaptation, EphysConfig)


def adaptation_summary(ds: xr.Dataset) -> list[str]:
    """Lines describing a stored ``adaptation`` recording: the drop and the recovery time constants."""
    r = ds.hs_g_test_ratio
    first = r.isel(condition=0)
    return [f"configured adaptation τa {ds.attrs['adapt_tau_s']:g} s, g½ {ds.attrs['adapt_half_g']:g}",
            f"HS conductance to the test right after the adapter (gap {float(ds.gap_s[0]):g} s): "
            f"{float(first):.2f} of the control's; HS potential {float(ds.hs_v_test_ratio.isel(condition=0)):.2f}",
            f"recovery time constant (gaps ≥ {ds.attrs['fit_from_s']:g} s): conductance "
            f"{float(ds.hs_g_recovery_tau_s):.3g} ± {float(ds.hs_g_recovery_tau_s_se):.2g} s, potential "
            f"{float(ds.hs_v_recovery_tau_s):.3g} ± {float(ds.hs_v_recovery_tau_s_se):.2g} s"]


def plot_adaptation(ds: xr.Dataset, path) -> list:
    """HS potential against time for a few gaps and the control; the test responses against the gap with the
    recovery fits; PNG and PDF."""
    from .figures import _colours, _plt, save_png_and_pdf

    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(11.5, 4.3), layout="constrained")
    gaps = ds.gap_s.values
    G = int(np.isfinite(gaps).sum())
    show = sorted(set(np.linspace(0, G - 1, min(G, 4)).round().astype(int).tolist())) + [G]
    cols = _colours(len(show))
    t = ds.time.values
    if "hs_v" in ds:
        for j, col in zip(show, cols):
            v = ds.hs_v.isel(condition=j).mean(("trial", "hs_cell"))
            ax[0].plot(t, v, color=col, lw=1.0, label="control (no adapter)" if j == G else f"gap {gaps[j]:g} s")
        ax[0].axvline(ds.attrs["test_onset_s"], color="0.5", ls="--", lw=0.8, label="test onset")
    else:
        ax[0].text(0.5, 0.5, "hs.v not recorded", ha="center", transform=ax[0].transAxes)
    ax[0].set_xlabel("time since stimulus start (s)")
    ax[0].set_ylabel("HS potential re rest (mV, cell mean)")
    ax[0].set_title("Adapter, blank gap, test", fontsize=9)
    ax[0].legend(fontsize=7, frameon=False)
    gg = np.linspace(0, np.nanmax(gaps), 200)
    for name, col, words in (("hs_g", "C0", "HS conductance"), ("hs_v", "C3", "HS potential")):
        ratio = ds[f"{name}_test_ratio"].values[:G]
        ax[1].plot(gaps[:G], ratio, "o", color=col, ms=5, label=f"{words} to the test / control")
        tau, amp = float(ds[f"{name}_recovery_tau_s"]), float(ds[f"{name}_recovery_amplitude"])
        if np.isfinite(tau):
            scale = float(ds["hs_g_exc_test" if name == "hs_g" else "hs_v_test"].isel(condition=G).mean())
            ax[1].plot(gg, 1.0 - amp / scale * np.exp(-gg / tau), color=col, lw=1.2,
                       label=f"fit: τ = {tau:.3g} s")
    ax[1].axvline(ds.attrs["fit_from_s"], color="0.6", ls=":", lw=0.8, label="shortest gap fitted")
    ax[1].axhline(1.0, color="0.7", lw=0.8)
    ax[1].set_xlabel("gap between adapter and test (s)")
    ax[1].set_ylabel("test response / control's")
    ax[1].set_title(f"Recovery from motion adaptation (configured τa = {ds.attrs['adapt_tau_s']:g} s)", fontsize=9)
    ax[1].legend(fontsize=7, frameon=False)
    fig.suptitle("Motion adaptation of the HS cells; " + _suptitle(ds), fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)
