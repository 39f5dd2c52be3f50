"""One circuit on the compound eye: photoreceptors → HR EMDs → LC matched filters for translation.

Input: luminance of every ommatidium of :class:`lobula.compound_eye.CompoundEye` at the
eye's own rate (500 Hz by default), and the gyroscope ("haltere") angular velocity.
Output, per LC field f and readout step: the expansion rate ρ_f = v/D (1/s; D the range
along the field's direction) and the convective-corrected r²-term the readout needs.

Stages
------
1. **Photoreceptors** (:mod:`lobula.photoreceptor`): low-pass τ = 10 ms
   (light-adapted Drosophila R1–6, Juusola & Hardie 2001), then the LMCs' **lateral
   inhibition**, x' = x − mean of the six neighbouring columns, which removes the mean
   luminance in space (see "Lateral inhibition" below).
2. **EMDs** (:mod:`lobula.emd`, the project's one correlator) along every neighbour pair
   of the spherical lattice, delay τ = 35 ms (temporal-frequency optimum 1/(2πτ) ≈ 4.5 Hz,
   as blowfly HS cells: Hausen 1982; Borst & Egelhaaf 1989, TINS 12:297).
3. **LC fields**: Gaussian receptive fields of FWHM ``size_deg`` (tens of degrees, the
   size of Drosophila LC receptive fields: Wu et al. 2016, eLife 5:e21022) on each eye.
   Forward translation at speed v moves the image at direction d as
   ``ḋ = ρ·((d·ẑ)d − ẑ)``, ρ = v/D, so along pair p (unit tangent u_p from A to B) the
   image moves at ``ρ·m_p`` rad/s with the **matched-filter template** ``m_p = −ẑ·u_p``
   (magnitude sin θ·|cos| of the angle to the pair axis; θ from the focus of expansion
   ẑ, the body axis). With the gradient-ratio decoding of :mod:`lobula.emd_decoding`,
   ``R_p ≈ c_p·G_p·(ḋ·u_p)``, c_p = 2τ/Δφ_p and G_p = (x_B − x_A)², a field fits
   ρ(θ) = ρ_f + g_f·(θ − θ_f) by weighted least squares (noise variance ∝ G):
   two matched filters per field (the template, and the template weighted by θ − θ_f),
   divided by the pooled contrast signals — a 2×2 solve per field and step. By default
   each pair's speed is decoded before the pooling (see "Per-pair decoding" below).
4. **Material derivative.** ṙ = a/d + r² holds along a scene point; at a fixed direction
   points flow through. For ρ = v/D along a point, Dρ/Dt = a/D + ρ² cos θ, and
   at a fixed direction ∂ρ/∂t = Dρ/Dt − θ̇·∂ρ/∂θ with θ̇ = ρ sin θ. So
   ``v = a·ρ / (∂ρ/∂t − r2_eff)`` with ``r2_eff = ρ² cos θ − ρ sin θ · g`` — the
   readout's own ``v_f = a·r̄/(ṙ − r²)`` with r²̄ replaced by r2_eff. Exact for any plane
   (a side wall gives r2_eff = 0, a frontal wall ρ²/cos θ).

**Normalisation.** The gradient-ratio pool G = (x_B − x_A)² cancels contrast and pattern
only while ωτ ≪ 1: for a sine, R̄/Ḡ = ωτ·cot(Δϕ/2)/(1 + (ωτ)²). A fly's eye in a
textured world is far from that limit (components near the lattice's Nyquist limit have
high temporal frequency), and the loss grows with speed, so ρ̂ is not proportional to ρ
and ρ̂'s derivative misleads the readout. The "delayed" pool pairs the contrast difference
with its own delayed copy, ``G = (LP_τ(x_B) − LP_τ(x_A))·(x_B − x_A)``, made of the same
four signals the correlator multiplies: its mean is C²(1 − cos Δϕ)/(1 + (ωτ)²), so
``R̄/Ḡ = ωτ·cot(Δϕ/2)`` exactly — the correlator's temporal-frequency tuning divides out
(a divisive normalisation by a pool with the same temporal filtering as the EMD), and
only the spatial-sampling factor (Δϕ/2)·cot(Δϕ/2), constant in speed, remains.

**Per-pair decoding** (``normaliser = "pair"``, the default). Summed over a field *before*
the division, each pair counts with its pool, ∝ 1/(1 + (ωτ)²): the faster a part of the
field moves (the nearer its surface), the less it counts, so a field's ρ̂ leans on its far,
slow parts and grows slower than ρ. Measured on the dev worlds (seeds 7, 8; log–log slope β of
each field's ρ̂ against the exact v/D from the rendered range): β = 0.59–0.63 in a corridor,
where walls at very different distances share a field, and the readout's (ρ̇ − r²)/ρ of ρ^β
is β·a/v. So each pair's speed is decoded first, s_p = LP(R_p)/(c_p·(LP(G_p)⁺ + ε_p)), and
the field fits ρ_f, g_f to the s_p weighted by the pair's contrast energy LP((x_B − x_A)²),
which does not depend on speed (:meth:`EyeCircuit._pair_speeds`). Test: rings moving at
0.5 rad/s on one half of a field and 2 rad/s on the other read 0.999 of the mean of the two
alone (the delayed pool: 0.78). On the dev worlds β rises to 0.78–0.79 in the corridor and the
κ = a/v error falls from 0.46–0.51 to 0.26–0.30 of the rms acceleration. Each T4/T5 input in
the fly is normalised by its own recent local contrast (Drews et al. 2020, Curr Biol 30:209;
Matulis et al. 2020, Curr Biol 30:222); the field's synaptic drive Σ w·c·m·R (``lc.input``)
keeps the correlator's temporal-frequency tuning either way.

**Lateral inhibition** (``surround``, default 1). The correlator needs its inputs' mean
removed: with a mean luminance L in both arms, R gains a term L·(HP(x_B) − HP(x_A)) that is
linear in the pattern, zero on average and large wherever contrast is low. The usual model
removes it in time with an LMC-like high-pass (0.25 s: Eichner et al. 2011), but a temporal
high-pass of a moving pattern subtracts a trailing, blurred copy of it that moves with the
*past* speed: after every change of speed, and most after a reversal, the pairs' decoded speed
carries a transient of the high-pass's time constant, the same in every field (with the
high-pass, on dev panels worlds the fields' slow gains correlate at 0.54–0.66 across fields, the
common part 40 % of their variance, not explained by speed or timing). The readout takes that
drift for an accelerometer offset ("offset learned" in docs/fly-eye.md). LMCs also have an antagonistic
surround (Srinivasan, Laughlin & Dubs 1982, Proc R Soc B 216:427; Freifeld et al. 2013,
Neuron 79:111 for L2), and subtracting the neighbours' mean removes the mean luminance in
space, with no memory: the photoreceptor stage then needs no temporal high-pass. On
development eye worlds (seeds 100–105, 10 s, rates, causal, accelerometer), the surround against
the 0.25 s high-pass: panels 0.033 against 0.081 m/s, corridor 0.013 against 0.045, rotation
(100–102) 0.181 against 0.252; with the true acceleration and an offset to learn, panels 0.030
against 0.063, corridor 0.010 against 0.060 — with the surround the offset is not mislearned.
The alternatives read worse or no better: no high-pass and no surround (panels 0.17: the mean
leaks in as above), a 1 s high-pass (panels 0.08–0.30 on seeds 100–102, mean 0.18), the surround
together with the 0.25 s high-pass (panels 0.082, corridor 0.044), a Gaussian surround of
σ = 2Δφ instead of the six neighbours (panels / corridor 0.030 / 0.014 against 0.033 / 0.013:
within the seeds' spread, for a denser filter).

**Columnar pooling** (a hypothesis, off by default). Before the EMDs each column's
signal may be averaged with its six neighbours' (``column_pool``), as the T4/T5 input neurons pool over several columns
(Tm3's receptive field spans ~2–3 columns: Takemura et al. 2013, Nature 500:175; Behnia
et al. 2014, Nature 512:427). Why it matters here: the gradient ratio underestimates a
sine of phase step Δϕ between neighbours by (Δϕ/2)·cot(Δϕ/2) (0 at the Nyquist limit),
and with Δρ = Δφ a 1/f world puts much contrast near it; the 7-column average passes
λ = 2Δφ at −1/7 and λ = 6Δφ at 0.78, which raises the decoded gain toward 1 — but on a
panels world it also lowers the fields' correlation with the exact v/D (0.65 against 0.83
without) and raises the velocity RMSE, so it is off by default. (A gain γ on ρ does not cancel
in the readout v = a·ρ/(ρ̇ − r²): r² is made from ρ too, at γ², so κ = (ρ̇ − r²)/ρ errs by
(1 − γ)·r²/ρ, and a gain that varies adds γ̇/γ. Measured on the camera's EMD front end, whose
r̄ reads 0.45–0.65 of DIS's: dividing its rates by that gain takes a replay's RMSE only from 0.0111
to 0.0107 m/s.)

Rotation, two hypotheses (``rotation``):

- ``"haltere"``: the gyroscope's angular velocity ω predicts each pair's rotational image
  motion ``ω·(u_p × d_p)``; its EMD response ``c_p·G_p·ω·(u_p × d_p)`` is subtracted
  before pooling (ω passes the photoreceptor and EMD low-passes first, to stay in phase).
- ``"wide-field"``: mirror-image fields of the two eyes are summed before the solve. Yaw
  and roll move mirror points with opposite signs along mirror templates and cancel;
  translation adds (Krapp & Hengstenberg 1996, Nature 384:463 on matched wide-field
  filters). Pitch is symmetric left–right and does not cancel.
- ``"both"`` applies the two; ``"none"`` neither.

Causality: every stage is a causal filter; the readout step is a block sum over the
last ``1/readout_rate_hz`` s. Outputs are stamped ``latency_s`` earlier (photoreceptor
τ + EMD τ + half a block, and τ_EMD more for the per-pair decoding's low-pass), the same convention as the pinhole EMD front end: an estimate
stamped t is available at t + latency.

Shapes: luminance (T, n), gyro (T, 3); outputs per readout step (K, F). torch on CPU;
Python loops run over time only (inside the photoreceptor and EMD stages).
"""
from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ._optional import torch
from .compound_eye import CompoundEye
from .emd import EMDArray, EMDConfig
from .photoreceptor import PhotoreceptorConfig, Photoreceptors, lattice_filter, lowpass_scan, spatial_filter
from .readout import hold_gaps

