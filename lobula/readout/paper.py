"""The FLIVVER paper's readout, as its text states it (``ReadoutConfig.method`` "median")."""
from __future__ import annotations

import numpy as np

from .config import ReadoutConfig, ReadoutResult
from .filters import butterworth, staggered_difference
from .measurements import field_velocity, nanmedian_rows


def paper_readout(t, r, r2, a, cfg: ReadoutConfig) -> ReadoutResult:
    """The paper's readout, step by step.

    A Butterworth (``cfg.paper_wn``, ``cfg.paper_order``) on r̄_f, a ``cfg.stagger``-frame
    staggered difference for ṙ̄_f, v_f per field, the median across fields, a final Butterworth.
    Its error concentrates where a changes sign or stays near zero, because v_f is then a ratio
    of two small numbers.

    Parameters
    ----------
    t : ndarray, (n,)
        s, uniformly spaced.
    r, r2 : ndarray, (n, F)
        1/s and 1/s²: the fields' r̄ and r²̄.
    a : ndarray, (n,)
        m/s²: the forward acceleration.
    cfg : ReadoutConfig

    Returns
    -------
    ReadoutResult
        v_std and measurement_std NaN throughout: the paper gives no uncertainty.
    """
    zp = cfg.filter == "zero-phase"
    dt = float(np.median(np.diff(t)))
    rf = butterworth(r, cfg.paper_wn, cfg.paper_order, zp)
    r_dot = staggered_difference(rf, cfg.stagger, dt, centred=False)
    v_f, _ = field_velocity(r, r2, r_dot, a)
    v_f = np.where(np.isfinite(v_f), v_f, np.nan)
    med = nanmedian_rows(v_f)
    v = butterworth(med, cfg.paper_wn, cfg.paper_order, zp) if np.isfinite(med).any() else med
    # The paper has no notion of observability; we add only the honest minimum:
    # without acceleration the ratio carries no speed information.
    a_s = butterworth(a, cfg.paper_wn, cfg.paper_order, zp)
    obs = np.isfinite(v) & (np.abs(a_s) >= cfg.accel_min_m_s2)
    return ReadoutResult(np.where(obs, v, np.nan), obs, np.full(len(t), np.nan), v_f, r_dot, med,
                         np.full(len(t), np.nan), a)
