"""Neurodata Without Borders (NWB) export of an ephys recording, with pynwb.

Physiologists share recordings as NWB (pynwb, NWB widgets, DANDI). A recording's
conditions × trials were simulated side by side from t = 0; in the NWB file they are laid
end to end on one session timeline, each (condition, trial) an epoch of the recording's
duration plus a 0.5 s gap, in the Dataset's order (conditions row-major, then trials):

- **trials** (TimeIntervals): one row per epoch — start/stop (s), the condition's
  stimulus values (one column per stimulus dim), ``trial_index``, ``condition_index`` and
  ``stimulus_time_zero`` (the session time where the recording's own time coordinate is 0:
  stimulus onset, or collision for looming). rf-map's spot passages are its trials, with
  each passage's per-field response as a column.
- **units** (Units): every recorded spiking unit (LC units, readout neurons) with its spike
  times over the session — the start of the model step each spike fell in, as the NetCDF's time
  (``time`` or ``spike_time``) coordinate — and columns
  ``unit_type``, ``field_index``, ``rf_azimuth_deg``, ``rf_elevation_deg``, ``rf_size_deg``
  (NaN where a unit has no receptive field).
- **acquisition**: every other time-resolved variable (rates, membrane potentials,
  photoreceptor and EMD signals, LC pathways) as a TimeSeries (time × channel) with
  explicit timestamps (starting_time and rate where the recording is one epoch); a variable without a trial dim (the deterministic front end)
  covers each condition's first epoch.
- **processing/analysis**: every variable without time (tuning curves, RF estimates,
  looming peaks) as a long-form DynamicTable (one column per dim coordinate, plus value).
- The file's ``notes`` hold the recording's attributes as JSON (configuration, protocol
  parameters, version, commit, command line); ``source_script`` the command line.

:func:`write_nwb` writes atomically (temporary name, then rename); :func:`read_nwb_spike_counts`
and :func:`read_nwb_series` read the numbers back on the recording's grid (the round trip).
"""
from __future__ import annotations

import gc
import json
import uuid
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import xarray as xr

from .store import atomic_path, signals_deferred

__all__ = ["write_nwb", "read_nwb_spike_counts", "read_nwb_series", "epoch_layout", "GAP_S"]

GAP_S = 0.5
_TIME_DIMS = ("time", "spike_time")
_CHANNEL_DIMS = ("neuron", "unit", "field", "ommatidium", "pair")
_SPIKES = ("lc_spikes", "readout_spikes")
#: time-resolved variables that describe the stimulus: written as templates under /stimulus
_STIMULUS_VARS = ("angular_size_deg",)


def _stimulus_templates(nwb, ds: xr.Dataset, lay: dict) -> None:
    """The stimulus of each condition as a template under ``/stimulus/templates`` (time × condition,
    conditions in the trials table's ``condition_index`` order, the recording's own time from its first
    sample); the trials' stimulus columns name each condition's parameters.

    looming: the disc's angular size (degree). tf-tuning: the grating's luminance at one point of the
    eye (mean · (1 + contrast · sin 2πft)), relative to the mean luminance."""
    from pynwb import TimeSeries

    protocol = ds.attrs.get("protocol")
    cdims = lay["cdims"]
    if "time" not in ds.dims or len(ds.time) < 2:
        return
    rate = 1.0 / float(np.median(np.diff(ds.time.values)))
    comments = json.dumps({"dims": ["time", "condition_index"], "conditions": cdims})
    if protocol == "looming" and "angular_size_deg" in ds:
        x = _condition_major(ds.angular_size_deg, cdims, ["time"]).reshape(lay["C"], -1).T
        nwb.add_stimulus_template(TimeSeries(
            name="angular_size_deg", data=x.astype(np.float64), unit="degree", rate=rate, starting_time=0.0,
            description=ds.angular_size_deg.attrs.get("long_name", "disc angular size"), comments=comments))
    elif protocol == "tf-tuning" and {"temporal_frequency_hz", "contrast"} <= set(cdims):
        g = np.meshgrid(*[ds[d].values for d in cdims], indexing="ij")
        cv = dict(zip(cdims, (a.ravel() for a in g)))
        t_abs = ds.time.values
        x = 1.0 + cv["contrast"][None, :] * np.sin(2 * np.pi * cv["temporal_frequency_hz"][None, :] * t_abs[:, None])
        x[t_abs < 0] = 1.0  # the mean-luminance baseline before the grating's onset at time 0
        nwb.add_stimulus_template(TimeSeries(
            name="grating_luminance", data=x, unit="1", rate=rate, starting_time=0.0,
            description="drifting grating's luminance at one point of the eye relative to the mean "
                        "(1 + contrast·sin 2πft from the grating's onset, 1 before it); every point sees it "
                        "phase-shifted", comments=comments))