__all__ = ["EyeFieldConfig", "EyeCircuitConfig", "EyeFields", "EyeCircuit", "eye_fields", "field_reliability",
           "natural_scene_gain"]

ROTATION_MODES = ("none", "haltere", "wide-field", "both")


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
        return float(self.spacing_deg if self.spacing_deg is not None else 2.0 * self.size_deg / 3.0)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["azimuth_deg"], d["elevation_deg"] = list(self.azimuth_deg), list(self.elevation_deg)
        return d


@dataclass
class EyeCircuitConfig:
    """The circuit from photoreceptor to LC fields on the compound eye (SI units).

    photoreceptor, emd: stage configurations (see the module docstring for the values'
    sources). fields: :class:`EyeFieldConfig`. rotation: "none" | "haltere" |
    "wide-field" | "both". readout_rate_hz: rate of the LC outputs the readout sees
    (block sums of the eye-rate signals). r2_term: what the readout's r²̄ receives —
    "convective" (ρ² cos θ − ρ sin θ·g, the material-derivative form; default), "point"
    (ρ² cos θ: along a point, no convective term; an ablation) or "none" (0). normaliser: the contrast pool G of the decoding,
    "delayed" ((LP(x_B) − LP(x_A))·(x_B − x_A)), "gradient" ((x_B − x_A)², the
    pinhole front end's) or "pair" (default: each pair's speed decoded with its own delayed pool,
    then pooled with contrast-energy weights); see "Normalisation" and "Per-pair decoding" in the
    module docstring. column_pool: weight α of the six neighbouring
    columns in each EMD input, x' = (1 − α)·x + α·mean(neighbours) (0: none, the default;
    6/7: a uniform 7-column average) — see "Columnar pooling" in the module docstring.
    surround: weight s of the LMC's lateral inhibition, x' = x − s·mean(neighbours) after the
    photoreceptors (and any columnar pooling): 1 (default) removes the mean luminance in space,
    so the photoreceptor stage needs no temporal high-pass (its ``tau_hp_s`` is None); 0: none
    (then pair it with the photoreceptor's ``tau_hp_s`` 0.25 s to remove the mean in time) — see
    "Lateral inhibition" in the module docstring.
    rotation_gain: "adaptive" (default: each field learns the gain γ at which its EMDs report the turn
    the haltere predicts, see :meth:`EyeCircuit._rotation_gain`) or "fixed" (the prediction subtracted at
    unit gain). rotation_gain_prior: γ's prior mean, what the adaptive gain starts from before a field
    has seen a turn (about a second) and is drawn toward while its evidence is weak; None (default):
    :func:`natural_scene_gain` for this eye and these lattice filters (0.48 for the default eye); 1: the
    unit gain, which over-subtracts a turn by half, a residue ~10× the fields' own signal in their first
    second (docs/fly-eye.md).
    calibration: gain on ρ (1 = none).
    latency_s: stamp shift; None = τ_photoreceptor + τ_EMD + half a block (+ τ_EMD more for the
    "pair" normaliser, whose per-pair decoding low-passes once more).
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

    def __post_init__(self):
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

    def to_dict(self) -> dict:
        return dict(photoreceptor=self.photoreceptor.to_dict(), emd=self.emd.to_dict(),
                    fields=self.fields.to_dict(), rotation=self.rotation, normaliser=self.normaliser,
                    r2_term=self.r2_term,
                    column_pool=self.column_pool, surround=self.surround, rotation_gain=self.rotation_gain,
                    rotation_gain_prior=self.rotation_gain_prior, readout_rate_hz=self.readout_rate_hz,
                    calibration=self.calibration, latency_s=self.latency_s)

    @classmethod
    def from_dict(cls, d: dict) -> "EyeCircuitConfig":
        d = dict(d)
        # A stored configuration without these fields describes a circuit without them: no surround
        # and the haltere gain's prior at unit gain.
        d.setdefault("surround", 0.0)
        d.setdefault("rotation_gain_prior", 1.0)
        f = dict(d.pop("fields", {}))
        for k in ("azimuth_deg", "elevation_deg"):
            if k in f:
                f[k] = tuple(f[k])
        return cls(photoreceptor=PhotoreceptorConfig(**d.pop("photoreceptor", {})),
                   emd=EMDConfig(**d.pop("emd", {})), fields=EyeFieldConfig(**f), **d)


@dataclass
class EyeFields:
    """LC fields: centres (F, 2) deg (az, el), eye (F,), unit centre directions (F, 3), theta (F,) rad
    from ẑ, the (F, P) pair weights, and ``mirror`` (F,): the index of each field's mirror field."""

    centres_deg: np.ndarray
    eye: np.ndarray
    directions: np.ndarray
    theta: np.ndarray
    weights: np.ndarray
    mirror: np.ndarray
    size_deg: float

    @property
    def n_fields(self) -> int:
        return len(self.eye)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (radians) between unit vectors, broadcast over leading dims."""
    return np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0))


def eye_fields(eye: CompoundEye, config: EyeFieldConfig) -> EyeFields:
    """Tile both eyes with mirror-symmetric Gaussian fields; weights over the eye's own pairs."""
    from .compound_eye import eye_directions

    sp = config.spacing
    a0, a1 = config.azimuth_deg
    e0, e1 = config.elevation_deg
    naz = max(1, int(math.floor((a1 - a0) / sp + 1e-9)) + 1)
    nel = max(1, int(math.floor((e1 - e0) / sp + 1e-9)) + 1)
    az = a0 + 0.5 * ((a1 - a0) - (naz - 1) * sp) + sp * np.arange(naz)
    el = e0 + 0.5 * ((e1 - e0) - (nel - 1) * sp) + sp * np.arange(nel)
    AZ, EL = (x.ravel() for x in np.meshgrid(az, el, indexing="xy"))
    present = [k for k in (0, 1) if (eye.eye == k).any()]
    cen = np.concatenate([np.stack([AZ if k == 0 else -AZ, EL], -1) for k in present])
    f_eye = np.concatenate([np.full(len(AZ), k) for k in present])
    nf = len(AZ)
    mirror = (np.concatenate([np.arange(nf) + nf, np.arange(nf)]) if len(present) == 2
              else np.arange(nf))
    dirs = eye_directions(np.radians(cen[:, 0]), np.radians(cen[:, 1]))
    ang = _angle(dirs[:, None, :], eye.pair_midpoint[None, :, :])               # (F, P)
    fwhm = math.radians(config.size_deg)
    w = np.exp(-4.0 * math.log(2.0) * (ang / fwhm) ** 2)
    w *= (ang <= 1.5 * fwhm) & (f_eye[:, None] == eye.eye[eye.pairs_a][None, :])
    theta = _angle(dirs, np.array([0.0, 0.0, 1.0]))
    return EyeFields(cen, f_eye, dirs, theta, w, mirror, float(config.size_deg))


