"""Figures of the fly's compound eye, each over ≥ 3 seeds with the spread shown.

``eye_rate_vs_spiking`` — on the worlds' families (panels, rotation, corridor; seeds 0–2, 10 s):
the causal velocity RMSE of the eye's circuit read out by (i) the arithmetic readout's rates,
(ii) the same v̂ carried by the eye's N push–pull output-neuron pairs (encoder lead) — Poisson
(N = 1, 3, 10, 30) or leaky integrate-and-fire (N = 1, 10; the eye's default) — and decoded
causally, (iii) the shunting readout neuron (rates and LIF spikes), beside causal DIS on the D435i camera (same world and trajectory) and the zero estimator. Renders are cached in the
work folder (:func:`eye_benchmark`'s layout: ``FAMILY-SEED-eye`` and
``FAMILY-SEED-cam``); rendering them is the cost (CPU-minutes per run), the figure itself takes
~1 min on cached renders.
"""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["eye_benchmark", "figure_eye", "ensure_runs", "ensure_gaze_runs", "eye_folder", "GAZE_FAMILY", "rate_vs_spiking_numbers", "figure_eye_rate_vs_spiking", "plot_eye_rate_vs_spiking", "dphi_fov_numbers",
           "figure_eye_dphi_fov", "FRONTAL_FIELDS"]

FAMILIES = ("panels", "rotation", "corridor")
#: LC fields only inside the D435i's 69°×42° view (centres |az| ≤ 30°, |el| ≤ 20°): the eye's
#: :class:`lobula.eye_circuit.EyeCircuitConfig` ``fields`` overrides
FRONTAL_FIELDS = dict(azimuth_deg=(10.0, 30.0), elevation_deg=(-20.0, 20.0), spacing_deg=20.0)


def ensure_runs(workdir, families=FAMILIES, seeds=(0, 1, 2), duration_s: float = 10.0, scale: float = 0.5,
                cast_every: int = 1) -> dict:
    """Render (if absent) the eye and pinhole footage of each family × seed; return {(family, seed): DIS RMSE}.

    DIS: the project's default velocity pipeline on the pinhole footage, causal filter, scored after 2 s.
    """
    from experiments.suite import family_config
    from experiments.velocity import score
    from lobula.velocity import estimate_velocity
    from lobula.compound_eye import CompoundEyeConfig
    from lobula.config import VelocityConfig
    from stimuli.eye import make_eye_run
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    dis = {}
    for fam in families:
        for seed in seeds:
            cfg = family_config(fam, seed, duration_s, scale)
            eye_dir, cam_dir = workdir / f"{fam}-{seed}-eye", workdir / f"{fam}-{seed}-cam"
            if not eye_dir.exists():
                make_eye_run(eye_dir, cfg, CompoundEyeConfig(), 500.0, progress=False, cast_every=cast_every)
            if not cam_dir.exists():
                make_track_run(cam_dir, cfg, progress=False)
            vc = VelocityConfig(front_end="dis")
            vc.readout.filter = "causal"
            dis[(fam, seed)] = score(estimate_velocity(open_footage(cam_dir), vc, progress=False))["rmse_m_s"]
    return dis


#: the rotation world seen by a gaze-stabilised head (lobula.gaze), rendered as ``rotation-SEED-eye-gaze``
GAZE_FAMILY = "rotation, gaze-stabilised head"


def ensure_gaze_runs(workdir, seeds=(0, 1, 2), duration_s: float = 10.0, scale: float = 0.5,
                     cast_every: int = 1) -> None:
    """Render (if absent) the rotation family's eye footage with haltere-driven gaze stabilisation
    (:class:`lobula.gaze.GazeConfig` defaults): the same world, trajectory and IMU as ``rotation-SEED-eye``."""
    from experiments.suite import family_config
    from lobula.compound_eye import CompoundEyeConfig
    from lobula.gaze import GazeConfig
    from stimuli.eye import make_eye_run

    for seed in seeds:
        out = Path(workdir) / f"rotation-{seed}-eye-gaze"
        if not out.exists():
            make_eye_run(out, family_config("rotation", seed, duration_s, scale), CompoundEyeConfig(), 500.0,
                         progress=False, cast_every=cast_every, gaze=GazeConfig())


