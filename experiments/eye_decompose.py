"""Where the fly eye loses velocity accuracy: the same readout fed ever less ideal LC inputs.

Levels (each the readout's RMSE after ``skip_s``, ±2σ coverage and observable fraction — an RMSE
is over the steps the readout calls observable, so one level can look better only by saying less —
with the acceleration from the accelerometer (``|imu``), from truth (``|true``), from truth with an
offset the readout must learn as it would an accelerometer's (``|offset``), so the readout's own share
shows too, and, on synthetic footage, from the accelerometer with the attitude integrated at the
gyroscope's true bias (``|gyro-bias``, :func:`true_gyro_bias`): what the bias the attitude cannot learn
under a turn that never stops costs):

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

On a flight with saccades every level is read out as the pipeline reads the circuit: its visual update
suppressed at the steps the haltere's gate flags (:func:`experiments.eye_readout.suppressed_readout`), so
that a level's cost is not that of a saccade's jump in ρ.

The exact motion uses the forward velocity of ``truth.csv`` only (the tracks translate along
the body axis; the lateral velocity a turn adds in the camera frame changes the exact level by
< 0.006 m/s on the dev worlds). Run: ``python -m experiments.eye_decompose EYE_FOOTAGE ...``.
"""
from __future__ import annotations

import json
import math
import sys
from dataclasses import replace

import numpy as np

from lobula._optional import torch
from lobula.eye_circuit import EyeCircuit, EyeCircuitConfig
from lobula.imu import forward_acceleration, resample_to, turn_rate
from lobula.photoreceptor import lowpass_scan, spatial_filter

from .eye_readout import suppressed_readout
from .eye_velocity import EyeVelocityConfig, estimate_eye_velocity, readout_inputs

__all__ = ["exact_pair_motion", "IdealDetectorCircuit", "ideal_fields", "slow_gain_fields", "true_gyro_bias",
           "readout_rmse", "decompose"]


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


def true_gyro_bias(fo) -> np.ndarray:
    """The gyroscope's true bias (rad/s, (n, 3), camera frame) at the samples of ``fo.imu``.

    Synthetic footage only: its ``scene.json`` records the run configuration, whose seeded IMU
    (:func:`stimuli.track.build_track`) draws the same bias walk again; the eye footage stores the gyro
    in the camera frame, so the IMU-frame bias b reads there as R·b (R = imu_to_camera). Raises
    ValueError where the footage has no run configuration (a real recording) or the regenerated
    IMU's samples are not the footage's.
    """
    from stimuli.track import build_track

    from .sweep_params import run_config_from_dict

    path = fo.path / "scene.json"
    try:
        cfg = run_config_from_dict(json.loads(path.read_text())["config"])
    except (OSError, KeyError, TypeError, ValueError) as exc:  # SweepError is a ValueError
        raise ValueError(f"{path}: no synthetic run configuration to regenerate the IMU from ({exc})") from None
    imu = build_track(cfg)[1]
    t = np.asarray(imu["time_s"], float)
    if fo.imu is None or len(t) != len(fo.imu.time_s) or np.max(np.abs(t - fo.imu.time_s)) > 1e-6:
        raise ValueError(f"{path}: the regenerated IMU's samples are not those of {fo.path / 'imu.csv'}")
    return np.asarray(imu["gyro_bias_t"], float) @ np.asarray(imu["imu_to_camera"], float).T


#: the accelerations a level is read out with (see the module docstring)
SOURCES = ("true", "offset", "imu", "gyro-bias")


