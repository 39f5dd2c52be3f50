"""The ``contrast`` protocol: a drum grating drifting front-to-back at the correlators' optimum 1/(2πτ) over a
contrast series, through the lobula-plate chain (:mod:`.plate`).

Naka–Rushton fits (:func:`naka_rushton_fit`) to the T4 and T5 front-to-back layers, the HS conductance
and the HS potential. With ``OnOffConfig.contrast_c50`` set, the T4/T5 fit returns c₅₀ (in stimulus
contrast: c₅₀ over the optics' and filters' attenuation, ``c50_expected``), and the HS potential's
half-maximum lies lower, at c₅₀/√(1 + γ) (γ the conductance the saturated drive opens;
``hs_v_c50_predicted``), because the shunting membrane saturates on top.

:func:`hs_tf_prediction` is the model's own discrete prediction of the HS cells' temporal-frequency tuning.
"""
from __future__ import annotations

import math

import numpy as np
import xarray as xr

from lobula.motion_pathways import DIRECTIONS
from lobula.photoreceptor import (PhotoreceptorConfig, photoreceptor_frequency_response)
from stimuli.lattice_stimuli import GratingSource

from .edges import _image_angles
from .protocols import _specs
from .rig import EphysConfig, Rig, protocol
from .plate import (_check_common, _dataset, _describe, log_panel, noise_attrs, _noisy_config, _optics, plate_chain,
                    _plate_monitors, _suptitle, _time_mean, _trials, _window)

__all__ = ["contrast", "naka_rushton", "naka_rushton_fit", "hs_tf_prediction", "plot_contrast", "contrast_summary", "CONTRASTS"]

#: contrast's default Michelson contrasts: 13 log-spaced from 0.01 to 1
CONTRASTS = np.geomspace(0.01, 1.0, 13)


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


def _store_fit(ds: xr.Dataset, prefix: str, fit: dict, units: str, what: str) -> None:
    """A Naka–Rushton fit's parameters and standard errors as scalar variables ``<prefix>_c50`` …"""
    for key, u, words in (("c50", "1", "semi-saturation contrast c50"), ("n", "1", "exponent n"),
                          ("rmax", units, "maximum response Rmax")):
        ds[f"{prefix}_{key}"] = ((), fit[key], {"units": u, "long_name": f"Naka-Rushton {words} of the {what}"})
        ds[f"{prefix}_{key}_se"] = ((), fit[f"{key}_se"], {
            "units": u, "long_name": f"standard error of the Naka-Rushton {words} of the {what}",
            "note": "square root of the fit covariance's diagonal (scipy.optimize.curve_fit)"})


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
    log_panel(ax[0], "grating contrast (Michelson)", "mean response (photoreceptor output squared)",
              "T4/T5: the motion detectors' contrast response")
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
    log_panel(ax[1], "grating contrast (Michelson)", "HS potential re rest (mV)",
              "HS cells: the shunting membrane saturates on top of the lamina")
    fig.suptitle(f"Contrast response: grating front-to-back at {ds.attrs['temporal_frequency_hz']:.3g} Hz; "
                 + _suptitle(ds), fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)

