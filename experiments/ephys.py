"""Virtual electrophysiology: show the model fly a stimulus, record any neuron, get labelled arrays.

A *rig* is a lattice (the eye) and a :class:`lobula.population.Circuit` (photoreceptors →
EMD array → LC population → LC neurons) stepped at 1 ms. *Monitors*, chosen like
Brian2's (``"POPULATION.VARIABLE"`` with an optional subset, e.g. ``"lc.rate"``,
``"lc.spikes[expansion]"``, ``"emd.response[0:20]"``, ``"photoreceptor.v"``), say what
to record. A *protocol* builds the stimuli, runs them as a batch of conditions × trials
and returns an :class:`xarray.Dataset`:

- dims ``trial``, ``time`` (s), ``neuron`` (LC units; coords ``neuron_type``,
  ``azimuth_deg``, ``elevation_deg``, ``size_deg``, ``field_index``), ``field`` (LC
  fields), ``ommatidium``, ``pair`` (EMDs), plus one dim per stimulus parameter
  (``temporal_frequency_hz``, ``contrast``, ``l_over_v_s``, ``motion``, …);
- one variable per monitor (``lc_rate``, ``emd_response``, …) with ``units`` in its
  attrs; the front end is deterministic and runs once per condition, so its variables
  carry no ``trial`` dim (they are identical across trials); neuron variables do;
- analysis variables (tuning curves, RF estimates, looming peaks) beside the raw data;
- attrs: the protocol, its parameters and the whole configuration as JSON
  (:func:`experiments.store.provenance`), and the package version.

Protocols: ``tf-tuning`` (temporal-frequency tuning; known answer: the optimum
1/(2πτ)), ``rf-map`` (local-motion spot mapping of each LC field: centre, size and
local preferred directions), ``looming`` (approach vs recession, l/|v| sweep). Each has
a PNG plot. :func:`psth` and :func:`raster` work on any spiking recording.
:func:`bench_tuning_sweep` is the benchmark of issue 5. ``add_parser`` registers
``lobula ephys``.
"""
from __future__ import annotations

import json
import math
import re
import time as _time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import xarray as xr

from lobula.camera import PinholeCamera, normalised_to_angles
from lobula.emd import emd_sine_response_discrete
from lobula.lattice import Lattice, LatticeConfig, dphi_for_count
from lobula.photoreceptor import photoreceptor_frequency_response
from lobula.circuit import Circuit, CircuitConfig
from lobula.population import (FIELD_RECORDS, NEURON_RECORDS, UNIT_RECORDS, LCNeuronConfig, LCPopulationConfig,
                               ReceptiveFieldConfig, config_from_dict)
from stimuli.lattice_stimuli import GratingSource, direction_from_angles, looming_disc, moving_spot, tangent_basis

__all__ = ["EphysConfig", "Rig", "Monitor", "parse_monitor", "tf_tuning", "rf_map", "looming", "psth", "raster",
           "steady_state_mean", "plot_tf_tuning", "plot_rf_map", "plot_looming", "plot_recording",
           "bench_tuning_sweep", "add_parser", "main", "PROTOCOLS"]

PROTOCOLS = ("tf-tuning", "rf-map", "looming", "velocity-replay")


# =========================================================================== configuration

@dataclass(frozen=True)
class EphysConfig:
    """The rig: eye, circuit, trials, seed (written whole into every recording).

    lattice: Δφ = 2° by default — a ~550-ommatidia patch over the D435i's 55°×42° field
        of view, fine enough to map 10° LC fields; ``dphi_deg=4.6`` is Drosophila's
        sampling (then use fields of ≥ 20°).
    camera_scale: the D435i intrinsics scaled by this (only the field of view matters;
        stimuli are rendered on the lattice, never as frames).
    circuit: photoreceptors, EMD (τ = 35 ms), LC population, step dt = 1 ms.
    trials: repeats per condition; seed: the neurons' noise; device: "cpu" or "cuda".
    threads: torch CPU threads while a protocol runs (None: torch's default). 1 by
        default: the per-step tensors are small, and on a shared machine a second
        OpenMP thread waiting for a busy core made runs 5–10× slower (measured).
    """

    lattice: LatticeConfig = field(default_factory=lambda: LatticeConfig(dphi_deg=2.0))
    camera_scale: float = 0.5
    circuit: CircuitConfig = field(default_factory=CircuitConfig)
    trials: int = 4
    seed: int = 0
    device: str = "cpu"
    threads: int | None = 1

    def __post_init__(self):
        if not (isinstance(self.trials, int) and self.trials >= 1):
            raise ValueError(f"trials must be a positive integer, got {self.trials!r}")
        if not isinstance(self.seed, int):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True, default=list)

    @classmethod
    def from_dict(cls, d: dict) -> "EphysConfig":
        return config_from_dict(cls, d)

    def with_tau(self, tau_s: float | None) -> "EphysConfig":
        """The same rig with the EMD delay τ (s) replaced (None: unchanged)."""
        if tau_s is None:
            return self
        return replace(self, circuit=replace(self.circuit, emd=replace(self.circuit.emd, tau_s=float(tau_s))))

    def with_neurons(self, model: str | None) -> "EphysConfig":
        """The same rig with the LC neuron model ("rate", "lif", "poisson") replaced."""
        if model is None:
            return self
        pop = self.circuit.population
        return replace(self, circuit=replace(self.circuit, population=replace(
            pop, neurons=replace(pop.neurons, model=model))))


@contextmanager
def torch_threads(n: int | None):
    """Run a block with ``n`` torch CPU threads (None: unchanged), restoring the setting after."""
    old = torch.get_num_threads()
    if n:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


class Rig:
    """An eye and its circuit, built from an :class:`EphysConfig`."""

    def __init__(self, config: EphysConfig | None = None):
        self.config = cfg = config or EphysConfig()
        camera = PinholeCamera(frame_rate_hz=1.0 / cfg.circuit.dt_s).scaled(cfg.camera_scale)
        self.lattice = Lattice(camera, cfg.lattice)
        self.circuit = Circuit(self.lattice, cfg.circuit, device=cfg.device)

    @property
    def population(self):
        return self.circuit.population

    @property
    def dt(self) -> float:
        return self.config.circuit.dt_s

    def default_records(self) -> tuple:
        """The neuron variables worth recording for this neuron model."""
        return {"rate": ("lc.rate",), "poisson": ("lc.rate", "lc.spikes"),
                "lif": ("lc.v", "lc.spikes")}[self.config.circuit.population.neurons.model]


