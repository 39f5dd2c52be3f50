"""Could a fly do it? The compound eye on fly flight: figures against Δφ, flight and motion detector.

Scenes: the accuracy suite's ``saccadic`` family (:func:`experiments.suite_scene.family_config`: panels on
even seeds, corridor on odd ones; the flight draws its own speed, 0.1–1 m/s), flown four ways
(:data:`FLIGHTS`), each the same world, flight seed and IMU:

* ``turning`` — the same kind of flight with every turn spread over 0.4–0.8 s (peak yaw rate 2A/d at
  most 240 °/s, under the saccade gate's 300 °/s): continuous turning, never suppressed;
* ``saccadic`` — body saccades of 20–90° in 50–100 ms (800–1800 °/s at the peak) and the flight's
  ±1.5° wobble on three axes (2–8 Hz);
* ``saccadic, gaze`` — the same flight seen by a gaze-stabilised head (:class:`lobula.gaze.GazeConfig`,
  the haltere-driven neck reflex);
* ``saccadic, no wobble`` — the same saccades with the wobble's amplitude 0 (the wobble's random draws are
  the plan's last, so the segments and saccades are the same).

Each is ray-cast onto two compound eyes at Δφ = Δρ in :data:`DPHIS` (500 Hz, cast at 250 Hz) and read by
the eye's causal pipeline (:func:`experiments.eye_velocity.estimate_eye_velocity`, the readout's rates, haltere rotation
handling with the learned gain, saccadic suppression on) with the Hassenstein–Reichardt detector or the
three-arm detector (:mod:`lobula.three_arm`); causal DIS on the D435i camera (320×240) of the same world and
flight is the reference. Scores after 2 s (:func:`flight_scores`): the RMSE where the eye answers, the
fraction of frames outside saccades where it answers, the RMSE of its posterior mean on every frame outside
saccades, and the lock-on time (:func:`experiments.suite_metrics.lock_on_time`).

Figures (:func:`figure_fly_flight`): ``fly_flight_dphi`` (RMSE and answered fraction against Δφ per flight,
HR), ``fly_flight_detector`` (HR against the three-arm detector on the same flights), ``fly_flight_lock_on``
(lock-on time from the start of the flight) and ``fly_flight_fov`` (HR with its LC fields over both eyes or only
inside the D435i's view, :data:`FIELDS_OF_VIEW`), each with its JSON of every seed's numbers
(:func:`write_fly_flight`; ``python -m experiments.fly_flight_figures --out figures``, about 2½ h on 2 cores with the
renders). Renders and scores are cached in a work folder (``FLIGHT-SEED-dDPHI-eye``,
``FLIGHT-SEED-cam``, ``scores.json``).
"""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["FLIGHTS", "FIGURE_FLIGHTS", "DPHIS", "FIELDS_OF_VIEW", "DETECTORS", "flight_run_config", "eye_dir", "cam_dir",
           "ensure_flight_runs", "flight_scores", "eye_scores", "posterior_mean", "dis_scores", "fly_flight_numbers",
           "plot_fly_flight", "figure_fly_flight", "write_fly_flight"]

#: flight name -> (FlightConfig overrides, gaze-stabilised head)
FLIGHTS = {
    "turning": (dict(saccade_s=(0.4, 0.8), saccade_jitter_s=0.05), False),
    "saccadic": ({}, False),
    "saccadic, gaze": ({}, True),
    "saccadic, no wobble": (dict(wobble_deg=(0.0, 0.0, 0.0)), False),
}
#: the flights the figures compare (the no-wobble flight answers why the eye fails between saccades)
FIGURE_FLIGHTS = ("turning", "saccadic", "saccadic, gaze")
#: interommatidial angles Δφ = Δρ (deg)
DPHIS = (1.0, 2.0, 3.5, 5.0, 6.0)
#: fields of view the HR eye is read with: LC fields over both eyes, or only inside the D435i's view
FIELDS_OF_VIEW = ("both eyes", "frontal")
#: motion detectors (EyeCircuitConfig.detector)
DETECTORS = ("hr", "three-arm")
DURATION_S, SKIP_S, SCALE = 8.0, 2.0, 0.5
#: the world is ray-cast every second eye sample and interpolated (as ``lobula scene --eye fly``'s default
#: 250 Hz cast rate; docs/fly-eye.md: within 0.0001 m/s of casting every sample)
CAST_EVERY = 2


