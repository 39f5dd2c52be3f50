"""`lobula suite`: the accuracy suite — scene families × seeds, every configuration, beside baselines.

Each (family, seed) scene is rendered once (``lobula scene``'s generator, exact truth, a
realistic IMU by default) into ``OUT/scenes/``; every estimator configuration runs on it
(:func:`lobula.velocity.estimate_velocity`), zero-phase and causal, and so do two
baselines that need no vision: the zero estimator (v̂ = 0) and IMU-only dead reckoning.
Named explicitly (not in "all": each renders the scene again, onto the eye, CPU-minutes per scene),
the fly's compound eye (:data:`EYE_CONFIGURATIONS`): the same world, trajectory and IMU ray-cast onto
two compound eyes at 500 Hz (``OUT/scenes/<scene>-eye``, :func:`stimuli.eye.make_eye_run`) and read
by :func:`experiments.eye_velocity.estimate_eye_velocity`, causal (and, named so, its rates offline), scored the
same way.
Metrics, per window — after a skip (``--skip``) and over the first 2 s —:

* ``rmse_m_s``, ``median_abs_error_m_s``: over frames where v̂ is observable (finite);
* ``coverage_2sigma``: fraction of those frames with |v̂ − v| ≤ 2·v_std (NaN without a std);
* ``z95``: the 95th percentile of |v̂ − v| / v_std over those frames — 1.96 for a calibrated Gaussian
  band, below it where the band is too wide, above where too narrow (a coverage of 100 % cannot tell
  a calibrated band from one ten times too wide; NaN without a std);
* ``observable_fraction``: fraction of the window's frames with an observable v̂;
* ``lock_on_s`` (whole run, the same in both windows): time from the first frame until the
  error stays within 0.05 m/s + 10 % of |v| for a full second (NaN: never);
* ``rmse_all_m_s``: over every frame with a v̂, where vision answers or the accelerometer carries it
  (:mod:`lobula.readout.carry`);
* ``coverage_2sigma_all``: fraction of all the window's frames with |v̂ − v| ≤ 2·v_std, carried v̂
  included and a frame without v̂ counted outside (NaN without a std): what a user who reads every v̂
  with its σ meets.

Outputs in ``OUT``: ``suite.nc`` (family × seed × configuration × window × metric, with the
per-scene settings), ``suite_table.csv`` (mean, sd and n over seeds), ``suite.png``,
``worlds.png`` (a frame of each family), and
``series/<scene>.nc`` (truth, v̂ answered and v̂ answered or carried, and v_std of every configuration),
``series.png`` (each scene's truth against v̂ ± 2σ, online and offline). Scenes and
per-scene results are kept, so an interrupted suite resumes where it stopped: a scene is
re-rendered only if its settings changed, a result reused only if the settings and the
code's git commit match (with uncommitted changes, "+dirty", or outside a checkout,
delete ``OUT/results`` to recompute).
"""
from __future__ import annotations

import json
import time as _time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from .families import ALL_FAMILIES, EXTRA_FAMILIES, FAMILIES, parse_seeds  # the families and --seeds syntax (light: the parser shares them)
# The scores and the scenes live in their own modules; their public names are named from here as well.
from .suite_metrics import METRIC_UNITS, METRICS, WINDOWS, Z95_TARGET, lock_on_time, score_series, window_metrics
from .suite_scene import (BASELINES, CONFIGURATIONS, EYE_CONFIGURATIONS, EYE_RATE_HZ, SceneJob, dead_reckoning,
                          ensure_eye_scene, ensure_rendered, family_config, family_seed, remove_partial_scenes,
                          run_scene_job, scene_name, series_key, velocity_config)


def seed_summary(values, name: str) -> dict:
    """:func:`experiments.store.seed_summary`, imported on first use: building `lobula suite`'s parser imports this
    module, and that must not load xarray."""
    from .store import seed_summary as summary

    return summary(values, name)