# =========================================================================== monitors

@dataclass(frozen=True)
class Monitor:
    """What to record: ``variable`` ("lc.rate", …) and an optional subset ``neurons`` (indices)."""

    variable: str
    neurons: tuple | None = None

    @property
    def name(self) -> str:
        return self.variable.replace(".", "_")


_MONITOR = re.compile(r"^\s*([a-z_]+\.[a-z_]+)\s*(?:\[(.*)\])?\s*$")


def parse_monitor(spec: str | Monitor, rig: Rig) -> Monitor:
    """``"POP.VAR"``, ``"POP.VAR[i:j]"``, ``"POP.VAR[i,j,k]"`` or ``"lc.VAR[TYPE]"`` → :class:`Monitor`.

    Variables: photoreceptor.v, emd.response, lc.input, lc.r, lc.r2, lc.rdot, lc.drive,
    lc.rate, lc.x (rate/Poisson units), lc.v (LIF), lc.spikes (Poisson/LIF). A type name
    (expansion, contraction, r2, rdot+, rdot-) selects LC units of that type.
    """
    if isinstance(spec, Monitor):
        return spec
    m = _MONITOR.match(spec)
    available = rig.circuit.available()
    if not m or m.group(1) not in available:
        raise ValueError(f"cannot record {spec!r}; use POPULATION.VARIABLE[subset] with a variable from "
                         f"{list(available)} (e.g. lc.rate, lc.spikes[expansion], emd.response[0:10])")
    var, sub = m.group(1), m.group(2)
    if sub is None or not sub.strip():
        return Monitor(var, None)
    sub = sub.strip()
    pop = rig.population
    if sub in pop.types:
        if var not in UNIT_RECORDS + NEURON_RECORDS:
            raise ValueError(f"{spec!r}: a unit type selects LC units; {var} is not a per-unit variable")
        return Monitor(var, tuple(int(i) for i in pop.units_of(sub)))
    size = {"photoreceptor.v": rig.lattice.n, "emd.response": rig.lattice.n_pairs}.get(
        var, pop.n_fields if var in FIELD_RECORDS else pop.n_units)
    try:
        if ":" in sub:
            parts = [int(p) if p.strip() else None for p in sub.split(":")]
            idx = tuple(range(size))[slice(*parts)]
        else:
            idx = tuple(int(p) for p in sub.split(","))
    except ValueError:
        raise ValueError(f"{spec!r}: the subset must be i:j, i,j,k or a unit type {list(pop.types)}") from None
    if not idx or min(idx) < -size or max(idx) >= size:
        raise ValueError(f"{spec!r}: indices must lie in [0, {size}) for {var}")
    return Monitor(var, tuple(i % size for i in idx))


# =========================================================================== recording → Dataset

_UNITS = {"photoreceptor.v": "photoreceptor output (luminance units after the LMC high-pass)",
          "emd.response": "photoreceptor units squared",
          "lc.input": "R per (ommatidial step/s): matched-filter projection before normalisation",
          "lc.r": "1/s", "lc.r2": "1/s^2", "lc.rdot": "1/s^2", "lc.drive": "1 (dimensionless drive)",
          "lc.rate": "Hz", "lc.x": "1 (integrated drive)", "lc.v": "V", "lc.spikes": "spikes per time step"}


def _neuron_dim(var: str) -> str:
    if var == "photoreceptor.v":
        return "ommatidium"
    if var == "emd.response":
        return "pair"
    return "field" if var in FIELD_RECORDS else "neuron"


def _dim_coords(rig: Rig, dim: str, idx) -> dict:
    """Coordinates of one neuron-like dim for the indices idx (None: all)."""
    lat, pop = rig.lattice, rig.population
    sel = (lambda a: a) if idx is None else (lambda a: np.asarray(a)[np.asarray(idx)])
    if dim == "ommatidium":
        return {"ommatidium": sel(np.arange(lat.n)), "ommatidium_azimuth_deg": ("ommatidium", sel(lat.azimuth_deg)),
                "ommatidium_elevation_deg": ("ommatidium", sel(lat.elevation_deg))}
    if dim == "pair":
        mid = lat.pair_midpoint
        az, el = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
        ang = np.degrees(np.arctan2(lat.pair_direction[:, 1], lat.pair_direction[:, 0]))
        return {"pair": sel(np.arange(lat.n_pairs)), "pair_azimuth_deg": ("pair", sel(az)),
                "pair_elevation_deg": ("pair", sel(el)), "pair_axis": ("pair", sel(lat.pair_axis)),
                "pair_direction_deg": ("pair", sel(ang))}
    if dim == "field":
        fc = pop.field_coords()
        return {"field": sel(np.arange(pop.n_fields)), **{f"field_{k}": ("field", sel(v)) for k, v in fc.items()}}
    uc = pop.unit_coords()
    return {"neuron": sel(np.arange(pop.n_units)), **{k: ("neuron", sel(v)) for k, v in uc.items()}}


