"""How close online can come to offline: optimal filter against optimal smoother on the suite's trajectories.

The project's target is a causal readout within 1.5× of the zero-phase one. This module asks what any
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
  correlated over 3–9 frames, a per-frame-equivalent 0.05–0.26 (median 0.135).
- The accelerometer's white noise after the readout's removal of its slow part: 0.001–0.009 m/s² over 1 s
  (ReadoutConfig.accel_noise, 0.01 m/s²/√Hz).
- The offset's walk: ReadoutConfig.bias_walk (0.002). The realistic IMU's own is 0.001; the gravity the
  attitude leaks moves it more.
- Scale: the realistic IMU's 1 % per axis.

The model is not tight in absolute terms: the pipeline's zero-phase readout beats its optimal offline figures on
DIS (it also uses reversals, rest and an estimated shared error, and per-frame equivalents may overstate errors
that persist). Its ratios say what white errors of the measured size allow.

``--footage PATH…`` measures the noise instead of assuming it (:func:`footage_kappa`, :func:`kappa_noise`): κ
formed as the readout forms it on synthetic footage (the camera's DIS or EMD front end, or the compound eye),
against the truth, and the model's optimum at that noise on the footage's own trajectory.

Known answers (tests/test_online_bound.py): b known and the motion deterministic, each frame measures the start
velocity (filter 1/(1/prior + Σ_{j≤k} info_j), smoother the sum over all); a random walk observed each frame (the
scalar Riccati fixed points; the steady-state smoother's variance half the filter's, √2 in RMSE, in the
continuous limit); a known white and a known correlated κ error measured back.

The model's priors (1 m/s, 0.1 m/s²) suit the indoor families; ``--priors readout`` gives each record the priors
the readout itself starts from (:func:`readout_priors`), which is what a drone or a car at metres per second
calls for.

Run: ``python -m experiments.online_bound [--families all] [--seeds 3] [--duration 10] [--priors model|readout]``
or ``python -m experiments.online_bound --footage PATH… [--front-end dis|emd] [--priors model|readout]``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from dataclasses import asdict, dataclass, replace

import numpy as np

__all__ = ["InformationModel", "NOISE_MODELS", "readout_latency_s", "filter_and_smoother", "online_offline",
           "family_trajectory", "bound_table", "vision_kappa", "kappa_noise", "footage_kappa", "suite_ratios",
           "plot_ratios", "readout_priors", "PRIORS"]


@dataclass(frozen=True)
class InformationModel:
    """What the readout's sensors tell about v (SI units; see the module docstring).

    kappa_rel_error: per-frame-equivalent relative error of κ (fraction). kappa_abs_error: its absolute error
    (1/s). accel_floor: the vision measurement's floor (m/s²). accel_noise: white noise of the acceleration
    that drives v (m/s²/√Hz). bias_walk: the offset's random walk (m/s²/√s). bias_prior / v_prior: prior
    stds (m/s², m/s). scale_error: the accelerometer's scale-factor error (fraction, 1σ), common to both
    estimators. latency_s: how late vision's κ reaches the online estimator (s); None: the readout's own
    (:func:`readout_latency_s`). bias_prior_online: the online estimator's offset prior std (m/s²) where it
    differs from the offline one's (None: bias_prior for both).
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
    bias_prior_online: float | None = None


#: The measured noise sizes (median) and their measured range's two ends.
NOISE_MODELS = {
    "measured": InformationModel(),
    "optimistic": InformationModel(kappa_rel_error=0.05, kappa_abs_error=0.02, accel_floor=0.005,
                                   accel_noise=0.005, bias_walk=0.001),
    "pessimistic": InformationModel(kappa_rel_error=0.26, kappa_abs_error=0.1, accel_floor=0.02,
                                    bias_walk=0.005),
}


def readout_latency_s(dt: float, config=None) -> float:
    """How late the causal readout's κ is (s): :func:`lobula.readout.readout_lag` frames of ``dt`` (its centred
    online low-pass's half-width plus half the stagger of ṙ's difference; 11 frames at 30 frames/s for the
    camera's readout)."""
    from lobula.readout import ReadoutConfig, readout_lag

    return readout_lag(replace(config or ReadoutConfig(), filter="causal"), dt) * dt


