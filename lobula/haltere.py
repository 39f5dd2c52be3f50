"""Forward acceleration from an accelerometer (and gyroscope), as the fly's halteres would supply it.

An accelerometer reads specific force f = a − g (plus bias) in the camera frame.
Forward acceleration needs gravity removed, and the recording may start in motion,
so nothing assumes an initial rest. Instead: the gyroscope (its bias estimated where the
camera is still, :func:`gyro_bias`) tracks the camera's orientation, the
specific force is rotated into the first frame where gravity is a constant vector,
and that vector is the (zero-phase: whole-record; causal: running) mean, because the
platform's mean acceleration over a bounded track is ~0. The remaining constant
offset (mean acceleration Δv/T, accelerometer bias along z) is left for the readout's
bias state to absorb. Samples are then averaged over each flow interval and
interpolated to the flow's time stamps.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


GYRO_NOISE_DENSITY = np.radians(0.014)  # rad/s/√Hz, Bosch BMI055 (the D435i's IMU) datasheet


def gyro_bias(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False, window_s: float = 0.5,
              noise_density: float = GYRO_NOISE_DENSITY) -> np.ndarray:
    """Gyroscope bias (rad/s, (n, 3)) estimated where the camera is still — the one implementation.

    A sample is still when, over a window of ``window_s`` around it (causal: ending at it),
    the rate's standard deviation on every axis stays within 1.5× the white noise the
    sensor's ``noise_density`` allows, i.e. the camera is not turning. The bias is the
    mean rate over the still samples: online, those seen so far (0 before the first,
    the bias's expected value); offline, all of the record's. A camera that keeps turning
    gives no estimate rather than a wrong one: a mean rate over motion is the net angle
    turned divided by the time, not the bias.
    """
    time_s, gyro = np.asarray(time_s, float), np.asarray(gyro, float)
    n = len(time_s)
    if n < 3:
        return np.zeros((n, 3))
    rate = 1.0 / float(np.median(np.diff(time_s)))
    sigma = noise_density * np.sqrt(rate / 2)
    k = max(3, int(round(window_s * rate)))
    c1 = np.concatenate([np.zeros((1, 3)), np.cumsum(gyro, 0)])
    c2 = np.concatenate([np.zeros((1, 3)), np.cumsum(gyro ** 2, 0)])
    hi = np.arange(1, n + 1) if causal else np.minimum(np.arange(n) + k // 2 + 1, n)
    lo = np.maximum(hi - k, 0)
    m = (hi - lo)[:, None]
    mean = (c1[hi] - c1[lo]) / m
    var = np.maximum((c2[hi] - c2[lo]) / m - mean ** 2, 0.0)
    still = (m[:, 0] >= k) & np.all(var <= (1.5 * sigma) ** 2, axis=1)
    if causal:
        count = np.cumsum(still)[:, None]
        total = np.cumsum(gyro * still[:, None], 0)
        return np.where(count > 0, total / np.maximum(count, 1), 0.0)
    return np.broadcast_to(gyro[still].mean(0) if still.any() else np.zeros(3), (n, 3)).copy()


def orientation_from_gyro(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False) -> np.ndarray:
    """Rotations (n, 3, 3) taking camera-frame vectors at each sample into the first sample's frame.

    The gyro bias (:func:`gyro_bias`) is removed first.
    """
    n = len(time_s)
    w = gyro - gyro_bias(time_s, gyro, causal)
    dt = np.diff(time_s, prepend=time_s[0])
    steps = Rotation.from_rotvec(w * dt[:, None]).as_matrix()
    out = np.empty((n, 3, 3))
    r = np.eye(3)
    for k in range(n):  # composition is sequential; 3x3 products, ~µs each
        r = r @ steps[k]
        out[k] = r
    return out


def forward_acceleration(time_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray | None = None,
                         causal: bool = False) -> np.ndarray:
    """Gravity-free acceleration along the optical axis (m/s², (n,)) from specific force (n, 3).

    Raises ValueError for non-finite input. With ``gyro`` (n, 3) rad/s the gravity
    direction follows the camera's rotation; without it the orientation is taken as fixed.
    """
    if not (np.all(np.isfinite(accel)) and np.all(np.isfinite(time_s))):
        raise ValueError("accelerometer samples contain NaN or inf")
    n = len(time_s)
    rot = orientation_from_gyro(time_s, gyro, causal) if gyro is not None else np.broadcast_to(np.eye(3), (n, 3, 3))
    f0 = np.einsum("nij,nj->ni", rot, accel)  # specific force in the first frame
    g0 = -(np.cumsum(f0, 0) / np.arange(1, n + 1)[:, None] if causal else f0.mean(0, keepdims=True))
    g_cam = np.einsum("nji,nj->ni", rot, np.broadcast_to(g0, f0.shape))
    return (accel + g_cam)[:, 2]


def resample_to(times: np.ndarray, sample_t: np.ndarray, values: np.ndarray, window_s: float) -> np.ndarray:
    """Mean of ``values`` over [t − window/2, t + window/2] for each t in ``times``.

    Uses the integral of the linearly interpolated signal, so it works for any
    sample rate relative to the window and never reads outside the recording
    (times beyond it get the edge value).
    """
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (values[1:] + values[:-1]) * np.diff(sample_t))])
    lo = np.clip(times - window_s / 2, sample_t[0], sample_t[-1])
    hi = np.clip(times + window_s / 2, sample_t[0], sample_t[-1])
    integral = np.interp(hi, sample_t, cum) - np.interp(lo, sample_t, cum)
    width = hi - lo
    return np.where(width > 0, integral / np.where(width > 0, width, 1), np.interp(times, sample_t, values))