def _slug(flight: str) -> str:
    return flight.replace(", ", "-").replace(" ", "-")


def flight_run_config(flight: str, seed: int, duration_s: float = DURATION_S, scale: float = SCALE):
    """The :class:`stimuli.track.TrackRunConfig` of one flight (:data:`FLIGHTS`) and seed: the suite's
    ``saccadic`` scene of that seed with the flight's :class:`stimuli.flight.FlightConfig` overrides."""
    from experiments.suite_scene import family_config
    from stimuli.flight import FlightConfig

    overrides, _ = FLIGHTS[flight]
    cfg = family_config("saccadic", seed, duration_s, scale)
    return replace(cfg, flight_config=FlightConfig(**overrides)) if overrides else cfg


def eye_dir(workdir, flight: str, seed: int, dphi: float) -> Path:
    """The eye-footage folder of a flight, seed and Δφ (deg) in the work folder."""
    return Path(workdir) / f"{_slug(flight)}-{seed}-d{dphi:g}-eye"


def cam_dir(workdir, flight: str, seed: int) -> Path:
    """The pinhole footage of a flight and seed (a gaze-stabilised flight's camera is its body-fixed twin's)."""
    return Path(workdir) / f"{_slug(flight.replace(', gaze', ''))}-{seed}-cam"


def ensure_flight_runs(workdir, flights=FIGURE_FLIGHTS, seeds=(0, 1), dphis=DPHIS, duration_s: float = DURATION_S,
                       camera: bool = True, progress: bool = True) -> None:
    """Render (where absent) the eye footage of every flight × seed × Δφ (deg) and, with ``camera``, the
    pinhole footage of every flight × seed, into ``workdir``."""
    from lobula.compound_eye import CompoundEyeConfig
    from lobula.gaze import GazeConfig
    from stimuli.eye import make_eye_run
    from stimuli.track import make_track_run

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    for dphi in sorted(dphis, reverse=True):   # the coarse eyes first: they cost least
        for flight in flights:
            for seed in seeds:
                out = eye_dir(workdir, flight, seed, dphi)
                if not out.exists():
                    t0 = time.perf_counter()
                    make_eye_run(out, flight_run_config(flight, seed, duration_s), CompoundEyeConfig(dphi_deg=dphi),
                                 500.0, progress=False, cast_every=CAST_EVERY,
                                 gaze=GazeConfig() if FLIGHTS[flight][1] else None)
                    if progress:
                        print(f"  rendered {out.name}: {time.perf_counter() - t0:.0f} s", flush=True)
    if camera:
        for flight in flights:
            for seed in seeds:
                out = cam_dir(workdir, flight, seed)
                if not out.exists():
                    t0 = time.perf_counter()
                    make_track_run(out, flight_run_config(flight.replace(", gaze", ""), seed, duration_s),
                                   progress=False)
                    if progress:
                        print(f"  rendered {out.name}: {time.perf_counter() - t0:.0f} s", flush=True)


def flight_scores(ds, skip_s: float = SKIP_S) -> dict:
    """The scores of one eye (or camera) velocity Dataset after ``skip_s`` s, in m/s, fractions and s.

    ``rmse_answered``: RMSE where the readout answers (``observable``); ``answered``: the fraction of the
    frames outside saccades (``saccade``, where the Dataset has it) on which it answers; ``rmse_all``: RMSE
    of v̂ on every frame outside saccades where it is finite (:func:`eye_scores` and :func:`dis_scores` put
    the posterior mean there, also where the readout does not answer); ``coverage_2sigma``: truth within
    ±2·v_std on those frames; ``lock_on_s``: seconds from the start until
    the error of the answered v̂ stays within 0.05 m/s + 10 %·|v| for 1 s
    (:func:`experiments.suite_metrics.lock_on_time`; NaN: never); ``lock_on_all_s``: the same for v̂ wherever
    it is finite; ``zero``: the zero estimator's RMSE on the scored frames.
    """
    from experiments.suite_metrics import lock_on_time

    t = ds.time.values
    v, vt, obs = ds.v_hat.values, ds.v_true.values, ds.observable.values.astype(bool)
    sac = ds.saccade.values.astype(bool) if "saccade" in ds else np.zeros(len(t), bool)
    keep = (t >= t[0] + skip_s) & ~sac
    err = v - vt
    fin = keep & np.isfinite(err)
    ans = fin & obs
    sd = ds.v_std.values if "v_std" in ds else np.full(len(t), np.nan)
    with np.errstate(invalid="ignore"):
        cov = float(np.mean(np.abs(err[fin]) <= 2 * sd[fin])) if fin.any() else float("nan")
    rms = (lambda m: float(np.sqrt(np.mean(err[m] ** 2))) if m.any() else float("nan"))
    return dict(rmse_answered=rms(ans), answered=float(ans.sum() / max(1, keep.sum())), rmse_all=rms(fin),
                coverage_2sigma=cov, lock_on_s=lock_on_time(t, np.where(obs, err, np.nan), vt),
                lock_on_all_s=lock_on_time(t, err, vt),
                zero=float(np.sqrt(np.mean(vt[keep] ** 2))) if keep.any() else float("nan"))