def readout_priors(model: InformationModel, t, v) -> InformationModel:
    """``model`` with the priors the readout itself starts from on a record of times t (n,) s and true
    forward velocity v (n,) m/s, in place of the model's fixed ones.

    v: :attr:`ReadoutConfig.v_prior_m_s <lobula.readout.ReadoutConfig>`. The offset: the accelerometer's own
    (``bias_prior_m_s2``) and, in quadrature, the gravity reference's error as the pipeline sizes it
    (:func:`lobula.velocity.inertial.offline_gravity_error`): offline the record's mean acceleration, up to
    v_prior / its span; online the start's acceleration, the start prior for a camera seen moving where the
    truth moves at the first frame, else the resting one. A drone or a car starts a record at metres per
    second and takes up its mean acceleration; the model's fixed priors (1 m/s, 0.1 m/s²) know both far
    better than the readout does.
    """
    from lobula.readout import ReadoutConfig
    from lobula.velocity.inertial import START_ACCEL_PRIOR_M_S2, START_ACCEL_PRIOR_MOVING_M_S2, offline_gravity_error

    rc = ReadoutConfig()
    start = START_ACCEL_PRIOR_MOVING_M_S2 if v[0] != 0 else START_ACCEL_PRIOR_M_S2
    return replace(model, v_prior=rc.v_prior_m_s,
                   bias_prior=float(np.hypot(rc.bias_prior_m_s2, offline_gravity_error(float(t[-1] - t[0]),
                                                                                        rc.v_prior_m_s))),
                   bias_prior_online=float(np.hypot(rc.bias_prior_m_s2, start)))


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
    # P(k | k − L) = F^L P_f(k − L) F^Lᵀ + Σ_{i<L} F^i Q F^iᵀ; before the first measurement arrives, the prior
    # predicted (its first L frames, which the same recursion gives).
    FL, QL, P = np.eye(2), np.zeros((2, 2)), np.diag([m.v_prior ** 2, m.bias_prior ** 2])
    Pl = np.empty_like(Pf)
    for k in range(L):
        if k < n:
            Pl[k] = P
        P = F @ P @ F.T + Q
        QL = F @ QL @ F.T + Q
        FL = F @ FL
    Pl[L:] = np.einsum("ij,njk,lk->nil", FL, Pf[:n - L], FL) + QL
    return Pf[:, 0, 0], Ps[:, 0, 0], Pl[:, 0, 0]


def online_offline(t, v, a, model: InformationModel, skip_s: float = 2.0) -> dict:
    """Expected RMSE (m/s) after ``skip_s`` of the optimal online estimate (vision late by the latency), the
    optimal causal one with vision on time, and the optimal offline one, each with the scale-factor error
    (scale_error·|v|) added, and their ratios to offline. The online two start from ``bias_prior_online``
    where the model has one."""
    pf, ps, pl = filter_and_smoother(t, v, a, model)
    if model.bias_prior_online is not None:
        pf, _, pl = filter_and_smoother(t, v, a, replace(model, bias_prior=model.bias_prior_online))
    keep = np.asarray(t) - t[0] >= skip_s
    common = (model.scale_error * np.asarray(v)[keep]) ** 2
    rms = {name: float(np.sqrt(np.mean(p[keep] + common))) for name, p in
           (("online", pl), ("filter", pf), ("offline", ps))}
    return {**rms, "online_ratio": rms["online"] / rms["offline"], "filter_ratio": rms["filter"] / rms["offline"]}


def vision_kappa(t, r, r2, a, config, material=None) -> np.ndarray:
    """Vision's κ = a/v per frame (1/s, (n,), NaN where uninformative), formed as the kalman readout forms it
    (:func:`lobula.readout.readout_terms`, :func:`lobula.readout.ratio_measurement`), offline (no latency):
    fields whose implied depth is not physical left out where |a| is clear of the offset's prior.

    t (n,) s; r, r2 (n, F) the fields' rates (1/s, 1/s²); a (n,) m/s² (for that judgement only); config a
    ReadoutConfig; material: the rates along the content (:class:`lobula.readout.MaterialRates`) or None.
    """
    from lobula.readout import physical_kappa, readout_terms, vision_measurement

    cfg = replace(config, filter="zero-phase")
    terms = readout_terms(t, r, r2, a, cfg, material)[0]
    return physical_kappa(terms, vision_measurement(*terms, cfg)[2], cfg, cfg.bias_prior_m_s2)[0]