def eye_folder(workdir, family: str, seed: int) -> Path:
    """The eye-footage folder of a family (or :data:`GAZE_FAMILY`) and seed in the work folder."""
    return Path(workdir) / (f"rotation-{seed}-eye-gaze" if family == GAZE_FAMILY else f"{family}-{seed}-eye")


#: Short names of the output neurons' spike models in the figure.
SPIKE_LABEL = {"poisson": "Poisson", "lif": "LIF"}


def rate_vs_spiking_numbers(workdir, families=FAMILIES, seeds=(0, 1, 2), populations=(1, 3, 10, 30),
                            gaze: bool = True, lif_populations=(1, 10)) -> dict:
    """RMSEs per family and seed: kalman (rates), spikes with N Poisson (``populations``) and LIF
    (``lif_populations``) output pairs, the readout neuron (rate; LIF spikes), DIS, zero.

    gaze: also the rotation world seen by a gaze-stabilised head (:data:`GAZE_FAMILY`; DIS and the
    zero estimator as for the rotation world: the same world and trajectory)."""
    from experiments.eye_velocity import EyeVelocityConfig, estimate_eye_velocity
    from experiments.velocity import score
    from stimuli.eye import open_eye_footage

    dis = ensure_runs(workdir, families, seeds)
    fams = list(families)
    if gaze and "rotation" in families:
        ensure_gaze_runs(workdir, seeds)
        fams.insert(fams.index("rotation") + 1, GAZE_FAMILY)
        dis.update({(GAZE_FAMILY, s): dis[("rotation", s)] for s in seeds})
    res: dict = {}
    for fam in fams:
        rows = res.setdefault(fam, {})
        for seed in seeds:
            fo = open_eye_footage(eye_folder(workdir, fam, seed))
            t0 = time.perf_counter()
            ds = estimate_eye_velocity(fo, EyeVelocityConfig())
            rows.setdefault("rate (arithmetic readout)", []).append(score(ds)["rmse_m_s"])
            # The eye's output neurons (encoder lead), their spike model and number varied.
            neuron = EyeVelocityConfig().neuron
            for model, pops in (("poisson", populations), ("lif", lif_populations)):
                for n in pops:
                    c = EyeVelocityConfig(readout_kind="spikes", neuron=replace(
                        neuron, spiking=True, population=n, seed=seed, spike_model=model))
                    rows.setdefault(f"spikes ({SPIKE_LABEL[model]}), {n} pair{'s' if n > 1 else ''}", []).append(
                        score(estimate_eye_velocity(fo, c))["rmse_m_s"])
            for spk in (False, True):
                c = EyeVelocityConfig(readout_kind="neuron", neuron=replace(neuron, spiking=spk, seed=seed))
                rows.setdefault(f"readout neuron ({'LIF spikes, 10 pairs' if spk else 'rate'})", []).append(
                    score(estimate_eye_velocity(fo, c))["rmse_m_s"])
            keep = ds.time.values >= ds.time.values[0] + 2.0
            rows.setdefault("zero estimator", []).append(float(np.sqrt(np.mean(ds.v_true.values[keep] ** 2))))
            rows.setdefault("DIS on the D435i (causal)", []).append(dis[(fam, seed)])
            print(f"  {fam} seed {seed}: {time.perf_counter() - t0:.1f} s", flush=True)
    return res


def figure_eye_rate_vs_spiking(out_dir, seeds=(0, 1, 2), workdir=None) -> tuple[Path, dict]:
    """Make ``eye_rate_vs_spiking.png`` (and its numbers); returns (path, numbers)."""
    out_dir = Path(out_dir)
    workdir = Path(workdir) if workdir else out_dir / "eye_runs"
    res = rate_vs_spiking_numbers(workdir, FAMILIES, tuple(seeds))
    return plot_eye_rate_vs_spiking(res, out_dir / "eye_rate_vs_spiking.png"), res