def eye_scores(folder, detector: str = "hr", fov: str = "both eyes", **circuit) -> dict:
    """:func:`flight_scores` of the eye's causal pipeline (the readout's rates) on one eye footage folder, with
    the circuit's ``detector``, its LC fields over the field of view ``fov`` (:data:`FIELDS_OF_VIEW`;
    "frontal": :data:`experiments.eye_figures.FRONTAL_FIELDS`) and any other
    :class:`lobula.eye_circuit.EyeCircuitConfig` fields, plus the circuit's wall time (s)."""
    from experiments.eye_figures import FRONTAL_FIELDS
    from experiments.eye_velocity import EyeVelocityConfig, estimate_eye_velocity
    from stimuli.eye import open_eye_footage

    if fov not in FIELDS_OF_VIEW:
        raise ValueError(f"fov must be one of {', '.join(FIELDS_OF_VIEW)}, got {fov!r}")
    cfg = EyeVelocityConfig()
    cfg.circuit = replace(cfg.circuit, detector=detector, **circuit)
    if fov == "frontal":
        cfg.circuit = replace(cfg.circuit, fields=replace(cfg.circuit.fields, **FRONTAL_FIELDS))
    t0 = time.perf_counter()
    fo = open_eye_footage(folder)
    ds = estimate_eye_velocity(fo, cfg)
    out = flight_scores(ds)
    # The readout's posterior mean on every frame: the same filter on the same LC outputs, every step reported.
    full = ds.copy()
    full["v_hat"] = ("time", posterior_mean(fo, ds, cfg))
    every = flight_scores(full)
    for k in ("rmse_all", "coverage_2sigma", "lock_on_all_s"):
        out[k] = every[k]
    out["rotation"] = cfg.circuit.rotation
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def posterior_mean(fo, ds, cfg) -> np.ndarray:
    """(n,) m/s: the eye readout's posterior mean on every LC step of ``ds`` (the Dataset
    :func:`experiments.eye_velocity.estimate_eye_velocity` made from footage ``fo`` with ``cfg``), also where
    it does not answer: the same readout on the same gated LC outputs, its reporting bounds lifted (no std
    limit, no coupling test; neither changes the filter)."""
    from experiments.eye_velocity import readout_inputs, suppressed_readout
    from lobula.imu import turn_rate

    t = ds.time.values
    sac = ds.saccade.values.astype(bool)
    used = ds.field_used.values.astype(bool)
    rho = np.where(used & ~sac[:, None], ds.r.values, np.nan)
    r2 = np.where(used, ds.r2.values, np.nan)
    rcfg, tau, drift = readout_inputs(fo, t, cfg)
    rcfg = replace(rcfg, max_rel_std=1e9, coupling_z=0.0)
    dt = float(np.median(np.diff(t)))
    turn = None if cfg.accel_from_truth else turn_rate(t, fo.imu.time_s, fo.imu.gyro, dt)
    return suppressed_readout(t, rho, r2, ds.accel.values, rcfg, sac, gravity_tau=tau, drift_std=drift,
                              turn_rate=turn).info["posterior_mean"]


