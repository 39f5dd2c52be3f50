"""The readout's low-passes and differences along time (axis 0), with NaN gaps bridged and restored."""
from __future__ import annotations

import numpy as np
from scipy import signal


def _integral(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """∫x dt from t[0] to each t (trapezoid rule).

    Parameters
    ----------
    x : ndarray, (n,)
        The integrand (units U).
    t : ndarray, (n,)
        s: the sample times.

    Returns
    -------
    ndarray, (n,)
        U·s: the integral up to each t, 0 at t[0].
    """
    return np.concatenate([[0.0], np.cumsum(0.5 * (x[1:] + x[:-1]) * np.diff(t))])


def _lag(x: np.ndarray, h: int) -> np.ndarray:
    """x delayed by h frames along axis 0 (NaN-filled): what an online stage has at each step.

    Parameters
    ----------
    x : ndarray, (n, ...)
    h : int
        Frames of delay (0: x itself).

    Returns
    -------
    ndarray, (n, ...)
    """
    if not h:
        return x
    h = min(h, len(x))
    return np.concatenate([np.full((h,) + x.shape[1:], np.nan), x[:len(x) - h]])


def hold_gaps(x: np.ndarray) -> np.ndarray:
    """Each NaN replaced by the last finite value before it along axis 0.

    A leading gap takes the first finite value; an all-NaN column stays NaN: what a causal stage
    knows through a silent stretch, never a value from after it.

    Parameters
    ----------
    x : array_like, (n, ...)

    Returns
    -------
    ndarray, (n, ...)
        A float copy of x with its gaps held.
    """
    x = np.array(x, dtype=float)
    ok = np.isfinite(x)
    idx = np.arange(len(x)).reshape((-1,) + (1,) * (x.ndim - 1))
    last = np.maximum.accumulate(np.where(ok, idx, -1), axis=0)
    last = np.where(last >= 0, last, np.argmax(ok, axis=0))
    return np.take_along_axis(x, last, axis=0)


def _fill_nan(x: np.ndarray, causal: bool = False) -> np.ndarray:
    """Bridge NaNs along axis 0 so filters can run through gaps.

    Offline, a gap is interpolated linearly (edges held). causal: a gap holds the last value
    before it (a leading gap the first value, which no output before that value reads once
    NaNs are restored): interpolating toward the value after a gap would let the online
    filter's output before the gap see that later value.

    Parameters
    ----------
    x : array_like, (n, ...)
    causal : bool
        Hold gaps (online) rather than interpolate them (offline).

    Returns
    -------
    ndarray, (n, ...)
        A float copy of x without NaN (a column with no finite value at all: 0).
    """
    x = np.array(x, dtype=float)
    flat = x.reshape(len(x), -1)
    bad = np.flatnonzero(~np.isfinite(flat).all(0))  # only the affected columns
    if causal:
        held = hold_gaps(flat[:, bad])
        flat[:, bad] = np.where(np.isfinite(held), held, 0.0)  # a column with no value at all: 0
        return flat.reshape(x.shape)
    idx = np.arange(len(x))
    for j in bad:
        ok = np.isfinite(flat[:, j])
        flat[:, j] = np.interp(idx, idx[ok], flat[ok, j]) if ok.any() else 0.0
    return flat.reshape(x.shape)


def vision_runs(x: np.ndarray) -> list[slice]:
    """The runs of rows along axis 0 with at least one finite value, between rows with none.

    A row with no finite value at all is a break in what the camera saw (the pairs of a fast turn:
    ``VelocityConfig.saccade_gate_deg_s``): the surfaces after it are others than before, so a
    smoothing does not carry one run's level into the next.

    Parameters
    ----------
    x : ndarray, (n, ...)

    Returns
    -------
    list of slice
        In order; empty where no row has a finite value.
    """
    ok = np.isfinite(np.asarray(x, float).reshape(len(x), -1)).any(1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    return [slice(a, b) for a, b in zip(edges[::2], edges[1::2])]


def _by_runs(fn, x: np.ndarray) -> np.ndarray:
    """fn applied to each run of :func:`vision_runs` alone (rows between runs NaN); fn(x) where there is at most one."""
    runs = vision_runs(x)
    if len(runs) <= 1:
        return fn(x)
    y = np.full(np.shape(x), np.nan)
    for run in runs:
        y[run] = fn(x[run])
    return y


def butterworth(x: np.ndarray, wn: float, order: int, zero_phase: bool) -> np.ndarray:
    """Butterworth low-pass along axis 0; NaNs bridged, then restored.

    Parameters
    ----------
    x : ndarray, (n, ...)
    wn : float
        Cutoff as a fraction of Nyquist (held below 0.99).
    order : int
        The filter's order.
    zero_phase : bool
        Forward–backward (offline) or forward only, started at the first value's steady state (online).

    Returns
    -------
    ndarray, (n, ...)
        NaN where x is.
    """
    sos = signal.butter(order, min(wn, 0.99), output="sos")
    nan = ~np.isfinite(x)
    xf = _fill_nan(x, causal=not zero_phase)
    if zero_phase:
        y = signal.sosfiltfilt(sos, xf, axis=0, padlen=min(len(xf) - 1, 3 * (2 * len(sos) + 1)))
    else:
        zi = signal.sosfilt_zi(sos)
        zi = zi.reshape(zi.shape + (1,) * (xf.ndim - 1)) * xf[:1]
        y = signal.sosfilt(sos, xf, axis=0, zi=zi)[0]
    y[nan] = np.nan
    return y


def gaussian_lowpass(x: np.ndarray, cutoff_hz: float, dt: float, truncate: float = 2.5,
                     causal: bool = False, restart: bool = False) -> tuple[np.ndarray, int]:
    """Linear-phase (symmetric Gaussian FIR) low-pass along axis 0, centred; NaNs bridged, then restored.

    The Gaussian's gain is ½ at ``cutoff_hz``, as for the zero-phase (forward–backward)
    Butterworth of order 2. The value at k needs data up to k + M (M the half-width), so lagged
    by M it is causal, and every frequency is delayed by the same M frames. (A causal IIR delays
    each frequency by a different amount, so ratios of filtered signals such as (ṙ̄ − r²̄)/r̄ are
    biased.) Edges are padded with the edge values.

    Parameters
    ----------
    x : ndarray, (n, ...)
    cutoff_hz : float
        Hz: where the gain is ½.
    dt : float
        s: the frame interval.
    truncate : float
        The kernel is cut at this many of its σ either side.
    causal : bool
        NaN gaps hold their last value (see :func:`_fill_nan`), so the output lagged by M reads
        nothing after its own time.
    restart : bool
        Smooth each run between rows without a finite value alone, its edges padded with its own
        values (:func:`vision_runs`); the output lagged by M still reads nothing after its time.

    Returns
    -------
    y : ndarray, (n, ...)
        The centred smoothing, NaN where x is.
    m : int
        Frames: the kernel's half-width M.
    """
    sigma = np.sqrt(np.log(2.0) / 2.0) / (np.pi * cutoff_hz) / dt  # frames
    m = max(1, int(np.ceil(truncate * sigma)))
    if restart:
        return _by_runs(lambda part: gaussian_lowpass(part, cutoff_hz, dt, truncate, causal)[0], x), m
    k = np.exp(-0.5 * (np.arange(-m, m + 1) / sigma) ** 2)
    k /= k.sum()
    nan = ~np.isfinite(x)
    xf = _fill_nan(x, causal)
    pad = np.concatenate([np.repeat(xf[:1], m, 0), xf, np.repeat(xf[-1:], m, 0)])
    flat = pad.reshape(len(pad), -1)
    y = np.stack([np.convolve(flat[:, j], k, mode="valid") for j in range(flat.shape[1])], 1)  # per field, not pixel
    y = y.reshape(xf.shape)
    y[nan] = np.nan
    return y, m


def difference_mean(x: np.ndarray, stagger: int) -> np.ndarray:
    """x averaged over the span of a centred difference ``stagger`` frames wide, along axis 0.

    A difference (y[k + s/2] − y[k − s/2])/(s·dt) is the mean of ẏ over those s frame intervals,
    not ẏ at k: a quantity set beside it (the forward acceleration beside ṙ̄) must be averaged over the
    same span, or a fast change reads smaller in the difference than in the quantity (a walker's 1.7 Hz
    surge by 8 % at s = 4 and 30 frames/s). The mean is the trapezoid rule over the s + 1 samples,
    centred, the edges held.

    Parameters
    ----------
    x : ndarray, (n, ...)
        Units U, finite.
    stagger : int
        Frames s between the difference's two samples (even).

    Returns
    -------
    ndarray, (n, ...)
        U.
    """
    from scipy.ndimage import convolve1d

    x = np.asarray(x, float)
    if stagger < 2 or len(x) < 2:
        return x
    w = np.ones(stagger + 1) / stagger
    w[[0, -1]] *= 0.5
    return convolve1d(x, w, axis=0, mode="nearest")


def end_mean(x: np.ndarray, stagger: int) -> np.ndarray:
    """The mean of x at the two ends of a centred difference ``stagger`` frames wide, (x[k − s/2] + x[k + s/2])/2,
    along axis 0, the edges held: what the material fields' r̄ takes of the motion (:func:`difference_mean`).
    NaN only where an end is.

    Parameters
    ----------
    x : ndarray, (n, ...)
        Units U.
    stagger : int
        Frames s between the two ends (even).

    Returns
    -------
    ndarray, (n, ...)
        U.
    """
    x = np.asarray(x, float)
    h, n = stagger // 2, len(x)
    if h < 1 or n < 2:
        return x
    k = np.arange(n)
    return 0.5 * (x[np.clip(k - h, 0, n - 1)] + x[np.clip(k + h, 0, n - 1)])


def staggered_difference(x: np.ndarray, stagger: int, dt: float, centred: bool) -> np.ndarray:
    """Derivative by a difference ``stagger`` frames wide, along axis 0.

    Parameters
    ----------
    x : ndarray, (n, ...)
        Units U.
    stagger : int
        Frames s between the difference's two samples.
    dt : float
        s: the frame interval.
    centred : bool
        (x[k + s/2] − x[k − s/2]) / (s·dt), which belongs to frame k (s even); otherwise the
        paper's (x[k] − x[k − s]) / (s·dt), which belongs to k − s/2.

    Returns
    -------
    ndarray, (n, ...)
        U/s; NaN at frames without a partner.
    """
    out = np.full(x.shape, np.nan)
    if stagger >= len(x):
        return out
    d = (x[stagger:] - x[:-stagger]) / (stagger * dt)
    if centred:
        h = stagger // 2
        out[h:h + len(d)] = d
    else:
        out[stagger:] = d
    return out
