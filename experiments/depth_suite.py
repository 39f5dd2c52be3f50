"""Depth on the accuracy suite's scene families × seeds, beside baselines.

``lobula depth-suite --out DIR`` renders each (family, seed) scene with
the suite's own generator (:func:`experiments.suite.family_config`: the realistic IMU
mounted rotated, every family's geometry, texture, rotation and profile from the seed),
short (6 s at 160×120 by default; ``lobula suite`` renders 10 s at 320×240, where v̂ and so
the depth's scale are better, at about 7× the cost: ``--duration 10 --scale 0.5``; pairs of
the first 2 s, while the velocity readout locks on, are not scored) with exact depth
every ``--every`` frames (5); runs the
velocity pipeline once; then for every flow pair whose first frame has exact depth it
computes the depth pass's flow once and ranges it with every method, for two speed
sources:

* ``estimate`` — v̂ of the velocity pipeline with its defaults (what a user has);
* ``estimate_medium`` — v̂ of the same pipeline with DIS's "medium" preset
  (``lobula velocity --dis-preset medium``, ``lobula depth --dis-preset medium``);
* ``truth`` — the exact mean forward velocity over the pair (what the geometry gives
  when the speed is right).

Methods: ``ratio``, ``tv``, ``parallax`` (:mod:`experiments.depth_stream`, defaults),
and two baselines: ``constant`` — every pixel at the median of the exact depth over the
scored pixels (an oracle constant: it knows the truth's median), and ``tv exact flow`` —
TV on the scene's exact flow through the same pipeline (gyro, refinement, the same
speed): what the geometry allows when the flow is perfect, an upper bound.

Scored: pixels whose exact depth is finite and ≤ ``--max-range`` (sky and farther
pixels are counted apart), on every pair where the camera truly moves (|v| ≥ 0.03 m/s);
a pair the method cannot range (v̂ unobservable or slow) counts as zero coverage.
Metrics pooled over a scene's maps: median and mean AbsRel, δ<1.25, RMSE(log),
coverage; then mean ± sd over seeds.

**Honest scale.** Depth is v times what the flow says of 1/d, so a map inherits v̂'s
relative error one to one, whatever the solver does. As ``lobula depth`` reports them, maps
whose speed has v_std/|v| above ``--max-scale-rel-std`` (0.2) have no known metric scale
and are unobservable: the headline ``median_abs_rel`` is over the maps with a known scale,
``metric_fraction`` says how many those are (never hidden: the table prints it beside),
``median_abs_rel_all`` is the same error over every map the speed could range (nothing
masked for scale) and ``si_median_abs_rel`` the scale-invariant error (each map scaled by
median(d/d̂) first: the geometry's error alone). ``METRIC_DOC`` defines each metric.

Measured with the defaults (seeds 0–2, cached scenes, TV median AbsRel mean over seeds,
maps of known scale): with v̂ 0.06–0.11 on seven families, 0.193 on ``rotation`` (seed 1:
0.337) and 0.194 on ``dim`` (seed 2: 0.228), with 70 % and 56 % of the maps metric (60 % on
``offaxis``, 94–100 % elsewhere); unmasked 0.262 and 0.325 there; scale-invariant 0.03–0.13
on every family; exact speed 0.035–0.141. 100–300 s a scene on the shared, loaded 2-core
machine (about 25 s unloaded); ``--workers N`` runs N scenes at once (processes),
``--device cuda`` solves TV on a GPU.

Outputs in DIR: ``depth_suite.nc`` (family × seed × source × estimator × metric; "method" would clash with
xarray's ``sel`` keyword),
``depth_suite_table.csv`` (mean, sd, n over seeds), ``depth_suite.png`` (median AbsRel
per family and method, both sources, with coverage), ``depth_suite_maps.png`` (one map
per family: frame, exact depth, TV with v̂) and ``scenes/`` (kept and reused when their
settings match).
"""
from __future__ import annotations

import json
import math
import time as _time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .depth_score import PooledScores, ring_masks
from .depth_stream import DepthRunConfig, depth_at_first_frame, ranged_pairs, ring_edges, torch_threads
from .store import seed_summary

