"""Lobula-columnar (LC) populations: matched filters for expansion on the EMD array, their pathways
and neurons. :mod:`lobula.circuit` wires them behind the photoreceptors and EMDs into the circuit
that virtual electrophysiology records from; :mod:`lobula.lc_geometry` holds the templates and fields,
:mod:`lobula.lc_config` the configuration of each layer.

The LC stage
------------
Input: the opponent Hassenstein–Reichardt outputs ``R_p`` of every neighbour pair p of a
:class:`lobula.lattice.Lattice` (pair direction u_p, midpoint m_p, step Δp from A to B,
all in normalised image coordinates; see :mod:`lobula.emd`). Forward translation with
expansion rate r = v/d about the epipole e moves the image as ``ṗ = r·(p − e)``; along
pair p that is ``s_p = r·t_p`` inter-ommatidial steps per second with the
**template** ``t_p = ⟨m_p − e, Δp⟩ / |Δp|²``.

Each field f (receptive-field centre (az, el) and size in degrees; Gaussian of FWHM
``size`` or a box of side ``size`` in azimuth/elevation) has a **matched filter**: pair
weight ``w_f(p)·μ_p`` with ``μ_p = ⟨u_p, (m_p − e)/|m_p − e|⟩`` (``template="direction"``:
the local preferred direction of an expansion-tuned LPTC/LC dendrite, Krapp &
Hengstenberg 1996) or ``μ_p = t_p`` (``"flow"``: the least-squares matched filter of
Franz & Krapp 2000, the same estimator as :mod:`lobula.receptive_field` and the
EMD front end). The field's expansion estimate is a ratio of pooled sums,

    r̂_f = Σ_p w μ R_p / (Σ_p w μ t_p·g_p + φ_f),

with ``g_p`` the gain of pair p in R per step/s. ``normalisation="gradient-ratio"``
(default) measures it: ``g_p = 2τ·LP(G_p)``, ``G_p = (x_B − x_A)²`` the squared
contrast difference at the pair's inputs, low-passed with ``tau_s`` — a divisive,
contrast-normalising pool. At low temporal frequency (ωτ ≪ 1) and fine sampling
(Δϕ = 2πΔφ/λ ≪ 1) R̄_p = 2τ·s_p·Ḡ_p exactly (for a sine, R̄/Ḡ =
ωτ·cot(Δϕ/2)/(1+(ωτ)²), see :mod:`lobula.emd_front_end`), so C², the pattern and the
photoreceptor's attenuation all cancel and r̂_f is r in 1/s; faster motion is
underestimated by 1/(1+(ωτ)²), which is why the unit's temporal-frequency tuning still
peaks at 1/(2πτ). ``normalisation="none"`` uses ``g_p = 1``: r̂_f is then in R units
per step/s and scales with contrast² (what an un-normalised LC dendrite sums).
φ_f = ``floor``·Σ2τwμt is a semi-saturation constant (a floor on G) that keeps the
ratio finite in a featureless field.

Two-stage pooling (why): pairs are first summed into **subunits** — blocks of b×b
ommatidia of the lattice grid (``subunit_deg``; b = 1 for coarse eyes) — then fields
pool subunits with their RF weight at the subunit's centre. Biologically these are the
dendritic compartments on which T4/T5 terminals converge; computationally the first
stage is one sparse sum over pairs (``index_add``) and the second one small dense
product, which is what makes a 5,000-ommatidia eye at 1 ms steps fast.

Pathways and unit types (per field; a unit is a (type, field) pair)
- ``expansion`` / ``contraction``: a push–pull pair with drive ``±r̂_f/scale_r``;
  rectification in the neuron keeps rates ≥ 0, their difference carries the signed r.
- ``r2``: the mean of r² over the field, ``Σ_s a_fs q_s²/D_s / Σ_s a_fs D_s`` with
  q_s = LP(num_s) (``tau_local_s``) and D_s the subunit's pooled gain: the
  least-squares analogue of :func:`lobula.receptive_field.pool_fields`' r²̄ at the
  subunit scale (r²̄ ≠ r̄² when a field spans several depths).
- ``rdot+`` / ``rdot-``: a transient pathway ``(LP_fast(r̂) − LP_slow(r̂)) / (lag_slow −
  lag_fast)``, exact for a ramp in r (lags are the discrete low-passes' exact ramp lags).
Drives feed :mod:`lobula.neurons`: rate neurons (Naka–Rushton), LIF neurons (current =
bias + gain·drive) or Poisson spikes from rate neurons; :meth:`LCPopulation.decode_rates`
inverts the rate units back to (r, r²̄, ṙ) for a readout neuron to sit on.

Shapes: stimulus conditions B (front end, deterministic) × trials K (neurons, where the
noise is) × time T × units U; fields F, subunits S, ommatidia n, pairs P. Everything is
torch on CPU or GPU; Python loops run over time steps only.
"""
from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._optional import torch
from .camera import normalised_to_angles
from .emd import pair_difference, pair_runs
from .lc_config import (UNIT_TYPES, LCNeuronConfig, LCPopulationConfig, MatchedFilterConfig, NormalisationConfig,
                        PathwayConfig, ReceptiveFieldConfig, config_from_dict)
