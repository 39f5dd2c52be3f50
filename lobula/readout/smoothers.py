"""The Rauch–Tung–Striebel smoother's backward passes over the kalman readout's forward filter.

Offline the whole record (:func:`rts_smooth`); online with a declared delay, each frame given the
measurements up to ``lag`` s after it (:func:`fixed_lag_smooth`).
"""
from __future__ import annotations

import numpy as np


def rts_smooth(xs, Ps, xs_pred, Ps_pred, Fs):
    """The Rauch–Tung–Striebel smoother's backward pass over the forward filter's record, in place.

    Parameters
    ----------
    xs : ndarray, (n, N)
        The forward filter's posterior means; overwritten with the smoothed ones.
    Ps : ndarray, (n, N, N)
        Their covariances; overwritten likewise.
    xs_pred : ndarray, (n, N)
        Its predictions (before each frame's measurements).
    Ps_pred : ndarray, (n, N, N)
        Their covariances.
    Fs : ndarray, (n, N, N)
        The transition into each frame.

    Returns
    -------
    xs : ndarray, (n, N)
        Each frame's state mean given the whole record.
    Ps : ndarray, (n, N, N)
        Its covariance.
    """
    for k in range(len(xs) - 2, -1, -1):
        C = Ps[k] @ Fs[k + 1].T @ np.linalg.pinv(Ps_pred[k + 1])
        xs[k] = xs[k] + C @ (xs[k + 1] - xs_pred[k + 1])
        Ps[k] = Ps[k] + C @ (Ps[k + 1] - Ps_pred[k + 1]) @ C.T
    return xs, Ps


def fixed_lag_smooth(t, xf, Pf, xp, Pp, F, lag: float):
    """Fixed-lag Rauch–Tung–Striebel smoothing: each frame's state given the measurements up to ``lag`` s after it.

    Frame k's estimate is the RTS smoother's of the record cut at the last frame e_k ≤ t_k + lag
    (the end of the record where that comes first), exactly: the backward gains
    C_i = Pf_i F_{i+1}ᵀ Pp_{i+1}⁻¹ do not depend on where the record ends, so they are computed
    once and every frame's backward pass runs at once, one step of depth at a time (vectorised
    over frames; the loop runs over the lag's frames).

    Parameters
    ----------
    t : ndarray, (n,)
        s.
    xf : ndarray, (n, N)
        The forward filter's posterior means.
    Pf : ndarray, (n, N, N)
        Their covariances.
    xp : ndarray, (n, N)
        Its predictions (before each frame's measurements).
    Pp : ndarray, (n, N, N)
        Their covariances.
    F : ndarray, (n, N, N)
        The transition into each frame.
    lag : float
        s.

    Returns
    -------
    xs : ndarray, (n, N)
        Each frame's state mean given the measurements up to ``lag`` after it.
    Ps : ndarray, (n, N, N)
        Its covariance.
    """
    n = len(t)
    end = np.searchsorted(t, t + lag + 1e-9 * max(lag, 1.0), side="right") - 1   # e_k (n,)
    C = np.zeros_like(Pf)
    C[:-1] = Pf[:-1] @ np.swapaxes(F[1:], -1, -2) @ np.linalg.pinv(Pp[1:])
    x, P = xf[end].copy(), Pf[end].copy()
    k = np.arange(n)
    for depth in range(int((end - k).max(initial=0)) - 1, -1, -1):
        i = k + depth                      # step from frame i + 1 back to frame i, where i + 1 ≤ e_k
        on = i < end
        if not on.any():
            continue
        j, c = i[on], C[i[on]]
        x[on] = xf[j] + np.einsum("kab,kb->ka", c, x[on] - xp[j + 1])
        P[on] = Pf[j] + c @ (P[on] - Pp[j + 1]) @ np.swapaxes(c, -1, -2)
    return x, P
