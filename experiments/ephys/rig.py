"""The recording layer of virtual electrophysiology: the rig, its monitors, and labelled, self-describing data.

A *rig* is a lattice (the eye) and a :class:`lobula.circuit.Circuit` stepped at ``dt``.
*Monitors*, chosen like Brian2's (``"POPULATION.VARIABLE"`` with an optional subset),
say what to record. :func:`record_dataset` turns the circuit's tensors into an
:class:`xarray.Dataset`; :func:`recording_attrs` and :func:`cf_describe` make every
recording self-describing (CF-1.10: units and long_name on every variable and
coordinate; configuration, version, commit, command line, creation time). Nothing here
depends on the circuit's parameters: a protocol names what it records, this layer
labels whatever the circuit returns.
"""
from __future__ import annotations

import json
import re
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.camera import PinholeCamera, normalised_to_angles
from lobula.circuit import Circuit, CircuitConfig
from lobula.lattice import Lattice, LatticeConfig
from lobula.motion_pathways import DIRECTIONS, OnOffConfig
from lobula.population import FIELD_RECORDS, NEURON_RECORDS, UNIT_RECORDS, config_from_dict
from lobula.tangential_cells import TangentialConfig

__all__ = ["EphysConfig", "Rig", "Monitor", "parse_monitor", "monitors_for", "record_dataset", "dim_coords",
           "recording_attrs", "cf_describe", "torch_threads", "VARIABLES", "neuron_model_attrs", "trial_seed",
           "PATHWAY_RECORDS", "LAYER_RECORDS", "direction_layer"]

#: what each monitor variable is: (units (UDUNITS), long_name). Spike counts are per model step.
VARIABLES = {
    "photoreceptor.v": ("1", "photoreceptor output (LMC-like high-passed relative luminance)"),
    "emd.response": ("1", "EMD opponent (Hassenstein-Reichardt) response, photoreceptor output squared"),
    "lc.input": ("1", "LC matched-filter input before the divisive pool, per unit template gain"),
    "lc.r": ("s-1", "LC field expansion rate estimate r"),
    "lc.r2": ("s-2", "LC field mean squared expansion rate"),
    "lc.rdot": ("s-2", "LC field rate of change of the expansion rate"),
    "lc.drive": ("1", "LC unit drive (dimensionless)"),
    "lc.rate": ("Hz", "LC unit firing rate"),
    "lc.x": ("1", "LC rate unit integrated drive"),
    "lc.v": ("V", "LC unit membrane potential"),
    "lc.spikes": ("1", "LC unit spike count per model time step"),
    "t4.response": ("1", "T4 (ON x ON) half-correlator output per preferred direction, photoreceptor output squared"),
    "t5.response": ("1", "T5 (OFF x OFF) half-correlator output per preferred direction, photoreceptor output squared"),
    "hs.v": ("mV", "HS cell membrane potential relative to rest"),
    "vs.v": ("mV", "VS cell membrane potential relative to rest"),
}

#: the lobula-plate variables the rig computes from the photoreceptor output, only when monitored
PATHWAY_RECORDS = ("t4.response", "t5.response", "hs.v", "vs.v")
#: the variables with a T4/T5 layer (preferred-direction) dim after the ommatidium dim
LAYER_RECORDS = ("t4.response", "t5.response")