def _condition_dims(ds: xr.Dataset) -> list[str]:
    """Stimulus dims, the conditions simulated side by side.

    The recording layer puts them first: a time-resolved variable is (conditions…, [trial], time,
    channels…). So the condition dims are the dims every time-resolved variable has before its trial
    or time dim, in the first one's order; whatever follows time is a channel (LC units, ommatidia,
    T4/T5 layers, HS/VS cells, …). Without a time-resolved variable: every dim that is neither
    time, trial nor a known channel dim.
    """
    if ds.attrs.get("protocol") == "rf-map":
        return ["location", "direction_deg"]
    lead = []
    for v in ds.data_vars:
        dims = ds[v].dims
        tdim = next((d for d in _TIME_DIMS if d in dims), None)
        if tdim is None:
            continue
        stop = min(dims.index(tdim), dims.index("trial") if "trial" in dims else len(dims))
        lead.append(list(dims[:stop]))
    if lead:
        return [d for d in lead[0] if all(d in other for other in lead[1:])]
    skip = set(_TIME_DIMS) | {"trial"} | set(_CHANNEL_DIMS)
    return [d for d in ds.dims if d not in skip]


def _channel_dims(da: xr.DataArray, cdims: list[str], tdim: str) -> list[str]:
    """A time-resolved variable's channel dims: every dim that is not a condition, trial or its time."""
    return [d for d in da.dims if d not in cdims and d not in ("trial", tdim)]


def _channel_labels(ds: xr.Dataset, chans: list[str]) -> dict:
    """The channels of a (flattened, row-major) channel grid: each channel dim's coordinates, and every
    coordinate along one of them (e.g. ``hs_cell_name``), one entry per channel."""
    if not chans:
        return {}
    grids = np.meshgrid(*[np.arange(ds.sizes[d]) for d in chans], indexing="ij")
    out = {}
    for d, g in zip(chans, grids):
        for name, c in ds.coords.items():
            if c.dims == (d,):
                out[name] = c.values[g.ravel()].tolist()
    return out


def _epoch_duration(ds: xr.Dataset) -> float:
    if "time" in ds.dims:
        t = ds.time.values
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
        return float(t[-1] - t[0]) + dt
    p = json.loads(ds.attrs.get("parameters", "{}"))
    if ds.attrs.get("protocol") == "rf-map":
        return float(p["path_deg"]) / float(p["speed_deg_s"]) + float(p["tail_s"])
    return 1.0


def epoch_layout(ds: xr.Dataset) -> dict:
    """Where each (condition, trial) lies on the session timeline: dims, shapes, start times (C, K), duration."""
    cdims = _condition_dims(ds)
    cshape = [ds.sizes[d] for d in cdims]
    C = int(np.prod(cshape)) if cdims else 1
    K = ds.sizes.get("trial", 1)
    dur = _epoch_duration(ds)
    starts = (np.arange(C * K) * (dur + GAP_S)).reshape(C, K)
    t0 = float(ds.time.values[0]) if "time" in ds.coords else 0.0
    return dict(cdims=cdims, cshape=cshape, C=C, K=K, duration=dur, starts=starts, t0=t0)


def _condition_major(da: xr.DataArray, cdims: list[str], rest: list[str]) -> np.ndarray:
    """(C, *rest) array with conditions flattened row-major (a missing condition dim broadcasts)."""
    order = [d for d in cdims if d in da.dims] + [d for d in rest if d in da.dims]
    x = da.transpose(*order).values
    return x


def _session_times(ds: xr.Dataset, lay: dict, tdim: str) -> np.ndarray:
    """(C, K, T) session times of a time dim's samples (for spike bins: the step's start)."""
    t = ds[tdim].values.astype(float)
    rel = t - lay["t0"]
    return lay["starts"][:, :, None] + rel[None, None, :]