def dis_scores(folder) -> dict:
    """:func:`flight_scores` of causal DIS (the default pipeline, causal filter) on one pinhole footage folder,
    ``rmse_all`` and ``coverage_2sigma`` of its posterior mean on every frame (its reporting bounds lifted).
    Every frame after the skip counts: the camera's pipeline leaves a saccade's flow out
    (``VelocityConfig.saccade_gate_deg_s``) but its filter carries v̂ through the saccade and reports there."""
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from lobula.velocity import estimate_velocity

    fo = open_footage(folder)
    vc = VelocityConfig(front_end="dis")
    vc.readout.filter = "causal"
    out = flight_scores(estimate_velocity(fo, vc, progress=False))
    # Its posterior mean on every frame, as the eye's: the reporting bounds lifted (the filter is the same).
    vc.readout.max_rel_std, vc.readout.coupling_z = 1e9, 0.0
    every = flight_scores(estimate_velocity(fo, vc, progress=False))
    for k in ("rmse_all", "coverage_2sigma", "lock_on_all_s"):
        out[k] = every[k]
    return out


def fly_flight_numbers(workdir, flights=FIGURE_FLIGHTS, seeds=(0, 1), dphis=DPHIS, detectors=DETECTORS,
                       progress: bool = True) -> dict:
    """Every score the figures plot: {"eye": {flight: {detector: {Δφ: [per seed]}}}, "fov": {flight: {field of
    view: {Δφ: [per seed]}}} (HR), "dis": {flight: [per seed]}}, each entry :func:`flight_scores`' dict. Only the
    Δφ whose footage is in ``workdir`` for every flight and seed are scored (:func:`ensure_flight_runs` renders
    them); scores are cached in ``workdir/scores.json``."""
    workdir = Path(workdir)
    cache_path = workdir / "scores.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    have = [d for d in dphis if all(eye_dir(workdir, f, s, d).exists() for f in flights for s in seeds)]
    eye: dict = {}
    for flight in flights:
        for det in detectors:
            for dphi in have:
                for seed in seeds:
                    key = f"{eye_dir(workdir, flight, seed, dphi).name}|{det}"
                    if key not in cache:
                        cache[key] = eye_scores(eye_dir(workdir, flight, seed, dphi), det)
                        cache_path.write_text(json.dumps(cache, indent=1))
                        if progress:
                            print(f"  {key}: {cache[key]['wall_s']} s", flush=True)
                    eye.setdefault(flight, {}).setdefault(det, {}).setdefault(f"{dphi:g}", []).append(cache[key])
    fov: dict = {}
    for flight in flights:
        for view in FIELDS_OF_VIEW:
            for dphi in have:
                for seed in seeds:
                    name = eye_dir(workdir, flight, seed, dphi).name
                    key = f"{name}|hr" if view == "both eyes" else f"{name}|hr|{view}"
                    if key not in cache:
                        cache[key] = eye_scores(eye_dir(workdir, flight, seed, dphi), "hr", view)
                        cache_path.write_text(json.dumps(cache, indent=1))
                        if progress:
                            print(f"  {key}: {cache[key]['wall_s']} s", flush=True)
                    fov.setdefault(flight, {}).setdefault(view, {}).setdefault(f"{dphi:g}", []).append(cache[key])
    dis: dict = {}
    for flight in flights:
        for seed in seeds:
            key = f"{cam_dir(workdir, flight, seed).name}|dis"
            if key not in cache and cam_dir(workdir, flight, seed).exists():
                cache[key] = dis_scores(cam_dir(workdir, flight, seed))
                cache_path.write_text(json.dumps(cache, indent=1))
            if key in cache:
                dis.setdefault(flight, []).append(cache[key])
    return dict(eye=eye, fov=fov, dis=dis, seeds=list(seeds), dphis_deg=list(have), duration_s=DURATION_S,
                skip_s=SKIP_S)


COLOURS = {"turning": "tab:green", "saccadic": "tab:red", "saccadic, gaze": "tab:blue", "saccadic, no wobble": "tab:purple"}
DETECTOR_LABEL = {"hr": "HR correlator", "three-arm": "three-arm (HR × Barlow–Levick)"}


def _series(rows: dict, key: str):
    """Δφ (deg), mean, min, max and the seeds' values of score ``key`` over {Δφ: [per seed]}."""
    d = np.array(sorted(float(k) for k in rows))
    vals = [np.array([r[key] for r in rows[f"{x:g}"]], float) for x in d]
    mean = np.array([np.nanmean(v) if np.isfinite(v).any() else np.nan for v in vals])
    lo = np.array([np.nanmin(v) if np.isfinite(v).any() else np.nan for v in vals])
    hi = np.array([np.nanmax(v) if np.isfinite(v).any() else np.nan for v in vals])
    return d, mean, lo, hi, vals


