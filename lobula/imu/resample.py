"""IMU samples brought to the frames' times: window means of the linearly interpolated signal."""
from __future__ import annotations

import numpy as np

def turn_rate(times: np.ndarray, sample_t: np.ndarray, gyro: np.ndarray, window_s: float) -> np.ndarray:
    """The body's turn rate |ω| (rad/s, (n,)) at ``times``: the gyro's (haltere's) rate magnitude,
    gyro (m, 3) rad/s sampled at ``sample_t`` (m,) s, averaged over ``window_s`` about each time
    (:func:`resample_to`). The readout widens its acceleration noise by it
    (``ReadoutConfig.accel_turn_noise``): gravity leaks into the accelerometer through attitude
    error while turning."""
    return resample_to(times, sample_t, np.linalg.norm(gyro, axis=1), window_s)


def resample_to(times: np.ndarray, sample_t: np.ndarray, values: np.ndarray, window_s: float) -> np.ndarray:
    """Mean of ``values`` over [t − window/2, t + window/2] for each t in ``times``.

    times (n,) s; values (m,) sampled at ``sample_t`` (m,) s, in any units (the result's, (n,));
    window_s: s, one for all or one per time (n,). Uses the integral of the linearly interpolated signal, so it works for any
    sample rate relative to the window and never reads outside the recording
    (times beyond it get the edge value).
    """
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (values[1:] + values[:-1]) * np.diff(sample_t))])
    lo = np.clip(times - window_s / 2, sample_t[0], sample_t[-1])
    hi = np.clip(times + window_s / 2, sample_t[0], sample_t[-1])
    integral = np.interp(hi, sample_t, cum) - np.interp(lo, sample_t, cum)
    width = hi - lo
    return np.where(width > 0, integral / np.where(width > 0, width, 1), np.interp(times, sample_t, values))