def _nwb_file(ds: xr.Dataset, lay: dict, experimenter, institution, lab):
    """The NWB file of ``ds`` with its general metadata, subject, virtual rig and electrode group;
    returns (file, electrode group)."""
    from pynwb import NWBFile
    from pynwb.file import Subject

    C, K = lay["C"], lay["K"]
    created = ds.attrs.get("created")
    try:
        start = datetime.fromisoformat(created) if created else datetime.now(timezone.utc)
    except ValueError:
        start = datetime.now(timezone.utc)
    protocol = ds.attrs.get("protocol", "unknown")
    notes = {k: (v.item() if hasattr(v, "item") else v) for k, v in ds.attrs.items()}
    nwb = NWBFile(
        session_description=f"lobula virtual electrophysiology, protocol {protocol}: {C} condition(s) x {K} "
                            f"trial(s) on one timeline (epochs of {lay['duration']:g} s + {GAP_S:g} s gaps)",
        identifier=str(uuid.uuid4()), session_start_time=start,
        experiment_description=f"in-silico recording from the lobula model ({ds.attrs.get('title', protocol)})",
        notes=json.dumps(notes, default=str), source_script=str(ds.attrs.get("command_line", "")),
        source_script_file_name="lobula (experiments.cli)", keywords=["lobula", "virtual electrophysiology",
                                                                       protocol],
        data_collection=f"lobula {ds.attrs.get('lobula_version', '')}, commit {ds.attrs.get('git_commit', 'unknown')}",
        session_id=protocol,
        **({"experimenter": [experimenter] if isinstance(experimenter, str) else list(experimenter)}
           if experimenter else {}),
        **({"institution": institution} if institution else {}), **({"lab": lab} if lab else {}))
    # The model is of Drosophila's optic lobe; it has no age or sex: sex "U" (unknown) and the open range
    # "P0D/" (age ≥ 0 days, unknown) say so in NWB's terms.
    nwb.subject = Subject(subject_id="lobula-model", sex="U", age="P0D/", species="Drosophila melanogaster",
                          description="in-silico model of the fly's (Drosophila melanogaster) optic lobe "
                                      "(photoreceptors, EMDs, LC units, readout neuron); not an animal")
    device = nwb.create_device(name="lobula_virtual_rig",
                               description="virtual electrophysiology rig of the lobula software model: every "
                                           "model neuron recorded exactly, at the model's time step")
    probe = nwb.create_electrode_group(name="virtual_electrodes", device=device,
                                       location="lobula (optic lobe), in silico",
                                       description="one virtual electrode per recorded spiking unit, "
                                                   "isolating that unit alone")
    return nwb, probe


def _add_trials(nwb, ds: xr.Dataset, lay: dict) -> None:
    """One trials row per (condition, trial) epoch, with the condition's stimulus values (rf-map: the
    spot passage's location and per-field response)."""
    cdims, C, K = lay["cdims"], lay["C"], lay["K"]
    protocol = ds.attrs.get("protocol", "unknown")
    cvals = {}
    if cdims:
        grids = np.meshgrid(*[ds[d].values for d in cdims], indexing="ij")
        cvals = {d: g.ravel() for d, g in zip(cdims, grids)}
    for d in cdims:
        desc = ds[d].attrs.get("long_name", d) + (f" ({ds[d].attrs['units']})" if "units" in ds[d].attrs else "")
        nwb.add_trial_column(name=d, description=desc)
    if protocol == "rf-map":
        for d in ("location_azimuth_deg", "location_elevation_deg"):
            nwb.add_trial_column(name=d, description=ds[d].attrs.get("long_name", d) + " (degree)")
        nwb.add_trial_column(name="rf_response", description=ds.rf_response.attrs.get("long_name", "") +
                             f" ({ds.rf_response.attrs.get('units', '')}), one value per LC field "
                             f"{ds.field.values.tolist()}")
        resp = ds.rf_response.transpose("location", "direction_deg", "field").values.reshape(C, -1)
        loc = np.repeat(np.arange(ds.sizes["location"]), ds.sizes["direction_deg"])
    nwb.add_trial_column(name="trial_index", description="trial (repeat) index within the condition")
    nwb.add_trial_column(name="condition_index", description="condition index (stimulus dims row-major)")
    nwb.add_trial_column(name="stimulus_time_zero", description="session time (s) of the recording's time 0 "
                                                               "(stimulus onset; collision for looming)")
    for c in range(C):
        for k in range(K):
            s = float(lay["starts"][c, k])
            row = dict(start_time=s, stop_time=s + lay["duration"], trial_index=k, condition_index=c,
                       stimulus_time_zero=s - lay["t0"])
            for d in cdims:
                v = cvals[d][c]
                row[d] = v.item() if hasattr(v, "item") else v
            if protocol == "rf-map":
                row["location_azimuth_deg"] = float(ds.location_azimuth_deg.values[loc[c]])
                row["location_elevation_deg"] = float(ds.location_elevation_deg.values[loc[c]])
                row["rf_response"] = resp[c]
            nwb.add_trial(**row)