SOURCES = ("estimate", "estimate_medium", "truth")
METHODS = ("ratio", "tv", "parallax", "constant", "tv exact flow")
METRICS = ("median_abs_rel", "abs_rel", "delta_1_25", "rmse_log", "valid_fraction", "sky_far_fraction",
           "n_maps", "metric_fraction", "median_abs_rel_all", "valid_fraction_all", "si_median_abs_rel")
#: what each metric is (the NetCDF's ``metric_description`` and the module doc)
METRIC_DOC = dict(
    median_abs_rel="median |d̂−d|/d over the scored pixels of the maps with a known metric scale (speed's "
                   "v_std/|v| ≤ max_scale_rel_std): what `lobula depth` reports; the others are unobservable",
    abs_rel="mean |d̂−d|/d, the same pixels", delta_1_25="fraction within 1.25×, the same pixels",
    rmse_log="RMS of ln d̂ − ln d, the same pixels",
    valid_fraction="coverage: scored pixels with a metric estimate / scored pixels of every moving pair "
                   "(unobservable maps count as uncovered)",
    sky_far_fraction="pixels without a surface or beyond --max-range (not scored)", n_maps="maps scored",
    metric_fraction="fraction of the moving scored pairs whose map has a known metric scale",
    median_abs_rel_all="median AbsRel over every map the speed could range, scale known or not (nothing masked "
                       "for scale)",
    valid_fraction_all="coverage of that unmasked set",
    si_median_abs_rel="scale-invariant median AbsRel: each map multiplied by median(d/d̂) over its scored pixels "
                      "first (the geometry's error without the scale's), every map the speed could range")
MOVING_M_S = 0.03


def _scene(out: Path, family: str, seed: int, duration_s: float, scale: float, every: int, imu: str,
           imu_mount: str):
    """Render (or reuse) one family's seed; returns (folder, TrackRunConfig)."""
    from stimuli.track import make_track_run

    from .suite import family_config
    from .suite_scene import ensure_rendered

    cfg = replace(family_config(family, seed, duration_s, scale, imu, imu_mount), depth_every=every)
    folder = ensure_rendered(out / "scenes" / f"{family}-s{seed}", cfg.to_dict(),
                             lambda f: make_track_run(f, cfg, progress=False))
    return folder, cfg


def _scale_free(d: np.ndarray, true: np.ndarray, ok: np.ndarray, max_range_m: float) -> np.ndarray:
    """d times median(true/d) over the pixels it is scored on (the scale-invariant map); NaN map if none."""
    from lobula.depth import scorable

    m = ok & scorable(true, max_range_m)[0] & np.isfinite(d) & (d > 0)
    if not m.any():
        return np.full(d.shape, np.nan)
    return d * float(np.median(true[m] / d[m]))


def _scene_results(pooled: dict, n_scored: int, n_metric: dict) -> dict:
    """{(source, method): {"metric"|"all"|"si": (pooled ring scores, n_maps), "n_pairs", "n_metric"}} of
    :func:`range_scene`, from its pooled scores and its counts of scored and metric pairs."""
    out = {}
    for s in SOURCES:
        for m in METHODS:
            out[(s, m)] = {w: (pooled[(s, m, w)].result(), pooled[(s, m, w)].n_maps) for w in ("metric", "all", "si")}
            out[(s, m)].update(n_pairs=n_scored, n_metric=n_scored if m == "constant" else n_metric[s])
    return out


