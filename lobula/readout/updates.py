"""The kalman readout's measurement updates: the moments v passed through 0, the sign of v, the rest
bounds, and vision's κ = a/v against the accelerometer, each a linear update of the state (v, b, c, ḃ[, δ])
(:mod:`lobula.readout.kalman`), gated where the posterior is sure the measurement cannot hold."""
from __future__ import annotations

import numpy as np
from scipy.special import log_ndtr

from .config import ReadoutConfig

from .record import FilterRecord

#: a reversal or rest bound whose innovation exceeds this many of its standard deviations is taken for the front
#: end's fault, not a fact about v (kalman_velocity): an expansion read with the wrong sign for a moment gives two
#: false reversals and, low-passed offline, frames of "no expansion" (tests/test_readout.py)
OUTLIER_GATE = 4.0


def _reversal_update(x, P, k: int, rec: FilterRecord, reversal, floor: float, consider: bool):
    """Update with v(t_k − delay) = 0 where the fields' expansion changed sign (:func:`reversal_measurement`).

    Its std is the crossing time's std × the acceleration as the posterior has it (|accel − b̂| + 2σ_b),
    floored at ``floor`` (m/s); gated: a posterior sure that v was far from 0 takes the sign change for a
    front-end fault.

    Parameters
    ----------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    k : int
        The frame.
    rec : FilterRecord
    reversal : tuple of ndarray
        (shift, time_std, delay, accel), each (n,), as :func:`kalman_velocity` takes it.
    floor : float
        m/s: the least std.
    consider : bool
        As in :func:`_update`.

    Returns
    -------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    """
    Hr = rec.v_row(k, reversal[2][k])
    s_rev = max(reversal[1][k] * rec.accel_reach(x, P, k, reversal[3][k], 2.0), floor)
    return _gated_update(x, P, Hr, reversal[0][k] - Hr @ x, s_rev ** 2, consider)


def _stop_update(x, P, k: int, rec: FilterRecord, stop, floor: float, cf: float, consider: bool):
    """Update with v(t_k) = ρ·v(t_k − Δ) where the fields' expansion has fallen to a stop (:func:`stop_measurement`).

    Its std is ρ's std × the velocity it multiplies as the posterior has it (|v̂(t_k − Δ)| + 2σ), floored at
    ``floor`` (m/s) and counted once per ``cf`` frames (corr_frames on the smoother's pass, else 1: the frames'
    ratios share their reference). Not gated: a stop held for SIGN_PERSIST_S is what corrects a posterior sure
    of a speed that an offset it could not tell from the braking made up. ``stop``: (shift, ratio, ratio_std,
    delay), each (n,), as :func:`kalman_velocity` takes it; the rest as :func:`_reversal_update`, returning the
    posterior (x, P).
    """
    h, nu, r = _stop_row(x, P, k, rec, stop, floor, cf)
    return _update(x, P, h, nu, r, consider)


def _stop_row(x, P, k: int, rec: FilterRecord, stop, floor: float, cf: float):
    """The stop's row h (N,), innovation (m/s) and noise variance ((m/s)²) at frame k (see :func:`_stop_update`)."""
    shift, rho, rho_std, delay = (q[k] for q in stop)
    H0 = rec.v_row(k, delay)  # v(t − Δ) + shift
    h = rec.v_row(k, 0.0) - rho * H0
    reach = abs(H0 @ x - shift) + 2.0 * np.sqrt(max(H0 @ P @ H0, 0.0))
    return h, -rho * shift - h @ x, cf * max(rho_std * reach, floor) ** 2


def _stop_contradicts(x, P, k: int, rec: FilterRecord, stop, floor: float, cf: float) -> bool:
    """Whether the prior (x, P) is sure the stop at frame k cannot be: its innovation beyond OUTLIER_GATE of its std."""
    h, nu, r = _stop_row(x, P, k, rec, stop, floor, cf)
    return nu ** 2 > OUTLIER_GATE ** 2 * (h @ P @ h + r)


def _velocity_updates(x, P, k: int, rec: FilterRecord, H, measurements, rest_accel, consider: bool):
    """Update with frame k's direct measurements of v (:func:`kalman_velocity`'s ``measurements``), each gated.

    With ``rest_accel`` (the measurements are rest bounds) one is used only where the reading less the
    offset the posterior has learned could be a camera that does not accelerate.

    Parameters
    ----------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    k : int
        The frame.
    rec : FilterRecord
    H : ndarray, (N,)
        The row of v one latency ago (:meth:`FilterRecord.v_row`), for measurements without their own delay.
    measurements : list of tuple
        As :func:`kalman_velocity` takes them.
    rest_accel : tuple of ndarray or None
        As :func:`kalman_velocity` takes it.
    consider : bool
        As in :func:`_update`.

    Returns
    -------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    """
    for m in measurements:
        z, sd = m[0], m[1]
        Hm = H if len(m) < 3 else rec.v_row(k, m[2])
        if np.isfinite(z[k]) and np.isfinite(sd[k]):
            if rest_accel is not None and rec.accel_reach(x, P, k, rest_accel[0][k], -2.0) > rest_accel[1][k]:
                continue
            x, P = _gated_update(x, P, Hm, z[k] - Hm @ x, sd[k] ** 2, consider)
    return x, P


