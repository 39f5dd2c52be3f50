"""How close online can come to offline: optimal filter against optimal smoother on the suite's trajectories.

Issue 10 asks the causal readout to stay within 1.5× of the zero-phase one. This module asks what any
estimator could do with the information the readout has, under a linear-Gaussian model of it, so that the
pipeline's ratio can be read against the ratio the information allows.

The model (SI units) is the readout's own (:func:`lobula.readout.kalman_velocity`) stripped to what the sensors
carry. State: forward velocity v (m/s) and the accelerometer's offset b (m/s²).

- Motion: v̇ = a_m − b + w_a, with a_m the accelerometer's forward reading and w_a white (``accel_noise``,
  m/s²/√Hz). ḃ is a random walk (``bias_walk``, m/s²/√s).
- Vision, each frame: y = κ·v + b + n. κ = a/v is the fields' (ṙ − r²)/r, which needs no depth, and y is the
  low-passed accelerometer, the readout's measurement. n has three parts:
  - a shared relative error of κ (``kappa_rel_error``·|a|);
  - an absolute error of κ (``kappa_abs_error``·|v|, e.g. residual rotation);
  - a floor (``accel_floor``): ṙ's noise over a vanishing r, σ_ṙ·D, and the filtered accelerometer's own noise.

The truth's v(t) and a(t) set κ and the noise at each frame. The Kalman filter's posterior variance at each
frame is then the least any causal estimator can reach under the model, and the Rauch–Tung–Striebel smoother's
the least any offline one can (both are the MMSE estimators of a linear-Gaussian system). Online, the readout's
κ also reaches it ``latency_s`` late: it is built from a centred low-pass of the fields' rates. The estimate at
t then rests on measurements up to t − latency, predicted forward through the motion model (the bridge over
∫(a_m − b) whose offset is uncertain).

Both sides also carry the accelerometer's scale-factor error, ``scale_error``·|v| (a 1σ fraction). Vision
measures only κ = a/v, so v̂ = a_m/κ takes the accelerometer's scale whole, online and offline alike.

Measured, not fitted (the models: :data:`NOISE_MODELS`):

- κ's relative error: on the suite's development worlds (seeds 100–103, true acceleration), 2–10 % rms,
  correlated over 3–9 frames, a per-frame-equivalent 0.05–0.26 (median 0.135; docs/accuracy-history.md,
  eighteenth session).
- The accelerometer's white noise after the readout's removal of its slow part: 0.001–0.009 m/s² over 1 s
  (ReadoutConfig.accel_noise, 0.01 m/s²/√Hz).
- The offset's walk: ReadoutConfig.bias_walk (0.002). The realistic IMU's own is 0.001; the gravity the
  attitude leaks moves it more.
- Scale: the realistic IMU's 1 % per axis.

Known answers (tests/test_online_bound.py): a constant v measured alike each frame (filter 1/(k+1), smoother
1/N of one frame's variance); a random walk observed each frame (the steady-state smoother's variance half the
filter's: a ratio of √2 in RMSE, the floor of any online/offline ratio for random-walk errors).

Run: ``python -m experiments.online_bound [--families all] [--seeds 3] [--duration 10]``.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, replace

import numpy as np

__all__ = ["InformationModel", "NOISE_MODELS", "readout_latency_s", "filter_and_smoother", "online_offline",
           "family_trajectory", "bound_table"]


@dataclass(frozen=True)
class InformationModel:
    """What the readout's sensors tell about v (SI units; see the module docstring).

    kappa_rel_error: per-frame-equivalent relative error of κ (fraction). kappa_abs_error: its absolute error
    (1/s). accel_floor: the vision measurement's floor (m/s²). accel_noise: white noise of the acceleration
    that drives v (m/s²/√Hz). bias_walk: the offset's random walk (m/s²/√s). bias_prior / v_prior: prior
    stds (m/s², m/s). scale_error: the accelerometer's scale-factor error (fraction, 1σ), common to both
    estimators. latency_s: how late vision's κ reaches the online estimator (s); None: the readout's own
    (:func:`readout_latency_s`).
    """

    kappa_rel_error: float = 0.135
    kappa_abs_error: float = 0.05
    accel_floor: float = 0.01
    accel_noise: float = 0.01
    bias_walk: float = 0.002
    bias_prior: float = 0.1
    v_prior: float = 1.0
    scale_error: float = 0.01
    latency_s: float | None = None


#: The measured noise sizes (median) and their measured range's two ends.
NOISE_MODELS = {
    "measured": InformationModel(),
    "optimistic": InformationModel(kappa_rel_error=0.05, kappa_abs_error=0.02, accel_floor=0.005,
                                   accel_noise=0.005, bias_walk=0.001),
    "pessimistic": InformationModel(kappa_rel_error=0.26, kappa_abs_error=0.1, accel_floor=0.02,
                                    bias_walk=0.005),
}


def readout_latency_s(dt: float, config=None) -> float:
    """How late the causal readout's κ is (s): its centred online low-pass's half-width plus half the
    stagger of ṙ's difference, as :func:`lobula.readout.kalman_readout` takes it (11 frames at 30 frames/s)."""
    from lobula.readout import ReadoutConfig, gaussian_lowpass

    cfg = config or ReadoutConfig()
    stagger = max(2, cfg.stagger + cfg.stagger % 2)
    half = gaussian_lowpass(np.zeros(3), cfg.cutoff_hz, dt, truncate=cfg.online_window_sigma)[1]
    return (half + stagger // 2) * dt


def filter_and_smoother(t, v, a, model: InformationModel):
    """Posterior variances of v (m²/s²), each (n,): the Kalman filter's, the RTS smoother's, and the online
    estimate's with vision ``model.latency_s`` late (the filter's at t − latency predicted to t).

    t (n,) s, uniformly spaced; v (n,) m/s and a (n,) m/s² the truth that sets κ = a/v and the noise.
    The scale-factor term is not included (see :func:`online_offline`).
    """
    t, v, a = (np.asarray(x, float) for x in (t, v, a))
    n = len(t)
    if n < 2 or not np.all(np.isfinite(np.stack([t, v, a]))):
        raise ValueError("t, v and a must be finite, with at least 2 samples")
    dt = float(np.median(np.diff(t)))
    m = model
    F = np.array([[1.0, -dt], [0.0, 1.0]])
    Q = np.diag([m.accel_noise ** 2 * dt, m.bias_walk ** 2 * dt])
    # κ·v + b: where v ≈ 0 the row keeps b alone (κ undefined; a = 0 there in the truth's smooth runs).
    kappa = np.divide(a, v, out=np.zeros(n), where=np.abs(v) > 1e-3)
    R = (m.kappa_rel_error * a) ** 2 + (m.kappa_abs_error * v) ** 2 + m.accel_floor ** 2
    P = np.diag([m.v_prior ** 2, m.bias_prior ** 2])
    Pp, Pf = np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
    for k in range(n):  # over time steps; the state has two dimensions
        if k:
            P = F @ P @ F.T + Q
        Pp[k] = P
        h = np.array([kappa[k], 1.0])
        g = P @ h / (h @ P @ h + R[k])
        P = P - np.outer(g, h @ P)
        Pf[k] = P
    Ps = Pf.copy()
    for k in range(n - 2, -1, -1):
        C = Pf[k] @ F.T @ np.linalg.inv(Pp[k + 1])
        Ps[k] = Pf[k] + C @ (Ps[k + 1] - Pp[k + 1]) @ C.T
    lat = readout_latency_s(dt) if m.latency_s is None else float(m.latency_s)
    L = int(round(lat / dt))
    # P(k | k − L) = F^L P_f(k − L) F^Lᵀ + Σ_{i<L} F^i Q F^iᵀ; before the first measurement arrives, the prior.
    FL, QL = np.eye(2), np.zeros((2, 2))
    for _ in range(L):
        QL = F @ QL @ F.T + Q
        FL = F @ FL
    Pl = np.empty_like(Pf)
    Pl[L:] = np.einsum("ij,njk,lk->nil", FL, Pf[:n - L], FL) + QL
    P0 = np.diag([m.v_prior ** 2, m.bias_prior ** 2])
    for k in range(min(L, n)):
        Pl[k] = np.linalg.matrix_power(F, k) @ P0 @ np.linalg.matrix_power(F, k).T
    return Pf[:, 0, 0], Ps[:, 0, 0], Pl[:, 0, 0]


def online_offline(t, v, a, model: InformationModel, skip_s: float = 2.0) -> dict:
    """Expected RMSE (m/s) after ``skip_s`` of the optimal online estimate (vision late by the latency), the
    optimal causal one with vision on time, and the optimal offline one, each with the scale-factor error
    (scale_error·|v|) added, and their ratios to offline."""
    pf, ps, pl = filter_and_smoother(t, v, a, model)
    keep = np.asarray(t) - t[0] >= skip_s
    common = (model.scale_error * np.asarray(v)[keep]) ** 2
    rms = {name: float(np.sqrt(np.mean(p[keep] + common))) for name, p in
           (("online", pl), ("filter", pf), ("offline", ps))}
    return {**rms, "online_ratio": rms["online"] / rms["offline"], "filter_ratio": rms["filter"] / rms["offline"]}


def family_trajectory(family: str, seed: int, duration_s: float = 10.0):
    """The truth of one accuracy-suite scene without rendering it: frame times (s), forward velocity (m/s) and
    forward acceleration (m/s²) along the optical axis, (n,) each, as ``truth.csv`` holds them."""
    from stimuli.track import build_track

    from .suite import family_config

    scene, _ = build_track(family_config(family, seed, duration_s, scale=0.5))
    times = np.arange(0.0, duration_s - 1e-9, 1.0 / scene.camera.frame_rate_hz)
    # As stimuli.footage.write_footage writes truth.csv: the track's acceleration projected on the optical axis.
    v = scene.camera_velocity(times)[:, 2]
    a = scene.trajectory.acceleration(times) * scene.rotation(times)[:, 2, 2]
    return times, v, a


def bound_table(families, seeds, duration_s: float = 10.0, models=None, skip_s: float = 2.0) -> list[dict]:
    """One row per family × seed × noise model: :func:`online_offline`'s figures."""
    models = models or NOISE_MODELS
    rows = []
    for fam in families:
        for seed in seeds:
            t, v, a = family_trajectory(fam, seed, duration_s)
            for name, model in models.items():
                rows.append(dict(family=fam, seed=seed, model=name, **online_offline(t, v, a, model, skip_s)))
    return rows


def _summary(rows, key: str) -> str:
    r = np.array([x[key] for x in rows])
    return f"{np.median(r):.2f} ({r.min():.2f}–{r.max():.2f})"


def main(argv=None) -> int:
    from .suite import FAMILIES, parse_seeds
    from .store import provenance, write_text

    p = argparse.ArgumentParser(prog="python -m experiments.online_bound", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--families", default="all", help="comma-separated suite families, or all")
    p.add_argument("--seeds", default="3", help="a count (seeds 0…N−1), or a comma-separated list (e.g. 100,101)")
    p.add_argument("--duration", type=float, default=10.0, help="scene length (s)")
    p.add_argument("--skip", type=float, default=2.0, help="seconds left out of the RMSE at the start")
    p.add_argument("--models", default=",".join(NOISE_MODELS), help="noise models (of NOISE_MODELS)")
    p.add_argument("--out", default=None, help="also write the rows and the models as JSON here (atomically)")
    args = p.parse_args(argv)
    families = list(FAMILIES) if args.families == "all" else [f.strip() for f in args.families.split(",") if f.strip()]
    seeds = parse_seeds(args.seeds)
    seeds = list(range(seeds)) if isinstance(seeds, int) else seeds
    names = [m.strip() for m in args.models.split(",") if m.strip()]
    unknown = [m for m in names if m not in NOISE_MODELS]
    if unknown:
        p.error(f"unknown noise model(s) {', '.join(unknown)}; choose from {', '.join(NOISE_MODELS)}")
    models = {m: NOISE_MODELS[m] for m in names}
    rows = bound_table(families, seeds, args.duration, models, args.skip)
    print(f"optimal online / offline RMSE after {args.skip:g} s, median (range) over seeds; "
          f"vision {readout_latency_s(1 / 30):.2f} s late online / on time:")
    print("| family | " + " | ".join(f"{m} online | {m} on time" for m in names) + " |")
    print("|---|" + "---|---|" * len(names))
    for fam in families + ["all"]:
        sel = [r for r in rows if fam in ("all", r["family"])]
        cells = [f"{_summary([r for r in sel if r['model'] == m], 'online_ratio')} | "
                 f"{_summary([r for r in sel if r['model'] == m], 'filter_ratio')}" for m in names]
        print(f"| {fam} | " + " | ".join(cells) + " |")
    if args.out:
        doc = dict(rows=rows, models={m: asdict(replace(models[m])) for m in names},
                   provenance=provenance(json.dumps(vars(args))))
        write_text(args.out, json.dumps(doc, indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
