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
   ẑ, the body axis). With the gradient-ratio decoding of :mod:`lobula.emd_front_end`,
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

**Saccadic suppression** (``saccade_gate_deg_s``, 300 °/s). While the haltere's |ω| exceeds the gate and
for a hold after (three times the sum of the circuit's time constants, 0.24 s by default: the saccade's
residue down to e⁻³), the readout steps are flagged ``saccade``: the haltere gain and the pools' floor do not
learn from them, and the readout (:func:`experiments.eye_velocity.suppressed_readout`) skips their visual
update. A body saccade moves the image far past the EMDs' temporal-frequency optimum, where the haltere's
linear prediction fails, and turns every field onto other surfaces, so ρ jumps by what they are, not by
a/D; flies suppress motion vision during course-changing turns (Kim, Fitzgerald & Maimon 2015, Nat Neurosci
18:1247; Fenk, Kim & Maimon 2021, Curr Biol 31). A flight that never turns that fast is unchanged.

**The motion detector** (``detector``, "hr" by default). ``"three-arm"`` replaces the correlator along every
pair by :mod:`lobula.three_arm`'s detector at the same delay τ: on ON and OFF pathways (T4, T5), a delayed
preferred-side arm multiplies the centre (HR enhancement) and a delayed null-side arm, one ommatidium
beyond the pair, shunts it (Barlow–Levick suppression; Haag et al. 2016, eLife 5:e17421; Leong et al. 2016,
J Neurosci 36:8078). The decoding, pools, fields and rotation handling are unchanged; with "hr" the circuit
is the correlator's, bit for bit.

Causality: every stage is a causal filter; the readout step is a block sum over the
last ``1/readout_rate_hz`` s. Outputs are stamped ``latency_s`` earlier (photoreceptor
τ + EMD τ + half a block, and τ_EMD more for the per-pair decoding's low-pass), the same convention as the pinhole EMD front end: an estimate
stamped t is available at t + latency.

Shapes: luminance (T, n), gyro (T, 3); outputs per readout step (K, F). torch on CPU;
Python loops run over time only (inside the photoreceptor and EMD stages).

The package, one module per concept: :mod:`lobula.eye_circuit.config` (:class:`EyeCircuitConfig`,
:class:`EyeFieldConfig`), :mod:`lobula.eye_circuit.fields` (the LC fields on the eyes),
:mod:`lobula.eye_circuit.circuit` (:class:`EyeCircuit`, the streaming circuit),
:mod:`lobula.eye_circuit.scene_gain` (:func:`natural_scene_gain`) and
:mod:`lobula.eye_circuit.reliability` (:func:`field_reliability`); every public name is
importable from ``lobula.eye_circuit`` itself.
"""
from __future__ import annotations

from .circuit import EyeCircuit
from .config import EyeCircuitConfig, EyeFieldConfig
from .fields import EyeFields, eye_fields
from .reliability import field_reliability
from .scene_gain import natural_scene_gain

__all__ = ["EyeFieldConfig", "EyeCircuitConfig", "EyeFields", "EyeCircuit", "eye_fields", "field_reliability",
           "natural_scene_gain"]