def ratio_update(x, P, k: int, rec: FilterRecord, cfg: ReadoutConfig, H, D: float, q, r_scale: float,
                 cf: float, consider: bool):
    """Update with vision's κ against the accelerometer: a_m = κ·(v(t − D) + shift) + the offset one latency ago.

    Parameters
    ----------
    x : ndarray, (N,)
        The prior mean.
    P : ndarray, (N, N)
        Its covariance.
    k : int
        The frame.
    rec : FilterRecord
    cfg : ReadoutConfig
    H : ndarray, (N,)
        The row of v one latency ago (:meth:`FilterRecord.v_row`).
    D : float
        s: the latency.
    q : sequence
        Frame k's (κ (1/s), σ_κ (1/s), a_m (m/s²), shift (m/s)[, e_lp (m/s)[, c_κ (3,)]]), as
        :func:`kalman_velocity`'s ``ratio``.
    r_scale : float
        The factor on the noise variance (covariance matching, :class:`_KappaNoise`).
    cf : float
        The frames each floor's error is counted over (corr_frames on the smoother's pass, else 1).
    consider : bool
        As in :func:`_update`.

    Returns
    -------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    nu : float
        m/s²: the innovation.
    hph : float
        (m/s²)²: its prior variance.
    R : float
        (m/s²)²: the noise variance, before ``r_scale``.
    """
    # Long only by its comments, which say why each term of the row and of the noise is what it is.
    kap, skap, am, shift = q[:4]
    e_lp = q[4] if len(q) > 4 else 0.0  # the rates' timing error (m/s), see kalman_readout
    # Where no acceleration is seen (|a_m| below accel_min) the frame carries no depth
    # information (as for v_f): it then speaks for the offset b alone, not for v through a
    # noisy κ ≈ 0. A small a_m alone does not make it so: a_m holds the offset (online the
    # gravity reference's, up to ~1 m/s²; offline the record's mean acceleration), so a_m ≈ 0
    # may be a true −b that κ̂ sees; asking a_m alone pulls b̂ toward 0 there (offline, exact
    # rates with a constant 0.3 m/s² offset: 0.034 m/s RMSE, 0.0002 with this rule; the
    # development scenes' zero-phase 0.0054 against 0.0052). So the frame counts as
    # informative when vision sees an acceleration too.
    informative = abs(am) >= cfg.accel_min_m_s2
    # v one latency ago as the posterior has it: mean and variance (x, P are the prior here).
    vd, pd = H @ x - shift, H @ P @ H
    if not informative:
        # Vision sees an acceleration where κ̂·v would reach accel_min for v as the posterior has
        # it — its RMS √(v̂² + σ_v²), not v̂ alone: while v is unknown (the prior's mean 0) κ̂·v̂ ≈ 0
        # would call every frame uninformative, and those frames, read as a_m = b, would hold the
        # offset at the reading (exact rates receding at 0.15 m/s with a 0.05 m/s² offset: the
        # truth outside ±2σ on 97 % of the first 2 s). Not also "κ̂ ≥ 2σ_κ": σ_κ holds a share of
        # |κ̂| (kappa_rel_error), so that asks for a relative error under ½, not a κ apart from 0,
        # and with the eye's 0.5 it would hold every such frame at the reading (exact fields
        # under rotation: 0.235 m/s against 0.028).
        informative = abs(kap) * np.sqrt(vd ** 2 + pd) >= cfg.accel_min_m_s2
    kv = kap if informative else 0.0
    # a_m = κ·(v(t − D) + shift) + the offset one latency ago, b − ḃ·D (+ c(t − D)·δ)
    # The gravity error δ enters a_m along the axis a_m is measured on: the optical axis one latency ago, or
    # the material fields' κ axis where a_m is the acceleration along it (lobula.readout.field_axes).
    c = rec.c_at(k, D)
    if len(q) > 5 and len(c):
        c = np.asarray(q[5], float)
    h = kv * H + np.concatenate([[0.0, 1.0, 1.0 if cfg.shared_error_frac > 0 else 0.0, -D], c])
    zk = am + (kap * shift if informative else 0.0)
    # The fields' spread (v·σ_κ, floored at meas_floor as a velocity measurement would
    # be) and the filtered accelerometer's noise floor (accel_min_m_s2); its offset and
    # ramp are states, not noise.
    # κ's error multiplies the v it was measured at, v(t − D) (H above), so it counts with
    # E[v(t − D)²] = vd² + pd (errors in variables: a noisy κ ≈ 0 must not pin v while v is unknown).
    # Offline, those floors, like the fields' spread (σ_κ holds it already), are errors of
    # low-passed signals, correlated over corr_frames frames, and counted once per frame they
    # would add up over the whole record to a confidence the data do not hold. Online the
    # filter has only the past, and so counted they slow it down more than they help: the
    # development scenes' causal RMSE falls (0.020 m/s against 0.026), but a real still EuRoC
    # sequence reads 0.013 m/s of motion (bound 0.01) and a 3 s librealsense recording is
    # observable on 44 % only.
    R = ((vd ** 2 + pd) * skap ** 2 + cf * ((kap * cfg.meas_floor_m_s) ** 2
         + (cfg.meas_floor_m_s * skap) ** 2 + cfg.accel_min_m_s2 ** 2 + (kap * e_lp) ** 2))
    hph, nu = h @ P @ h, zk - h @ x
    x, P = _update(x, P, h, nu, r_scale * R, consider)
    return x, P, nu, hph, R


