"""`lobula suite`: the accuracy suite — scene families × seeds, every configuration, beside baselines.

Each (family, seed) scene is rendered once (``lobula scene``'s generator, exact truth, a
realistic IMU by default) into ``OUT/scenes/``; every estimator configuration runs on it
(:func:`experiments.velocity.estimate_velocity`), zero-phase and causal, and so do two
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
  error stays within 0.05 m/s + 10 % of |v| for a full second (NaN: never).

Outputs in ``OUT``: ``suite.nc`` (family × seed × configuration × window × metric, with the
per-scene settings), ``suite_table.csv`` (mean, sd and n over seeds), ``suite.png``,
``worlds.png`` (a frame of each family), and
``series/<scene>.nc`` (truth, v̂ and v_std of every configuration, for plots). Scenes and
per-scene results are kept, so an interrupted suite resumes where it stopped: a scene is
re-rendered only if its settings changed, a result reused only if the settings and the
code's git commit match (with uncommitted changes, "+dirty", or outside a checkout,
delete ``OUT/results`` to recompute).
"""
from __future__ import annotations

import json
import os
import time as _time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .families import FAMILIES, parse_seeds  # the suite's families and --seeds syntax (light: its parser shares them)


def seed_summary(values, name: str) -> dict:
    """:func:`experiments.store.seed_summary`, imported on first use: building `lobula suite`'s parser imports this
    module, and that must not load xarray."""
    from .store import seed_summary as summary

    return summary(values, name)


#: window name -> description
WINDOWS = ("after_skip", "first_2s")
METRICS = ("rmse_m_s", "median_abs_error_m_s", "coverage_2sigma", "z95", "observable_fraction", "lock_on_s")
#: each metric's units (suite.nc's ``metric_units``)
METRIC_UNITS = dict(rmse_m_s="m/s", median_abs_error_m_s="m/s", coverage_2sigma="1", z95="1",
                    observable_fraction="1", lock_on_s="s")
#: z95 where a Gaussian error's ±2σ coverage is 99 % and 85 % (1.96·2/z₀.₉₉₅, 1.96·2/z₀.₉₂₅): the suite figure's band
Z95_TARGET = (1.52, 2.72)

#: configuration name -> (base, filter, {config path: value}); base "lobula" (DIS), a front end's name
#: (lobula.front_ends.FRONT_ENDS, with its own defaults: VelocityConfig(front_end=base); "emd", the camera's
#: EMD front end) or "paper"
CONFIGURATIONS = {
    "lobula zero-phase": ("lobula", "zero-phase", {}),
    "lobula causal": ("lobula", "causal", {}),
    "emd zero-phase": ("emd", "zero-phase", {}),
    "emd causal": ("emd", "causal", {}),
    "lobula fixed-lag 1s": ("lobula", "causal", {"readout.lag_s": 1.0}),
    "lobula fixed-lag 2s": ("lobula", "causal", {"readout.lag_s": 2.0}),
    "paper zero-phase": ("paper", "zero-phase", {}),
    "paper causal": ("paper", "causal", {}),
    "r2=mean_squared zero-phase": ("lobula", "zero-phase", {"readout.r2_term": "mean_squared"}),
    "r2=mean_squared causal": ("lobula", "causal", {"readout.r2_term": "mean_squared"}),
    "vision-only zero-phase": ("lobula", "zero-phase", {"readout.fusion": "vision-only"}),
    "vision-only causal": ("lobula", "causal", {"readout.fusion": "vision-only"}),
}
BASELINES = ("zero", "imu dead reckoning")
#: configuration name -> {EyeVelocityConfig path: value}: the fly's eye on the scene's world (made only when
#: named, like the baselines it is scored beside): spiking output (10 LIF pairs) or the readout's rates, causal;
#: and the rates offline ("eye rates zero-phase": the readout's smoother with the whole record's gravity, as
#: `lobula eye-velocity --filter zero-phase`), which says how much of the eye's causal error the signals
#: themselves hold and how much is the forward filter's lack of the future. The spiking decoder is causal only.
EYE_CONFIGURATIONS = {
    "eye causal": {"readout_kind": "spikes"},
    "eye rates causal": {"readout_kind": "kalman"},
    "eye rates zero-phase": {"readout_kind": "kalman", "readout.filter": "zero-phase"},
}
#: Hz: the eye footage's rate (the photoreceptor model's 2 ms step, as `lobula scene --eye fly`)
EYE_RATE_HZ = 500.0


