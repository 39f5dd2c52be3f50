"""Whether the image's expansion follows the accelerometer: the test that vision can fix the speed at all.

FLIVVER reads the speed from how the expansion changes as the camera accelerates: for a field at
depth d, ṙ − r² = a/d (the readout's terms, low-passed alike), so across frames the fields'
pooled ṙ̄ − r²̄ rises and falls with the forward acceleration a, with a positive slope 1/d. Where it
does not — the image is stabilised against the body, the scene moves, the flow is noise, or the
camera holds a steady pace so there is nothing to follow — κ = a/v is noise, and a filter that takes
it at its stated error settles on whatever v makes that noise smallest (v ≈ 0 for a noisy κ, errors
in variables), with a confident, wrong σ.

:func:`expansion_coupling` measures it: the correlation ρ of ṙ̄ − r²̄ (the fields' median) with the
low-passed acceleration over a window, as Fisher's z with the window's effective number of
independent samples (the low-pass leaves about 2·cutoff of them per second),
z = atanh(ρ)·√(n_eff − 3). Vision informs v once z has reached ``coupling_z`` (one-sided: a
negative slope is not a depth); once a whole window has passed without it, the readout reports no
speed, whatever its posterior says, and tells the user why (before that — the first ``window`` of an
online run, or a record shorter than it — the test cannot tell, and the posterior's std decides
alone). A still camera that the rest bound holds at 0 needs no coupling.
"""
from __future__ import annotations

import numpy as np

__all__ = ["expansion_coupling", "window_full", "vision_locked"]


def _window_sums(x: np.ndarray, w: int, causal: bool) -> np.ndarray:
    """Sums of x (n,) over windows of w frames: trailing (frames k − w + 1 … k, fewer at the start) or centred."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    n = len(x)
    k = np.arange(n)
    if causal:
        lo, hi = np.maximum(k - w + 1, 0), k + 1
    else:
        lo, hi = np.maximum(k - w // 2, 0), np.minimum(k + w - w // 2, n)
    return c[hi] - c[lo]


def expansion_coupling(g, a, dt: float, window_s: float, cutoff_hz: float, causal: bool) -> np.ndarray:
    """Fisher's z of the correlation between the pooled ṙ̄ − r²̄ and the acceleration, frame by frame.

    Parameters
    ----------
    g : ndarray, (n,)
        1/s²: the fields' median ṙ̄ − r²̄ (NaN where no field is valid).
    a : ndarray, (n,)
        m/s²: the low-passed forward acceleration, paired with ``g`` in time.
    dt : float
        s: the frame interval.
    window_s : float
        s: the window the correlation is taken over.
    cutoff_hz : float
        Hz: the low-pass both signals went through; sets the effective samples per second (2·cutoff).
    causal : bool
        True: the window ends at each frame (frames so far at the start); False: centred on it.

    Returns
    -------
    ndarray, (n,)
        z (dimensionless), positive where the expansion rises with the acceleration; 0 where the window
        holds fewer than four effective samples or either signal is constant.
    """
    g = np.asarray(g, float)
    a = np.asarray(a, float)
    ok = np.isfinite(g) & np.isfinite(a)
    g0, a0, m = np.where(ok, g, 0.0), np.where(ok, a, 0.0), ok.astype(float)
    w = max(2, int(round(window_s / dt)))
    n = _window_sums(m, w, causal)
    sg, sa = _window_sums(g0, w, causal), _window_sums(a0, w, causal)
    sgg, saa, sga = (_window_sums(g0 * g0, w, causal), _window_sums(a0 * a0, w, causal),
                     _window_sums(g0 * a0, w, causal))
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sga - sg * sa / n
        var_g, var_a = sgg - sg ** 2 / n, saa - sa ** 2 / n
        rho = cov / np.sqrt(var_g * var_a)
    n_eff = n * dt * 2.0 * cutoff_hz
    good = np.isfinite(rho) & (var_g > 0) & (var_a > 0) & (n_eff > 3.0)
    rho = np.clip(np.where(good, rho, 0.0), -0.999999, 0.999999)
    return np.where(good, np.arctanh(rho) * np.sqrt(np.maximum(n_eff - 3.0, 0.0)), 0.0)


def window_full(n: int, dt: float, window_s: float, causal: bool) -> np.ndarray:
    """Frames (n,) whose coupling window holds a whole ``window_s`` (s) of record: before that (online, the first
    seconds; offline, a record shorter than the window) the test cannot yet tell coupling from noise, and the
    posterior's std alone decides what is reported."""
    w = max(2, int(round(window_s / dt)))
    if causal:
        return np.arange(n) + 1 >= w
    return np.full(n, n >= w)


def vision_locked(z, still, threshold: float, causal: bool, decided=None) -> np.ndarray:
    """Where vision has fixed the speed: the coupling reached ``threshold`` (or the camera was held still), or
    the test has not yet had a whole window to decide (``decided`` False there).

    Parameters
    ----------
    z : ndarray, (n,)
        :func:`expansion_coupling`'s z.
    still : ndarray of bool, (n,)
        Frames where the rest bound holds v at 0 (the image shows no expansion while the accelerometer
        is steady).
    threshold : float
        z needed; 0 or less: every frame.
    causal : bool
        True: from the first such frame on; False: everywhere once any frame qualifies (the smoother
        carries what one frame fixes over the whole record).
    decided : ndarray of bool, (n,), optional
        :func:`window_full`; None: every frame decided.

    Returns
    -------
    ndarray of bool, (n,)
    """
    z = np.asarray(z, float)
    if threshold <= 0:
        return np.ones(len(z), bool)
    hit = (z >= threshold) | np.asarray(still, bool)
    locked = np.maximum.accumulate(hit) if causal else np.full(len(z), bool(hit.any()))
    return locked if decided is None else locked | ~np.asarray(decided, bool)
