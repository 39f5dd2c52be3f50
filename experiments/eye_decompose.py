"""Where the fly eye loses velocity accuracy: the same readout fed ever less ideal LC inputs.

Levels (each a velocity Dataset's RMSE after ``skip_s``, with the acceleration from the
accelerometer, from truth, and from truth with an offset the readout must learn as it would an
accelerometer's (``|offset``), so the readout's own share shows too):

1. ``exact``  — each LC field's fit to the exact translational image motion of every pair,
   ρ_p·m_p with ρ_p = v/D_p (D_p the rendered range along the pair, ``range.npy``), all pairs
   weighted alike: the geometry and resolution of the eye (Δφ, field layout, the linear
   gradient fit, the material-derivative r²-term) with perfect motion detectors.
2. ``ideal``  — the same exact motion, but weighted as the circuit weights its pairs (each pair
   by its own contrast pool, from the rendered luminance): texture-dependent pooling, still a
   perfect, linear detector.
3. ``gain``   — the exact fields of level 1, each times its EMD field's slow gain γ_f(t) (a 1 Hz
   causal low-pass of the circuit's ρ_f over the exact ρ_f, clipped to [−3, 5]): what the
   correlators' gain drift alone costs. A constant gain per field costs nothing (κ = (ṙ − r²)/r
   is blind to it, up to the r²-term), but γ_f changes as texture flows through the field, and
   ṙ/r then carries γ̇/γ. Measured on the dev panels worlds (seeds 100–103): the κ error this
   level leaves (0.042–0.052 m/s² in a = κ·v) is most of the EMD fields' (0.053–0.068).
4. ``emd``    — the circuit itself (:class:`lobula.eye_circuit.EyeCircuit`, the configuration
   given): the correlators' velocity tuning and pattern noise, and the haltere's residue
   under rotation; the fields the pipeline gates by reliability (``field_used``) left out.

The exact motion uses the forward velocity of ``truth.csv`` only (the tracks translate along
the body axis; the lateral velocity a turn adds in the camera frame changed the exact level by
< 0.006 m/s on the dev worlds). Run: ``python -m experiments.eye_decompose EYE_FOOTAGE ...``.
"""
from __future__ import annotations

import json
import math
import sys
from dataclasses import replace

import numpy as np
import torch

from lobula.eye_circuit import EyeCircuit, EyeCircuitConfig
from lobula.haltere import forward_acceleration, resample_to, turn_rate
from lobula.photoreceptor import lowpass_scan, spatial_filter
from lobula.readout import readout

from .eye_velocity import EyeVelocityConfig, estimate_eye_velocity, readout_inputs

__all__ = ["exact_pair_motion", "IdealDetectorCircuit", "ideal_fields", "slow_gain_fields", "readout_rmse",
           "decompose"]


