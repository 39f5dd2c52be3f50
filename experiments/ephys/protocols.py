"""Virtual-electrophysiology protocols and their analyses: stimuli, runs and known answers.

``tf-tuning`` (drifting gratings; known answer: the optimum 1/(2πτ)), ``rf-map``
(local-motion spot mapping of each LC field: centre, size, local preferred directions),
``looming`` (approach vs recession over l/|v|; time relative to collision). Each returns a
self-describing :class:`xarray.Dataset` built by the recording layer
(:mod:`experiments.ephys.rig`). :func:`psth`, :func:`psth_sem` and :func:`raster` work on
any spiking recording.
"""
from __future__ import annotations

import math

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.camera import normalised_to_angles
from lobula.emd import emd_sine_response_discrete
from lobula.motion_pathways import DIRECTIONS
from lobula.lc_geometry import pair_templates
from lobula.photoreceptor import photoreceptor_frequency_response
from lobula.population import FIELD_RECORDS
from stimuli.lattice_stimuli import GratingSource, direction_from_angles, looming_disc, moving_spot, tangent_basis

from .rig import (VARIABLES, EphysConfig, Rig, _neuron_dim, cf_describe, dim_coords, monitors_for, protocol,
                  record_dataset, rig_attrs)

__all__ = ["tf_tuning", "rf_map", "looming", "psth", "psth_sem", "raster", "steady_state_mean", "TF_GRID_HZ",
           "LOOMING_L_OVER_V_S", "BASELINE_S"]

#: tf-tuning's default temporal frequencies (Hz): 16 log-spaced from 0.5 to 32 (steps of 32 %)
TF_GRID_HZ = np.geomspace(0.5, 32.0, 16)
#: looming's default l/|v| values (s)
LOOMING_L_OVER_V_S = (0.01, 0.02, 0.04, 0.08)


# =========================================================================== analysis helpers

def steady_state_mean(x: np.ndarray, t: np.ndarray, freq_hz, settle_s: float) -> np.ndarray:
    """Mean over time (axis −2 of x (..., T, X)) over the largest whole number of stimulus periods after settle_s.

    freq_hz: scalar or broadcastable to x's leading dims (one frequency per condition);
    averaging whole periods removes the 2f ripple of a single correlator. Fewer than one
    period left: the whole window after settle_s.
    """
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    f = np.broadcast_to(np.asarray(freq_hz, dtype=float), x.shape[:-2])
    out = np.empty(x.shape[:-2] + x.shape[-1:])
    span = t[-1] + (t[1] - t[0] if len(t) > 1 else 0.0) - settle_s
    for idx in np.ndindex(f.shape):  # a handful of conditions
        fi = abs(float(f[idx]))
        win = math.floor(span * fi) / fi if fi > 0 and span * fi >= 1 else span
        sel = (t >= settle_s) & (t < settle_s + win - 1e-12)
        out[idx] = x[idx][sel].mean(axis=0)
    return out


def _binned_rate(ds: xr.Dataset, var: str, bin_s: float) -> xr.DataArray:
    """Spike counts of ``var`` summed in bins of ``bin_s`` (whole model steps) as a rate (Hz), per trial."""
    if var not in ds:
        raise ValueError(f"no {var!r} in this recording: record lc.spikes with --neuron-model poisson or lif")
    dt = float(ds[var].attrs.get("dt_s", float(ds.time[1] - ds.time[0])))
    k = max(1, int(round(bin_s / dt)))
    da = ds[var]
    n = da.sizes["time"] // k * k
    out = da.isel(time=slice(0, n)).coarsen(time=k).sum() / (k * dt)
    return out.assign_attrs(units="Hz", bin_s=k * dt)


def psth(ds: xr.Dataset, var: str = "lc_spikes", bin_s: float = 0.01) -> xr.DataArray:
    """Peri-stimulus time histogram (Hz): spikes summed in bins of ``bin_s`` and averaged over trials.

    Bins are labelled by the mean of their steps' times (their centre)."""
    binned = _binned_rate(ds, var, bin_s)
    out = binned.mean("trial") if "trial" in binned.dims else binned
    out.attrs = {"units": "Hz", "long_name": "peri-stimulus time histogram (trial mean)",
                 "bin_s": binned.attrs["bin_s"]}
    return out.rename("psth")