def readout_rmse(fo, t, rho, r2, source: str, cfg: EyeVelocityConfig | None = None, skip_s: float = 2.0,
                 gyro_bias: np.ndarray | None = None,
                 saccade: np.ndarray | None = None) -> tuple[float, float, float]:
    """The eye pipeline's readout (settle time, acceleration, readout inputs) on given fields:
    (RMSE m/s, ±2σ coverage, observable fraction) over the steps after ``skip_s``.

    source (:data:`SOURCES`): "true", the true forward acceleration, the readout told so; "offset",
    the same, but the readout not told so — it learns an accelerometer offset (prior std
    ``ReadoutConfig.bias_prior_m_s2``, 0.1 m/s²) that is in truth zero, so what the fields' κ errors
    make of an offset shows on its own; "imu", the accelerometer as the pipeline reads it; "gyro-bias",
    the accelerometer with the attitude integrated at ``gyro_bias`` (n, 3) rad/s, the true bias
    (:func:`true_gyro_bias`), the readout's noise model unchanged. ``saccade`` (n,) bool: the steps whose
    visual update is suppressed, as the pipeline suppresses them (:func:`suppressed_readout`). RMSE and
    coverage are over the observable steps only (NaN where there are none).
    """
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    if (source == "gyro-bias") != (gyro_bias is not None):
        raise ValueError("gyro_bias is given with, and only with, source 'gyro-bias'")
    cfg = replace(cfg or EyeVelocityConfig(), accel_from_truth=source in ("true", "offset"))
    rho, r2 = rho.copy(), r2.copy()
    cold = (t - t[0]) < cfg.settle_time()
    if saccade is not None:
        cold = cold | saccade
    rho[cold], r2[cold] = np.nan, np.nan
    dt = float(np.median(np.diff(t)))
    if cfg.accel_from_truth:
        a = np.interp(t, fo.truth["time_s"], fo.truth["a_forward_m_s2"])
        turn = None
    else:
        a_imu = forward_acceleration(fo.imu.time_s, fo.imu.accel, fo.imu.gyro,
                                     causal=cfg.readout.filter == "causal", bias=gyro_bias)
        a = resample_to(t, fo.imu.time_s, a_imu, dt)
        # As estimate_eye_velocity does: the readout is told the gyro's turn rate (accelerometer noise under turns).
        turn = turn_rate(t, fo.imu.time_s, fo.imu.gyro, dt)
    rcfg, tau, drift = readout_inputs(fo, t, cfg)
    if source == "offset":
        rcfg = replace(rcfg, bias_prior_m_s2=cfg.readout.bias_prior_m_s2)
    res = suppressed_readout(t, rho, r2, a, rcfg, saccade, gravity_tau=tau, drift_std=drift, turn_rate=turn)
    vt = np.interp(t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    late = t >= t[0] + skip_s
    k = late & res.observable
    if not k.any():
        return float("nan"), float("nan"), 0.0
    err = res.v_hat[k] - vt[k]
    return (float(np.sqrt(np.mean(err ** 2))), float(np.mean(np.abs(err) <= 2 * res.v_std[k])),
            float(k.sum() / max(late.sum(), 1)))


def decompose(fo, config: EyeVelocityConfig | None = None, skip_s: float = 2.0) -> dict:
    """(RMSE m/s, ±2σ coverage, observable fraction) of the readout at each level and acceleration
    source (:func:`readout_rmse`), keyed "level|source"; "gyro-bias" only where the footage's IMU can
    be regenerated (:func:`true_gyro_bias`); "zero": the zero estimator's RMSE."""
    cfg = config or EyeVelocityConfig()
    try:
        bias = true_gyro_bias(fo)
    except ValueError:
        bias = None
    sources = [s for s in SOURCES if s != "gyro-bias" or bias is not None]
    out = {}
    ds = estimate_eye_velocity(fo, replace(cfg, readout_kind="kalman"))
    t_ds, flagged = ds.time.values, ds.saccade.values.astype(float)

    def rows(level, t, rho, r2):
        # Every level is suppressed where the pipeline's haltere gate suppressed vision (by time: the levels'
        # latencies differ), so that what a level costs is not what a saccade's jump in ρ costs.
        saccade = np.interp(t, t_ds, flagged) > 0 if flagged.any() else None
        for src in sources:
            out[f"{level}|{src}"] = readout_rmse(fo, t, rho, r2, src, cfg, skip_s,
                                                 gyro_bias=bias if src == "gyro-bias" else None, saccade=saccade)

    exact = None
    for level, uniform in (("exact", True), ("ideal", False)):
        t, rho, r2 = ideal_fields(fo, uniform, cfg.circuit)
        exact = exact or (t, rho, r2)
        rows(level, t, rho, r2)
    used = ds.field_used.values
    if cfg.circuit.rotation not in ("wide-field", "both"):   # field by field (not mirror sums)
        theta = EyeCircuit(fo.eye, fo.rate_hz, cfg.circuit).fields.theta
        rho_g, r2_g = slow_gain_fields(*exact, t_ds, ds.r.values, theta)
        rows("gain", t_ds, np.where(used, rho_g, np.nan), np.where(used, r2_g, np.nan))
    # The fields the pipeline's readout was given (EyeVelocityConfig.reliability_min).
    t = t_ds
    rows("emd", t, np.where(used, ds.r.values, np.nan), np.where(used, ds.r2.values, np.nan))
    vt = np.interp(t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    out["zero"] = float(np.sqrt(np.mean(vt[t >= t[0] + skip_s] ** 2)))
    return out


if __name__ == "__main__":
    from stimuli.eye import open_eye_footage

    for path in sys.argv[1:]:
        print(path, json.dumps({k: np.round(v, 4).tolist() for k, v in decompose(open_eye_footage(path)).items()}),
              flush=True)
