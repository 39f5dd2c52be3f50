"""The recorded circuit: photoreceptors → EMD array → LC population → LC neurons, stepped in time.

Each stage is its own module's implementation: :mod:`lobula.photoreceptor`
(photoreceptor_run), :mod:`lobula.emd` (emd_run: the Hassenstein–Reichardt array),
:mod:`lobula.population` (matched filters, normalisation pool, pathways, LC neurons).
:class:`Circuit` streams a stimulus through them in time chunks, batched over stimulus
conditions B (deterministic front end) and trials K (the neurons' noise), and returns
what a monitor asked for (:data:`FRONT_END_RECORDS`, :data:`FIELD_RECORDS`,
:data:`UNIT_RECORDS`, :data:`NEURON_RECORDS`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Callable, NamedTuple

import numpy as np

from ._optional import torch
from .emd import EMDConfig, EMDState, emd_init, emd_run
from .lc_config import _positive
from .photoreceptor import PhotoreceptorConfig, PhotoreceptorState, photoreceptor_init, photoreceptor_run
from .population import (FIELD_RECORDS, FRONT_END_RECORDS, NEURON_RECORDS, UNIT_RECORDS, LCNeurons, LCPopulation,
                         LCPopulationConfig, PopulationState)

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["CircuitConfig", "CircuitState", "Circuit"]


@dataclass(frozen=True)
class CircuitConfig:
    """The recorded circuit: photoreceptors → EMD array → LC population, at a fixed step.

    photoreceptor: 10 ms low-pass and an LMC-like 0.25 s high-pass (the fly's EMD inputs
        L1/L2 are transient; without it the mean luminance leaks into the correlator's
        instantaneous output). emd: τ = 35 ms (optimum 4.5 Hz, blowfly HS cells).
    population: the LC population (:class:`lobula.lc_config.LCPopulationConfig`).
    dt_s: simulation step (s), 1 ms (the ephys protocols' resolution). chunk_steps: time
        steps processed per batch (memory and speed only; results do not depend on it).
    compile: fuse the first pooling stage (pairs → subunits, with the gain pool) with
        ``torch.compile`` (inductor; needs a C++ compiler on CPU, Triton on GPU), after a
        one-off compilation (cached on disk between runs). Same results.
    """

    photoreceptor: PhotoreceptorConfig = field(default_factory=lambda: PhotoreceptorConfig(tau_s=0.010, tau_hp_s=0.25))
    emd: EMDConfig = field(default_factory=lambda: EMDConfig(tau_s=0.035))
    population: LCPopulationConfig = field(default_factory=LCPopulationConfig)
    dt_s: float = 0.001
    chunk_steps: int = 16
    compile: bool = False

    def __post_init__(self):
        _positive(self, "dt_s")
        if not (isinstance(self.chunk_steps, int) and self.chunk_steps >= 1):
            raise ValueError(f"chunk_steps must be a positive integer, got {self.chunk_steps!r}")

    def to_dict(self) -> dict:
        """Every field as a dict, nested configurations as dicts."""
        return asdict(self)



# =========================================================================== the circuit


class CircuitState(NamedTuple):
    """Everything a stream needs to continue: photoreceptors, the EMD array's
    :class:`lobula.emd.EMDState` (low-pass and last input, (B, n)), LC pool and pathways,
    LC neurons (B, K, U)."""

    pr: PhotoreceptorState
    emd: EMDState
    population: PopulationState
    neurons: object


class Circuit:
    """Photoreceptors → EMD array → LC population → LC neurons, stepped at ``config.dt_s``.

    lattice: a :class:`lobula.lattice.Lattice`; config: :class:`CircuitConfig`; device:
    where it runs. The EMD stage is :func:`lobula.emd.emd_run` over all neighbour pairs
    (the code base's one correlator), streamed chunk by chunk with its state.
    """

    def __init__(self, lattice, config: CircuitConfig | None = None, device="cpu"):
        self.lattice = lattice
        self.config = cfg = config or CircuitConfig()
        self.device = torch.device(device)
        self.population = LCPopulation(lattice, cfg.population, cfg.emd.tau_s)
        self.neurons = LCNeurons(cfg.population.neurons)
        self._AB = torch.cat([torch.as_tensor(lattice.pairs_a, dtype=torch.long),
                              torch.as_tensor(lattice.pairs_b, dtype=torch.long)]).to(self.device)
        self._R_buffer = None
        self._pool = self.population.pool_pairs
        if cfg.compile:
            self._pool = torch.compile(self.population.pool_pairs, dynamic=False)

    @property
    def gradient(self) -> bool:
        """Whether the LC pool normalises by the gradient ratio (normalisation "gradient-ratio")."""
        return self.config.population.normalisation.kind == "gradient-ratio"

    def available(self) -> tuple:
        """Names this circuit can record (the neuron variables depend on the LC neuron model)."""
        return FRONT_END_RECORDS + FIELD_RECORDS + UNIT_RECORDS + self.neurons.records

    def to_dict(self) -> dict:
        """Configuration of the circuit, lattice and population, for the attrs of an output file."""
        return {"circuit": self.config.to_dict(), "lattice": self.lattice.to_dict(),
                "population": self.population.to_dict()}

    # -- state
    def init_state(self, baseline, batch: int, trials: int = 1, dtype=torch.float32,
                   generator: torch.Generator | None = None) -> CircuitState:
        """Every stage at rest and adapted to a static ``baseline`` luminance (the stimulus' units; scalar, (n,)
        or (B, n)), as after a long blank at the stimulus' mean luminance: ``batch`` B conditions, ``trials``
        K, tensors in ``dtype``; ``generator``: the torch generator of the LC neurons' starting noise."""
        n = self.lattice.n
        x0 = torch.as_tensor(baseline, dtype=dtype, device=self.device)
        x0 = x0.expand(batch, n).clone() if x0.dim() < 2 else x0.clone()
        pr = photoreceptor_init(self.config.photoreceptor, x0)
        y0, pr = photoreceptor_run(self.config.photoreceptor, self.config.dt_s, x0.unsqueeze(1), pr)
        y0 = y0[:, 0]
        den0 = None
        if self.gradient:
            _, den0 = self.population.pool_pairs(torch.zeros(batch, self.lattice.n_pairs, dtype=dtype,
                                                             device=self.device), y0)
        pop = self.population.init_state(den0, batch, self.device, dtype)
        neu = self.neurons.init_state((batch, trials, self.population.n_units), self.device, dtype, generator)
        return CircuitState(pr, emd_init(y0), pop, neu)

    # -- one chunk
    def _advance(self, x: Tensor, state: CircuitState, want: dict, generator) -> tuple[dict, CircuitState]:
        """x: (B, Tc, n) luminance → records (time-major: (Tc, B, …) or (Tc, B, K, U)), new state."""
        cfg = self.config
        dt = cfg.dt_s
        y, pr = photoreceptor_run(cfg.photoreceptor, dt, x, state.pr)          # (B, Tc, n)
        # R's storage is reused chunk to chunk unless it is recorded (a fresh block this large is
        # page-faulted in anew each chunk, which cost more than the correlator itself).
        P, Tc, B = self.lattice.n_pairs, y.shape[1], y.shape[0]
        buf = None
        if "emd.response" not in want:
            buf = self._R_buffer
            if buf is None or buf.shape != (P, Tc, B) or buf.dtype != y.dtype or buf.device != y.device:
                buf = self._R_buffer = y.new_empty((P, Tc, B))
        R, emd_state = emd_run(cfg.emd, dt, y, None, None, state.emd, pair_index=self._AB, out=buf)  # (B, Tc, P)
        out = {}
        if "photoreceptor.v" in want:
            out["photoreceptor.v"] = _select(y, want["photoreceptor.v"]).transpose(0, 1)
        if "emd.response" in want:
            out["emd.response"] = _select(R, want["emd.response"]).transpose(0, 1)
        # Pool in the (B, Tc, ·) layout emd_run returns (gathers along a transposed view are
        # several times slower); only the small subunit sums are made time-major.
        num_s, den_s = self._pool(R, y if self.gradient else None)
        num_s = num_s.transpose(0, 1).contiguous()
        den_s = den_s.transpose(0, 1).contiguous() if den_s is not None else None
        rec, pop = self.population.advance(num_s, den_s, state.population, dt, set(want))
        for name in FIELD_RECORDS + UNIT_RECORDS:
            if name in want:
                out[name] = _select(rec[name], want[name])
        neu = state.neurons
        nw = [k for k in want if k in NEURON_RECORDS]
        if nw:
            _, K, U_ = self.neurons.shape(neu)
            bufs = {k: torch.empty((R.shape[1], R.shape[0], K, U_), dtype=x.dtype, device=x.device) for k in nw}
        drv = rec["lc.drive"].unsqueeze(2)                                   # (Tc, B, 1, U)
        for t in range(R.shape[1] if nw else 0):  # neuron dynamics (only when recorded), vectorised over B × K × U
            neu = self.neurons.step(neu, drv[t], dt, generator)
            for k in nw:
                bufs[k][t] = self.neurons.read(neu, k)
        for k in nw:
            out[k] = _select(bufs[k], want[k])
        return out, CircuitState(pr, emd_state, pop, neu)

    # -- a whole run
    def run(self, stimulus, n_steps: int | None = None, *, trials: int = 1, record=("lc.rate",),
            state: CircuitState | None = None, seed: int | None = 0, baseline=None,
            callback: Callable | None = None, return_state: bool = False):
        """Run a stimulus through the circuit and record what ``record`` names.

        stimulus: luminance (B, T, n) or (T, n) tensor, or a callable ``(start, stop) →
            (B, stop − start, n)`` (e.g. :class:`stimuli.lattice_stimuli.GratingSource`)
            with ``n_steps``; sampled every ``config.dt_s`` seconds.
        trials: K repeats of every condition; the front end is deterministic and runs
            once per condition, the LC neurons run K times (their noise differs).
        record: names from :meth:`available`, or a dict name → indices (a subset of
            ommatidia, pairs, fields or units, like a Brian2 monitor's ``record=``).
        seed: seeds the neurons' noise (same seed, same arrays). baseline: luminance the
            eye is adapted to before the stimulus (default: the first frame's mean over
            ommatidia, per condition). callback: ``callback(start, records)`` gets each
            chunk's records (time-major) instead of accumulating them (for long sweeps).
        Returns {name: tensor}: front-end and field/unit records (B, T, X), neuron
        records (B, K, T, U); with ``return_state`` also the final state.
        """
        want = _parse_record(record, self.available())
        if callable(stimulus) and not isinstance(stimulus, torch.Tensor):
            if n_steps is None:
                raise ValueError("a stimulus callable needs n_steps")
            source = stimulus
        else:
            stim = torch.as_tensor(stimulus)
            if stim.dim() == 2:
                stim = stim.unsqueeze(0)
            if stim.dim() != 3 or stim.shape[-1] != self.lattice.n:
                raise ValueError(f"stimulus must be (conditions, time, {self.lattice.n}) or (time, {self.lattice.n}) "
                                 f"for this lattice, got shape {tuple(stim.shape)}")
            n_steps = stim.shape[1] if n_steps is None else int(n_steps)
            source = lambda a, b: stim[:, a:b]  # noqa: E731
        first = source(0, 1)
        first = first.unsqueeze(0) if first.dim() == 2 else first
        B = first.shape[0]
        dtype = first.dtype if first.is_floating_point() else torch.float32
        gen = None
        if self.neurons.stochastic:
            if seed is None:
                raise ValueError("stochastic LC units (Poisson or noisy LIF) need an integer seed")
            gen = torch.Generator(device=self.device)
            gen.manual_seed(int(seed))
        if state is None:
            if baseline is None:
                baseline = first[:, 0].to(dtype).mean(dim=-1, keepdim=True).expand(B, self.lattice.n)
            state = self.init_state(baseline, B, trials, dtype, gen)
        chunks: dict = {k: [] for k in want}
        step = self.config.chunk_steps
        for a in range(0, n_steps, step):  # time chunks: memory and speed only
            b = min(n_steps, a + step)
            x = source(a, b)
            x = (x.unsqueeze(0) if x.dim() == 2 else x).to(device=self.device, dtype=dtype)
            rec, state = self._advance(x, state, want, gen)
            if callback is not None:
                callback(a, rec)
            else:
                for k, val in rec.items():
                    if k in chunks:
                        chunks[k].append(val)
        out = {}
        if callback is None:
            for k, parts in chunks.items():
                full = torch.cat(parts, dim=0)                                      # (T, B, …)
                out[k] = full.movedim(0, 2) if k in NEURON_RECORDS else full.movedim(0, 1)
        return (out, state) if return_state else out


def _select(x: Tensor, idx) -> Tensor:
    return x if idx is None else x.index_select(-1, torch.as_tensor(idx, dtype=torch.long, device=x.device))


def _parse_record(record, available) -> dict:
    """record names or {name: indices} → {name: LongTensor or None}, checked."""
    items = record.items() if isinstance(record, dict) else ((r, None) for r in ([record] if isinstance(record, str) else record))
    want = {}
    for name, idx in items:
        if name not in available:
            raise ValueError(f"cannot record {name!r}: this circuit records {list(available)}")
        want[name] = None if idx is None else torch.as_tensor(np.asarray(idx), dtype=torch.long)
    return want