def range_scene(footage, velocity, scene, run: DepthRunConfig, depth_every: int,
                keep_map: int | None = None, skip_s: float = 0.0, v_medium=None,
                v_std_medium=None) -> tuple[dict, dict]:
    """Every source × method on the pairs of a footage that have exact depth.

    scene: the stimuli TrackScene the footage was rendered from (for the exact flow);
    depth_every: frames between its exact depth maps; skip_s: pairs starting earlier are
    not scored (the velocity readout's lock-on). v_medium, v_std_medium: v̂ per pair
    (observable, else NaN) of the velocity run with DIS "medium" and its std, for the source
    ``estimate_medium``.

    Each source × method pools three ways: "metric" — as ``lobula depth`` reports, a map
    whose speed has v_std/|v| above ``run.max_scale_rel_std`` is unobservable (no pixel
    covered; :func:`experiments.depth_stream.metric_scale`); "all" — every map the speed can
    range, scale known or not; "si" — the same maps, each scaled by median(d/d̂) first
    (scale-invariant). The constant oracle and the true speed are always metric.
    Returns ({(source, method): {"metric"|"all"|"si": (pooled ring scores, n_maps),
    "n_pairs": moving scored pairs, "n_metric": of them metric}}, the sample maps of the
    ``keep_map``-th scored pair for the figure).
    """
    from .depth_stream import metric_scale

    from lobula.depth import angle_from_epipole

    cam = footage.camera
    labels, lo, hi = ring_edges(run.depth)
    gap = json.loads(velocity.attrs["config"])["flow"]["gap"]
    n_pairs = len(footage) - gap
    starts = list(range(0, n_pairs, depth_every))
    every_run = replace(run, velocity="truth", min_speed_m_s=0.0)    # flow for every pair; speeds chosen below
    pooled = {(s, m, w): PooledScores(labels, run.max_range_m) for s in SOURCES for m in METHODS
              for w in ("metric", "all", "si")}
    n_metric = {s: 0 for s in SOURCES}
    v_std_all = velocity.v_std.values.astype(float)
    sample = {}
    n_scored = 0
    for p in ranged_pairs(footage, velocity, every_run, starts=starts):
        true = footage.depth_map(p.i0)
        if (true is None or p.t0 < skip_s or not (math.isfinite(p.v_true) and abs(p.v_true) >= MOVING_M_S)
                or p.flow is None):
            continue
        exact = scene.flow(p.t0, p.t1) / p.dt
        for s in SOURCES:
            v = {"estimate": p.v_hat, "truth": p.v_true,
                 "estimate_medium": float(v_medium[p.k]) if v_medium is not None else float("nan")}[s]
            v_std = {"estimate": float(v_std_all[p.k]), "truth": 0.0,
                     "estimate_medium": float(v_std_medium[p.k]) if v_std_medium is not None else float("nan")}[s]
            usable = math.isfinite(v) and abs(v) >= run.min_speed_m_s
            metric = usable and metric_scale(v, v_std, run.max_scale_rel_std)[1]
            n_metric[s] += int(metric)
            e_used = p.e
            for m in METHODS:
                if not usable:
                    d, ok = np.full(true.shape, np.nan), np.zeros(true.shape, bool)
                elif m == "constant":
                    t = true[np.isfinite(true) & (true > 0) & (true <= run.max_range_m)]
                    d = np.full(true.shape, float(np.median(t)) if t.size else np.nan)
                    ok = np.isfinite(d)
                else:
                    meth, flow = ("tv", exact) if m == "tv exact flow" else (m, p.flow)
                    res, _ = depth_at_first_frame(flow, cam, v, p.e, p.dt, meth, rotation=p.rotation,
                                                  config=run.depth, device=run.device, weighted=run.weighted,
                                                  snr_min=run.snr_min, noise_window_deg=run.noise_window_deg,
                                                  refine=run.refine)
                    d, ok = res.depth, res.valid
                    if m == "tv" and res.epipole is not None:
                        e_used = res.epipole
                    if s in ("estimate", "truth") and m == "tv" and keep_map is not None and n_scored == keep_map:
                        sample.update(frame=p.i0, t0=p.t0, v_true=p.v_true, true=true)
                        sample[s] = dict(v=v, depth=d, valid=ok)
                rings = ring_masks(angle_from_epipole(cam, e_used), labels, lo, hi)
                pooled[(s, m, "all")].add(d, true, ok, rings)
                pooled[(s, m, "si")].add(_scale_free(d, true, ok, run.max_range_m), true, ok, rings)
                known = metric or m == "constant"
                pooled[(s, m, "metric")].add(d, true, ok & known, rings)
        n_scored += 1
    return _scene_results(pooled, n_scored, n_metric), sample