def _correlation_time(x: np.ndarray, dt: float, max_s: float = 3.0) -> float:
    """Integrated autocorrelation time (s) of a series with NaN gaps: dt·(1 + 2 Σ ρ_k), summed while ρ_k stays
    above the 2/√n a white series reaches by chance, at most to max_s."""
    x = np.asarray(x, float) - np.nanmean(x)
    var = np.nanmean(x * x)
    chance = 2.0 / np.sqrt(np.isfinite(x).sum())
    total = 1.0
    for k in range(1, int(max_s / dt)):  # over lags
        prod = x[k:] * x[:-k]
        rho = np.nanmean(prod) / var if np.isfinite(prod).sum() > 10 else 0.0
        if not rho > chance:
            break
        total += 2.0 * rho
    return total * dt


def kappa_noise(t, kappa, v, a, frame_dt: float = 1 / 30, v_min: float = 0.1) -> dict:
    """κ's error as :class:`InformationModel` sizes it, measured against the truth.

    t (n,) s; kappa (n,) 1/s vision's κ (:func:`vision_kappa`); v (n,) m/s and a (n,) m/s² the truth through
    the same low-pass. The error in the readout's a_m = κ·v + b is n = κ·v − a (m/s²), taken where
    |v| ≥ v_min; its rms is ``rms_m_s2``. Less κ's gain (κ·v regressed on a), its variance is split as
    ε²·a² + s0²·v² + f² (non-negative least squares on n²), and each part scaled by the errors' correlation
    time over ``frame_dt``: white errors, one per frame of the model, that carry the same information.
    Returns the InformationModel fields kappa_rel_error (ε), kappa_abs_error (s0, 1/s), accel_floor (f,
    m/s²), and correlation_s, rms_m_s2, n_frames and gain (below 1, v̂ = a_m/κ reads that much high).
    """
    from scipy.optimize import nnls

    t, kappa, v, a = (np.asarray(x, float) for x in (t, kappa, v, a))
    err = np.where(np.isfinite(kappa) & (np.abs(v) >= v_min), kappa * v - a, np.nan)
    ok = np.isfinite(err)
    if ok.sum() < 20:
        raise ValueError(f"only {ok.sum()} frames where κ is measured and |v| ≥ {v_min} m/s; need 20")
    dt = float(np.median(np.diff(t)))
    # κ's gain (a scale error, which v̂ = a_m/κ takes whole as it does the accelerometer's) is reported apart,
    # not counted as noise.
    gain = float(np.sum(a[ok] * (kappa[ok] * v[ok])) / np.sum(a[ok] ** 2))
    rms = float(np.sqrt(np.mean(err[ok] ** 2)))
    err = err - (gain - 1.0) * a
    coef = nnls(np.stack([a[ok] ** 2, v[ok] ** 2, np.ones(ok.sum())], 1), err[ok] ** 2)[0]
    tau = _correlation_time(err, dt)
    eq = np.sqrt(coef * max(1.0, tau / frame_dt))
    return dict(kappa_rel_error=float(eq[0]), kappa_abs_error=float(eq[1]), accel_floor=float(eq[2]),
                correlation_s=float(tau), rms_m_s2=rms, gain=gain, n_frames=int(ok.sum()))


