"""Velocity from eye footage: photoreceptors → EMDs → LC fields → the project's readout, causal.

``estimate_eye_velocity(eye_footage, config)`` streams the luminance of an eye-footage
folder (``lobula scene OUT --eye fly``) through :class:`lobula.eye_circuit.EyeCircuit`
with the gyroscope as haltere input, takes forward acceleration from the accelerometer
(:func:`lobula.imu.forward_acceleration`, causal: running gravity and bias), and reads
velocity out with :func:`lobula.readout.readout` (the estimator's readout, causal filter).
The LC fields' convective-corrected r²-term (see :mod:`lobula.eye_circuit`) is passed as
the readout's r²̄, so ṙ − r²̄ is the material-derivative form of a/d on any surface.

Returns the DESIGN.md velocity Dataset (dims ``time`` and ``field``).
"""
from __future__ import annotations

import json
import time as _time
from dataclasses import dataclass, field, replace

import numpy as np
import xarray as xr

from lobula.eye_circuit import EyeCircuit, EyeCircuitConfig, field_reliability
from lobula.gaze import retinal_rotation
from lobula.imu import (GRAVITY_WINDOW_S, forward_acceleration, gravity_drift_std, gravity_time_constant,
                            resample_to, turn_rate)
from lobula.photoreceptor import mean_removal
from lobula.readout import ReadoutConfig, answered_velocity
from lobula.readout_neuron import SPIKE_MODELS, ReadoutNeuronConfig, readout_neuron, spiking_output
from lobula.velocity.pipeline import vision_variables

from .eye_readout import (field_halves, readout_offset, reliability_gate, split_half_variance,  # noqa: F401
                          suppressed_readout)
from .store import provenance

__all__ = ["EyeVelocityConfig", "estimate_eye_velocity", "causal_gyro", "readout_inputs", "split_half_variance",
           "suppressed_readout",
           "readout_offset", "reliability_gate",
           "field_halves",
           "add_parser", "run_eye_velocity"]


#: m/s: the eye's speed prior (1σ): Drosophila cruises at 0.1-1 m/s, where a camera's readout allows for cars
#: and drones (lobula.readout.ReadoutConfig.v_prior_m_s)
FLY_SPEED_PRIOR_M_S = 1.0

#: the long name of the eye's v_std (as the camera's: lobula.velocity.pipeline)
STD_NAME = ("std of v_hat: the posterior's where vision answers, beyond grown by the accelerometer offset's prior std "
            "times the time from the nearest frame where it answered (online: the last)")