from .lc_geometry import field_centres, field_weights, pair_blocks, pair_templates
from .neurons import LIFNeuron, LIFState, PoissonNeuron, PoissonState, RateNeuron, RateState

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "ReceptiveFieldConfig", "MatchedFilterConfig", "NormalisationConfig", "PathwayConfig", "LCNeuronConfig",
    "LCPopulationConfig", "LCPopulation", "PopulationState", "LCNeurons",
    "UNIT_TYPES", "pair_templates", "field_centres", "field_weights", "config_from_dict",
    "FRONT_END_RECORDS", "FIELD_RECORDS", "UNIT_RECORDS", "NEURON_RECORDS",
]

_SIGNAL = {"expansion": ("r", 1.0), "contraction": ("r", -1.0), "r2": ("r2", 1.0),
           "rdot+": ("rdot", 1.0), "rdot-": ("rdot", -1.0)}

# What a Circuit can record, by level (see Circuit.run).
FRONT_END_RECORDS = ("photoreceptor.v", "emd.response")
FIELD_RECORDS = ("lc.input", "lc.r", "lc.r2", "lc.rdot")
UNIT_RECORDS = ("lc.drive",)
NEURON_RECORDS = ("lc.rate", "lc.x", "lc.v", "lc.spikes")


# =========================================================================== LC population