def family_seed(family: str, seed: int) -> int:
    """The scene seed of a family's seed index: distinct across families, stable across runs."""
    return zlib.crc32(family.encode()) % 100000 + 1000 * seed


def family_config(family: str, seed: int, duration_s: float, scale: float, imu: str = "realistic",
                  imu_mount: str = "rotated"):
    """The stimuli.track.TrackRunConfig of one family's seed (all randomness from the seed)."""
    from stimuli.imu import IMUConfig
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, recorded_profile

    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(FAMILIES)}")
    s = family_seed(family, seed)
    rng = np.random.default_rng([s, 9])
    scene = dict(seed=s)
    run = dict(duration_s=duration_s, scale=scale)
    real = recorded_profile()

    def real_window():
        # A window of the real run (or the built-in profile) starting anywhere after its first rest.
        if real:
            run.update(profile=str(real), start_s=float(rng.uniform(4.0, 77.5 - duration_s)))
        else:
            run.update(start_s=float(rng.uniform(3.0, 40.0)))

    if family in ("panels", "rotation", "offaxis", "dim"):
        real_window()
    if family == "rotation":
        scene.update(rotation3_amp_deg=tuple(float(a) for a in 5.0 * rng.uniform(0.6, 1.0, 3)))
    elif family == "corridor":
        scene.update(world="corridor")
        run.update(random_peak_m_s=1.0, random_start="rest")
    elif family == "fast":
        scene.update(world="corridor")
        run.update(random_peak_m_s=2.0, random_start="motion")
    elif family == "offaxis":
        scene.update(off_axis_yaw_deg=float(rng.choice([-1, 1]) * rng.uniform(5.0, 9.0)),
                     off_axis_pitch_deg=float(rng.uniform(-4.0, 4.0)))
    elif family == "dim":
        scene.update(brightness=0.35, contrast=0.5, noise_grey=6.0)
    elif family == "ground":
        scene.update(world="ground")
        run.update(random_peak_m_s=1.5, random_start="rest")
    elif family in ("rest", "moving"):
        run.update(random_peak_m_s=0.6, random_start="rest" if family == "rest" else "motion")
    elif family == "mixed":
        # The other families change one thing at a time; the footage the project is judged on
        # changes several at once. Nothing is tuned on this family.
        world = str(rng.choice(["panels", "corridor", "ground"]))
        peak = {"panels": (0.6, 1.0), "corridor": (0.8, 2.5), "ground": (0.8, 2.5)}[world]
        scene.update(world=world, side_walls=bool(world == "panels" and rng.random() < 0.5),
                     rotation3_amp_deg=tuple(float(a) for a in rng.uniform(2.0, 5.0, 3)),
                     off_axis_yaw_deg=float(rng.uniform(-9.0, 9.0)), off_axis_pitch_deg=float(rng.uniform(-4.0, 4.0)),
                     noise_grey=float(rng.uniform(1.0, 6.0)))
        run.update(random_peak_m_s=float(rng.uniform(*peak)), random_start=str(rng.choice(["rest", "motion"])))
    return TrackRunConfig(scene=SceneConfig(**scene), imu=IMUConfig.model(imu, seed=s, mount=imu_mount), **run)