@dataclass
class EyeVelocityConfig:
    """The eye velocity pipeline: circuit, readout (causal by default), streaming chunk (samples).

    Parameters
    ----------
    circuit : EyeCircuitConfig
        The compound eye's circuit (:mod:`lobula.eye_circuit`).
    readout : ReadoutConfig
        The estimator's readout, causal, with the noise the eye's κ = a/v carries:
        :meth:`ReadoutConfig.emd` (kappa_rel_error 0.5, shared_error_frac 0.8), min_valid_fraction
        0.1 (8 of the 80 fields, so that a few reliable fields suffice), online_window_sigma 2.5,
        reversal off, sign on, the speed prior a fly's (:data:`FLY_SPEED_PRIOR_M_S`). Why each:

        * κ's errors. The eye's κ errs more and for longer than DIS flow's (dev worlds, seeds
          100–103, gated fields, κ against lp(a)/lp(v) of truth where |v| > 0.1 m/s: rms relative
          error 0.24–0.32 on panels and corridors, 0.46–1.75 under rotation), mostly shared by the
          fields and slow: each field's EMD gain γ(t) changes as texture flows through it (ρ̂ = γρ,
          so ρ̂'s ṙ/r carries γ̇/γ). Exact fields times the slow part (1 Hz) of the measured γ(t)
          err by 0.042–0.052 m/s², most of the EMD fields' 0.053–0.068 (panels); a constant gain
          per field errs by only 0.001–0.005. A slow shared error taken as white noise locks a
          wrong accelerometer offset in. Mean RMSE panels / rotation / corridor (dev seeds 100–103,
          causal, accelerometer): 0.0499 / 0.2176 / 0.0420 m/s at 0.5 / 0.8, 0.0561 / 0.2328 /
          0.0537 at the camera's 0.25 / 0.5 (0.3 / 0.8: 0.053 / 0.218 / 0.056; 0.7 / 0.8: 0.050 /
          0.218 / 0.040; 0.5 / 1.0: 0.048 / 0.209 / 0.040 — a broad optimum, not a knife edge).
        * The 2.5σ online window. The camera's 1.5σ is no clear gain on development eye worlds
          (seeds 100–102, 10 s, Δφ = 5°: rates panels / rotation / corridor 0.057 / 0.252 / 0.044
          m/s at 2.5σ, 0.051 / 0.246 / 0.041 at 1.5σ) and the coarse 6 s test scene
          (`tests/test_compound_eye.py`) reads 0.269 m/s at 1.5σ against 0.142 (zero estimator
          0.319); 3.5σ and 4.5σ are worse everywhere.
        * No reversals (``ReadoutConfig.reversal``): the EMD's r̄ is stamped only to within its
          group delay, and on the same worlds they are no clear gain (rates 0.056 / 0.254 / 0.048
          m/s with them, 0.057 / 0.253 / 0.044 without).
        * The expansion's sign (``ReadoutConfig.sign``): the fields' gains drift fastest under
          rotation, κ then cannot pin the accelerometer's offset, and without the sign the filter
          carries v̂ through zero, confidently, against what every field shows (development mixed
          world 100: v̂ +0.8 m/s where the truth is −0.4, ±2σ 43 %). On development worlds (rates,
          causal; rotation 100–109, panels, corridor and mixed 100–101) the mean RMSE is 0.098 m/s
          with it against 0.127 without, ±2σ 92 against 89 %, observable 81 against 85 %; panels
          and corridor within 0.001.
    chunk : int
        Eye samples per streaming chunk.
    accel_from_truth : bool
        Take the forward acceleration from truth.csv's a_forward_m_s2 instead of the accelerometer
        (isolates the visual circuit from gravity removal; labelled in the output).
    readout_kind : {"kalman", "spikes", "neuron"}
        "kalman": :func:`lobula.readout.readout`, the arithmetic readout, causal filter, v_std its
        posterior std. "spikes": the same readout's v̂ carried by ``neuron.population`` push–pull
        spiking output neuron pairs and decoded causally
        (:func:`lobula.readout_neuron.spiking_output`); v_std combines the posterior std and the
        decoding's count noise. "neuron": :func:`lobula.readout_neuron.readout_neuron` (shunting
        division, haltere integration, push–pull output neurons; spikes decoded causally when
        ``neuron.spiking``); v_std is then the spike decoding's count noise only, and
        ``observable`` the neuron's confidence.
    neuron : ReadoutNeuronConfig
        The output neurons (and the "neuron" readout): 10 pairs of leaky integrate-and-fire
        neurons with 1 mV membrane noise (``spike_model="lif"``), as a driven fly neuron fires
        nearly regularly (H1: de Ruyter van Steveninck et al. 1997), driven by v̂ phase-advanced
        by the decoder's own filter (``lead="encoder"``), so the decoder needs no accelerometer
        and its lag is made up exactly, lock-on included. Poisson trains (``--spike-model
        poisson``) make the output's count noise most of the spiking error: on dev eye worlds
        (seeds 100–103) LIF with the encoder lead reads panels 0.036 and corridor 0.016 m/s,
        Poisson with the haltere lead 0.045 / 0.041, the rates 0.035 / 0.015. A stored
        configuration without ``spike_model`` and ``lead`` reads as Poisson with the haltere lead.
    settle_s : float or None
        s: LC output the readout ignores at the start while the circuit's filters leave their
        resting state (None: :meth:`settle_time`'s default, 0.09 s for the default circuit).
    uncertainty : {"halves", "posterior"}
        What ``v_std`` states for the "kalman" and "spikes" readouts. "posterior": the readout's
        posterior std alone. "halves" (default): that std combined with (1) the disagreement of
        the two eyes, each read out alone, and of the upper and lower halves of the fields
        (:func:`field_halves`, :func:`split_half_variance`, causal running mean over
        ``split_tau_s``), which sees the errors the halves do not share — a turn's haltere residue
        is opposite on the two sides (yaw, roll) or above and below (pitch) — and (2)
        ``emd_gain_error``·|v̂|, the error every field shares. Together they cover the truth within
        ±2σ on 100 % of the steps after 2 s on the dev panels and corridor worlds (seeds 100–105;
        the posterior alone 91–100 %), 61–84 % on the rotating ones.
    split_tau_s : float
        s: time constant of that running mean. 1 s: the readout's 1 Hz low-pass makes errors that
        persist about that long.
    emd_gain_error : float
        Fraction of |v̂|: the EMD's response is not proportional to image speed but grows as ρ^β
        (a correlator's velocity tuning: Egelhaaf & Reichardt 1987; Borst & Egelhaaf 1989), and
        the readout's (ρ̇ − r²)/ρ of a power law is β·a/v, so v̂ is off by a factor ~1/β that no
        spread across fields can show. With the surround (:mod:`lobula.eye_circuit`) β, the
        log–log slope of each field's ρ̂ against the exact v/D after 2 s, has medians 1.03–1.10
        and lower quartiles 0.95–1.04 (panels and corridor, seeds 100, 103), hence 0.05 ≈ 1 − β
        at the lowest lower quartile.
    lead_offset_tau_s : float
        s: with ``neuron.lead="haltere"``, the spiking decoder's lead τ_d·a uses the accelerometer
        less the offset the readout's v̂ implies (:func:`readout_offset`, running mean over this
        time constant); 0: the raw accelerometer. Where the start's offset is large (panels seed
        7, 0.6 m/s²) spikes read 0.098 m/s with it against 0.134 without (rates 0.093); elsewhere
        within ±0.02.
    rest_bound : bool
        Whether the readout may take "no detectable expansion" as a bound on the speed
        (:func:`lobula.readout.rest_measurement`, |v| ≤ D·(|r̄| + 2·SE)). The fly's EMDs at Δφ = 5°
        decode γ·v/D with γ = 0.28–0.37 in a corridor at every speed (dev seed 100, pooled over the
        fields against the exact v/D) and 0.9–1.0 on panels, so a depth given in metres
        (``readout.rest_depth_max_m``) bounds |v| by D/γ and calls slow flight rest (on dev seeds
        100–103, causal, a 5 m depth: corridor RMSE 0.111 m/s against 0.054 without the bound). The
        depth the readout learns, a/(ṙ̄ − r²̄), carries the same 1/γ, so the bound on it holds at any
        gain. False (default): the bound only where the image is frozen (depth bound 10⁶ m);
        elsewhere at rest v̂ rests on the accelerometer and the readout says when it cannot tell (NaN).
        True: the bound as for the camera.
    reliability_min : float
        A field's output reaches the readout only at steps where its causal slow-to-fast power
        ratio (:func:`lobula.eye_circuit.field_reliability`, running means over
        ``reliability_tau_s``) is at least this (0: every field always), provided at least
        ``min_valid_fraction`` of the fields pass (else every field, :func:`reliability_gate`).
        Under rotation the fields that see nothing near (sky, a distant backdrop) carry little
        expansion and much correlator noise and rotation residue, which the readout's median
        would take as measurements of a/v (development rotation world, seed 100: fields looking
        down at the floor follow the exact v/D at correlation 0.97–0.98, fields looking up at
        −0.24–0.3). 10: chosen on development seeds 100–103 (mean causal RMSE over 11 dev worlds
        0.136 m/s at 10, 0.143 at 5, 0.169 without the gate).
    reliability_tau_s : float
        s: time constant of the running powers in :func:`lobula.eye_circuit.field_reliability`.
    """

    circuit: EyeCircuitConfig = field(default_factory=EyeCircuitConfig)
    readout: ReadoutConfig = field(default_factory=lambda: ReadoutConfig.emd(filter="causal", min_valid_fraction=0.1,
                                                                            online_window_sigma=2.5, reversal=False,
                                                                            sign=True, v_prior_m_s=FLY_SPEED_PRIOR_M_S))
    chunk: int = 500
    accel_from_truth: bool = False
    readout_kind: str = "kalman"
    neuron: ReadoutNeuronConfig = field(default_factory=lambda: ReadoutNeuronConfig(spiking=True, population=10,
                                                                                 spike_model="lif", lead="encoder"))
    settle_s: float | None = None
    uncertainty: str = "halves"
    split_tau_s: float = 1.0
    emd_gain_error: float = 0.05
    lead_offset_tau_s: float = 1.0
    rest_bound: bool = False
    reliability_min: float = 10.0
    reliability_tau_s: float = 2.0

    def __post_init__(self):
        if self.uncertainty not in ("halves", "posterior"):
            raise ValueError(f"uncertainty must be 'halves' or 'posterior', got {self.uncertainty!r}")
        if not (self.reliability_min >= 0 and self.reliability_tau_s > 0):
            raise ValueError(f"reliability_min must be >= 0 and reliability_tau_s > 0, got {self.reliability_min}, "
                             f"{self.reliability_tau_s}")
        if not self.lead_offset_tau_s >= 0:
            raise ValueError(f"lead_offset_tau_s must be >= 0 seconds, got {self.lead_offset_tau_s}")
        if not self.split_tau_s > 0 or not self.emd_gain_error >= 0:
            raise ValueError(f"split_tau_s must be > 0 and emd_gain_error >= 0, got {self.split_tau_s}, "
                             f"{self.emd_gain_error}")
        if self.readout_kind not in ("kalman", "spikes", "neuron"):
            raise ValueError(f"readout_kind must be 'kalman', 'spikes' or 'neuron', got {self.readout_kind!r}")
        if self.settle_s is not None and not self.settle_s >= 0:
            raise ValueError(f"settle_s must be >= 0 seconds or None, got {self.settle_s}")

    def settle_time(self, circuit: EyeCircuitConfig | None = None) -> float:
        """Seconds of LC output the readout ignores at the start (``settle_s``; None: twice the sum of the
        photoreceptor low-pass, EMD delay and photoreceptor high-pass time constants, the circuit's
        filters from rest to within e⁻² of their moving level)."""
        if self.settle_s is not None:
            return float(self.settle_s)
        c = circuit or self.circuit
        return 2.0 * (c.photoreceptor.tau_s + c.emd.tau_s + (c.photoreceptor.tau_hp_s or 0.0))

    def to_dict(self) -> dict:
        return dict(circuit=self.circuit.to_dict(), readout=self.readout.to_dict(), chunk=self.chunk,
                    accel_from_truth=self.accel_from_truth, readout_kind=self.readout_kind,
                    neuron=self.neuron.to_dict(), settle_s=self.settle_time(), uncertainty=self.uncertainty,
                    split_tau_s=self.split_tau_s, emd_gain_error=self.emd_gain_error,
                    lead_offset_tau_s=self.lead_offset_tau_s, rest_bound=self.rest_bound,
                    reliability_min=self.reliability_min, reliability_tau_s=self.reliability_tau_s)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)


