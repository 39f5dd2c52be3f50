"""``lobula figures``: the hypothesis figures, each saved with the command and configuration that made it.

One synthetic replay of the real FLIVVER trajectory is rendered once (cached in the
output folder) and every figure is computed from it, deterministically (seeded scene,
seeded IMU, seeded spikes; OpenCV DIS is deterministic). Each figure NAME gets
``NAME.png`` and ``NAME.json`` (command, configuration, the numbers plotted, version).

1. ``replay_emd_vs_dis`` — v̂ against truth for the EMD and DIS front ends.
2. ``rmse_vs_field_size`` — RMSE against receptive-field size (and so field count).
3. ``rmse_vs_dphi`` — RMSE against lattice resolution Δφ (EMD front end).
4. ``rmse_vs_tau_contrast_noise`` — RMSE against EMD delay τ for several stimulus contrasts,
   the contrast changed on noise-free renders and the sensor noise added after it, so the
   front end's contrast invariance is tested, not built in; 3 replay seeds
   (:mod:`experiments.contrast_figure`).
5. ``error_vs_acceleration`` — |error| and observability against |a|: where velocity
   becomes unobservable, and that the readout says so (the paper's readout does not).
6. ``rate_vs_spiking`` — readout-neuron RMSE against output firing rate and population size.
7. ``replay_velocity`` — the default pipeline (DIS, zero-phase) on the replay, with truth.
8. ``eye_rmse`` (only with ``--only eye_rmse``) — the fly's compound eye against causal DIS on the
   panels, rotation and corridor worlds, against LC field size and rotation handling
   (:func:`experiments.eye_figures.figure_eye`).
9. ``eye_rate_vs_spiking`` (only by name) — the eye's causal RMSE with rate readout, spiking output
   neurons (1–30 pairs) and the shunting readout neuron, beside causal DIS, 3 worlds × 3 seeds
   (:mod:`experiments.eye_figures`; ~2 min on cached renders).
   ``eye_rmse_vs_dphi_fov`` (only by name) — the eye's RMSE against Δφ and field of view.
10. ``emd_gaze`` (only by name) — the camera's EMD front end on its own image and with the fixating
   gaze, beside DIS, on the suite's rotation, mixed and panels families × 3 seeds
   (:mod:`experiments.gaze_figure`; ~10 min with the renders).
"""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lobula.version import command_line, provenance_attrs
from lobula.config import VelocityConfig
from lobula.readout import ReadoutConfig, answered_velocity, readout
from lobula.readout_neuron import ReadoutNeuronConfig, readout_neuron
from lobula.readers import open_footage

FIGURES = ("replay_emd_vs_dis", "rmse_vs_field_size", "rmse_vs_dphi", "rmse_vs_tau_contrast_noise",
           "error_vs_acceleration", "rate_vs_spiking", "replay_velocity")
#: made only when asked for by name (``--only eye_rmse``): it renders 9 fly-eye runs (CPU-minutes each)
EXTRA_FIGURES = ("eye_rmse", "eye_rate_vs_spiking", "eye_rmse_vs_dphi_fov", "emd_gaze", "fly_flight")
#: the fly-eye figures of experiments.eye_figures: name -> (function, what the record says it shows)
EYE_FIGURES = {
    "eye_rate_vs_spiking": ("figure_eye_rate_vs_spiking", "causal fly-eye RMSE: rate readout, spiking output neurons "
                            "(N pairs), shunting readout neuron; causal DIS and the zero estimator (3 seeds per world, "
                            "10 s)"),
    "eye_rmse_vs_dphi_fov": ("figure_eye_dphi_fov", "causal fly-eye RMSE against Δφ (=Δρ) and field of view (LC fields "
                             "over both eyes or only in the D435i's view), beside causal DIS (3 seeds per world, 10 s)"),
}


def _rmse(ds, skip_s=2.0):
    from experiments.velocity import score
    s = score(ds, skip_s)
    return s["rmse_m_s"], s["observable_fraction"]


def _save(fig, name, out: Path, record: dict):
    from experiments.store import save_figure
    import matplotlib.pyplot as plt
    save_figure(fig, out / f"{name}.png", provenance={k: v for k, v in record.items() if k != "results"}, dpi=150)
    plt.close(fig)
    _save_record(name, out, record)