#: which neuron model records which neuron variable (the fix to name when one is asked for in vain)
_MODEL_FOR = {"lc.spikes": "poisson or lif", "lc.v": "lif", "lc.rate": "rate or poisson", "lc.x": "rate or poisson"}


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
    on_off: the lamina ON/OFF split and the T4/T5 correlators (:class:`lobula.motion_pathways.OnOffConfig`);
        tangential: the HS/VS cells (:class:`lobula.tangential_cells.TangentialConfig`). Both act only
        when a monitor records t4.response, t5.response, hs.v or vs.v.
    trials: repeats per condition (a deterministic neuron model stores one: its trials
        would be identical); seed: the neurons' noise; device: "cpu" or "cuda".
    threads: torch CPU threads while a protocol runs (None: torch's default). 1 by
        default: the per-step tensors are small, and on a shared machine a second
        OpenMP thread waiting for a busy core made runs 5–10× slower (measured).
    """

    lattice: LatticeConfig = field(default_factory=lambda: LatticeConfig(dphi_deg=2.0))
    camera_scale: float = 0.5
    circuit: CircuitConfig = field(default_factory=CircuitConfig)
    on_off: OnOffConfig = field(default_factory=OnOffConfig)
    tangential: TangentialConfig = field(default_factory=TangentialConfig)
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

    def with_fields(self, **kw) -> "EphysConfig":
        """The same rig with LC receptive-field settings replaced (size_deg, centres_deg, shape, …)."""
        pop = self.circuit.population
        return replace(self, circuit=replace(self.circuit, population=replace(pop, fields=replace(pop.fields, **kw))))


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


def protocol(impl, config_type, doc: str | None = None):
    """The public form of a protocol ``impl(cfg, **kw)``: ``config`` defaults to
    ``config_type()``, and the protocol runs with that configuration's torch threads."""
    def run(config=None, **kw):
        cfg = config or config_type()
        with torch_threads(cfg.threads):
            return impl(cfg, **kw)
    run.__name__ = run.__qualname__ = impl.__name__.lstrip("_")
    run.__doc__ = doc or impl.__doc__
    return run


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

    @property
    def neuron_model(self) -> str:
        return self.config.circuit.population.neurons.model

    @property
    def stochastic(self) -> bool:
        """Whether trials differ (Poisson spikes, noisy LIF); a deterministic model stores one trial."""
        return self.circuit.neurons.stochastic

    @property
    def stored_trials(self) -> int:
        return self.config.trials if self.stochastic else 1

    def default_records(self) -> tuple:
        """The neuron variables worth recording for this neuron model."""
        return {"rate": ("lc.rate",), "poisson": ("lc.rate", "lc.spikes"),
                "lif": ("lc.v", "lc.spikes")}[self.neuron_model]

    def available(self) -> tuple:
        """Names this rig records: the circuit's and the lobula plate's (:data:`PATHWAY_RECORDS`)."""
        return self.circuit.available() + PATHWAY_RECORDS

    def run(self, stimulus, n_steps, monitors, *, baseline=None) -> dict:
        """Run the circuit on a stimulus, recording the monitors; trials as :attr:`stored_trials`.

        The front end (deterministic) runs once; the LC units then run once per trial, trial k
        on its own random stream :func:`trial_seed` (seed, k), so trial k holds the same spikes
        whatever the number of trials. The lobula plate (T4/T5, HS/VS:
        :func:`experiments.ephys.edges.plate_records`) runs on the same photoreceptor output,
        only when a monitor records it. Returns {variable: tensor}:
        (B, T, X); neuron variables (B, K, T, U); T4/T5 (B, T, X, L), L their layers."""
        rec = {m.variable: m.neurons for m in monitors}
        plate = [m for m in monitors if m.variable in PATHWAY_RECORDS]
        if not plate:
            return self._run_circuit(stimulus, n_steps, rec, baseline)
        for m in plate:
            del rec[m.variable]
        own = rec.get("photoreceptor.v", ())                 # () : photoreceptor.v not monitored itself
        rec["photoreceptor.v"] = None
        out = self._run_circuit(stimulus, n_steps, rec, baseline)
        y = out.pop("photoreceptor.v") if own == () else out["photoreceptor.v"]
        if own:
            out["photoreceptor.v"] = y.index_select(-1, torch.as_tensor(own, dtype=torch.long, device=y.device))
        from .edges import plate_records  # the lobula plate's module imports this one

        out.update(plate_records(self, y, plate))
        return out

    def _run_circuit(self, stimulus, n_steps, rec: dict, baseline) -> dict:
        """:meth:`run` for the circuit's own variables, ``rec`` {variable: indices or None}."""
        if not self.stochastic:
            return self.circuit.run(stimulus, n_steps, trials=1, record=rec, seed=self.config.seed,
                                    baseline=baseline)
        neuron = {k: v for k, v in rec.items() if k in NEURON_RECORDS}
        front = {k: v for k, v in rec.items() if k not in NEURON_RECORDS}
        out = self.circuit.run(stimulus, n_steps, trials=1, record={**front, "lc.drive": None}, seed=self.config.seed,
                               baseline=baseline)
        drive = out["lc.drive"]                                              # (B, T, U)
        if "lc.drive" in front and front["lc.drive"] is not None:
            out["lc.drive"] = drive.index_select(-1, torch.as_tensor(front["lc.drive"], device=drive.device))
        elif "lc.drive" not in front:
            del out["lc.drive"]
        neurons, dt = self.circuit.neurons, self.dt
        B, T, U = drive.shape
        per_trial = {k: [] for k in neuron}
        for trial in range(self.stored_trials):
            gen = torch.Generator(device=drive.device)
            gen.manual_seed(trial_seed(self.config.seed, trial))
            state = neurons.init_state((B, 1, U), drive.device, drive.dtype, gen)
            bufs = {k: drive.new_empty((T, B, 1, U)) for k in neuron}
            for t in range(T):  # the circuit's own neuron step, on this trial's stream
                state = neurons.step(state, drive[:, t].unsqueeze(1), dt, gen)
                for k in neuron:
                    bufs[k][t] = neurons.read(state, k)
            for k, idx in neuron.items():
                x = bufs[k].movedim(0, 2)                                    # (B, 1, T, U)
                per_trial[k].append(x if idx is None else
                                    x.index_select(-1, torch.as_tensor(idx, device=x.device)))
        out.update({k: torch.cat(v, dim=1) for k, v in per_trial.items()})
        return out


def trial_seed(seed: int, trial: int) -> int:
    """The seed of trial ``trial``'s random stream, a function of (seed, trial) alone, the same for every
    number of trials: trial 0 takes ``seed`` itself (a one-trial recording is the pipeline run with that
    seed), trial k > 0 numpy's ``SeedSequence(seed).spawn(n)[k]`` (entropy ``seed``, spawn key ``(k,)``)."""
    if int(trial) == 0:
        return int(seed)
    return int(np.random.SeedSequence(int(seed), spawn_key=(int(trial),)).generate_state(1, np.uint64)[0]
               & 0x7FFF_FFFF_FFFF_FFFF)


# =========================================================================== monitors

@dataclass(frozen=True)
class Monitor:
    """What to record: ``variable`` ("lc.rate", …), an optional subset ``neurons`` (indices: units, fields,
    pairs, ommatidia or HS/VS cells) and, for T4/T5, ``layers`` (indices into
    :data:`lobula.motion_pathways.DIRECTIONS`; None: all four)."""

    variable: str
    neurons: tuple | None = None
    layers: tuple | None = None

    @property
    def name(self) -> str:
        return self.variable.replace(".", "_")


_MONITOR = re.compile(r"^\s*([a-z_][a-z_0-9]*\.[a-z_0-9]+)\s*(?:\[(.*)\])?\s*$")


def _size(rig: Rig, var: str) -> int:
    pop, n = rig.population, rig.lattice.n
    return {"photoreceptor.v": n, "emd.response": rig.lattice.n_pairs, "t4.response": n, "t5.response": n,
            "hs.v": rig.config.tangential.n_hs, "vs.v": rig.config.tangential.n_vs}.get(
        var, pop.n_fields if var in FIELD_RECORDS else pop.n_units)


def _valid(rig: Rig) -> str:
    return (f"this rig ({rig.neuron_model} LC units) records {', '.join(rig.available())}; subsets: "
            f"[i:j], [i,j,k], for LC unit variables a unit type [{', '.join(rig.population.types)}], for "
            f"T4/T5 preferred directions [{', '.join(d.replace('_', '-') for d in DIRECTIONS)}]")


def empty_slice(spec: str, var: str, sub: str, size: int) -> str:
    """The error of a subset ``[i:j]`` that selects none of ``var``'s ``size`` indices (j ≤ i, or past the end)."""
    return (f"{spec!r}: the slice [{sub}] selects nothing; give [i:j] with 0 ≤ i < j ≤ {size} ({var} has {size} "
            f"indices, 0 to {size - 1}: e.g. {var}[0:{size}])")


def direction_layer(name: str) -> int | None:
    """The T4/T5 layer of a direction name (front-to-back or front_to_back, …), or None if it is none."""
    key = name.strip().replace("-", "_")
    return DIRECTIONS.index(key) if key in DIRECTIONS else None


def parse_monitor(spec: str | Monitor, rig: Rig) -> Monitor:
    """``"POP.VAR"``, ``"POP.VAR[i:j]"``, ``"POP.VAR[i,j,k]"`` or ``"lc.VAR[TYPE]"`` → :class:`Monitor`.

    Variables: photoreceptor.v, emd.response, lc.input, lc.r, lc.r2, lc.rdot, lc.drive,
    lc.rate, lc.x (rate/Poisson units), lc.v (LIF), lc.spikes (Poisson/LIF), t4.response,
    t5.response (ommatidium × preferred direction), hs.v, vs.v (one per cell). A type name
    (expansion, contraction, r2, rdot+, rdot-) selects LC units of that type; direction names
    (front-to-back, back-to-front, upward, downward; comma-separated) select T4/T5 layers, an
    index subset their ommatidia. Errors name the fix (the neuron model that records a
    variable, the valid names and subsets).
    """
    if isinstance(spec, Monitor):
        return spec
    m = _MONITOR.match(spec)
    available = rig.available()
    if m and m.group(1) in _MODEL_FOR and m.group(1) not in available:
        raise ValueError(f"cannot record {spec!r}: {rig.neuron_model} LC units have no {m.group(1)}; use "
                         f"--neuron-model {_MODEL_FOR[m.group(1)]} (EphysConfig.with_neurons); {_valid(rig)}")
    if not m or m.group(1) not in available:
        raise ValueError(f"cannot record {spec!r}: use POPULATION.VARIABLE[subset]; {_valid(rig)}")
    var, sub = m.group(1), m.group(2)
    if sub is None or not sub.strip():
        return Monitor(var, None)
    sub = sub.strip()
    pop = rig.population
    layers = [direction_layer(p) for p in sub.split(",")]
    if any(x is not None for x in layers):
        if var not in LAYER_RECORDS:
            raise ValueError(f"{spec!r}: a direction selects T4/T5 layers, and {var} has none; record "
                             f"t4.response[{sub}] or t5.response[{sub}], or give {var} an index subset [i:j]")
        if None in layers:
            raise ValueError(f"{spec!r}: give directions only ({', '.join(DIRECTIONS)}, with - or _), or an "
                             f"index subset of ommatidia [i:j], not both")
        return Monitor(var, None, tuple(sorted(set(layers))))
    if sub in pop.types:
        if var not in UNIT_RECORDS + NEURON_RECORDS:
            raise ValueError(f"{spec!r}: a unit type selects LC units, and {var} is not a per-unit variable; "
                             f"use an index subset [i:j] or a unit variable (lc.drive, {', '.join(rig.circuit.neurons.records)})")
        return Monitor(var, tuple(int(i) for i in pop.units_of(sub)))
    size = _size(rig, var)
    try:
        if ":" in sub:
            parts = [int(p) if p.strip() else None for p in sub.split(":")]
            idx = tuple(range(size))[slice(*parts)]
        else:
            idx = tuple(int(p) for p in sub.split(","))
    except (ValueError, TypeError):
        raise ValueError(f"{spec!r}: the subset must be i:j, i,j,k, a unit type {list(pop.types)} or, for T4/T5, "
                         f"directions {[d.replace('_', '-') for d in DIRECTIONS]}") from None
    if not idx and ":" in sub:
        raise ValueError(empty_slice(spec, var, sub, size))
    if not idx or min(idx) < -size or max(idx) >= size:
        raise ValueError(f"{spec!r}: indices must lie in [0, {size}) for {var}")
    return Monitor(var, tuple(i % size for i in idx))


def monitors_for(rig: Rig, record, default) -> list[Monitor]:
    """Parse ``record`` (or ``default`` when None/empty) into monitors; each variable once."""
    specs = list(default if not record else record)
    mons = [parse_monitor(s, rig) for s in specs]
    names = [m.variable for m in mons]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ValueError(f"record each variable once (with one subset); repeated: {sorted(dup)}")
    return mons


# =========================================================================== recording → Dataset

def _neuron_dim(var: str) -> str:
    if var in ("photoreceptor.v",) + LAYER_RECORDS:
        return "ommatidium"
    if var in ("hs.v", "vs.v"):
        return var[:2] + "_cell"
    if var == "emd.response":
        return "pair"
    return "field" if var in FIELD_RECORDS else "neuron"


def dim_coords(rig: Rig, dim: str, idx) -> dict:
    """Coordinates of one neuron-like dim ("ommatidium", "pair", "field", "neuron", "hs_cell", "vs_cell")
    for indices idx (None: all)."""
    lat, pop = rig.lattice, rig.population
    sel = (lambda a: a) if idx is None else (lambda a: np.asarray(a)[np.asarray(idx)])
    if dim in ("hs_cell", "vs_cell"):
        from .edges import cell_coords

        return {k: (v[0], sel(v[1]), *v[2:]) if isinstance(v, tuple) else sel(v)
                for k, v in cell_coords(rig, dim).items()}
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


def neuron_model_attrs(rig: Rig) -> dict:
    """What a spiking or membrane variable needs to be read: the neuron model, its step and its parameters."""
    nc = rig.config.circuit.population.neurons
    params = {"rate": nc.rate, "poisson": {"rate": nc.rate, "poisson": nc.poisson},
              "lif": {"lif": nc.lif, "gain_A": nc.lif_gain_A, "bias_A": nc.lif_bias_A}}[nc.model]
    return {"neuron_model": nc.model, "dt_s": rig.dt,
            "neuron_parameters": json.dumps(params, default=lambda o: asdict(o) if hasattr(o, "__dataclass_fields__")
                                            else str(o), sort_keys=True)}


def _spread(arr: np.ndarray, axis: int, own, idx, size: int) -> np.ndarray:
    """``arr`` holding indices ``own`` (None: all ``size``) along ``axis``, placed on the dim's union
    ``idx`` (None: all), NaN where the monitor did not record."""
    if (own is None and idx is None) or (own is not None and idx is not None and np.array_equal(own, idx)):
        return arr
    where = np.searchsorted(idx, np.asarray(own)) if idx is not None else np.asarray(own)
    shape = list(arr.shape)
    shape[axis] = len(idx) if idx is not None else size
    filled = np.full(shape, np.nan, dtype=arr.dtype)
    np.moveaxis(filled, axis, -1)[..., where] = np.moveaxis(arr, axis, -1)
    return filled


def record_dataset(rig: Rig, records: dict, monitors: list, cond: dict, n_steps: int, attrs: dict,
                   time_offset_s: float = 0.0) -> xr.Dataset:
    """Labelled arrays from :meth:`Circuit.run` output.

    records: {variable: tensor (B, T, X) or (B, K, T, X), T4/T5 (B, T, X, L)}; cond: ordered
    {dim: values} whose product of lengths is B (the conditions, row-major); n_steps: T.
    Monitors that record different subsets of one dim share it: its coordinate is the union
    of their indices, and a variable is NaN where its monitor did not record (T4/T5 layers
    alike, dim ``preferred_direction``). time_offset_s: the
    time coordinate is ``step·dt − time_offset_s`` (looming: relative to collision).
    """
    cdims = list(cond)
    cshape = [len(v) for v in cond.values()]
    t = np.arange(n_steps) * rig.dt - time_offset_s
    coords = {"time": ("time", t), **{k: (k, np.asarray(v)) for k, v in cond.items()}}
    union: dict = {}
    for mon in monitors:  # (dim, the monitor's indices along it): its neuron-like dim, and T4/T5 layers
        for dim, own in [(_neuron_dim(mon.variable), mon.neurons)] + (
                [("preferred_direction", mon.layers)] if mon.variable in LAYER_RECORDS else []):
            prev = union.get(dim, set())
            union[dim] = None if own is None or prev is None else prev | set(own)
    index = {d: (None if u is None else np.array(sorted(u))) for d, u in union.items()}
    for d, idx in index.items():
        coords.update({d: np.array(DIRECTIONS)[idx if idx is not None else slice(None)]}
                      if d == "preferred_direction" else dim_coords(rig, d, idx))
    data = {}
    for mon in monitors:
        arr = records[mon.variable].detach().to("cpu").numpy()
        dim = _neuron_dim(mon.variable)
        arr = arr.reshape(cshape + list(arr.shape[1:]))
        layered = mon.variable in LAYER_RECORDS
        own = None if mon.neurons is None else np.asarray(mon.neurons)
        arr = _spread(arr, -2 if layered else -1, own, index[dim], _size(rig, mon.variable))
        if layered:
            arr = _spread(arr, -1, mon.layers, index["preferred_direction"], len(DIRECTIONS))
        if mon.variable == "lc.spikes" and np.isfinite(arr).all():
            arr = arr.astype(np.uint16)  # whole counts per step: 2 bytes, not 4 (a 1 ms step holds < 65536)
        dims = (cdims + (["trial"] if mon.variable in NEURON_RECORDS else []) + ["time", dim]
                + (["preferred_direction"] if layered else []))
        units, long_name = VARIABLES[mon.variable]
        a = {"units": units, "long_name": long_name, "monitor": mon.variable,
             "recorded": "all" if own is None else json.dumps(own.tolist())}
        if layered:
            a["recorded_layers"] = "all" if mon.layers is None else json.dumps([DIRECTIONS[i] for i in mon.layers])
        if mon.variable in NEURON_RECORDS:
            a.update(neuron_model_attrs(rig))
        if mon.variable == "lc.spikes":
            a["note"] = ("spike counts in each model step of dt_s; a spike's time is its step's start, the time "
                         "coordinate (the same in the NWB Units table)")
        data[mon.name] = (dims, arr, a)
    ds = xr.Dataset(data, coords=coords)
    if any(m.variable in NEURON_RECORDS for m in monitors):
        ds = ds.assign_coords(trial=np.arange(ds.sizes["trial"]))
    ds.attrs.update(attrs)
    return ds


# =========================================================================== self-description

#: units and long names of coordinates and analysis variables, by name
DESCRIPTIONS = {
    "time": ("s", "time since stimulus onset"),
    "trial": ("1", "trial index"),
    "neuron": ("1", "LC unit index"), "neuron_type": (None, "LC unit type"),
    "field_index": ("1", "index of the unit's LC receptive field"),
    "azimuth_deg": ("degree", "receptive-field centre azimuth"),
    "elevation_deg": ("degree", "receptive-field centre elevation (positive down)"),
    "size_deg": ("degree", "receptive-field size (FWHM or box side)"),
    "field": ("1", "LC receptive-field index"),
    "field_azimuth_deg": ("degree", "receptive-field centre azimuth"),
    "field_elevation_deg": ("degree", "receptive-field centre elevation (positive down)"),
    "field_size_deg": ("degree", "receptive-field size (FWHM or box side)"),
    "ommatidium": ("1", "ommatidium index"),
    "ommatidium_azimuth_deg": ("degree", "ommatidium viewing azimuth"),
    "ommatidium_elevation_deg": ("degree", "ommatidium viewing elevation (positive down)"),
    "pair": ("1", "EMD (neighbour pair) index"),
    "pair_azimuth_deg": ("degree", "EMD pair midpoint azimuth"),
    "pair_elevation_deg": ("degree", "EMD pair midpoint elevation (positive down)"),
    "pair_axis": ("1", "lattice axis of the EMD pair"),
    "pair_direction_deg": ("degree", "EMD preferred direction in the image (0 right, 90 down)"),
    "temporal_frequency_hz": ("Hz", "stimulus temporal frequency"),
    "contrast": ("1", "stimulus Michelson contrast"),
    "l_over_v_s": ("s", "looming half-size over approach speed l/|v|"),
    "motion": (None, "looming disc motion (approach or recede)"),
    "location": ("1", "spot-passage location index"),
    "location_azimuth_deg": ("degree", "spot-passage centre azimuth"),
    "location_elevation_deg": ("degree", "spot-passage centre elevation (positive down)"),
    "direction_deg": ("degree", "spot motion direction in the image (0 right, 90 down)"),
    "preferred_direction": (None, "preferred direction of the T4/T5 cells (their lobula-plate layer)"),
    "hs_cell": ("1", "HS cell index (elevation bands, dorsal to ventral)"),
    "vs_cell": ("1", "VS cell index (azimuth stripes, in order of increasing azimuth)"),
}


def cf_describe(ds: xr.Dataset) -> xr.Dataset:
    """Give every variable and coordinate a ``long_name`` and (numeric ones) ``units``; set ``Conventions``.

    Known names take :data:`DESCRIPTIONS`; monitor variables already carry theirs. A
    variable without either raises (a recording must not leave the lab undescribed).
    """
    missing = []
    for name in list(ds.variables):
        da = ds[name]
        units, long_name = DESCRIPTIONS.get(name, (None, None))
        if "long_name" not in da.attrs and long_name:
            da.attrs["long_name"] = long_name
        if "units" not in da.attrs and units and da.dtype.kind in "fiub":
            da.attrs["units"] = units
        if "long_name" not in da.attrs or (da.dtype.kind in "fiub" and "units" not in da.attrs):
            missing.append(name)
    if missing:
        raise ValueError(f"recording variables without long_name/units (describe them where they are made): {missing}")
    ds.attrs["Conventions"] = "CF-1.10"
    return ds


def recording_attrs(protocol: str, config: dict, parameters: dict, **common) -> dict:
    """The attributes every ephys recording carries, whatever the protocol.

    config: the whole configuration (written as JSON); parameters: the protocol's stimulus
    settings; common: dt_s, trials, trials_requested, seed, neuron_model,
    neuron_parameters, emd_tau_s. Adds version, commit, command line and creation time
    (:func:`experiments.store.provenance`) and CF's title, source and history.
    """
    from experiments.store import provenance

    attrs = provenance(json.dumps(config, sort_keys=True, default=_json_default), protocol=protocol,
                       parameters=json.dumps(parameters, sort_keys=True, default=_json_default))
    attrs.update({k: (v if isinstance(v, (str, int, float)) else json.dumps(v, default=_json_default))
                  for k, v in common.items()})
    attrs.update(Conventions="CF-1.10", title=f"lobula virtual electrophysiology: {protocol}",
                 source=f"lobula {attrs.get('lobula_version', '')} model (commit {attrs.get('git_commit', 'unknown')})",
                 history=f"{attrs.get('created', '')} {attrs.get('command_line', '')}".strip())
    return attrs


def rig_attrs(rig: Rig, protocol: str, params: dict) -> dict:
    """:func:`recording_attrs` for a rig's protocol (tf-tuning, rf-map, looming)."""
    cfg = rig.config
    full = {"ephys": cfg.to_dict(), "protocol": protocol, "parameters": params,
            "lattice": {"n_ommatidia": rig.lattice.n, "n_pairs": rig.lattice.n_pairs,
                        "camera": rig.lattice.camera.to_dict()},
            "population": rig.population.to_dict()}
    nm = neuron_model_attrs(rig)
    return recording_attrs(protocol, full, params, trials=rig.stored_trials, trials_requested=cfg.trials,
                           trials_note=("" if rig.stochastic else f"the {rig.neuron_model} model is deterministic: "
                                        "every trial would be identical, one is stored"),
                           seed=cfg.seed, emd_tau_s=cfg.circuit.emd.tau_s, **nm)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if hasattr(o, "__dataclass_fields__"):
        return asdict(o)
    return str(o)