def psth_sem(ds: xr.Dataset, var: str = "lc_spikes", bin_s: float = 0.01) -> xr.DataArray:
    """Standard error of the PSTH across trials (Hz): std(ddof=1)/√K per bin; needs K ≥ 2 trials."""
    binned = _binned_rate(ds, var, bin_s)
    k = binned.sizes.get("trial", 1)
    if k < 2:
        raise ValueError(f"the SEM across trials needs at least 2 trials; this recording has {k} (use --trials N)")
    out = binned.std("trial", ddof=1) / np.sqrt(k)
    out.attrs = {"units": "Hz", "long_name": "standard error of the PSTH across trials",
                 "bin_s": binned.attrs["bin_s"], "trials": k}
    return out.rename("psth_sem")


def raster(ds: xr.Dataset, neuron: int, var: str = "lc_spikes", **sel) -> tuple[np.ndarray, np.ndarray]:
    """Spike times (s) and trial indices of one neuron (``sel`` picks one condition, e.g. contrast=0.5)."""
    da = ds[var].sel(neuron=neuron).sel(**sel) if sel else ds[var].sel(neuron=neuron)
    extra = [d for d in da.dims if d not in ("trial", "time")]
    if extra:
        da = da.isel({d: 0 for d in extra})
    s = da.transpose("trial", "time").values
    tr, ti = np.nonzero(s > 0)
    counts = s[tr, ti].astype(int)
    return np.repeat(da.time.values[ti], counts), np.repeat(da.trial.values[tr], counts)


# =========================================================================== protocols

#: seconds of uniform luminance before a tf-tuning or looming stimulus starts (the PSTH's baseline)
BASELINE_S = 0.3


def _check_baseline(baseline_s: float) -> None:
    if not (baseline_s >= 0 and math.isfinite(baseline_s)):
        raise ValueError(f"the pre-stimulus baseline must be a non-negative number of seconds, got {baseline_s}")


class _AfterBaseline:
    """A streaming stimulus ``src(start, stop)`` (conditions, time, n) preceded by ``n_pre`` frames of
    uniform luminance ``level``: the eye sees the mean luminance, then the stimulus appears."""

    def __init__(self, src, n_pre: int, level: float):
        self.src, self.n_pre, self.level = src, int(n_pre), float(level)

    def __call__(self, start: int, stop: int):
        parts = []
        if start < self.n_pre:
            first = self.src(0, 1)
            shape = list(first.shape)
            shape[-2] = min(stop, self.n_pre) - start
            parts.append(torch.full(shape, self.level, dtype=first.dtype, device=first.device))
        if stop > self.n_pre:
            parts.append(self.src(max(start, self.n_pre) - self.n_pre, stop - self.n_pre))
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-2)


def _specs(monitors) -> list[str]:
    """The monitors as the strings that would request them (written to the recording's parameters)."""
    return [m.variable + ("" if m.neurons is None else f"[{','.join(map(str, m.neurons))}]")
            + ("" if m.layers is None else f"[{','.join(DIRECTIONS[i].replace('_', '-') for i in m.layers)}]")
            for m in monitors]


def _probe_pairs(rig: Rig, kind: str, direction_deg: float, centre_deg=(0.0, 0.0)) -> np.ndarray:
    """For each LC field, the EMD pair nearest its centre that points along the stimulus motion
    (radially outward for rings, along direction_deg for a drum grating)."""
    lat, pop = rig.lattice, rig.population
    mid = lat.pair_midpoint
    az, el = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
    if kind == "radial":
        align, _ = pair_templates(lat, centre_deg, "direction")
    else:
        th = math.radians(direction_deg)
        align = lat.pair_direction @ np.array([math.cos(th), math.sin(th)])
    good = np.nonzero(align > 0.8)[0]
    d = (az[good][None, :] - pop.centres_deg[:, :1]) ** 2 + (el[good][None, :] - pop.centres_deg[:, 1:]) ** 2
    return np.unique(good[np.argmin(d, axis=1)])


