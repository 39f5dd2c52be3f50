"""One scene of the accuracy suite: what is run on it, and the job that runs it.

Which scene a family's seed is (:func:`family_config`), which estimator a configuration name is
(:data:`CONFIGURATIONS`, :data:`EYE_CONFIGURATIONS`, :func:`velocity_config`), the IMU-only baseline
(:func:`dead_reckoning`), and :func:`run_scene_job`: render the scene (and the eye's footage) unless
it is already there, run every configuration and baseline on it, score them
(:func:`experiments.suite_metrics.score_series`) and keep the series and the result.
"""
from __future__ import annotations

import json
import os
import time as _time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .families import ALL_FAMILIES, FAMILIES  # noqa: F401  (the families; light: the parser shares them)
from .suite_metrics import score_series


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
    from dataclasses import replace

    from stimuli.imu import IMUConfig
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, recorded_profile

    if family not in ALL_FAMILIES:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(ALL_FAMILIES)}")
    s = family_seed(family, seed)
    rng = np.random.default_rng([s, 9])
    scene = dict(seed=s)
    run = dict(duration_s=duration_s, scale=scale)
    vibration = {}  # the IMU's platform vibration (stimuli.imu.IMUConfig), none but the drone's
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
    elif family == "saccadic":
        # The fly's own flight draws its speed (stimuli.flight); the world turns with the seed: indoors, a corridor,
        # outdoors at the fly's scale.
        scene.update(world=("panels", "corridor", "meadow")[seed % 3])
        run.update(flight="saccadic")
    elif family == "drone":
        # Metre-scale texture (fields, tracks, roofs): what a camera 3-30 m up resolves. The gimbal's tilt is
        # the world's off-axis mount; the vibration is the IMU's (stimuli.imu.vibration).
        scene.update(world="ground", ground_height_m=(3.0, 30.0), ground_backdrop_m=(100.0, 2000.0),
                     ground_backdrop_height_m=(30.0, 300.0), off_axis_pitch_deg=float(rng.uniform(0.0, 20.0)),
                     texture_wavelengths_m=(0.3, 20.0), texture_texel_m=0.05, roadside_spacing_m=30.0,
                     roadside_ahead_m=300.0, roadside_lateral_m=(5.0, 150.0), roadside_width_m=(3.0, 30.0),
                     roadside_height_m=(3.0, 25.0))
        run.update(flight="drone")
        vibration = dict(vibration_rms_m_s2=float(rng.uniform(0.3, 1.0)), vibration_hz=float(rng.uniform(50.0, 200.0)))
    elif family == "road":
        scene.update(world="ground", ground_height_m=(1.0, 2.0), texture_wavelengths_m=(0.05, 3.0),
                     texture_texel_m=0.01, roadside_spacing_m=15.0, roadside_ahead_m=120.0,
                     roadside_lateral_m=(2.5, 12.0), roadside_width_m=(0.3, 10.0), roadside_height_m=(1.0, 8.0))
        run.update(flight="road")
    elif family == "walking":
        world = ("ground", "corridor")[seed % 2]
        scene.update(world=world)
        if world == "ground":
            scene.update(ground_height_m=(1.0, 1.6), roadside_spacing_m=6.0, roadside_ahead_m=40.0,
                         roadside_lateral_m=(1.0, 6.0), roadside_width_m=(0.3, 4.0), roadside_height_m=(0.5, 4.0))
        run.update(flight="walking")
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
    imu_cfg = IMUConfig.model(imu, seed=s, mount=imu_mount)
    return TrackRunConfig(scene=SceneConfig(**scene), imu=replace(imu_cfg, **vibration) if vibration else imu_cfg,
                          **run)


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
def scene_name(family: str, seed: int) -> str:
    """A scene's name in the suite's folders (``scenes/``, ``series/``, ``results/``)."""
    return f"{family}-s{seed}"


def series_key(configuration: str) -> str:
    """A configuration's name in ``series/<scene>.nc``'s variables (``v_hat__<key>``, ``v_hat_all__<key>``,
    ``v_std__<key>``)."""
    return configuration.replace(" ", "_").replace("=", "-")


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
        return scene_name(self.family, self.seed)

    def key(self) -> str:
        """What a stored result must match to be reused: the settings and the code's git commit."""
        from lobula.version import git_commit

        d = dict(self.__dict__)
        d.pop("out")
        d["code"] = git_commit()
        return json.dumps(d, sort_keys=True)


def run_scene_job(job: SceneJob) -> dict:
    """Render (unless already there), run every configuration, write series and result; return the result."""
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    from .store import write_netcdf, write_text

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
    series, errors, wall, eye_render_s = _run_configurations(job, cfg, footage)
    metrics = {}
    # Baselines on the frame times the camera's estimator used (or all frames if it ran none: the
    # eye's own steps are 500 Hz, its series is interpolated onto these for the file).
    t_ref = next((v[0] for k, v in series.items() if k not in EYE_CONFIGURATIONS), footage.times)
    v_true_ref = np.interp(t_ref, tt, vt)
    if "zero" in job.configurations:
        series["zero"] = (t_ref, np.zeros_like(t_ref), None, np.zeros_like(t_ref))
    if "imu dead reckoning" in job.configurations:
        v_dr = dead_reckoning(footage, t_ref, float(np.interp(t_ref[0], tt, vt)))
        series["imu dead reckoning"] = (t_ref, v_dr, None, v_dr)
    for name, (t, v_hat, v_std, v_all) in series.items():
        metrics[name] = score_series(t, v_hat, v_std, np.interp(t, tt, vt), job.skip_s, v_all)
    write_netcdf(_series_dataset(job, cfg, series, t_ref, v_true_ref), out / "series" / f"{job.name}.nc")
    res = dict(key=job.key(), family=job.family, seed=job.seed, scene_seed=cfg.scene.seed, metrics=metrics,
               errors=errors, render_s=render_s, eye_render_s=eye_render_s, estimator_s=wall,
               scene_config=cfg.to_dict(),
               peak_speed_m_s=float(np.abs(vt).max()))
    write_text(res_path, json.dumps(res, default=str))
    return res


