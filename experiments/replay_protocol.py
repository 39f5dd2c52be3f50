"""The ``velocity-replay`` protocol: record the velocity circuit while the model fly replays footage.

Footage (a synthetic track run, or any footage folder) passes through the EMD front end
(:mod:`lobula.emd_front_end`); the LC pathways and the readout neuron
(:mod:`lobula.readout_neuron`) run over trials (Poisson spikes differ per trial, seeded);
the arithmetic readout runs on the same input for comparison. The recording is a
self-describing Dataset (the attributes every ephys recording carries) with dims
``trial``, ``time`` (frames), ``neuron`` (the readout's push–pull pair), ``field`` (LC
fields), ``unit`` (every spiking output neuron: ``population`` pairs, each with its own train) and
``spike_time`` (the spike generator's steps, a whole number per frame: frame interval /
round(frame interval / 1 ms), e.g. 1.0101 ms at 30 frames/s; readout spikes are counts per step, not
per frame; a spike's time is its step's start). Trial k's noise is seeded by (seed, k) alone.

On the compound eye (``lobula ephys velocity-replay --eye fly``, :func:`eye_velocity_replay`)
the footage is eye footage (``lobula scene OUT --eye fly``) and the circuit is
:func:`experiments.eye_velocity.estimate_eye_velocity`'s, causal throughout: the LC fields'
expansion rates ρ = v/D (50 Hz readout steps) and the readout's ṙ are what drive the readout, whose
v̂ the spiking output neurons (10 push–pull pairs, leaky integrate-and-fire by default) carry on each
trial — the same units, parameters and numbers as ``lobula eye-velocity --readout spikes``.
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
from lobula.readout import answered_velocity
from lobula.readout_neuron import ReadoutNeuronConfig, lc_pathways, readout_neuron, spike_steps_per_frame

__all__ = ["velocity_replay", "eye_velocity_replay", "REPLAY_RECORDS"]

#: what velocity-replay can record (the arithmetic readout, truth and acceleration are always stored)
REPLAY_RECORDS = ("readout.v", "readout.rate", "readout.spikes", "readout.confidence", "lc.r", "lc.rdot")


def _replay_records(record, spiking: bool, eye: bool = False) -> tuple:
    # The eye's readout states its uncertainty as v_std (always stored), not a readout neuron's confidence.
    avail = tuple(r for r in REPLAY_RECORDS if not (eye and r == "readout.confidence"))
    if not record:
        return tuple(r for r in avail if spiking or r != "readout.spikes")
    out = []
    for spec in record:
        name = spec.strip()
        if re.search(r"\[.*\]", name):
            raise ValueError(f"velocity-replay records whole variables, no subsets: {spec!r}; "
                             f"use one of {', '.join(REPLAY_RECORDS)}")
        if name == "readout.spikes" and not spiking:
            raise ValueError("cannot record 'readout.spikes': the rate readout neuron has no spikes; use "
                             "--neuron-model " + ("lif or poisson" if eye else "poisson"))
        if eye and name == "readout.confidence":
            raise ValueError("cannot record 'readout.confidence' on the compound eye: its readout states its "
                             "uncertainty as a standard deviation (always stored, arithmetic_v_std); record "
                             f"{', '.join(avail)}")
        if name not in REPLAY_RECORDS:
            raise ValueError(f"velocity-replay cannot record {spec!r}; it records {', '.join(REPLAY_RECORDS)} "
                             f"(the LC rig's monitors such as lc.spikes[expansion] belong to tf-tuning, rf-map "
                             f"and looming)")
        if name in out:
            raise ValueError(f"record each variable once; repeated: {name}")
        out.append(name)
    return tuple(out)


def per_trial(run, trials: int, ncfg) -> dict[str, np.ndarray]:
    """``run(config)`` once per trial, trial k with the seed :func:`experiments.ephys.rig.trial_seed`
    (config.seed, k), stacked along a leading trial dim: trial k's spikes are the same whatever the
    number of trials."""
    from experiments.ephys.rig import trial_seed

    outs = [run(replace(ncfg, seed=trial_seed(ncfg.seed, k))) for k in range(trials)]
    return {key: np.stack([np.asarray(o[key]) for o in outs]) for key in outs[0]}


def velocity_replay(footage_path: str | Path | None = None, trials: int = 4, seed: int = 0,
                    spiking: bool = True, duration_s: float = 10.0, progress: bool = False,
                    tau_s: float | None = None, dphi_deg: float | None = None,
                    field_size_deg: float | None = None, record=None) -> xr.Dataset:
    """Run the protocol; without footage, a built-in synthetic run of ``duration_s`` is rendered.

    tau_s, dphi_deg: the EMD front end's delay (s) and interommatidial angle (degree);
    field_size_deg: the LC fields' size (degree); None keeps the velocity pipeline's
    defaults. record: names from :data:`REPLAY_RECORDS` (default: all).
    """
    from lobula._optional import torch

    from experiments.ephys.rig import cf_describe, recording_attrs
    from lobula.velocity import estimate_velocity
    from lobula.readers import open_footage
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
    out = per_trial(lambda c: readout_neuron(t, ds.r.values, ds.r2.values, ds.accel.values, c), trials, ncfg)
    dt = float(np.median(np.diff(t)))
    r_s, _, r_dot = lc_pathways(torch.as_tensor(np.nan_to_num(ds.r.values))[None],
                                torch.as_tensor(np.nan_to_num(ds.r2.values))[None], dt, ncfg)
    data = {}
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
    rec, spike_dt = _replay_dataset(ds, want, out, ncfg, spiking, data, "readout neuron's forward velocity (decoded; "
                                    "NaN where not confident)")
    full = dict(velocity=json.loads(vcfg.to_json()), readout_neuron=ncfg.to_dict(), trials=trials, seed=seed,
                footage=source, record=list(want))
    params = dict(footage=source, duration_s=duration_s if "built-in" in source else None, record=list(want))
    rec.attrs.update(recording_attrs(
        "velocity-replay", full, params, footage=source, dt_s=spike_dt,
        frame_interval_s=dt, trials=trials, trials_requested=trials, trials_note="", seed=seed,
        emd_tau_s=vcfg.emd.emd.tau_s, neuron_model="poisson" if spiking else "rate",
        neuron_parameters=json.dumps(ncfg.to_dict(), sort_keys=True)))
    return cf_describe(rec)


def _replay_dataset(ds: xr.Dataset, want, out: dict, ncfg: ReadoutNeuronConfig, spiking: bool, data: dict,
                    v_long_name: str) -> tuple[xr.Dataset, float]:
    """The recording both front ends share: the output neurons' decoded v (trial, time), rates (trial, time,
    neuron) and every output neuron's spike counts (trial, spike_time, unit) as ``want`` names them, beside
    ``data`` (the front end's own variables), the acceleration and the truth, on the velocity Dataset ``ds``'s
    times and fields.
    ``out``: the output neurons' arrays (trials, ...) (:func:`lobula.readout_neuron.readout_neuron` or
    :func:`lobula.readout_neuron.spiking_output`). Returns the Dataset and the spike generator's step (s)."""
    t = ds.time.values
    dt = float(np.median(np.diff(t)))
    trials = out["rate_plus"].shape[0]
    data = dict(data)
    if "readout.v" in want:
        data["readout_v"] = (("trial", "time"), out["v_hat"], {"units": "m s-1", "long_name": v_long_name})
    if "readout.rate" in want:
        data["readout_rate"] = (("trial", "time", "neuron"), np.stack([out["rate_plus"], out["rate_minus"]], -1),
                                {"units": "Hz", "long_name": "push-pull readout neurons' firing rate"})
    data["accel"] = ("time", ds.accel.values, {"units": "m s-2", "long_name": "forward acceleration (haltere input)"})
    coords = dict(trial=("trial", np.arange(trials), {"long_name": "trial index", "units": "1"}),
                  time=("time", t, {"units": "s", "long_name": "time of the footage frame"}),
                  neuron=("neuron", ["plus", "minus"], {"long_name": "readout neuron (push-pull pair)"}),
                  field=("field", np.arange(ds.sizes["field"]), {"units": "1", "long_name": "LC receptive-field index"}),
                  azimuth_deg=("field", ds.azimuth_deg.values, {"units": "degree",
                               "long_name": "receptive-field centre azimuth"}),
                  elevation_deg=("field", ds.elevation_deg.values, {"units": "degree",
                                 "long_name": "receptive-field centre elevation (positive down)"}),
                  size_deg=("field", ds.size_deg.values, {"units": "degree", "long_name": "receptive-field size"}))
    sub = spike_steps_per_frame(dt, ncfg)
    spike_dt = dt / sub
    if spiking and "readout.spikes" in want:
        st = t[0] + np.arange(len(t) * sub) * spike_dt
        n = int(ncfg.population)
        coords["spike_time"] = ("spike_time", st, {
            "units": "s", "long_name": f"start of the spike generator's step (a spike's time; steps of "
                                       f"{spike_dt * 1e3:.5g} ms: the frame interval / {sub})"})
        # Every output neuron its own train (a unit an experimenter would isolate); the decoder reads
        # the population of each sign pooled (sum over the units of one unit_neuron).
        coords["unit"] = ("unit", [f"{sign} {i}" for sign in ("plus", "minus") for i in range(n)],
                          {"long_name": "output neuron: its sign and its pair's index"})
        coords["unit_neuron"] = ("unit", ["plus"] * n + ["minus"] * n,
                                 {"long_name": "which of the push-pull pair the unit is (plus carries v > 0)"})
        data["readout_spikes"] = (("trial", "spike_time", "unit"), out["spikes_units"].astype(np.uint16),
                                  {"units": "1", "long_name": "each output neuron's spike count per spike-generator "
                                   "step", "neuron_model": ncfg.spike_model, "dt_s": spike_dt,
                                   "neuron_parameters": json.dumps(ncfg.to_dict(), sort_keys=True)})
    if "v_true" in ds:
        data["v_true"] = ("time", ds.v_true.values, {"units": "m s-1", "long_name": "true forward velocity"})
    return xr.Dataset(data, coords=coords), spike_dt