NEVER_OBSERVABLE_Y = 0.005  # where a seed with no observable frame (RMSE NaN) is marked, m/s (log axis from 0.004)


def plot_eye_rate_vs_spiking(res: dict, png) -> Path:
    """Draw :func:`rate_vs_spiking_numbers`' RMSEs (:func:`draw_eye_rate_vs_spiking`) to ``png``; returns its path."""
    import matplotlib.pyplot as plt

    from experiments.store import save_figure

    fig = draw_eye_rate_vs_spiking(res)
    save_figure(fig, png, dpi=150)
    plt.close(fig)
    return Path(png)


def draw_eye_rate_vs_spiking(res: dict):
    """The figure of :func:`rate_vs_spiking_numbers`' RMSEs: one panel per family, a log axis (the
    readout neuron's erratic seeds sit two decades above the rest)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in next(iter(res.values())) if k not in ("zero estimator", "DIS on the D435i (causal)")]
    fig, axes = plt.subplots(1, len(res), figsize=(4.3 * len(res), 4.6), sharey=True, squeeze=False)
    x = np.arange(len(keys))
    any_missing = False
    for ax, (fam, rows) in zip(axes[0], res.items()):
        vals = [np.array(rows[k], float) for k in keys]
        # A seed whose estimate is never observable scores NaN: the bar is the mean of the others,
        # and the missing seed is drawn as a cross on the axis, not dropped from sight.
        mean = np.array([np.nanmean(v) if np.isfinite(v).any() else np.nan for v in vals])
        col = ["tab:blue" if k.startswith("rate") else "tab:green" if k.startswith("readout neuron")
               else "tab:orange" if "LIF" in k else "tab:red" for k in keys]
        ax.bar(x, mean, color=col, alpha=0.55)
        for i, v in enumerate(vals):
            ok = np.isfinite(v)
            ax.plot(np.full(ok.sum(), x[i]), v[ok], "k.", ms=5)
            if ok.any():
                ax.plot([x[i], x[i]], [v[ok].min(), v[ok].max()], "k-", lw=1)
            if not ok.all():
                ax.plot(np.full((~ok).sum(), x[i]), np.full((~ok).sum(), NEVER_OBSERVABLE_Y), "kx", ms=6,
                        label="seed never observable" if not any_missing else None)
                any_missing = True
        d = np.array(rows["DIS on the D435i (causal)"])
        ax.axhspan(d.min(), d.max(), color="m", alpha=0.12, lw=0)
        ax.axhline(d.mean(), color="m", ls="--", label="DIS on the D435i, causal (mean; band: seeds)")
        ax.axhline(1.5 * d.mean(), color="m", ls=":", label="1.5 × DIS")
        ax.axhline(np.mean(rows["zero estimator"]), color="k", ls=":", label="zero estimator (mean)")
        ax.set_xticks(x, keys, rotation=60, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylim(0.004, 3.0)
        ax.grid(True, axis="y", which="both", alpha=0.25)
        ax.set_title(f"{fam} ({len(vals[0])} seeds)", fontsize=9)
    axes[0][0].set_ylabel("velocity RMSE after 2 s (m/s, log)")
    handles = {h.get_label(): h for ax in axes[0] for h in ax.get_legend_handles_labels()[0]}
    axes[0][0].legend(list(handles.values()), list(handles), fontsize=7, loc="upper left")
    fig.suptitle("Fly eye (Δφ = 5°, both eyes, 500 Hz), causal: rate readout against spiking output neurons "
                 "(200 Hz per m/s, causal synaptic decoding). Bars: mean over the observable seeds; dots: seeds",
                 fontsize=9)
    fig.tight_layout()
    return fig


def dphi_fov_numbers(workdir, families=FAMILIES, seeds=(0, 1, 2), dphis=(8.0, 5.0), cast_every: int = 2) -> dict:
    """Causal RMSE (arithmetic readout) against Δφ (Δρ = Δφ; renders cached, Δφ ≠ 5° cast at 250 Hz and
    interpolated) and field of view: LC fields over the whole eye (±150°) or only inside the D435i's
    69°×42° view (centres |az| ≤ 30°, |el| ≤ 20°), beside causal DIS on the D435i."""
    from dataclasses import replace as _replace

    from experiments.eye_velocity import EyeVelocityConfig, estimate_eye_velocity
    from experiments.suite import family_config
    from experiments.velocity import score
    from lobula.compound_eye import CompoundEyeConfig
    from stimuli.eye import make_eye_run, open_eye_footage

    workdir = Path(workdir)
    dis = ensure_runs(workdir, families, seeds)
    res: dict = {}
    for fam in families:
        rows = res.setdefault(fam, {})
        for seed in seeds:
            for d in dphis:
                path = workdir / (f"{fam}-{seed}-eye" if d == 5.0 else f"{fam}-{seed}-eye-dphi{d:g}")
                if not path.exists():
                    make_eye_run(path, family_config(fam, seed, 10.0, 0.5), CompoundEyeConfig(dphi_deg=d), 500.0,
                                 progress=False, cast_every=cast_every)
                fo = open_eye_footage(path)
                for fov in ("wide", "frontal"):
                    cfg = EyeVelocityConfig()
                    if fov == "frontal":
                        cfg.circuit.fields = _replace(cfg.circuit.fields, **FRONTAL_FIELDS)
                    rows.setdefault(f"{fov}|{d:g}", []).append(score(estimate_eye_velocity(fo, cfg))["rmse_m_s"])
            rows.setdefault("dis", []).append(dis[(fam, seed)])
            print(f"  {fam} seed {seed} done", flush=True)
    return res


def figure_eye_dphi_fov(out_dir, seeds=(0, 1, 2), workdir=None, dphis=(8.0, 5.0)) -> tuple[Path, dict]:
    """Make ``eye_rmse_vs_dphi_fov.png``; returns (path, numbers)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from experiments.store import save_figure

    out_dir = Path(out_dir)
    workdir = Path(workdir) if workdir else out_dir / "eye_runs"
    res = dphi_fov_numbers(workdir, FAMILIES, tuple(seeds), dphis)
    fig, axes = plt.subplots(1, len(res), figsize=(4.4 * len(res), 3.9), sharey=True, squeeze=False)
    for ax, (fam, rows) in zip(axes[0], res.items()):
        for k, (fov, col, lab) in enumerate((("wide", "tab:blue", "both eyes, LC fields over ±150°"),
                                             ("frontal", "tab:orange", "LC fields only in the D435i's 69°×42°"))):
            v = [np.array(rows[f"{fov}|{d:g}"]) for d in dphis]
            m = np.array([x.mean() for x in v])
            ax.errorbar(np.array(dphis) * (1 + 0.02 * (k - 0.5)), m,
                        yerr=[m - [x.min() for x in v], [x.max() for x in v] - m], marker="o", capsize=3,
                        color=col, label=lab)
        d = np.array(rows["dis"])
        ax.axhspan(d.min(), d.max(), color="m", alpha=0.12, lw=0)
        ax.axhline(d.mean(), color="m", ls="--", label="DIS on the D435i (0.2° pixels), causal")
        ax.set_xlabel("interommatidial angle Δφ = Δρ (deg)")
        ax.set_title(f"{fam} ({len(seeds)} seeds: mean, bars min–max)", fontsize=9)
    axes[0][0].set_ylabel("velocity RMSE after 2 s (m/s)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Fly eye, causal arithmetic readout: resolution and field of view (pinhole-sized against wide)",
                 fontsize=9)
    fig.tight_layout()
    png = out_dir / "eye_rmse_vs_dphi_fov.png"
    save_figure(fig, png, dpi=150)
    plt.close(fig)
    return png, res


