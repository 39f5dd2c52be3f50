"""Synthetic IMU (accelerometer + gyroscope), exact to the scene's trajectory and rotation.

The accelerometer reads specific force f = Rᵀ(a_world − g_world), so a level camera at
rest reads about −9.81 m/s² on y (y points down). The gyroscope reads the body-frame
angular velocity ω of the same rotation R(t) that renders the frames.

Two error models (:class:`IMUConfig`):

* **ideal** (the default): a constant bias drawn once per run plus white
  noise, in the camera optical frame;
* **realistic** (:meth:`IMUConfig.realistic`): on top of that, a bias random walk
  (the bias drifts, so no whole-record mean removes it), per-axis scale-factor errors
  and axis misalignment (a sensor matrix M = (I + S)(I + A), S diagonal, A small
  off-diagonal), and a camera–IMU rotation: samples are written in the IMU's own frame
  and ``imu_to_camera`` (v_cam = R @ v_imu) goes to camera.json.

Either model can add a platform's vibration (``vibration_rms_m_s2``: a drone's propellers): each of
``vibration_rotors`` rotors shakes the sensor at its blade-pass rate, near ``vibration_hz``. The sensor
samples it at its own rate with no anti-alias filter in front, so a vibration above half the sample rate
folds down into the recorded band (250 Hz sampling records 200 Hz as 50 Hz), as on a real flight controller.

Figures are BMI055-like (the IMU of the Intel RealSense D435i). White noise from the
Bosch BMI055 data sheet (BST-BMI055-DS000): accelerometer 150 µg/√Hz, gyroscope
0.014 °/s/√Hz; per-sample standard deviation is density·√(rate/2). The data sheet gives
sensitivity tolerances of about ±1 % and cross-axis sensitivity of about ±1 %, so scale
factors and misalignments are drawn with 1 % and 0.5 % standard deviations. The data
sheet gives no bias random walk; the figures used are those of the usual Kalibr/VIO
configurations for the D435i's BMI055 (accelerometer ≈ 1e-3 m/s³/√Hz, gyroscope
≈ 4e-5 rad/s²/√Hz, Allan-variance values inflated for unmodelled effects). Initial
biases: 0.05 m/s² and 0.25 °/s (a factory-calibrated unit; the raw data-sheet zero
offsets are ±70 mg and ±1 °/s).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np


@dataclass
class IMUConfig:
    """IMU sampling and error model (SI units; the defaults are the ideal model).

    rate_hz: sample rate. *_noise_density: white noise. *_bias_std: initial bias, drawn
    once per run. *_bias_walk: bias random walk (m/s³/√Hz, rad/s²/√Hz; 0 = constant).
    *_scale_std: per-axis scale-factor error std (fraction). *_misalign_std: axis
    misalignment std (rad, off-diagonal of the sensor matrix). mount: "camera" (the IMU
    axes are the camera's: imu.csv in the camera frame, nothing written to camera.json)
    or "rotated" (the IMU is mounted with its x forward, y left, z up — a ROS body frame —
    plus a mount error of mount_error_deg std per axis; imu.csv is then in the IMU frame
    and camera.json carries imu_to_camera). seed: the IMU's random stream.
    vibration_rms_m_s2: rms of the platform's vibration on each accelerometer axis (m/s²; 0 = none);
    vibration_hz: its frequency (Hz), the rotors' rates spread by ±vibration_spread (a fraction) around
    it; vibration_rotors: how many rotors (module doc).
    """

    rate_hz: float = 250.0
    accel_noise_density: float = 150e-6 * 9.80665     # m/s²/√Hz
    gyro_noise_density: float = np.radians(0.014)      # rad/s/√Hz
    accel_bias_std: float = 0.02                       # m/s², drawn once per run
    gyro_bias_std: float = np.radians(0.05)            # rad/s, drawn once per run
    accel_bias_walk: float = 0.0                       # m/s³/√Hz
    gyro_bias_walk: float = 0.0                        # rad/s²/√Hz
    accel_scale_std: float = 0.0
    gyro_scale_std: float = 0.0
    accel_misalign_std: float = 0.0                    # rad
    gyro_misalign_std: float = 0.0                     # rad
    mount: str = "camera"
    mount_error_deg: float = 1.0
    seed: int = 0
    vibration_rms_m_s2: float = 0.0                    # m/s² rms per axis
    vibration_hz: float = 100.0                        # Hz
    vibration_spread: float = 0.03
    vibration_rotors: int = 4

    #: the vibration's fields: left out of :meth:`to_dict` when there is no vibration, so the configuration
    #: of an IMU without one reads as it does without these fields
    VIBRATION_FIELDS = ("vibration_rms_m_s2", "vibration_hz", "vibration_spread", "vibration_rotors")

    MODELS = ("ideal", "realistic")
    MOUNTS = ("camera", "rotated")

    def __post_init__(self):
        if self.mount not in self.MOUNTS:
            raise ValueError(f"unknown IMU mount {self.mount!r}; choose camera or rotated")
        if self.rate_hz <= 0:
            raise ValueError(f"IMU rate must be positive, got {self.rate_hz}")
        if self.vibration_rms_m_s2 < 0 or self.vibration_hz <= 0 or self.vibration_rotors < 1:
            raise ValueError("vibration_rms_m_s2 must be >= 0, vibration_hz > 0 and vibration_rotors >= 1")

    @classmethod
    def realistic(cls, seed: int = 0, mount: str = "camera", **kw) -> "IMUConfig":
        """BMI055-like errors (module doc): drifting biases, scale factors, misalignment."""
        return replace(cls(seed=seed, mount=mount), accel_bias_std=0.05, gyro_bias_std=np.radians(0.25),
                       accel_bias_walk=1e-3, gyro_bias_walk=4e-5, accel_scale_std=0.01, gyro_scale_std=0.01,
                       accel_misalign_std=0.005, gyro_misalign_std=0.005, **kw)

    @classmethod
    def model(cls, name: str, seed: int = 0, mount: str = "camera") -> "IMUConfig":
        """The named error model: "ideal" or "realistic"."""
        if name == "ideal":
            return cls(seed=seed, mount=mount)
        if name == "realistic":
            return cls.realistic(seed, mount)
        raise ValueError(f"unknown IMU model {name!r}; choose ideal or realistic")

    def to_dict(self) -> dict:
        d = asdict(self)
        if not self.vibration_rms_m_s2:
            for k in self.VIBRATION_FIELDS:
                del d[k]
        return d


#: IMU axes (x forward, y left, z up) in the camera optical frame (x right, y down, z forward):
#: columns are the IMU axes, so v_cam = BODY_TO_CAMERA @ v_imu.
BODY_TO_CAMERA = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def angular_velocity(rotation, t: np.ndarray, h: float = 1e-4) -> np.ndarray:
    """Body-frame angular velocity ω (rad/s), shape (n, 3), of rotation(t) -> (n, 3, 3).

    ω is the vee of Rᵀ·dR/dt, taken by a central difference of step h (s).
    """
    r0, r1, r = rotation(t - h), rotation(t + h), rotation(t)
    w = np.einsum("nji,njk->nik", r, (r1 - r0) / (2 * h))
    w = 0.5 * (w - np.swapaxes(w, -1, -2))
    return np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=-1)


def small_rotation(v: np.ndarray) -> np.ndarray:
    """The rotation matrix exp([v]×) for a rotation vector v (rad), by Rodrigues' formula."""
    th = float(np.linalg.norm(v))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(th) / th * k + (1 - np.cos(th)) / th ** 2 * (k @ k)


def sensor_matrix(rng: np.random.Generator, scale_std: float, misalign_std: float) -> np.ndarray:
    """M = (I + S)(I + A): S diagonal scale-factor errors, A off-diagonal misalignment (rad)."""
    s = np.diag(rng.normal(0.0, scale_std, 3)) if scale_std else np.zeros((3, 3))
    a = rng.normal(0.0, misalign_std, (3, 3)) if misalign_std else np.zeros((3, 3))
    np.fill_diagonal(a, 0.0)
    return (np.eye(3) + s) @ (np.eye(3) + a)


def bias_random_walk(rng: np.random.Generator, n: int, rate_hz: float, walk: float, b0: np.ndarray) -> np.ndarray:
    """A bias (n, 3) starting at b0 that random-walks with density ``walk`` (units/s/√Hz).

    Each step adds N(0, walk²·dt): after T seconds the std of the drift is walk·√T.
    """
    if not walk:
        return np.broadcast_to(b0, (n, 3)).copy()
    steps = rng.normal(0.0, walk * np.sqrt(1.0 / rate_hz), (n, 3))
    steps[0] = 0.0
    return b0 + np.cumsum(steps, axis=0)


def vibration(cfg: IMUConfig, t: np.ndarray) -> np.ndarray:
    """The platform's vibration (m/s²) at the sample times t (n,) (s), shape (n, 3), camera axes.

    Each rotor r runs at f_r = vibration_hz·(1 + vibration_spread·u_r), u_r uniform in [-1, 1], and shakes
    every axis with its own phase; each axis's share of the rotors is drawn (weights summing to one) so
    that every axis's rms is vibration_rms_m_s2. Evaluated at t itself: no filter before the sampling.
    """
    if not cfg.vibration_rms_m_s2:
        return np.zeros((np.size(t), 3))
    rng = np.random.default_rng([cfg.seed, 6])  # its own stream: the other draws do not move
    k = cfg.vibration_rotors
    freq = cfg.vibration_hz * (1.0 + cfg.vibration_spread * rng.uniform(-1.0, 1.0, k))  # (k,)
    phase = rng.uniform(0.0, 2 * np.pi, (3, k))
    amp = cfg.vibration_rms_m_s2 * np.sqrt(2.0 * rng.dirichlet(np.ones(k), 3))  # (3, k): Σ A²/2 = rms²
    return np.sum(amp * np.sin(2 * np.pi * freq * np.asarray(t, float)[:, None, None] + phase), axis=-1)


def synthesize_imu(scene, duration_s: float, config: IMUConfig | None = None) -> dict[str, np.ndarray]:
    """Accelerometer and gyroscope samples for a :class:`~stimuli.scene.TrackScene`.

    On the straight track the world acceleration is the trajectory's, along z; a scene flying a
    :class:`stimuli.flight.FlightPlan` gives its 3-D world acceleration (with the saccades'
    centripetal part) and its exact angular velocity (:meth:`~stimuli.scene.TrackScene.angular_velocity`).

    Returns time_s (n,), accel (n, 3) m/s², gyro (n, 3) rad/s in the IMU frame (the
    camera optical frame when config.mount == "camera"), the exact camera-frame
    specific force and angular velocity (accel_true, gyro_true), the biases
    (accel_bias, gyro_bias: (3,) initial values, the ideal model's constants;
    accel_bias_t, gyro_bias_t: (n, 3) over time), the sensor matrices (accel_matrix,
    gyro_matrix: IMU-frame reading = M @ true + bias + noise) and imu_to_camera (3, 3); with a vibration
    (IMUConfig.vibration_rms_m_s2), accel_vibration (n, 3): the sensor's own shaking in the camera frame
    (:func:`vibration`), in the readings but not in accel_true (the camera's motion).
    """
    cfg = config or IMUConfig()
    rng = np.random.default_rng([cfg.seed, 2])
    t = np.arange(0.0, duration_s + 1e-9, 1.0 / cfg.rate_hz)
    rot = scene.rotation(t)
    flight = getattr(scene, "flight", None)
    if flight is not None:  # a 3-D path: the world acceleration and the exact body rates
        a_world = scene.world_acceleration(t)
    else:
        a_world = np.zeros((t.size, 3))
        a_world[:, 2] = scene.trajectory.acceleration(t)
    # Specific force in the camera frame: Rᵀ(a − g).
    f = np.einsum("nji,nj->ni", rot, a_world - scene.gravity_world)
    omega = scene.angular_velocity(t) if flight is not None else angular_velocity(scene.rotation, t)
    # The ideal model's draws come first and in the same order as before (same bytes).
    accel_bias = rng.normal(0.0, cfg.accel_bias_std, 3)
    gyro_bias = rng.normal(0.0, cfg.gyro_bias_std, 3)
    sa = cfg.accel_noise_density * np.sqrt(cfg.rate_hz / 2)
    sg = cfg.gyro_noise_density * np.sqrt(cfg.rate_hz / 2)
    noise_a = rng.normal(0.0, sa, f.shape)
    noise_g = rng.normal(0.0, sg, omega.shape)
    # The realistic model's errors: their own stream, so the ideal draws above stay put.
    rng2 = np.random.default_rng([cfg.seed, 4])
    r_ic = np.eye(3)
    if cfg.mount == "rotated":
        r_ic = BODY_TO_CAMERA @ small_rotation(rng2.normal(0.0, np.radians(cfg.mount_error_deg), 3))
    m_a = sensor_matrix(rng2, cfg.accel_scale_std, cfg.accel_misalign_std)
    m_g = sensor_matrix(rng2, cfg.gyro_scale_std, cfg.gyro_misalign_std)
    ba = bias_random_walk(rng2, t.size, cfg.rate_hz, cfg.accel_bias_walk, accel_bias)
    bg = bias_random_walk(rng2, t.size, cfg.rate_hz, cfg.gyro_bias_walk, gyro_bias)
    # The sensor's specific force: the camera's plus the vibration of the board it sits on (micrometres of
    # motion at these frequencies: the camera's truth does not see it).
    vib = vibration(cfg, t)
    f_sensor = f + vib if cfg.vibration_rms_m_s2 else f
    # True quantities in the IMU frame: v_imu = Rᵀ v_cam.
    f_imu, w_imu = f_sensor @ r_ic, omega @ r_ic
    if cfg.mount == "camera" and not (cfg.accel_scale_std or cfg.accel_misalign_std):
        accel = f_sensor + ba + noise_a
    else:
        accel = f_imu @ m_a.T + ba + noise_a
    if cfg.mount == "camera" and not (cfg.gyro_scale_std or cfg.gyro_misalign_std):
        gyro = omega + bg + noise_g
    else:
        gyro = w_imu @ m_g.T + bg + noise_g
    return dict(time_s=t, accel=accel, gyro=gyro, accel_true=f, gyro_true=omega,
                accel_bias=accel_bias, gyro_bias=gyro_bias, accel_bias_t=ba, gyro_bias_t=bg,
                accel_matrix=m_a, gyro_matrix=m_g, imu_to_camera=r_ic, accel_vibration=vib)