def footage_kappa(path, front_end: str = "dis") -> dict:
    """κ measured on synthetic footage with truth: the camera's (``front_end`` "dis", the default, or "emd")
    or the compound eye's (its circuit and gated fields; ``front_end`` is then ignored), offline. Returns t,
    kappa, and the truth's v and a through the readout's own zero-phase low-pass, each (n,), with the readout
    configuration (``config``) and the front end's name (``front_end``)."""
    from lobula.config import VelocityConfig
    from lobula.readout import butterworth
    from stimuli.eye import is_eye_footage, open_eye_footage
    from lobula.readers import open_footage

    from .eye_velocity import EyeVelocityConfig, estimate_eye_velocity
    from lobula.velocity import field_rates

    eye = is_eye_footage(path)
    fo = open_eye_footage(path) if eye else open_footage(path)
    if fo.truth is None or "a_forward_m_s2" not in fo.truth:
        raise ValueError(f"{path}: needs truth.csv with v_forward_m_s and a_forward_m_s2")
    if eye:
        cfg = EyeVelocityConfig()
        ds = estimate_eye_velocity(fo, cfg, progress=False)
        t = ds.time.values
        r = np.where(ds.field_used.values, ds.r.values, np.nan)
        r2 = np.where(ds.field_used.values, ds.r2.values, np.nan)
        rcfg, material, front = cfg.readout, None, "compound eye"
    else:
        vcfg = VelocityConfig(front_end=front_end)
        rates = field_rates(fo, vcfg, progress=False)
        t, r, r2, material, rcfg, front = rates.t, rates.r, rates.r2, rates.material, vcfg.readout, vcfg.front_end
    v = np.interp(t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    a = np.interp(t, fo.truth["time_s"], fo.truth["a_forward_m_s2"])
    dt = float(np.median(np.diff(t)))
    lp = lambda x: butterworth(x, rcfg.cutoff_hz / (0.5 / dt), rcfg.order, True)
    return dict(t=t, kappa=vision_kappa(t, r, r2, a, rcfg, material), v=lp(v), a=lp(a), v_raw=v, a_raw=a,
                config=rcfg, front_end=front)


def family_trajectory(family: str, seed: int, duration_s: float = 10.0):
    """The truth of one accuracy-suite scene without rendering it: frame times (s), forward velocity (m/s) and
    forward acceleration (m/s²) along the optical axis, (n,) each, as ``truth.csv`` holds them."""
    from stimuli.track import build_track

    from .suite import family_config

    scene, _ = build_track(family_config(family, seed, duration_s, scale=0.5))
    times = np.arange(0.0, duration_s - 1e-9, 1.0 / scene.camera.frame_rate_hz)
    # As stimuli.footage_writer.write_footage writes truth.csv: the track's acceleration projected on the optical axis.
    v = scene.camera_velocity(times)[:, 2]
    a = scene.trajectory.acceleration(times) * scene.rotation(times)[:, 2, 2]
    return times, v, a


PRIORS = ("model", "readout")


def _with_priors(model: InformationModel, priors: str, t, v) -> InformationModel:
    """``model`` itself (``priors`` "model") or with the readout's priors on that record ("readout":
    :func:`readout_priors`)."""
    if priors not in PRIORS:
        raise ValueError(f"priors must be one of {', '.join(PRIORS)}, got {priors!r}")
    return readout_priors(model, t, v) if priors == "readout" else model


def bound_table(families, seeds, duration_s: float = 10.0, models=None, skip_s: float = 2.0,
                priors: str = "model") -> list[dict]:
    """One row per family × seed × noise model: :func:`online_offline`'s figures; ``priors`` as
    :func:`_with_priors` takes it."""
    models = models or NOISE_MODELS
    rows = []
    for fam in families:
        for seed in seeds:
            t, v, a = family_trajectory(fam, seed, duration_s)
            for name, model in models.items():
                rows.append(dict(family=fam, seed=seed, model=name,
                                 **online_offline(t, v, a, _with_priors(model, priors, t, v), skip_s)))
    return rows


def suite_ratios(path, families, seeds, skip_s: float, duration_s: float) -> dict:
    """{(family, seed): causal / zero-phase RMSE after the skip} from a `lobula suite` suite.nc; refuses a file
    that lacks a family, seed or configuration asked, or was run with another skip or duration."""
    import xarray as xr

    with xr.open_dataset(path) as ds:
        settings = json.loads(ds.attrs.get("suite", "{}"))
        for key, want in (("skip_s", skip_s), ("duration_s", duration_s)):
            if key in settings and abs(float(settings[key]) - want) > 1e-9:
                raise ValueError(f"{path}: the suite ran with {key} {settings[key]}, the bound with {want}")
        if not {"family", "seed", "configuration", "value"} <= set(ds.variables):
            raise ValueError(f"{path}: not a `lobula suite` suite.nc (no family, seed, configuration and value)")
        have = {"family": set(map(str, ds.family.values)), "seed": set(int(x) for x in ds.seed.values),
                "configuration": set(map(str, ds.configuration.values))}
        for dim, want in (("family", set(families)), ("seed", set(seeds)),
                          ("configuration", {"lobula causal", "lobula zero-phase"})):
            if not want <= have[dim]:
                raise ValueError(f"{path}: no {dim} {', '.join(map(str, sorted(want - have[dim])))}")
        rmse = ds.value.sel(window="after_skip", metric="rmse_m_s")
        ratio = rmse.sel(configuration="lobula causal") / rmse.sel(configuration="lobula zero-phase")
        return {(f, s): float(ratio.sel(family=f, seed=s)) for f in families for s in seeds}


def plot_ratios(rows, families, models, path):
    """Online / offline RMSE per family: the model optimum's per seed (filled: vision as late as the causal readout;
    open: on time), one colour per noise model, and the pipeline's where given; the targets 1.5 and 1.25."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    fig, ax = plt.subplots(figsize=(max(8.0, 1.1 * len(families) + 3) + 3.5, 5))
    x = np.arange(len(families))
    offsets = np.linspace(-0.25, 0.25, len(models) + 1)
    for j, m in enumerate(models):
        sel = [r for r in rows if r["model"] == m]
        xs = np.array([x[families.index(r["family"])] + offsets[j] for r in sel])
        ax.scatter(xs, [r["online_ratio"] for r in sel], color=f"C{j}", s=22, label=f"optimum, {m} noise, κ late")
        ax.scatter(xs, [r["filter_ratio"] for r in sel], facecolor="none", edgecolor=f"C{j}", s=22,
                   label=f"optimum, {m} noise, κ on time")
    pipe = [r for r in rows if r["model"] == models[0] and np.isfinite(r.get("pipeline_ratio", np.nan))]
    if pipe:
        ax.scatter([x[families.index(r["family"])] + offsets[-1] for r in pipe], [r["pipeline_ratio"] for r in pipe],
                   marker="D", color="k", s=26, label="the pipeline (lobula causal / zero-phase)")
    ax.axhline(1.5, color="r", lw=1, label="the target, 1.5")
    ax.axhline(1.25, color="r", lw=1, ls="--", label="its stretch target, 1.25")
    ax.axhline(1.0, color="0.6", lw=0.8)
    ax.set_xticks(x, families)
    ax.set_ylabel("online / offline RMSE after the skip")
    ax.set_title("How close online can come to offline (one mark per seed)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    out = save_figure(fig, path, dpi=120)
    plt.close(fig)
    return out


def _summary(rows, key: str, digits: int = 2) -> str:
    r = np.array([x[key] for x in rows])
    return f"{np.median(r):.{digits}f} ({r.min():.{digits}f}–{r.max():.{digits}f})"


PROG = "python -m experiments.online_bound"


def main(argv=None) -> int:
    """Run the command line; a refusal, an unwritable output or an interrupt is one line, as `lobula`'s."""
    from lobula.readers.core import FootageError

    from .store import OutputError

    try:
        return _main(argv)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing written", file=sys.stderr)
        return 130
    except (FootageError, OutputError, ValueError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


def _check_options(p, args, families: list[str]) -> None:
    """Refuse, before any work, what the bound cannot run or write (one line via ``p.error``)."""
    from .cli import _output_clash
    from .store import writable_problem
    from .suite import ALL_FAMILIES

    unknown = [f for f in families if f not in ALL_FAMILIES]
    if unknown:
        p.error(f"--families: unknown {', '.join(unknown)}; choose from {', '.join(ALL_FAMILIES)}")
    if not (np.isfinite(args.duration) and np.isfinite(args.skip) and 0 <= args.skip < args.duration):
        p.error(f"--duration {args.duration:g} and --skip {args.skip:g}: the skip must lie in [0, duration) s")
    clash = _output_clash([(f"--{o}", getattr(args, o)) for o in ("out", "plot") if getattr(args, o)])
    if clash:
        p.error(clash)
    for option in ("out", "plot"):
        problem = getattr(args, option) and writable_problem(getattr(args, option))
        if problem:
            p.error(f"--{option}: {problem}")


def _main(argv=None) -> int:
    from .cli import _Parser
    from .suite import FAMILIES, parse_seeds

    p = _Parser(prog=PROG, description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--families", default="all", help="comma-separated suite families, or all")
    p.add_argument("--seeds", default="3",
                   help="a count (seeds 0…N−1), or a comma-separated list (100,101; one seed: 7,)")
    p.add_argument("--duration", type=float, default=10.0, help="scene length (s)")
    p.add_argument("--skip", type=float, default=2.0, help="seconds left out of the RMSE at the start")
    p.add_argument("--models", default=",".join(NOISE_MODELS), help="noise models (of NOISE_MODELS)")
    p.add_argument("--footage", nargs="+", default=None, metavar="PATH",
                   help="instead of the bound: measure vision's κ against the truth on synthetic footage (camera or "
                        "compound eye, with truth.csv)")
    p.add_argument("--front-end", default="dis", choices=["dis", "emd"],
                   help="the camera footage's front end for --footage (the compound eye has its own circuit)")
    p.add_argument("--priors", default="model", choices=PRIORS,
                   help="the estimators' priors on v and the offset: the noise model's (1 m/s, 0.1 m/s²), or those "
                        "the readout starts from on each record (15 m/s; the offset with the gravity reference's "
                        "error, offline the record's mean acceleration, online the start's)")
    p.add_argument("--suite", default=None, metavar="SUITE_NC",
                   help="a `lobula suite` suite.nc with 'lobula causal' and 'lobula zero-phase' on the same "
                        "families and seeds: the pipeline's causal / zero-phase ratio beside the optimum's")
    p.add_argument("--plot", default=None, metavar="PNG", help="draw the ratios per family (atomically)")
    p.add_argument("--out", default=None, help="also write the rows and the models as JSON here (atomically)")
    args = p.parse_args(argv)
    bound_only = [f"--{k.replace('_', '-')}" for k in ("families", "seeds", "duration", "skip", "models", "suite",
                                                        "plot")
                  if getattr(args, k) != p.get_default(k)]
    if args.footage and bound_only:
        p.error(f"{', '.join(bound_only)} set the bound's families and models; --footage measures footage instead")
    if not args.footage and args.front_end != p.get_default("front_end"):
        p.error("--front-end applies to --footage only")
    if args.footage:
        try:
            rows = footage_rows(args.footage, args.front_end, priors=args.priors)
        except (ValueError, OSError) as e:  # unreadable footage, no truth: said, not a traceback
            p.error(str(e))
        print("vision's κ against the truth, offline: the error of a_m = κ·v (κ·v − a, where |v| ≥ 0.1 m/s), "
              "κ's gain, the errors' correlation time, the per-frame equivalents the bound's model takes (at 30 frames/s), and "
              "the model's optimal online (vision as late as the front end's causal readout) and offline RMSE (m/s) "
              "after 2 s at that noise")
        print("| footage | front end | frames | rms κ·v − a (m/s²) | gain | correlation (s) | κ relative | "
              "κ absolute (1/s) | floor (m/s²) | latency (s) | optimal online | optimal offline |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['footage']} | {r['front_end']} | {r['n_frames']} | {r['rms_m_s2']:.4f} | {r['gain']:.3f} | "
                  f"{r['correlation_s']:.2f} | {r['kappa_rel_error']:.3f} | {r['kappa_abs_error']:.3f} | "
                  f"{r['accel_floor']:.3f} | {r['latency_s']:.2f} | {r['online']:.4f} | {r['offline']:.4f} |")
        _write(args, rows, {})
        return 0
    families = list(FAMILIES) if args.families == "all" else [f.strip() for f in args.families.split(",") if f.strip()]
    _check_options(p, args, families)
    seeds = parse_seeds(args.seeds)
    seeds = list(range(seeds)) if isinstance(seeds, int) else seeds
    names = [m.strip() for m in args.models.split(",") if m.strip()]
    unknown = [m for m in names if m not in NOISE_MODELS]
    if unknown:
        p.error(f"unknown noise model(s) {', '.join(unknown)}; choose from {', '.join(NOISE_MODELS)}")
    models = {m: NOISE_MODELS[m] for m in names}
    try:
        pipeline = suite_ratios(args.suite, families, seeds, args.skip, args.duration) if args.suite else {}
    except (ValueError, OSError) as e:
        p.error(str(e))
    rows = bound_table(families, seeds, args.duration, models, args.skip, args.priors)
    for r in rows:
        r["pipeline_ratio"] = pipeline.get((r["family"], r["seed"]), float("nan"))
    print(f"optimal online / offline RMSE after {args.skip:g} s, median (range) over seeds; "
          f"vision {readout_latency_s(1 / 30):.2f} s late online / on time:")
    print("| family | " + " | ".join(f"{m} online | {m} on time" for m in names)
          + (" | pipeline |" if pipeline else " |"))
    print("|---|" + "---|---|" * len(names) + ("---|" if pipeline else ""))
    for fam in families + ["all"]:
        sel = [r for r in rows if fam in ("all", r["family"])]
        cells = [f"{_summary([r for r in sel if r['model'] == m], 'online_ratio')} | "
                 f"{_summary([r for r in sel if r['model'] == m], 'filter_ratio')}" for m in names]
        if pipeline:
            cells.append(_summary([r for r in sel if r["model"] == names[0]], "pipeline_ratio"))
        print(f"| {fam} | " + " | ".join(cells) + " |")
    print(f"\noptimal online / offline RMSE (m/s) after {args.skip:g} s, {names[0]} noise, {args.priors} priors, "
          f"median (range) over seeds:")
    print("| family | online | offline |\n|---|---|---|")
    for fam in families:
        sel = [r for r in rows if r["family"] == fam and r["model"] == names[0]]
        print(f"| {fam} | {_summary(sel, 'online', 3)} | {_summary(sel, 'offline', 3)} |")
    if args.plot:
        print(f"wrote {plot_ratios(rows, families, names, args.plot)}")
    _write(args, rows, {m: asdict(models[m]) for m in names})
    return 0


def _write(args, rows, models) -> None:
    from .store import provenance, write_text

    if args.out:
        doc = dict(rows=rows, models=models, provenance=provenance(json.dumps(vars(args))))
        write_text(args.out, json.dumps(doc, indent=1))
        print(f"wrote {args.out}")


def footage_rows(paths, front_end: str = "dis", skip_s: float = 2.0, priors: str = "model") -> list[dict]:
    """One row per footage: κ's error against the truth (:func:`kappa_noise` at 30 frames/s), and the optimal
    online and offline RMSE at that noise on the footage's own trajectory (:func:`online_offline`, vision as
    late as that front end's causal readout; ``priors`` as :func:`_with_priors` takes it)."""
    rows = []
    for path in paths:
        k = footage_kappa(path, front_end)
        noise = kappa_noise(k["t"], k["kappa"], k["v"], k["a"])
        model = InformationModel(kappa_rel_error=noise["kappa_rel_error"], kappa_abs_error=noise["kappa_abs_error"],
                                 accel_floor=noise["accel_floor"],
                                 latency_s=readout_latency_s(float(np.median(np.diff(k["t"]))), k["config"]))
        t = np.arange(k["t"][0], k["t"][-1], 1 / 30)  # the model's frames: 30 a second, as the noise is sized
        v, a = (np.interp(t, k["t"], k[x]) for x in ("v_raw", "a_raw"))
        rows.append(dict(footage=Path(path).name, front_end=k["front_end"], latency_s=model.latency_s, **noise,
                         **online_offline(t, v, a, _with_priors(model, priors, t, v), skip_s)))
    return rows


if __name__ == "__main__":
    sys.exit(main())