def figure_eye(out_dir, seeds=(0, 1, 2), duration_s: float = 10.0, workdir=None,
               families=("panels", "rotation", "corridor"), field_sizes=(20.0, 30.0, 45.0),
               rotations=("none", "haltere", "wide-field")):
    """`lobula figures` entry: render (cached in ``workdir``) and score the eye beside causal DIS, then plot.

    With the rotation family, also the rotation world seen by a gaze-stabilised head
    (:data:`GAZE_FAMILY`), under the same rotation handling: the two
    rotation hypotheses (haltere, gaze) side by side. Writes ``out_dir/eye_rmse.png`` and its JSON;
    returns the path of the PNG.
    """
    from pathlib import Path

    out_dir = Path(out_dir)
    workdir = Path(workdir) if workdir else out_dir / "eye_runs"

    rows = eye_benchmark(workdir, families, seeds, duration_s, rotations=("haltere",))
    fams = list(families)
    if "rotation" in families:
        # The second rotation hypothesis family: the fly's own route, a head stabilised on the halteres.
        ensure_gaze_runs(workdir, seeds, duration_s)
        fams.insert(fams.index("rotation") + 1, GAZE_FAMILY)
    runs = {f: dict(eye=[eye_folder(workdir, f, s) for s in seeds],
                    dis_rmse=[r["dis_rmse"] for r in rows if r["family"] == (f if f != GAZE_FAMILY else "rotation")])
            for f in fams}
    png = out_dir / "eye_rmse.png"
    eye_figure(runs, png, field_sizes=field_sizes, rotations=rotations)
    return png


