"""``lobula figures --only emd_gaze``: the camera's EMD front end with and without its fixating gaze.

Under the suite's turns (3-axis, 3–5°, 0.3–1.5 Hz) a 30 frames/s image moves up to 1.6° a frame,
two ommatidial spacings at Δφ = 0.75°, and the correlators alias; the fixating gaze
(:func:`lobula.gaze.fixation_reference`, ``EMDFrontEndConfig.gaze``) warps each frame into a gaze
held by the integrated gyro first. This figure renders the suite's rotation, mixed and panels
families (:func:`experiments.suite.family_config`, 10 s at 320×240, the realistic IMU) for three
seeds and runs the causal pipeline with the EMD front end on the camera's own image (``gaze
"none"``), with the fixating gaze (the default), and with DIS, the default flow front end:
RMSE after 2 s and the share of the truth inside ±2σ, per seed.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: the runs compared: label -> (front end, EMD gaze or None)
CONFIGURATIONS = {"EMD, camera's image": ("emd", "none"), "EMD, fixating gaze": ("emd", "fixate"),
                  "DIS": ("dis", None)}


def _config(front_end: str, gaze: str | None):
    from lobula.config import VelocityConfig

    cfg = VelocityConfig(front_end=front_end)
    cfg.readout.filter = "causal"
    if gaze is not None:
        cfg.emd.gaze = gaze
    return cfg


def coverage(ds, skip_s: float = 2.0) -> float:
    """Share of the observable steps after ``skip_s`` with the truth inside v̂ ± 2·v_std."""
    t, v, vt, s = (ds[k].values for k in ("time", "v_hat", "v_true", "v_std"))
    answered = ds.observable.values.astype(bool) if "observable" in ds else np.isfinite(v)
    k = (t >= t[0] + skip_s) & answered & np.isfinite(s)
    return float(np.mean(np.abs(v[k] - vt[k]) <= 2 * s[k])) if k.any() else float("nan")


def gaze_numbers(workdir, seeds=(0, 1, 2), families=("rotation", "mixed", "panels"), duration_s: float = 10.0,
                 progress: bool = False):
    """Render (cached in ``workdir``) and score every family × seed × configuration.

    Returns (numbers, traces): numbers[family][label] = dict(rmse=[per seed], coverage=[per seed]);
    traces: the first family's first seed, {label: (t, v_hat)} plus "truth"."""
    from experiments.suite import family_config
    from experiments.velocity import score
    from lobula.velocity import estimate_velocity
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    workdir = Path(workdir)
    numbers, traces = {}, {}
    for fam in families:
        numbers[fam] = {label: dict(rmse=[], coverage=[]) for label in CONFIGURATIONS}
        for seed in seeds:
            folder = workdir / f"{fam}-{seed}"
            if not (folder / "frames.csv").exists():
                make_track_run(folder, family_config(fam, seed, duration_s, 0.5), progress=progress)
            fo = open_footage(folder)
            for label, (fe, gaze) in CONFIGURATIONS.items():
                ds = estimate_velocity(fo, _config(fe, gaze), progress=False)
                numbers[fam][label]["rmse"].append(score(ds)["rmse_m_s"])
                numbers[fam][label]["coverage"].append(coverage(ds))
                if fam == families[0] and seed == seeds[0]:
                    traces[label] = (ds.time.values, ds.v_hat.values)
                    traces["truth"] = (ds.time.values, ds.v_true.values)
            if progress:
                print(f"  {fam} seed {seed}: " + ", ".join(f"{k} {v['rmse'][-1]:.3f}" for k, v in numbers[fam].items()),
                      flush=True)
    return numbers, traces


def plot_emd_gaze(numbers: dict, traces: dict, png, trace_label: str = "") -> Path:
    """v̂ against truth on one world (left) and RMSE per family, configuration and seed (right, log axis)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from experiments.store import save_figure

    colours = {"EMD, camera's image": "tab:red", "EMD, fixating gaze": "tab:blue", "DIS": "tab:green"}
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.4), gridspec_kw=dict(width_ratios=[1.3, 1]))
    t, v = traces["truth"]
    ax.plot(t, v, "k--", lw=1.4, label="truth")
    for label, c in colours.items():
        tt, vv = traces[label]
        ax.plot(tt, vv, color=c, lw=1.2, label=label)
    ax.axvspan(t[0], t[0] + 2.0, color="0.9", lw=0)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("forward velocity (m/s)")
    ax.set_title(f"causal v̂ against truth, {trace_label} (grey: first 2 s, not scored)", fontsize=9)
    ax.legend(fontsize=8, loc="best")
    fams = list(numbers)
    labels = list(colours)
    width = 0.8 / len(labels)
    for i, label in enumerate(labels):
        x = np.arange(len(fams)) + (i - (len(labels) - 1) / 2) * width
        vals = [np.array(numbers[f][label]["rmse"]) for f in fams]
        cov = [np.nanmean(numbers[f][label]["coverage"]) for f in fams]
        bx.bar(x, [v.mean() for v in vals], width, color=colours[label], alpha=0.5, label=label)
        for xi, v, c in zip(x, vals, cov):
            bx.plot(np.full(len(v), xi), v, "k.", ms=4)
            bx.text(xi, v.max() * 1.15, f"{100 * c:.0f}%", ha="center", fontsize=6)
    bx.set_xticks(np.arange(len(fams)), fams)
    bx.set_yscale("log")
    highest = np.nanmax([np.nanmax(numbers[f][label]["rmse"]) for f in fams for label in labels
                         if np.isfinite(numbers[f][label]["rmse"]).any()])
    bx.set_ylim(top=highest * 2.0)  # room for the coverage labels above the highest seed
    bx.set_ylabel("causal RMSE after 2 s (m/s, log)")
    n = len(next(iter(numbers[fams[0]].values()))["rmse"])
    bx.set_title(f"{n} seeds each (bar: mean, dots: seeds, label: truth within ±2σ)", fontsize=9)
    bx.grid(True, axis="y", which="both", alpha=0.25)
    bx.legend(fontsize=7, loc="upper right")
    fig.suptitle("The camera's EMD front end (Δφ = 0.75°, 30 frames/s) under the suite's turns: "
                 "its own image against a gaze fixated by the integrated gyro", fontsize=10)
    fig.tight_layout()
    save_figure(fig, png, dpi=150)
    plt.close(fig)
    return Path(png)


def figure_emd_gaze(out, cache, seeds=(0, 1, 2), families=("rotation", "mixed", "panels"), duration_s: float = 10.0,
                    progress: bool = False):
    """Make ``emd_gaze.png`` in ``out`` (renders cached under ``cache/gaze_runs``); returns (png, numbers)."""
    numbers, traces = gaze_numbers(Path(cache) / "gaze_runs", seeds, families, duration_s, progress)
    png = plot_emd_gaze(numbers, traces, Path(out) / "emd_gaze.png", f"{families[0]} seed {seeds[0]}")
    return png, numbers
