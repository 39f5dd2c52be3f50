"""The ``velocity-replay`` protocol: record the velocity circuit while the model fly replays footage.

Footage (a synthetic track run, or any footage folder) passes through the EMD front end
(:mod:`lobula.emd_decoding`); the LC pathways and the readout neuron
(:mod:`lobula.readout_neuron`) run over trials (Poisson spikes differ per trial, seeded);
the arithmetic readout runs on the same input for comparison. The recording is a
self-describing Dataset (the attributes every ephys recording carries) with dims
``trial``, ``time`` (frames), ``neuron`` (the readout's push–pull pair), ``field`` (LC
fields) and ``spike_time`` (the spike generator's 1 ms steps: readout spikes are counts
per step, not per frame).
"""
from __future__ import annotations

import json
import re
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.config import VelocityConfig
from lobula.readout_neuron import ReadoutNeuronConfig, lc_pathways, readout_neuron, spike_steps_per_frame

__all__ = ["velocity_replay", "REPLAY_RECORDS"]

#: what velocity-replay can record (the arithmetic readout, truth and acceleration are always stored)
REPLAY_RECORDS = ("readout.v", "readout.rate", "readout.spikes", "readout.confidence", "lc.r", "lc.rdot")


def _replay_records(record, spiking: bool) -> tuple:
    if not record:
        return tuple(r for r in REPLAY_RECORDS if spiking or r != "readout.spikes")
    out = []
    for spec in record:
        name = spec.strip()
        if re.search(r"\[.*\]", name):
            raise ValueError(f"velocity-replay records whole variables, no subsets: {spec!r}; "
                             f"use one of {', '.join(REPLAY_RECORDS)}")
        if name == "readout.spikes" and not spiking:
            raise ValueError("cannot record 'readout.spikes': the rate readout neuron has no spikes; use "
                             "--neuron-model poisson")
        if name not in REPLAY_RECORDS:
            raise ValueError(f"velocity-replay cannot record {spec!r}; it records {', '.join(REPLAY_RECORDS)} "
                             f"(the LC rig's monitors such as lc.spikes[expansion] belong to tf-tuning, rf-map "
                             f"and looming)")
        if name in out:
            raise ValueError(f"record each variable once; repeated: {name}")
        out.append(name)
    return tuple(out)