def _add_tuning(ds: xr.Dataset, monitors, rig: Rig, tf: np.ndarray, settle_s: float) -> None:
    """Per monitor, ``<var>_tuning`` (and ``_tuning_sem`` over trials) and ``<var>_peak_temporal_frequency_hz``
    from the recording's steady state after ``settle_s`` (s), at the temporal frequencies ``tf`` (Hz)."""
    t = ds.time.values
    for mon in monitors:
        da = ds[mon.name]
        # T4/T5 carry a layer dim after their ommatidia: it joins the leading dims, so time is second to last.
        extra = ["preferred_direction"] if "preferred_direction" in da.dims else []
        nd = [d for d in da.dims if d not in ("time", "trial", *extra)][-1]
        x = da.transpose(..., *extra, "time", nd).values
        f = tf.reshape((-1,) + (1,) * (x.ndim - 3))
        scale = 1.0 / rig.dt if mon.variable == "lc.spikes" else 1.0
        units = "Hz" if mon.variable == "lc.spikes" else da.attrs["units"]
        what = "firing rate from spike counts" if mon.variable == "lc.spikes" else da.attrs["long_name"]
        out_dims = ("temporal_frequency_hz", "contrast", *extra, nd)
        if "trial" in da.dims:  # per trial, then mean and SEM across trials
            ax = da.dims.index("trial")
            per = steady_state_mean(np.moveaxis(x, ax, 2), t, tf[:, None, None], settle_s) * scale  # (TF, C, K, X)
            mean = per.mean(axis=2)
            k = per.shape[2]
            if k > 1:
                ds[f"{mon.name}_tuning_sem"] = (out_dims, per.std(axis=2, ddof=1) / np.sqrt(k),
                                                {"units": units, "long_name": f"SEM across {k} trials of the "
                                                 f"steady-state {what}"})
        else:
            mean = steady_state_mean(x, t, f, settle_s) * scale
        ds[f"{mon.name}_tuning"] = (out_dims, mean,
                                    {"units": units, "long_name": f"steady-state {what} (mean over whole "
                                     f"periods after {settle_s} s, trial mean)"})
        ok = np.isfinite(mean).all(axis=0)
        peak = np.where(ok, tf[np.argmax(np.where(np.isfinite(mean), mean, -np.inf), axis=0)], np.nan)
        ds[f"{mon.name}_peak_temporal_frequency_hz"] = (out_dims[1:], peak, {
            "units": "Hz", "long_name": f"temporal frequency of the largest steady-state {what}"})


def _tf_tuning(config: EphysConfig, *, temporal_frequencies_hz=None, contrasts=(0.5,),
              wavelength_deg: float = 20.0, stimulus: str = "rings", direction_deg: float = 0.0,
              duration_s: float = 2.0, settle_s: float = 0.5, baseline_s: float = BASELINE_S,
              tau_s: float | None = None, record=None, mean_luminance: float = 1.0) -> xr.Dataset:
    """Temporal-frequency tuning: drifting sine gratings at every (TF, contrast).

    stimulus: "rings" (concentric rings expanding about the epipole: every pair of an
    expansion unit sees the same TF) or "grating" (a planar drum grating moving in
    direction_deg). tau_s: the EMD delay (s), overriding the config. record: monitors
    (default: probe EMD pairs — per LC field, the pair nearest its centre along the
    motion — and the LC neurons). Adds ``<var>_tuning`` (steady-state mean over whole
    periods after settle_s, trial-averaged, per TF and contrast), ``peak_temporal_frequency_hz``
    per recorded unit, and ``emd_prediction`` (the exact discrete EMD tuning times the
    photoreceptor transfer, normalised), with attrs ``optimum_hz`` = 1/(2πτ).

    baseline_s: seconds of uniform mean luminance before the grating appears (the PSTH's
    pre-stimulus baseline); the stored time is relative to the grating's onset (negative during
    the baseline) and the steady state is taken after ``settle_s`` past onset.
    """
    cfg = (config or EphysConfig()).with_tau(tau_s)
    rig = Rig(cfg)
    tf = TF_GRID_HZ if temporal_frequencies_hz is None else np.atleast_1d(np.asarray(temporal_frequencies_hz, float))
    c = np.atleast_1d(np.asarray(contrasts, dtype=float))
    if stimulus not in ("rings", "grating"):
        raise ValueError(f"tf-tuning stimulus must be 'rings' or 'grating', got {stimulus!r}")
    if not (np.all(tf > 0) and np.all(np.isfinite(tf))):
        raise ValueError(f"temporal frequencies must be positive (Hz), got {tf.tolist()}")
    nyquist = 0.5 / rig.dt
    if np.any(tf >= nyquist):
        # Sampled every dt, a grating above the Nyquist limit aliases to a lower frequency moving the
        # other way: the response flips sign.
        raise ValueError(f"temporal frequencies must lie below the Nyquist limit {nyquist:g} Hz of the "
                         f"{1.0 / rig.dt:g} Hz stimulus, got {tf[tf >= nyquist].tolist()}")
    if not np.all((c > 0) & (c <= 1)):
        raise ValueError(f"contrasts must lie in (0, 1], got {c.tolist()}")
    _check_baseline(baseline_s)
    if not 0 <= settle_s < duration_s:
        raise ValueError(f"settle_s must lie in [0, duration_s = {duration_s}) s, got {settle_s}; "
                         f"use a longer --duration or a shorter --settle")
    kind = "radial" if stimulus == "rings" else "drum"
    epi = cfg.circuit.population.matched_filter.epipole_deg
    default = [f"emd.response[{','.join(map(str, _probe_pairs(rig, kind, direction_deg, epi)))}]"] + \
        list(rig.default_records())
    monitors = monitors_for(rig, record, default)
    TF, C = np.meshgrid(tf, c, indexing="ij")
    n_steps = int(round(duration_s / rig.dt))
    src = GratingSource(rig.lattice, kind=kind, temporal_freq_hz=TF.ravel(), contrast=C.ravel(),
                        wavelength_deg=wavelength_deg, direction_deg=direction_deg, centre_deg=epi,
                        mean_luminance=mean_luminance, frame_rate_hz=1.0 / rig.dt,
                        device=cfg.device)
    n_pre = int(round(baseline_s / rig.dt))
    recs = rig.run(_AfterBaseline(src, n_pre, mean_luminance), n_pre + n_steps, monitors, baseline=mean_luminance)
    params = dict(temporal_frequencies_hz=tf, contrasts=c, wavelength_deg=wavelength_deg, stimulus=stimulus,
                  direction_deg=direction_deg, duration_s=duration_s, settle_s=settle_s, baseline_s=n_pre * rig.dt,
                  mean_luminance=mean_luminance, stimulus_info=src.info, monitors=_specs(monitors))
    ds = record_dataset(rig, recs, monitors, {"temporal_frequency_hz": tf, "contrast": c}, n_pre + n_steps,
                        rig_attrs(rig, "tf-tuning", params), time_offset_s=n_pre * rig.dt)
    ds["time"].attrs.update(long_name="time since the grating's onset (negative: the mean-luminance baseline)",
                            units="s")
    ds.attrs["baseline_s"] = n_pre * rig.dt
    tau = cfg.circuit.emd.tau_s
    _add_tuning(ds, monitors, rig, tf, settle_s)
    pr = np.abs(photoreceptor_frequency_response(cfg.circuit.photoreceptor, rig.dt, tf)) ** 2
    pred = emd_sine_response_discrete(cfg.circuit.emd, rig.dt, tf, np.pi / 2) * pr
    ds["emd_prediction"] = ("temporal_frequency_hz", pred / pred.max(),
                            {"units": "1", "long_name": "predicted EMD tuning, normalised to its maximum",
                             "note": "exact discrete EMD tuning × |photoreceptor transfer|²"})
    # The gradient-ratio pool divides out the photoreceptor's attenuation (it enters R and G alike).
    lc = pred / pr if cfg.circuit.population.normalisation.kind == "gradient-ratio" else pred
    ds["lc_drive_prediction"] = ("temporal_frequency_hz", lc / lc.max(),
                                 {"units": "1", "long_name": "predicted LC drive tuning (before the neurons' "
                                                             "saturating output), normalised to its maximum"})
    ds.attrs["optimum_hz"] = 1.0 / (2.0 * math.pi * tau)
    return cf_describe(ds)