def _save_record(name, out: Path, record: dict):
    from experiments.store import write_text

    write_text(out / f"{name}.json",
               json.dumps(record, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def make_replay(out: Path, start_s: float, duration_s: float, seed: int, progress: bool) -> tuple[Path, str]:
    """Render (once; cached) the replay the figures share; returns its folder and a label of its profile."""
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run, recorded_profile

    real = recorded_profile()
    label = "real FLIVVER trajectory (velocity.csv)" if real else "built-in profile (stimuli.track.builtin_profile)"
    folder = out / f"replay_{'real' if real else 'builtin'}_{start_s:g}_{duration_s:g}_seed{seed}"
    if not (folder / "frames.csv").exists():
        cfg = TrackRunConfig(profile=str(real) if real else None, start_s=start_s, duration_s=duration_s,
                             scale=0.5, scene=SceneConfig(seed=seed))
        make_track_run(folder, cfg, progress=progress)
    return folder, label


def _fig_replay_emd_vs_dis(dis, emd, profile, base, out):
    """``replay_emd_vs_dis``: v̂ (m/s) against truth for the DIS and EMD replays; returns its record."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5), layout="constrained")
    t = dis.time.values
    ax.plot(t, dis.v_true, "k--", lw=1.2, label="truth")
    nums = {}
    for name, ds, col in (("DIS", dis, "tab:blue"), ("EMD", emd, "m")):
        r, o = _rmse(ds)
        nums[name] = dict(rmse_m_s=r, observable=o)
        ax.plot(ds.time, ds.v_hat, color=col, lw=1.5, label=f"{name}: RMSE {r:.4f} m/s")
    ax.set(xlabel="time (s)", ylabel="forward velocity (m/s)",
           title=f"Replay ({profile.split(' (')[0]}): EMD and DIS front ends, same readout")
    ax.legend(fontsize=8)
    record = dict(base, what="v̂ against truth, EMD and DIS front ends",
                  configs={k: json.loads(v.attrs["config"]) for k, v in (("dis", dis), ("emd", emd))},
                  results=nums)
    _save(fig, "replay_emd_vs_dis", out, record)
    return record


def _fig_rmse_vs_field_size(run, quick, base, out):
    """``rmse_vs_field_size``: RMSE (m/s) against receptive-field size (deg) on DIS; returns its record."""
    import matplotlib.pyplot as plt

    sizes = [3.0, 5.0, 10.0] if quick else [2.0, 3.0, 5.0, 7.5, 10.0, 15.0]
    res = []
    for s in sizes:
        cfg = VelocityConfig()
        cfg.fields.size_deg = s
        ds = run(f"dis_field{s}", cfg)
        res.append((s, ds.sizes["field"], *_rmse(ds)))
    res = np.array(res)
    fig, ax = plt.subplots(figsize=(6, 4), layout="constrained")
    ax.plot(res[:, 0], res[:, 2], "o-")
    for s, n, r, _ in res:
        ax.annotate(f"{int(n)} fields", (s, r), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set(xlabel="receptive-field size (deg)", ylabel="velocity RMSE (m/s)",
           title="RMSE against receptive-field size (DIS, tiling the view)")
    record = dict(base, what="RMSE vs field size and count",
                  results=dict(size_deg=res[:, 0], n_fields=res[:, 1], rmse_m_s=res[:, 2], observable=res[:, 3]))
    _save(fig, "rmse_vs_field_size", out, record)
    return record


def _fig_rmse_vs_dphi(run, quick, base, out):
    """``rmse_vs_dphi``: RMSE (m/s) against lattice resolution Δφ (deg) on the EMD front end; returns its record."""
    import matplotlib.pyplot as plt

    dphis = [0.75, 1.5] if quick else [0.5, 0.75, 1.0, 1.5, 2.0, 3.0]
    res = []
    for d in dphis:
        cfg = VelocityConfig(front_end="emd")
        cfg.emd.lattice = replace(cfg.emd.lattice, dphi_deg=d)
        ds = run(f"emd_dphi{d}", cfg)
        res.append((d, *_rmse(ds)))
    res = np.array(res)
    fig, ax = plt.subplots(figsize=(6, 4), layout="constrained")
    ax.plot(res[:, 0], res[:, 1], "o-", color="m")
    ax.set(xlabel="interommatidial angle Δφ (deg; Δρ = Δφ)", ylabel="velocity RMSE (m/s)",
           title="RMSE against lattice resolution (EMD front end, 5° fields)")
    record = dict(base, what="RMSE vs Δφ", results=dict(dphi_deg=res[:, 0], rmse_m_s=res[:, 1], observable=res[:, 2]))
    _save(fig, "rmse_vs_dphi", out, record)
    return record


def _fig_error_vs_acceleration(dis, base, out):
    """``error_vs_acceleration``: median |error| (m/s) and the informative fraction per |a| bin (m/s²) of
    the DIS replay, our readout against the paper's; returns its record."""
    import matplotlib.pyplot as plt

    t, r, r2, a = dis.time.values, dis.r.values, dis.r2.values, dis.accel.values
    vt = dis.v_true.values
    ours = readout(t, r, r2, a, ReadoutConfig())
    paper = readout(t, r, r2, a, ReadoutConfig.paper())
    meas = ours.measurement  # the single-frame vision measurement, before the Kalman filter
    edges = np.array([0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0])
    absa = np.abs(a)
    keep = t > t[0] + 2
    rows = []
    answered = answered_velocity(ours)
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = keep & (absa >= lo) & (absa < hi)
        if m.sum() < 5:
            continue
        err = lambda v: float(np.nanmedian(np.abs(v - vt)[m])) if np.isfinite(v[m]).any() else np.nan
        rows.append((0.5 * (lo + hi), m.sum(), err(answered), err(paper.measurement),
                     float(np.isfinite(meas[m]).mean()), err(meas)))
    rows = np.array(rows)
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6.5, 6), sharex=True, layout="constrained")
    ax.plot(rows[:, 0], rows[:, 3], "s-", color="tab:orange", label="paper: per-frame median of v_f")
    ax.plot(rows[:, 0], rows[:, 5], "^-", color="tab:green", label="ours: per-frame vision measurement")
    ax.plot(rows[:, 0], rows[:, 2], "o-", color="m", label="ours: after haltere integration (v̂)")
    ax.set_yscale("log")
    ax.set(ylabel="median |error| (m/s)", title="Velocity error against |acceleration| (DIS, replay)")
    ax.legend(fontsize=7)
    ax2.bar(rows[:, 0], rows[:, 4], width=np.diff(edges)[:len(rows)] * 0.8, color="tab:green", alpha=0.6)
    ax2.set(xlabel="|a| bin centre (m/s²)", ylabel="fraction of frames with\na vision measurement", ylim=(0, 1.05))
    record = dict(base, what="median |error| and informative fraction per |a| bin",
                  results=dict(a_bin_centre=rows[:, 0], n=rows[:, 1], v_hat_error=rows[:, 2], paper_error=rows[:, 3],
                               informative_fraction=rows[:, 4], measurement_error=rows[:, 5]))
    _save(fig, "error_vs_acceleration", out, record)
    return record


