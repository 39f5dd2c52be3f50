"""The LC population's configuration: one frozen dataclass per layer, and the rebuilding of one from a dict.

Receptive fields, matched filter, normalisation, pathways and neurons (:class:`LCPopulationConfig`
holds one of each); the defaults' sources are in each class's docstring, and what each layer
computes is :mod:`lobula.population`'s module doc. :func:`config_from_dict` rebuilds a nested
config from :func:`dataclasses.asdict` output (a recording's provenance).
"""
from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, field, fields as dc_fields, is_dataclass

import numpy as np

from .neurons import LIFConfig, PoissonConfig, RateNeuronConfig

#: the unit types a field can have, one per pathway (push–pull halves apart; :mod:`lobula.population`)
UNIT_TYPES = ("expansion", "contraction", "r2", "rdot+", "rdot-")


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
    """An LC population: one config per layer — ``fields`` (:class:`ReceptiveFieldConfig`), ``matched_filter``
    (:class:`MatchedFilterConfig`), ``normalisation`` (:class:`NormalisationConfig`), ``pathways``
    (:class:`PathwayConfig`), ``neurons`` (:class:`LCNeuronConfig`)."""

    fields: ReceptiveFieldConfig = field(default_factory=ReceptiveFieldConfig)
    matched_filter: MatchedFilterConfig = field(default_factory=MatchedFilterConfig)
    normalisation: NormalisationConfig = field(default_factory=NormalisationConfig)
    pathways: PathwayConfig = field(default_factory=PathwayConfig)
    neurons: LCNeuronConfig = field(default_factory=LCNeuronConfig)

    def to_dict(self) -> dict:
        """Every field as a dict, nested configurations as dicts."""
        return asdict(self)


def config_from_dict(cls, d: dict):
    """Rebuild a (nested, frozen) config dataclass ``cls`` from ``d``, :func:`dataclasses.asdict` output."""
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

