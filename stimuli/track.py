"""Synthetic track runs: a trajectory, a scene and an IMU, written as a footage folder.

``make_track_run`` is what ``lobula scene`` calls: it replays a velocity profile (by
default the real FLIVVER trajectory when ``../shared`` is present, else a built-in
profile with rests, accelerations and reversals) through a :class:`TrackScene`.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lobula import __version__
from lobula.camera import PinholeCamera

from .footage import write_footage
from .imu import IMUConfig, synthesize_imu
from .scene import SceneConfig, TrackScene
from .trajectory import trajectory_from_function, trajectory_from_profile

REAL_PROFILE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "flivver_d435i" / "velocity.csv"


def builtin_profile(t: np.ndarray) -> np.ndarray:
    """A track-like velocity (m/s): 3 s at rest, then forward/backward sweeps of varying speed."""
    t = np.asarray(t, dtype=float)
    ramp = np.clip((t - 3.0) / 2.0, 0.0, 1.0)
    v = 0.45 * np.sin(2 * np.pi * t / 9.0) + 0.15 * np.sin(2 * np.pi * t / 3.7 + 1.0)
    return ramp ** 2 * (3 - 2 * ramp) * v


@dataclass
class TrackRunConfig:
    """A synthetic run: profile (CSV path or None for the built-in one), window, camera scale."""

    profile: str | None = None
    start_s: float = 0.0
    duration_s: float = 30.0
    scale: float = 0.5
    constant_velocity_m_s: float | None = None
    camera_json: str | None = None
    scene: SceneConfig = field(default_factory=SceneConfig)
    imu: IMUConfig = field(default_factory=IMUConfig)
    depth_every: int = 10

    def to_dict(self) -> dict:
        return asdict(self)


def build_track(cfg: TrackRunConfig) -> tuple[TrackScene, dict]:
    """The scene (camera, trajectory, world) and its IMU recording for a run configuration."""
    cam = PinholeCamera.from_json(cfg.camera_json) if cfg.camera_json else PinholeCamera()
    cam = cam.scaled(cfg.scale) if cfg.scale != 1 else cam
    if cfg.constant_velocity_m_s is not None:
        v0 = float(cfg.constant_velocity_m_s)
        traj = trajectory_from_function(lambda t: np.full_like(t, v0), cfg.duration_s)
    elif cfg.profile:
        traj = trajectory_from_profile(cfg.profile, cfg.start_s, cfg.duration_s)
    else:
        traj = trajectory_from_function(lambda t: builtin_profile(t + cfg.start_s), cfg.duration_s)
    scene = TrackScene(cam, traj, cfg.scene)
    imu = synthesize_imu(scene, cfg.duration_s, cfg.imu)
    return scene, imu


def make_track_run(folder, cfg: TrackRunConfig, progress: bool = True) -> Path:
    """Render a run into a footage folder (atomically) and return its path."""
    from tqdm.auto import tqdm

    scene, imu = build_track(cfg)
    times = np.arange(0.0, cfg.duration_s - 1e-9, 1.0 / scene.camera.frame_rate_hz)
    meta = dict(lobula_version=__version__, config=cfg.to_dict(), epipole=scene.epipole(0.0),
                accel_bias=imu["accel_bias"].tolist(), gyro_bias=imu["gyro_bias"].tolist(),
                trajectory=scene.trajectory.source)
    with tqdm(total=len(times), desc="rendering", unit="frame", disable=not progress, leave=False, mininterval=2) as bar:
        return write_footage(folder, scene, imu, times, meta, cfg.depth_every, progress=bar.update)