def _rf_locations(rig: Rig, fields, spacing: float, extent: float) -> np.ndarray:
    """Union of square grids (deg) of half-width ``extent`` about each probed field, inside the eye."""
    pts = []
    for f in fields:
        a0, e0 = rig.population.centres_deg[f]
        g = np.arange(-extent, extent + 1e-9, spacing)
        A, E = np.meshgrid(a0 + g, e0 + g, indexing="xy")
        pts.append(np.stack([A.ravel(), E.ravel()], axis=1))
    pts = np.unique(np.round(np.concatenate(pts) / spacing * 1e6) / 1e6 * spacing, axis=0)
    lat = rig.lattice
    inside = ((pts[:, 0] >= lat.azimuth_deg.min()) & (pts[:, 0] <= lat.azimuth_deg.max())
              & (pts[:, 1] >= lat.elevation_deg.min()) & (pts[:, 1] <= lat.elevation_deg.max()))
    return pts[inside]


def _moments(w: np.ndarray, az: np.ndarray, el: np.ndarray):
    """Centroid (2,) and per-axis variances (2,) of non-negative weights w at points (az, el)."""
    w = np.clip(w, 0.0, None)
    s = w.sum()
    if s <= 0:
        return np.full(2, np.nan), np.full(2, np.nan)
    ca, ce = (w * az).sum() / s, (w * el).sum() / s
    return np.array([ca, ce]), np.array([(w * (az - ca) ** 2).sum() / s, (w * (el - ce) ** 2).sum() / s])