def run_one(out: Path, family: str, seed: int, args) -> dict:
    """Render, estimate velocity, range one scene; returns its record (metrics and the sample map)."""
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from stimuli.track import build_track

    from lobula.readout import answered_velocity
    from lobula.velocity import estimate_velocity

    t0 = _time.perf_counter()
    folder, cfg = _scene(out, family, seed, args.duration, args.scale, args.every, args.imu, args.imu_mount)
    footage = open_footage(folder)
    vcfg = VelocityConfig()
    vcfg.readout.filter = args.filter
    velocity = estimate_velocity(footage, vcfg, progress=False)
    mcfg = VelocityConfig()
    mcfg.readout.filter = args.filter
    mcfg.flow.dis_preset = "medium"
    vmed = estimate_velocity(footage, mcfg, progress=False)
    v_medium = answered_velocity(vmed)
    scene, _ = build_track(cfg)
    run = _run_config(args)
    with torch_threads(1):
        scores, sample = range_scene(footage, velocity, scene, run, cfg.depth_every, keep_map=args.sample_map,
                                     skip_s=args.skip, v_medium=v_medium, v_std_medium=vmed.v_std.values)
    frame = None
    if sample:
        _, _, frame = next(footage.frames(sample["frame"], sample["frame"] + 1))
    after = velocity.time.values >= args.skip

    def rmse(ds):
        e = answered_velocity(ds) - ds.v_true.values
        return float(np.sqrt(np.nanmean(e[after] ** 2)))
    return dict(family=family, seed=seed, scores=scores, sample=sample, frame=frame, v_hat_rmse=rmse(velocity),
                v_hat_rmse_medium=rmse(vmed), seconds=_time.perf_counter() - t0)


def _run_config(args) -> DepthRunConfig:
    return DepthRunConfig(max_range_m=args.max_range, average_frames=args.average_frames,
                          max_scale_rel_std=args.max_scale_rel_std, device=args.device)


def _metric_values(res: dict) -> list[float]:
    """The METRICS of one scene's (source, method) entry of :func:`range_scene`."""
    (met, n_maps), (al, _), (si, _) = res["metric"], res["all"], res["si"]
    a = met["all"]
    total = a["n_true"] + a["n_sky"] + a["n_far"]
    frac = res["n_metric"] / res["n_pairs"] if res["n_pairs"] else float("nan")
    return [a["median_abs_rel"], a["abs_rel"], a["delta_1_25"], a["rmse_log"], a["valid_fraction"],
            (a["n_sky"] + a["n_far"]) / total if total else float("nan"), float(n_maps), frac,
            al["all"]["median_abs_rel"], al["all"]["valid_fraction"], si["all"]["median_abs_rel"]]


def _per_scene(records, families, seeds, key) -> np.ndarray:
    return np.array([[next((r[key] for r in records if r["family"] == f and r["seed"] == s), np.nan)
                      for s in seeds] for f in families])


def collect(records: list[dict], families, seeds, attrs: dict):
    """The family × seed × source × method × metric Dataset."""
    import xarray as xr

    arr = np.full((len(families), len(seeds), len(SOURCES), len(METHODS), len(METRICS)), np.nan)
    for r in records:
        i, j = families.index(r["family"]), seeds.index(r["seed"])
        for (s, m), res in r["scores"].items():
            arr[i, j, SOURCES.index(s), METHODS.index(m)] = _metric_values(res)
    ds = xr.Dataset(
        dict(score=(("family", "seed", "source", "estimator", "metric"), arr,
                    {"units": "1", "long_name": "depth scores pooled over each scene's maps (ring 'all'; "
                                                "every metric a ratio, fraction or count)"}),
             v_hat_rmse=(("family", "seed"), _per_scene(records, families, seeds, "v_hat_rmse"),
                         {"units": "m/s", "long_name": "RMSE of v̂ (default velocity pipeline) after the skip"}),
             v_hat_rmse_medium=(("family", "seed"), _per_scene(records, families, seeds, "v_hat_rmse_medium"),
                                {"units": "m/s", "long_name": "RMSE of v̂ (DIS medium) after the skip"})),
        coords=dict(family=("family", list(families), {"long_name": "scene family"}),
                    seed=("seed", list(seeds), {"units": "1", "long_name": "scene seed"}),
                    source=("source", list(SOURCES), {"long_name": "forward speed the depth is ranged with"}),
                    estimator=("estimator", list(METHODS), {"long_name": "depth estimator"}),
                    metric=("metric", list(METRICS), {"long_name": "depth metric"}),
                    metric_description=("metric", [METRIC_DOC[k] for k in METRICS],
                                        {"long_name": "what the metric is"})))
    ds.attrs.update(attrs)
    return ds


def table_rows(ds) -> list[dict]:
    rows = []
    for f in ds.family.values:
        for s in ds.source.values:
            for m in ds.estimator.values:
                row = dict(family=str(f), source=str(s), method=str(m))
                for k in METRICS:
                    row.update(seed_summary(ds.score.sel(family=f, source=s, estimator=m, metric=k).values, k))
                rows.append(row)
    return rows


