"""The accuracy suite's scores: the metrics of one configuration's velocity series against the truth.

:func:`score_series` scores a series in the suite's two windows (after the skip, and the first 2 s):
RMSE and median |error| over the observable frames, the 2σ coverage and z95 of the stated std, the
observable fraction, the lock-on time, and the RMSE and 2σ coverage over every frame, v̂ carried by the
accelerometer included (:mod:`experiments.suite` says what each means).
"""
from __future__ import annotations

import numpy as np


#: window name -> description
WINDOWS = ("after_skip", "first_2s")
METRICS = ("rmse_m_s", "median_abs_error_m_s", "coverage_2sigma", "z95", "observable_fraction", "lock_on_s",
           "rmse_all_m_s", "coverage_2sigma_all")
#: each metric's units (suite.nc's ``metric_units``)
METRIC_UNITS = dict(rmse_m_s="m/s", median_abs_error_m_s="m/s", coverage_2sigma="1", z95="1",
                    observable_fraction="1", lock_on_s="s", rmse_all_m_s="m/s", coverage_2sigma_all="1")
#: z95 where a Gaussian error's ±2σ coverage is 99 % and 85 % (1.96·2/z₀.₉₉₅, 1.96·2/z₀.₉₂₅): the suite figure's band
Z95_TARGET = (1.52, 2.72)


def lock_on_time(t: np.ndarray, err: np.ndarray, v_true: np.ndarray, hold_s: float = 1.0,
                 moving_m_s: float = 0.1) -> float:
    """Seconds from t[0] to the start of the first hold_s-long stretch in which |err| ≤ 0.05 m/s + 10 % of |v|
    throughout, while the camera moves (|v| > moving_m_s) for at least half of it; NaN if none.

    A NaN (unobservable) error breaks a stretch. Being right about a still camera alone does not count.
    """
    ok = np.isfinite(err) & (np.abs(err) <= 0.05 + 0.1 * np.abs(v_true))
    moving = np.abs(v_true) > moving_m_s
    start = None
    for i in range(len(t)):  # a scan over frames (hundreds), not pixels
        if not ok[i]:
            start = None
            continue
        start = i if start is None else start
        # Slide the stretch's start forward past still frames so motion can fill it.
        while start < i and not moving[start] and t[i] - t[start + 1] >= hold_s:
            start += 1
        if t[i] - t[start] >= hold_s and moving[start:i + 1].mean() >= 0.5:
            return float(t[start] - t[0])
    return float("nan")


def window_metrics(t, v_hat, v_std, v_true, mask, v_all=None) -> dict:
    """The metrics of one window (the frames in ``mask``, bool (n,)); every array (n,), m/s but t (s).

    RMSE, median |e|, 2σ coverage, z95 (the 95th percentile of |e|/σ) and observable fraction over the frames
    where ``v_hat`` (NaN where not answered) is finite; ``rmse_all_m_s`` over the frames where ``v_all`` (v̂
    answered or carried by the accelerometer, NaN where unknown; None: ``v_hat``) is, and
    ``coverage_2sigma_all`` over every frame in the window, one without v̂ or σ counted outside ±2σ — what a
    user who reads every v̂ with its σ meets."""
    vh, vt = v_hat[mask], v_true[mask]
    obs = np.isfinite(vh)
    err = vh[obs] - vt[obs]
    out = dict(observable_fraction=float(obs.mean()) if obs.size else float("nan"))
    if err.size:
        out.update(rmse_m_s=float(np.sqrt(np.mean(err ** 2))), median_abs_error_m_s=float(np.median(np.abs(err))))
    else:
        out.update(rmse_m_s=float("nan"), median_abs_error_m_s=float("nan"))
    out["coverage_2sigma"] = out["z95"] = out["coverage_2sigma_all"] = float("nan")
    e_all = (v_hat if v_all is None else v_all)[mask] - vt
    out["rmse_all_m_s"] = float(np.sqrt(np.mean(e_all[np.isfinite(e_all)] ** 2))) if np.isfinite(e_all).any() \
        else float("nan")
    if v_std is not None and mask.any():
        with np.errstate(invalid="ignore"):
            out["coverage_2sigma_all"] = float(np.mean(np.abs(e_all) <= 2 * v_std[mask]))  # NaN compares False
    if v_std is not None and err.size:
        sd = v_std[mask][obs]
        # An estimator that reports no uncertainty at all has no coverage (NaN), not 0.
        has = np.isfinite(sd)
        if has.any():
            # A frame without a std counts outside the band, and as an unbounded |e|/σ.
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.abs(err) / sd                       # σ = 0: inf, or 0 where the error is 0 too
            z = np.where(has, np.nan_to_num(z, nan=0.0, posinf=np.inf), np.inf)
            out["coverage_2sigma"] = float(np.mean(z <= 2))
            out["z95"] = float(np.quantile(z, 0.95, method="inverted_cdf"))  # a sample: no inf − inf
    return out


def score_series(t, v_hat, v_std, v_true, skip_s: float, v_all=None) -> dict:
    """{window: {metric: value}} for one configuration's series (v̂ NaN where unobservable; ``v_all`` v̂ answered
    or carried, as :func:`window_metrics` takes it)."""
    lock = lock_on_time(t, v_hat - v_true, v_true)
    out = {}
    for w, mask in (("after_skip", t >= t[0] + skip_s), ("first_2s", t < t[0] + 2.0)):
        m = window_metrics(t, v_hat, v_std, v_true, mask, v_all)
        m["lock_on_s"] = lock
        out[w] = m
    return out