def _add_units(nwb, ds: xr.Dataset, lay: dict, probe) -> list[str]:
    """Every recorded spiking unit with its session spike times (s) and receptive field; returns the
    spike variables written."""
    from pynwb.misc import Units

    cdims, C, K = lay["cdims"], lay["C"], lay["K"]
    spike_vars = [v for v in _SPIKES if v in ds]
    if spike_vars:
        # Spike times are known to the model step: that is the table's resolution (several spikes of a
        # Poisson unit may share one step, so equal consecutive times are expected, not refractory violations).
        res = min(float(ds[v].attrs["dt_s"]) for v in spike_vars)
        nwb.units = Units(name="units", description="spiking model units; spike times at the start of the model "
                                                    "step each spike fell in", resolution=res)
        for col, desc in (("unit_type", "unit type (LC: expansion, contraction, r2, rdot+, rdot-; readout: plus, "
                                        "minus)"), ("source_variable", "recording variable the spikes come from"),
                          ("field_index", "LC receptive-field index (-1: none)"),
                          ("rf_azimuth_deg", "receptive-field centre azimuth (degree; NaN: none)"),
                          ("rf_elevation_deg", "receptive-field centre elevation (degree, positive down; NaN: none)"),
                          ("rf_size_deg", "receptive-field size (degree; NaN: none)"),
                          ("neuron_model", "neuron model and its step, e.g. poisson@0.001s")):
            nwb.add_unit_column(name=col, description=desc)
    for var in spike_vars:
        da = ds[var]
        tdim = next(d for d in _TIME_DIMS if d in da.dims)
        dt = float(da.attrs.get("dt_s", np.median(np.diff(ds[tdim].values))))
        ch = "neuron" if "neuron" in da.dims else "unit"   # LC units / the readout's output neurons
        x = _condition_major(da, cdims, ["trial", tdim, ch]).reshape(C, K, ds.sizes[tdim], -1)
        times = _session_times(ds, lay, tdim)  # a spike's time: its step's start, as the time coordinate
        for j, n in enumerate(da[ch].values):
            counts = x[..., j]
            if not np.isfinite(counts).all():
                continue  # a unit this monitor did not record
            idx = np.nonzero(counts > 0)
            st = np.sort(np.repeat(times[idx], counts[idx].astype(int)))
            is_lc = "neuron_type" in ds.coords and var == "lc_spikes"
            kind = (ds.neuron_type.sel(neuron=n).values if is_lc else
                    ds.unit_neuron.sel(unit=n).values if "unit_neuron" in da.coords else n)
            nwb.add_electrode(group=probe, location="lobula (optic lobe), in silico")
            nwb.add_unit(spike_times=st, unit_type=str(kind), electrodes=[len(nwb.electrodes) - 1],
                         electrode_group=probe,
                         source_variable=var,
                         field_index=int(ds.field_index.sel(neuron=n)) if is_lc else -1,
                         rf_azimuth_deg=float(ds.azimuth_deg.sel(neuron=n)) if is_lc else float("nan"),
                         rf_elevation_deg=float(ds.elevation_deg.sel(neuron=n)) if is_lc else float("nan"),
                         rf_size_deg=float(ds.size_deg.sel(neuron=n)) if is_lc else float("nan"),
                         neuron_model=f"{da.attrs.get('neuron_model', '')}@{dt:g}s")
    return spike_vars