def _fig_rate_vs_spiking(emd, quick, seed, base, out):
    """``rate_vs_spiking``: the readout neuron's RMSE (m/s) on the EMD replay against its firing rate (Hz)
    and the number of LC fields it pools; returns its record."""
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    t, r, r2, a, vt = emd.time.values, emd.r.values, emd.r2.values, emd.accel.values, emd.v_true.values
    keep = t > t[0] + 2
    gains = [50.0, 200.0] if quick else [20.0, 50.0, 100.0, 200.0, 500.0]
    sizes = [10, 70] if quick else [5, 10, 20, 40, 70]
    rng = np.random.default_rng(seed)
    rm = lambda v: float(np.sqrt(np.nanmean((v - vt)[keep] ** 2)))
    rate_rmse = rm(readout_neuron(t, r, r2, a)["v_hat"])
    spk = [rm(readout_neuron(t, r, r2, a, ReadoutNeuronConfig(spiking=True, gain_hz_per_m_s=g, seed=seed))["v_hat"])
           for g in gains]
    pop_rate, pop_spk = [], []
    for n in sizes:
        idx = np.sort(rng.choice(r.shape[1], size=min(n, r.shape[1]), replace=False))
        pop_rate.append(rm(readout_neuron(t, r[:, idx], r2[:, idx], a)["v_hat"]))
        pop_spk.append(rm(readout_neuron(t, r[:, idx], r2[:, idx], a, ReadoutNeuronConfig(spiking=True, seed=seed))["v_hat"]))
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    ax.plot(np.array(gains) * 0.3, spk, "o-", color="tab:red", label="spiking (Poisson)")
    ax.axhline(rate_rmse, color="m", ls="--", label="rate neuron")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set(xlabel="readout firing rate at 0.3 m/s (Hz)", ylabel="velocity RMSE (m/s)",
           title="Readout neuron: firing rate")
    ax.legend(fontsize=8)
    ax2.plot(sizes, pop_rate, "o-", color="m", label="rate")
    ax2.plot(sizes, pop_spk, "s-", color="tab:red", label="spiking")
    ax2.set(xlabel="LC fields converging on the readout", ylabel="velocity RMSE (m/s)",
            title="Readout neuron: population size (EMD replay)")
    ax2.legend(fontsize=8)
    record = dict(base, what="readout neuron RMSE vs firing rate and population size",
                  results=dict(gain_hz_per_m_s=gains, spiking_rmse=spk, rate_rmse=rate_rmse,
                               population=sizes, population_rate_rmse=pop_rate,
                               population_spiking_rmse=pop_spk),
                  neuron=ReadoutNeuronConfig().to_dict())
    _save(fig, "rate_vs_spiking", out, record)
    return record


