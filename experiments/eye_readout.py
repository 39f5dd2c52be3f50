"""The compound eye's readout stage, between its circuit and the velocity filter: which fields reach the
readout (their reliability), the split-half spread of two field halves, the accelerometer offset the
estimate implies, and the readout that never differentiates across a saccade (:func:`suppressed_readout`).
Used by :func:`experiments.eye_velocity.estimate_eye_velocity`."""
from __future__ import annotations

import numpy as np

from lobula.readout import readout

__all__ = ["readout_offset", "reliability_gate", "split_half_variance", "field_halves", "suppressed_readout"]


def readout_offset(t: np.ndarray, v_hat: np.ndarray, a: np.ndarray, tau_s: float) -> np.ndarray:
    """The accelerometer offset b̂ (m/s², (n,)) the readout's own estimate implies, causally.

    Between vision's corrections the readout's v̂ moves by a − b̂ (it integrates the accelerometer
    less its offset estimate), and vision's corrections average out over time, so the running mean
    (time constant ``tau_s``) of a − Δv̂/Δt tracks b̂. t (n,) s; v_hat (n,) m/s, NaN where unobservable
    (those steps are skipped: the mean is held); a (n,) m/s². Step k uses steps ≤ k only; 0 until v̂
    has two finite steps.
    """
    v = np.asarray(v_hat, dtype=float)
    rate = np.full(len(v), np.nan)
    rate[1:] = np.diff(v) / np.diff(t)
    g = np.empty(len(v))
    g[0] = 1.0
    g[1:] = 1.0 - np.exp(-np.diff(t) / tau_s)
    x = np.asarray(a, dtype=float) - rate
    out = np.zeros(len(v))
    m = 0.0
    for k in range(len(v)):  # a loop over readout steps (a scalar recursion)
        if np.isfinite(x[k]):
            m += g[k] * (x[k] - m)
        out[k] = m
    return out


def reliability_gate(reliability: np.ndarray, finite: np.ndarray, threshold: float, n_min: int) -> np.ndarray:
    """Which fields (K, F) bool reach the readout: those with ``reliability`` ≥ ``threshold`` at each step,
    unless fewer than ``n_min`` do — then every finite field (``finite``), as without the gate: a readout
    left with too few fields would have nothing to measure and drift on the accelerometer alone (dev
    rotation world, seed 102: 19 fields follow the exact v/D at r > 0.8 but none reaches a ratio of 5;
    gated without this fallback the readout declared 94 % of the steps unobservable and its v̂ there
    erred by 0.95 m/s). threshold 0: every finite field always."""
    if threshold <= 0:
        return np.asarray(finite, bool).copy()
    used = (reliability >= threshold) & finite
    few = used.sum(-1) < n_min
    used[few] = np.asarray(finite, bool)[few]
    return used


def split_half_variance(t: np.ndarray, v_a: np.ndarray, v_b: np.ndarray, tau_s: float) -> np.ndarray:
    """Causal running mean of (v_a − v_b)² (m²/s²), time constant ``tau_s``: two halves' disagreement.

    t (n,) s; v_a, v_b (n,) two estimates of the same velocity from disjoint halves of the fields
    (NaN where a half has none: the mean is held). Step k uses steps ≤ k only. NaN until both
    halves have spoken. If the halves' errors were independent and equal, the estimate from both
    would err by var(v_a − v_b)/4; errors they share (the accelerometer, the readout's filter) are
    not in the difference at all, so the whole disagreement is taken, not a quarter of it.
    """
    d2 = (np.asarray(v_a, float) - np.asarray(v_b, float)) ** 2
    out = np.full(len(d2), np.nan)
    m = np.nan
    for k in range(len(d2)):  # a loop over readout steps (a scalar recursion)
        if np.isfinite(d2[k]):
            w = 1.0 - np.exp(-(t[k] - t[k - 1]) / tau_s) if k > 0 and np.isfinite(m) else 1.0
            m = d2[k] if not np.isfinite(m) else m + w * (d2[k] - m)
        out[k] = m
    return out


def field_halves(fields, n_outputs: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Boolean masks (n_outputs,) of the field halves whose disagreement :func:`estimate_eye_velocity`
    adds to v_std: right eye against left (a yaw or roll residue is opposite on the two sides), and
    upper against lower (elevation ≥ 0 against ≤ 0, the equator's fields in both: a pitch residue is
    opposite above and below the equator relative to the expansion). Under wide-field rotation
    cancelling the outputs are mirror sums of the right eye's fields: upper against lower only."""
    both = n_outputs == fields.n_fields
    idx = np.arange(fields.n_fields) if both else np.flatnonzero(fields.eye == 0)
    el = fields.centres_deg[idx, 1]
    out = [(el >= 0, el <= 0)]
    if both and (fields.eye == 0).any() and (fields.eye == 1).any():
        out.insert(0, (fields.eye == 0, fields.eye == 1))
    return [(x, y) for x, y in out if x.any() and y.any()]


def suppressed_readout(t, rho, r2, a, rcfg, saccade=None, **kw):
    """:func:`lobula.readout.readout` of LC outputs with saccadic suppression: a :class:`ReadoutResult`.

    t (n,) s; rho, r2 (n, F) 1/s, 1/s², NaN at the steps ``saccade`` (n,) bool flags (a body saccade and the
    circuit's hold after it); a (n,) m/s²; rcfg a ReadoutConfig; kw: :func:`readout`'s other arguments.
    Without a flagged step this is :func:`readout` itself. With one, the readout is given ṙ as well as ρ and
    r²̄ (as material rates: ρ and r²̄ the means of the difference's two ends, as the camera's material fields
    take them), ṙ the same centred difference over ``rcfg.stagger`` steps the readout takes of its low-passed
    ρ — NaN wherever it would span a flagged step — so that no difference is taken across a saccade: a
    saccade turns every field onto other surfaces, and ρ jumps by what they are, not by a/D.
    Online the readout smooths each run of steps between saccades alone (:func:`lobula.readout.filters.vision_runs`;
    offline the zero-phase low-pass bridges the gap), its terms are NaN at the flagged steps, and there the
    filter predicts from the acceleration alone and its σ grows.
    """
    if saccade is None or not np.any(saccade):
        return readout(t, rho, r2, a, rcfg, **kw)
    from lobula.readout import MaterialRates, staggered_difference
    from lobula.readout.filters import end_mean

    dt = float(np.median(np.diff(t)))
    stagger = rcfg.difference_frames
    rho, r2 = np.asarray(rho, float), np.asarray(r2, float)
    r_dot = staggered_difference(rho, stagger, dt, centred=True)
    k, h = np.arange(len(t)), stagger // 2
    edge = (k < h) | (k >= len(t) - h)   # no difference there

    def ends(x):
        return np.where(edge[:, None], np.nan, end_mean(x, stagger))
    return readout(t, rho, r2, a, rcfg, material=MaterialRates(ends(rho), ends(r2), r_dot), **kw)