def _update(x, P, h, nu, r, consider: bool):
    """One scalar measurement update of the state.

    consider: state 2 (vision's shared error) is a Schmidt–Kalman consider state: its gain is
    zeroed, and the covariance takes the Joseph form, exact for that suboptimal gain.

    Parameters
    ----------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    h : ndarray, (N,)
        The measurement's row.
    nu : float
        The innovation (the measurement's units).
    r : float
        The measurement's noise variance (its units squared).
    consider : bool

    Returns
    -------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    """
    K = P @ h / (h @ P @ h + r)
    if not consider:
        return x + K * nu, P - np.outer(K, h @ P)
    K[2] = 0.0
    A = np.eye(len(x)) - np.outer(K, h)
    return x + K * nu, A @ P @ A.T + np.outer(K, K) * r


def _gated_update(x, P, h, nu, r, consider: bool):
    """:func:`_update`, unless the innovation exceeds OUTLIER_GATE of its standard deviations: a measurement
    the posterior is sure it cannot be is the front end's fault, not a fact about v, and is left out."""
    if nu ** 2 > OUTLIER_GATE ** 2 * (h @ P @ h + r):
        return x, P
    return _update(x, P, h, nu, r, consider)


def _sign_update(x, P, h, sgn: float, max_std: float):
    """Move the posterior of y = h·x (v) to the side of zero ``sgn`` says, where it lies on the other.

    Only a posterior confident enough to be reported (std ≤ ``max_std``) is judged, and only where its
    mean has the wrong sign. Its variance is first widened until zero lies 1σ from the mean (a posterior
    that was sure of the wrong sign is wrong, not the fields), then its mean moves to that Gaussian's mean
    truncated to the allowed side, m + sgn·σ·φ(u)/Φ(u) with u = sgn·m/σ (Simon 2010, IET Control Theory
    Appl 4:1303, "Kalman filtering with state constraints"), carried to the whole state by y's regression;
    the covariance is kept (truncating it too, frame after frame, left ±2σ at 45 and 25 % on development eye
    worlds rotation 100 and mixed 100: the same constraint counted as new information each frame).

    Parameters
    ----------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    h : ndarray, (N,)
        The row of v.
    sgn : float
        ±1: v's sign.
    max_std : float
        m/s: the largest std judged.

    Returns
    -------
    x : ndarray, (N,)
    P : ndarray, (N, N)
        Widened where the mean lay more than 1σ on the wrong side.
    """
    m, s2 = float(h @ x), float(h @ P @ h)
    if not 0.0 < s2 <= max_std ** 2 or sgn * m >= 0.0:
        return x, P
    if sgn * m < -np.sqrt(s2):
        P = P.copy()
        P += np.outer(h, h) * (m * m - s2) / float(h @ h) ** 2
        s2 = m * m
    s = np.sqrt(s2)
    u = sgn * m / s                          # in [−1, 0): how far onto the wrong side the mean lies, in σ
    lam = float(np.exp(-0.5 * u * u - 0.5 * np.log(2.0 * np.pi) - log_ndtr(u)))   # inverse Mills ratio φ(u)/Φ(u)
    return x + P @ h / s2 * (sgn * s * lam), P