def _figures_of_their_own_worlds(which, out: Path, cache: Path, base: dict, seed: int, quick: bool, progress: bool,
                                 records: dict) -> None:
    """The figures that render their own worlds (eye, gaze, contrast modules): each made, its record saved
    and put in ``records``."""
    if "eye_rmse" in which:
        from experiments.eye_figures import figure_eye

        figure_eye(out, seeds=(seed, seed + 1, seed + 2), workdir=cache / "eye_runs")
        numbers = json.loads((out / "eye_rmse.json").read_text())
        records["eye_rmse"] = dict(base, what="causal fly-eye RMSE against LC field size and rotation handling, "
                                   "beside causal DIS and the zero estimator (3 seeds per world, 10 s)",
                                   results=numbers)
        _save_record("eye_rmse", out, records["eye_rmse"])

    for name, (func, what) in EYE_FIGURES.items():  # each renders its own 3 worlds × 3 seeds
        if name in which:
            import experiments.eye_figures as eye_figures

            t0 = time.perf_counter()
            _, numbers = getattr(eye_figures, func)(out, seeds=(seed, seed + 1, seed + 2), workdir=cache / "eye_runs")
            records[name] = dict(base, what=what, results=numbers, seconds=round(time.perf_counter() - t0, 1))
            _save_record(name, out, records[name])

    if "emd_gaze" in which:
        from experiments.gaze_figure import figure_emd_gaze

        t0 = time.perf_counter()
        _, numbers = figure_emd_gaze(out, cache, seeds=(seed, seed + 1, seed + 2), progress=progress)
        records["emd_gaze"] = dict(base, what="causal RMSE and ±2σ coverage of the camera's EMD front end on its own "
                                   "image and with the fixating gaze, beside DIS (suite families rotation, mixed, "
                                   "panels; 3 seeds, 10 s, 320×240)", results=numbers,
                                   seconds=round(time.perf_counter() - t0, 1))
        _save_record("emd_gaze", out, records["emd_gaze"])

    if "fly_flight" in which:  # four figures, each with its own record (experiments.fly_flight_figures)
        from experiments.fly_flight_figures import write_fly_flight

        t0 = time.perf_counter()
        for name, record in write_fly_flight(out, workdir=cache / "fly_flight_runs", seeds=(seed, seed + 1),
                                             progress=progress).items():
            records[name] = dict(record, seconds=round(time.perf_counter() - t0, 1))

    if "rmse_vs_tau_contrast_noise" in which:
        from experiments.contrast_figure import figure_contrast_noise

        t0 = time.perf_counter()
        kw = dict(taus=(0.005, 0.035), contrasts=(1.0, 0.25), duration_s=6.0) if quick else {}
        _, numbers = figure_contrast_noise(out, cache, seeds=(seed, seed + 1, seed + 2), **kw)
        records["rmse_vs_tau_contrast_noise"] = dict(base, what="RMSE vs EMD τ and contrast; sensor noise added "
                                                     "after the contrast change (noise-free renders)",
                                                     results=numbers, seconds=round(time.perf_counter() - t0, 1))
        _save_record("rmse_vs_tau_contrast_noise", out, records["rmse_vs_tau_contrast_noise"])


#: s: the shortest replay the replay's figures are drawn from (2 s skipped, then enough frames per |a| bin)
MIN_REPLAY_S = 6.0


#: s: the replay's window in the recorded trajectory by default (`lobula figures --start/--duration`)
REPLAY_START_S, REPLAY_DURATION_S = 5.0, 25.0