def _plot_metric(ax, rows, key, colour, label, shift=0.0, ls="-", marker="o"):
    d, mean, lo, hi, vals = _series(rows, key)
    ax.errorbar(d + shift, mean, yerr=[mean - lo, hi - mean], color=colour, marker=marker, ms=5, capsize=3, ls=ls,
                label=label)
    for x, v in zip(d, vals):
        ax.plot(np.full(len(v), x + shift), v, ".", color=colour, ms=3, alpha=0.6)


def _variant_panels(rows, variants, dis_of, dphis, path, title, zero: bool = False) -> Path:
    """One column per flight of ``rows`` ({flight: {variant: {Δφ: [per seed]}}}): the RMSE of the posterior mean
    (top) and the frames answered (bottom) against Δφ (deg, ``dphis``), one line per variant of ``variants``
    ((key, label, line style, marker)) where the flight has it, causal DIS (``dis_of(flight)``: its scores)
    dashed and, with ``zero``, the zero estimator dotted; saved to ``path`` under ``title``."""
    import matplotlib.pyplot as plt

    from experiments.store import save_figure

    flights = list(rows)
    fig, axes = plt.subplots(2, len(flights), figsize=(3.8 * len(flights), 6.2), squeeze=False, sharex=True)
    for j, f in enumerate(flights):
        c = COLOURS.get(f, f"C{j}")
        for k, (key, label, ls, mk) in enumerate(variants):
            if key in rows[f]:
                for row, metric in enumerate(("rmse_all", "answered")):
                    _plot_metric(axes[row][j], rows[f][key], metric, c, label, shift=0.05 * (2 * k - 1), ls=ls,
                                 marker=mk)
        if dis_of(f):
            for row, metric in enumerate(("rmse_all", "answered")):
                axes[row][j].axhline(np.nanmean([r[metric] for r in dis_of(f)]), color="m", ls="--", lw=1,
                                     label="DIS on the D435i (causal)")
        if zero:
            axes[0][j].axhline(np.nanmean([r["zero"] for rows_d in rows[f][variants[0][0]].values() for r in rows_d]),
                               color="k", ls=":", lw=1, label="zero estimator")
        axes[0][j].set_title(f, fontsize=9)
        axes[0][j].set_ylim(bottom=0)
        axes[1][j].set_ylim(-0.03, 1.03)
        axes[1][j].set_xlabel("Δφ = Δρ (deg)")
        axes[1][j].set_xticks(dphis)
    axes[0][0].set_ylabel("RMSE of v̂, every frame (m/s)")
    axes[1][0].set_ylabel("frames answered")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(title, fontsize=8.5)
    fig.tight_layout()
    save_figure(fig, path, dpi=150)
    plt.close(fig)
    return path