def exact_pair_motion(fo) -> np.ndarray:
    """True translational image motion along every pair's unit tangent (rad/s), (T, P) at the eye's samples.

    ḋ·u_p = −(v·u_p)/D for a translation v (camera frame) and range D; with v = v_fwd·ẑ this is
    −v_fwd·(ẑ·u_p)/D_p, D_p the pair's mean inverse range (linear in time between stored ranges)."""
    rt, R = fo.range_samples()
    if not len(rt) or fo.truth is None:
        raise ValueError(f"{fo.path}: needs range.npy and truth.csv for the exact image motion")
    inv = np.where(np.isfinite(R) & (R > 0), 1.0 / np.maximum(R, 1e-9), 0.0)
    inv_t = np.stack([np.interp(fo.times, rt, inv[:, i]) for i in range(inv.shape[1])], 1)
    e = fo.eye
    inv_p = 0.5 * (inv_t[:, e.pairs_a] + inv_t[:, e.pairs_b])
    v = np.interp(fo.times, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    return (-v[:, None] * e.pair_direction[None, :, 2] * inv_p).astype(np.float32)


class IdealDetectorCircuit(EyeCircuit):
    """The eye circuit with each EMD replaced by a perfect linear detector of the given motion.

    ``uniform``: every pair weighted alike (level 1); else each pair by its delayed contrast pool
    from the luminance (level 2). No rotation (the motion is translational)."""

    def __init__(self, eye, rate_hz, motion: np.ndarray, uniform: bool, config: EyeCircuitConfig | None = None):
        cfg = replace(config or EyeCircuitConfig(), rotation="none", rotation_gain="fixed", normaliser="delayed",
                      latency_s=None)
        super().__init__(eye, rate_hz, cfg)
        self.latency_s = 0.5 * self.block * self.dt    # exact motion has no detector latency
        self._motion, self._pos, self.uniform = motion, 0, uniform

    def _sums(self, lum, gyro, keep=None, with_rotation=False):
        n = lum.shape[-2]
        mot = torch.as_tensor(self._motion[self._pos:self._pos + n])
        self._pos += n
        if self.uniform:
            G = torch.ones_like(mot)
        else:
            # The pairs see what the EMDs see: the photoreceptors after the circuit's spatial filter (the surround).
            y = spatial_filter(self._pool, self.photoreceptors.run(lum))
            dy = y[..., self._b] - y[..., self._a]
            lp = lowpass_scan(dy, math.exp(-self.dt / self.config.emd.tau_s), self._lp_state)
            self._lp_state = lp[..., -1, :].clone()
            G = lp * dy
        F = self.fields.n_fields
        return torch.cat([(self._c * G * mot) @ self._num, (G @ self._den)[..., :3 * F]], -1)


def ideal_fields(fo, uniform: bool, config: EyeCircuitConfig | None = None, chunk: int = 500):
    """(t, ρ, r2_eff) of :class:`IdealDetectorCircuit` over an eye footage."""
    circ = IdealDetectorCircuit(fo.eye, fo.rate_hz, exact_pair_motion(fo), uniform, config)
    outs = [circ.process(lum, np.zeros((len(ts), 3))) for ts, lum in fo.chunks(chunk)] + [circ.finish()]
    t = np.concatenate([o["t"] for o in outs]) + float(fo.times[0])
    return t, np.concatenate([o["rho"] for o in outs]), np.concatenate([o["r2_eff"] for o in outs])


def slow_gain_fields(t_exact, rho_exact, grad_exact_r2, t, rho_emd, theta, cutoff_hz: float = 1.0):
    """Exact fields times each field's slow EMD gain: (ρ, r2_eff) at the EMD's times t (K,).

    t_exact (K',), rho_exact (K', F): the exact fields (:func:`ideal_fields`, uniform), r2 likewise
    (``grad_exact_r2``); rho_emd (K, F): the circuit's; theta (F,) rad: the fields' angles from the
    body axis. γ_f(t) = causal Gaussian low-pass (``cutoff_hz``, the readout's) of ρ_emd/ρ_exact,
    clipped to [−3, 5] (silent or near-zero steps read 1). r2_eff = γ²ρ²cos θ − γρ sin θ·γg, g the exact
    gradient recovered from the exact r2_eff."""
    from lobula.readout import gaussian_lowpass

    interp = lambda x: np.stack([np.interp(t, t_exact, x[:, f]) for f in range(x.shape[1])], 1)  # noqa: E731
    re, r2e = interp(rho_exact), interp(grad_exact_r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        g_exact = np.where(np.abs(re) > 1e-9, (re ** 2 * np.cos(theta) - r2e) / (re * np.sin(theta)), 0.0)
        ratio = np.clip(np.nan_to_num(rho_emd / re, nan=1.0, posinf=1.0, neginf=1.0), -3.0, 5.0)
    dt = float(np.median(np.diff(t)))
    gam = np.stack([gaussian_lowpass(ratio[:, f], cutoff_hz, dt, causal=True)[0] for f in range(ratio.shape[1])], 1)
    rho = gam * re
    return rho, rho ** 2 * np.cos(theta) - rho * np.sin(theta) * gam * g_exact


def readout_rmse(fo, t, rho, r2, accel_from_truth: bool, cfg: EyeVelocityConfig | None = None,
                 skip_s: float = 2.0, learn_offset: bool = False) -> tuple[float, float]:
    """The eye pipeline's readout (settle time, acceleration, readout inputs) on given fields: (RMSE, ±2σ coverage).

    learn_offset (with accel_from_truth): the true acceleration, but the readout not told so — it
    learns an accelerometer offset (prior std ``ReadoutConfig.bias_prior_m_s2``, 0.1 m/s²) that is
    in truth zero, so what the fields' κ errors make of an offset shows on its own.
    """
    cfg = replace(cfg or EyeVelocityConfig(), accel_from_truth=accel_from_truth)
    rho, r2 = rho.copy(), r2.copy()
    cold = (t - t[0]) < cfg.settle_time()
    rho[cold], r2[cold] = np.nan, np.nan
    dt = float(np.median(np.diff(t)))
    if accel_from_truth:
        a = np.interp(t, fo.truth["time_s"], fo.truth["a_forward_m_s2"])
        turn = None
    else:
        a_imu = forward_acceleration(fo.imu.time_s, fo.imu.accel, fo.imu.gyro, causal=cfg.readout.filter == "causal")
        a = resample_to(t, fo.imu.time_s, a_imu, dt)
        # As estimate_eye_velocity does: the readout is told the gyro's turn rate (accelerometer noise under turns).
        turn = turn_rate(t, fo.imu.time_s, fo.imu.gyro, dt)
    rcfg, tau, drift = readout_inputs(fo, t, cfg)
    if accel_from_truth and learn_offset:
        rcfg = replace(rcfg, bias_prior_m_s2=cfg.readout.bias_prior_m_s2)
    res = readout(t, rho, r2, a, rcfg, gravity_tau=tau, drift_std=drift, turn_rate=turn)
    vt = np.interp(t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    k = (t >= t[0] + skip_s) & np.isfinite(res.v_hat)
    err = res.v_hat[k] - vt[k]
    return float(np.sqrt(np.mean(err ** 2))), float(np.mean(np.abs(err) <= 2 * res.v_std[k]))


#: the acceleration each level is read out with: (label, from truth, offset learned)
SOURCES = (("true", True, False), ("offset", True, True), ("imu", False, False))


def decompose(fo, config: EyeVelocityConfig | None = None, skip_s: float = 2.0) -> dict:
    """RMSE (m/s) and ±2σ coverage of the readout at each level, with the accelerometer ("imu"), the true
    acceleration ("true") and the true acceleration with an offset learned as for an accelerometer
    ("offset", :func:`readout_rmse`'s learn_offset)."""
    cfg = config or EyeVelocityConfig()
    out = {}
    exact = None
    for level, uniform in (("exact", True), ("ideal", False)):
        t, rho, r2 = ideal_fields(fo, uniform, cfg.circuit)
        exact = exact or (t, rho, r2)
        for src, truth, learn in SOURCES:
            out[f"{level}|{src}"] = readout_rmse(fo, t, rho, r2, truth, cfg, skip_s, learn)
    ds = estimate_eye_velocity(fo, replace(cfg, readout_kind="kalman"))
    if cfg.circuit.rotation not in ("wide-field", "both"):   # field by field (not mirror sums)
        theta = EyeCircuit(fo.eye, fo.rate_hz, cfg.circuit).fields.theta
        rho_g, r2_g = slow_gain_fields(*exact, ds.time.values, ds.r.values, theta)
        used = ds.field_used.values
        for src, truth, learn in SOURCES:
            out[f"gain|{src}"] = readout_rmse(fo, ds.time.values, np.where(used, rho_g, np.nan),
                                              np.where(used, r2_g, np.nan), truth, cfg, skip_s, learn)
    # The fields the pipeline's readout was given (EyeVelocityConfig.reliability_min).
    used = ds.field_used.values
    t, rho, r2 = ds.time.values, np.where(used, ds.r.values, np.nan), np.where(used, ds.r2.values, np.nan)
    for src, truth, learn in SOURCES:
        out[f"emd|{src}"] = readout_rmse(fo, t, rho, r2, truth, cfg, skip_s, learn)
    vt = np.interp(t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    out["zero"] = float(np.sqrt(np.mean(vt[t >= t[0] + skip_s] ** 2)))
    return out


if __name__ == "__main__":
    from stimuli.eye import open_eye_footage

    for path in sys.argv[1:]:
        print(path, json.dumps({k: np.round(v, 4).tolist() for k, v in decompose(open_eye_footage(path)).items()}),
              flush=True)
