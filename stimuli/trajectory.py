"""Forward-motion trajectories: a velocity profile made smooth, with exact a(t), v(t), s(t).

A profile comes from a function of time or from a CSV such as the real
``velocity.csv`` of the FLIVVER track run. The samples are smoothed (their
tracking-camera quantisation would otherwise make the derivative meaningless) and
interpolated by a cubic spline, whose derivative and antiderivative give the exact
acceleration and position used by the renderer and the IMU synthesiser, so all three
agree to float precision.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d


@dataclass
class Trajectory:
    """Motion along a straight track, starting at position 0 at time 0.

    ``velocity(t)`` (m/s), ``acceleration(t)`` (m/s^2) and ``position(t)`` (m) are
    vectorised over ``t`` (s); ``duration_s`` bounds the valid time range.
    """

    spline: CubicSpline
    duration_s: float
    source: str

    def velocity(self, t):
        return self.spline(np.asarray(t, dtype=float))

    def acceleration(self, t):
        return self.spline(np.asarray(t, dtype=float), 1)

    def position(self, t):
        return self._position(np.asarray(t, dtype=float)) - self._position(0.0)

    def __post_init__(self):
        self._position = self.spline.antiderivative()

    def position_range(self, dt: float = 0.01) -> tuple[float, float]:
        s = self.position(np.arange(0.0, self.duration_s + dt, dt))
        return float(s.min()), float(s.max())


def trajectory_from_function(velocity: Callable[[np.ndarray], np.ndarray], duration_s: float,
                             sample_hz: float = 200.0) -> Trajectory:
    """A trajectory whose forward velocity (m/s) is ``velocity(t)`` for t in [0, duration_s]."""
    t = np.arange(0.0, duration_s + 2.0 / sample_hz, 1.0 / sample_hz)
    return Trajectory(CubicSpline(t, np.asarray(velocity(t), dtype=float)), float(duration_s),
                      source="function")


def read_velocity_profile(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``time_s`` and a velocity column (``v_true_m_s`` or ``v_forward_m_s``) from a CSV."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: velocity profile not found") from None
    if not rows:
        raise ValueError(f"{path}: empty velocity profile")
    col = next((c for c in ("v_true_m_s", "v_forward_m_s", "velocity_m_s") if c in rows[0]), None)
    if col is None or "time_s" not in rows[0]:
        raise ValueError(f"{path}: needs columns time_s and v_true_m_s (or v_forward_m_s); has {list(rows[0])}")
    t = np.array([float(r["time_s"]) for r in rows])
    v = np.array([float(r[col]) for r in rows])
    if not np.all(np.isfinite(t)) or not np.all(np.isfinite(v)):
        raise ValueError(f"{path}: non-finite values in time_s or {col}")
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{path}: time_s must increase strictly")
    return t, v


def trajectory_from_profile(path: str | Path, start_s: float = 0.0, duration_s: float = 30.0,
                            smoothing_s: float = 0.1, scale: float = 1.0) -> Trajectory:
    """The window [start_s, start_s + duration_s] of a CSV velocity profile.

    smoothing_s: standard deviation (s) of the Gaussian that smooths the samples
    before the spline; it removes tracking quantisation, not the motion.
    scale: multiplies the velocity (a faster run of the same shape).
    """
    t, v = read_velocity_profile(path)
    if start_s < t[0] or start_s + duration_s > t[-1] + 1e-9:
        raise ValueError(f"{path}: window {start_s}..{start_s + duration_s} s is outside "
                         f"the profile's {t[0]:.2f}..{t[-1]:.2f} s")
    dt = float(np.median(np.diff(t)))
    v_s = gaussian_filter1d(v, smoothing_s / dt, mode="nearest") if smoothing_s > 0 else v
    keep = (t >= start_s - 1.0) & (t <= start_s + duration_s + 1.0)
    src = f"{path}[{start_s}:{start_s + duration_s}]" + (f"x{scale:g}" if scale != 1 else "")
    v_s = v_s * scale if scale != 1 else v_s
    return Trajectory(CubicSpline(t[keep] - start_s, v_s[keep]), float(duration_s), source=src)