def velocity_config(name: str):
    """The VelocityConfig of a configuration name (an EyeVelocityConfig for :data:`EYE_CONFIGURATIONS`);
    a config path the estimator lacks raises ValueError."""
    from lobula.config import VelocityConfig
    from lobula.front_ends import FRONT_ENDS

    if name in EYE_CONFIGURATIONS:
        from .eye_velocity import EyeVelocityConfig

        return _set_paths(EyeVelocityConfig(), EYE_CONFIGURATIONS[name], name)
    base, filt, paths = CONFIGURATIONS[name]
    cfg = (VelocityConfig.paper("dis", filt) if base == "paper" else
           VelocityConfig(front_end=base) if base in FRONT_ENDS else VelocityConfig())
    cfg.readout.filter = filt
    return _set_paths(cfg, paths, name)


def _set_paths(cfg, paths: dict, name: str):
    """cfg with each dotted config path set (validated by the dataclasses' __post_init__)."""
    for path, value in paths.items():
        obj = cfg
        *parents, leaf = path.split(".")
        for p in parents:
            obj = getattr(obj, p)
        if not hasattr(obj, leaf):
            raise ValueError(f"configuration {name!r}: {type(obj).__name__} has no field {leaf!r} "
                             f"(config path {path}); this estimator does not implement it")
        setattr(obj, leaf, value)
        obj.__post_init__() if hasattr(obj, "__post_init__") else None
    return cfg


# ---------------------------------------------------------------------- metrics
def lock_on_time(t: np.ndarray, err: np.ndarray, v_true: np.ndarray, hold_s: float = 1.0,
                 moving_m_s: float = 0.1) -> float:
    """Seconds from t[0] to the start of the first hold_s-long stretch in which |err| ≤ 0.05 m/s + 10 % of |v|
    throughout, while the camera moves (|v| > moving_m_s) for at least half of it; NaN if none.

    A NaN (unobservable) error breaks a stretch. Being right about a still camera alone does not count.
    """
    ok = np.isfinite(err) & (np.abs(err) <= 0.05 + 0.1 * np.abs(v_true))
    moving = np.abs(v_true) > moving_m_s
    start = None
    for i in range(len(t)):  # a scan over frames (hundreds), not pixels
        if not ok[i]:
            start = None
            continue
        start = i if start is None else start
        # Slide the stretch's start forward past still frames so motion can fill it.
        while start < i and not moving[start] and t[i] - t[start + 1] >= hold_s:
            start += 1
        if t[i] - t[start] >= hold_s and moving[start:i + 1].mean() >= 0.5:
            return float(t[start] - t[0])
    return float("nan")


def window_metrics(t, v_hat, v_std, v_true, mask) -> dict:
    """RMSE, median |e|, 2σ coverage, z95 (the 95th percentile of |e|/σ) and observable fraction over the frames in mask."""
    vh, vt = v_hat[mask], v_true[mask]
    obs = np.isfinite(vh)
    err = vh[obs] - vt[obs]
    out = dict(observable_fraction=float(obs.mean()) if obs.size else float("nan"))
    if err.size:
        out.update(rmse_m_s=float(np.sqrt(np.mean(err ** 2))), median_abs_error_m_s=float(np.median(np.abs(err))))
    else:
        out.update(rmse_m_s=float("nan"), median_abs_error_m_s=float("nan"))
    out["coverage_2sigma"] = out["z95"] = float("nan")
    if v_std is not None and err.size:
        sd = v_std[mask][obs]
        # An estimator that reports no uncertainty at all has no coverage (NaN), not 0.
        has = np.isfinite(sd)
        if has.any():
            # A frame without a std counts outside the band, and as an unbounded |e|/σ.
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.abs(err) / sd                       # σ = 0: inf, or 0 where the error is 0 too
            z = np.where(has, np.nan_to_num(z, nan=0.0, posinf=np.inf), np.inf)
            out["coverage_2sigma"] = float(np.mean(z <= 2))
            out["z95"] = float(np.quantile(z, 0.95, method="inverted_cdf"))  # a sample: no inf − inf
    return out