def _run_configurations(job: SceneJob, cfg, footage) -> tuple[dict, dict, dict, float]:
    """Every configuration of ``job`` but the baselines on its scene (``footage``, run configuration ``cfg``).

    Returns ({name: (t (s), v̂ (m/s, NaN where unobservable), v_std (m/s), v̂ answered or carried (m/s, NaN
    where unknown))}, {name: why it did not run}, {name: wall time (s)}, the seconds spent rendering the eye's
    footage).
    """
    from lobula.readout import answered_velocity
    from lobula.velocity import estimate_velocity

    out = Path(job.out)
    series, errors, wall = {}, {}, {}
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
        v_hat = answered_velocity(ds)
        series[name] = (t, v_hat, ds.v_std.values, ds.v_hat.values)
        wall[name] = _time.perf_counter() - t1
    return series, errors, wall, eye_render_s


def _series_dataset(job: SceneJob, cfg, series: dict, t_ref: np.ndarray, v_true_ref: np.ndarray):
    """``series/<scene>.nc``: the true forward velocity ``v_true_ref`` (m/s) and each series' v̂ where answered,
    v̂ answered or carried, and stated std (m/s) on the reference times ``t_ref`` (s); ``series`` as
    :func:`_run_configurations` gives it, baselines added."""
    import xarray as xr

    # Series file: every configuration on the reference times (the paper stamps pairs at their
    # first frame, so its times differ; interpolated for the file only, scored on its own).
    data = {"v_true": ("time", v_true_ref, {"units": "m/s", "long_name": "ground-truth forward velocity"})}
    for name, (t, v_hat, v_std, v_all) in series.items():
        key = series_key(name)
        data[f"v_hat__{key}"] = ("time", np.interp(t_ref, t, v_hat, left=np.nan, right=np.nan),
                                 {"units": "m/s", "long_name": f"estimated forward velocity, {name} (NaN: not "
                                                               "observable)"})
        data[f"v_hat_all__{key}"] = ("time", np.interp(t_ref, t, v_all, left=np.nan, right=np.nan),
                                     {"units": "m/s", "long_name": f"estimated forward velocity, {name}, answered "
                                                                   "or carried by the accelerometer (NaN: unknown)"})
        if v_std is not None:
            data[f"v_std__{key}"] = ("time", np.interp(t_ref, t, v_std, left=np.nan, right=np.nan),
                                     {"units": "m/s", "long_name": f"stated std of v_hat, {name}"})
    return xr.Dataset(data, coords={"time": ("time", t_ref, {"units": "s", "long_name": "frame time on the "
                                                                                          "footage clock"})},
                      attrs=dict(scene=job.name, config=json.dumps(cfg.to_dict(), default=str)))


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


def folder_fingerprint(folder: Path) -> dict:
    """The sizes of what ``folder`` holds: {file: bytes} for its files, {sub/: [files, bytes]} for each
    subfolder's files; what a rendered scene is checked against before it is reused."""
    out = {}
    for e in sorted(os.scandir(folder), key=lambda e: e.name):
        if e.is_file():
            out[e.name] = e.stat().st_size
        elif e.is_dir():
            sizes = [f.stat().st_size for f in os.scandir(e.path) if f.is_file()]
            out[e.name + "/"] = [len(sizes), sum(sizes)]
    return out


def ensure_rendered(folder: Path, settings: dict, render) -> Path:
    """``folder``, rendered by ``render(folder)`` unless it is already there with these ``settings`` and its
    files as the render left them (both kept beside it in ``<folder>.json``, written atomically after the
    render: a cut-off run never leaves a marker that reads as a scene to reuse, and a file since cut short
    or removed has the scene rendered again)."""
    import shutil

    marker = folder.with_name(f"{folder.name}.json")
    settings = json.loads(json.dumps(settings, default=str))  # as the marker stores it (tuples -> lists)
    try:
        kept = json.loads(marker.read_text()) if folder.is_dir() else None
        reuse = kept == dict(settings=settings, files=folder_fingerprint(folder))
    except (OSError, ValueError):
        reuse = False
    if not reuse:
        shutil.rmtree(folder, ignore_errors=True)
        render(folder)
        tmp = marker.with_name(f".{marker.name}.tmp")
        try:
            tmp.write_text(json.dumps(dict(settings=settings, files=folder_fingerprint(folder))))
            os.replace(tmp, marker)
        except BaseException:  # a full disk or a signal: no partial marker
            tmp.unlink(missing_ok=True)
            raise
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