def causal_gyro(imu, times: np.ndarray, saccade_deg_s: float | None = None, hold_s: float = 0.0) -> np.ndarray:
    """Angular velocity (T, 3) rad/s at ``times`` (T,) s: the latest IMU sample at or before each time (no
    look-ahead), minus the running mean of the samples so far (the gyro bias, since a
    track's heading returns; lobula.imu does the same).

    saccade_deg_s: samples whose |ω| exceeds this (°/s), and those within ``hold_s`` s after one, are left
    out of that mean (None: none are). A fly's heading also returns, but in body saccades: the mean over
    the samples so far is then the net angle turned over the time, 45° over the first 0.34 s ≈ 130 °/s after a
    first saccade (saccadic flight seed 0), against a bias of tenths of a °/s; between saccades the rate is
    intersaccadic drift and wobble, which average out. Before the first sample outside a saccade the bias
    is 0 (its expected value).
    """
    g = imu.gyro
    if saccade_deg_s is None:
        bias = np.cumsum(g, 0) / np.arange(1, len(g) + 1)[:, None]
    else:
        ti = np.asarray(imu.time_s, float)
        fast = np.linalg.norm(g, axis=1) > np.radians(saccade_deg_s)
        last = np.maximum.accumulate(np.where(fast, ti, -np.inf))
        calm = (ti - last) > hold_s
        n = np.cumsum(calm)
        bias = np.cumsum(g * calm[:, None], 0) / np.maximum(n, 1)[:, None]
    k = np.clip(np.searchsorted(imu.time_s, times, side="right") - 1, 0, len(g) - 1)
    return (g - bias)[k]