def score_series(t, v_hat, v_std, v_true, skip_s: float) -> dict:
    """{window: {metric: value}} for one configuration's series (v̂ NaN where unobservable)."""
    lock = lock_on_time(t, v_hat - v_true, v_true)
    out = {}
    for w, mask in (("after_skip", t >= t[0] + skip_s), ("first_2s", t < t[0] + 2.0)):
        m = window_metrics(t, v_hat, v_std, v_true, mask)
        m["lock_on_s"] = lock
        out[w] = m
    return out


def dead_reckoning(footage, times: np.ndarray, v0: float, calib_s: float = 1.0, still_rad_s: float = 0.01) -> np.ndarray:
    """IMU-only forward velocity (m/s) at ``times``: integrate the forward specific force minus gravity.

    Gravity (as specific force) is the mean of the first calib_s seconds, as a device
    calibrates at start-up; the gyro bias too, but only if the gyro is still then (every
    axis's std below still_rad_s; a turning camera's mean rate is not a bias, so then the
    bias is left as the factory's). The attitude is propagated from the gyro so gravity is
    tracked through turns. Starts from the true initial velocity v0 (a generous start no
    IMU alone has). Any accelerometer bias drift or scale error, any acceleration during
    the first second and any attitude error integrate into a drift that grows with time.
    """
    from stimuli.imu import small_rotation

    imu = footage.imu
    ti, acc, gyr = imu.time_s, imu.accel, imu.gyro
    first = ti < ti[0] + calib_s
    f0 = acc[first].mean(0)
    still = gyr is not None and bool(np.all(gyr[first].std(0) < still_rad_s))
    bg = gyr[first].mean(0) if still else np.zeros(3)
    n = len(ti)
    rot = np.empty((n, 3, 3))
    rot[0] = np.eye(3)
    for k in range(n - 1):  # attitude relative to the first sample (samples, not pixels)
        w = 0.5 * (gyr[k] + gyr[k + 1]) - bg if gyr is not None else np.zeros(3)
        rot[k + 1] = rot[k] @ small_rotation(w * (ti[k + 1] - ti[k]))
    f_rest = np.einsum("nji,j->ni", rot, f0)  # gravity's specific force in the current camera frame
    a = (acc - f_rest)[:, 2]
    v = np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * np.diff(ti))])
    v -= np.interp(times[0], ti, v)
    return v0 + np.interp(times, ti, v)


# ---------------------------------------------------------------------- one scene
@dataclass
class SceneJob:
    family: str
    seed: int
    duration_s: float
    scale: float
    imu: str
    imu_mount: str
    configurations: tuple
    skip_s: float
    out: str

    @property
    def name(self) -> str:
        return f"{self.family}-s{self.seed}"

    def key(self) -> str:
        """What a stored result must match to be reused: the settings and the code's git commit."""
        from lobula.version import git_commit

        d = dict(self.__dict__)
        d.pop("out")
        d["code"] = git_commit()
        return json.dumps(d, sort_keys=True)