def record_dataset(rig: Rig, records: dict, monitors: list, cond: dict, n_steps: int, attrs: dict) -> xr.Dataset:
    """Labelled arrays from :meth:`Circuit.run` output.

    records: {variable: tensor (B, T, X) or (B, K, T, X)}; cond: ordered {dim: values}
    whose product of lengths is B (the conditions, row-major); n_steps: T. Monitors that
    record different subsets of one dim share it: its coordinate is the union of their
    indices, and a variable is NaN where its monitor did not record.
    """
    cdims = list(cond)
    cshape = [len(v) for v in cond.values()]
    t = np.arange(n_steps) * rig.dt
    coords = {"time": ("time", t, {"units": "s", "note": "stimulus frame times; neuron states are at the end "
                                                        "of each frame's step (t + dt)"}),
              **{k: (k, np.asarray(v)) for k, v in cond.items()}}
    union: dict = {}
    for mon in monitors:
        dim = _neuron_dim(mon.variable)
        full = mon.neurons is None
        prev = union.get(dim, set())
        union[dim] = None if full or prev is None else prev | set(mon.neurons)
    index = {d: (None if u is None else np.array(sorted(u))) for d, u in union.items()}
    for d, idx in index.items():
        coords.update(_dim_coords(rig, d, idx))
    data = {}
    for mon in monitors:
        arr = records[mon.variable].detach().to("cpu").numpy()
        dim = _neuron_dim(mon.variable)
        arr = arr.reshape(cshape + list(arr.shape[1:]))
        idx = index[dim]
        own = None if mon.neurons is None else np.asarray(mon.neurons)
        if not (own is None and idx is None) and not (idx is not None and own is not None and np.array_equal(own, idx)):
            size = len(idx) if idx is not None else {"ommatidium": rig.lattice.n, "pair": rig.lattice.n_pairs,
                                                     "field": rig.population.n_fields}.get(dim, rig.population.n_units)
            where = np.searchsorted(idx, own) if idx is not None else own
            filled = np.full(arr.shape[:-1] + (size,), np.nan, dtype=arr.dtype)
            filled[..., where] = arr
            arr = filled
        dims = cdims + (["trial"] if mon.variable in NEURON_RECORDS else []) + ["time", dim]
        data[mon.name] = (dims, arr, {"units": _UNITS[mon.variable], "monitor": mon.variable,
                                      "recorded": "all" if own is None else json.dumps(own.tolist())})
    ds = xr.Dataset(data, coords=coords)
    if any(m.variable in NEURON_RECORDS for m in monitors):
        ds = ds.assign_coords(trial=np.arange(ds.sizes["trial"]))
    ds.attrs.update(attrs)
    return ds


def _provenance(rig: Rig, protocol: str, params: dict) -> dict:
    from experiments.store import provenance

    full = {"ephys": rig.config.to_dict(), "protocol": protocol, "parameters": params,
            "lattice": {"n_ommatidia": rig.lattice.n, "n_pairs": rig.lattice.n_pairs,
                        "camera": rig.lattice.camera.to_dict()},
            "population": rig.population.to_dict()}
    return provenance(json.dumps(full, sort_keys=True, default=_json_default), protocol=protocol,
                      parameters=json.dumps(params, sort_keys=True, default=_json_default),
                      dt_s=rig.dt, trials=rig.config.trials, seed=rig.config.seed,
                      neuron_model=rig.config.circuit.population.neurons.model,
                      emd_tau_s=rig.config.circuit.emd.tau_s)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def _monitors(rig: Rig, record, default) -> list[Monitor]:
    specs = list(default if not record else record)
    mons = [parse_monitor(s, rig) for s in specs]
    names = [m.variable for m in mons]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ValueError(f"record each variable once (with one subset); repeated: {sorted(dup)}")
    return mons


def _run(rig: Rig, stimulus, n_steps, monitors, *, baseline=None) -> dict:
    rec = {m.variable: m.neurons for m in monitors}
    cfg = rig.config
    return rig.circuit.run(stimulus, n_steps, trials=cfg.trials, record=rec, seed=cfg.seed, baseline=baseline)


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


def psth(ds: xr.Dataset, var: str = "lc_spikes", bin_s: float = 0.01) -> xr.DataArray:
    """Peri-stimulus time histogram (Hz): spikes summed in bins of ``bin_s`` and averaged over trials."""
    if var not in ds:
        raise ValueError(f"no {var!r} in this recording; record lc.spikes (Poisson or LIF units)")
    dt = float(ds.time[1] - ds.time[0])
    k = max(1, int(round(bin_s / dt)))
    da = ds[var]
    n = da.sizes["time"] // k * k
    binned = da.isel(time=slice(0, n)).coarsen(time=k).sum() / (k * dt)
    out = binned.mean("trial") if "trial" in binned.dims else binned
    out.attrs = {"units": "Hz", "bin_s": k * dt}
    return out.rename("psth")


def raster(ds: xr.Dataset, neuron: int, var: str = "lc_spikes", **sel) -> tuple[np.ndarray, np.ndarray]:
    """Spike times (s) and trial indices of one neuron (``sel`` picks one condition, e.g. contrast=0.5)."""
    da = ds[var].sel(neuron=neuron).sel(**sel) if sel else ds[var].sel(neuron=neuron)
    extra = [d for d in da.dims if d not in ("trial", "time")]
    if extra:
        da = da.isel({d: 0 for d in extra})
    s = da.transpose("trial", "time").values
    tr, ti = np.nonzero(s > 0)
    counts = s[tr, ti].astype(int)
    return np.repeat(da.time.values[ti], counts), np.repeat(tr, counts)


# =========================================================================== protocols

def _probe_pairs(rig: Rig, kind: str, direction_deg: float, centre_deg=(0.0, 0.0)) -> np.ndarray:
    """For each LC field, the EMD pair nearest its centre that points along the stimulus motion
    (radially outward for rings, along direction_deg for a drum grating)."""
    lat, pop = rig.lattice, rig.population
    mid = lat.pair_midpoint
    az, el = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
    if kind == "radial":
        from lobula.population import pair_templates
        align, _ = pair_templates(lat, centre_deg, "direction")
    else:
        th = math.radians(direction_deg)
        align = lat.pair_direction @ np.array([math.cos(th), math.sin(th)])
    good = np.nonzero(align > 0.8)[0]
    d = (az[good][None, :] - pop.centres_deg[:, :1]) ** 2 + (el[good][None, :] - pop.centres_deg[:, 1:]) ** 2
    return np.unique(good[np.argmin(d, axis=1)])