def format_table(rows, source: str, max_scale_rel_std: float | None = None) -> str:
    """A Markdown table of one speed source: family × method, median AbsRel mean ± sd, coverage,
    and for TV the metric-depth fraction, the unmasked and the scale-invariant median AbsRel."""
    fams = list(dict.fromkeys(r["family"] for r in rows))
    head = ("| family | " + " | ".join(f"{m}" for m in METHODS) + " | TV δ<1.25 | TV RMSE(log) | TV coverage "
            "| metric maps | TV, every map (unmasked) | TV scale-invariant |")
    bound = "" if max_scale_rel_std is None else f" ≤ {max_scale_rel_std:g}"
    lines = [f"median AbsRel (mean ± sd over seeds), speed: {source}; maps with a known scale (v_std/|v|{bound}), "
             "the others unobservable", "", head, "|" + "---|" * (len(METHODS) + 7)]

    def ms(r, k):
        # A seed without a metric map has no error to average: say how many seeds the mean is over.
        short = f" (n={r[k + '_n']})" if r[k + "_n"] < r["n_maps_n"] else ""
        return f"{r[k + '_mean']:.3f} ± {r[k + '_sd']:.3f}{short}"
    for f in fams:
        by = {r["method"]: r for r in rows if r["family"] == f and r["source"] == source}
        cells = [ms(by[m], "median_abs_rel") for m in METHODS]
        tv = by["tv"]
        lines.append(f"| {f} | " + " | ".join(cells) + f" | {tv['delta_1_25_mean']:.2f} | {tv['rmse_log_mean']:.3f} "
                     f"| {100 * tv['valid_fraction_mean']:.0f}% | {100 * tv['metric_fraction_mean']:.0f}% "
                     f"| {ms(tv, 'median_abs_rel_all')} | {ms(tv, 'si_median_abs_rel')} |")
    return "\n".join(lines)