def run_scene_job(job: SceneJob) -> dict:
    """Render (unless already there), run every configuration, write series and result; return the result."""
    import xarray as xr

    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    from .store import write_netcdf
    from .velocity import estimate_velocity

    out = Path(job.out)
    res_path = out / "results" / f"{job.name}.json"
    if res_path.exists():
        res = json.loads(res_path.read_text())
        if res.get("key") == job.key():
            res["resumed"] = True
            return res
    t0 = _time.perf_counter()
    cfg = family_config(job.family, job.seed, job.duration_s, job.scale, job.imu, job.imu_mount)
    folder = ensure_rendered(out / "scenes" / job.name, cfg.to_dict(),
                             lambda f: make_track_run(f, cfg, progress=False))
    render_s = _time.perf_counter() - t0
    footage = open_footage(folder)
    if cfg.imu.mount != "camera" and getattr(footage, "imu_to_camera", None) is None:
        raise ValueError(f"{folder}: the footage reader did not apply camera.json's imu_to_camera; "
                         f"run the suite with --imu-mount camera")
    tt, vt = footage.truth["time_s"], footage.truth["v_forward_m_s"]
    series, metrics, errors, wall = {}, {}, {}, {}
    eye_render_s = 0.0
    for name in job.configurations:
        t1 = _time.perf_counter()
        if name in BASELINES:
            continue
        try:
            vc = velocity_config(name)
            if name in EYE_CONFIGURATIONS:
                from stimuli.eye import open_eye_footage

                from .eye_velocity import estimate_eye_velocity

                t2 = _time.perf_counter()
                eye_folder = ensure_eye_scene(out / "scenes", job.name, cfg)
                eye_render_s += _time.perf_counter() - t2
                ds = estimate_eye_velocity(open_eye_footage(eye_folder), vc)
            else:
                ds = estimate_velocity(footage, vc, progress=False)
        except ValueError as exc:
            errors[name] = str(exc)
            continue
        t = ds.time.values
        v_hat = np.where(ds.observable.values, ds.v_hat.values, np.nan)
        series[name] = (t, v_hat, ds.v_std.values)
        wall[name] = _time.perf_counter() - t1
    # Baselines on the frame times the camera's estimator used (or all frames if it ran none: the
    # eye's own steps are 500 Hz, its series is interpolated onto these for the file).
    t_ref = next((v[0] for k, v in series.items() if k not in EYE_CONFIGURATIONS), footage.times)
    v_true_ref = np.interp(t_ref, tt, vt)
    if "zero" in job.configurations:
        series["zero"] = (t_ref, np.zeros_like(t_ref), None)
    if "imu dead reckoning" in job.configurations:
        series["imu dead reckoning"] = (t_ref, dead_reckoning(footage, t_ref, float(np.interp(t_ref[0], tt, vt))),
                                        None)
    for name, (t, v_hat, v_std) in series.items():
        metrics[name] = score_series(t, v_hat, v_std, np.interp(t, tt, vt), job.skip_s)
    # Series file: every configuration on the reference times (the paper stamps pairs at their
    # first frame, so its times differ; interpolated for the file only, scored on its own).
    data = {"v_true": ("time", v_true_ref, {"units": "m/s", "long_name": "ground-truth forward velocity"})}
    for name, (t, v_hat, v_std) in series.items():
        key = name.replace(" ", "_").replace("=", "-")
        data[f"v_hat__{key}"] = ("time", np.interp(t_ref, t, v_hat, left=np.nan, right=np.nan),
                                 {"units": "m/s", "long_name": f"estimated forward velocity, {name} (NaN: not "
                                                               "observable)"})
        if v_std is not None:
            data[f"v_std__{key}"] = ("time", np.interp(t_ref, t, v_std, left=np.nan, right=np.nan),
                                     {"units": "m/s", "long_name": f"stated std of v_hat, {name}"})
    ds = xr.Dataset(data, coords={"time": ("time", t_ref, {"units": "s", "long_name": "frame time on the "
                                                                                      "footage clock"})},
                    attrs=dict(scene=job.name, config=json.dumps(cfg.to_dict(), default=str)))
    write_netcdf(ds, out / "series" / f"{job.name}.nc")
    res = dict(key=job.key(), family=job.family, seed=job.seed, scene_seed=cfg.scene.seed, metrics=metrics,
               errors=errors, render_s=render_s, eye_render_s=eye_render_s, estimator_s=wall,
               scene_config=cfg.to_dict(),
               peak_speed_m_s=float(np.abs(vt).max()))
    res_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = res_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(res, default=str))
    os.replace(tmp, res_path)
    return res