def _add_time_series(nwb, ds: xr.Dataset, lay: dict, spike_vars: list[str]) -> None:
    """Every other time-resolved variable as an acquisition TimeSeries (epoch-major time × channel)."""
    from pynwb import TimeSeries

    cdims, C, K = lay["cdims"], lay["C"], lay["K"]
    for var in ds.data_vars:
        da = ds[var]
        tdim = next((d for d in _TIME_DIMS if d in da.dims), None)
        if var in spike_vars or tdim is None or var in _STIMULUS_VARS:
            continue
        chans = _channel_dims(da, cdims, tdim)
        x = _condition_major(da, cdims, ["trial", tdim] + chans)
        T = ds.sizes[tdim]
        kk = K if "trial" in da.dims else 1
        x = x.reshape(C, kk, T, -1)
        times = _session_times(ds, lay, tdim)[:, :kk]
        data = x.reshape(C * kk * T, -1)
        ts = times.reshape(-1)
        if data.shape[1] == 1:
            data = data[:, 0]
        # Several channel dims (T4/T5: ommatidium × layer) are one channel axis, row-major; each channel's
        # labels say which it is.
        comments = {"dims": ["epoch-major time"] + (["channel (" + " x ".join(chans) + ", row-major)"] if chans
                                                    else []),
                    "trials": "all" if kk == K else "first epoch of each condition (no trial dim: deterministic)"}
        comments.update(_channel_labels(ds, chans))
        # One epoch (a single condition and trial) is sampled at a constant rate: NWB's best practice is
        # starting_time and rate then; several epochs have the gaps between them, so explicit timestamps.
        step = np.diff(ts)
        regular = ts.size > 2 and np.unique(step.round(9)).size == 1 and step[0] > 0
        timing = (dict(starting_time=float(ts[0]), rate=1.0 / float(np.median(step))) if regular
                  else dict(timestamps=ts))
        nwb.add_acquisition(TimeSeries(name=var, data=data.astype(np.float64), **timing,
                                       unit=str(da.attrs.get("units", "n.a.")),
                                       description=str(da.attrs.get("long_name", var)),
                                       comments=json.dumps(comments, default=str)))


def _add_channel_tables(nwb, ds: xr.Dataset, lay: dict) -> None:
    """One DynamicTable per channel dim of the time-resolved variables under processing/channels: a row per
    channel (LC unit, ommatidium, T4/T5 layer, HS or VS cell, …) with every coordinate along that dim, so
    that a TimeSeries' channel labels (its ``comments``) have a table to look up."""
    from hdmf.common import DynamicTable, VectorData

    dims = []
    for v in ds.data_vars:
        tdim = next((d for d in _TIME_DIMS if d in ds[v].dims), None)
        if tdim is not None:
            dims += [d for d in _channel_dims(ds[v], lay["cdims"], tdim) if d not in dims]
    if not dims:
        return
    mod = nwb.create_processing_module("channels", "the recorded channels of each time-resolved variable, one "
                                                   "table per channel dim, with every coordinate along it")
    for d in dims:
        cols = []
        for name, c in ds.coords.items():
            if c.dims != (d,):
                continue
            vals = c.values.astype(str) if c.values.dtype.kind in "OUS" else c.values
            desc = c.attrs.get("long_name", name) + (f" ({c.attrs['units']})" if c.attrs.get("units") else "")
            cols.append(VectorData(name=name, description=desc, data=vals))
        if not cols:
            cols = [VectorData(name=d, description=f"{d} index", data=np.arange(ds.sizes[d]))]
        desc = ds[d].attrs.get("long_name", d) if d in ds.coords else d
        mod.add(DynamicTable(name=d, description=f"channels along {d}: {desc}", columns=cols))