def _eye_replay_config(tau_s: float | None, field_size_deg: float | None, rotation: str | None,
                       haltere_gain: str | float | None):
    """The eye pipeline's configuration for a replay: EMD delay τ (s), LC field FWHM (degree), rotation
    handling and haltere gain as ``lobula eye-velocity`` takes them (None: its defaults)."""
    import argparse

    from experiments.eye_velocity import EyeVelocityConfig, apply_eye_options

    ecfg = EyeVelocityConfig()  # the rates readout; its v̂ is carried by the replay's output neurons, per trial
    if tau_s is not None:
        ecfg.circuit.emd = replace(ecfg.circuit.emd, tau_s=float(tau_s))
    if field_size_deg is not None:
        ecfg.circuit.fields = replace(ecfg.circuit.fields, size_deg=float(field_size_deg))
    ecfg = apply_eye_options(ecfg, argparse.Namespace(rotation=rotation, haltere_gain=None if haltere_gain is None
                                                      else str(haltere_gain)))
    ecfg.circuit.__post_init__()
    ecfg.__post_init__()
    return ecfg


def _eye_replay_run(footage_path, ecfg, duration_s: float, seed: int, dphi_deg: float | None,
                    progress: bool) -> tuple:
    """The eye pipeline on eye footage, or on a built-in run rendered for it (``footage_path`` None);
    returns (velocity Dataset, the footage's description, the eye's summary)."""
    from experiments.eye_velocity import estimate_eye_velocity
    from lobula.compound_eye import CompoundEyeConfig
    from stimuli.eye import make_eye_run, open_eye_footage
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig

    with tempfile.TemporaryDirectory() as tmp:
        if footage_path is None:
            run = TrackRunConfig(profile=None, start_s=2.0, duration_s=duration_s, scale=0.5,
                                 scene=SceneConfig(seed=seed))
            eye = CompoundEyeConfig() if dphi_deg is None else CompoundEyeConfig(dphi_deg=float(dphi_deg))
            footage_path = make_eye_run(Path(tmp) / "replay-eye", run, eye, 500.0, progress=progress, cast_every=2)
            source = f"built-in profile, {duration_s} s, scene seed {seed}, compound eye at 500 Hz"
        else:
            source = str(footage_path)
        fo = open_eye_footage(footage_path)
        ds = estimate_eye_velocity(fo, ecfg, progress=progress)
        eye_summary = fo.eye.summary()
    return ds, source, eye_summary