def remove_partial_scenes(out: Path) -> list[Path]:
    """Remove the partial scene folders (``OUT/scenes/.<scene>.partial-<pid>``, ``.<scene>.track-<pid>``)
    that a suite stopped outright (SIGKILL, power loss) left: those whose process is gone and that are
    older than this run (stimuli.footage_writer.remove_stale). Returns them."""
    import re

    from stimuli.footage_writer import remove_stale

    scenes = Path(out) / "scenes"
    if not scenes.is_dir():
        return []
    # ".<scene>.partial-<pid>" (stimuli.footage_writer.atomic_folder), ".<scene>.track-<pid>" (stimuli.track's
    # rendering folder) and the one inside the other
    prefixes = {m.group(1) for e in os.scandir(scenes)
                if (m := re.fullmatch(r"(\..+\.(?:partial|track)-)\d+", e.name))}
    return [p for prefix in sorted(prefixes) for p in remove_stale(scenes, prefix)]


def ensure_rendered(folder: Path, settings: dict, render) -> Path:
    """``folder``, rendered by ``render(folder)`` unless it is already there with these ``settings``
    (kept beside it in ``<folder>.json``, written atomically after the render: a cut-off run never
    leaves a marker that reads as a scene to reuse)."""
    import shutil

    marker = folder.with_name(f"{folder.name}.json")
    settings = json.loads(json.dumps(settings, default=str))  # as the marker stores it (tuples -> lists)
    if not (folder.exists() and marker.exists() and json.loads(marker.read_text()) == settings):
        shutil.rmtree(folder, ignore_errors=True)
        render(folder)
        tmp = marker.with_name(f".{marker.name}.tmp")
        tmp.write_text(json.dumps(settings))
        os.replace(tmp, marker)
    return folder


def ensure_eye_scene(scenes: Path, name: str, cfg) -> Path:
    """The scene's eye footage, ``scenes/<name>-eye`` (rendered unless already there with these settings):
    the run configuration ``cfg`` (world, trajectory, IMU) ray-cast onto the default compound eyes at
    :data:`EYE_RATE_HZ` (stimuli.eye.make_eye_run; the folder appears only when complete)."""
    from lobula.compound_eye import CompoundEyeConfig
    from stimuli.eye import make_eye_run

    eye = CompoundEyeConfig()
    return ensure_rendered(scenes / f"{name}-eye", dict(run=cfg.to_dict(), eye=eye.to_dict(), rate_hz=EYE_RATE_HZ),
                           lambda f: make_eye_run(f, cfg, eye, EYE_RATE_HZ, progress=False))


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
        if f not in FAMILIES:
            raise ValueError(f"unknown family {f!r}; choose from {', '.join(FAMILIES)}")
    if duration_s <= skip_s:
        raise ValueError(f"--duration ({duration_s} s) must exceed --skip ({skip_s} s)")
    out = Path(out)
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
    plot_worlds(out, families, seeds[0])
    return ds, rows