class EyeCircuit:
    """Streaming circuit: ``process(luminance (T, n), gyro (T, 3))`` → completed readout steps.

    Keeps photoreceptor, EMD, gyro-filter and partial-block state between calls.
    ``finish()`` returns the last, partial block (if any). Each result is a dict of
    numpy arrays over readout steps: ``t`` (K,) stamped times, ``rho`` (K, F') 1/s,
    ``grad`` (K, F') 1/s per rad, ``r2_eff`` (K, F') 1/s², ``rot`` (K, F') 1/s (the rotation
    the haltere subtracted, as ρ at the learned gain; 0 without haltere subtraction),
    ``haltere_gain`` (K, F') the gain it was subtracted at (1 + α; 1 fixed; NaN without), with
    F' = F fields, or the mirror groups (F/2) under wide-field rotation cancelling.
    """

    #: haltere gain regression: running-mean time constant and memory (readout steps), prior std of α
    HP_STEPS, MEMORY_STEPS, ALPHA_PRIOR_STD = 50, 500, 0.5

    def __init__(self, eye: CompoundEye, rate_hz: float, config: EyeCircuitConfig | None = None):
        self.config = cfg = config or EyeCircuitConfig()
        self.eye = eye
        self.dt = 1.0 / float(rate_hz)
        self.block = max(1, int(round(rate_hz / cfg.readout_rate_hz)))
        self.fields = fields = eye_fields(eye, cfg.fields)
        self.photoreceptors = Photoreceptors(cfg.photoreceptor, self.dt)
        self.emds = EMDArray(eye.pairs_a, eye.pairs_b, cfg.emd, self.dt)
        # The per-pair decoding low-passes R and G once more with the EMD's τ (see _pair_speeds): a
        # first-order lag of τ more on the decoded speed (stamping without it put vision ~τ behind the
        # accelerometer: on the dev worlds, seeds 7, 8, 100, the causal RMSE fell 0.005–0.04 m/s with it).
        n_lp = 2 if cfg.normaliser == "pair" else 1
        self.latency_s = (cfg.latency_s if cfg.latency_s is not None
                          else cfg.photoreceptor.tau_s + n_lp * cfg.emd.tau_s + 0.5 * self.block * self.dt)
        tau = cfg.emd.tau_s
        c = 2.0 * tau / eye.pair_separation                                     # (P,)
        zhat = np.array([0.0, 0.0, 1.0])
        m = -(eye.pair_direction @ zhat)                                        # template (P,)
        theta_p = _angle(eye.pair_midpoint, zhat)
        delta = theta_p[None, :] - fields.theta[:, None]                        # (F, P)
        W = fields.weights
        k = np.cross(eye.pair_direction, eye.pair_midpoint)                     # rotational template (P, 3)
        # Numerator filters (on R) and denominator filters (on G), stacked for one matmul each.
        num = np.concatenate([(W * c * m), (W * c * m * delta)], 0)            # (2F, P)
        cgm = W * c * c * m
        den = [cgm * m, cgm * m * delta, cgm * m * delta ** 2]
        rot = [cgm * k[:, j] for j in range(3)] + [cgm * delta * k[:, j] for j in range(3)]
        if cfg.normaliser == "pair":
            # Each pair's speed is decoded first (R/(c·G)), then pooled with speed-independent weights.
            num = np.concatenate([W * m, W * m * delta], 0)
            wm = W * m
            den = [wm * m, wm * m * delta, wm * m * delta ** 2]
            rot = [wm * k[:, j] for j in range(3)] + [wm * delta * k[:, j] for j in range(3)]
        self._c = torch.as_tensor(c, dtype=torch.float32)
        # The LC's synaptic drive from its EMDs, Σ_p w·c·m·R_p (recorded as lc.input, whatever the pool).
        self._lc_input = torch.as_tensor((W * c * m).T, dtype=torch.float32)    # (P, F)
        self._num = torch.as_tensor(num.T, dtype=torch.float32)                  # (P, 2F)
        self._den = torch.as_tensor(np.concatenate(den + rot, 0).T, dtype=torch.float32)  # (P, 9F)
        self._pair_state = None
        self._pool = lattice_filter(eye, cfg.column_pool, cfg.surround)
        self._a = torch.as_tensor(eye.pairs_a)
        self._b = torch.as_tensor(eye.pairs_b)
        self._gyro_state: torch.Tensor | None = None
        self._gyro_pair: torch.Tensor | None = None
        self._lp_state: torch.Tensor | None = None
        self._carry: list = []           # partial block of per-step sums
        self._t0 = 0.0
        self._n_steps = 0
        self._floor = None
        self._rot_state = None
        self.gain_prior = (cfg.rotation_gain_prior if cfg.rotation_gain_prior is not None else
                           natural_scene_gain(eye.config.dphi_deg, eye.config.acceptance_deg, cfg.surround,
                                              cfg.column_pool))
        self.timings = dict(photoreceptor=0.0, emd=0.0, fields=0.0)

    @property
    def n_outputs(self) -> int:
        F = self.fields.n_fields
        return F // 2 if self.config.rotation in ("wide-field", "both") and F > 1 and \
            (self.fields.mirror != np.arange(F)).all() else F

    def _gyro_filtered(self, gyro: torch.Tensor) -> torch.Tensor:
        """ω through the photoreceptor and EMD low-passes (continuing state), (..., T, 3)."""
        cfg = self.config
        if self._gyro_state is None:
            self._gyro_state = torch.stack([gyro[..., 0, :], gyro[..., 0, :]])
        a1 = math.exp(-self.dt / cfg.photoreceptor.tau_s) if cfg.photoreceptor.tau_s > 0 else 0.0
        a2 = math.exp(-self.dt / cfg.emd.tau_s)
        g1 = lowpass_scan(gyro, a1, self._gyro_state[0])
        g2 = lowpass_scan(g1, a2, self._gyro_state[1])
        self._gyro_state = torch.stack([g1[..., -1, :], g2[..., -1, :]])
        if cfg.normaliser == "pair":   # the pairs' speeds pass one more low-pass (see _pair_speeds)
            if self._gyro_pair is None:
                self._gyro_pair = g2[..., 0, :]
            g2 = lowpass_scan(g2, a2, self._gyro_pair)
            self._gyro_pair = g2[..., -1, :]
        return g2

    #: time constant (s) of the running mean of each pair's contrast energy that sets its semi-saturation floor
    PAIR_FLOOR_TAU_S = 2.0

    def _pair_speeds(self, R: torch.Tensor, dy: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
        """Per-pair decoded image speed times its contrast weight, and the weights: (..., T, 2F + 9F) sums.

        Each EMD's output is divided by its own delayed-contrast pool before any pooling,
        s_p = LP(R_p) / (c_p·(LP(G_p)⁺ + ε_p)) (rad/s along u_p; LP the EMD's own τ, which
        averages the correlator's ripple; ε_p = ``fields.floor`` × the pair's contrast energy
        (x_B − x_A)² averaged over ``PAIR_FLOOR_TAU_S``, a semi-saturation constant), and the
        LC field then fits ρ_f, g_f to the s_p weighted by the contrast energy H_p = LP((x_B − x_A)²),
        which does not depend on the speed. Why: pooled first (default "delayed"), a pair's weight in
        the fit is its pool G_p ∝ C²/(1 + (ωτ)²), smaller the faster its image moves, so the fit leans
        on the far, slow parts of a field and ρ̂ grows slower than ρ (measured on dev worlds, log–log
        slope β of ρ̂ against the exact v/D: 0.6 in a corridor); the readout's (ρ̇ − r²)/ρ of ρ^β is
        β·a/v. Local contrast normalisation before the direction-selective stage is what the fly's
        motion pathway does (Drews et al. 2020, Curr Biol 30:209; Matulis et al. 2020, Curr Biol
        30:222): each T4/T5 input is normalised by its own recent contrast.
        """
        a = math.exp(-self.dt / self.config.emd.tau_s)
        af = math.exp(-self.dt / self.PAIR_FLOOR_TAU_S)
        H = dy * dy
        st = self._pair_state or {}
        lR = lowpass_scan(R, a, st.get("R"))
        lG = lowpass_scan(G, a, st.get("G"))
        lH = lowpass_scan(H, a, st.get("H"))
        slow = lowpass_scan(H, af, st.get("slow"))
        self._pair_state = dict(R=lR[..., -1, :].clone(), G=lG[..., -1, :].clone(), H=lH[..., -1, :].clone(),
                                slow=slow[..., -1, :].clone())
        speed = lR / (self._c * (lG.clamp(min=0.0) + self.config.fields.floor * slow + 1e-12))
        return torch.cat([(speed * lH) @ self._num, lH @ self._den], dim=-1)

    def _sums(self, lum: torch.Tensor, gyro: torch.Tensor | None, keep: dict | None = None,
              with_rotation: bool = False) -> torch.Tensor:
        """Per-step pooled sums (..., T, 5F): b1, b2 (2F), A11, A12, A22 (3F), haltere-corrected.

        with_rotation: when the haltere correction ran, also return the two subtracted
        predictions (the rotational response of b1, b2 at unit gain), as (..., T, 7F).

        lum (..., T, n); gyro (..., T, 3) or None (no rotation signal: nothing subtracted).
        keep: a dict that receives the stages' signals "photoreceptor.v" (..., T, n) and
        "emd.response" (..., T, P) when it has those keys (for recording).
        """
        import time as _time
        t0 = _time.perf_counter()
        y = self.photoreceptors.run(lum)
        y = spatial_filter(self._pool, y)
        t1 = _time.perf_counter()
        R = self.emds.run(y)                                                    # (..., T, P)
        t2 = _time.perf_counter()
        if keep is not None:
            if "photoreceptor.v" in keep:
                keep["photoreceptor.v"] = y
            if "emd.response" in keep:
                keep["emd.response"] = R
            if "lc.input" in keep:
                keep["lc.input"] = R @ self._lc_input
        dy = y[..., self._b] - y[..., self._a]
        if self.config.normaliser in ("delayed", "pair"):
            # The contrast difference times its own delayed (low-passed) copy: the EMD's four signals.
            lp = lowpass_scan(dy, math.exp(-self.dt / self.config.emd.tau_s), self._lp_state)
            self._lp_state = lp[..., -1, :].clone()
            G = lp * dy
        else:
            G = dy * dy
        out = (self._pair_speeds(R, dy, G) if self.config.normaliser == "pair"
               else torch.cat([R @ self._num, G @ self._den], dim=-1))
        self.timings["photoreceptor"] += t1 - t0
        self.timings["emd"] += t2 - t1
        self.timings["fields"] += _time.perf_counter() - t2
        F = self.fields.n_fields
        if self.config.rotation in ("haltere", "both") and gyro is not None:
            w = self._gyro_filtered(gyro)                                       # (..., T, 3)
            rot = out[..., 5 * F:].reshape(out.shape[:-1] + (2, 3, F))
            corr = torch.einsum("...tj,...tkjf->...tkf", w, rot)                # (..., T, 2, F)
            corr = corr.reshape(out.shape[:-1] + (2 * F,))
            out[..., :2 * F] -= corr
            if with_rotation:
                # The subtracted prediction travels with the sums: the solve learns its gain (see _solve).
                return torch.cat([out[..., :5 * F], corr], dim=-1)
        return out[..., :5 * F]

    def run_steps(self, luminance, gyro=None, record=()) -> dict:
        """The circuit at the eye's rate, batched over leading dims (stimulus conditions).

        luminance (..., T, n); gyro (..., T, 3) rad/s or None (a stimulus without
        self-rotation). Continues the circuit's state like :meth:`process`. Returns torch
        tensors: ``sums`` (..., T, 5F), the per-step pooled signals (b1, b2, then the pools
        A11, A12, A22), plus "photoreceptor.v", "emd.response" and "lc.input" (the fields'
        matched-filter input Σ_p w·c·m·R_p, (..., T, F): b1 itself for the "delayed" and
        "gradient" pools) when named in ``record``.
        """
        lum = torch.as_tensor(luminance, dtype=torch.float32)
        if lum.dim() < 2 or lum.shape[-1] != self.eye.n:
            raise ValueError(f"luminance must be (..., time, {self.eye.n}) for this eye, got {tuple(lum.shape)}")
        gyr = None if gyro is None else torch.as_tensor(gyro, dtype=torch.float32)
        if gyr is not None and gyr.shape != lum.shape[:-1] + (3,):
            raise ValueError(f"gyro must be (..., time, 3) matching the luminance, got {tuple(gyr.shape)}")
        keep = {k: None for k in record if k in ("photoreceptor.v", "emd.response", "lc.input")}
        sums = self._sums(lum, gyr, keep)
        return dict(sums=sums, **{k: v for k, v in keep.items() if v is not None})

    def solve_blocks(self, block_sums: np.ndarray, t_end: np.ndarray) -> dict:
        """ρ, g and r2_eff from block sums (..., K, 5F) (the readout's 2×2 solve; continues the floor)."""
        return self._solve(np.asarray(block_sums, dtype=float), np.asarray(t_end, dtype=float))

    def process(self, luminance, gyro) -> dict:
        """Feed (T, n) luminance and (T, 3) angular velocity (rad/s, camera frame) at the eye's rate."""
        lum = torch.as_tensor(np.array(luminance, dtype=np.float32))
        gyr = torch.as_tensor(np.array(gyro, dtype=np.float32))
        if lum.dim() != 2 or lum.shape[1] != self.eye.n:
            raise ValueError(f"luminance must be (time, {self.eye.n}) for this eye, got {tuple(lum.shape)}")
        if gyr.shape != (lum.shape[0], 3):
            raise ValueError(f"gyro must be (time, 3) matching the luminance, got {tuple(gyr.shape)}")
        s = self._sums(lum, gyr, with_rotation=self.config.rotation_gain == "adaptive").double()
        if self._carry:
            s = torch.cat([self._carry.pop(), s])
        start = self._n_steps - (len(s) - lum.shape[0])
        self._n_steps += lum.shape[0]
        nb = len(s) // self.block
        if len(s) > nb * self.block:
            self._carry.append(s[nb * self.block:])
        if nb == 0:
            return self._solve(np.zeros((0, s.shape[1])), np.zeros(0))
        blocks = s[:nb * self.block].reshape(nb, self.block, -1).sum(1).numpy()
        t_end = (start + self.block * np.arange(1, nb + 1) - 1) * self.dt
        return self._solve(blocks, t_end)

    def finish(self) -> dict:
        """The final partial block, if any."""
        if not self._carry:
            return self._solve(np.zeros((0, 5 * self.fields.n_fields)), np.zeros(0))
        s = self._carry.pop()
        t_end = np.array([(self._n_steps - 1) * self.dt])
        return self._solve(s.sum(0, keepdim=True).numpy() * (self.block / len(s)), t_end)

    def _rotation_gain(self, rho: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Causal per-field estimate of α = γ − 1, the field's gain γ less the haltere's unit gain, (K, F').

        The decoded image motion is γ·(true motion) with γ = (Δϕ/2)·cot(Δϕ/2) averaged
        over the field's texture (< 1, and the same for rotation and translation: one set
        of EMDs sees both). The haltere predicts the rotational response at gain 1, so
        ρ̂ = γρ + α·q after the subtraction, q the subtracted rotation's ρ. Rotation is
        independent of translation, so α is the regression of ρ̂ on q — over past readout
        steps only, both with their running means (time constant ``HP_STEPS``, learning starts
        once they have run that long; a constant turn is not told from translation) removed, with
        forgetting (``MEMORY_STEPS``) and a prior α = α₀ ± ``ALPHA_PRIOR_STD`` (α₀ = ``gain_prior`` − 1,
        the config's ``rotation_gain_prior`` or :func:`natural_scene_gain`) against ρ̂'s own running
        variance s² as the noise: the posterior mean (Σ δρ·δq + α₀·s²/σ₀²) / (Σ δq² + s²/σ₀²), α₀ until
        the field has learned (no rotation seen: the prior's gain). α is held in [−1, 0.5] (γ between 0
        and 1.5) and the estimate at step k uses steps before k only.
        """
        K, Fo = rho.shape[-2], rho.shape[-1]
        st = self._rot_state
        if st is None:
            z = np.zeros(rho.shape[:-2] + (Fo,))
            st = dict(mr=np.nan_to_num(rho[..., 0, :]), mq=q[..., 0, :].copy(), sxy=z.copy(), sxx=z.copy(),
                      vr=z.copy(), n=0)
        hp, mem = 1.0 / self.HP_STEPS, 1.0 / self.MEMORY_STEPS
        a0, w0 = self.gain_prior - 1.0, 1.0 / self.ALPHA_PRIOR_STD ** 2
        alpha = np.empty_like(rho)
        for k in range(K):  # a loop over readout steps, vectorised over fields
            den = st["sxx"] + st["vr"] * w0
            with np.errstate(invalid="ignore", divide="ignore"):
                a = np.where(den > 0, (st["sxy"] + a0 * st["vr"] * w0) / den, a0)
            alpha[..., k, :] = np.clip(np.nan_to_num(a, nan=a0), -1.0, 0.5)
            r, qk = rho[..., k, :], q[..., k, :]
            ok = np.isfinite(r)
            dr, dq = np.where(ok, r - st["mr"], 0.0), np.where(ok, qk - st["mq"], 0.0)
            st["mr"] = np.where(ok, st["mr"] + hp * dr, st["mr"])
            st["mq"] = st["mq"] + hp * (qk - st["mq"])
            st["n"] += 1
            if st["n"] > self.HP_STEPS:   # the running means have settled: learn
                st["sxy"] = (1 - mem) * st["sxy"] + dr * dq
                st["sxx"] = (1 - mem) * st["sxx"] + dq * dq
                st["vr"] = (1 - mem) * st["vr"] + mem * dr * dr
        self._rot_state = st
        return alpha

    def _solve(self, sums: np.ndarray, t_end: np.ndarray) -> dict:
        """Per-block 2×2 weighted least squares for (ρ_f, g_f) and r2_eff."""
        F = self.fields.n_fields
        parts = [sums[..., i * F:(i + 1) * F] for i in range(sums.shape[-1] // F)]
        theta = self.fields.theta
        if self.n_outputs != F:   # wide-field: sum mirror fields (right f with left mirror[f])
            right = np.flatnonzero(self.fields.eye == 0)
            left = self.fields.mirror[right]
            parts = [x[..., right] + x[..., left] for x in parts]
            theta = theta[right]
        b1, b2, A11, A12, A22 = parts[:5]
        cfg = self.config.fields
        q = np.zeros_like(b1)
        # The gain each field subtracts the haltere's prediction at: 1 + α learned, 1 when fixed, NaN without.
        gain = np.full_like(b1, 1.0 if self.config.rotation in ("haltere", "both") else np.nan)
        if A11.shape[-2]:
            # Semi-saturation floor: a running mean (over past blocks only) of each field's pool.
            floors = np.empty_like(A11)
            level = A11[..., 0, :] if self._floor is None else self._floor
            for k in range(A11.shape[-2]):  # a loop over readout steps, vectorised over fields
                level = 0.99 * level + 0.01 * A11[..., k, :]
                floors[..., k, :] = level
            self._floor = level
            A11 = A11 + cfg.floor * floors
        A22 = A22 * (1.0 + cfg.gradient_ridge)
        det = A11 * A22 - A12 * A12
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(det > 0, (A22 * b1 - A12 * b2) / det, np.nan)
            grad = np.where(det > 0, (A11 * b2 - A12 * b1) / det, np.nan)
            if len(parts) == 7 and A11.shape[-2]:
                # ρ and g of the rotation the haltere subtracted, at unit gain.
                c1, c2 = parts[5:]
                q = np.where(det > 0, (A22 * c1 - A12 * c2) / det, 0.0)
                qg = np.where(det > 0, (A11 * c2 - A12 * c1) / det, 0.0)
                alpha = self._rotation_gain(rho, q)
                rho, grad = rho - alpha * q, grad - alpha * qg
                q, gain = (1.0 + alpha) * q, 1.0 + alpha
            rho, grad = rho * self.config.calibration, grad * self.config.calibration
        mode = self.config.r2_term
        r2_eff = (rho ** 2 * np.cos(theta) - rho * np.sin(theta) * grad if mode == "convective"
                  else rho ** 2 * np.cos(theta) if mode == "point" else np.zeros_like(rho))
        return dict(t=t_end - self.latency_s, rho=rho, grad=grad, r2_eff=r2_eff, rot=q * self.config.calibration,
                    haltere_gain=gain)


@functools.lru_cache(maxsize=32)
def natural_scene_gain(dphi_deg: float, drho_deg: float, surround: float = 1.0, column_pool: float = 0.0,
                       spectrum_exponent: float = 2.0, n: int = 401, k_max: float = 12.0) -> float:
    """The gain γ at which a pair's decoded speed reads image motion on a natural scene (dimensionless).

    A pair's speed LP(R)/(c·LP(G)) reads a sine of phase step k between its two ommatidia at
    (k/2)·cot(k/2) of its true speed (:mod:`lobula.emd_decoding`), and a texture's components add in
    R and G with weights ∝ their power P(k⃗) times 1 − cos k∥, so γ = Σ P·(k∥/2)·sin k∥ / Σ P·(1 − cos k∥)
    (k∥ the phase step along the pair; components beyond the Nyquist limit count with sin k∥'s sign,
    as aliasing does). P: natural scenes' isotropic 1/f^``spectrum_exponent`` power spectrum (≈ 2:
    Field 1987, J Opt Soc Am A 4:2379; van der Schaaf & van Hateren 1996, Vision Res 36:2759), times the
    Gaussian acceptance's squared MTF (FWHM ``drho_deg``) and the squared transfer of the lattice
    filters, ((1 − α) + α·N(k⃗))·(1 − s·N(k⃗)) with N the six-neighbour mean on the hexagonal lattice of
    spacing ``dphi_deg`` (:func:`lobula.photoreceptor.lattice_filter`). Averaged over the lattice's
    three pair orientations on an n × n grid of k⃗ up to ``k_max`` rad per Δφ.

    The default eye (Δφ = Δρ = 5°, surround 1): 0.48 (1/f^1.5 … 1/f^2.5: 0.43 … 0.52); without the
    surround 0.73. Measured on development rotation worlds 100 / 101 (per-field least-squares fits
    over 1–10 s of ρ̂ on the exact v/D and the haltere's subtracted rotation): α = γ − 1 = −0.48 to −0.56.
    """
    if not (dphi_deg > 0 and drho_deg > 0 and math.isfinite(dphi_deg) and math.isfinite(drho_deg)):
        raise ValueError(f"natural_scene_gain needs positive, finite Δφ and Δρ (degree), got {dphi_deg}, {drho_deg}")
    if not (0.0 <= surround <= 1.0 and 0.0 <= column_pool <= 1.0):
        raise ValueError(f"surround and column_pool must lie in [0, 1], got {surround}, {column_pool}")
    k = np.linspace(-k_max, k_max, n)
    kx, ky = np.meshgrid(k, k)
    kk = np.maximum(np.hypot(kx, ky), 1e-9)
    sigma = drho_deg / dphi_deg / (2.0 * math.sqrt(2.0 * math.log(2.0)))   # acceptance σ in units of Δφ
    angles = np.arange(6) * np.pi / 3
    ring = np.mean([np.cos(kx * np.cos(a) + ky * np.sin(a)) for a in angles], 0)
    transfer = ((1.0 - column_pool) + column_pool * ring) * (1.0 - surround * ring)
    power = kk ** -spectrum_exponent * np.exp(-(kk * sigma) ** 2) * transfer ** 2
    gains = []
    for a in angles[:3]:
        kp = kx * np.cos(a) + ky * np.sin(a)
        gains.append(float((power * 0.5 * kp * np.sin(kp)).sum() / (power * (1.0 - np.cos(kp))).sum()))
    return float(np.mean(gains))


def _first_order(x: np.ndarray, alpha: np.ndarray | float, axis: int = 0) -> np.ndarray:
    """Causal first-order low-pass y_k = y_{k−1} + α·(x_k − y_{k−1}) along ``axis``, starting from 0."""
    from scipy.signal import lfilter

    return lfilter([alpha], [1.0, alpha - 1.0], x, axis=axis)


def field_reliability(t: np.ndarray, rho: np.ndarray, slow_hz: float = 0.5, fast_hz: float = 2.0,
                      tau_s: float = 2.0) -> np.ndarray:
    """Causal slow-to-fast power ratio of each LC field's output: how much of it is the flight's expansion.

    t (K,) s, uniformly spaced; rho (K, F) 1/s (NaN: silent, taken as 0). Returns (K, F): the running
    mean (time constant ``tau_s``) of the square of the field's slow component (first-order low-pass
    at ``slow_hz``) over that of its fast component (the field less a low-pass at ``fast_hz``); step k
    uses steps ≤ k only. The expansion a translating fly sees changes slowly (ρ = v/D: the speed and
    the distances change over seconds), whereas the correlators' pattern noise is broadband and grows
    with image speed: a turn moves the whole image, so under rotation a field looking at nothing near
    (sky, a distant backdrop) carries little expansion and much fast noise and rotation residue — its
    slow part is then mostly that noise's leak. Measured on development worlds (seeds 100, 101; causal
    circuit, haltere rotation handling): the ratio over the whole record separates the fields whose ρ
    follows the exact v/D (correlation 0.92–0.99 where it exceeds 5; 0.1–0.3 where it is below 1); the
    log of the ratio correlates with the field's correlation at 0.80 (rotation world) and 0.95 (panels).
    A downstream neuron can compute it: two low-passes of the same input and the running mean of
    each's square (the rectified power of a slow and a fast channel).
    """
    t = np.asarray(t, dtype=float)
    rho = np.asarray(rho, dtype=float)
    if len(t) < 2:
        return np.zeros_like(rho)
    dt = float(np.median(np.diff(t)))
    # Each field's channels start at its first output (the circuit's start-up is silent, NaN): its value
    # held before that, its last value held through silent steps, so no start-up step reads as fast power.
    ok = np.isfinite(rho)
    first = np.argmax(ok, axis=0)
    x = np.nan_to_num(hold_gaps(rho))
    live = np.arange(len(rho))[:, None] >= np.where(ok.any(0), first, len(rho))
    lp = lambda y, fc: _first_order(y - y[:1], 1.0 - math.exp(-2.0 * math.pi * fc * dt)) + y[:1]  # noqa: E731
    slow = lp(x, slow_hz)
    fast = x - lp(x, fast_hz)
    a = 1.0 - math.exp(-dt / tau_s)
    ps, pf = _first_order(slow ** 2 * live, a), _first_order(fast ** 2 * live, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(pf > 0, ps / np.maximum(pf, 1e-300), np.where(ps > 0, np.inf, 0.0))