def readout_inputs(fo, t: np.ndarray, cfg: EyeVelocityConfig):
    """What the readout's filter must know about the acceleration it is given, as for the camera.

    The same terms :func:`lobula.velocity.estimate_velocity` gives the readout (the
    accelerometer is the same, so its errors are): online, the gravity reference is set over
    the first seconds and holds the platform's acceleration there, an offset of up to
    ``START_ACCEL_PRIOR_M_S2`` (measured on a panels world: −0.44 m/s², four times the
    readout's default offset prior, which then cannot absorb it), and it keeps learning
    with time constant τ(t) (:func:`lobula.imu.gravity_time_constant`), so the offset
    moves as ḃ = −a/τ; gravity seen through a gyro-integrated attitude ramps at up to
    |g|·σ_b (:func:`lobula.imu.gravity_drift_std`). Offline, gravity is a windowed
    mean that holds Δv/T. Acceleration from truth has no offset to learn. Unlike the camera's
    pipeline, the gravity reference's error is held here as one forward offset, not as a vector
    whose forward share turns with the body (lobula.readout.kalman_velocity's offset_axis), and the
    transport term is left out (the eye's heading is taken along its body axis, where λ = 0): the
    eye's worlds turn by a few degrees. On a development rotation world (seed 100, rates) the camera's
    vector offset (prior 1 m/s² per axis) reads 0.263 m/s against 0.257 as one offset, panels 0.038
    either way; with the attitude's leak walk as well, the same. Nor is the gyro bias behind the gravity
    this attitude lets in the eye's error under rotation: given the camera's flow-fitted bias track,
    rotation seeds 100 / 101 read 0.247 / 0.213 against 0.257 / 0.197.
    Returns (ReadoutConfig, gravity_tau (n,) or None, drift_std (n,) or None).
    """
    from lobula.velocity.inertial import START_ACCEL_PRIOR_M_S2, TRUTH_ACCEL_OFFSET_M_S2

    rcfg = cfg.readout
    if not cfg.rest_bound:
        # The EMDs cannot tell slow flight from rest (see EyeVelocityConfig.rest_bound): a depth bound of
        # 10⁶ m leaves the rest bound only where no field sees any motion at all (a frozen image).
        rcfg = replace(rcfg, rest_depth_max_m=1e6)
    if cfg.accel_from_truth:
        return replace(rcfg, bias_prior_m_s2=min(rcfg.bias_prior_m_s2, TRUTH_ACCEL_OFFSET_M_S2)), None, None
    causal = rcfg.filter == "causal"
    imu_t = fo.imu.time_s
    if causal:
        rcfg = replace(rcfg, bias_prior_m_s2=float(np.hypot(rcfg.bias_prior_m_s2, START_ACCEL_PRIOR_M_S2)))
        tau = gravity_time_constant(t, float(imu_t[0]))
    else:
        span = min(GRAVITY_WINDOW_S, float(imu_t[-1] - imu_t[0]))
        rcfg = replace(rcfg, bias_prior_m_s2=float(np.hypot(rcfg.bias_prior_m_s2, rcfg.v_prior_m_s / max(span, 1.0))))
        tau = None
    drift = np.interp(t, imu_t, gravity_drift_std(imu_t, fo.imu.gyro, causal=causal))
    return rcfg, tau, drift