def plot_worlds(out: Path, families, seed: int = 0) -> Path | None:
    """``worlds.png``: the middle frame of each family's scene at ``seed``, to see what was measured."""
    import cv2
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    frames = []
    for f in families:
        folder = out / "scenes" / f"{f}-s{seed}" / "frames"
        files = sorted(folder.glob("*.png")) if folder.is_dir() else []
        if files:
            frames.append((f, cv2.imread(str(files[len(files) // 2]), cv2.IMREAD_GRAYSCALE)))
    if not frames:
        return None
    cols = min(len(frames), 5)
    rows = -(-len(frames) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.2 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (f, img) in zip(axes.ravel(), frames):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        ax.set_title(f, fontsize=9)
    fig.suptitle(f"scene families (seed {seed}, middle frame)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, out / "worlds.png", dpi=150)
    plt.close(fig)
    return out / "worlds.png"


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
                    family_description=("family", [FAMILIES[f] for f in families],
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
             "| observable | lock-on (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["window"] != window:
            continue
        lock = r["lock_on_s_mean"]
        lock_s = (f"{lock:.1f}" if np.isfinite(lock) else "never") + (
            f" ({r['lock_on_s_n']} of {r['observable_fraction_n']} seeds)"
            if r["lock_on_s_n"] != r["observable_fraction_n"] else "")
        lines.append(f"| {r['family']} | {r['configuration']} | {ms(r, 'rmse_m_s')} | "
                     f"{ms(r, 'median_abs_error_m_s')} | {ms(r, 'coverage_2sigma', True)} | {ms(r, 'z95')} | "
                     f"{ms(r, 'observable_fraction', True)} | {lock_s} |")
    return "\n".join(lines)


def plot_suite(ds, path):
    """RMSE (after the skip and over the first 2 s), 2σ coverage and z95 per family and configuration.

    The coverage cannot tell a calibrated band from one far too wide (both hold ~100 %), so the last
    panel shows z95, the 95th percentile of |e|/σ (1.96 for a calibrated Gaussian band; log scale),
    shaded where a Gaussian error would put the ±2σ coverage at 85–99 % (z95 1.52–2.72, the project's
    target). Configurations that state no σ (z95 infinite) have no bar there."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .store import save_figure

    fams = [str(f) for f in ds.family.values]
    confs = [str(c) for c in ds.configuration.values]
    x = np.arange(len(fams))
    width = 0.8 / len(confs)
    cmap = plt.get_cmap("tab10")
    fig, axes = plt.subplots(4, 1, figsize=(max(11, 1.3 * len(fams) + 5), 13), sharex=True)
    for ax, win, metric, label in ((axes[0], "after_skip", "rmse_m_s", "RMSE after skip (m/s)"),
                                   (axes[1], "first_2s", "rmse_m_s", "RMSE, first 2 s (m/s)"),
                                   (axes[2], "after_skip", "coverage_2sigma", "truth within ±2σ (after skip)"),
                                   (axes[3], "after_skip", "z95", "z95: 95th pct of |e|/σ (after skip)")):
        for k, c in enumerate(confs):
            v = ds.value.sel(configuration=c, window=win, metric=metric).values  # (family, seed)
            v = np.where(np.isfinite(v), v, np.nan)  # z95 is infinite where no σ is stated
            ran = np.isfinite(ds.value.sel(configuration=c, metric="observable_fraction").values).any()
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
        else:
            ax.axhspan(0.85, 0.99, color="g", alpha=0.1, lw=0)
            ax.set_ylim(0, 1.02)
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1].set_xticks(x, fams)
    settings = json.loads(ds.attrs.get("suite", "{}")) if isinstance(ds.attrs.get("suite"), str) else {}
    fig.suptitle(f"lobula suite: {len(fams)} families × {ds.sizes['seed']} seeds "
                 f"({settings.get('duration_s', '?')} s, scale {settings.get('scale', '?')}, "
                 f"IMU {settings.get('imu', '?')}); bars: mean ± sd over seeds", y=0.995, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    save_figure(fig, path, dpi=150)
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
    from .parsers import COUNT, NONNEGATIVE, POSITIVE, seeds

    s = subparsers.add_parser("suite", help="accuracy suite: scene families x seeds, all configurations, baselines",
                              description="The accuracy suite: scene families × seeds, every configuration, "
                                          "beside baselines.")
    s.add_argument("--out", required=True, help="output folder (scenes, per-scene results, suite.nc, table, figure)")
    s.add_argument("--families", default="all",
                   help="comma-separated families, or all: " + "; ".join(f"{k}: {v}" for k, v in FAMILIES.items())
                   .replace("%", "%%"))
    s.add_argument("--seeds", type=seeds, default="3",
                   help="seeds per family: a count N (seeds 0..N-1) or a comma-separated list (e.g. 100,101 "
                        "for development seeds that the reported 0..N-1 never see; 7, for seed 7 alone)")
    s.add_argument("--duration", type=POSITIVE, default=10.0, help="seconds per scene")
    s.add_argument("--scale", type=POSITIVE, default=0.5,
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