def _tf_tuning(config: EphysConfig, *, temporal_frequencies_hz=None, contrasts=(0.5,),
              wavelength_deg: float = 20.0, stimulus: str = "rings", direction_deg: float = 0.0,
              duration_s: float = 2.0, settle_s: float = 0.5, tau_s: float | None = None,
              record=None, mean_luminance: float = 1.0) -> xr.Dataset:
    """Temporal-frequency tuning: drifting sine gratings at every (TF, contrast).

    stimulus: "rings" (concentric rings expanding about the epipole: every pair of an
    expansion unit sees the same TF) or "grating" (a planar drum grating moving in
    direction_deg). tau_s: the EMD delay (s), overriding the config. record: monitors
    (default: probe EMD pairs — per LC field, the pair nearest its centre along the
    motion — and the LC neurons). Adds ``<var>_tuning`` (steady-state mean over whole
    periods after settle_s, trial-averaged, per TF and contrast), ``peak_temporal_frequency_hz``
    per recorded unit, and ``emd_prediction`` (the exact discrete EMD tuning times the
    photoreceptor transfer, normalised), with attrs ``optimum_hz`` = 1/(2πτ).
    """
    cfg = (config or EphysConfig()).with_tau(tau_s)
    rig = Rig(cfg)
    tf = np.geomspace(0.5, 32.0, 16) if temporal_frequencies_hz is None else np.asarray(temporal_frequencies_hz, float)
    c = np.asarray(contrasts, dtype=float)
    if stimulus not in ("rings", "grating"):
        raise ValueError(f"tf-tuning stimulus must be 'rings' or 'grating', got {stimulus!r}")
    kind = "radial" if stimulus == "rings" else "drum"
    epi = cfg.circuit.population.matched_filter.epipole_deg
    default = [f"emd.response[{','.join(map(str, _probe_pairs(rig, kind, direction_deg, epi)))}]"] + \
        list(rig.default_records())
    monitors = _monitors(rig, record, default)
    TF, C = np.meshgrid(tf, c, indexing="ij")
    n_steps = int(round(duration_s / rig.dt))
    src = GratingSource(rig.lattice, kind=kind, temporal_freq_hz=TF.ravel(), contrast=C.ravel(),
                        wavelength_deg=wavelength_deg, direction_deg=direction_deg, centre_deg=epi,
                        mean_luminance=mean_luminance, frame_rate_hz=1.0 / rig.dt,
                        device=cfg.device)
    recs = _run(rig, src, n_steps, monitors, baseline=mean_luminance)
    params = dict(temporal_frequencies_hz=tf, contrasts=c, wavelength_deg=wavelength_deg, stimulus=stimulus,
                  direction_deg=direction_deg, duration_s=duration_s, settle_s=settle_s,
                  mean_luminance=mean_luminance, stimulus_info=src.info)
    ds = record_dataset(rig, recs, monitors, {"temporal_frequency_hz": tf, "contrast": c}, n_steps,
                        {**_provenance(rig, "tf-tuning", params)})
    t = ds.time.values
    tau = cfg.circuit.emd.tau_s
    for mon in monitors:
        da = ds[mon.name]
        x = da.values
        if "trial" in da.dims:
            x = x.mean(axis=da.dims.index("trial"))
        scale = 1.0 / rig.dt if mon.variable == "lc.spikes" else 1.0
        mean = steady_state_mean(x, t, tf[:, None], settle_s) * scale
        nd = da.dims[-1]
        ds[f"{mon.name}_tuning"] = (("temporal_frequency_hz", "contrast", nd), mean,
                                    {"units": "Hz" if mon.variable == "lc.spikes" else da.attrs["units"],
                                     "note": "steady-state mean over whole periods, trial-averaged"})
        ok = np.isfinite(mean).all(axis=0)
        peak = np.where(ok, tf[np.argmax(np.where(np.isfinite(mean), mean, -np.inf), axis=0)], np.nan)
        ds[f"{mon.name}_peak_temporal_frequency_hz"] = (("contrast", nd), peak, {"units": "Hz"})
    pr = np.abs(photoreceptor_frequency_response(cfg.circuit.photoreceptor, rig.dt, tf)) ** 2
    pred = emd_sine_response_discrete(cfg.circuit.emd, rig.dt, tf, np.pi / 2) * pr
    ds["emd_prediction"] = ("temporal_frequency_hz", pred / pred.max(),
                            {"units": "1", "note": "exact discrete EMD tuning × |photoreceptor transfer|², normalised"})
    # The gradient-ratio pool divides out the photoreceptor's attenuation (it enters R and G alike).
    lc = pred / pr if cfg.circuit.population.normalisation.kind == "gradient-ratio" else pred
    ds["lc_drive_prediction"] = ("temporal_frequency_hz", lc / lc.max(),
                                 {"units": "1", "note": "predicted tuning of the LC drive (before the neurons' "
                                                        "saturating output), normalised"})
    ds.attrs["optimum_hz"] = 1.0 / (2.0 * math.pi * tau)
    return ds


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
    fields = np.arange(pop.n_fields) if fields is None else np.atleast_1d(np.asarray(fields, dtype=int))
    if len(fields) == 0 or fields.min() < 0 or fields.max() >= pop.n_fields:
        raise ValueError(f"fields must be indices in [0, {pop.n_fields}), got {fields}")
    dphi = lat.dphi_deg
    spacing = dphi if spacing_deg is None else float(spacing_deg)
    extent = 1.6 * pop.size_deg if extent_deg is None else float(extent_deg)
    size = dphi if spot_size_deg is None else float(spot_size_deg)
    path = 2.0 * dphi if path_deg is None else float(path_deg)
    speed = 50.0 * dphi if speed_deg_s is None else float(speed_deg_s)
    dirs = np.arange(directions) * 360.0 / directions
    if directions < 3:
        raise ValueError("rf-map needs at least 3 directions to separate sensitivity from direction")
    locs = _rf_locations(rig, fields, spacing, extent)
    L, D = len(locs), len(dirs)
    pass_s = path / speed
    n_steps = int(round((pass_s + tail_s) / rig.dt))
    t_mid = pass_s / 2.0
    monitors = _monitors(rig, record, ["lc.input"])
    field_mons = [m for m in monitors if m.variable in FIELD_RECORDS]
    if not field_mons:
        raise ValueError("rf-map maps a field variable: record lc.input, lc.r, lc.r2 or lc.rdot")
    mon = field_mons[0]
    ev_loc = np.repeat(np.arange(L), D)
    ev_dir = np.tile(dirs, L)
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
    coords = {"location": np.arange(L), "location_azimuth_deg": ("location", locs[:, 0]),
              "location_elevation_deg": ("location", locs[:, 1]), "direction_deg": dirs,
              **_dim_coords(rig, "field", None), **_dim_coords(rig, "neuron", None)}
    ds = xr.Dataset({
        "rf_response": (("location", "direction_deg", "field"), resp,
                        {"units": f"({_UNITS[mon.variable]})·s", "note": f"time integral of {mon.variable} per spot passage"}),
        "rf_sensitivity": (("location", "field"), sens, {"units": f"({_UNITS[mon.variable]})·s",
                                                          "note": "local motion sensitivity along the radial direction"}),
        "rf_preferred_direction_deg": (("location", "field"), pref, {"units": "deg (image: 0 right, 90 down)"}),
        "rf_centre_azimuth_deg": ("field", cen[:, 0], {"units": "deg"}),
        "rf_centre_elevation_deg": ("field", cen[:, 1], {"units": "deg"}),
        "rf_size_deg": ("field", sz, {"units": "deg", "note": "FWHM (gaussian) or side (box), probe deconvolved"}),
    }, coords=coords)
    unit_f = pop.unit_field
    pushpull = np.isin(pop.unit_type, ["expansion", "contraction"])
    for k, v in (("azimuth", cen[:, 0]), ("elevation", cen[:, 1])):
        ds[f"neuron_rf_centre_{k}_deg"] = ("neuron", np.where(pushpull, v[unit_f], np.nan), {"units": "deg"})
    ds["neuron_rf_size_deg"] = ("neuron", np.where(pushpull, sz[unit_f], np.nan), {"units": "deg"})
    ds.attrs.update(_provenance(rig, "rf-map", params))
    ds.attrs["dphi_deg"] = dphi
    return ds


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


