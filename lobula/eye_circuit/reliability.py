"""How much of each LC field's output is the flight's expansion: the causal slow-to-fast power ratio.
"""
from __future__ import annotations

import math

import numpy as np

from ..readout import hold_gaps


def _first_order(x: np.ndarray, alpha: np.ndarray | float, axis: int = 0) -> np.ndarray:
    """Causal first-order low-pass y_k = y_{k−1} + α·(x_k − y_{k−1}) along ``axis``, starting from 0."""
    from scipy.signal import lfilter

    return lfilter([alpha], [1.0, alpha - 1.0], x, axis=axis)


def field_reliability(t: np.ndarray, rho: np.ndarray, slow_hz: float = 0.5, fast_hz: float = 2.0,
                      tau_s: float = 2.0) -> np.ndarray:
    """Causal slow-to-fast power ratio of each LC field's output: how much of it is the flight's expansion.

    t (K,) s, uniformly spaced; rho (K, F) 1/s (NaN: silent, taken as 0). Returns (K, F): the running
    mean (time constant ``tau_s``) of the square of the field's slow component (first-order low-pass
    at ``slow_hz``) over that of its fast component (the field less a low-pass at ``fast_hz``); step k
    uses steps ≤ k only. The expansion a translating fly sees changes slowly (ρ = v/D: the speed and
    the distances change over seconds), whereas the correlators' pattern noise is broadband and grows
    with image speed: a turn moves the whole image, so under rotation a field looking at nothing near
    (sky, a distant backdrop) carries little expansion and much fast noise and rotation residue — its
    slow part is then mostly that noise's leak. Measured on development worlds (seeds 100, 101; causal
    circuit, haltere rotation handling): the ratio over the whole record separates the fields whose ρ
    follows the exact v/D (correlation 0.92–0.99 where it exceeds 5; 0.1–0.3 where it is below 1); the
    log of the ratio correlates with the field's correlation at 0.80 (rotation world) and 0.95 (panels).
    A downstream neuron can compute it: two low-passes of the same input and the running mean of
    each's square (the rectified power of a slow and a fast channel).
    """
    t = np.asarray(t, dtype=float)
    rho = np.asarray(rho, dtype=float)
    if len(t) < 2:
        return np.zeros_like(rho)
    dt = float(np.median(np.diff(t)))
    # Each field's channels start at its first output (the circuit's start-up is silent, NaN): its value
    # held before that, its last value held through silent steps, so no start-up step reads as fast power.
    ok = np.isfinite(rho)
    first = np.argmax(ok, axis=0)
    x = np.nan_to_num(hold_gaps(rho))
    live = np.arange(len(rho))[:, None] >= np.where(ok.any(0), first, len(rho))
    lp = lambda y, fc: _first_order(y - y[:1], 1.0 - math.exp(-2.0 * math.pi * fc * dt)) + y[:1]  # noqa: E731
    slow = lp(x, slow_hz)
    fast = x - lp(x, fast_hz)
    a = 1.0 - math.exp(-dt / tau_s)
    ps, pf = _first_order(slow ** 2 * live, a), _first_order(fast ** 2 * live, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(pf > 0, ps / np.maximum(pf, 1e-300), np.where(ps > 0, np.inf, 0.0))