# ---------------------------------------------------------------------- benchmark
def eye_benchmark(workdir, families=("panels", "rotation", "corridor"), seeds=(0,), duration_s: float = 30.0,
                  rate_hz: float = 500.0, eye_config=None, scale: float = 0.5,
                  rotations=("haltere", "wide-field", "both", "none")) -> list[dict]:
    """The fly eye against causal DIS on the D435i camera, same worlds and trajectories.

    For each family (experiments.suite.family_config: the worlds' families) and seed, renders
    (once, cached under ``workdir``) the eye footage and the pinhole footage of the same run
    configuration, runs causal DIS (the project's default velocity pipeline, causal filter) and
    the eye circuit under each rotation hypothesis, and returns one row per run with the RMSEs
    (after 2 s), the zero estimator's, and the eye's render and circuit wall times.
    """
    from experiments.eye_velocity import EyeVelocityConfig, estimate_eye_velocity
    from experiments.suite import family_config
    from experiments.velocity import score
    from lobula.velocity import estimate_velocity
    from lobula.compound_eye import CompoundEyeConfig
    from lobula.config import VelocityConfig
    from stimuli.eye import make_eye_run, open_eye_footage
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for fam in families:
        for seed in seeds:
            cfg = family_config(fam, seed, duration_s, scale)
            eye_dir, cam_dir = workdir / f"{fam}-{seed}-eye", workdir / f"{fam}-{seed}-cam"
            if not eye_dir.exists():
                make_eye_run(eye_dir, cfg, eye_config or CompoundEyeConfig(), rate_hz, progress=False)
            if not cam_dir.exists():
                make_track_run(cam_dir, cfg, progress=False)
            vc = VelocityConfig(front_end="dis")
            vc.readout.filter = "causal"
            dis = estimate_velocity(open_footage(cam_dir), vc, progress=False)
            fo = open_eye_footage(eye_dir)
            row = dict(family=fam, seed=seed, dis_rmse=score(dis)["rmse_m_s"],
                       render_s=float(fo.info.get("render_s", float("nan"))), duration_s=duration_s)
            for rot in rotations:
                ec = EyeVelocityConfig()
                ec.circuit.rotation = rot
                ds = estimate_eye_velocity(fo, ec)
                row[f"eye_{rot}_rmse"] = score(ds)["rmse_m_s"]
                row[f"eye_{rot}_observable"] = score(ds)["observable_fraction"]
                row["circuit_s"] = json.loads(ds.attrs["timings_s"])["circuit_total"]
            keep = ds.time.values >= ds.time.values[0] + 2.0
            row["zero_rmse"] = float(np.sqrt(np.mean(ds.v_true.values[keep] ** 2)))
            rows.append(row)
            print(json.dumps(row))
    return rows