def _eye_readout(cfg, rcfg, fields, t, rho_in, r2_in, a, tau, drift, turn, n_outputs: int,
                 saccade: np.ndarray | None = None) -> tuple:
    """The readout of the gated LC outputs: (v_hat, observable, r_dot, v_field, v_std, std_name, method, filter,
    info), info the readout's verdicts on vision (:func:`lobula.readout.readout`'s; {} for the readout neuron);
    ``saccade`` (n,) bool: the steps whose visual update is suppressed (their rho_in, r2_in are NaN)."""
    if cfg.readout_kind == "neuron":
        nout = readout_neuron(t, rho_in, r2_in, a, cfg.neuron)
        v_hat, observable, r_dot, v_field = nout["v_hat"], nout["observable"], nout["r_dot"], nout["v_field"]
        v_std = nout["decode_std"]
        std_name = (f"std of the readout neuron's spike decoding ({SPIKE_MODELS[cfg.neuron.spike_model]} count noise only; "
                    "not the model error)"
                    if cfg.neuron.spiking else "0: the rate readout neuron has no decoding noise (not the model error)")
        method = "readout neuron (" + (f"{SPIKE_MODELS[cfg.neuron.spike_model]} spikes, causal decoding"
                                       if cfg.neuron.spiking else "rate") + ")"
        filt = "causal" if not cfg.neuron.spiking or cfg.neuron.decode == "causal" else "centred spike window"
        info = {}
    else:
        res = suppressed_readout(t, rho_in, r2_in, a, rcfg, saccade, gravity_tau=tau, drift_std=drift, turn_rate=turn)
        v_hat, observable, r_dot, v_field, v_std = res.v_hat, res.observable, res.r_dot, res.v_field, res.v_std
        info = res.info
        # The halves, the offset and the spikes take v̂ where vision answers only (answered_velocity), not where
        # it is carried.
        std_name, method, filt = STD_NAME, cfg.readout.method, cfg.readout.filter
        if cfg.uncertainty == "halves":
            extra = (cfg.emd_gain_error * np.nan_to_num(res.v_hat)) ** 2
            for a_half, b_half in field_halves(fields, n_outputs):
                # Each half through the same readout alone: their disagreement is an error the posterior misses.
                halves = [answered_velocity(suppressed_readout(t, rho_in[:, h], r2_in[:, h], a, rcfg, saccade,
                                                               gravity_tau=tau, drift_std=drift, turn_rate=turn))
                          for h in (a_half, b_half)]
                extra = extra + np.nan_to_num(split_half_variance(t, *halves, cfg.split_tau_s))
            v_std = np.sqrt(v_std ** 2 + extra)
            std_name = (f"{STD_NAME}, combined with the disagreement of the field halves (left and right "
                        f"eye, upper and lower) and the EMD gain error ({cfg.emd_gain_error:g}·|v_hat|)")
        if cfg.readout_kind == "spikes":
            if cfg.readout.filter != "causal":
                raise ValueError("spiking output neurons decode causally; use the causal readout filter")
            # The decoder's lead τ_d·a takes the accelerometer less the offset the readout has found
            # (its v̂ moves by a − b̂): the raw accelerometer's offset, up to 0.6 m/s² at the start of
            # a dev world, would shift every decoded step by τ_d·b.
            v_ans = answered_velocity(res)
            a_lead = a - readout_offset(t, v_ans, a, cfg.lead_offset_tau_s) if cfg.lead_offset_tau_s else a
            enc = spiking_output(t, v_ans, a_lead, replace(cfg.neuron, spiking=True))
            v_hat = np.where(observable, enc["v_dec"], np.nan)
            v_std = np.sqrt(v_std ** 2 + enc["decode_std"] ** 2)
            std_name = std_name.replace("std of v_hat", "std of the readout's v_hat", 1) + \
                f" and the {SPIKE_MODELS[cfg.neuron.spike_model]} count noise of the spike decoding"
            method = (f"{cfg.readout.method}, carried by {cfg.neuron.population} push-pull "
                      f"{SPIKE_MODELS[cfg.neuron.spike_model]} output neuron pairs "
                      f"({cfg.neuron.gain_hz_per_m_s:g} Hz per m/s), causal decoding, {cfg.neuron.lead} lead")
    return v_hat, observable, r_dot, v_field, v_std, std_name, method, filt, info