def _looming(config: EphysConfig, *, l_over_v_s=(0.01, 0.02, 0.04, 0.08), duration_s: float = 1.0,
            t_collision_s: float | None = None, centre_deg=None, max_size_deg: float = 60.0, contrast: float = 1.0,
            record=None, tau_s: float | None = None) -> xr.Dataset:
    """Looming: a dark disc approaching (``2·atan((l/v)/(t_c − t))``) or receding (the time reversal).

    Conditions: dims ``l_over_v_s`` × ``motion`` ∈ {approach, recede}; the disc is
    centred on the epipole unless ``centre_deg`` is given, collision at ``t_collision_s``
    (default 0.8·duration), capped at ``max_size_deg``. Adds ``angular_size_deg``
    (l_over_v_s, motion, time), and per recorded neuron variable ``<var>_peak`` (the
    trial-averaged maximum) and ``<var>_time_of_peak_s`` (relative to collision).
    """
    cfg = (config or EphysConfig()).with_tau(tau_s)
    rig = Rig(cfg)
    lv = np.atleast_1d(np.asarray(l_over_v_s, dtype=float))
    n_steps = int(round(duration_s / rig.dt))
    tc = 0.8 * duration_s if t_collision_s is None else float(t_collision_s)
    centre = cfg.circuit.population.matched_filter.epipole_deg if centre_deg is None else tuple(centre_deg)
    monitors = _monitors(rig, record, rig.default_records())
    kw = dict(t_collision_s=tc, centre_deg=centre, contrast=contrast, max_size_deg=max_size_deg,
              frame_rate_hz=1.0 / rig.dt, device=cfg.device)
    app, info = looming_disc(rig.lattice, n_steps, l_over_v_s=lv, **kw)
    rec, info_r = looming_disc(rig.lattice, n_steps, l_over_v_s=lv, receding=True, **kw)
    stim = torch.stack([app.reshape(len(lv), n_steps, -1), rec.reshape(len(lv), n_steps, -1)], dim=1)
    stim = stim.reshape(2 * len(lv), n_steps, -1)
    recs = _run(rig, stim, n_steps, monitors, baseline=1.0)
    params = dict(l_over_v_s=lv, duration_s=duration_s, t_collision_s=tc, centre_deg=centre,
                  max_size_deg=max_size_deg, contrast=contrast)
    ds = record_dataset(rig, recs, monitors, {"l_over_v_s": lv, "motion": np.array(["approach", "recede"])},
                        n_steps, _provenance(rig, "looming", params))
    sizes = np.stack([np.atleast_2d(info["angular_size_deg"]), np.atleast_2d(info_r["angular_size_deg"])], axis=1)
    ds["angular_size_deg"] = (("l_over_v_s", "motion", "time"), sizes, {"units": "deg"})
    t = ds.time.values
    for mon in monitors:
        da = ds[mon.name]
        x = da.mean("trial") if "trial" in da.dims else da
        if mon.variable == "lc.spikes":  # smooth spike counts into a rate before taking the peak
            x = x.rolling(time=max(1, int(round(0.02 / rig.dt))), center=True, min_periods=1).mean() / rig.dt
        ds[f"{mon.name}_peak"] = x.max("time").assign_attrs(units="Hz" if mon.variable == "lc.spikes"
                                                            else da.attrs["units"])
        ds[f"{mon.name}_time_of_peak_s"] = (t[x.argmax("time").values] - tc) * xr.ones_like(x.isel(time=0))
        ds[f"{mon.name}_time_of_peak_s"].attrs["units"] = "s relative to collision"
    ds.attrs["t_collision_s"] = tc
    return ds


def tf_tuning(config: EphysConfig | None = None, **kw) -> xr.Dataset:
    cfg = config or EphysConfig()
    with torch_threads(cfg.threads):
        return _tf_tuning(cfg, **kw)


def rf_map(config: EphysConfig | None = None, **kw) -> xr.Dataset:
    cfg = config or EphysConfig()
    with torch_threads(cfg.threads):
        return _rf_map(cfg, **kw)


def looming(config: EphysConfig | None = None, **kw) -> xr.Dataset:
    cfg = config or EphysConfig()
    with torch_threads(cfg.threads):
        return _looming(cfg, **kw)


tf_tuning.__doc__ = _tf_tuning.__doc__
rf_map.__doc__ = _rf_map.__doc__
looming.__doc__ = _looming.__doc__


# =========================================================================== plots

def _figure(nrows=1, ncols=2, size=(10, 4)):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt.subplots(nrows, ncols, figsize=size, squeeze=False)


def _save(fig, path):
    import matplotlib.pyplot as plt

    from experiments.store import save_figure
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return Path(path)