def plot_suite(ds, path) -> Path:
    """Median AbsRel per family and method (bars, ± sd over seeds), one panel per speed source."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    fams = [str(f) for f in ds.family.values]
    fig, axes = plt.subplots(len(SOURCES), 1, figsize=(11, 3.4 * len(SOURCES) + 0.6), sharex=True,
                             layout="constrained")
    colours = dict(zip(METHODS, ["tab:blue", "tab:red", "tab:green", "0.6", "tab:purple"]))
    w = 0.8 / len(METHODS)
    x = np.arange(len(fams))
    import warnings

    def seed_mean_sd(v):
        with warnings.catch_warnings():          # a family with no metric map on any seed: NaN, no bar
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(v, 1)
            sd = np.nanstd(v, 1, ddof=1) if v.shape[1] > 1 else np.zeros_like(mean)
        return mean, sd

    for ax, s in zip(axes, SOURCES):
        for j, m in enumerate(METHODS):
            v = ds.score.sel(source=s, estimator=m, metric="median_abs_rel").values
            cov = ds.score.sel(source=s, estimator=m, metric="valid_fraction").values
            mean, sd = seed_mean_sd(v)
            xj = x + (j - (len(METHODS) - 1) / 2) * w
            ax.bar(xj, mean, w, yerr=sd, color=colours[m], label=m, capsize=2)
            if m == "tv":
                # Beside the bar (metric maps only): every map unmasked (—) and scale-invariant (×).
                un = seed_mean_sd(ds.score.sel(source=s, estimator=m, metric="median_abs_rel_all").values)[0]
                si = seed_mean_sd(ds.score.sel(source=s, estimator=m, metric="si_median_abs_rel").values)[0]
                ax.scatter(xj, un, marker="_", s=120, color="k", zorder=3,
                           label="tv, every map (unmasked)" if s == SOURCES[0] else None)
                ax.scatter(xj, si, marker="x", s=18, color="k", zorder=3,
                           label="tv, scale-invariant" if s == SOURCES[0] else None)
            if m in ("ratio", "tv"):
                for xi, (mi, ci) in enumerate(zip(mean, seed_mean_sd(cov)[0])):
                    if np.isfinite(mi):
                        ax.text(xi + (j - (len(METHODS) - 1) / 2) * w, mi + 0.01, f"{100 * ci:.0f}%",
                                ha="center", va="bottom", fontsize=5.5, rotation=90)
        ax.axhline(0.2, color="k", ls="--", lw=0.8)
        ax.set_ylabel("median AbsRel")
        ax.set_yscale("log")
        ax.set_ylim(5e-4, 2)
        what = {"estimate": "v̂ of the velocity pipeline (defaults: DIS fast)",
                "estimate_medium": "v̂ of the velocity pipeline with DIS medium",
                "truth": "exact mean velocity over each pair"}[s]
        rm = {"estimate": "v_hat_rmse", "estimate_medium": "v_hat_rmse_medium"}.get(s)
        extra = ("; v̂ RMSE per family: " + ", ".join(f"{float(x):.2f}" for x in ds[rm].mean("seed").values)
                 if rm else "")
        ax.set_title(f"speed: {what}{extra}\nbars: maps with a known scale; over bars: coverage of ratio / TV "
                     f"(unobservable maps uncovered); dashed: 0.2", fontsize=8)
    axes[0].legend(ncol=4, fontsize=7, loc="upper left")
    axes[-1].set_xticks(x, fams)
    fig.suptitle(f"lobula depth on the suite's families: {ds.attrs.get('scene_summary', '')}", fontsize=10)
    save_figure(fig, path, dpi=150)
    plt.close(fig)
    return Path(path)


def plot_maps(records: list[dict], path, max_range_m: float) -> Path | None:
    """One row per family: the frame, its exact depth and TV's depth with v̂ and with the true v; None (no figure,
    and one left by an earlier run removed) where no scene kept a sample map."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    seen, rows = set(), []
    for r in records:
        if r["sample"].get("estimate") and r["sample"].get("truth") and r["family"] not in seen:
            seen.add(r["family"])
            rows.append(r)
    if not rows:
        Path(path).unlink(missing_ok=True)  # not this run's
        return None
    fig, axes = plt.subplots(len(rows), 4, figsize=(10, 1.95 * len(rows) + 0.6), squeeze=False, layout="constrained")
    cmap = matplotlib.colormaps["viridis_r"].with_extremes(bad="0.6")
    for ax_row, r in zip(axes, rows):
        smp = r["sample"]
        true = np.where(np.isfinite(smp["true"]) & (smp["true"] > 0), smp["true"], np.nan)
        vals = true[np.isfinite(true) & (true <= max_range_m)]
        lo, hi = (np.percentile(vals, [1, 99]) if vals.size else (0.5, 5.0))
        norm = matplotlib.colors.LogNorm(vmin=lo, vmax=max(hi, lo * 1.1), clip=True)
        ax_row[0].imshow(r["frame"], cmap="gray", vmin=0, vmax=255)
        ax_row[1].imshow(np.ma.masked_invalid(true), cmap=cmap, norm=norm)
        ax_row[0].set_title(f"{r['family']} (seed {r['seed']}), t = {smp['t0']:.2f} s", fontsize=7)
        ax_row[1].set_title("exact depth (grey: sky)", fontsize=7)
        for ax, key in zip(ax_row[2:], ("estimate", "truth")):
            d = smp[key]
            im = ax.imshow(np.ma.masked_invalid(np.where(d["valid"], d["depth"], np.nan)), cmap=cmap, norm=norm)
            ok = d["valid"] & np.isfinite(true) & (true <= max_range_m)
            med = np.median(np.abs(d["depth"][ok] - true[ok]) / true[ok]) if ok.any() else float("nan")
            ax.set_title(f"TV, {'v̂' if key == 'estimate' else 'true v'} = {d['v']:+.2f} m/s\n"
                         f"median AbsRel {med:.2f}", fontsize=7)
        for ax in ax_row:
            ax.set_xticks([])
            ax.set_yticks([])
        fig.colorbar(im, ax=ax_row[3], shrink=0.9, label="m (log)")
    save_figure(fig, path, dpi=150)
    plt.close(fig)
    return Path(path)