def _eye_dataset(fo, cfg, rcfg, f, t, rho, r2, haltere_gain, reliability, used, a, a_source, v_hat, observable,
                 r_dot, v_field, v_std, std_name) -> xr.Dataset:
    """The velocity Dataset (dims time, field) of the readout's outputs and the LC fields' (no attributes)."""
    if cfg.readout_kind == "neuron":
        obs_definition = "the readout neuron's own confidence"
    else:
        # What v_std adds beyond the posterior does not gate: gating on it leaves the eye blind, so the
        # file says which std the flag is of.
        obs_definition = (f"the readout's std of v̂ (its posterior's, grown beyond the frames vision answers) ≤ "
                          f"max({rcfg.max_std_m_s:g} m/s, {rcfg.max_rel_std:g}·|v̂|) and "
                          f"vision coupled to the accelerometer (lobula.readout.coupling)") + (
            "; v_std adds the field halves' disagreement and the EMD gain error, so it may exceed that"
            if cfg.uncertainty == "halves" else "")
    keep = np.flatnonzero(f.eye == 0) if rho.shape[1] != f.n_fields else np.arange(f.n_fields)
    data = dict(
        v_hat=("time", v_hat, {"units": "m/s", "long_name": "estimated forward velocity"}),
        observable=("time", observable, {"units": "1", "long_name": "velocity observable",
                                          "definition": obs_definition}),
        v_std=("time", v_std, {"units": "m/s", "long_name": std_name}),
        accel=("time", a, {"units": "m/s2", "long_name": "forward acceleration", "source": a_source}),
        r=(("time", "field"), rho, {"units": "1/s", "long_name": "LC field expansion rate v/D"}),
        r2=(("time", "field"), r2, {"units": "1/s2",
                                    "long_name": "r-squared term with the convective correction (r2_eff)"}),
        r_dot=(("time", "field"), r_dot, {"units": "1/s2", "long_name": "time derivative of the field rate r"}),
        haltere_gain=(("time", "field"), haltere_gain, {"units": "1", "long_name": "gain at which the field subtracts "
                      "the haltere's predicted turn (1 + the learned α; 1: fixed; NaN: no haltere subtraction)"}),
        reliability=(("time", "field"), reliability, {"units": "1", "long_name": "field's causal slow-to-fast power "
                     "ratio (lobula.eye_circuit.field_reliability)"}),
        field_used=(("time", "field"), used, {"units": "1", "long_name": "field output passed to the readout "
                                                             f"(reliability >= {cfg.reliability_min:g})"}),
        v_field=(("time", "field"), v_field, {"units": "m/s", "long_name": "per-field forward velocity "
                                                                   "a·r/(r_dot − r2)"}),
    )
    if fo.truth is not None:
        data["v_true"] = ("time", np.interp(t, fo.truth["time_s"], fo.truth["v_forward_m_s"]),
                          {"units": "m/s", "long_name": "ground-truth forward velocity"})
    coords = dict(time=("time", t, {"units": "s", "long_name": "time of the LC step on the footage clock"}),
                  azimuth_deg=("field", f.centres_deg[keep, 0],
                               {"units": "degree", "long_name": "LC field centre azimuth"}),
                  elevation_deg=("field", f.centres_deg[keep, 1],
                                 {"units": "degree", "long_name": "LC field centre elevation (positive down)"}),
                  size_deg=("field", np.full(len(keep), f.size_deg),
                            {"units": "degree", "long_name": "LC field size (Gaussian FWHM, or box side)"}),
                  eye=("field", np.where(f.eye[keep] == 0, "right" if len(keep) == f.n_fields else "both", "left"),
                       {"long_name": "eye of the field (both: the mirror sum of a right-eye field and its left-eye twin)"}))
    return xr.Dataset(data, coords=coords)


