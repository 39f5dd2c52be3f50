"""The ``velocity-replay`` protocol: record the velocity circuit while the model fly replays footage.

Footage (a synthetic track run, or any footage folder) passes through the EMD front end
(:mod:`lobula.emd_decoding`); the LC pathways and the readout neuron
(:mod:`lobula.readout_neuron`) run over trials (Poisson spikes differ per trial, seeded);
the arithmetic readout runs on the same input for comparison. The recording is a
Dataset with dims ``trial``, ``time``, ``neuron`` (LC fields, or the readout's push–pull
pair) like every other ephys recording.
"""
from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.config import VelocityConfig
from lobula.readout_neuron import ReadoutNeuronConfig, lc_pathways, readout_neuron


def velocity_replay(footage_path: str | Path | None = None, trials: int = 4, seed: int = 0,
                    spiking: bool = True, duration_s: float = 10.0, progress: bool = False) -> xr.Dataset:
    """Run the protocol; without footage, a built-in synthetic run of ``duration_s`` is rendered."""
    import torch

    from experiments.store import provenance
    from experiments.velocity import estimate_velocity
    from stimuli.footage import open_footage
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run

    with tempfile.TemporaryDirectory() as tmp:
        if footage_path is None:
            cfg = TrackRunConfig(profile=None, start_s=2.0, duration_s=duration_s, scale=0.5,
                                 scene=SceneConfig(seed=seed))
            footage_path = make_track_run(Path(tmp) / "replay", cfg, progress=progress)
            source = f"built-in profile, {duration_s} s, scene seed {seed}"
        else:
            source = str(footage_path)
        vcfg = VelocityConfig(front_end="emd")
        ds = estimate_velocity(open_footage(footage_path), vcfg, progress=progress)
    t = ds.time.values
    ncfg = ReadoutNeuronConfig(spiking=spiking, seed=seed)
    r = np.broadcast_to(ds.r.values, (trials,) + ds.r.shape)
    r2 = np.broadcast_to(ds.r2.values, (trials,) + ds.r2.shape)
    a = np.broadcast_to(ds.accel.values, (trials, len(t)))
    out = readout_neuron(t, r, r2, a, ncfg)
    dt = float(np.median(np.diff(t)))
    r_s, _, r_dot = lc_pathways(torch.as_tensor(np.nan_to_num(ds.r.values))[None],
                                torch.as_tensor(np.nan_to_num(ds.r2.values))[None], dt, ncfg)
    field = np.arange(ds.sizes["field"])
    rec = xr.Dataset(
        dict(readout_v=(("trial", "time"), out["v_hat"], {"units": "m/s", "long_name": "readout neuron's velocity"}),
             readout_rate=(("trial", "time", "neuron"), np.stack([out["rate_plus"], out["rate_minus"]], -1),
                           {"units": "Hz", "long_name": "push-pull readout rates"}),
             readout_confidence=(("trial", "time"), out["confidence"], {"units": "1"}),
             lc_r=(("time", "field"), r_s[0].numpy(), {"units": "1/s", "long_name": "LC sustained pathway r"}),
             lc_r_dot=(("time", "field"), r_dot[0].numpy(), {"units": "1/s2", "long_name": "LC transient pathway"}),
             arithmetic_v=("time", ds.v_hat.values, {"units": "m/s", "long_name": "arithmetic readout (zero-phase)"}),
             accel=("time", ds.accel.values, {"units": "m/s2"})),
        coords=dict(trial=np.arange(trials), time=("time", t, {"units": "s"}), neuron=["plus", "minus"],
                    field=field, azimuth_deg=("field", ds.azimuth_deg.values),
                    elevation_deg=("field", ds.elevation_deg.values), size_deg=("field", ds.size_deg.values)))
    if spiking:
        rec["readout_spikes"] = (("trial", "time", "neuron"), np.stack([out["spikes_plus"], out["spikes_minus"]], -1),
                                 {"units": "spikes per step"})
    if "v_true" in ds:
        rec["v_true"] = ("time", ds.v_true.values, {"units": "m/s"})
    full = dict(velocity=json.loads(vcfg.to_json()), readout_neuron=ncfg.to_dict(), trials=trials, seed=seed,
                footage=source)
    rec.attrs.update(provenance(json.dumps(full, sort_keys=True), protocol="velocity-replay", footage=source,
                                trials=trials, seed=seed))
    return rec


def replay_scores(rec: xr.Dataset, skip_s: float = 2.0) -> dict:
    """RMSE of the neuron (trial mean) and of the arithmetic readout against truth after skip_s."""
    if "v_true" not in rec:
        return {}
    m = (rec.time >= rec.time[0] + skip_s).values
    vt = rec.v_true.values[m]
    rm = lambda v: float(np.sqrt(np.nanmean((v[m] - vt) ** 2)))
    return dict(neuron_rmse_m_s=rm(rec.readout_v.mean("trial").values), arithmetic_rmse_m_s=rm(rec.arithmetic_v.values))


def plot_velocity_replay(rec: xr.Dataset, path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from experiments.store import save_figure

    t = rec.time.values
    fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True, gridspec_kw=dict(height_ratios=[3, 1.2, 1.5]),
                             layout="constrained")
    ax = axes[0]
    if "v_true" in rec:
        ax.plot(t, rec.v_true, "k--", lw=1.2, label="truth")
    ax.plot(t, rec.arithmetic_v, color="tab:blue", lw=1.2, label="arithmetic readout (zero-phase)")
    v = rec.readout_v
    ax.plot(t, v.mean("trial"), color="m", lw=1.6, label=f"readout neuron (mean of {rec.sizes['trial']} trials)")
    ax.fill_between(t, v.min("trial"), v.max("trial"), color="m", alpha=0.2, lw=0)
    sc = replay_scores(rec)
    if sc:
        ax.set_title(f"velocity replay: neuron RMSE {sc['neuron_rmse_m_s']:.3f} m/s, arithmetic "
                     f"{sc['arithmetic_rmse_m_s']:.3f} m/s")
    ax.set_ylabel("v (m/s)")
    ax.legend(fontsize=8, loc="upper right")
    ax = axes[1]
    if "readout_spikes" in rec:
        for k, (name, col) in enumerate([("plus", "tab:red"), ("minus", "tab:blue")]):
            s = rec.readout_spikes.sel(neuron=name).values
            tr, ti = np.nonzero(s > 0)
            ax.plot(t[ti], tr + k * (rec.sizes["trial"] + 1), "|", color=col, ms=4, label=f"{name} neuron")
        ax.set_ylabel("trial")
        ax.legend(fontsize=7, loc="upper right")
    else:
        ax.plot(t, rec.readout_rate.isel(trial=0).sel(neuron="plus"), color="tab:red", label="plus")
        ax.plot(t, rec.readout_rate.isel(trial=0).sel(neuron="minus"), color="tab:blue", label="minus")
        ax.set_ylabel("rate (Hz)")
    ax = axes[2]
    order = np.argsort(np.hypot(rec.azimuth_deg.values, rec.elevation_deg.values))
    im = ax.imshow(rec.lc_r.values[:, order].T, aspect="auto", cmap="RdBu_r", vmin=-0.6, vmax=0.6,
                   extent=(t[0], t[-1], len(order), 0), interpolation="nearest")
    ax.set_ylabel("LC field\n(by eccentricity)")
    ax.set_xlabel("time (s)")
    fig.colorbar(im, ax=ax, label="LC r (1/s)")
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return Path(path)