def velocity_replay(footage_path: str | Path | None = None, trials: int = 4, seed: int = 0,
                    spiking: bool = True, duration_s: float = 10.0, progress: bool = False,
                    tau_s: float | None = None, dphi_deg: float | None = None,
                    field_size_deg: float | None = None, record=None) -> xr.Dataset:
    """Run the protocol; without footage, a built-in synthetic run of ``duration_s`` is rendered.

    tau_s, dphi_deg: the EMD front end's delay (s) and interommatidial angle (degree);
    field_size_deg: the LC fields' size (degree); None keeps the velocity pipeline's
    defaults. record: names from :data:`REPLAY_RECORDS` (default: all).
    """
    import torch

    from experiments.ephys.rig import cf_describe, recording_attrs
    from experiments.velocity import estimate_velocity
    from stimuli.footage import open_footage
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run

    if not (isinstance(trials, int) and trials >= 1):
        raise ValueError(f"trials must be a positive integer, got {trials!r}")
    if not spiking and trials != 1:
        raise ValueError(f"trials={trials}: the rate readout is deterministic; use trials=1 or spiking=True")
    want = _replay_records(record, spiking)
    vcfg = VelocityConfig(front_end="emd")
    if tau_s is not None:
        vcfg = replace(vcfg, emd=replace(vcfg.emd, emd=replace(vcfg.emd.emd, tau_s=float(tau_s))))
    if dphi_deg is not None:
        vcfg = replace(vcfg, emd=replace(vcfg.emd, lattice=replace(vcfg.emd.lattice, dphi_deg=float(dphi_deg))))
    if field_size_deg is not None:
        vcfg = replace(vcfg, fields=replace(vcfg.fields, size_deg=float(field_size_deg)))
    with tempfile.TemporaryDirectory() as tmp:
        if footage_path is None:
            cfg = TrackRunConfig(profile=None, start_s=2.0, duration_s=duration_s, scale=0.5,
                                 scene=SceneConfig(seed=seed))
            footage_path = make_track_run(Path(tmp) / "replay", cfg, progress=progress)
            source = f"built-in profile, {duration_s} s, scene seed {seed}"
        else:
            source = str(footage_path)
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
    data = {}
    if "readout.v" in want:
        data["readout_v"] = (("trial", "time"), out["v_hat"], {"units": "m s-1",
                             "long_name": "readout neuron's forward velocity (decoded; NaN where not confident)"})
    if "readout.rate" in want:
        data["readout_rate"] = (("trial", "time", "neuron"), np.stack([out["rate_plus"], out["rate_minus"]], -1),
                                {"units": "Hz", "long_name": "push-pull readout neurons' firing rate"})
    if "readout.confidence" in want:
        data["readout_confidence"] = (("trial", "time"), out["confidence"],
                                      {"units": "1", "long_name": "readout neuron's confidence (low-passed trust)"})
    if "lc.r" in want:
        data["lc_r"] = (("time", "field"), r_s[0].numpy(), {"units": "s-1",
                        "long_name": "LC sustained pathway: low-passed expansion rate r"})
    if "lc.rdot" in want:
        data["lc_r_dot"] = (("time", "field"), r_dot[0].numpy(), {"units": "s-2",
                            "long_name": "LC transient pathway: rate of change of r"})
    data["arithmetic_v"] = ("time", ds.v_hat.values, {"units": "m s-1",
                            "long_name": "arithmetic readout's forward velocity (zero-phase), for comparison"})
    data["accel"] = ("time", ds.accel.values, {"units": "m s-2", "long_name": "forward acceleration (haltere input)"})
    coords = dict(trial=("trial", np.arange(trials), {"long_name": "trial index", "units": "1"}),
                  time=("time", t, {"units": "s", "long_name": "time of the footage frame"}),
                  neuron=("neuron", ["plus", "minus"], {"long_name": "readout neuron (push-pull pair)"}),
                  field=("field", field, {"units": "1", "long_name": "LC receptive-field index"}),
                  azimuth_deg=("field", ds.azimuth_deg.values, {"units": "degree",
                               "long_name": "receptive-field centre azimuth"}),
                  elevation_deg=("field", ds.elevation_deg.values, {"units": "degree",
                                 "long_name": "receptive-field centre elevation (positive down)"}),
                  size_deg=("field", ds.size_deg.values, {"units": "degree", "long_name": "receptive-field size"}))
    sub = spike_steps_per_frame(dt, ncfg)
    spike_dt = dt / sub
    if spiking and "readout.spikes" in want:
        st = t[0] + np.arange(len(t) * sub) * spike_dt
        coords["spike_time"] = ("spike_time", st, {"units": "s", "long_name": "start of the spike generator's step"})
        data["readout_spikes"] = (("trial", "spike_time", "neuron"),
                                  np.stack([out["spikes_plus"], out["spikes_minus"]], -1).astype(np.uint16),
                                  {"units": "1", "long_name": "readout neurons' spike count per spike-generator step",
                                   "neuron_model": "poisson", "dt_s": spike_dt,
                                   "neuron_parameters": json.dumps(ncfg.to_dict(), sort_keys=True)})
    if "v_true" in ds:
        data["v_true"] = ("time", ds.v_true.values, {"units": "m s-1", "long_name": "true forward velocity"})
    rec = xr.Dataset(data, coords=coords)
    full = dict(velocity=json.loads(vcfg.to_json()), readout_neuron=ncfg.to_dict(), trials=trials, seed=seed,
                footage=source, record=list(want))
    params = dict(footage=source, duration_s=duration_s if "built-in" in source else None, record=list(want))
    rec.attrs.update(recording_attrs(
        "velocity-replay", full, params, footage=source, dt_s=spike_dt, frame_interval_s=dt, trials=trials,
        trials_requested=trials, trials_note="", seed=seed, emd_tau_s=vcfg.emd.emd.tau_s,
        neuron_model="poisson" if spiking else "rate", neuron_parameters=json.dumps(ncfg.to_dict(), sort_keys=True)))
    return cf_describe(rec)