def _rf_responses(rig: Rig, mon, locs: np.ndarray, dirs: np.ndarray, n_steps: int, speed: float, path: float,
                  t_mid: float, size: float, contrast: float, batch: int) -> np.ndarray:
    """Time integral of the monitored field variable per spot passage, (location, direction, field)."""
    cfg, lat, pop = rig.config, rig.lattice, rig.population
    L, D = len(locs), len(dirs)
    ev_loc = np.repeat(np.arange(L), D)
    ev_dir = np.tile(dirs, L)
    if L == 0:
        raise ValueError("no mapping location lies inside the eye; use a larger --extent or other --fields")
    resp = np.empty((L * D, pop.n_fields))
    rec_mon = {mon.variable: None}
    for a in range(0, L * D, batch):  # batches of spot passages, each a condition from rest
        b = min(L * D, a + batch)
        stim, _ = moving_spot(lat, n_steps, centre_deg=locs[ev_loc[a:b]], direction_deg=ev_dir[a:b],
                              speed_deg_s=speed, path_deg=path, t_mid_s=t_mid, size_deg=size, contrast=contrast,
                              frame_rate_hz=1.0 / rig.dt, device=cfg.device)
        out = rig.circuit.run(stim, trials=1, record=rec_mon, baseline=1.0)
        resp[a:b] = out[mon.variable].sum(dim=1).double().cpu().numpy() * rig.dt
    resp = resp.reshape(L, D, pop.n_fields)
    return resp


def _rf_sensitivity(cfg: EphysConfig, locs: np.ndarray, dirs: np.ndarray, resp: np.ndarray):
    """Radial (expansion-direction) sensitivity and local preferred direction (degree), each (location, field)."""
    D = len(dirs)
    # Local motion sensitivity along each field's preferred (radial) direction, and the
    # local preferred direction, from the first Fourier component over directions.
    epi = direction_from_angles(*cfg.circuit.population.matched_filter.epipole_deg)
    q = direction_from_angles(locs[:, 0], locs[:, 1])
    east, south = tangent_basis(q)
    radial = q * (q @ epi)[:, None] - epi[None, :]                      # away from the epipole, ⟂ q
    nrm = np.linalg.norm(radial, axis=1, keepdims=True)
    radial = np.where(nrm > 1e-9, radial / np.maximum(nrm, 1e-9), 0.0)
    rad_ang = np.arctan2(np.sum(radial * south, 1), np.sum(radial * east, 1))       # (L,) image angle
    th = np.radians(dirs)
    z = (resp * np.exp(1j * th)[None, :, None]).sum(axis=1) * 2.0 / D               # (L, F)
    sens = np.real(z * np.exp(-1j * rad_ang)[:, None])
    pref = np.degrees(np.angle(z))
    return sens, pref


def _rf_dataset(rig: Rig, mon, fields: np.ndarray, locs: np.ndarray, dirs: np.ndarray, resp, sens, pref, cen,
                sz) -> xr.Dataset:
    """The rf-map Dataset: responses, sensitivity and preferred-direction maps, mapped centres and sizes per
    field and per push-pull LC unit (no attributes)."""
    pop = rig.population
    L = len(locs)
    units, long_name = VARIABLES[mon.variable]
    iunits = "s" if units == "1" else f"{units} s"
    units_of = np.nonzero(np.isin(pop.unit_field, fields))[0]
    coords = {"location": np.arange(L), "location_azimuth_deg": ("location", locs[:, 0]),
              "location_elevation_deg": ("location", locs[:, 1]), "direction_deg": dirs,
              **dim_coords(rig, "field", fields), **dim_coords(rig, "neuron", units_of)}
    f = fields
    ds = xr.Dataset({
        "rf_response": (("location", "direction_deg", "field"), resp[:, :, f],
                        {"units": iunits, "long_name": f"time integral of the {long_name} per spot passage",
                         "monitor": mon.variable}),
        "rf_sensitivity": (("location", "field"), sens[:, f], {
            "units": iunits, "long_name": "local motion sensitivity along the radial (expansion) direction"}),
        "rf_preferred_direction_deg": (("location", "field"), pref[:, f], {
            "units": "degree", "long_name": "local preferred direction in the image (0 right, 90 down)"}),
        "rf_centre_azimuth_deg": ("field", cen[f, 0], {"units": "degree", "long_name": "mapped RF centre azimuth"}),
        "rf_centre_elevation_deg": ("field", cen[f, 1], {"units": "degree",
                                                         "long_name": "mapped RF centre elevation (positive down)"}),
        "rf_size_deg": ("field", sz[f], {"units": "degree", "long_name": "mapped RF size, probe deconvolved",
                                         "note": "FWHM (gaussian fields) or side (box fields)"}),
    }, coords=coords)
    unit_f = pop.unit_field[units_of]
    pushpull = np.isin(pop.unit_type[units_of], ["expansion", "contraction"])
    for k, v in (("azimuth", cen[:, 0]), ("elevation", cen[:, 1])):
        ds[f"neuron_rf_centre_{k}_deg"] = ("neuron", np.where(pushpull, v[unit_f], np.nan), {
            "units": "degree", "long_name": f"mapped RF centre {k} of the unit's field (push-pull units)"})
    ds["neuron_rf_size_deg"] = ("neuron", np.where(pushpull, sz[unit_f], np.nan), {
        "units": "degree", "long_name": "mapped RF size of the unit's field (push-pull units)"})
    return ds


