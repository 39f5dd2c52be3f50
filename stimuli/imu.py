"""Synthetic IMU (accelerometer + gyroscope) in the camera optical frame.

The accelerometer reads specific force f = Rᵀ(a_world − g_world) + bias + noise, so a
level camera at rest reads about −9.81 m/s² on y (y points down). Noise densities
default to the Bosch BMI055 of the D435i (accelerometer 150 µg/√Hz, gyroscope
0.014 °/s/√Hz); per-sample standard deviation is density·√(rate/2).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class IMUConfig:
    rate_hz: float = 250.0
    accel_noise_density: float = 150e-6 * 9.80665     # m/s²/√Hz
    gyro_noise_density: float = np.radians(0.014)      # rad/s/√Hz
    accel_bias_std: float = 0.02                       # m/s², drawn once per run
    gyro_bias_std: float = np.radians(0.05)            # rad/s, drawn once per run
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def angular_velocity(rotation, t: np.ndarray, h: float = 1e-4) -> np.ndarray:
    """Body-frame angular velocity ω (rad/s), shape (n, 3), of rotation(t) -> (n, 3, 3).

    ω is the vee of Rᵀ·dR/dt, taken by a central difference of step h (s).
    """
    r0, r1, r = rotation(t - h), rotation(t + h), rotation(t)
    w = np.einsum("nji,njk->nik", r, (r1 - r0) / (2 * h))
    w = 0.5 * (w - np.swapaxes(w, -1, -2))
    return np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=-1)


def synthesize_imu(scene, duration_s: float, config: IMUConfig | None = None) -> dict[str, np.ndarray]:
    """Accelerometer and gyroscope samples for a :class:`~stimuli.scene.TrackScene`.

    Returns arrays time_s (n,), accel (n, 3) m/s², gyro (n, 3) rad/s, and the
    bias actually drawn, in the camera optical frame.
    """
    cfg = config or IMUConfig()
    rng = np.random.default_rng([cfg.seed, 2])
    t = np.arange(0.0, duration_s + 1e-9, 1.0 / cfg.rate_hz)
    rot = scene.rotation(t)
    a_world = np.zeros((t.size, 3))
    a_world[:, 2] = scene.trajectory.acceleration(t)
    # Specific force in the camera frame: Rᵀ(a − g).
    f = np.einsum("nji,nj->ni", rot, a_world - scene.gravity_world)
    omega = angular_velocity(scene.rotation, t)
    accel_bias = rng.normal(0.0, cfg.accel_bias_std, 3)
    gyro_bias = rng.normal(0.0, cfg.gyro_bias_std, 3)
    sa = cfg.accel_noise_density * np.sqrt(cfg.rate_hz / 2)
    sg = cfg.gyro_noise_density * np.sqrt(cfg.rate_hz / 2)
    accel = f + accel_bias + rng.normal(0.0, sa, f.shape)
    gyro = omega + gyro_bias + rng.normal(0.0, sg, omega.shape)
    return dict(time_s=t, accel=accel, gyro=gyro, accel_bias=accel_bias, gyro_bias=gyro_bias)