# ---------------------------------------------------------------------- the suite
def run_suite(families, seeds, duration_s, scale, out, configurations=None, workers=1, skip_s=2.0,
              imu="realistic", imu_mount="rotated", progress=print):
    """Run every (family, seed) scene; returns the suite Dataset (also written with table and figure).

    ``seeds``: a count N (seeds 0..N-1, the reported ones) or a list of seeds (e.g. development seeds 100, 101).
    """
    seeds = list(range(seeds)) if isinstance(seeds, int) else [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"seeds must be a count or distinct non-negative integers, got {seeds}")
    configurations = tuple(configurations or (*CONFIGURATIONS, *BASELINES))
    known = [*CONFIGURATIONS, *BASELINES, *EYE_CONFIGURATIONS]
    bad = [c for c in configurations if c not in known]
    if bad:
        raise ValueError(f"unknown configuration(s) {bad}; choose from {known}")
    for f in families:
        if f not in ALL_FAMILIES:
            raise ValueError(f"unknown family {f!r}; choose from {', '.join(ALL_FAMILIES)}")
    if duration_s <= skip_s:
        raise ValueError(f"--duration ({duration_s} s) must exceed --skip ({skip_s} s)")
    out = Path(out)
    footage = [n for n in ("camera.json", "frames.csv") if (out / n).exists()]
    if footage:  # its own results, scenes and series would be mixed into the recording
        raise ValueError(f"{out} is a footage folder ({footage[0]}): give the suite a folder of its own")
    out.mkdir(parents=True, exist_ok=True)
    stale = remove_partial_scenes(out)
    if stale:
        progress(f"removed {len(stale)} partial scene folder(s) a stopped run left: "
                 f"{', '.join(p.name for p in stale)}")
    jobs = [SceneJob(f, s, duration_s, scale, imu, imu_mount, configurations, skip_s, str(out))
            for f in families for s in seeds]
    results = []
    t0 = _time.perf_counter()

    def done(res):
        results.append(res)
        if not res.get("resumed"):  # kept when the suite is stopped: the same command resumes from it
            from .store import WRITTEN

            kept = out / "results" / f"{scene_name(res['family'], res['seed'])}.json"
            if kept not in WRITTEN:  # a scene run in this process counted it when writing it
                WRITTEN.append(kept)
        how = "resumed" if res.get("resumed") else f"scene ready in {res['render_s']:.0f} s"
        lz = res["metrics"].get("lobula zero-phase", {}).get("after_skip", {}).get("rmse_m_s")
        progress(f"[{len(results)}/{len(jobs)}] {res['family']} seed {res['seed']}: {how}"
                 + (f", lobula zero-phase RMSE {lz:.3f} m/s" if lz is not None else "")
                 + f" ({_time.perf_counter() - t0:.0f} s elapsed)")
        for name, msg in res["errors"].items():
            progress(f"  ERROR {name}: {msg}")

    if workers > 1:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(run_scene_job, j) for j in jobs]
            for fut in as_completed(futures):
                done(fut.result())
    else:
        for j in jobs:
            done(run_scene_job(j))
    ds = collect(results, families, seeds, configurations, dict(duration_s=duration_s, scale=scale, skip_s=skip_s,
                                                                imu=imu, imu_mount=imu_mount))
    from .store import write_csv, write_netcdf
    write_netcdf(ds, out / "suite.nc")
    rows = table_rows(ds)
    write_csv(rows, out / "suite_table.csv")
    plot_suite(ds, out / "suite.png")
    plot_worlds(out, families, seeds)
    plot_series(out, families, seeds, configurations)
    return ds, rows


#: the configurations ``series.png`` draws, where the suite ran them
SERIES_CONFIGURATIONS = ("lobula zero-phase", "lobula causal")


