"""The record the kalman readout's filter runs over (:class:`FilterRecord`): the frames' times, the forward
acceleration, the transport rate and its integral, and the rows its measurements take in the state."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .filters import _integral


@dataclass
class FilterRecord:
    """The record the filter runs over, and the rows its measurements take in the state.

    Parameters
    ----------
    t, a : ndarray, (n,)
        s and m/s²: the frames' times and the forward acceleration.
    lam, cum_lam : ndarray, (n,)
        1/s and its integral over t (1): the transport rate λ (:func:`kalman_velocity`'s transport).
    c_at, c_mean : callable
        (k, d) → (3,) or (0,): the axis c at t_k − d and its mean over [t_k − d, t_k] (:func:`_axis_terms`).
    gravity_tau, drift_std, turn_rate, offset_walk : ndarray, (n,), or None
        :func:`kalman_velocity`'s inputs of those names.
    """

    t: np.ndarray
    a: np.ndarray
    lam: np.ndarray
    cum_lam: np.ndarray
    c_at: Callable
    c_mean: Callable
    gravity_tau: np.ndarray | None
    drift_std: np.ndarray | None
    turn_rate: np.ndarray | None
    offset_walk: np.ndarray | None

    def v_row(self, k: int, d: float) -> np.ndarray:
        """Row (N,) giving v(t_k − d) + ∫a over the last d from the state at t_k (d in s):
        v(t − d) = v − ∫(a − offset − λv), v taken constant over d in the λ term."""
        lam_d = self.cum_lam[k] - np.interp(self.t[k] - d, self.t, self.cum_lam)
        return np.concatenate([[1.0 + lam_d, d, 0.0, -0.5 * d * d], d * self.c_mean(k, d)])

    def offset_row(self, k: int) -> np.ndarray:
        """Row (N,) giving the acceleration's whole offset at t_k."""
        return np.concatenate([[0.0, 1.0, 0.0, 0.0], self.c_at(k, 0.0)])

    def accel_reach(self, x, P, k: int, reading: float, n_sigma: float) -> float:
        """m/s²: |reading − b̂| + n_sigma·σ_b, the acceleration a reading (m/s²) stands for, as the posterior
        (mean x (N,), covariance P (N, N)) has the whole offset at t_k; n_sigma 2 its most, −2 its least."""
        o = self.offset_row(k)
        return abs(reading - o @ x) + n_sigma * np.sqrt(o @ P @ o)


def filter_record(t, a, offset_axis, transport, gravity_tau, drift_std, turn_rate, offset_walk) -> FilterRecord:
    """The :class:`FilterRecord` of :func:`kalman_velocity`'s inputs (same names, units and shapes)."""
    c_at, c_mean = _axis_terms(t, offset_axis)
    lam = np.zeros(len(t)) if transport is None else np.asarray(transport, float)
    return FilterRecord(t, a, lam, _integral(lam, t), c_at, c_mean, gravity_tau, drift_std, turn_rate, offset_walk)


def _axis_terms(t, axis):
    """The start frame's gravity error δ's forward share: functions of (k, d) for the axis c.

    Parameters
    ----------
    t : ndarray, (n,)
        s.
    axis : ndarray, (n, 3), or None
        :func:`kalman_velocity`'s offset_axis.

    Returns
    -------
    c_at, c_mean : callable
        (k, d) → (3,): the axis c at t_k − d (s) and its mean over [t_k − d, t_k] — c·δ is the forward
        offset then, and its integral over the latency what ∫a bridging that latency holds of it — or
        empty rows (0,) where there is no axis.
    """
    if axis is None:
        empty = np.zeros(0)
        return (lambda k, d: empty), (lambda k, d: empty)
    c = np.asarray(axis, float)
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (c[1:] + c[:-1]) * np.diff(t)[:, None], 0)])
    at = lambda tq, y: np.array([np.interp(tq, t, y[:, j]) for j in range(3)])  # held at the record's start

    def c_at(k, d):
        return c[k] if d == 0 else at(t[k] - d, c)

    def c_mean(k, d):
        if d <= 0:
            return c[k]
        t0 = max(t[k] - d, t[0])
        return (cum[k] - at(t0, cum)) / d + (d - (t[k] - t0)) / d * c[0]  # before the start: c held at c[0]

    return c_at, c_mean