def _rf_map(config: EphysConfig, *, fields=None, directions: int = 4, spacing_deg: float | None = None,
           extent_deg: float | None = None, spot_size_deg: float | None = None, path_deg: float | None = None,
           speed_deg_s: float | None = None, contrast: float = 1.0, tail_s: float = 0.12, batch: int = 256,
           record=None, tau_s: float | None = None) -> xr.Dataset:
    """Receptive-field maps of LC fields by local-motion spot mapping (Krapp & Hengstenberg 1996 style).

    A small bright spot (FWHM ``spot_size_deg``, default Δφ) crosses each grid location
    (spacing default Δφ, half-width ``extent_deg``, default 1.6 × the field size, about
    every probed field) along a short path (default 2Δφ) at ``speed_deg_s`` (default
    50 Δφ/s), in ``directions`` evenly spaced directions; every passage is one condition
    of the batch, starting from rest. A single flash cannot map a correlator-based unit
    (the two halves of an opponent EMD cancel), a short motion can.

    The response is the time integral of the recorded field variable (default
    ``lc.input``, the matched filter's input before the divisive pool: with the pool, a
    unit reports *how fast* whatever is in its field moves, not where, so the rate map is
    flat-topped at high contrast — Sceniak et al. 1999's contrast-dependent RF size).
    Per location the first Fourier component over directions gives the local motion
    sensitivity along the unit's preferred (radial) direction and the local preferred
    direction. Centre = the weighted centroid of the positive sensitivity map; size =
    the map's second moments minus the probe's own (measured on the EMD array with the
    same spots), as FWHM (Gaussian) or side (box). Output: ``rf_response`` (location,
    direction, field), ``rf_sensitivity`` and ``rf_preferred_direction_deg`` (location,
    field), ``rf_centre_azimuth_deg``, ``rf_centre_elevation_deg``, ``rf_size_deg``
    (field), and the same per LC unit (``neuron``) for expansion/contraction units.
    """
    cfg = (config or EphysConfig()).with_tau(tau_s)
    rig = Rig(cfg)
    lat, pop = rig.lattice, rig.population
    fields = np.arange(pop.n_fields) if fields is None else np.unique(np.atleast_1d(np.asarray(fields, dtype=int)))
    if len(fields) == 0 or fields.min() < 0 or fields.max() >= pop.n_fields:
        raise ValueError(f"fields must be indices in [0, {pop.n_fields}) (this rig has {pop.n_fields} LC fields), "
                         f"got {fields.tolist()}")
    dphi = lat.dphi_deg
    spacing = dphi if spacing_deg is None else float(spacing_deg)
    extent = 1.6 * pop.size_deg if extent_deg is None else float(extent_deg)
    size = dphi if spot_size_deg is None else float(spot_size_deg)
    path = 2.0 * dphi if path_deg is None else float(path_deg)
    speed = 50.0 * dphi if speed_deg_s is None else float(speed_deg_s)
    if not (isinstance(directions, (int, np.integer)) and directions >= 3):
        raise ValueError(f"rf-map needs at least 3 spot directions to separate sensitivity from direction, "
                         f"got {directions!r}")
    dirs = np.arange(directions) * 360.0 / directions
    for name, val in (("spacing_deg", spacing), ("extent_deg", extent), ("spot_size_deg", size),
                      ("path_deg", path), ("speed_deg_s", speed), ("contrast", contrast)):
        if not (val > 0 and math.isfinite(val)):
            raise ValueError(f"rf-map {name} must be a positive number, got {val}")
    locs = _rf_locations(rig, fields, spacing, extent)
    pass_s = path / speed
    n_steps = int(round((pass_s + tail_s) / rig.dt))
    t_mid = pass_s / 2.0
    monitors = monitors_for(rig, record, ["lc.input"])
    if len(monitors) != 1 or monitors[0].variable not in FIELD_RECORDS or monitors[0].neurons is not None:
        raise ValueError(f"rf-map maps one whole-field variable: record one of {', '.join(FIELD_RECORDS)} "
                         f"(no subset; choose fields with --fields), got {[m.variable for m in monitors]}")
    mon = monitors[0]
    resp = _rf_responses(rig, mon, locs, dirs, n_steps, speed, path, t_mid, size, contrast, batch)
    sens, pref = _rf_sensitivity(cfg, locs, dirs, resp)
    psf_mean, psf_var = _probe_psf(rig, dirs, size, path, speed, t_mid, n_steps, contrast)
    cen = np.full((pop.n_fields, 2), np.nan)
    sz = np.full(pop.n_fields, np.nan)
    shape = cfg.circuit.population.fields.shape
    for f in fields:
        c, var = _moments(sens[:, f], locs[:, 0], locs[:, 1])
        cen[f] = c - psf_mean
        v = max(float(np.mean(var - psf_var)), 0.0)
        sz[f] = 2.0 * math.sqrt(2.0 * math.log(2.0) * v) if shape == "gaussian" else math.sqrt(12.0 * v)

    params = dict(fields=fields, directions=dirs, spacing_deg=spacing, extent_deg=extent, spot_size_deg=size,
                  path_deg=path, speed_deg_s=speed, contrast=contrast, tail_s=tail_s, recorded=mon.variable,
                  probe_psf_mean_deg=psf_mean, probe_psf_variance_deg2=psf_var)
    ds = _rf_dataset(rig, mon, fields, locs, dirs, resp, sens, pref, cen, sz)
    ds.attrs.update(rig_attrs(rig, "rf-map", params))
    ds.attrs["dphi_deg"] = dphi
    return cf_describe(ds)