def _neuron_var(ds: xr.Dataset) -> str | None:
    for v in ("lc_rate", "lc_spikes", "lc_v", "lc_x", "lc_drive"):
        if v in ds:
            return v
    return None


def plot_tf_tuning(ds: xr.Dataset, path) -> Path:
    """Tuning curves (normalised) of the recorded EMDs and LC expansion units against the prediction,
    and a raster/PSTH panel at the optimum when spikes were recorded."""
    spikes = "lc_spikes" in ds
    fig, ax = _figure(1, 3 if spikes else 2, (15 if spikes else 10, 4))
    tf = ds.temporal_frequency_hz.values
    opt = ds.attrs.get("optimum_hz")
    for a, name in zip(ax[0], [v for v in ("emd_response_tuning", _neuron_var(ds) and f"{_neuron_var(ds)}_tuning")
                               if v and v in ds][:2]):
        da = ds[name].isel(contrast=0)
        nd = da.dims[-1]
        if nd == "neuron":
            keep = ds.neuron_type.sel(neuron=da.neuron).values == "expansion"
            da = da.isel(neuron=np.nonzero(keep)[0]) if keep.any() else da
        y = da.values
        y = y / np.nanmax(np.abs(y), axis=0, keepdims=True)
        a.semilogx(tf, y, color="0.6", lw=0.8)
        a.semilogx(tf, np.nanmean(y, axis=1), "k", lw=2, label="mean (normalised)")
        if name.startswith("emd"):
            a.semilogx(tf, ds.emd_prediction.values, "r--", label="EMD prediction (discrete × photoreceptor)")
        else:
            a.semilogx(tf, ds.lc_drive_prediction.values, "r--", label="LC drive prediction (before saturation)")
        if opt:
            a.axvline(opt, color="b", ls=":", label=f"1/(2πτ) = {opt:.2f} Hz")
        a.set_xlabel("temporal frequency (Hz)")
        a.set_ylabel("normalised response")
        a.set_title(name.replace("_tuning", "").replace("_", "."))
        a.legend(fontsize=7)
    if spikes:
        a = ax[0][-1]
        k = int(np.argmin(np.abs(tf - (opt or tf[len(tf) // 2]))))
        units = np.nonzero(ds.neuron_type.values == "expansion")[0]
        n = int(ds.neuron.values[units[0]]) if len(units) else int(ds.neuron.values[0])
        ts, tr = raster(ds, n, temporal_frequency_hz=tf[k], contrast=ds.contrast.values[0])
        a.plot(ts, tr, "|k", ms=6)
        a.set_xlabel("time (s)")
        a.set_ylabel("trial")
        a.set_title(f"raster, neuron {n} at {tf[k]:.2f} Hz")
    return _save(fig, path)


def plot_rf_map(ds: xr.Dataset, path) -> Path:
    """Sensitivity maps of the probed fields with designed (white) and recovered (red) centres and sizes,
    and the local preferred directions as arrows."""
    probed = [int(f) for f in np.atleast_1d(json.loads(ds.attrs["parameters"])["fields"])][:6]
    fig, ax = _figure(1, len(probed), (4 * len(probed), 3.6))
    az, el = ds.location_azimuth_deg.values, ds.location_elevation_deg.values
    for a, f in zip(ax[0], probed):
        s = ds.rf_sensitivity.sel(field=f).values
        sc = a.scatter(az, el, c=s, cmap="viridis", s=30, marker="s")
        pdir = np.radians(ds.rf_preferred_direction_deg.sel(field=f).values)
        mag = np.abs(s) / (np.abs(s).max() + 1e-30)
        a.quiver(az, el, mag * np.cos(pdir), mag * np.sin(pdir), color="w", scale=25, width=0.004)
        for (x, y, d, col) in ((ds.field_azimuth_deg.sel(field=f), ds.field_elevation_deg.sel(field=f),
                                ds.field_size_deg.sel(field=f), "w"),
                               (ds.rf_centre_azimuth_deg.sel(field=f), ds.rf_centre_elevation_deg.sel(field=f),
                                ds.rf_size_deg.sel(field=f), "r")):
            a.add_patch(__import__("matplotlib.patches", fromlist=["Circle"]).Circle(
                (float(x), float(y)), float(d) / 2, fill=False, color=col, lw=1.5))
        a.set_aspect("equal")
        a.invert_yaxis()
        a.set_xlabel("azimuth (deg)")
        a.set_ylabel("elevation (deg, down)")
        a.set_title(f"field {f}: size {float(ds.rf_size_deg.sel(field=f)):.1f}° "
                    f"(designed {float(ds.field_size_deg.sel(field=f)):.1f}°)", fontsize=9)
        fig.colorbar(sc, ax=a, shrink=0.8)
    return _save(fig, path)


def plot_looming(ds: xr.Dataset, path) -> Path:
    """Expansion units' responses (mean over units and trials) against time to collision, approach
    vs recede, and the disc's angular size; a PSTH when spikes were recorded."""
    var = _neuron_var(ds)
    fig, ax = _figure(1, 2, (10, 4))
    t = ds.time.values - ds.attrs["t_collision_s"]
    if var:
        da = ds[var]
        if "neuron" in da.dims:
            da = da.isel(neuron=np.nonzero(ds.neuron_type.sel(neuron=da.neuron).values == "expansion")[0])
        if var == "lc_spikes":
            da = psth(ds.assign({var: da}), var, 0.02)
            tt = da.time.values - ds.attrs["t_collision_s"]
        else:
            tt = t
        m = da.mean([d for d in da.dims if d in ("trial", "neuron")])
        for lv in ds.l_over_v_s.values:
            for mot, ls in (("approach", "-"), ("recede", "--")):
                ax[0][0].plot(tt, m.sel(l_over_v_s=lv, motion=mot).values, ls, label=f"l/v={lv:g} s {mot}")
        ax[0][0].set_xlabel("time to collision (s)")
        ax[0][0].set_ylabel(f"{var} ({ds[var].attrs.get('units', '')})")
        ax[0][0].legend(fontsize=6)
        ax[0][0].set_title("expansion units")
    for lv in ds.l_over_v_s.values:
        ax[0][1].plot(t, ds.angular_size_deg.sel(l_over_v_s=lv, motion="approach"), label=f"l/v={lv:g} s")
    ax[0][1].set_xlabel("time to collision (s)")
    ax[0][1].set_ylabel("angular size (deg)")
    ax[0][1].legend(fontsize=7)
    return _save(fig, path)


def plot_recording(ds: xr.Dataset, path) -> Path:
    """The protocol's plot (from ds.attrs["protocol"])."""
    p = ds.attrs.get("protocol")
    fn = {"tf-tuning": plot_tf_tuning, "rf-map": plot_rf_map, "looming": plot_looming}.get(p)
    if fn is None:
        raise ValueError(f"no plot for protocol {p!r}")
    return fn(ds, path)


# =========================================================================== benchmark

def bench_tuning_sweep(n_ommatidia: int = 5000, n_tf: int = 20, n_contrasts: int = 5, trials: int = 10,
                       duration_s: float = 2.0, dt_s: float = 1e-3, neuron_model: str = "poisson",
                       field_size_deg: float = 5.0, threads: int | None = 1, device: str = "cpu",
                       chunk_steps: int = 8, compile: bool = True, max_steps: int | None = None,
                       verbose: bool = True) -> dict:
    """Issue 5's benchmark: a tuning sweep of n_tf TFs × n_contrasts contrasts × trials, duration_s at dt_s,
    for an eye of ~n_ommatidia (D435i field of view at 320×240) with its LC population (5° Gaussian
    fields tiling the eye, 5 unit types each).

    The front end (photoreceptors, EMDs, LC pooling) is deterministic and runs once per
    stimulus condition (n_tf·n_contrasts conditions, all batched); the LC neurons run per
    trial (their noise differs). Only the steady-state spike counts/rates are kept (no
    time courses). threads: torch CPU threads during the run (1 is fastest on a shared
    2-core machine: per-step tensors are small); compile: fuse the EMD array and pooling
    with torch.compile (its one-off compilation is timed separately, as ``compile_s``,
    by a short warm-up run); max_steps: time only that many steps and extrapolate. Returns a dict with seconds and neuron-steps per second:
    ``computed`` counts each stage as run (front end per condition, LC per trial),
    ``equivalent`` as if every trial ran the whole eye.
    """
    with torch_threads(threads):
        t0 = _time.perf_counter()
        camera = PinholeCamera(frame_rate_hz=1.0 / dt_s).scaled(0.5)
        lat = Lattice(camera, LatticeConfig(dphi_deg=dphi_for_count(camera, n_ommatidia)))
        pop = LCPopulationConfig(fields=ReceptiveFieldConfig(size_deg=field_size_deg),
                                 neurons=LCNeuronConfig(model=neuron_model))
        circuit = Circuit(lat, CircuitConfig(population=pop, dt_s=dt_s, chunk_steps=chunk_steps, compile=compile),
                          device=device)
        tf = np.geomspace(0.5, 32.0, n_tf)
        c = np.geomspace(0.05, 0.8, n_contrasts)
        TF, C = np.meshgrid(tf, c, indexing="ij")
        src = GratingSource(lat, kind="drum", temporal_freq_hz=TF.ravel(), contrast=C.ravel(), wavelength_deg=20.0,
                            frame_rate_hz=1.0 / dt_s, device=device)
        n_steps = int(round(duration_s / dt_s))
        run_steps = n_steps if max_steps is None else min(n_steps, int(max_steps))
        settle = int(round(0.5 / dt_s))
        var = "lc.spikes" if neuron_model in ("poisson", "lif") else "lc.rate"
        acc = {"sum": None}

        def keep(start, rec):  # steady-state sums only: no time courses are kept
            x = rec[var]                                                        # (Tc, B, K, U)
            lo = max(0, settle - start)
            if lo < x.shape[0]:
                s = x[lo:].sum(0)
                acc["sum"] = s if acc["sum"] is None else acc["sum"] + s

        setup = _time.perf_counter() - t0
        compile_s = 0.0
        if compile:  # compile on a warm-up chunk of the same shape, timed on its own
            tc = _time.perf_counter()
            circuit.run(src, chunk_steps, trials=trials, record=(var,), seed=0, baseline=1.0, callback=lambda *a: None)
            compile_s = _time.perf_counter() - tc
        t1 = _time.perf_counter()
        circuit.run(src, run_steps, trials=trials, record=(var,), seed=0, baseline=1.0, callback=keep)
        if device != "cpu":
            torch.cuda.synchronize()
        run_s = _time.perf_counter() - t1
    B, U, n, P = TF.size, circuit.population.n_units, lat.n, lat.n_pairs
    scale = n_steps / run_steps
    total = run_s * scale
    computed = (B * (n + P) + B * trials * U) * n_steps
    equivalent = B * trials * (n + P + U) * n_steps
    res = {"n_ommatidia": n, "n_pairs": P, "n_lc_units": U, "n_fields": circuit.population.n_fields,
           "conditions": B, "trials": trials, "steps": n_steps, "dt_s": dt_s, "neuron_model": neuron_model,
           "device": device, "threads": threads, "compile": compile, "setup_s": setup, "compile_s": compile_s,
           "run_s": total,
           "extrapolated_from_steps": run_steps if run_steps < n_steps else None,
           "computed_neuron_steps_per_s": computed / total, "equivalent_neuron_steps_per_s": equivalent / total,
           "target_s": 60.0}
    if verbose:
        print(f"ephys tuning sweep: {n_tf} TF × {n_contrasts} contrasts × {trials} trials, {duration_s:g} s at "
              f"{dt_s * 1e3:g} ms; eye {n} ommatidia, {P} EMDs, {U} LC units ({neuron_model}) on {device}: "
              f"{total:.1f} s{' (extrapolated from %d steps)' % run_steps if run_steps < n_steps else ''} "
              f"+ {setup:.1f} s setup{' + %.1f s compilation' % compile_s if compile else ''}; "
              f"{computed / total:.3g} neuron-steps/s computed, "
              f"{equivalent / total:.3g} equivalent (target < 60 s)")
    return res


# =========================================================================== command line

def add_parser(subparsers):
    """Register ``lobula ephys PROTOCOL ...`` on an argparse subparsers object."""
    e = subparsers.add_parser("ephys", help="virtual electrophysiology: record LC/EMD/photoreceptor neurons",
                              description=__doc__.split("\n\n")[0])
    e.add_argument("protocol", choices=PROTOCOLS, help="tf-tuning | rf-map | looming | velocity-replay")
    e.add_argument("--footage", help="velocity-replay: footage folder (default: render a built-in 10 s run)")
    e.add_argument("--record", nargs="+", metavar="POP.VAR",
                   help="monitors, e.g. lc.rate lc.spikes[expansion] emd.response[0:10] photoreceptor.v "
                        "(default: the protocol's)")
    e.add_argument("--trials", type=int, default=4)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--tau", type=float, help="EMD delay τ (s); default 0.035")
    e.add_argument("--neuron-model", choices=["rate", "lif", "poisson"], default=None)
    e.add_argument("--dphi", type=float, help="interommatidial angle (deg); default 2")
    e.add_argument("--field-size", type=float, help="LC receptive-field size (deg); default 10")
    e.add_argument("--duration", type=float, help="stimulus duration (s)")
    e.add_argument("--tf", type=float, nargs="+", help="tf-tuning: temporal frequencies (Hz)")
    e.add_argument("--contrast", type=float, nargs="+", help="tf-tuning: contrasts")
    e.add_argument("--wavelength", type=float, default=20.0, help="tf-tuning: wavelength (deg)")
    e.add_argument("--stimulus", choices=["rings", "grating"], default="rings", help="tf-tuning stimulus")
    e.add_argument("--l-over-v", type=float, nargs="+", help="looming: l/|v| values (s)")
    e.add_argument("--fields", type=int, nargs="+", help="rf-map: field indices to map (default all)")
    e.add_argument("--device", default="cpu")
    e.add_argument("--out", required=True, help="output NetCDF (written atomically)")
    e.add_argument("--plot", help="PNG of the protocol's figure")
    e.set_defaults(func=main)
    return e


def _config_from_args(args) -> EphysConfig:
    cfg = EphysConfig(trials=args.trials, seed=args.seed, device=args.device)
    if args.dphi:
        cfg = replace(cfg, lattice=replace(cfg.lattice, dphi_deg=args.dphi))
    if args.field_size:
        pop = cfg.circuit.population
        cfg = replace(cfg, circuit=replace(cfg.circuit, population=replace(
            pop, fields=replace(pop.fields, size_deg=args.field_size))))
    return cfg.with_tau(args.tau).with_neurons(args.neuron_model)


def main(args) -> int:
    """Handler of ``lobula ephys``: run the protocol, write the NetCDF (and PNG), print a summary."""
    from experiments.store import write_netcdf

    if args.protocol == "velocity-replay":
        from experiments.replay_protocol import plot_velocity_replay, replay_scores, velocity_replay

        ds = velocity_replay(args.footage, trials=args.trials, seed=args.seed,
                             spiking=(args.neuron_model or "poisson") != "rate", duration_s=args.duration or 10.0)
        write_netcdf(ds, args.out)
        print(f"wrote {args.out} (velocity-replay; " + ", ".join(f"{k}={v}" for k, v in ds.sizes.items()) + ")")
        for k, v in replay_scores(ds).items():
            print(f"  {k}: {v:.4f}")
        if args.plot:
            plot_velocity_replay(ds, args.plot)
            print(f"wrote {args.plot}")
        return 0
    cfg = _config_from_args(args)
    if args.protocol == "tf-tuning":
        kw = {}
        if args.tf:
            kw["temporal_frequencies_hz"] = args.tf
        if args.contrast:
            kw["contrasts"] = args.contrast
        if args.duration:
            kw["duration_s"] = args.duration
        ds = tf_tuning(cfg, wavelength_deg=args.wavelength, stimulus=args.stimulus, record=args.record, **kw)
        summary = [f"optimum 1/(2πτ) = {ds.attrs['optimum_hz']:.2f} Hz"]
        for v in ds.data_vars:
            if v.endswith("_peak_temporal_frequency_hz"):
                da = ds[v]
                who = "probe pairs"
                if "neuron" in da.dims:  # the push–pull expansion units are the ones this stimulus drives
                    da = da.isel(neuron=np.nonzero(ds.neuron_type.sel(neuron=da.neuron).values == "expansion")[0])
                    who = "expansion units"
                summary.append(f"{v.replace('_peak_temporal_frequency_hz', '')}: median peak over {who} "
                               f"{float(np.nanmedian(da.values)):.2f} Hz")
    elif args.protocol == "rf-map":
        ds = rf_map(cfg, fields=args.fields, record=args.record)
        f = json.loads(ds.attrs["parameters"])["fields"]
        err = np.hypot(ds.rf_centre_azimuth_deg - ds.field_azimuth_deg,
                       ds.rf_centre_elevation_deg - ds.field_elevation_deg).sel(field=f)
        summary = [f"{len(f)} fields: centre error median {float(err.median()):.2f}°, "
                   f"size {float(ds.rf_size_deg.sel(field=f).median()):.1f}° "
                   f"(designed {float(ds.field_size_deg.sel(field=f).median()):.1f}°)"]
    else:
        kw = {"l_over_v_s": args.l_over_v} if args.l_over_v else {}
        if args.duration:
            kw["duration_s"] = args.duration
        ds = looming(cfg, record=args.record, **kw)
        summary = []
        for v in ds.data_vars:
            if v.endswith("_peak") and "neuron" in ds[v].dims:
                ex = ds[v].isel(neuron=np.nonzero(ds.neuron_type.sel(neuron=ds[v].neuron).values == "expansion")[0])
                m = ex.mean([d for d in ex.dims if d not in ("motion",)])
                summary.append(f"{v}: expansion units approach {float(m.sel(motion='approach')):.3g} vs "
                               f"recede {float(m.sel(motion='recede')):.3g}")
    write_netcdf(ds, args.out)
    dims = ", ".join(f"{k}={v}" for k, v in ds.sizes.items())
    print(f"wrote {args.out} ({args.protocol}; {dims})")
    for line in summary:
        print("  " + line)
    if args.plot:
        plot_recording(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0