def _add_analysis(nwb, ds: xr.Dataset) -> None:
    """Every variable without time as a long-form DynamicTable under processing/analysis."""
    from hdmf.common import DynamicTable, VectorData

    static = [v for v in ds.data_vars if not any(d in ds[v].dims for d in _TIME_DIMS)]
    if static:
        mod = nwb.create_processing_module("analysis", "analyses of the recording (tuning curves, RF estimates, "
                                                       "looming peaks), long form")
        for var in static:
            da = ds[var]
            # a scalar analysis (no dim) is a one-row table
            flat = (da.to_dataframe(name="value") if da.ndim else da.expand_dims("_").to_dataframe(name="value")
                    .drop(columns=[c for c in da.coords], errors="ignore")).reset_index()
            flat = flat.drop(columns=["_"], errors="ignore")
            cols = []
            for c in flat.columns:
                vals = flat[c].values
                if vals.dtype == object:
                    vals = vals.astype(str)
                src = da if c == "value" else ds[c] if c in ds.variables else None
                desc = (src.attrs.get("long_name", c) if src is not None else c)
                unit = src.attrs.get("units") if src is not None else None
                cols.append(VectorData(name=c, description=f"{desc}" + (f" ({unit})" if unit else ""), data=vals))
            mod.add(DynamicTable(name=var, description=str(da.attrs.get("long_name", var)), columns=cols))


def write_nwb(ds: xr.Dataset, path: str | Path, *, experimenter: list[str] | str | None = None,
              institution: str | None = None, lab: str | None = None) -> Path:
    """Write the recording ``ds`` (any ephys protocol) as an NWB file at ``path``, atomically.

    experimenter ("Last, First", one or several), institution, lab: the file's general metadata
    (left out when None)."""
    from pynwb import NWBHDF5IO

    path = Path(path)
    nwb = probe = io = None
    try:
        lay = epoch_layout(ds)
        nwb, probe = _nwb_file(ds, lay, experimenter, institution, lab)
        _stimulus_templates(nwb, ds, lay)
        _add_trials(nwb, ds, lay)
        spike_vars = _add_units(nwb, ds, lay, probe)
        _add_time_series(nwb, ds, lay, spike_vars)
        _add_channel_tables(nwb, ds, lay)
        _add_analysis(nwb, ds)
        with atomic_path(path, suffix=".tmp.nwb") as tmp, NWBHDF5IO(str(tmp), "w") as io:
            io.write(nwb)
    finally:
        # The file is closed; the NWB objects refer to one another (parents, children), so left to the garbage
        # collector their finalisers would run at some later moment of the run, and an interrupt that arrived
        # while one ran would be ignored. They go here, the interrupt held until they have gone.
        with signals_deferred():
            nwb = probe = io = None
            gc.collect()
    return path


def read_nwb_spike_counts(path, ds: xr.Dataset, var: str = "lc_spikes") -> np.ndarray:
    """Spike counts of ``var``'s units back on the recording's grid, (C, K, T, units recorded), from an NWB file.

    ``ds`` gives the grid (its epoch layout and time coordinate); units come in file order.
    """
    from pynwb import NWBHDF5IO

    lay = epoch_layout(ds)
    tdim = next(d for d in _TIME_DIMS if d in ds[var].dims)
    dt = float(ds[var].attrs["dt_s"])
    T = ds.sizes[tdim]
    with NWBHDF5IO(str(path), "r") as io:
        f = io.read()
        units = f.units.to_dataframe()
        units = units[units.source_variable == var]
        out = np.zeros((lay["C"], lay["K"], T, len(units)))
        t_first = float(ds[tdim].values[0]) - lay["t0"]
        for j, st in enumerate(units.spike_times.values):
            st = np.asarray(st)
            e = np.floor(st / (lay["duration"] + GAP_S)).astype(int)
            c, k = np.divmod(e, lay["K"])
            step = np.rint((st - lay["starts"].ravel()[e] - t_first) / dt).astype(int)  # times are step starts
            np.add.at(out, (c, k, step, j), 1)
    return out


def read_nwb_series(path, name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(data, timestamps, unit) of an acquisition TimeSeries: data (samples, [channels]), timestamps (samples,)
    in s on the session timeline (from starting_time and rate where the series has no explicit timestamps)."""
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(str(path), "r") as io:
        ts = io.read().acquisition[name]
        data = np.asarray(ts.data[:])
        if ts.timestamps is None:
            times = ts.starting_time + np.arange(len(data)) / ts.rate
        else:
            times = np.asarray(ts.timestamps[:])
        return data, times, ts.unit
