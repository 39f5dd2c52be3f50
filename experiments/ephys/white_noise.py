"""The ``white-noise`` protocol: spatiotemporal white noise and reverse correlation (receptive fields).

Stimulus: each ommatidium (or each square pixel of ``pixel_deg`` on the lattice plane) takes a
luminance ``L₀(1 + c·ξ)`` per frame of ``frame_s``, ξ = ±1 (binary) or a standard normal (Gaussian),
independent across pixels and frames; trial k's noise is drawn from
``numpy.random.default_rng(trial_seed(seed, k))`` (:func:`experiments.ephys.rig.trial_seed`), so a
trial shows the same noise on every device and whatever the number of trials.

Reverse correlation: for every recorded cell (a photoreceptor, a T4/T5 cell of one layer, an HS or
VS cell) the response-weighted average of the contrast signal s = L/L₀ − 1 before each response,

    STRF[τ, x] = Σ_{k,t} (r_k[t] − r̄_k) · s̄_k[t − τ, x] / (N σ²),

s̄[·, x] the mean contrast of the ommatidia at offset x from the cell along its axis (a strip one
column wide: lateral distance < 0.6 Δφ, offsets resampled by linear interpolation onto a grid of the
lattice's row spacing), σ² the contrast's variance, N the number of response samples (after
``max(SETTLE_S, max_lag_s)`` of each trial). For a linear stage with frames of one model step this is
its impulse response per step (response units per unit contrast); longer frames (or pixels) smooth it
with their own autocorrelation. Axes: front-to-back for photoreceptors, HS cells and the horizontal
T4/T5 layers, downward for VS cells and the vertical layers; so a front-to-back cell's STRF tilts one
way in space-time and a back-to-front cell's the other. Computed with FFTs over time, all cells at
once (the stimulus first projected onto each cell's offsets by one sparse product).
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.motion_pathways import DIRECTIONS, _direction_vectors
from lobula.tangential_cells import tangential_fields

from .protocols import _specs
from .rig import (LAYER_RECORDS, EphysConfig, Rig, cf_describe, monitors_for, protocol, record_dataset,
                  recording_attrs, trial_seed)

__all__ = ["white_noise", "white_noise_stimulus", "reverse_correlate", "plot_white_noise", "white_noise_summary",
           "NOISE_KINDS", "SETTLE_S", "RECORDABLE"]

#: stimulus noise kinds
NOISE_KINDS = ("binary", "gaussian")
#: time (s) of each trial left out before responses enter the average (the lamina's and the
#: correlators' start-up; at least the longest lag)
SETTLE_S = 0.1
#: what white-noise records: the layers with a place on the lattice
RECORDABLE = ("photoreceptor.v", "t4.response", "t5.response", "hs.v", "vs.v")
#: the axis each recorded layer's offsets lie along (DIRECTIONS name; T4/T5: per layer, below)
_AXIS = {"photoreceptor.v": "front_to_back", "hs.v": "front_to_back", "vs.v": "downward"}
#: the axis of each T4/T5 layer: its preferred direction's line, oriented front-to-back or downward
LAYER_AXIS = {"front_to_back": "front_to_back", "back_to_front": "front_to_back", "upward": "downward",
              "downward": "downward"}
#: the direction of motion a negative space-time tilt means (the response follows the stimulus at
#: larger offsets sooner), per axis; a positive tilt means the opposite one
_TOWARD = {"front_to_back": ("front_to_back", "back_to_front"), "downward": ("downward", "upward")}
#: the lateral half-width of a cell's strip, in Δφ: one column (a hexagonal lattice's oblique
#: neighbours lie 0.5 Δφ aside, the next rows 0.87 Δφ)
_STRIP = 0.6


def white_noise_stimulus(rig: Rig, n_steps: int, seed: int, *, contrast: float = 0.5, noise: str = "binary",
                         pixel_deg: float | None = None, frame_steps: int = 1, mean_luminance: float = 1.0):
    """One trial's noise: luminance (T, n) float32 and its contrast s = L/L₀ − 1 (T, n), numpy.

    n_steps: T, model steps; seed: the trial's seed; pixel_deg: square pixels (degree) on the lattice
    plane (None: one per ommatidium); frame_steps: steps each frame is held. Gaussian luminance below 0 is
    clipped to 0 (rare at the contrasts accepted: ≤ 1/3)."""
    rng = np.random.default_rng(seed)
    n = rig.lattice.n
    if pixel_deg is None:
        pid, P = np.arange(n), n
    else:
        cells = np.floor(np.degrees(rig.lattice.plane) / pixel_deg).astype(np.int64)
        _, pid = np.unique(cells, axis=0, return_inverse=True)
        pid = pid.ravel()
        P = int(pid.max()) + 1
    F = -(-n_steps // frame_steps)
    xi = (rng.integers(0, 2, (F, P)) * 2 - 1).astype(np.float32) if noise == "binary" else \
        rng.standard_normal((F, P)).astype(np.float32)
    s = np.repeat(contrast * xi[:, pid], frame_steps, axis=0)[:n_steps]
    lum = np.maximum(mean_luminance * (1.0 + s), 0.0).astype(np.float32)
    return lum, lum / np.float32(mean_luminance) - np.float32(1.0)


def _axis_vectors(eye: str) -> dict:
    v = _direction_vectors(eye)
    return {"front_to_back": v[DIRECTIONS.index("front_to_back")], "downward": v[DIRECTIONS.index("downward")]}


def offset_grid(rig: Rig, extent_deg: float) -> tuple[np.ndarray, float]:
    """Offsets (degree) of the STRF and their spacing: the smallest row spacing along the two axes (Δφ
    along a hexagonal lattice's horizontal rows, Δφ·√3/2 down its columns), out to ±``extent_deg``."""
    lat = rig.lattice
    steps = np.asarray(lat.axis_vectors, float)
    spacing = []
    for u in _axis_vectors("right").values():
        along, aside = np.abs(steps @ u), np.abs(steps @ np.array([-u[1], u[0]]))
        ok = (along > 1e-9) & (aside < _STRIP)
        spacing.append(along[ok].min() if ok.any() else 1.0)
    g = float(min(spacing)) * lat.dphi_deg
    m = int(math.floor(extent_deg / g + 1e-9))
    return np.arange(-m, m + 1) * g, g


def _projection(rig: Rig, centres: np.ndarray, axes: np.ndarray, offsets: np.ndarray, g: float):
    """Sparse (n, S·O) weights: column (site i, offset o) averages the ommatidia of site i's strip by linear
    interpolation onto offset o (degree). centres (S, 2) degree on the lattice plane; axes (S, 2) unit.
    Also the number of contributing ommatidia per (S, O) (0: the offset lies outside the eye)."""
    import scipy.sparse as sp

    plane = np.degrees(rig.lattice.plane)                                         # (n, 2)
    rel = plane[None, :, :] - centres[:, None, :]                                 # (S, n, 2)
    along = np.einsum("snk,sk->sn", rel, axes)
    aside = np.abs(np.einsum("snk,sk->sn", rel, np.stack([-axes[:, 1], axes[:, 0]], 1)))
    inside = aside < _STRIP * rig.lattice.dphi_deg
    w = np.clip(1.0 - np.abs(along[:, :, None] - offsets[None, None, :]) / g, 0.0, None) * inside[:, :, None]
    tot = w.sum(1)                                                                # (S, O)
    w = w / np.where(tot > 0, tot, 1.0)[:, None, :]
    S, n, O = w.shape
    mat = sp.csr_matrix(np.moveaxis(w, 1, 0).reshape(n, S * O))
    return mat, (w > 0).sum(1)


def reverse_correlate(responses: np.ndarray, stimulus: np.ndarray, proj, site: np.ndarray, n_lags: int,
                      start: int) -> np.ndarray:
    """Response-weighted averages of the projected stimulus, every cell at once.

    responses: (K, T, C) per trial; stimulus: contrast (K, T, n); proj: sparse (n, S·O) from
    :func:`_projection`; site: (C,) each cell's site; n_lags: lags 0 … n_lags − 1 (steps); start: the
    first response step used (≥ n_lags − 1). Returns (n_lags, O, C): Σ r·s̄ / (N σ²), responses
    mean-subtracted per trial and cell, σ² the contrast's variance, N = K·(T − start)."""
    K, T, C = responses.shape
    O = proj.shape[1] // (int(site.max()) + 1)
    nfft = 1 << int(math.ceil(math.log2(T + n_lags)))
    r = np.asarray(responses, dtype=np.float64)[:, start:]
    r = np.concatenate([np.zeros((K, start, C)), r - r.mean(1, keepdims=True)], axis=1)
    var = float(np.var(stimulus, dtype=np.float64))
    acc = np.zeros((n_lags, O, C))
    for k in range(K):  # trials one at a time: the spectra of one trial's cells × offsets stay small
        s_bar = (proj.T @ np.asarray(stimulus[k], dtype=np.float64).T).T.reshape(T, -1, O)   # (T, S, O)
        sf = np.fft.rfft(s_bar, nfft, axis=0)[:, site]                                     # (F, C, O)
        rf = np.fft.rfft(r[k], nfft, axis=0)                                               # (F, C)
        # Σ_t r[t]·s̄[t − τ] = irfft(R·conj(S))[τ]; zero padding to ≥ T + n_lags keeps it acyclic.
        acc += np.fft.irfft(rf[:, :, None] * np.conj(sf), nfft, axis=0)[:n_lags].transpose(0, 2, 1)
    return acc / (K * (T - start) * var)


def _tilt(strf: np.ndarray, lags: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Space-time tilt (s/degree) of STRFs (L, O, ...): the STRF²-weighted regression slope of lag on offset
    (negative: the response follows stimuli at larger offsets sooner, i.e. motion toward them)."""
    w = np.nan_to_num(strf) ** 2
    tot = w.sum((0, 1))
    lag = lags[:, None] + 0 * offsets[None, :]
    off = offsets[None, :] + 0 * lags[:, None]
    ext = (slice(None), slice(None)) + (None,) * (strf.ndim - 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        mo = (w * off[ext]).sum((0, 1)) / tot
        ml = (w * lag[ext]).sum((0, 1)) / tot
        cov = (w * (off[ext] - mo) * (lag[ext] - ml)).sum((0, 1))
        var = (w * (off[ext] - mo) ** 2).sum((0, 1))
        return cov / var


def _cells(rig: Rig, mon, rec_shape) -> tuple[np.ndarray, list]:
    """Centres (X, 2) degree on the lattice plane of a monitor's cells, and the axis name of each of its
    layers (one for a layer-less variable)."""
    lat = rig.lattice
    plane = np.degrees(lat.plane)
    if mon.variable in ("hs.v", "vs.v"):
        w_hs, w_vs = tangential_fields(lat, rig.config.tangential)
        w = w_hs if mon.variable == "hs.v" else w_vs
        cen = w @ plane / w.sum(1, keepdims=True)
        idx = np.arange(len(w)) if mon.neurons is None else np.asarray(mon.neurons)
        return cen[idx], [_AXIS[mon.variable]]
    idx = np.arange(lat.n) if mon.neurons is None else np.asarray(mon.neurons)
    if mon.variable in LAYER_RECORDS:
        layers = range(len(DIRECTIONS)) if mon.layers is None else mon.layers
        return plane[idx], [LAYER_AXIS[DIRECTIONS[i]] for i in layers]
    return plane[idx], [_AXIS[mon.variable]]


def _check(contrast, noise, pixel_deg, frame_s, duration_s, max_lag_s, extent_deg, mean_luminance, dt):
    if noise not in NOISE_KINDS:
        raise ValueError(f"the white noise is one of {NOISE_KINDS}, got {noise!r}")
    if not 0 < contrast <= 1:
        raise ValueError(f"white-noise contrast must lie in (0, 1], got {contrast}")
    if noise == "gaussian" and contrast > 1 / 3:
        raise ValueError(f"Gaussian noise of contrast {contrast:g} drives luminance below 0 in over 0.1 % of samples "
                         f"(clipped, no longer Gaussian); use --contrast ≤ 0.33 or --noise binary")
    for name, v in (("pixel size", pixel_deg), ("the STRF's extent", extent_deg)):
        if v is not None and not (v > 0 and math.isfinite(v)):
            raise ValueError(f"{name} must be a positive number of degrees, got {v}")
    if not (mean_luminance > 0 and math.isfinite(mean_luminance)):
        raise ValueError(f"the mean luminance must be positive, got {mean_luminance}")
    steps = frame_s / dt
    if not (frame_s > 0 and math.isfinite(frame_s)) or steps < 1 - 1e-9 or abs(steps - round(steps)) > 1e-6:
        raise ValueError(f"the noise frame must be a whole number of the {dt:g} s model steps, got {frame_s} s; "
                         f"use --frame {dt:g}, {2 * dt:g}, …")
    if not (max_lag_s > 0 and math.isfinite(max_lag_s)):
        raise ValueError(f"the longest lag must be a positive number of seconds, got {max_lag_s}")
    if not (duration_s > 0 and math.isfinite(duration_s)) or duration_s < max(SETTLE_S, max_lag_s) + 10 * max_lag_s:
        raise ValueError(f"each trial must last at least {max(SETTLE_S, max_lag_s) + 10 * max_lag_s:g} s (the "
                         f"settling time plus ten times the longest lag {max_lag_s:g} s) for a stable average; "
                         f"use a longer --duration or a shorter --max-lag")


def _white_noise(config: EphysConfig, *, contrast: float = 0.5, noise: str = "binary", pixel_deg: float | None = None,
                 frame_s: float | None = None, duration_s: float = 5.0, max_lag_s: float = 0.15,
                 extent_deg: float | None = None, mean_luminance: float = 1.0, record=None,
                 tau_s: float | None = None) -> xr.Dataset:
    """Spatiotemporal white noise on the eye; each recorded cell's spatiotemporal receptive field.

    Parameters
    ----------
    config : EphysConfig
        The rig; ``trials`` noise segments (trial k seeded by ``trial_seed(seed, k)``).
    contrast : float
        c: binary ±c, or the Gaussian's SD relative to the mean (≤ 1/3).
    noise : {"binary", "gaussian"}
    pixel_deg : float, optional
        Square pixels (degree) on the lattice plane; None: one per ommatidium.
    frame_s : float, optional
        Each frame's duration (s), a whole number of model steps (default: one step).
    duration_s : float
        Each trial's duration (s).
    max_lag_s : float
        The longest lag of the STRF (s).
    extent_deg : float, optional
        The STRF's offsets reach ±extent (degree) (default 4 Δφ).
    mean_luminance : float
        L₀.
    record : list of str, optional
        Monitors among :data:`RECORDABLE` (default: photoreceptor.v, t4.response and t5.response of the
        eye's central column and its neighbours).
    tau_s : float, optional
        The correlators' delay τ (s): EMD, T4 and T5.

    Returns
    -------
    xarray.Dataset
        The monitors (trial, time, …), and per monitor ``<var>_strf`` (lag_s, offset_deg, cells…) and
        ``<var>_strf_tilt`` (cells…, s/degree) and ``<var>_strf_motion`` (the direction of motion the tilt
        prefers); ``trial_seed`` (trial).
    """
    from .edges import _centre_columns

    cfg = config or EphysConfig()
    if tau_s is not None:
        cfg = replace(cfg.with_tau(tau_s), on_off=replace(cfg.on_off, tau_delay_t4_s=float(tau_s),
                                                          tau_delay_t5_s=float(tau_s)))
    dt = cfg.circuit.dt_s
    frame_s = dt if frame_s is None else float(frame_s)
    _check(contrast, noise, pixel_deg, frame_s, duration_s, max_lag_s, extent_deg, mean_luminance, dt)
    rig = Rig(cfg)
    extent_deg = 4 * rig.lattice.dphi_deg if extent_deg is None else float(extent_deg)
    cols = ",".join(map(str, _centre_columns(rig)))
    monitors = monitors_for(rig, record, [f"photoreceptor.v[{cols}]", f"t4.response[{cols}]", f"t5.response[{cols}]"])
    bad = [m.variable for m in monitors if m.variable not in RECORDABLE]
    if bad:
        raise ValueError(f"white-noise maps the receptive fields of {', '.join(RECORDABLE)}; {', '.join(bad)} "
                         f"cannot be recorded here (the LC units pool opponent motion, which has no first-order "
                         f"receptive field)")
    n_steps = int(round(duration_s / dt))
    n_lags = int(round(max_lag_s / dt)) + 1
    start = max(int(round(SETTLE_S / dt)), n_lags - 1)
    K = cfg.trials
    seeds = np.array([trial_seed(cfg.seed, k) for k in range(K)], dtype=np.int64)
    lum, con = zip(*(white_noise_stimulus(rig, n_steps, int(s), contrast=contrast, noise=noise, pixel_deg=pixel_deg,
                                          frame_steps=int(round(frame_s / dt)), mean_luminance=mean_luminance)
                     for s in seeds))
    stim = torch.as_tensor(np.stack(lum), device=cfg.device)                        # (K, T, n)
    recs = rig.run(stim, n_steps, monitors, baseline=mean_luminance)
    del stim
    con = np.stack(con)                                                              # (K, T, n)
    offsets, g = offset_grid(rig, extent_deg)
    lags = np.arange(n_lags) * dt
    params = dict(contrast=contrast, noise=noise, pixel_deg=pixel_deg, frame_s=frame_s, duration_s=duration_s,
                  max_lag_s=max_lag_s, extent_deg=extent_deg, mean_luminance=mean_luminance, settle_s=start * dt,
                  monitors=_specs(monitors))
    full = {"ephys": cfg.to_dict(), "protocol": "white-noise", "parameters": params,
            "lattice": {"n_ommatidia": rig.lattice.n, "n_pairs": rig.lattice.n_pairs,
                        "camera": rig.lattice.camera.to_dict()}}
    attrs = recording_attrs("white-noise", full, params, trials=K, seed=cfg.seed, emd_tau_s=cfg.circuit.emd.tau_s,
                            t4_tau_s=cfg.on_off.tau_delay_t4_s, t5_tau_s=cfg.on_off.tau_delay_t5_s, dt_s=dt,
                            dphi_deg=rig.lattice.dphi_deg)
    ds = record_dataset(rig, recs, monitors, {"trial": np.arange(K)}, n_steps, attrs)
    ds.coords["trial_seed"] = ("trial", seeds, {"units": "1", "long_name": "seed of the trial's noise: "
                                                "experiments.ephys.rig.trial_seed(seed, trial), numpy default_rng"})
    ds.coords["lag_s"] = ("lag_s", lags, {"units": "s", "long_name": "time from the stimulus to the response"})
    ds.coords["offset_deg"] = ("offset_deg", offsets, {
        "units": "degree", "long_name": "stimulus offset from the cell along its axis (front-to-back or downward)"})
    if "preferred_direction" in ds.coords:
        ds.coords["strf_axis"] = ("preferred_direction", [LAYER_AXIS[str(d)] for d in ds.preferred_direction.values],
                                  {"long_name": "the axis the layer's STRF offsets lie along (positive this way)"})
    for m in monitors:
        _add_strf(ds, rig, m, recs[m.variable], con, offsets, g, lags, n_lags, start)
    ds.attrs["frame_steps"] = int(round(frame_s / dt))
    return cf_describe(ds)


def _add_strf(ds, rig, mon, rec, con, offsets, g, lags, n_lags, start) -> None:
    """``<var>_strf``, ``<var>_strf_tilt`` and ``<var>_strf_motion`` of one monitor into ``ds``."""
    r = rec.detach().to("cpu").double().numpy()                                       # (K, T, X[, L])
    K, T = r.shape[:2]
    cell_shape = r.shape[2:]
    centres, axes = _cells(rig, mon, cell_shape)
    vec = _axis_vectors(rig.config.on_off.eye)
    names = sorted(set(axes))
    # Sites: every (centre, axis) pair the cells need, centre-major; a cell's site is its centre × its axis.
    site_c = np.repeat(centres, len(names), axis=0)
    site_a = np.tile(np.stack([vec[a] for a in names]), (len(centres), 1))
    proj, count = _projection(rig, site_c, site_a, offsets, g)
    X = len(centres)
    layer_axis = np.array([names.index(a) for a in axes])                             # (L,) or (1,)
    site = (np.arange(X)[:, None] * len(names) + layer_axis[None, :]).ravel()         # (X·L,) row-major
    strf = reverse_correlate(r.reshape(K, T, -1), con, proj, site, n_lags, start)     # (lags, O, X·L)
    strf[:, count[site].T == 0] = np.nan                                              # offsets beyond the eye
    name = mon.name
    cdims = list(ds[name].dims[2:])                                                   # after trial, time
    strf = strf.reshape((n_lags, len(offsets)) + cell_shape)
    units = ds[name].attrs.get("units", "1")
    ds[f"{name}_strf"] = (["lag_s", "offset_deg"] + cdims, strf, {
        "units": units, "long_name": f"{mon.variable} spatiotemporal receptive field: response-weighted average of "
                                     "the stimulus contrast over the contrast variance",
        "note": "per unit contrast; for a linear stage and frames of one step, its impulse response per step",
        "offset_axis": "each layer's strf_axis" if mon.variable in LAYER_RECORDS else axes[0]})
    tilt = _tilt(strf, lags, offsets)
    ds[f"{name}_strf_tilt"] = (cdims, tilt, {
        "units": "s degree-1", "long_name": f"{mon.variable} STRF space-time tilt: the STRF^2-weighted slope of lag "
                                            "on offset (negative: tuned to motion toward positive offsets)"})
    if mon.variable == "photoreceptor.v":   # a photoreceptor has no direction to read from its tilt
        return
    ax = np.broadcast_to(np.array(axes), tilt.shape) if mon.variable in LAYER_RECORDS else \
        np.full(tilt.shape, axes[0])
    toward = np.array([_TOWARD[a][0] for a in ax.ravel()]).reshape(tilt.shape)
    away = np.array([_TOWARD[a][1] for a in ax.ravel()]).reshape(tilt.shape)
    motion = np.where(tilt < 0, toward, np.where(tilt > 0, away, "none"))
    ds[f"{name}_strf_motion"] = (cdims, motion.astype(str), {
        "long_name": f"{mon.variable}: the direction of motion its STRF's tilt prefers"})


white_noise = protocol(_white_noise, EphysConfig)


# =========================================================================== options, summary, figure

def run_from_options(opts: dict):
    """``lobula ephys white-noise`` from the given options: the rig as :func:`experiments.ephys.command.rig_config`
    builds it (its trials are noise segments, for any neuron model), the stimulus keywords."""
    from .command import rig_config

    cfg = rig_config("white-noise", {k: v for k, v in opts.items() if k != "trials"})
    cfg = replace(cfg, trials=int(opts.get("trials", 4)))
    kw = {k2: opts[k] for k, k2 in (("noise", "noise"), ("pixel", "pixel_deg"), ("frame", "frame_s"),
                                     ("duration", "duration_s"), ("max_lag", "max_lag_s"),
                                     ("strf_extent", "extent_deg"), ("tau", "tau_s")) if k in opts}
    if "contrast" in opts:
        if len(opts["contrast"]) != 1:
            raise ValueError(f"white-noise takes one --contrast value, got {opts['contrast']}")
        kw["contrast"] = opts["contrast"][0]
    return white_noise(cfg, record=opts.get("record"), **kw)


def _mean_strf(ds: xr.Dataset, var: str) -> xr.DataArray:
    """A monitor's STRF averaged over its recorded positions (ommatidia or cells), per layer."""
    da = ds[f"{var}_strf"]
    pos = [d for d in da.dims if d not in ("lag_s", "offset_deg", "preferred_direction")]
    return da.mean(pos, skipna=True)


def white_noise_summary(ds: xr.Dataset) -> list[str]:
    """Lines describing a stored ``white-noise`` recording: the stimulus, and each layer's preferred motion
    read from its STRF."""
    p = json.loads(ds.attrs["parameters"])
    lines = [f"{p['noise']} noise, contrast {p['contrast']:g}, frames {p['frame_s'] * 1e3:g} ms, pixels "
             f"{'one per ommatidium' if p['pixel_deg'] is None else str(p['pixel_deg']) + ' degree'}, "
             f"{ds.sizes['trial']} trial(s) × {p['duration_s']:g} s"]
    for v in ds.data_vars:
        if not v.endswith("_strf"):
            continue
        mean = _mean_strf(ds, v[:-5])
        tilt = _tilt(mean.values, ds.lag_s.values, ds.offset_deg.values)
        peak = float(np.nanmax(np.abs(mean.values)))
        if "preferred_direction" in mean.dims:
            parts = [f"{d}: tilt {t * 1e3:+.2f} ms/degree" for d, t in zip(mean.preferred_direction.values, tilt)]
            lines.append(f"{v} (mean over recorded columns), peak |STRF| {peak:.3g}; " + "; ".join(parts))
        else:
            lines.append(f"{v} (mean over recorded cells), peak |STRF| {peak:.3g} at lag "
                         f"{float(mean.lag_s[np.nanargmax(np.nanmax(np.abs(mean.values), 1))]) * 1e3:.0f} ms")
    return lines


def plot_white_noise(ds: xr.Dataset, path) -> list:
    """Space-time images of the STRFs (mean over the recorded columns/cells): one panel per monitor and
    T4/T5 layer, offset along the layer's axis against lag, a diverging colour map centred on 0 with a
    labelled colour bar. PNG and PDF."""
    from .figures import _plt, save_png_and_pdf

    plt = _plt()
    panels = []
    for v in ds.data_vars:
        if v.endswith("_strf"):
            mean = _mean_strf(ds, v[:-5])
            if "preferred_direction" in mean.dims:
                panels += [(v, str(d), mean.sel(preferred_direction=d)) for d in mean.preferred_direction.values]
            else:
                panels.append((v, None, mean))
    ncol = min(4, len(panels))
    nrow = -(-len(panels) // ncol)
    fig, axs = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 3.0 * nrow), layout="constrained", squeeze=False)
    off, lag = ds.offset_deg.values, ds.lag_s.values * 1e3
    g = off[1] - off[0] if len(off) > 1 else 1.0
    extent = (off[0] - g / 2, off[-1] + g / 2, lag[-1], lag[0])
    for a, (v, layer, m) in zip(axs.flat, panels):
        img = m.transpose("lag_s", "offset_deg").values
        top = float(np.nanmax(np.abs(img))) or 1.0
        im = a.imshow(img, aspect="auto", cmap="RdBu_r", vmin=-top, vmax=top, extent=extent, interpolation="nearest")
        var = v[:-5]
        axis = ds.strf_axis.sel(preferred_direction=layer).item() if layer else (
            "downward" if var == "vs_v" else "front_to_back")
        tilt = _tilt(img, ds.lag_s.values, off)
        who = ds[var].attrs.get("monitor", var).split(".")[0].upper()
        a.set_title(f"{who}" + (f" {layer.replace('_', '-')} layer" if layer else "")
                    + f"\ntilt {tilt * 1e3:+.2f} ms/degree", fontsize=9)
        a.set_xlabel(f"offset along {axis.replace('_', '-')} (degree)")
        a.set_ylabel("lag before the response (ms)")
        a.axvline(0, color="0.5", lw=0.5, ls=":")
        cb = fig.colorbar(im, ax=a, shrink=0.85)
        cb.set_label(f"STRF ({ds[v].attrs.get('units', '1')} per unit contrast)", fontsize=7)
        cb.ax.tick_params(labelsize=6)
    for a in list(axs.flat)[len(panels):]:
        a.set_axis_off()
    p = json.loads(ds.attrs["parameters"])
    fig.suptitle(f"White-noise reverse correlation: {p['noise']} noise, contrast {p['contrast']:g}, "
                 f"{ds.sizes['trial']} × {p['duration_s']:g} s (Δφ = {ds.attrs.get('dphi_deg', 0):g}°); "
                 "mean over the recorded columns", fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)
