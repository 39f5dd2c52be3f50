"""Carrying v̂ beyond the frames vision answers: the accelerometer's integral, with an honest σ.

Where vision has fixed the speed (``observable``), v̂ is the filter's posterior. Beyond those frames the
filter goes on integrating the acceleration, but its posterior std there takes the offset it learned
while vision answered as known; a κ error the filter absorbed into that offset (a heading swing, a gait's
bounce) then carries through the cruise with a σ of centimetres per second. The carried σ forgets what
vision taught about the offset: the offset is as uncertain as its prior, so σ grows by the prior's std
times the time since vision last answered: the last frame where a measurement of vision entered the
filter and its posterior fixed the speed (offline: the nearest such frame, either side).
Before vision has ever answered (online), or where it never does (offline), v̂ is unknown: NaN.
"""
from __future__ import annotations

import numpy as np


def vision_answers(v_std, allowed, fixed, informing):
    """Where vision answers (bool, of the arguments' one shape): a measurement of vision entered the filter
    (``informing``), vision has fixed the speed (``fixed``), and the posterior std v_std is within ``allowed``
    (both m/s; :func:`lobula.readout.config.std_allowed`). Carrying starts from these frames."""
    return (np.asarray(v_std) <= allowed) & np.asarray(fixed, bool) & np.asarray(informing, bool)


def answered_velocity(result) -> np.ndarray:
    """(n,) m/s: v̂ where vision answers (``observable``), NaN where it is carried or unknown; ``result`` a
    :class:`~lobula.readout.config.ReadoutResult` or a velocity Dataset (``v_hat``, ``observable`` over time)."""
    return np.where(np.asarray(result.observable, bool), np.asarray(result.v_hat, float), np.nan)


def time_from_answer(t: np.ndarray, answered: np.ndarray, causal: bool) -> np.ndarray:
    """s: each frame's time from the nearest answered frame; inf where there is none.

    Parameters
    ----------
    t : ndarray, (n,)
        s, increasing.
    answered : ndarray of bool, (n,)
        Frames where vision fixes the speed (0 there).
    causal : bool
        Count only answered frames at or before each frame (online), else either side (offline).

    Returns
    -------
    ndarray, (n,)
    """
    t = np.asarray(t, float)
    answered = np.asarray(answered, bool)
    n = len(t)
    idx = np.arange(n)
    last = np.maximum.accumulate(np.where(answered, idx, -1))
    since = np.where(last >= 0, t - t[np.maximum(last, 0)], np.inf)
    if causal:
        return since
    following = np.minimum.accumulate(np.where(answered, idx, n)[::-1])[::-1]
    until = np.where(following < n, t[np.minimum(following, n - 1)] - t, np.inf)
    return np.minimum(since, until)


def carried_std(v_std, since_s, offset_prior: float):
    """m/s: the std of v̂ carried ``since_s`` (s) from an answered frame: hypot(v_std, offset_prior·since_s).

    v_std (m/s) the filter's posterior std and since_s of any one shape (:func:`time_from_answer`);
    offset_prior m/s², the prior std of the acceleration's forward offset. NaN where since_s is inf.
    """
    since_s = np.asarray(since_s, float)
    finite = np.isfinite(since_s)
    return np.where(finite, np.hypot(v_std, offset_prior * np.where(finite, since_s, 0.0)), np.nan)