def _eye_replay_variables(ds: xr.Dataset, want) -> dict:
    """The eye pipeline's own variables the recording carries: LC rates and their derivative (as asked),
    the rates readout's v̂ and v_std, and which fields it used."""
    data = {}
    if "lc.r" in want:
        data["lc_r"] = (("time", "field"), ds.r.values, {"units": "s-1", "long_name": "LC field expansion rate v/D "
                        "(the field's fit, per readout step; what the readout takes)"})
    if "lc.rdot" in want:
        data["lc_r_dot"] = (("time", "field"), ds.r_dot.values, {"units": "s-2",
                            "long_name": "rate of change of the LC field's expansion rate, as the readout takes it "
                                         "(NaN where the field is not used)"})
    data["arithmetic_v"] = ("time", ds.v_hat.values, {"units": "m s-1",
                            "long_name": "readout's forward velocity (rates, causal) that the output neurons carry"})
    data["arithmetic_v_std"] = ("time", ds.v_std.values, {"units": "m s-1", "long_name": ds.v_std.attrs["long_name"]})
    data["lc_used"] = (("time", "field"), ds.field_used.values.astype(np.int8),
                       {"units": "1", "long_name": ds.field_used.attrs["long_name"]})
    return data


def eye_velocity_replay(footage_path: str | Path | None = None, trials: int = 4, seed: int = 0,
                        spike_model: str | None = "lif", duration_s: float = 10.0, progress: bool = False,
                        tau_s: float | None = None, dphi_deg: float | None = None,
                        field_size_deg: float | None = None, rotation: str | None = None,
                        haltere_gain: str | float | None = None, record=None) -> xr.Dataset:
    """Record the compound eye's velocity circuit while the fly replays eye footage (module docstring).

    footage_path: an eye-footage folder; None renders a built-in synthetic run of ``duration_s``
    (frontal panels, scene seed ``seed``) onto the default eyes at 500 Hz (cast at 250 Hz, as
    ``lobula scene --eye fly``; about 5 s of CPU per second of flight with four trials). spike_model: the output
    neurons, "lif" (the eye's default) or "poisson", each trial with its own noise from ``seed``;
    None: their rates only (deterministic, one trial). tau_s: the EMD delay (s); field_size_deg:
    the LC fields' FWHM (degree); dphi_deg: the interommatidial angle of the built-in run (eye
    footage keeps the Δφ it was rendered at). rotation, haltere_gain: the circuit's rotation handling and
    the haltere gain's prior, as ``lobula eye-velocity --rotation / --haltere-gain`` take them (None:
    haltere, natural). record: names from :data:`REPLAY_RECORDS` but readout.confidence (default: all
    of them).
    """
    from experiments.ephys.rig import cf_describe, recording_attrs
    from experiments.eye_velocity import readout_offset
    from lobula.readout_neuron import SPIKE_MODELS, spiking_output

    spiking = spike_model is not None
    if spiking and spike_model not in SPIKE_MODELS:
        raise ValueError(f"spike_model must be one of {', '.join(SPIKE_MODELS)} or None (rates), got {spike_model!r}")
    if not (isinstance(trials, int) and trials >= 1):
        raise ValueError(f"trials must be a positive integer, got {trials!r}")
    if not spiking and trials != 1:
        raise ValueError(f"trials={trials}: the output neurons' rates are deterministic; use trials=1 or a spike model")
    if footage_path is not None and dphi_deg is not None:
        raise ValueError("dphi_deg: eye footage keeps the Δφ it was rendered at (`lobula scene OUT --eye fly --dphi "
                         "…`); give it only for the built-in run")
    want = _replay_records(record, spiking, eye=True)
    ecfg = _eye_replay_config(tau_s, field_size_deg, rotation, haltere_gain)
    ds, source, eye_summary = _eye_replay_run(footage_path, ecfg, duration_s, seed, dphi_deg, progress)
    t = ds.time.values
    dt = float(np.median(np.diff(t)))
    ncfg = replace(ecfg.neuron, spiking=spiking, seed=seed, spike_model=spike_model or ecfg.neuron.spike_model)
    # As `lobula eye-velocity --readout spikes`: the readout's v̂ where observable (elsewhere NaN: the neurons
    # fall silent), the decoder's lead from the accelerometer less the offset that v̂ implies.
    v_hat, a = answered_velocity(ds), ds.accel.values
    a_lead = a - readout_offset(t, v_hat, a, ecfg.lead_offset_tau_s) if ecfg.lead_offset_tau_s else a
    out = per_trial(lambda c: spiking_output(t, v_hat, a_lead, c), trials, ncfg)
    out["v_hat"] = (np.where(ds.observable.values, out["v_dec"], np.nan) if spiking
                    else np.broadcast_to(ds.v_hat.values, (trials, len(t))).copy())
    data = _eye_replay_variables(ds, want)
    rec, spike_dt = _replay_dataset(ds, want, out, ncfg, spiking, data,
                                    f"output neurons' decoded forward velocity ({SPIKE_MODELS[ncfg.spike_model]}, "
                                    "causal; NaN where the readout is unobservable)" if spiking else
                                    "readout's forward velocity the output neurons' rates carry (no spikes)")
    rec = rec.assign_coords(eye=("field", ds.eye.values, {"long_name": "eye of the LC field"}))
    full = dict(eye_velocity=json.loads(ecfg.to_json()), output_neurons=ncfg.to_dict(), trials=trials, seed=seed,
                footage=source, record=list(want), eye=eye_summary)
    params = dict(footage=source, duration_s=duration_s if "built-in" in source else None, record=list(want))
    rec.attrs.update(recording_attrs(
        "velocity-replay", full, params, eye="fly", footage=source, dt_s=spike_dt,
        frame_interval_s=dt, trials=trials, trials_requested=trials,
        trials_note="" if spiking else "the output neurons' rates are deterministic: one trial",
        seed=seed, emd_tau_s=ecfg.circuit.emd.tau_s, neuron_model=ncfg.spike_model if spiking else "rate",
        neuron_parameters=json.dumps(ncfg.to_dict(), sort_keys=True),
        same_circuit_as="experiments.eye_velocity.EyeVelocityConfig (lobula eye-velocity --readout spikes)"))
    return cf_describe(rec)