def run_figures(out: str | Path = "figures", which=FIGURES, start_s: float = REPLAY_START_S,
                duration_s: float = REPLAY_DURATION_S, seed: int = 0, quick: bool = False, progress: bool = True) -> dict:
    """Make the figures into ``out``; returns {name: record}. ``quick`` uses coarse grids (for tests)."""
    import matplotlib
    matplotlib.use("Agg")

    from lobula.velocity import estimate_velocity

    if set(which) - set(EXTRA_FIGURES) and not duration_s >= MIN_REPLAY_S:
        raise ValueError(f"--duration {duration_s:g} s: the replay's figures score it after its first 2 s and bin the "
                         f"rest by |a|; give at least {MIN_REPLAY_S:g} s")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / ".cache"
    if set(which) - set(EXTRA_FIGURES):  # the shared replay; the extra figures render their own worlds
        replay, profile = make_replay(cache, start_s, duration_s, seed, progress)
        fo = open_footage(replay)
    else:
        profile, fo = "not used (this figure renders its own worlds)", None
    command = command_line() if command_line().startswith("lobula figures") \
        else f"lobula figures --out {out} --start {start_s} --duration {duration_s} --seed {seed}"
    base = dict(provenance_attrs(), command=command,
                replay=dict(start_s=start_s, duration_s=duration_s, seed=seed, profile=profile), quick=quick)
    records = {}
    runs = {}

    def run(key, cfg, footage=fo):
        if key not in runs:
            t0 = time.perf_counter()
            runs[key] = estimate_velocity(footage, cfg, progress=False)
            if progress:
                print(f"  {key}: {time.perf_counter() - t0:.1f} s", flush=True)
        return runs[key]

    if {"replay_emd_vs_dis", "error_vs_acceleration", "rate_vs_spiking", "replay_velocity"} & set(which):
        dis, emd = run("dis", VelocityConfig()), run("emd", VelocityConfig(front_end="emd"))
    if "replay_emd_vs_dis" in which:
        records["replay_emd_vs_dis"] = _fig_replay_emd_vs_dis(dis, emd, profile, base, out)
    if "rmse_vs_field_size" in which:
        records["rmse_vs_field_size"] = _fig_rmse_vs_field_size(run, quick, base, out)
    if "rmse_vs_dphi" in which:
        records["rmse_vs_dphi"] = _fig_rmse_vs_dphi(run, quick, base, out)
    if "error_vs_acceleration" in which:
        records["error_vs_acceleration"] = _fig_error_vs_acceleration(dis, base, out)
    if "rate_vs_spiking" in which:
        records["rate_vs_spiking"] = _fig_rate_vs_spiking(emd, quick, seed, base, out)

    if "replay_velocity" in which:
        from experiments.velocity import plot_velocity, score

        plot_velocity(dis, out / "replay_velocity.png", title=f"Default pipeline on the replay ({profile})")
        records["replay_velocity"] = dict(base, what="v̂ with its ±2σ band against truth, default pipeline (DIS, zero-phase)",
                                          config=json.loads(dis.attrs["config"]), results=score(dis, 2.0))
        _save_record("replay_velocity", out, records["replay_velocity"])

    _figures_of_their_own_worlds(which, out, cache, base, seed, quick, progress, records)
    return records


def add_parser(subparsers):
    """Register ``lobula figures`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_figures_parser`'s, built without importing this module."""
    from .parsers import add_figures_parser

    return add_figures_parser(subparsers)


def main(args) -> int:
    which = tuple(args.only or FIGURES)
    if set(which) <= set(EXTRA_FIGURES):  # these render their own worlds at their own sizes and grids
        given = [o for o, on in (("--start", args.start != REPLAY_START_S),
                                 ("--duration", args.duration != REPLAY_DURATION_S), ("--quick", args.quick)) if on]
        if given:
            raise ValueError(f"{', '.join(given)} set{'s' if len(given) == 1 else ''} the replay's figures; "
                             f"{', '.join(which)} {'renders its' if len(which) == 1 else 'render their'} own worlds: drop "
                             f"{'it' if len(given) == 1 else 'them'}")
    recs = run_figures(args.out, which, args.start, args.duration, args.seed, args.quick,
                       progress=not args.quiet)
    for name in recs:
        print(f"wrote {Path(args.out) / name}.png and .json")
    return 0