class LCPopulation:
    """The LC matched filters, normalisation pool and pathways over one lattice (no neuron dynamics).

    Attributes (numpy unless said): ``centres_deg`` (F, 2), ``size_deg``; per unit (U =
    len(types)·F, type-major): ``unit_type``, ``unit_field``, ``azimuth_deg``,
    ``elevation_deg``, ``unit_size_deg``; subunits: ``subunit_deg`` (S, 2) centres,
    ``A`` (S, F) field weights; per pair: ``mu``, ``t``, ``pair_subunit``.

    lattice: the eye (a :class:`lobula.lattice.Lattice` or compound eye); config: the population's
    :class:`LCPopulationConfig` (None: the default); emd_tau_s: the EMDs' delay τ (s), which sets the
    gradient-ratio gain 2τ.
    """

    def __init__(self, lattice, config: LCPopulationConfig | None = None, emd_tau_s: float = 0.035):
        self.lattice = lattice
        self.config = cfg = config or LCPopulationConfig()
        self.emd_tau_s = float(emd_tau_s)
        fc = cfg.fields
        self.centres_deg = field_centres(lattice, fc)
        self.size_deg = float(fc.size_deg)
        sub = fc.subunit_deg if fc.subunit_deg is not None else fc.size_deg / 4.0
        block = max(1, int(round(sub / lattice.dphi_deg))) if sub >= 1.5 * lattice.dphi_deg else 1
        self.block = block
        self.mu, self.t = pair_templates(lattice, cfg.matched_filter.epipole_deg, cfg.matched_filter.template)
        self.kappa = 2.0 * self.emd_tau_s if cfg.normalisation.kind == "gradient-ratio" else 1.0

        # Subunits: occupied blocks, centred on the (μt-weighted) mean midpoint of their pairs.
        blocks, inv = np.unique(pair_blocks(lattice, block), return_inverse=True)
        self.subunit_block = blocks
        self.pair_subunit = inv
        S = len(blocks)
        mid = lattice.pair_midpoint
        paz, pel = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
        wt = np.abs(self.mu * self.t) + 1e-12
        norm = np.bincount(inv, weights=wt, minlength=S)
        self.subunit_deg = np.stack([np.bincount(inv, weights=wt * paz, minlength=S) / norm,
                                     np.bincount(inv, weights=wt * pel, minlength=S) / norm], axis=1)
        self.static_s = np.bincount(inv, weights=self.mu * self.t, minlength=S)          # Σ μt per subunit
        self.A = field_weights(self.subunit_deg[:, 0], self.subunit_deg[:, 1], self.centres_deg,
                               self.size_deg, fc.shape).T                                     # (S, F)
        self.static_f = self.static_s @ self.A                                                # Σ wμt per field
        empty = np.nonzero(self.static_f <= 0)[0]
        if len(empty):
            raise ValueError(f"LC field(s) {empty.tolist()} at {self.centres_deg[empty].tolist()} deg contain no "
                             f"EMD pair with an expansion signal (outside the eye, or only at the epipole); "
                             f"move them or enlarge size_deg")

        types = cfg.neurons.types
        F = len(self.centres_deg)
        self.types = types
        self.unit_type = np.repeat(np.array(types, dtype=object), F).astype(str)
        self.unit_field = np.tile(np.arange(F), len(types))
        self.azimuth_deg = self.centres_deg[self.unit_field, 0]
        self.elevation_deg = self.centres_deg[self.unit_field, 1]
        self.unit_size_deg = np.full(len(self.unit_type), self.size_deg)
        nc = cfg.neurons
        scale = {"r": nc.scale_r, "r2": nc.scale_r2, "rdot": nc.scale_rdot}
        self._unit_gain = np.concatenate([np.full(F, _SIGNAL[t][1] / scale[_SIGNAL[t][0]]) for t in types])
        self._tensors: dict = {}

    # -- sizes and coordinates
    @property
    def n_fields(self) -> int:
        """Number of fields, F."""
        return len(self.centres_deg)

    @property
    def n_units(self) -> int:
        """Number of units, U = len(types)·F."""
        return len(self.unit_type)

    @property
    def n_subunits(self) -> int:
        """Number of subunits, S."""
        return len(self.subunit_block)

    def units_of(self, unit_type: str) -> np.ndarray:
        """Unit indices (F,) of the type ``unit_type``, in field order."""
        if unit_type not in self.types:
            raise ValueError(f"this population has no {unit_type!r} units; it has {list(self.types)}")
        return np.nonzero(self.unit_type == unit_type)[0]

    def unit_coords(self) -> dict:
        """Coordinates of the ``neuron`` dim (for xarray): type, field, RF centre and size (deg)."""
        return {"neuron_type": self.unit_type, "field_index": self.unit_field, "azimuth_deg": self.azimuth_deg,
                "elevation_deg": self.elevation_deg, "size_deg": self.unit_size_deg}

    def field_coords(self) -> dict:
        """Coordinates of the ``field`` dim: RF centre and size (deg)."""
        return {"azimuth_deg": self.centres_deg[:, 0], "elevation_deg": self.centres_deg[:, 1],
                "size_deg": np.full(self.n_fields, self.size_deg)}

    def to_dict(self) -> dict:
        """Configuration and sizes, for the attrs of an output file."""
        return {"config": self.config.to_dict(), "emd_tau_s": self.emd_tau_s, "n_fields": self.n_fields,
                "n_units": self.n_units, "n_subunits": self.n_subunits, "subunit_block": self.block}

    # -- tensors on a device
    def tensors(self, device, dtype=torch.float32) -> dict:
        """Weights as tensors on ``device`` in ``dtype`` (cached): per-pair μ and gain weights, subunit ids, A,
        gains."""
        key = (torch.device(device), dtype)
        if key not in self._tensors:
            mk = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=key[0])  # noqa: E731
            floor = self.config.normalisation.floor if self.config.normalisation.kind == "gradient-ratio" else 0.0
            self._tensors[key] = dict(
                mu=mk(self.mu), den=mk(self.kappa * self.mu * self.t), A=mk(self.A),
                subunit=torch.as_tensor(self.pair_subunit, dtype=torch.long, device=key[0]),
                pairs_a=torch.as_tensor(self.lattice.pairs_a, dtype=torch.long, device=key[0]),
                pairs_b=torch.as_tensor(self.lattice.pairs_b, dtype=torch.long, device=key[0]),
                static_s=mk(self.static_s), static_f=mk(self.static_f),
                floor_s=mk(floor * self.kappa * self.static_s), floor_f=mk(floor * self.kappa * self.static_f),
                kappa_static_s=mk(self.kappa * self.static_s), unit_gain=mk(self._unit_gain))
            t = self._tensors[key]
            t["AB"] = torch.cat([t["pairs_a"], t["pairs_b"]])
            t["runs"] = pair_runs(self.lattice.pairs_a, self.lattice.pairs_b)
            # Pairs → subunits as a sparse (S, P) matrix (one entry per pair): a CSR product on
            # pair-major signals, several times faster than index_add along the last dim.
            rows = torch.as_tensor(self.pair_subunit, dtype=torch.long, device=key[0])
            P = len(self.pair_subunit)
            order = torch.argsort(rows, stable=True)
            crow = torch.zeros(self.n_subunits + 1, dtype=torch.long, device=key[0])
            crow[1:] = torch.cumsum(torch.bincount(rows, minlength=self.n_subunits), 0)
            with warnings.catch_warnings():  # torch calls its CSR support "beta": a warning users need not see
                warnings.simplefilter("ignore", UserWarning)
                for name, w in (("mu_csr", t["mu"]), ("den_csr", t["den"])):
                    t[name] = torch.sparse_csr_tensor(crow, order, w[order], (self.n_subunits, P))
        return self._tensors[key]

    # -- the first stage: pairs → subunits
    def pool_pairs(self, R: Tensor, y: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """Subunit sums of the matched filter (Σ μ·R) and of the gain pool (Σ 2τμt·G), (…, S) each.

        R: the EMD array's responses (…, P) (:func:`lobula.emd.emd_run`; u², u the photoreceptor
        output's units); y: the photoreceptor output (…, n) (u) of the same frames, for G_p = (y_B − y_A)², or None
        (no normalisation pool). Each pair adds into its subunit: a sparse sum, the
        dendritic compartment on which its T4/T5 terminal converges.
        """
        T = self.tensors(R.device, R.dtype)
        Rm, back = _pair_major(R)
        num = back(T["mu_csr"] @ Rm)
        if y is None:
            return num, None
        ym, back = _pair_major(y)                                                  # (n, M)
        den = ym.new_empty((self.n_subunits, ym.shape[1]))
        step = max(1, _PIECE // max(1, len(self.pair_subunit)))
        for i in range(0, ym.shape[1], step):  # column pieces: small work buffers (memory, not results)
            G = pair_difference(ym[:, i:i + step], T["AB"], T["runs"])             # (P, m): y_B − y_A
            G.mul_(G)
            den[:, i:i + step] = T["den_csr"] @ G
        return num, back(den)

    # -- the second stage: subunits → fields and pathways, stepped in time
    def init_state(self, den_s0: Tensor | None, batch: int, device, dtype) -> "PopulationState":
        """Rest: no motion, the pool settled on the gradient energy ``den_s0`` (B, S) of the adapting frame
        (None: the population's static gain); ``batch`` B stimuli, tensors on ``device`` in ``dtype``."""
        T = self.tensors(device, dtype)
        S, F = self.n_subunits, self.n_fields
        D = den_s0.clone() if den_s0 is not None else T["kappa_static_s"].expand(batch, S).clone()
        z = torch.zeros(batch, S, device=device, dtype=dtype)
        zf = torch.zeros(batch, F, device=device, dtype=dtype)
        return PopulationState(D, z, zf.clone(), zf.clone())

    def advance(self, num_s: Tensor, den_s: Tensor | None, state: "PopulationState", dt: float,
                want: set) -> tuple[dict, "PopulationState"]:
        """Fields and pathways for a chunk: num_s, den_s (Tc, B, S) → records (Tc, B, F or U).

        ``want`` ⊆ {"lc.input", "lc.r", "lc.r2", "lc.rdot", "lc.drive"} (the drive is
        always computed when neurons follow; this only chooses what is returned). state: the
        :class:`PopulationState` before the chunk; dt: the time step (s). Returns (records: lc.r in
        1/s, lc.r2 and lc.rdot in 1/s² (with normalisation "none": in R units), lc.drive dimensionless;
        the state after the chunk).
        """
        cfg = self.config
        T = self.tensors(num_s.device, num_s.dtype)
        A = T["A"]
        norm = cfg.normalisation.kind == "gradient-ratio"
        a_n = math.exp(-dt / cfg.normalisation.tau_s)
        a_l = math.exp(-dt / cfg.pathways.tau_local_s)
        a_f = math.exp(-dt / cfg.pathways.tau_fast_s)
        a_s = math.exp(-dt / cfg.pathways.tau_slow_s)
        # Exact steady-state lag of a discrete low-pass behind a ramp: a·dt/(1 − a).
        lag = a_s * dt / (1 - a_s) - a_f * dt / (1 - a_f)
        Tc = num_s.shape[0]
        D, q, rf, rs = state
        if norm:
            Dseq = torch.empty_like(den_s)
            for t in range(Tc):  # the pool's low-pass is sequential in time
                D = torch.lerp(D, den_s[t], 1 - a_n, out=Dseq[t])
        else:
            Dseq = T["kappa_static_s"].expand_as(num_s)
        qseq = torch.empty_like(num_s)
        for t in range(Tc):
            q = torch.lerp(q, num_s[t], 1 - a_l, out=qseq[t])
        num_f = num_s @ A                                                       # (Tc, B, F)
        gain_f = Dseq @ A + T["floor_f"]
        r = num_f / gain_f
        Dfl = Dseq + T["floor_s"]
        r2 = ((qseq * qseq / Dfl.clamp_min(1e-30)) @ A) / (Dfl @ A).clamp_min(1e-30)
        rdot = torch.empty_like(r)
        for t in range(Tc):  # ṙ: fast minus slow low-pass of r̂
            rf = torch.lerp(rf, r[t], 1 - a_f)
            rs = torch.lerp(rs, r[t], 1 - a_s)
            rdot[t] = (rf - rs) / lag
        out = {}
        if "lc.input" in want:
            out["lc.input"] = num_f / T["static_f"]
        if "lc.r" in want:
            out["lc.r"] = r
        if "lc.r2" in want:
            out["lc.r2"] = r2
        if "lc.rdot" in want:
            out["lc.rdot"] = rdot
        sig = {"r": r, "r2": r2, "rdot": rdot}
        drive = torch.cat([sig[_SIGNAL[t][0]] for t in self.types], dim=-1) * T["unit_gain"]
        out["lc.drive"] = drive
        return out, PopulationState(D, q, rf, rs)

    def decode_rates(self, rates: Tensor) -> dict:
        """Invert rate units ``rates`` (…, U) in Hz to the signals they carry: {"r" 1/s, "r2" 1/s², "rdot"
        1/s²} (…, F).

        Inverts the Naka–Rushton output (exact at steady state; the τ_m lag remains)
        and takes the push–pull difference, e.g. r = scale_r·(x_expansion − x_contraction).
        Missing types give no entry; a pair needs both halves.
        """
        nc = self.config.neurons
        rc = nc.rate
        rho = (rates / rc.r_max).clamp(0.0, 1.0 - 1e-6)
        x = rc.c50 * (rho / (1 - rho)) ** (1.0 / rc.n)
        F = self.n_fields
        part = {t: x[..., i * F:(i + 1) * F] for i, t in enumerate(self.types)}
        out = {}
        if "expansion" in part and "contraction" in part:
            out["r"] = nc.scale_r * (part["expansion"] - part["contraction"])
        if "r2" in part:
            out["r2"] = nc.scale_r2 * part["r2"]
        if "rdot+" in part and "rdot-" in part:
            out["rdot"] = nc.scale_rdot * (part["rdot+"] - part["rdot-"])
        return out


# Elements of one work buffer in pool_pairs (16 MB in float32): pieces below glibc's largest
# mmap threshold (32 MB) are recycled by malloc instead of page-faulted in afresh each chunk.
_PIECE = 1 << 22


def _pair_major(x: Tensor):
    """x (..., P) as a 2-D (P, M) matrix (a view when x's storage is pair-major, as
    :func:`lobula.emd.emd_run` returns it; else one copy) and the function that turns a
    (K, M) result back into (..., K)."""
    lead = x.shape[:-1]
    dims = sorted(range(len(lead)), key=lambda d: -x.stride(d))        # lead dims in memory order
    xp = x.permute(len(lead), *dims)
    if not xp.is_contiguous():
        xp = xp.contiguous()
    shape = tuple(lead[d] for d in dims)
    inverse = [0] * len(dims)
    for i, d in enumerate(dims):
        inverse[d] = i

    def back(m: Tensor) -> Tensor:
        return m.reshape((m.shape[0],) + shape).permute(*[1 + i for i in inverse], 0)

    return xp.reshape(xp.shape[0], -1), back


class PopulationState(NamedTuple):
    """Pool D (B, S), local low-pass q (B, S), fast and slow low-passes of r̂ (B, F)."""

    D: Tensor
    q: Tensor
    r_fast: Tensor
    r_slow: Tensor


# =========================================================================== LC neurons

class LCNeurons:
    """The LC units' dynamics (rate, LIF or Poisson), batched as (B, K, U): stimuli × trials × units.

    config: the :class:`LCNeuronConfig` (None: the default).
    """

    def __init__(self, config: LCNeuronConfig | None = None):
        self.config = cfg = config or LCNeuronConfig()
        self.rate = RateNeuron(cfg.rate)
        self.lif = LIFNeuron(cfg.lif)
        self.poisson = PoissonNeuron(cfg.poisson)

    @property
    def records(self) -> tuple:
        """What the model records ("lc.rate" Hz, "lc.x" dimensionless, "lc.v" V, "lc.spikes" counts)."""
        return {"rate": ("lc.rate", "lc.x"), "poisson": ("lc.rate", "lc.x", "lc.spikes"),
                "lif": ("lc.v", "lc.spikes")}[self.config.model]

    @property
    def stochastic(self) -> bool:
        """Whether trials differ (Poisson spikes, or a noisy LIF)."""
        return self.config.model == "poisson" or (self.config.model == "lif" and self.config.lif.noisy)

    def init_state(self, shape: tuple, device, dtype, generator=None):
        """Rest state for ``shape`` (B, K, U), tensors on ``device`` in ``dtype``; ``generator``: the torch
        generator of a noisy LIF's starting membrane potentials."""
        B, K, U = shape
        if self.config.model == "lif":
            s = self.lif.init_state(B * K, U, device=device, dtype=dtype, generator=generator)
            return LIFState(*(f.reshape(B, K, U) for f in s))
        z = torch.zeros(shape, device=device, dtype=dtype)
        rs = RateState(z, z.clone())
        return (rs, PoissonState(z.clone())) if self.config.model == "poisson" else rs

    def shape(self, state) -> tuple:
        """(B, K, U) of a state."""
        m = self.config.model
        return tuple((state.v if m == "lif" else state.x if m == "rate" else state[0].x).shape)

    def step(self, state, drive: Tensor, dt: float, generator=None):
        """The state after one step of ``dt`` s from ``state`` under ``drive`` (B, 1 or K, U) dimensionless;
        ``generator``: the torch generator of the noise (Poisson, LIF)."""
        cfg = self.config
        if cfg.model == "lif":
            ex, inh = cfg.lif_excitation_max, cfg.lif_inhibition_max
            s = torch.where(drive > 0, ex * torch.tanh(drive / ex), inh * torch.tanh(drive / inh))
            return self.lif.step(state, cfg.lif_bias_A + cfg.lif_gain_A * s, dt, generator=generator)
        if cfg.model == "rate":
            return self.rate.step(state, drive, dt)
        rs = self.rate.step(state[0], drive, dt)
        return rs, self.poisson.step(state[1], rs.r, dt, generator=generator)

    def read(self, state, name: str) -> Tensor:
        """The record ``name`` (one of :attr:`records`) of ``state``, (B, K, U)."""
        m = self.config.model
        if name not in self.records:
            raise ValueError(f"{m} LC units do not record {name!r}; they record {list(self.records)}")
        if m == "lif":
            return state.v if name == "lc.v" else state.spikes
        rs = state if m == "rate" else state[0]
        if name == "lc.rate":
            return rs.r
        if name == "lc.x":
            return rs.x
        return state[1].spikes