def _probe_psf(rig: Rig, dirs, size, path, speed, t_mid, n_steps, contrast):
    """Centroid offset (2,) and per-axis variance (2,) of one spot passage's footprint on the EMD array.

    The footprint is ∫R_p dt projected on the motion direction (⟨u_p, m̂⟩), over pair
    midpoints, for passages through the eye's centre in every direction — the map a
    unit with uniform weights would measure; the fields' maps are their weights
    convolved with it, so its moments are subtracted.
    """
    lat = rig.lattice
    c = np.array([[lat.azimuth_deg[np.argmin(np.abs(lat.azimuth_deg) + np.abs(lat.elevation_deg))],
                   lat.elevation_deg[np.argmin(np.abs(lat.azimuth_deg) + np.abs(lat.elevation_deg))]]])
    stim, _ = moving_spot(lat, n_steps, centre_deg=np.repeat(c, len(dirs), 0), direction_deg=dirs,
                          speed_deg_s=speed, path_deg=path, t_mid_s=t_mid, size_deg=size, contrast=contrast,
                          frame_rate_hz=1.0 / rig.dt, device=rig.config.device)
    out = rig.circuit.run(stim, trials=1, record=("emd.response",), baseline=1.0)
    R = out["emd.response"].sum(dim=1).double().cpu().numpy() * rig.dt             # (D, P)
    mid = lat.pair_midpoint
    az, el = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
    means, vars_ = [], []
    for k, d in enumerate(np.radians(dirs)):
        w = R[k] * (lat.pair_direction @ np.array([math.cos(d), math.sin(d)]))
        m, v = _moments(w, az, el)
        means.append(m - c[0])
        vars_.append(v)
    return np.nanmean(means, axis=0), np.nanmean(vars_, axis=0)