def plot_fly_flight(numbers: dict, out_dir) -> list[Path]:
    """Draw ``fly_flight_dphi.png``, ``fly_flight_detector.png``, ``fly_flight_lock_on.png`` and, where the numbers
    hold the fields of view, ``fly_flight_fov.png`` from :func:`fly_flight_numbers`' ``numbers`` into ``out_dir``;
    returns their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from experiments.store import save_figure

    out_dir = Path(out_dir)
    eye, dis = numbers["eye"], numbers["dis"]
    flights = list(eye)
    n_seeds = len(numbers["seeds"])
    base = (f"{numbers['duration_s']:g} s flights, {n_seeds} seed{'' if n_seeds == 1 else 's'} (panels, corridor); "
            "causal, readout rates")
    sub = base + f", after {numbers['skip_s']:g} s,\nsaccades and their hold left out; bars: seeds' range, dots: seeds"
    dis_of = (lambda f: dis.get(f.replace(", gaze", ""), []))
    paths = []

    # (a) RMSE and answered fraction against Δφ, HR
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, f in enumerate(flights):
        c = COLOURS.get(f, f"C{k}")
        _plot_metric(axes[0], eye[f]["hr"], "rmse_all", c, f"fly eye, {f}", shift=0.1 * (k - 1))
        _plot_metric(axes[1], eye[f]["hr"], "answered", c, f"fly eye, {f}", shift=0.1 * (k - 1))
        if dis_of(f) and ", gaze" not in f:
            axes[0].axhline(np.nanmean([r["rmse_all"] for r in dis_of(f)]), color=c, ls="--", lw=1,
                            label=f"DIS on the D435i, {f} (causal)")
            axes[1].axhline(np.nanmean([r["answered"] for r in dis_of(f)]), color=c, ls="--", lw=1,
                            label=f"DIS on the D435i, {f} (causal)")
    zero = np.nanmean([r["zero"] for f in flights for rows in eye[f]["hr"].values() for r in rows])
    axes[0].axhline(zero, color="k", ls=":", label="zero estimator")
    axes[0].set_ylabel("RMSE of the posterior mean v̂, every frame (m/s)")
    axes[1].set_ylabel("frames answered (σ ≤ 0.1 m/s)")
    axes[1].set_ylim(-0.03, 1.03)
    for ax in axes:
        ax.set_xlabel("ommatidial spacing Δφ = Δρ (deg)")
        ax.set_xticks(numbers["dphis_deg"])
    axes[0].set_ylim(bottom=0)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle("Could a fly do it? Two compound eyes, HR detectors, against Δφ\n" + sub, fontsize=8.5)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    paths.append(out_dir / "fly_flight_dphi.png")
    save_figure(fig, paths[-1], dpi=150)
    plt.close(fig)

    # (b) HR against the three-arm detector
    paths.append(_variant_panels(
        eye, [(det, DETECTOR_LABEL[det], ls, mk) for det, ls, mk in (("hr", "-", "o"), ("three-arm", "--", "s"))],
        dis_of, numbers["dphis_deg"], out_dir / "fly_flight_detector.png",
        "HR correlator against the three-arm detector (τ = 35 ms both), same flights\n" + sub))

    # (c) lock-on time after take-off: on the answered frames, and for the posterior mean on every frame
    fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), sharex=True)
    never = numbers["duration_s"]
    for ax, key, what in ((axes[0], "lock_on_s", "answered v̂"), (axes[1], "lock_on_all_s", "posterior mean v̂")):
        labels = []
        for j, f in enumerate(flights):
            c = COLOURS.get(f, f"C{j}")
            for k, det in enumerate(d for d in DETECTORS if d in eye[f]):
                x = len(labels)
                labels.append(f"{f}\n{det}")
                spacings = sorted(eye[f][det], key=float)
                for i, dphi in enumerate(spacings):
                    v = np.array([r[key] for r in eye[f][det][dphi]], float)
                    ax.plot(np.full(len(v), x + 0.1 * (i - (len(spacings) - 1) / 2)), np.where(np.isfinite(v), v, never),
                            ls="none", marker="os^vPX"[i % 6], mfc="none" if det == "three-arm" else c, color=c,
                            label=f"Δφ {dphi}°" if j == 0 and k == 0 else None)
            if dis_of(f) and ", gaze" not in f:
                v = np.array([r[key] for r in dis_of(f)], float)
                labels.append(f"{f}\nDIS (camera)")
                ax.plot(np.full(len(v), len(labels) - 1), np.where(np.isfinite(v), v, never), "D", color="m",
                        label="DIS on the D435i" if j == 0 else None)
        ax.axhline(never, color="0.6", ls=":", lw=1)
        ticks = np.arange(0.0, never, 2.0)
        ax.set_yticks(list(ticks) + [never])
        ax.set_yticklabels([f"{x:g}" for x in ticks] + ["never"])
        ax.set_ylim(0, never * 1.1)
        ax.set_ylabel(f"lock-on (s), {what}", fontsize=8)
        ax.set_xticks(range(len(labels)))
        ax.set_xticklabels(labels, fontsize=6.5)
    axes[0].legend(fontsize=6.5, ncol=2, loc="lower left")
    fig.suptitle("Lock-on from the start of the flight: until |error| ≤ 0.05 m/s + 10 %·|v| for 1 s "
                 "(experiments.suite_metrics.lock_on_time)\n" + base + "; filled: HR, open: three-arm; "
                 "one marker per seed", fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "fly_flight_lock_on.png")
    save_figure(fig, paths[-1], dpi=150)
    plt.close(fig)

    # (d) the field of view: LC fields over both eyes against the D435i's view alone, HR
    if numbers.get("fov"):
        paths.append(_variant_panels(
            numbers["fov"], [("both eyes", "LC fields over both eyes", "-", "o"),
                             ("frontal", "LC fields in the D435i's 69°×42° only", "--", "s")],
            dis_of, numbers["dphis_deg"], out_dir / "fly_flight_fov.png",
            "The field of view: both eyes against the camera's view, HR detectors\n" + sub, zero=True))
    return paths


#: figure name -> what its record says it shows
FIGURE_WHAT = {
    "fly_flight_dphi": "fly eye (HR) on fly flight against Δφ: RMSE of the posterior mean and frames answered, "
                       "continuous turning, saccadic and gaze-stabilised saccadic flight, beside causal DIS",
    "fly_flight_detector": "HR correlator against the three-arm detector on the same flights and eyes",
    "fly_flight_lock_on": "lock-on time from the start of the flight per flight, detector and Δφ, on the answered "
                          "frames and for the posterior mean on every frame, beside causal DIS",
    "fly_flight_fov": "fly eye (HR) on fly flight against Δφ, its LC fields over both eyes or only inside the "
                      "D435i's view: RMSE of the posterior mean and frames answered, beside causal DIS",
}


def figure_fly_flight(out_dir, workdir=None, seeds=(0, 1), dphis=DPHIS, progress: bool = True) -> tuple[list, dict]:
    """Render (where absent) and score every flight, then draw the four figures into ``out_dir``;
    returns (their paths, the numbers)."""
    out_dir = Path(out_dir)
    workdir = Path(workdir) if workdir else out_dir / ".cache" / "fly_flight_runs"
    ensure_flight_runs(workdir, FIGURE_FLIGHTS, seeds, dphis, progress=progress)
    numbers = fly_flight_numbers(workdir, FIGURE_FLIGHTS, seeds, dphis, progress=progress)
    return plot_fly_flight(numbers, out_dir), numbers


def write_fly_flight(out_dir="figures", workdir=None, seeds=(0, 1), dphis=DPHIS, progress: bool = True) -> dict:
    """Make the four figures into ``out_dir``, each with ``NAME.json`` (command, provenance, what it shows, the
    numbers: every seed's scores); returns {name: record}."""
    from lobula.version import command_line, provenance_attrs

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    paths, numbers = figure_fly_flight(out_dir, workdir, seeds, dphis, progress)
    command = command_line() if "fly_flight_figures" in command_line() else \
        f"python -m experiments.fly_flight_figures --out {out_dir}"
    records = {}
    for p in paths:
        rec = dict(provenance_attrs(), command=command, what=FIGURE_WHAT[p.stem], flights={
            f: dict(flight_config=FLIGHTS[f][0], gaze=FLIGHTS[f][1]) for f in FIGURE_FLIGHTS},
            world="suite family 'saccadic' (experiments.suite_scene.family_config): panels on seed 0, corridor on 1",
            pipeline="experiments.eye_velocity.estimate_eye_velocity, defaults (rates, causal, haltere rotation "
                     "handling, saccade gate 300 deg/s); DIS: VelocityConfig(front_end='dis'), causal",
            results=numbers, seconds=round(time.perf_counter() - t0, 1))
        tmp = p.with_name(f".{p.stem}.json.tmp")
        tmp.write_text(json.dumps(rec, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
        tmp.replace(p.with_suffix(".json"))
        records[p.stem] = rec
    return records


def main(argv=None) -> int:
    """``python -m experiments.fly_flight_figures [--out figures] [--work DIR] [--seeds 0 1] [--dphi 1 2 3.5 5 6]``."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m experiments.fly_flight_figures", description=__doc__.split("\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--out", default="figures", help="folder for the PNGs and their JSON")
    ap.add_argument("--work", default=None, help="render cache; None: OUT/.cache/fly_flight_runs")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="flight seeds (even: panels, odd: corridor)")
    ap.add_argument("--dphi", type=float, nargs="+", default=list(DPHIS), help="Δφ = Δρ (deg)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    a = ap.parse_args(argv)
    for name in write_fly_flight(a.out, a.work, tuple(a.seeds), tuple(a.dphi), progress=not a.quiet):
        print(f"wrote {Path(a.out) / name}.png and .json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