def estimate_eye_velocity(fo, config: EyeVelocityConfig | None = None, progress: bool = False) -> xr.Dataset:
    """Velocity Dataset from an :class:`stimuli.eye.EyeFootage` (see the module docstring)."""
    from tqdm.auto import tqdm

    from lobula._optional import require_torch
    from lobula.readers.core import FootageError

    require_torch("the compound eye's circuit")
    cfg = config or EyeVelocityConfig()
    if fo.imu is None:
        raise FootageError(f"{fo.path / 'imu.csv'}: missing; the eye's readout needs the accelerometer and gyro")
    t_start = _time.perf_counter()
    circ = EyeCircuit(fo.eye, fo.rate_hz, cfg.circuit)
    gyro = causal_gyro(fo.imu, fo.times, cfg.circuit.saccade_gate_deg_s, cfg.circuit.saccade_hold_s())
    if getattr(fo, "head", None) is not None:
        # Gaze stabilised: the retina turns with the head; the haltere's prediction adds the neck's
        # own rotation (an efference copy: the head angles) to the body's, in the head's frame.
        gyro = retinal_rotation(fo.times, gyro, fo.head)
    outs = []
    pos = 0
    with tqdm(total=len(fo.times), desc="eye circuit", unit="sample", disable=not progress, leave=False,
              mininterval=2) as bar:
        for ts, lum in fo.chunks(cfg.chunk):
            outs.append(circ.process(lum, gyro[pos:pos + len(ts)]))
            pos += len(ts)
            bar.update(len(ts))
    outs.append(circ.finish())
    t = np.concatenate([o["t"] for o in outs]) + float(fo.times[0])   # the circuit counts from sample 0
    rho = np.concatenate([o["rho"] for o in outs])
    r2 = np.concatenate([o["r2_eff"] for o in outs])
    haltere_gain = np.concatenate([o["haltere_gain"] for o in outs])
    saccade = np.concatenate([o["saccade"] for o in outs])
    # The circuit starts at rest (the EMD delay lines and the photoreceptors' filters set to
    # the first sample, as if nothing had moved), so the LC outputs climb to their moving level
    # over the first few time constants: a ṙ that is the circuit's, not the world's (measured on
    # a dev panels world: a κ·v of +1.5 m/s² against a true −0.7 at the start, which the readout
    # took as the accelerometer's offset for the rest of the run). The readout ignores them.
    cold = (t - t[0]) < cfg.settle_time(circ.config)
    rho[cold], r2[cold] = np.nan, np.nan
    if len(t) < 3:
        raise FootageError(f"{fo.path}: too short for a readout ({len(t)} LC steps)")
    # Each field reaches the readout only while its output is mostly slow (the flight's expansion),
    # not the correlators' fast noise and rotation residue (EyeVelocityConfig.reliability_min); causal.
    # Saccadic suppression: the steps the haltere's gate flags (a body saccade and the circuit's hold after it)
    # reach neither the fields' reliability nor the readout, whose filter then carries v̂ on the acceleration
    # alone (see suppressed_readout).
    rho_vis = np.where(saccade[:, None], np.nan, rho)
    reliability = field_reliability(t, rho_vis, tau_s=cfg.reliability_tau_s)
    used = reliability_gate(reliability, np.isfinite(rho_vis), cfg.reliability_min,
                            max(3, int(np.ceil(cfg.readout.min_valid_fraction * rho.shape[1]))))
    rho_in, r2_in = np.where(used, rho_vis, np.nan), np.where(used, r2, np.nan)
    t_circ = _time.perf_counter() - t_start
    dt = float(np.median(np.diff(t)))
    if cfg.accel_from_truth:
        if fo.truth is None or "a_forward_m_s2" not in fo.truth:
            raise FootageError(f"{fo.path / 'truth.csv'}: no a_forward_m_s2 column for accel_from_truth")
        a = np.interp(t, fo.truth["time_s"], fo.truth["a_forward_m_s2"])
        a_source = "ground truth (a_forward_m_s2 of truth.csv; no accelerometer)"
        turn = None
    else:
        a_imu = forward_acceleration(fo.imu.time_s, fo.imu.accel, fo.imu.gyro, causal=cfg.readout.filter == "causal")
        a = resample_to(t, fo.imu.time_s, a_imu, dt)
        a_source = "accelerometer (causal gravity and bias removal)"
        turn = turn_rate(t, fo.imu.time_s, fo.imu.gyro, dt)  # told to the readout, as the camera's is
    rcfg, tau, drift = readout_inputs(fo, t, cfg)
    t1 = _time.perf_counter()
    (v_hat, observable, r_dot, v_field, v_std, std_name, method,
     filt, info) = _eye_readout(cfg, rcfg, circ.fields, t, rho_in, r2_in, a, tau, drift, turn, rho.shape[1], saccade)
    t_readout = _time.perf_counter() - t1
    ds = _eye_dataset(fo, cfg, rcfg, circ.fields, t, rho, r2, haltere_gain, reliability, used, a, a_source,
                      v_hat, observable, r_dot, v_field, v_std, std_name)
    ds = ds.assign(vision_variables(info))
    gate = cfg.circuit.saccade_gate_deg_s
    ds["saccade"] = ("time", saccade, {"units": "1", "long_name": "saccadic suppression, no visual update: " + (
        f"the haltere's rate above {gate:g} deg/s or within {cfg.circuit.saccade_hold_s():.3g} s after"
        if gate is not None else "none (no saccade gate)")})
    timings = dict(circ.timings, circuit_total=t_circ, readout=t_readout, n_ommatidia=fo.eye.n,
                   n_pairs=fo.eye.n_pairs)
    ds.attrs.update(provenance(cfg.to_json(), front_end="emd-compound-eye", filter=filt,
                               readout=method, rotation=cfg.circuit.rotation,
                               acceleration_source=a_source,
                               footage=str(fo.path), footage_kind="compound-eye",
                               eye=json.dumps(fo.eye.config.to_dict()), eye_rate_hz=fo.rate_hz,
                               latency_s=circ.latency_s,
                               timings_s=json.dumps({k: round(float(v), 4) for k, v in timings.items()}),
                               wall_s=round(_time.perf_counter() - t_start, 3)))
    return ds


