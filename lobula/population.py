"""Lobula-columnar (LC) populations: matched filters for expansion on the EMD array, and the circuit
photoreceptors → EMDs → LC units that virtual electrophysiology records from.

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
ωτ·cot(Δϕ/2)/(1+(ωτ)²), see :mod:`lobula.emd_decoding`), so C², the pattern and the
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
stage runs as strided sums on the lattice grid (no per-pair gathers) and the second as
one small dense product, which is what makes a 5,000-ommatidia eye at 1 ms steps fast.

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

import functools
import math
import warnings
from dataclasses import MISSING, asdict, dataclass, field, fields as dc_fields, is_dataclass
from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import Tensor

from .camera import angles_to_normalised, normalised_to_angles
from .emd import EMDConfig, emd_coefficients
from .neurons import (LIFConfig, LIFNeuron, LIFState, PoissonConfig, PoissonNeuron, PoissonState, RateNeuron,
                      RateNeuronConfig, RateState)
from .photoreceptor import PhotoreceptorConfig, PhotoreceptorState, photoreceptor_init, photoreceptor_run

__all__ = [
    "ReceptiveFieldConfig", "MatchedFilterConfig", "NormalisationConfig", "PathwayConfig", "LCNeuronConfig",
    "LCPopulationConfig", "CircuitConfig", "LCPopulation", "LCNeurons", "Circuit", "CircuitState",
    "UNIT_TYPES", "pair_templates", "field_centres", "field_weights", "correlator_factors", "config_from_dict",
    "FRONT_END_RECORDS", "FIELD_RECORDS", "UNIT_RECORDS", "NEURON_RECORDS",
]

UNIT_TYPES = ("expansion", "contraction", "r2", "rdot+", "rdot-")
_SIGNAL = {"expansion": ("r", 1.0), "contraction": ("r", -1.0), "r2": ("r2", 1.0),
           "rdot+": ("rdot", 1.0), "rdot-": ("rdot", -1.0)}

# What a Circuit can record, by level (see Circuit.run).
FRONT_END_RECORDS = ("photoreceptor.v", "emd.response")
FIELD_RECORDS = ("lc.input", "lc.r", "lc.r2", "lc.rdot")
UNIT_RECORDS = ("lc.drive",)
NEURON_RECORDS = ("lc.rate", "lc.x", "lc.v", "lc.spikes")


# =========================================================================== configs

def _positive(obj, *names):
    for n in names:
        v = getattr(obj, n)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{type(obj).__name__}.{n} must be a positive number, got {v!r}")


@dataclass(frozen=True)
class ReceptiveFieldConfig:
    """Where the LC fields are and how big (degrees at this user-facing edge).

    shape: "gaussian" (size = FWHM; weights cut at 1.5 FWHM from the centre) or "box"
        (size = side of a square in azimuth × elevation, as the paper's 5° fields).
    size_deg: 10° (default) — an order of magnitude for Drosophila LC receptive fields
        (LC types span ~10–60°, Wu et al. 2016, eLife 5:e21022); the paper used 5° boxes.
    centres_deg: explicit ((az, el), ...) list; None tiles the eye with ``spacing_deg``
        (None = size) inside ``margin_deg`` of the lattice's angular extent.
    subunit_deg: side of the dendritic subunits pairs are first pooled into (rounded to
        b×b ommatidia); None = size/4 (b = 1 when that is under 1.5 Δφ).
    """

    shape: str = "gaussian"
    size_deg: float = 10.0
    centres_deg: tuple | None = None
    spacing_deg: float | None = None
    margin_deg: float = 0.0
    subunit_deg: float | None = None

    def __post_init__(self):
        if self.shape not in ("gaussian", "box"):
            raise ValueError(f"receptive-field shape must be 'gaussian' or 'box', got {self.shape!r}")
        _positive(self, "size_deg")
        if self.spacing_deg is not None:
            _positive(self, "spacing_deg")
        if self.subunit_deg is not None:
            _positive(self, "subunit_deg")
        if self.centres_deg is not None:
            c = np.asarray(self.centres_deg, dtype=float)
            if c.ndim != 2 or c.shape[1] != 2 or len(c) == 0:
                raise ValueError(f"centres_deg must be a non-empty list of (azimuth, elevation) pairs, got {self.centres_deg!r}")
            object.__setattr__(self, "centres_deg", tuple(tuple(map(float, x)) for x in c))


@dataclass(frozen=True)
class MatchedFilterConfig:
    """The expansion template. epipole_deg: (az, el) of the focus of expansion (deg).
    template: "direction" (unit radial direction, Krapp-style local preferred directions)
    or "flow" (the expected flow component, least squares)."""

    epipole_deg: tuple = (0.0, 0.0)
    template: str = "direction"

    def __post_init__(self):
        if self.template not in ("direction", "flow"):
            raise ValueError(f"matched-filter template must be 'direction' or 'flow', got {self.template!r}")
        e = tuple(float(x) for x in self.epipole_deg)
        if len(e) != 2:
            raise ValueError(f"epipole_deg must be (azimuth, elevation), got {self.epipole_deg!r}")
        object.__setattr__(self, "epipole_deg", e)


@dataclass(frozen=True)
class NormalisationConfig:
    """Divisive contrast normalisation of the matched filter.

    kind: "gradient-ratio" (pool of squared input differences, see the module docstring)
        or "none".
    tau_s: time constant of the pool (s). 0.1 s: contrast gain control in fly motion
        vision acts over ~0.1–1 s (Harris, O'Carroll & Laughlin 2000, Neuron 28:595).
    floor: semi-saturation of the pool in units of G (photoreceptor output²); 1e-6 is a
        0.1 % contrast difference for unit mean luminance.
    """

    kind: str = "gradient-ratio"
    tau_s: float = 0.1
    floor: float = 1e-6

    def __post_init__(self):
        if self.kind not in ("gradient-ratio", "none"):
            raise ValueError(f"normalisation kind must be 'gradient-ratio' or 'none', got {self.kind!r}")
        _positive(self, "tau_s")
        if not self.floor >= 0:
            raise ValueError(f"normalisation floor must be >= 0, got {self.floor}")


@dataclass(frozen=True)
class PathwayConfig:
    """Time constants (s) of the r²̄ and ṙ pathways.

    tau_local_s: low-pass of each subunit's motion signal before squaring (r²̄): 50 ms,
        a dendritic/synaptic integration time that averages a few cycles of pattern noise.
    tau_fast_s, tau_slow_s: the transient pathway ṙ ∝ LP_fast(r̂) − LP_slow(r̂). 50 ms /
        200 ms: a fast/slow pair as in fly motion-adaptation and delay-line models; the
        difference is ṙ low-passed over roughly the slow time constant.
    """

    tau_local_s: float = 0.05
    tau_fast_s: float = 0.05
    tau_slow_s: float = 0.2

    def __post_init__(self):
        _positive(self, "tau_local_s", "tau_fast_s", "tau_slow_s")
        if not self.tau_slow_s > self.tau_fast_s:
            raise ValueError(f"tau_slow_s must exceed tau_fast_s, got {self.tau_slow_s} <= {self.tau_fast_s}")


@dataclass(frozen=True)
class LCNeuronConfig:
    """The LC units' neuron model and how each pathway's signal drives it.

    model: "rate" (leaky integrator + Naka–Rushton), "lif" (leaky integrate-and-fire),
        or "poisson" (rate neurons whose rate drives Poisson spikes).
    types: unit types per field, any of :data:`UNIT_TYPES`.
    scale_r (1/s), scale_r2 (1/s²), scale_rdot (1/s²): the signal value that gives a
        drive of 1 (half of r_max with the default c50 = 1); r = 2/s is an obstacle
        0.5 s from contact. With normalisation "none" the signals are in R units and
        these must be set accordingly.
    rate: rate-neuron parameters (τ_m = 10 ms, r_max = 100 Hz, c50 = 1, n = 2).
    lif: LIF parameters; default Dayan & Abbott's cell with an OU background current of
        0.2 nA SD (τ 5 ms; Destexhe et al. 2001) so trials differ.
    lif_gain_A, lif_bias_A: current = bias + gain·s(drive) (A). 2 nA per unit drive on a
        1 nA bias (rheobase 1.5 nA): silent at rest, ~110 Hz at drive 1.
    lif_excitation_max, lif_inhibition_max: synaptic saturation s(x) = x_max·tanh(x/x_max)
        for x > 0 (4: at most 9 nA, ~260 Hz) and x_inh·tanh(x/x_inh) for x < 0 (0.75: the
        membrane stays above ≈ −70 mV, an inhibitory reversal potential, instead of
        following an unbounded negative drive).
    poisson: Poisson spike-count mode.
    """

    model: str = "rate"
    types: tuple = UNIT_TYPES
    scale_r: float = 2.0
    scale_r2: float = 1.0
    scale_rdot: float = 1.0
    rate: RateNeuronConfig = field(default_factory=RateNeuronConfig)
    lif: LIFConfig = field(default_factory=lambda: LIFConfig(noise="ou", noise_std=0.2e-9, noise_tau=0.005))
    lif_gain_A: float = 2e-9
    lif_bias_A: float = 1e-9
    lif_excitation_max: float = 4.0
    lif_inhibition_max: float = 0.75
    poisson: PoissonConfig = field(default_factory=PoissonConfig)

    def __post_init__(self):
        if self.model not in ("rate", "lif", "poisson"):
            raise ValueError(f"LC neuron model must be 'rate', 'lif' or 'poisson', got {self.model!r}")
        types = tuple(self.types)
        bad = [t for t in types if t not in UNIT_TYPES]
        if bad or not types or len(set(types)) != len(types):
            raise ValueError(f"LC unit types must be distinct names from {UNIT_TYPES}, got {self.types!r}")
        object.__setattr__(self, "types", types)
        _positive(self, "scale_r", "scale_r2", "scale_rdot", "lif_excitation_max", "lif_inhibition_max")


@dataclass(frozen=True)
class LCPopulationConfig:
    """An LC population: one config per layer (fields, matched filter, normalisation, pathways, neurons)."""

    fields: ReceptiveFieldConfig = field(default_factory=ReceptiveFieldConfig)
    matched_filter: MatchedFilterConfig = field(default_factory=MatchedFilterConfig)
    normalisation: NormalisationConfig = field(default_factory=NormalisationConfig)
    pathways: PathwayConfig = field(default_factory=PathwayConfig)
    neurons: LCNeuronConfig = field(default_factory=LCNeuronConfig)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class CircuitConfig:
    """The recorded circuit: photoreceptors → EMD array → LC population, at a fixed step.

    photoreceptor: 10 ms low-pass and an LMC-like 0.25 s high-pass (the fly's EMD inputs
        L1/L2 are transient; without it the mean luminance leaks into the correlator's
        instantaneous output). emd: τ = 35 ms (optimum 4.5 Hz, blowfly HS cells).
    dt_s: simulation step, 1 ms (the ephys protocols' resolution). chunk_steps: time
        steps processed per batch (memory and speed only; results do not depend on it).
    compile: fuse the EMD array and the first pooling stage with ``torch.compile``
        (inductor; needs a C++ compiler on CPU, Triton on GPU). Several times faster on
        large eyes, after a one-off compilation of ~30 s (cached on disk between runs).
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
        return asdict(self)


def config_from_dict(cls, d: dict):
    """Rebuild a (nested, frozen) config dataclass from :func:`dataclasses.asdict` output."""
    kwargs = {}
    known = {f.name: f for f in dc_fields(cls)}
    for k, v in d.items():
        if k not in known:
            raise ValueError(f"{cls.__name__} has no field {k!r}; it has {sorted(known)}")
        f = known[k]
        proto = f.default_factory() if f.default_factory is not MISSING else f.default
        if is_dataclass(proto) and isinstance(v, dict):
            v = config_from_dict(type(proto), v)
        kwargs[k] = v
    return cls(**kwargs)


# =========================================================================== geometry

def pair_templates(lattice, epipole_deg=(0.0, 0.0), template: str = "direction") -> tuple[np.ndarray, np.ndarray]:
    """Per-pair matched-filter weight μ_p and expansion template t_p, both (P,).

    t_p = ⟨m_p − e, Δp⟩/|Δp|²: inter-ommatidial steps per second along pair p per unit
    expansion rate (s per s⁻¹). μ_p: ⟨u_p, (m_p − e)/|m_p − e|⟩ ("direction") or t_p
    ("flow"). μ_p·t_p ≥ 0 for both, so pooled gains are positive.
    """
    e = np.array(angles_to_normalised(*np.radians(np.asarray(epipole_deg, float))), dtype=float)
    step = lattice.normalised[lattice.pairs_b] - lattice.normalised[lattice.pairs_a]
    rel = lattice.pair_midpoint - e[None, :]
    t = np.einsum("pk,pk->p", rel, step) / np.einsum("pk,pk->p", step, step)
    if template == "flow":
        return t.copy(), t
    if template == "direction":
        dist = np.linalg.norm(rel, axis=1)
        mu = np.where(dist > 1e-12, np.einsum("pk,pk->p", lattice.pair_direction, rel) / np.maximum(dist, 1e-12), 0.0)
        return mu, t
    raise ValueError(f"template must be 'direction' or 'flow', got {template!r}")


def field_centres(lattice, config: ReceptiveFieldConfig) -> np.ndarray:
    """Field centres (F, 2) in degrees (az, el): the explicit list, or a grid tiling the lattice's extent."""
    if config.centres_deg is not None:
        return np.asarray(config.centres_deg, dtype=float)
    spacing = config.spacing_deg or config.size_deg
    half = config.size_deg / 2.0 + config.margin_deg

    def axis(lo, hi):
        k = int(np.floor((hi - lo - 2.0 * half) / spacing + 1e-9)) + 1
        if k < 1:
            raise ValueError(f"LC fields of {config.size_deg}° (margin {config.margin_deg}°) do not fit the eye's "
                             f"{hi - lo:.1f}° extent; use a smaller size_deg or give centres_deg")
        return (lo + hi) / 2.0 + (np.arange(k) - (k - 1) / 2.0) * spacing

    az, el = lattice.azimuth_deg, lattice.elevation_deg
    ga, ge = np.meshgrid(axis(az.min(), az.max()), axis(el.min(), el.max()), indexing="xy")
    return np.stack([ga.ravel(), ge.ravel()], axis=1)


def field_weights(az_deg: np.ndarray, el_deg: np.ndarray, centres_deg: np.ndarray, size_deg: float,
                  shape: str) -> np.ndarray:
    """Receptive-field weight (F, m) of each field at points (az, el) (m,), degrees, peak 1."""
    da = az_deg[None, :] - centres_deg[:, :1]
    de = el_deg[None, :] - centres_deg[:, 1:]
    if shape == "box":
        return ((np.abs(da) <= size_deg / 2.0) & (np.abs(de) <= size_deg / 2.0)).astype(float)
    if shape == "gaussian":
        q = (da * da + de * de) / (size_deg * size_deg)
        return np.where(q <= 1.5 ** 2, np.exp(-4.0 * math.log(2.0) * q), 0.0)
    raise ValueError(f"shape must be 'gaussian' or 'box', got {shape!r}")


def correlator_factors(config: EMDConfig, dt: float) -> tuple[np.ndarray, np.ndarray, tuple]:
    """The discrete correlator of :mod:`lobula.emd` as one two-signal Reichardt product.

    Per frame :mod:`lobula.emd` computes ``R = s_Aᵀ N s_B`` with ``s = (l₀, x_prev, x)``
    and N antisymmetric (entries n_lp, n_lc, n_pc). Any antisymmetric 3×3 matrix has
    rank 2, so ``N = u vᵀ − v uᵀ`` and ``R = U_A·V_B − V_A·U_B`` with ``U = u·s``,
    ``V = v·s`` computed once per ommatidium: two products per pair instead of four,
    with the same result. Returns (u, v, (decay, beta, gamma)).
    """
    c = emd_coefficients(config, dt)
    n = np.array([c.n_pc, -c.n_lc, c.n_lp])            # the axial vector of N: n = u × v
    j = int(np.argmin(np.abs(n)))
    u = np.eye(3)[j] - n * (n[j] / float(n @ n))        # any u ⟂ n
    v = np.cross(n, u) / float(u @ u)
    return u, v, (c.decay, c.beta, c.gamma)


class _LatticeGrid:
    """The lattice's integer (i, j) layout as a padded 2-D grid, so neighbour pairs are slices."""

    def __init__(self, lattice, block: int):
        idx = lattice.index
        lo = idx.min(axis=0)
        self.I, self.J = (idx.max(axis=0) - lo + 1).tolist()
        self.I2, self.J2 = self.I + 2, self.J + 2
        self.block = b = int(block)
        self.Ib, self.Jb = -(-self.I // b), -(-self.J // b)
        ij = idx - lo
        self.pos = torch.as_tensor((ij[:, 1] + 1) * self.I2 + (ij[:, 0] + 1), dtype=torch.long)
        self.axes = []
        for a, bb in lattice.axis_pairs:  # 2 or 3 axes, not pairs
            di, dj = (idx[bb[0]] - idx[a[0]]).tolist() if len(a) else (0, 0)
            self.axes.append((slice(1 + dj, self.J2 - 1 + dj), slice(1 + di, self.I2 - 1 + di)))
        # Core position of each pair's A and its block (subunit) id.
        ia, ja = ij[lattice.pairs_a, 0], ij[lattice.pairs_a, 1]
        self.pair_core = ja * self.I + ia
        self.pair_block = (ja // b) * self.Ib + (ia // b)

    def scatter(self, x: Tensor, out: Tensor | None = None) -> Tensor:
        """(..., n) → (..., J2, I2) with zeros where there is no ommatidium.

        out: a reusable zeroed buffer (..., J2, I2); only ommatidium positions are written.
        """
        if out is None:
            out = x.new_zeros(x.shape[:-1] + (self.J2, self.I2))
        flat = out.view(x.shape[:-1] + (self.J2 * self.I2,))
        flat.index_copy_(-1, self.pos.to(x.device), x)
        return out

    def axis_map(self, lattice, values: np.ndarray, k: int) -> np.ndarray:
        """Per-pair values of axis k laid out on the core grid (J, I), zero elsewhere."""
        m = np.zeros(self.J * self.I)
        sel = lattice.pair_axis == k
        m[self.pair_core[sel]] = values[sel]
        return m.reshape(self.J, self.I)


# =========================================================================== LC population

class LCPopulation:
    """The LC matched filters, normalisation pool and pathways over one lattice (no neuron dynamics).

    Attributes (numpy unless said): ``centres_deg`` (F, 2), ``size_deg``; per unit (U =
    len(types)·F, type-major): ``unit_type``, ``unit_field``, ``azimuth_deg``,
    ``elevation_deg``, ``unit_size_deg``; subunits: ``subunit_deg`` (S, 2) centres,
    ``A`` (S, F) field weights; per pair: ``mu``, ``t``, ``pair_subunit``.
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
        self.grid = _LatticeGrid(lattice, block)
        self.mu, self.t = pair_templates(lattice, cfg.matched_filter.epipole_deg, cfg.matched_filter.template)
        self.kappa = 2.0 * self.emd_tau_s if cfg.normalisation.kind == "gradient-ratio" else 1.0

        # Subunits: occupied blocks, centred on the (μt-weighted) mean midpoint of their pairs.
        blocks, inv = np.unique(self.grid.pair_block, return_inverse=True)
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
        return len(self.centres_deg)

    @property
    def n_units(self) -> int:
        return len(self.unit_type)

    @property
    def n_subunits(self) -> int:
        return len(self.subunit_block)

    def units_of(self, unit_type: str) -> np.ndarray:
        """Unit indices of one type, in field order."""
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
        return {"config": self.config.to_dict(), "emd_tau_s": self.emd_tau_s, "n_fields": self.n_fields,
                "n_units": self.n_units, "n_subunits": self.n_subunits, "subunit_block": self.grid.block}

    # -- tensors on a device
    def tensors(self, device, dtype=torch.float32) -> dict:
        """Weights as tensors on ``device`` (cached): per-axis grid maps, A, gains."""
        key = (torch.device(device), dtype)
        if key not in self._tensors:
            lat, g = self.lattice, self.grid
            mk = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=key[0])  # noqa: E731
            mu_maps = [mk(g.axis_map(lat, self.mu, k)) for k in range(lat.n_axes)]
            den_maps = [mk(g.axis_map(lat, self.kappa * self.mu * self.t, k)) for k in range(lat.n_axes)]
            floor = self.config.normalisation.floor if self.config.normalisation.kind == "gradient-ratio" else 0.0
            self._tensors[key] = dict(
                mu=mu_maps, den=den_maps, A=mk(self.A), blocks=torch.as_tensor(self.subunit_block, device=key[0]),
                static_s=mk(self.static_s), static_f=mk(self.static_f),
                floor_s=mk(floor * self.kappa * self.static_s), floor_f=mk(floor * self.kappa * self.static_f),
                kappa_static_s=mk(self.kappa * self.static_s), unit_gain=mk(self._unit_gain))
        return self._tensors[key]

    # -- the first stage: pairs → subunits
    def pool_subunits(self, Ug: Tensor, Vg: Tensor, Xg: Tensor | None, work: dict | None = None
                      ) -> tuple[Tensor, Tensor | None]:
        """Subunit sums of the matched filter (Σμ·R) and of the gain pool (Σ 2τμt·G).

        Ug, Vg: the correlator factors (…, J2, I2) on the grid (``R = U_A V_B − V_A U_B``);
        Xg: the photoreceptor output on the grid (for G = (x_B − x_A)²) or None.
        work: optional dict of reusable buffers (kept by the caller between chunks: large
        fresh allocations cost page faults on CPU). Returns (num (…, S), den (…, S) or None).
        """
        g = self.grid
        T = self.tensors(Ug.device, Ug.dtype)
        lead = Ug.shape[:-2]
        b = g.block
        work = {} if work is None else work

        def buf(name, shape):
            key = (name, tuple(shape))
            if key not in work:  # zeroed once: padding rows/columns are never written
                work[key] = Ug.new_zeros(shape)
            return work[key]

        acc_shape = lead + (g.Jb * b, g.Ib * b)
        num = buf("num", acc_shape)
        den = buf("den", acc_shape) if Xg is not None else None
        r = buf("r", lead + (g.J, g.I))
        core = (slice(1, g.J2 - 1), slice(1, g.I2 - 1))
        nv = num[..., :g.J, :g.I]
        dv = den[..., :g.J, :g.I] if den is not None else None
        UA, VA = Ug[..., core[0], core[1]], Vg[..., core[0], core[1]]
        XA = Xg[..., core[0], core[1]] if Xg is not None else None
        for k, (sj, si) in enumerate(g.axes):  # 2–3 lattice axes; each is whole-array slicing
            torch.mul(UA, Vg[..., sj, si], out=r)
            r.addcmul_(VA, Ug[..., sj, si], value=-1.0)            # R = U_A V_B − V_A U_B
            if k == 0:
                torch.mul(r, T["mu"][k], out=nv)
            else:
                nv.addcmul_(r, T["mu"][k])
            if dv is not None:
                torch.sub(Xg[..., sj, si], XA, out=r)
                r.mul_(r)
                if k == 0:
                    torch.mul(r, T["den"][k], out=dv)
                else:
                    dv.addcmul_(r, T["den"][k])
        return self._blocks(num, T), (self._blocks(den, T) if den is not None else None)

    def _blocks(self, x: Tensor, T: dict) -> Tensor:
        """Sum b×b blocks of (…, Jb·b, Ib·b) and keep the occupied ones: (…, S)."""
        b = self.grid.block
        if b > 1:  # strided slices are several times faster than a 6-D view-sum on CPU
            cols = x[..., 0::b]
            for i in range(1, b):
                cols = cols + x[..., i::b]
            x = cols[..., 0::b, :]
            for i in range(1, b):
                x = x + cols[..., i::b, :]
        return x.reshape(x.shape[:-2] + (-1,)).index_select(-1, T["blocks"])

    # -- the second stage: subunits → fields and pathways, stepped in time
    def init_state(self, den_s0: Tensor | None, batch: int, device, dtype) -> "PopulationState":
        """Rest: no motion, the pool settled on the gradient energy ``den_s0`` (B, S) of the adapting frame."""
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
        always computed when neurons follow; this only chooses what is returned).
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
        """Invert rate units (…, U) in Hz to the signals they carry: {"r", "r2", "rdot"} (…, F).

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


class PopulationState(NamedTuple):
    """Pool D (B, S), local low-pass q (B, S), fast and slow low-passes of r̂ (B, F)."""

    D: Tensor
    q: Tensor
    r_fast: Tensor
    r_slow: Tensor


# =========================================================================== LC neurons

class LCNeurons:
    """The LC units' dynamics (rate, LIF or Poisson), batched as (B, K, U)."""

    def __init__(self, config: LCNeuronConfig | None = None):
        self.config = cfg = config or LCNeuronConfig()
        self.rate = RateNeuron(cfg.rate)
        self.lif = LIFNeuron(cfg.lif)
        self.poisson = PoissonNeuron(cfg.poisson)

    @property
    def records(self) -> tuple:
        return {"rate": ("lc.rate", "lc.x"), "poisson": ("lc.rate", "lc.x", "lc.spikes"),
                "lif": ("lc.v", "lc.spikes")}[self.config.model]

    @property
    def stochastic(self) -> bool:
        return self.config.model == "poisson" or (self.config.model == "lif" and self.config.lif.noisy)

    def init_state(self, shape: tuple, device, dtype, generator=None):
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
        """drive: (B, 1 or K, U) dimensionless."""
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


# =========================================================================== the circuit

class CircuitState(NamedTuple):
    """Everything a stream needs to continue: photoreceptors, EMD low-pass and last input
    (B, n), LC pool and pathways, LC neurons (B, K, U)."""

    pr: PhotoreceptorState
    emd_lp: Tensor
    emd_x: Tensor
    population: PopulationState
    neurons: object


class Circuit:
    """Photoreceptors → EMD array → LC population → LC neurons, stepped at ``config.dt_s``.

    lattice: a :class:`lobula.lattice.Lattice`; config: :class:`CircuitConfig`; device:
    where it runs. The EMD stage computes exactly :mod:`lobula.emd`'s discrete
    correlator (same coefficients, see :func:`correlator_factors`), laid out on the
    lattice grid so that all pairs of an axis are one whole-array product.
    """

    def __init__(self, lattice, config: CircuitConfig | None = None, device="cpu"):
        self.lattice = lattice
        self.config = cfg = config or CircuitConfig()
        self.device = torch.device(device)
        self.population = LCPopulation(lattice, cfg.population, cfg.emd.tau_s)
        self.neurons = LCNeurons(cfg.population.neurons)
        self.u, self.v, (self.decay, self.beta, self.gamma) = correlator_factors(cfg.emd, cfg.dt_s)
        self._pairs = (torch.as_tensor(lattice.pairs_a, device=self.device),
                       torch.as_tensor(lattice.pairs_b, device=self.device))
        self._work: dict = {}   # reusable grid buffers, keyed by shape
        self._kernel = None
        if cfg.compile:
            g = self.population.grid
            self._kernel = torch.compile(functools.partial(
                _fused_front, u=tuple(map(float, self.u)), v=tuple(map(float, self.v)), axes=tuple(g.axes),
                J=g.J, I=g.I, b=g.block, gradient=self.gradient), dynamic=False)

    def _pair_response(self, Xf: Tensor, Lf: Tensor, pa: Tensor, pb: Tensor) -> Tensor:
        """R of the pairs at flat grid positions (pa, pb) from the grid inputs X and low-passes L (Tc+1, B, ·)."""
        u, v = self.u, self.v

        def factors(p):
            l0, xp, xc = Lf[:-1][..., p], Xf[:-1][..., p], Xf[1:][..., p]
            return l0 * u[0] + xp * u[1] + xc * u[2], l0 * v[0] + xp * v[1] + xc * v[2]

        (UA, VA), (UB, VB) = factors(pa), factors(pb)
        return UA * VB - VA * UB

    @property
    def gradient(self) -> bool:
        return self.config.population.normalisation.kind == "gradient-ratio"

    def available(self) -> tuple:
        """Names this circuit can record."""
        return FRONT_END_RECORDS + FIELD_RECORDS + UNIT_RECORDS + self.neurons.records

    def to_dict(self) -> dict:
        return {"circuit": self.config.to_dict(), "lattice": self.lattice.to_dict(),
                "population": self.population.to_dict()}

    # -- state
    def init_state(self, baseline, batch: int, trials: int = 1, dtype=torch.float32,
                   generator: torch.Generator | None = None) -> CircuitState:
        """Every stage at rest and adapted to a static ``baseline`` luminance (scalar, (n,) or (B, n)),
        as after a long blank at the stimulus' mean luminance."""
        n = self.lattice.n
        x0 = torch.as_tensor(baseline, dtype=dtype, device=self.device)
        x0 = x0.expand(batch, n).clone() if x0.dim() < 2 else x0.clone()
        pr = photoreceptor_init(self.config.photoreceptor, x0)
        y0, pr = photoreceptor_run(self.config.photoreceptor, self.config.dt_s, x0.unsqueeze(1), pr)
        y0 = y0[:, 0]
        den0 = None
        if self.gradient:
            g = self.population.grid
            zero = torch.zeros_like(y0)
            _, den0 = self.population.pool_subunits(g.scatter(zero), g.scatter(zero), g.scatter(y0))
        pop = self.population.init_state(den0, batch, self.device, dtype)
        neu = self.neurons.init_state((batch, trials, self.population.n_units), self.device, dtype, generator)
        return CircuitState(pr, y0.clone(), y0.clone(), pop, neu)

    # -- one chunk
    def _advance(self, x: Tensor, state: CircuitState, want: dict, generator) -> tuple[dict, CircuitState]:
        """x: (B, Tc, n) luminance → records (time-major: (Tc, B, …) or (Tc, B, K, U)), new state."""
        cfg = self.config
        dt = cfg.dt_s
        y, pr = photoreceptor_run(cfg.photoreceptor, dt, x, state.pr)
        yt = y.transpose(0, 1)                                                # (Tc, B, n) view
        Tc, B = yt.shape[0], yt.shape[1]
        g = self.population.grid
        pos = g.pos.to(self.device)
        work = self._work

        def buf(name, shape):
            key = (name, tuple(shape))
            if key not in work:  # zeroed once; grid padding is never written
                work[key] = y.new_zeros(shape)
            return work[key]

        # Everything from here runs on the lattice grid (no per-pair gathers): frames
        # 0…Tc of X hold the previous chunk's last input and this chunk's inputs, so the
        # previous frame x_prev is a view; L holds the delay low-pass at frame starts.
        gshape = (Tc + 1, B, g.J2, g.I2)
        X = buf("X", gshape)
        L = buf("L", gshape)
        Xf, Lf = X.view(Tc + 1, B, -1), L.view(Tc + 1, B, -1)
        Xf[0].index_copy_(-1, pos, state.emd_x)
        Xf[1:].index_copy_(-1, pos, yt)
        Lf[0].index_copy_(-1, pos, state.emd_lp)
        xp, xc = X[:-1], X[1:]
        drive = buf("drive", (Tc, B, g.J2, g.I2))
        torch.mul(xp, self.beta, out=drive)
        drive.add_(xc, alpha=self.gamma)
        for t in range(Tc):  # the EMD delay low-pass is sequential in time only
            torch.add(drive[t], L[t], alpha=self.decay, out=L[t + 1])
        out = {}
        if "photoreceptor.v" in want:
            out["photoreceptor.v"] = _select(yt, want["photoreceptor.v"])
        if "emd.response" in want:
            A, Bp = self._pairs
            idx = want["emd.response"]
            if idx is not None:
                A, Bp = A[idx], Bp[idx]
            out["emd.response"] = self._pair_response(Xf, Lf, pos[A], pos[Bp])
        num_s = None
        if self._kernel is not None:
            T = self.population.tensors(X.device, X.dtype)
            try:
                num_s, den_s = self._kernel(X, L, T["mu"], T["den"], T["blocks"])
            except Exception as exc:  # no C++ compiler / Triton: say so once and run eagerly
                warnings.warn(f"torch.compile of the EMD/pooling kernel failed ({type(exc).__name__}: {exc}); "
                              f"running it eagerly (same results, slower)", RuntimeWarning, stacklevel=3)
                self._kernel = None
        if num_s is None:
            l0 = L[:-1]
            u, v = self.u, self.v
            U = buf("U", (Tc, B, g.J2, g.I2))
            V = buf("V", (Tc, B, g.J2, g.I2))
            torch.mul(l0, u[0], out=U).add_(xp, alpha=u[1]).add_(xc, alpha=u[2])
            torch.mul(l0, v[0], out=V).add_(xp, alpha=v[1]).add_(xc, alpha=v[2])
            num_s, den_s = self.population.pool_subunits(U, V, xc if self.gradient else None, work)
        emd_lp = Lf[Tc].index_select(-1, pos)
        emd_x = yt[-1].clone()
        rec, pop = self.population.advance(num_s, den_s, state.population, dt, set(want))
        for name in FIELD_RECORDS + UNIT_RECORDS:
            if name in want:
                out[name] = _select(rec[name], want[name])
        neu = state.neurons
        nw = [k for k in want if k in NEURON_RECORDS]
        if nw:
            _, K, U_ = self.neurons.shape(neu)
            bufs = {k: torch.empty((Tc, B, K, U_), dtype=x.dtype, device=x.device) for k in nw}
        drv = rec["lc.drive"].unsqueeze(2)                                   # (Tc, B, 1, U)
        for t in range(Tc if nw else 0):  # neuron dynamics (only when recorded), vectorised over B × K × U
            neu = self.neurons.step(neu, drv[t], dt, generator)
            for k in nw:
                bufs[k][t] = self.neurons.read(neu, k)
        for k in nw:
            out[k] = _select(bufs[k], want[k])
        return out, CircuitState(pr, emd_lp, emd_x, pop, neu)

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
        if callable(stimulus) and not isinstance(stimulus, Tensor):
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


def _fused_front(X: Tensor, L: Tensor, mus: list, dens: list, blocks: Tensor, *, u: tuple, v: tuple, axes: tuple,
                 J: int, I: int, b: int, gradient: bool) -> tuple[Tensor, Tensor | None]:
    """The EMD array and the first pooling stage as one pure function (for ``torch.compile``).

    X, L: (Tc+1, B, J2, I2) grid inputs and delay low-passes (frame 0: the previous
    chunk's last). Same arithmetic as the eager path (:meth:`LCPopulation.pool_subunits`);
    compiled, the ~40 passes over these arrays fuse into a few.
    """
    xp, xc, l0 = X[:-1], X[1:], L[:-1]
    U = l0 * u[0] + xp * u[1] + xc * u[2]
    V = l0 * v[0] + xp * v[1] + xc * v[2]
    UA, VA, XA = U[..., 1:J + 1, 1:I + 1], V[..., 1:J + 1, 1:I + 1], xc[..., 1:J + 1, 1:I + 1]
    num = den = None
    for k, (sj, si) in enumerate(axes):
        r = (UA * V[..., sj, si] - VA * U[..., sj, si]) * mus[k]
        num = r if num is None else num + r
        if gradient:
            d = xc[..., sj, si] - XA
            d = d * d * dens[k]
            den = d if den is None else den + d
    Jb, Ib = -(-J // b), -(-I // b)

    def blocksum(x):
        x = torch.nn.functional.pad(x, (0, Ib * b - I, 0, Jb * b - J))
        x = x.reshape(x.shape[:-2] + (Jb, b, Ib, b)).sum(dim=(-3, -1))
        return x.reshape(x.shape[:-2] + (-1,)).index_select(-1, blocks)

    return blocksum(num), (blocksum(den) if gradient else None)


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