def _print_scene(r: dict) -> None:
    tv = r["scores"][("estimate", "tv")]
    a, a_all, a_si = (tv[w][0]["all"] for w in ("metric", "all", "si"))
    b = r["scores"][("truth", "tv")]["metric"][0]["all"]
    c = r["scores"][("estimate_medium", "tv")]["metric"][0]["all"]
    print(f"{r['family']}-s{r['seed']}: TV median AbsRel {a['median_abs_rel']:.3f} (v̂, metric maps "
          f"{tv['n_metric']}/{tv['n_pairs']}, coverage {a['valid_fraction']:.2f}; every map "
          f"{a_all['median_abs_rel']:.3f}, scale-invariant {a_si['median_abs_rel']:.3f}), "
          f"{c['median_abs_rel']:.3f} (v̂ DIS medium), {b['median_abs_rel']:.3f} (true v); v̂ RMSE "
          f"{r['v_hat_rmse']:.3f} / {r['v_hat_rmse_medium']:.3f} m/s [{r['seconds']:.0f} s]", flush=True)


def run_depth_suite(args) -> int:
    """Handler of ``lobula depth-suite``: returns 0."""
    from .store import provenance, write_csv, write_netcdf, write_text
    from .suite import FAMILIES, parse_seeds

    out = Path(args.out)
    families = list(FAMILIES) if args.families == "all" else [f.strip() for f in args.families.split(",") if f.strip()]
    bad = [f for f in families if f not in FAMILIES]
    if bad:
        raise ValueError(f"unknown families {', '.join(bad)}; choose from {', '.join(FAMILIES)} or 'all'")
    if args.every < 1:
        raise ValueError(f"--every must be ≥ 1, got {args.every}")
    if not args.duration > args.skip + 1.0:
        raise ValueError(f"--duration {args.duration:g} s must exceed --skip {args.skip:g} s by more than 1 s")
    if args.device != "cpu":  # before the renders, not after them
        from lobula._optional import torch_device

        torch_device(args.device)
    seeds = parse_seeds(args.seeds)
    seeds = list(range(seeds)) if isinstance(seeds, int) else seeds
    if args.workers < 1:
        raise ValueError(f"--workers must be ≥ 1, got {args.workers}")
    out.mkdir(parents=True, exist_ok=True)
    records = []
    jobs = [(f, s) for f in families for s in seeds]
    pool = None
    if args.workers > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # spawn, not fork: a worker may start CUDA (--device cuda), which a forked child cannot.
        pool = ProcessPoolExecutor(max_workers=args.workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        done = (pool.map(run_one, [out] * len(jobs), *zip(*jobs), [args] * len(jobs)) if pool is not None
                else (run_one(out, f, s, args) for f, s in jobs))
        for r in done:                               # in job order, whatever order the workers finish in
            records.append(r)
            _print_scene(r)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    summary = (f"{len(seeds)} seeds ({', '.join(map(str, seeds))}), {args.duration:g} s (scored after {args.skip:g} s), "
               f"scale {args.scale:g}, "
               f"depth every {args.every} frames, scored ≤ {args.max_range:g} m, {args.imu} IMU ({args.imu_mount})")
    run = _run_config(args)
    attrs = provenance(json.dumps(dict(depth_run=run.to_dict(), args=vars(args)), sort_keys=True, default=str),
                       scene_summary=summary, sources="estimate: v̂ of the velocity pipeline; truth: exact mean "
                       "forward velocity over each pair", baselines="constant: median of the exact depth over the "
                       "scored pixels (oracle); tv exact flow: TV on the scene's exact flow, same pipeline")
    ds = collect(records, families, seeds, attrs)
    write_netcdf(ds, out / "depth_suite.nc")
    rows = table_rows(ds)
    write_csv(rows, out / "depth_suite_table.csv")
    text = "\n\n".join(format_table(rows, s, args.max_scale_rel_std) for s in SOURCES)
    write_text(out / "depth_suite_table.md", text + "\n")
    print(text)
    plot_suite(ds, out / "depth_suite.png")
    maps = plot_maps(records, out / "depth_suite_maps.png", args.max_range)
    print(f"wrote {out / 'depth_suite.nc'}, depth_suite_table.csv/.md, depth_suite.png"
          + (", depth_suite_maps.png" if maps is not None else " (no sample map: no scene kept one)"))
    return 0


def add_parser(subparsers):
    """Register ``lobula depth-suite`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_depth_suite_parser`'s, built without importing this module."""
    from .parsers import add_depth_suite_parser

    return add_depth_suite_parser(subparsers)


if __name__ == "__main__":  # ``python -m experiments.depth_suite`` is ``lobula depth-suite``
    import sys

    from experiments.cli import main

    raise SystemExit(main(["depth-suite", *sys.argv[1:]]))
