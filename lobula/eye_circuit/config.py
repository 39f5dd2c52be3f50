"""The eye circuit's settings: :class:`EyeFieldConfig` (the LC receptive fields on the eyes) and
:class:`EyeCircuitConfig` (the circuit from photoreceptor to LC fields).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from ..emd import EMDConfig
from ..photoreceptor import PhotoreceptorConfig


ROTATION_MODES = ("none", "haltere", "wide-field", "both")
#: motion detectors along the neighbour pairs (EyeCircuitConfig.detector)
DETECTORS = ("hr", "three-arm")


@dataclass
class EyeFieldConfig:
    """LC receptive fields on the eyes (degrees).

    size_deg: Gaussian FWHM (weights cut at 1.5 FWHM). spacing_deg: centre grid spacing
    (None = 2/3 of the size). azimuth_deg / elevation_deg: range of centres on the
    right eye (the left mirrors it). gradient_ridge: prior weight keeping the fitted
    gradient g_f near 0 when a field's pairs do not constrain it, as a fraction of the
    field's own Σ c²Gm²δ². floor: semi-saturation floor on the pooled contrast, as a
    fraction of its running mean over past readout steps (causal, time constant ~100 steps).
    """

    size_deg: float = 30.0
    spacing_deg: float | None = None
    azimuth_deg: tuple = (10.0, 150.0)
    elevation_deg: tuple = (-45.0, 45.0)
    gradient_ridge: float = 0.05
    floor: float = 0.02

    def __post_init__(self):
        if not (2.0 <= self.size_deg <= 120.0):
            raise ValueError(f"LC field size_deg must be in [2, 120] degrees, got {self.size_deg}")
        if self.spacing_deg is not None and not self.spacing_deg > 0:
            raise ValueError(f"spacing_deg must be positive or None, got {self.spacing_deg}")

    @property
    def spacing(self) -> float:
        """Centre spacing (degrees): spacing_deg, or 2/3 of the size."""
        return float(self.spacing_deg if self.spacing_deg is not None else 2.0 * self.size_deg / 3.0)

    def to_dict(self) -> dict:
        """Every field as a dict (the angle ranges as lists)."""
        d = asdict(self)
        d["azimuth_deg"], d["elevation_deg"] = list(self.azimuth_deg), list(self.elevation_deg)
        return d


@dataclass
class EyeCircuitConfig:
    """The circuit from photoreceptor to LC fields on the compound eye (SI units).

    photoreceptor, emd: stage configurations (see :mod:`lobula.eye_circuit` for the values'
    sources). fields: :class:`EyeFieldConfig`. rotation: "none" | "haltere" |
    "wide-field" | "both". readout_rate_hz: rate of the LC outputs the readout sees
    (block sums of the eye-rate signals). r2_term: what the readout's r²̄ receives —
    "convective" (ρ² cos θ − ρ sin θ·g, the material-derivative form; default), "point"
    (ρ² cos θ: along a point, no convective term; an ablation) or "none" (0). normaliser: the contrast pool G of the decoding,
    "delayed" ((LP(x_B) − LP(x_A))·(x_B − x_A)), "gradient" ((x_B − x_A)², the
    pinhole front end's) or "pair" (default: each pair's speed decoded with its own delayed pool,
    then pooled with contrast-energy weights); see "Normalisation" and "Per-pair decoding" in the
    :mod:`lobula.eye_circuit`. column_pool: weight α of the six neighbouring
    columns in each EMD input, x' = (1 − α)·x + α·mean(neighbours) (0: none, the default;
    6/7: a uniform 7-column average) — see "Columnar pooling" in :mod:`lobula.eye_circuit`.
    surround: weight s of the LMC's lateral inhibition, x' = x − s·mean(neighbours) after the
    photoreceptors (and any columnar pooling): 1 (default) removes the mean luminance in space,
    so the photoreceptor stage needs no temporal high-pass (its ``tau_hp_s`` is None); 0: none
    (then pair it with the photoreceptor's ``tau_hp_s`` 0.25 s to remove the mean in time) — see
    "Lateral inhibition" in :mod:`lobula.eye_circuit`.
    rotation_gain: "adaptive" (default: each field learns the gain γ at which its EMDs report the turn
    the haltere predicts, see :meth:`EyeCircuit._rotation_gain`) or "fixed" (the prediction subtracted at
    unit gain). rotation_gain_prior: γ's prior mean, what the adaptive gain starts from before a field
    has seen a turn (about a second) and is drawn toward while its evidence is weak; None (default):
    :func:`natural_scene_gain` for this eye and these lattice filters (0.48 for the default eye); 1: the
    unit gain, which over-subtracts a turn by half, a residue ~10× the fields' own signal in their first
    second (docs/fly-eye.md).
    calibration: gain on ρ (1 = none).
    saccade_gate_deg_s: saccadic suppression (see "Saccadic suppression" in :mod:`lobula.eye_circuit`):
    while the haltere's |ω| exceeds this (°/s), and for :meth:`saccade_hold_s` after, the readout steps
    are flagged ``saccade`` and the circuit's learned state (the haltere gain, the pools' floor) does not
    learn from them; the readout skips their visual update. 300 (default): above the intersaccadic yaw
    rates of flies and below the peaks of their body saccades; None: no gate. A flight without saccades
    never reaches it, so there the gate changes nothing.
    latency_s: stamp shift; None = τ_photoreceptor + τ_EMD + half a block (+ τ_EMD more for the
    "pair" normaliser, whose per-pair decoding low-passes once more).
    detector: the motion detector along every neighbour pair — "hr" (default: the Hassenstein–Reichardt
    correlator of :mod:`lobula.emd`) or "three-arm" (:mod:`lobula.three_arm`: HR enhancement by the
    preferred-side arm and Barlow–Levick shunting by the null-side arm on ON and OFF pathways, as T4/T5;
    its delay is ``emd.tau_s``); the decoding, pools and rotation handling are the same for both.
    three_arm_weight: the three-arm detector's null-side shunting weight w (dimensionless; 0: the
    two-quadrant HR correlator).
    """

    photoreceptor: PhotoreceptorConfig = field(default_factory=lambda: PhotoreceptorConfig(tau_s=0.010))
    emd: EMDConfig = field(default_factory=lambda: EMDConfig(tau_s=0.035))
    fields: EyeFieldConfig = field(default_factory=EyeFieldConfig)
    rotation: str = "haltere"
    normaliser: str = "pair"
    r2_term: str = "convective"
    column_pool: float = 0.0
    surround: float = 1.0
    rotation_gain: str = "adaptive"
    rotation_gain_prior: float | None = None
    readout_rate_hz: float = 50.0
    calibration: float = 1.0
    latency_s: float | None = None
    saccade_gate_deg_s: float | None = 300.0
    detector: str = "hr"
    three_arm_weight: float = 1.0

    def __post_init__(self):
        if self.detector not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {self.detector!r}")
        if not (self.three_arm_weight >= 0.0 and math.isfinite(self.three_arm_weight)):
            raise ValueError(f"three_arm_weight must be a finite number >= 0, got {self.three_arm_weight}")
        if self.rotation not in ROTATION_MODES:
            raise ValueError(f"rotation must be one of {ROTATION_MODES}, got {self.rotation!r}")
        if self.r2_term not in ("convective", "point", "none"):
            raise ValueError(f"r2_term must be 'convective', 'point' or 'none', got {self.r2_term!r}")
        if self.normaliser not in ("delayed", "gradient", "pair"):
            raise ValueError(f"normaliser must be 'delayed', 'gradient' or 'pair', got {self.normaliser!r}")
        if self.rotation_gain not in ("adaptive", "fixed"):
            raise ValueError(f"rotation_gain must be 'adaptive' or 'fixed', got {self.rotation_gain!r}")
        if self.rotation_gain_prior is not None and not (0.0 < self.rotation_gain_prior <= 1.5):
            raise ValueError(f"rotation_gain_prior must lie in (0, 1.5] or be None, got {self.rotation_gain_prior}")
        if not (0.0 <= self.column_pool <= 1.0):
            raise ValueError(f"column_pool must lie in [0, 1], got {self.column_pool}")
        if not (0.0 <= self.surround <= 1.0):
            raise ValueError(f"surround must lie in [0, 1], got {self.surround}")
        if not self.readout_rate_hz > 0:
            raise ValueError(f"readout_rate_hz must be positive, got {self.readout_rate_hz}")
        if self.saccade_gate_deg_s is not None and not self.saccade_gate_deg_s > 0:
            raise ValueError(f"saccade_gate_deg_s must be positive (°/s) or None, got {self.saccade_gate_deg_s}")

    def saccade_hold_s(self) -> float:
        """s the saccade gate holds after the haltere's rate falls below ``saccade_gate_deg_s``: three times the
        sum of the circuit's own time constants (photoreceptor low-pass and high-pass, the EMD delay, and the
        per-pair decoding's low-pass for the "pair" normaliser), by when a saccade's residue in the LC
        outputs has decayed to e⁻³ (5 %) of its size; 0.24 s for the default circuit."""
        n_lp = 2 if self.normaliser == "pair" else 1
        return 3.0 * (self.photoreceptor.tau_s + n_lp * self.emd.tau_s + (self.photoreceptor.tau_hp_s or 0.0))

    def to_dict(self) -> dict:
        """Every field as a dict, nested configurations as dicts."""
        return dict(photoreceptor=self.photoreceptor.to_dict(), emd=self.emd.to_dict(),
                    fields=self.fields.to_dict(), rotation=self.rotation, normaliser=self.normaliser,
                    r2_term=self.r2_term,
                    column_pool=self.column_pool, surround=self.surround, rotation_gain=self.rotation_gain,
                    rotation_gain_prior=self.rotation_gain_prior, readout_rate_hz=self.readout_rate_hz,
                    calibration=self.calibration, latency_s=self.latency_s,
                    saccade_gate_deg_s=self.saccade_gate_deg_s, detector=self.detector,
                    three_arm_weight=self.three_arm_weight)

    @classmethod
    def from_dict(cls, d: dict) -> "EyeCircuitConfig":
        """The configuration :meth:`to_dict` wrote as ``d``."""
        d = dict(d)
        # A stored configuration without these fields describes a circuit without them: no surround
        # and the haltere gain's prior at unit gain.
        d.setdefault("surround", 0.0)
        d.setdefault("rotation_gain_prior", 1.0)
        d.setdefault("saccade_gate_deg_s", None)
        f = dict(d.pop("fields", {}))
        for k in ("azimuth_deg", "elevation_deg"):
            if k in f:
                f[k] = tuple(f[k])
        return cls(photoreceptor=PhotoreceptorConfig(**d.pop("photoreceptor", {})),
                   emd=EMDConfig(**d.pop("emd", {})), fields=EyeFieldConfig(**f), **d)