def apply_eye_options(cfg: EyeVelocityConfig, args) -> EyeVelocityConfig:
    """The command-line options of `lobula eye-velocity` (None: unchanged)."""
    from dataclasses import replace
    c = cfg.circuit
    if getattr(args, "rotation", None):
        c.rotation = args.rotation
    gain = getattr(args, "haltere_gain", None)
    if gain is not None:
        if c.rotation not in ("haltere", "both"):
            raise ValueError(f"--haltere-gain sets the prior of the gain the haltere's prediction is subtracted at; "
                             f"--rotation {c.rotation} subtracts none (use --rotation haltere or both)")
        c.rotation_gain_prior = None if gain == "natural" else parse_gain(gain)
    if getattr(args, "mean_removal", None):
        c.surround, c.photoreceptor = mean_removal(args.mean_removal, c.photoreceptor)
    if getattr(args, "field_size", None):
        c.fields = replace(c.fields, size_deg=args.field_size)
    if getattr(args, "tau", None):
        c.emd = replace(c.emd, tau_s=args.tau)
    if getattr(args, "filter", None):
        cfg.readout.filter = args.filter
    if getattr(args, "accel_from_truth", False):
        cfg.accel_from_truth = True
    if getattr(args, "uncertainty", None):
        cfg.uncertainty = args.uncertainty
    ro = getattr(args, "readout", None)
    if ro:
        cfg.readout_kind = {"neuron-rate": "neuron"}.get(ro, ro)
        cfg.neuron = replace(cfg.neuron, spiking=ro != "neuron-rate", seed=int(getattr(args, "seed", None) or 0))
    spiking = cfg.readout_kind == "spikes" or (cfg.readout_kind == "neuron" and cfg.neuron.spiking)
    for opt, name in (("seed", "--seed seeds"), ("spike_model", "--spike-model sets"),
                      ("membrane_noise", "--membrane-noise sets")):
        if not spiking and getattr(args, opt, None) is not None:
            raise ValueError(f"{name} output spikes; --readout {ro or 'kalman'} has none (use --readout spikes or neuron)")
    if getattr(args, "spike_model", None):
        cfg.neuron = replace(cfg.neuron, spike_model=args.spike_model)
    if getattr(args, "membrane_noise", None) is not None:
        if cfg.neuron.spike_model != "lif":
            raise ValueError("--membrane-noise is the LIF output neurons' noise; --spike-model poisson has none")
        cfg.neuron = replace(cfg.neuron, membrane_noise_mv=args.membrane_noise)  # validated there
    if getattr(args, "accel_scale_error", None) is not None:
        if cfg.readout_kind == "neuron":
            raise ValueError(f"--accel-scale-error widens the kalman readout's posterior std; --readout {ro} "
                             f"reports the spike decoding's noise only: drop one of them")
        cfg.readout = replace(cfg.readout, accel_scale_error=args.accel_scale_error)  # validated there
    if cfg.readout_kind != "kalman" and getattr(args, "filter", None) == "zero-phase":
        raise ValueError(f"--readout {ro} is causal; --filter zero-phase applies to --readout kalman")
    return cfg


def parse_gain(text: str) -> float:
    """A ``--haltere-gain`` value: a number in (0, 1.5] (or "natural", handled by the caller)."""
    try:
        g = float(text)
    except ValueError:
        raise ValueError(f"--haltere-gain takes 'natural' or a number in (0, 1.5], got {text!r}") from None
    if not 0.0 < g <= 1.5:
        raise ValueError(f"--haltere-gain must lie in (0, 1.5] (1: the unit gain), got {g}")
    return g


def run_eye_velocity(args) -> int:
    from experiments.store import write_netcdf
    from experiments.velocity import never_observable_reason, plot_velocity, score
    from stimuli.eye import open_eye_footage

    fo = open_eye_footage(args.footage)
    cfg = apply_eye_options(EyeVelocityConfig(), args)
    ds = estimate_eye_velocity(fo, cfg, progress=not args.quiet)
    write_netcdf(ds, args.out)
    skip = min(args.skip, 0.25 * float(ds.time[-1] - ds.time[0]))
    sc = score(ds, skip)
    tm = json.loads(ds.attrs["timings_s"])
    print(f"wrote {args.out}: {ds.sizes['time']} LC steps x {ds.sizes['field']} fields "
          f"[{fo.eye.summary()}; rotation: {cfg.circuit.rotation}; {ds.attrs['readout']}, {ds.attrs['filter']}]")
    print(f"circuit {tm['circuit_total']:.1f} s for {len(fo) / fo.rate_hz:.1f} s of flight at {fo.rate_hz:.0f} Hz")
    if sc:
        print(f"after {skip:.3g} s: RMSE {sc['rmse_m_s']:.4f} m/s, median |error| {sc['median_abs_error_m_s']:.4f} m/s, "
              f"observable {sc['observable_fraction']:.3f} of {sc['n_frames']} steps")
    why = never_observable_reason(ds)
    if why:
        print(why)
    if args.plot:
        plot_velocity(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def add_parser(subparsers):
    """Register ``lobula eye-velocity`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_eye_velocity_parser`'s, built without importing this module."""
    from .parsers import add_eye_velocity_parser

    return add_eye_velocity_parser(subparsers)