def eye_figure(runs: dict, out_png, field_sizes=(20.0, 30.0, 45.0, 60.0),
               rotations=("none", "haltere", "wide-field", "both"), skip_s: float = 2.0) -> dict:
    """RMSE of the causal eye circuit against LC field size and rotation handling, beside causal DIS.

    runs: {family: {"eye": [eye-footage folders (seeds)], "dis": [causal DIS velocity NetCDFs of the
    same worlds and trajectories on the pinhole camera] or "dis_rmse": [their RMSEs]}}. Every eye configuration is run on every
    seed; the plot shows the mean over seeds with min–max bars, DIS and the zero estimator as lines.
    Returns the numbers (JSON-able) and writes ``out_png`` (and ``out_png`` with .json).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import xarray as xr

    from experiments.eye_velocity import EyeVelocityConfig, estimate_eye_velocity
    from experiments.store import save_figure
    from experiments.velocity import score
    from stimuli.eye import open_eye_footage

    results: dict = {}
    for fam, spec in runs.items():
        res = results.setdefault(fam, dict(eye={}, dis=[], zero=[], seeds=len(spec["eye"])))
        for path in spec["eye"]:
            fo = open_eye_footage(path)
            for rot in rotations:
                for size in field_sizes:
                    cfg = EyeVelocityConfig()
                    cfg.circuit.rotation = rot
                    cfg.circuit.fields.size_deg = float(size)
                    ds = estimate_eye_velocity(fo, cfg)
                    res["eye"].setdefault(f"{rot}|{size:g}", []).append(score(ds, skip_s)["rmse_m_s"])
            keep = ds.time.values >= ds.time.values[0] + skip_s
            res["zero"].append(float(np.sqrt(np.mean(ds.v_true.values[keep] ** 2))))
        for nc in spec.get("dis", []):
            with xr.open_dataset(nc) as d:
                res["dis"].append(score(d, skip_s)["rmse_m_s"])
        res["dis"].extend(float(x) for x in spec.get("dis_rmse", []))
    fams = list(results)
    fig, axes = plt.subplots(1, len(fams), figsize=(4.2 * len(fams), 3.8), squeeze=False, sharey=True)
    for ax, fam in zip(axes[0], fams):
        res = results[fam]
        for k, (rot, colour) in enumerate(zip(rotations, ("0.5", "tab:blue", "tab:orange", "tab:green"))):
            vals = [res["eye"].get(f"{rot}|{s:g}", [np.nan]) for s in field_sizes]
            mean = np.array([np.mean(v) for v in vals])
            lo = mean - np.array([np.min(v) for v in vals])
            hi = np.array([np.max(v) for v in vals]) - mean
            shift = 0.6 * (k - 0.5 * (len(rotations) - 1))   # side by side where they coincide
            ax.errorbar(np.asarray(field_sizes) + shift, mean, yerr=[lo, hi], marker="o", ms=4, capsize=3,
                        color=colour, label=f"fly eye, rotation: {rot}")
        if res["dis"]:
            ax.axhspan(min(res["dis"]), max(res["dis"]), color="m", alpha=0.12, lw=0)
            ax.axhline(np.mean(res["dis"]), color="m", ls="--", label="DIS on the D435i camera (causal; band: seeds)")
        ax.axhline(np.mean(res["zero"]), color="k", ls=":", label="zero estimator (mean over seeds)")
        ax.set_title(f"{fam} ({res['seeds']} seed{'s' if res['seeds'] > 1 else ''})")
        ax.set_xlabel("LC field size, FWHM (deg)")
    axes[0][0].set_ylabel(f"velocity RMSE after {skip_s:g} s (m/s)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=7, frameon=False)
    ec = fo.eye.config
    fig.suptitle(f"Two compound eyes (Δφ = {ec.dphi_deg:g}°, Δρ = {ec.acceptance_deg:g}°, {fo.rate_hz:g} Hz): "
                 f"photoreceptors → EMDs (τ = {1000 * cfg.circuit.emd.tau_s:g} ms) → LC fields → readout, causal",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    save_figure(fig, out_png, dpi=150)
    plt.close(fig)
    from pathlib import Path
    js = Path(str(out_png)).with_suffix(".json")
    tmp = js.with_name(f".{js.name}.tmp")
    tmp.write_text(json.dumps(results, indent=1))
    tmp.replace(js)
    return results