def plot_series(out: Path, families, seeds, configurations) -> Path | None:
    """``series.png``: each scene's true forward velocity against v̂ ± 2σ of :data:`SERIES_CONFIGURATIONS`
    (those the suite ran; else its first estimator), one panel per (family, seed), read from ``series/``.

    v̂ is solid where vision answers and dotted where the accelerometer carries it; the band is ±2·v_std
    over both. Returns the path, or None where there is nothing to draw."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import xarray as xr

    from .store import save_figure

    names = [c for c in SERIES_CONFIGURATIONS if c in configurations] or \
        [c for c in configurations if c not in BASELINES][:1]
    files = [[out / "series" / f"{scene_name(f, s)}.nc" for s in seeds] for f in families]
    if not names or not any(p.exists() for row in files for p in row):
        return None
    rows, cols = len(families), len(seeds)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols + 1.5, 2.2 * rows + 0.8), squeeze=False,
                             sharex=True)
    colours = dict(zip(names, ("tab:blue", "tab:red", "tab:green")))
    for (i, f), (j, s) in ((a, b) for a in enumerate(families) for b in enumerate(seeds)):
        ax, path = axes[i, j], files[i][j]
        ax.set_title(f"{f} seed {s}", fontsize=8)
        ax.tick_params(labelsize=7)
        if not path.exists():
            ax.text(0.5, 0.5, "no series", ha="center", va="center", transform=ax.transAxes, fontsize=8)
            continue
        with xr.open_dataset(path) as ds:
            t = ds.time.values
            ax.plot(t, ds.v_true.values, "k--", lw=1.0, label="truth")
            given = False
            for c in names:
                key = series_key(c)
                if f"v_hat__{key}" not in ds:
                    continue
                answered, every = ds[f"v_hat__{key}"].values, ds[f"v_hat_all__{key}"].values
                sd = ds[f"v_std__{key}"].values if f"v_std__{key}" in ds else np.full_like(t, np.nan)
                given |= bool(np.isfinite(every).any())
                ax.fill_between(t, every - 2 * sd, every + 2 * sd, color=colours[c], alpha=0.15, lw=0)
                ax.plot(t, every, ":", color=colours[c], lw=1.0)
                ax.plot(t, answered, "-", color=colours[c], lw=1.4, label=f"{c} (dotted: carried)")
            top = np.nanmax(np.abs(ds.v_true.values))
            if not given:
                ax.text(0.5, 0.12, "no v̂: vision never answered", ha="center", transform=ax.transAxes, fontsize=8,
                        color="0.4")
        ax.set_ylim(-0.3 * top - 0.05, 1.6 * top + 0.05)  # a carried σ can grow without bound
        ax.axhline(0, color="0.6", lw=0.5)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("v (m/s)", fontsize=8)
    handles, labels = next(((h, l) for h, l in (ax.get_legend_handles_labels() for ax in axes.ravel()) if h),
                           ([], []))
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.suptitle("forward velocity: truth against v̂ ± 2σ (solid where vision answers)", fontsize=10)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    save_figure(fig, out / "series.png", dpi=130)
    plt.close(fig)
    return out / "series.png"


def plot_worlds(out: Path, families, seeds) -> Path | None:
    """``worlds.png``: the middle frame of each family's scene, to see what was measured — one panel per world a
    family flew among ``seeds`` (the first seed in each: the saccadic family turns from world to world with
    the seed), titled with the family, the seed and the world (:func:`world_frames`)."""
    import cv2
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    frames = [(title, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for title, path in world_frames(out, families, seeds)]
    if not frames:
        return None
    cols = min(len(frames), 5)
    rows = -(-len(frames) // cols)
    # wide enough for the title over a single panel
    fig, axes = plt.subplots(rows, cols, figsize=(max(2.6 * cols, 4.0), 2.3 * rows + 0.3), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (title, img) in zip(axes.ravel(), frames):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        ax.set_title(title, fontsize=8)
    fig.suptitle("the suite's worlds (middle frame)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, out / "worlds.png", dpi=150)
    plt.close(fig)
    return out / "worlds.png"


def world_frames(out: Path, families, seeds) -> list[tuple[str, Path]]:
    """(title, the middle frame's file) of each world each family flew among ``seeds`` under ``out``/scenes, the
    first seed in each world, in the families' and seeds' order; scenes not rendered are left out."""
    import json

    found = []
    for f in families:
        seen = set()
        for seed in seeds:
            folder = out / "scenes" / scene_name(f, seed)
            files = sorted((folder / "frames").glob("*.png")) if (folder / "frames").is_dir() else []
            meta = folder / "scene.json"
            world = json.loads(meta.read_text())["config"]["scene"]["world"] if meta.is_file() else "?"
            if files and world not in seen:
                seen.add(world)
                found.append((f"{f}, seed {seed} ({world})", files[len(files) // 2]))
    return found


def _what_runs(name: str):
    """A configuration's (base, filter, {config path: value}), or "baseline"."""
    if name in CONFIGURATIONS:
        return CONFIGURATIONS[name]
    if name in EYE_CONFIGURATIONS:
        return ("eye", EYE_CONFIGURATIONS[name].get("readout.filter", "causal"), EYE_CONFIGURATIONS[name])
    return "baseline"


def _eye_provenance(configurations) -> dict:
    """The eye pipeline's whole configuration (its defaults, before each name's paths), where one ran."""
    if not any(c in EYE_CONFIGURATIONS for c in configurations):
        return {}
    from lobula.compound_eye import CompoundEyeConfig

    from .eye_velocity import EyeVelocityConfig

    return dict(eye_config=EyeVelocityConfig().to_json(), compound_eye=json.dumps(CompoundEyeConfig().to_dict()),
                eye_rate_hz=EYE_RATE_HZ)


def collect(results, families, seeds, configurations, settings):
    """The suite Dataset: value (family, seed, configuration, window, metric), NaN where missing."""
    import xarray as xr

    from lobula.config import VelocityConfig

    from .store import provenance

    val = np.full((len(families), len(seeds), len(configurations), len(WINDOWS), len(METRICS)), np.nan)
    peak = np.full((len(families), len(seeds)), np.nan)
    errors = {}
    for r in results:
        i, s = families.index(r["family"]), seeds.index(r["seed"])
        peak[i, s] = r["peak_speed_m_s"]
        for c, name in enumerate(configurations):
            for w, win in enumerate(WINDOWS):
                m = r["metrics"].get(name, {}).get(win, {})
                val[i, s, c, w] = [m.get(k, np.nan) for k in METRICS]
        for name, msg in r["errors"].items():
            errors[name] = msg
    ds = xr.Dataset(
        dict(value=(("family", "seed", "configuration", "window", "metric"), val,
                    {"long_name": "suite metric (units: metric_units, also in the metric's name; fractions 0..1)",
                     "units_coordinate": "metric_units"}),
             peak_speed_m_s=(("family", "seed"), peak,
                             {"units": "m/s", "long_name": "peak |true forward velocity| of the scene"})),
        coords=dict(family=("family", list(families), {"long_name": "scene family"}),
                    seed=("seed", np.asarray(seeds), {"units": "1", "long_name": "scene seed"}),
                    configuration=("configuration", list(configurations),
                                   {"long_name": "estimator configuration or baseline"}),
                    window=("window", list(WINDOWS), {"long_name": "scoring window"}),
                    metric=("metric", list(METRICS), {"long_name": "metric"}),
                    metric_units=("metric", [METRIC_UNITS[m] for m in METRICS],
                                  {"long_name": "UDUNITS units of the metric's values"}),
                    family_description=("family", [ALL_FAMILIES[f] for f in families],
                                        {"long_name": "what the scene family is"})))
    ds.attrs.update(provenance(VelocityConfig().to_json(), suite=settings,
                               configurations={c: _what_runs(c) for c in configurations},
                               configuration_errors=errors or "none", **_eye_provenance(configurations)))
    return ds


def table_rows(ds) -> list[dict]:
    """One row per (family, configuration, window): mean and sd over seeds of each metric."""
    rows = []
    for f in ds.family.values:
        for c in ds.configuration.values:
            for w in ds.window.values:
                row = dict(family=str(f), configuration=str(c), window=str(w))
                for m in ds.metric.values:
                    row.update(seed_summary(ds.value.sel(family=f, configuration=c, window=w, metric=m).values, m))
                rows.append(row)
    return rows


def format_table(rows, window="after_skip") -> str:
    """A printable (markdown) table of one window."""
    def ms(r, m, pct=False):
        mu, sd = r[f"{m}_mean"], r[f"{m}_sd"]
        if not np.isfinite(mu):
            return "—"
        if pct:
            return f"{100 * mu:.0f}%"
        return f"{mu:.3f}" + (f" ± {sd:.3f}" if np.isfinite(sd) else "")

    lines = ["| family | configuration | RMSE (m/s) | median abs e | 2σ coverage | \\|e\\|/σ, 95th pct (1.96 calibrated) "
             "| observable | lock-on (s) | 2σ coverage, every frame (carried v̂ in, none out) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["window"] != window:
            continue
        lock = r["lock_on_s_mean"]
        lock_s = (f"{lock:.1f}" if np.isfinite(lock) else "never") + (
            f" ({r['lock_on_s_n']} of {r['observable_fraction_n']} seeds)"
            if r["lock_on_s_n"] != r["observable_fraction_n"] else "")
        lines.append(f"| {r['family']} | {r['configuration']} | {ms(r, 'rmse_m_s')} | "
                     f"{ms(r, 'median_abs_error_m_s')} | {ms(r, 'coverage_2sigma', True)} | {ms(r, 'z95')} | "
                     f"{ms(r, 'observable_fraction', True)} | {lock_s} | {ms(r, 'coverage_2sigma_all', True)} |")
    return "\n".join(lines)


def unanswered(ds, configuration: str, window: str = "after_skip") -> np.ndarray:
    """(family,) bool: the families on which ``configuration`` ran but answered no frame in ``window`` of any
    seed (an observable fraction stored, no RMSE), in the order of ``ds.family``."""
    v = ds.value.sel(configuration=configuration, window=window)
    ran = np.isfinite(v.sel(metric="observable_fraction").values).any(1)
    return ran & ~np.isfinite(v.sel(metric="rmse_m_s").values).any(1)


def plot_suite(ds, path):
    """RMSE (after the skip and over the first 2 s), the frames answered, 2σ coverage and z95 per family and
    configuration.

    An RMSE and a coverage are over the frames a configuration answers, so the answered fraction stands
    beside them, and where a configuration ran but answered no frame of a family its RMSE slot says "none".
    The coverage cannot tell a calibrated band from one far too wide (both hold ~100 %), so the last
    panel shows z95, the 95th percentile of |e|/σ (1.96 for a calibrated Gaussian band; log scale),
    shaded where a Gaussian error would put the ±2σ coverage at 85–99 % (z95 1.52–2.72, the project's
    target). Configurations that state no σ (z95 infinite) have no bar there. The coverage over every frame
    takes in the v̂ the accelerometer carries beyond the answered frames, and counts a frame without v̂ outside."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    fams = [str(f) for f in ds.family.values]
    confs = [str(c) for c in ds.configuration.values]
    x = np.arange(len(fams))
    width = 0.8 / len(confs)
    cmap = plt.get_cmap("tab10")
    fig, axes = plt.subplots(6, 1, figsize=(max(11, 1.3 * len(fams) + 5), 19), sharex=True)
    for ax, win, metric, label in ((axes[0], "after_skip", "rmse_m_s", "RMSE after skip (m/s)"),
                                   (axes[1], "first_2s", "rmse_m_s", "RMSE, first 2 s (m/s)"),
                                   (axes[2], "after_skip", "observable_fraction", "frames answered (after skip)"),
                                   (axes[3], "after_skip", "coverage_2sigma", "truth within ±2σ (after skip)"),
                                   (axes[4], "after_skip", "coverage_2sigma_all",
                                    "truth within ±2σ, every frame\n(carried v̂ in, none out; after skip)"),
                                   (axes[5], "after_skip", "z95", "z95: 95th pct of |e|/σ (after skip)")):
        for k, c in enumerate(confs):
            v = ds.value.sel(configuration=c, window=win, metric=metric).values  # (family, seed)
            v = np.where(np.isfinite(v), v, np.nan)  # z95 is infinite where no σ is stated
            ran = np.isfinite(ds.value.sel(configuration=c, metric="observable_fraction").values).any()
            if metric == "rmse_m_s":
                for i in np.flatnonzero(unanswered(ds, c, win)):
                    ax.text(x[i] + (k - len(confs) / 2 + 0.5) * width, 0.03, "none", rotation=90, ha="center",
                            va="bottom", fontsize=7, color=cmap(k % 10), transform=ax.get_xaxis_transform())
            if not np.isfinite(v).any():
                if ax is axes[0]:  # keep its colour in the legend, saying it did not run
                    ax.bar([np.nan], [np.nan], color=cmap(k % 10), label=c + ("" if ran else " (not run)"))
                continue
            with np.errstate(all="ignore"), __import__("warnings").catch_warnings():
                __import__("warnings").simplefilter("ignore")
                mu, sd = np.nanmean(v, axis=1), np.nanstd(v, axis=1)
            ax.bar(x + (k - len(confs) / 2 + 0.5) * width, mu, width, yerr=sd, color=cmap(k % 10),
                   label=c if ax is axes[0] else None, capsize=1.5, error_kw=dict(lw=0.6))
        ax.set_ylabel(label)
        ax.grid(axis="y", lw=0.3)
        if metric == "rmse_m_s":
            ax.set_yscale("log")
        elif metric == "z95":
            ax.set_yscale("log")
            ax.axhspan(*Z95_TARGET, color="g", alpha=0.1, lw=0)
            ax.axhline(1.96, color="g", lw=0.8, ls="--")
        elif metric.startswith("coverage_2sigma"):
            ax.axhspan(0.85, 0.99, color="g", alpha=0.1, lw=0)
            ax.set_ylim(0, 1.02)
        else:
            ax.set_ylim(0, 1.02)
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1].set_xticks(x, fams)
    settings = json.loads(ds.attrs.get("suite", "{}")) if isinstance(ds.attrs.get("suite"), str) else {}
    fig.suptitle(f"lobula suite: {len(fams)} families × {ds.sizes['seed']} seeds "
                 f"({settings.get('duration_s', '?')} s, scale {settings.get('scale', '?')}, "
                 f"IMU {settings.get('imu', '?')}); bars: mean ± sd over seeds", y=0.995, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    save_figure(fig, path, provenance=ds.attrs, dpi=150)
    plt.close(fig)
    return path


def run_suite_cli(args) -> int:
    families = args.families.split(",") if args.families != "all" else list(FAMILIES)
    configurations = None
    if args.configurations != "all":
        configurations = [c.strip() for c in args.configurations.split(",")]
    ds, rows = run_suite(families, parse_seeds(args.seeds), args.duration, args.scale, args.out, configurations,
                         args.workers, args.skip, args.imu, args.imu_mount,
                         progress=(lambda *a: None) if args.quiet else (lambda m: print(m, flush=True)))
    print(f"\nAfter the first {args.skip:g} s (mean ± sd over seeds {', '.join(map(str, ds.seed.values))}):")
    print(format_table(rows, "after_skip"))
    print("\nFirst 2 s:")
    print(format_table(rows, "first_2s"))
    err = json.loads(ds.attrs["configuration_errors"]) if ds.attrs["configuration_errors"] != "none" else {}
    for name, msg in err.items():
        print(f"lobula suite: error: configuration {name!r} did not run: {msg}")
    out = Path(args.out)
    print(f"\nwrote {out / 'suite.nc'}, {out / 'suite_table.csv'}, {out / 'suite.png'}")
    return 1 if err else 0


def add_parser(subparsers):
    """Register `lobula suite` (see experiments.cli)."""
    from .parsers import CAMERA_SCALE, COUNT, NONNEGATIVE, POSITIVE, seeds

    s = subparsers.add_parser("suite", help="accuracy suite: scene families x seeds, all configurations, baselines",
                              description="The accuracy suite: scene families × seeds, every configuration, "
                                          "beside baselines.")
    s.add_argument("--out", required=True, help="output folder (scenes, per-scene results, suite.nc, table, figure)")
    s.add_argument("--families", default="all",
                   help="comma-separated families, or all: " + "; ".join(f"{k}: {v}" for k, v in FAMILIES.items())
                   .replace("%", "%%") + ". Run only when named: " + "; ".join(
                       f"{k}: {v}" for k, v in EXTRA_FAMILIES.items()).replace("%", "%%"))
    s.add_argument("--seeds", type=seeds, default="3",
                   help="seeds per family: a count N (seeds 0..N-1) or a comma-separated list (e.g. 100,101 "
                        "for development seeds that the reported 0..N-1 never see; 7, for seed 7 alone)")
    s.add_argument("--duration", type=POSITIVE, default=10.0, help="seconds per scene")
    s.add_argument("--scale", type=CAMERA_SCALE, default=0.5,
                   help="image scale of the D435i camera (0.5 = 320x240; at 0.25 = 160x120 DIS resolves "
                        "the corridor and fast turns poorly)")
    s.add_argument("--configurations", default="all",
                   help="comma-separated, or all: " + ", ".join([*CONFIGURATIONS, *BASELINES])
                   + "; named only (the fly's eye on the same worlds, rendered again onto the eye, CPU-minutes "
                   "per scene): " + ", ".join(EYE_CONFIGURATIONS))
    s.add_argument("--skip", type=NONNEGATIVE, default=2.0, help="seconds left out at the start for the after-skip window")
    s.add_argument("--imu", default="realistic", choices=["ideal", "realistic"], help="IMU error model")
    s.add_argument("--imu-mount", default="rotated", choices=["camera", "rotated"],
                   help="IMU axes: rotated (imu.csv in the IMU frame, camera.json imu_to_camera) or camera")
    s.add_argument("--workers", type=COUNT, default=1, help="scenes run in parallel (processes)")
    s.add_argument("--quiet", action="store_true", help="no progress lines")
    s.set_defaults(func=run_suite_cli)