def _looming(config: EphysConfig, *, l_over_v_s=LOOMING_L_OVER_V_S, duration_s: float = 1.0,
            t_collision_s: float | None = None, centre_deg=None, max_size_deg: float = 60.0, contrast: float = 1.0,
            baseline_s: float = BASELINE_S, record=None, tau_s: float | None = None) -> xr.Dataset:
    """Looming: a dark disc approaching (``2·atan((l/v)/(t_c − t))``) or receding (the time reversal).

    Conditions: dims ``l_over_v_s`` × ``motion`` ∈ {approach, recede}; the disc is
    centred on the epipole unless ``centre_deg`` is given, collision at ``t_collision_s``
    (default 0.8·duration), capped at ``max_size_deg``. Adds ``angular_size_deg``
    (l_over_v_s, motion, time), and per recorded neuron variable ``<var>_peak`` (the
    trial-averaged maximum) and ``<var>_time_of_peak_s`` (relative to collision).

    baseline_s: seconds of the bare background (no disc) before stimulus onset (the PSTH's
    pre-stimulus baseline); the stored time stays relative to collision, so the baseline spans
    ``[−t_collision_s − baseline_s, −t_collision_s)``.
    """
    cfg = (config or EphysConfig()).with_tau(tau_s)
    rig = Rig(cfg)
    lv = np.atleast_1d(np.asarray(l_over_v_s, dtype=float))
    if not np.all(lv > 0):
        raise ValueError(f"l/|v| values must be positive (s), got {lv.tolist()}")
    n_steps = int(round(duration_s / rig.dt))
    tc = 0.8 * duration_s if t_collision_s is None else float(t_collision_s)
    if not 0 < tc <= duration_s:
        raise ValueError(f"the collision time must lie in (0, duration = {duration_s}] s after stimulus onset, "
                         f"got {tc}; use a longer --duration or an earlier --collision-time")
    _check_baseline(baseline_s)
    if not 0 < max_size_deg <= 180:
        raise ValueError(f"the disc's size cap must lie in (0, 180] degrees, got {max_size_deg}")
    centre = cfg.circuit.population.matched_filter.epipole_deg if centre_deg is None else tuple(centre_deg)
    monitors = monitors_for(rig, record, rig.default_records())
    kw = dict(t_collision_s=tc, centre_deg=centre, contrast=contrast, max_size_deg=max_size_deg,
              frame_rate_hz=1.0 / rig.dt, device=cfg.device)
    app, info = looming_disc(rig.lattice, n_steps, l_over_v_s=lv, **kw)
    rec, info_r = looming_disc(rig.lattice, n_steps, l_over_v_s=lv, receding=True, **kw)
    stim = torch.stack([app.reshape(len(lv), n_steps, -1), rec.reshape(len(lv), n_steps, -1)], dim=1)
    stim = stim.reshape(2 * len(lv), n_steps, -1)
    n_pre = int(round(baseline_s / rig.dt))
    stim = torch.cat([torch.ones_like(stim[:, :1]).expand(-1, n_pre, -1), stim], dim=1)  # background, no disc
    recs = rig.run(stim, n_pre + n_steps, monitors, baseline=1.0)
    params = dict(l_over_v_s=lv, duration_s=duration_s, t_collision_s=tc, centre_deg=centre,
                  max_size_deg=max_size_deg, contrast=contrast, baseline_s=n_pre * rig.dt, monitors=_specs(monitors))
    ds = record_dataset(rig, recs, monitors, {"l_over_v_s": lv, "motion": np.array(["approach", "recede"])},
                        n_pre + n_steps, rig_attrs(rig, "looming", params), time_offset_s=tc + n_pre * rig.dt)
    ds["time"].attrs.update(long_name="time relative to collision (negative before; the receding disc "
                                      "is the approach reversed in time)", units="s")
    sizes = np.stack([np.atleast_2d(info["angular_size_deg"]), np.atleast_2d(info_r["angular_size_deg"])], axis=1)
    sizes = np.concatenate([np.zeros(sizes.shape[:-1] + (n_pre,)), sizes], axis=-1)  # no disc in the baseline
    ds["angular_size_deg"] = (("l_over_v_s", "motion", "time"), sizes, {
        "units": "degree", "long_name": f"disc angular size (capped at {max_size_deg:g} degrees)"})
    t = ds.time.values
    for mon in monitors:
        da = ds[mon.name]
        if mon.neurons is not None:  # only the monitor's own neurons: the rest of a shared dim is NaN
            dim = _neuron_dim(mon.variable)
            da = da.sel({dim: list(mon.neurons)})
        if mon.layers is not None:  # and only its own T4/T5 layers
            da = da.isel(preferred_direction=np.isin(ds.preferred_direction.values,
                                                     np.array(DIRECTIONS)[list(mon.layers)]))
        x = da.mean("trial") if "trial" in da.dims else da
        units, what = da.attrs["units"], da.attrs["long_name"]
        if mon.variable == "lc.spikes":  # smooth spike counts into a rate before taking the peak
            x = x.rolling(time=max(1, int(round(0.02 / rig.dt))), center=True, min_periods=1).mean() / rig.dt
            units, what = "Hz", "firing rate (spike counts in a centred 20 ms window)"
        ds[f"{mon.name}_peak"] = x.max("time").assign_attrs(units=units, long_name=f"peak trial-mean {what}")
        ds[f"{mon.name}_time_of_peak_s"] = t[x.argmax("time").values] * xr.ones_like(x.isel(time=0))
        ds[f"{mon.name}_time_of_peak_s"].attrs.update(units="s", long_name=f"time of the peak trial-mean {what}, "
                                                                          "relative to collision")
    ds.attrs["t_collision_s"] = tc
    ds.attrs["baseline_s"] = n_pre * rig.dt
    ds.attrs["time_reference"] = ("collision: time coordinate = time since stimulus onset - t_collision_s; the "
                                  "baseline (no disc) lies before -t_collision_s")
    return cf_describe(ds)



tf_tuning = protocol(_tf_tuning, EphysConfig)
rf_map = protocol(_rf_map, EphysConfig)
looming = protocol(_looming, EphysConfig)


