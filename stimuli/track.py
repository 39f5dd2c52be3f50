"""Synthetic track runs: a trajectory, a scene and an IMU, written as a footage folder.

``make_track_run`` is what ``lobula scene`` calls: it replays a velocity profile (by
default the real FLIVVER trajectory when ``../shared`` is present (:func:`recorded_profile`), else a built-in
profile with rests, accelerations and reversals, or a seeded random smooth profile with
a given peak speed) through a :class:`TrackScene`, and synthesises the IMU from the same
trajectory and rotation. With ``flight="saccadic"`` the camera flies a seeded fly-like path instead
(:mod:`stimuli.flight`), whose own speed replaces the profile; with ``flight`` "drone", "road" or
"walking" it moves as that platform does (:mod:`stimuli.platforms`).
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lobula.version import provenance_attrs
from lobula.camera import PinholeCamera

from .flight import FlightConfig, saccadic_flight
from .footage_writer import write_footage
from .imu import IMUConfig, synthesize_imu
from .platforms import CONFIGS as PLATFORM_CONFIGS, PLATFORMS, platform_plan
from .scene import SceneConfig, TrackScene
from .trajectory import trajectory_from_function, trajectory_from_profile

# Resolved to the end: a checkout whose ../shared is a symlink names the same file, so the
# suite's scene markers (which store this path) agree across checkouts and worktrees.
REAL_PROFILE = (Path(__file__).resolve().parents[1].parent / "shared" / "data" / "flivver_d435i"
                / "velocity.csv").resolve()
#: Environment variable: "builtin" makes scenes that would follow the recorded profile follow the built-in
#: one even where the recording is beside the checkout, so that the same scene is rendered on every
#: machine (the test suite sets it: its verdict must not depend on an optional folder).
PROFILE_ENV = "LOBULA_PROFILE"


def recorded_profile() -> Path | None:
    """The recorded FLIVVER velocity profile (``REAL_PROFILE``) where it is present and ``$LOBULA_PROFILE``
    is not "builtin"; None where scenes follow :func:`builtin_profile` instead."""
    if os.environ.get(PROFILE_ENV, "").strip().lower() == "builtin" or not REAL_PROFILE.exists():
        return None
    return REAL_PROFILE


def builtin_profile(t: np.ndarray) -> np.ndarray:
    """A track-like velocity (m/s): 3 s at rest, then forward/backward sweeps of varying speed."""
    t = np.asarray(t, dtype=float)
    ramp = np.clip((t - 3.0) / 2.0, 0.0, 1.0)
    v = 0.45 * np.sin(2 * np.pi * t / 9.0) + 0.15 * np.sin(2 * np.pi * t / 3.7 + 1.0)
    return ramp ** 2 * (3 - 2 * ramp) * v


def random_profile(seed: int, duration_s: float, peak_m_s: float, start: str = "rest",
                   band_s: tuple[float, float] = (2.5, 9.0), n_components: int = 4):
    """A seeded smooth velocity profile (m/s) whose largest |v| over [0, duration_s] is peak_m_s.

    A sum of n_components sinusoids with periods drawn in band_s and random phases and
    weights. start: "rest" holds still for the first second and eases in over 1.5 s
    (v = a = 0 at t = 0); "motion" starts mid-stride (|v(0)| ≥ 40% of the peak).
    Returns a vectorised function of t (s).
    """
    if start not in ("rest", "motion"):
        raise ValueError(f"profile start must be 'rest' or 'motion', got {start!r}")
    if peak_m_s <= 0:
        raise ValueError(f"peak speed must be positive, got {peak_m_s}")
    rng = np.random.default_rng([seed, 5])
    for _ in range(100):
        per = rng.uniform(*band_s, n_components)
        ph = rng.uniform(0, 2 * np.pi, n_components)
        w = rng.uniform(0.3, 1.0, n_components)

        def raw(t, per=per, ph=ph, w=w):
            t = np.asarray(t, dtype=float)
            v = np.sum(w * np.sin(2 * np.pi * t[..., None] / per + ph), axis=-1)
            if start == "rest":
                ramp = np.clip((t - 1.0) / 1.5, 0.0, 1.0)
                v = ramp ** 2 * (3 - 2 * ramp) * v
            return v

        tt = np.arange(0.0, duration_s + 0.01, 0.01)
        peak = np.abs(raw(tt)).max()
        if start == "motion" and abs(raw(0.0)) < 0.4 * peak:
            continue  # redraw: this one starts nearly still
        if peak > 0:
            break
    k = peak_m_s / peak
    return lambda t: k * raw(t)


@dataclass
class TrackRunConfig:
    """A synthetic run: profile, window, camera scale, scene and IMU.

    profile: CSV path, or None for the built-in profile. random_peak_m_s: if set, a
    seeded random smooth profile (:func:`random_profile`, seed = scene seed) with this
    peak speed, starting as random_start says ("rest" or "motion"); it overrides profile.
    profile_scale: multiplies the profile's velocity (faster runs from the real one).
    lens: the lens the camera sees through, "MODEL:c1,c2,..." (:meth:`lobula.lens.LensDistortion.parse`;
    None: a pinhole); camera.json then carries its "distortion".
    flight: "track" (the camera moves along the straight track at the profile's velocity) or
    "saccadic" (it flies a seeded saccadic flight plan, :func:`stimuli.flight.saccadic_flight`, seed
    = scene seed, with flight_config's parameters (None: the defaults); the profile options are then
    not used), or "drone", "road" or "walking" (it moves as that platform does,
    :func:`stimuli.platforms.platform_plan`, seed = scene seed, flight_config its
    :class:`~stimuli.platforms.DroneConfig`, :class:`~stimuli.platforms.RoadConfig` or
    :class:`~stimuli.platforms.WalkConfig`; the profile options are not used either). :meth:`to_dict`
    leaves both out on the track, so a track run's configuration reads as it does without them.
    """

    profile: str | None = None
    start_s: float = 0.0
    duration_s: float = 30.0
    scale: float = 0.5
    constant_velocity_m_s: float | None = None
    random_peak_m_s: float | None = None
    random_start: str = "rest"
    profile_scale: float = 1.0
    camera_json: str | None = None
    lens: str | None = None
    scene: SceneConfig = field(default_factory=SceneConfig)
    imu: IMUConfig = field(default_factory=IMUConfig)
    depth_every: int = 10
    flight: str = "track"
    flight_config: FlightConfig | None = None

    FLIGHTS = ("track", "saccadic", *PLATFORMS)

    def __post_init__(self):
        if self.flight not in self.FLIGHTS:
            raise ValueError(f"unknown flight {self.flight!r}; choose one of {', '.join(self.FLIGHTS)}")
        if isinstance(self.flight_config, dict):  # read back from a to_dict()
            kind = PLATFORM_CONFIGS.get(self.flight, FlightConfig)
            self.flight_config = kind(**{k: tuple(v) if isinstance(v, list) else v
                                         for k, v in self.flight_config.items()})

    def to_dict(self) -> dict:
        d = asdict(self)
        # The scene's and the IMU's own forms, which leave out the fields they hold at a quiet default.
        d["scene"], d["imu"] = self.scene.to_dict(), self.imu.to_dict()
        if self.flight == "track" and self.flight_config is None:
            del d["flight"], d["flight_config"]
        return d


def build_track(cfg: TrackRunConfig) -> tuple[TrackScene, dict]:
    """The scene (camera, trajectory, world) and its IMU recording for a run configuration."""
    cam = PinholeCamera.from_json(cfg.camera_json) if cfg.camera_json else PinholeCamera()
    cam = cam.scaled(cfg.scale) if cfg.scale != 1 else cam
    from lobula.lens import LensDistortion

    lens = LensDistortion.parse(cfg.lens) if cfg.lens else None
    if cfg.flight == "saccadic":
        plan = saccadic_flight(cfg.scene.seed, cfg.duration_s, cfg.flight_config)
        scene = TrackScene(cam, plan.trajectory(), cfg.scene, lens=lens, flight=plan)
        return scene, synthesize_imu(scene, cfg.duration_s, cfg.imu)
    if cfg.flight in PLATFORMS:
        plan = platform_plan(cfg.flight, cfg.scene.seed, cfg.duration_s, cfg.flight_config)
        scene = TrackScene(cam, plan.trajectory(), cfg.scene, lens=lens, flight=plan)
        return scene, synthesize_imu(scene, cfg.duration_s, cfg.imu)
    k = float(cfg.profile_scale)
    if cfg.constant_velocity_m_s is not None:
        v0 = float(cfg.constant_velocity_m_s)
        traj = trajectory_from_function(lambda t: np.full_like(t, v0), cfg.duration_s)
    elif cfg.random_peak_m_s is not None:
        fn = random_profile(cfg.scene.seed, cfg.duration_s, cfg.random_peak_m_s, cfg.random_start)
        traj = trajectory_from_function(lambda t: k * fn(t), cfg.duration_s)
        traj.source = f"random(seed={cfg.scene.seed}, peak={cfg.random_peak_m_s} m/s, start={cfg.random_start})"
    elif cfg.profile:
        traj = trajectory_from_profile(cfg.profile, cfg.start_s, cfg.duration_s, scale=k)
    else:
        traj = trajectory_from_function(lambda t: k * builtin_profile(t + cfg.start_s), cfg.duration_s)
    scene = TrackScene(cam, traj, cfg.scene, lens=lens)
    imu = synthesize_imu(scene, cfg.duration_s, cfg.imu)
    return scene, imu


def make_track_run(folder, cfg: TrackRunConfig, progress: bool = True) -> Path:
    """Render a run into a footage folder (atomically) and return its path.

    With the IMU mounted rotated (IMUConfig.mount = "rotated"), imu.csv holds the IMU
    frame and camera.json gains "imu_to_camera" (v_cam = R @ v_imu, a list of 3 lists); with a rolling
    shutter (SceneConfig.rolling_shutter_s) it gains "rolling_shutter_s", the readout time (s) from the
    top row to the bottom, the frame's time stamp being its top row's.
    """
    from tqdm.auto import tqdm

    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise FileExistsError(f"{folder}: exists and is not empty; choose a new folder or delete it")
    scene, imu = build_track(cfg)
    rate = scene.camera.frame_rate_hz
    times = np.arange(0.0, cfg.duration_s - 1e-9, 1.0 / rate)
    if len(times) < 2:
        raise ValueError(f"a duration of {cfg.duration_s:g} s holds {len(times)} frame(s) at {rate:g} Hz: give at "
                         f"least {2.0 / rate:.3f} s")
    if not cfg.scene.rolling_shutter_s <= 1.0 / rate:
        raise ValueError(f"a rolling shutter of {cfg.scene.rolling_shutter_s:g} s reads out longer than a frame "
                         f"lasts ({1.0 / rate:.4f} s at {rate:g} Hz): give at most that")
    meta = dict(**provenance_attrs(), config=cfg.to_dict(), epipole=scene.epipole(0.0),
                accel_bias=imu["accel_bias"].tolist(), gyro_bias=imu["gyro_bias"].tolist(),
                trajectory=scene.trajectory.source,
                surfaces=[dict(axis=s.axis, offset=s.offset, bounds=s.bounds) for s in scene.surfaces])
    if cfg.imu.accel_bias_walk or cfg.imu.gyro_bias_walk:
        meta.update(accel_bias_end=imu["accel_bias_t"][-1].tolist(), gyro_bias_end=imu["gyro_bias_t"][-1].tolist())
    if cfg.imu.accel_scale_std or cfg.imu.accel_misalign_std or cfg.imu.gyro_scale_std or cfg.imu.gyro_misalign_std:
        meta.update(accel_matrix=imu["accel_matrix"].tolist(), gyro_matrix=imu["gyro_matrix"].tolist())
    extra = {}
    if cfg.imu.mount != "camera":
        extra["imu_to_camera"] = imu["imu_to_camera"].tolist()  # imu.csv holds the IMU frame
    if scene.lens is not None:
        extra["distortion"] = scene.lens.to_dict()
    if cfg.scene.rolling_shutter_s > 0:
        # s: top-to-bottom readout; each frame's time stamp is its top row's (stimuli.scene.TrackScene.row_times)
        extra["rolling_shutter_s"] = float(cfg.scene.rolling_shutter_s)
    # Keys added to camera.json after write_footage: write into a hidden sibling and rename only when
    # complete, so the folder never looks finished early.
    target = folder.parent / f".{folder.name}.track-{os.getpid()}" if extra else folder
    with tqdm(total=len(times), desc="rendering", unit="frame", disable=not progress, leave=False, mininterval=2) as bar:
        out = write_footage(target, scene, imu, times, meta, cfg.depth_every, progress=bar.update)
    if not extra:
        return out
    try:
        cam = json.loads((out / "camera.json").read_text())
        cam.update(extra)
        (out / "camera.json").write_text(json.dumps(cam, indent=1))
        if folder.exists():
            folder.rmdir()
        out.rename(folder)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return folder
