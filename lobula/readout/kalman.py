"""The kalman readout's filter: v driven by the acceleration, with the accelerometer's offset as states.

The state is (v, b, c, ḃ[, δ]): the forward velocity v (m/s), the accelerometer's offset b (m/s²),
vision's error c that all fields share (m/s², online a consider state, offline estimated), the
offset's ramp ḃ (m/s³) and, where the gravity reference's error turns with the camera, the start
frame's gravity error δ (3, m/s²). :func:`kalman_velocity` runs over the record a frame at a time
(:class:`ForwardPass`, which :class:`lobula.velocity.VelocityEstimator` also steps as frames come):
:func:`predict` carries the state to the frame, then vision's measurements update it
(:mod:`lobula.readout.updates`: the moments v passed through 0, the sign of v, the rest bounds and
κ = a/v) — and offline :func:`lobula.readout.smoothers.rts_smooth` (or, online with a declared delay,
:func:`lobula.readout.smoothers.fixed_lag_smooth`) runs back over it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import ReadoutConfig
from .smoothers import fixed_lag_smooth, rts_smooth
from .record import FilterRecord, _axis_terms, filter_record  # noqa: F401  (re-exported)
from .updates import (_reversal_update, _sign_update, _stop_contradicts, _stop_update, _velocity_updates,
                      ratio_update)



def kalman_velocity(t, a, measurements, cfg: ReadoutConfig, smooth: bool, gravity_tau=None,
                    ratio=None, drift_std=None, delay: float = 0.0, full: bool = False,
                    corr_frames: float = 1.0, turn_rate=None, rest_accel=None, offset_walk=None,
                    offset_axis=None, offset_axis_prior=0.0, transport=None, lag: float = 0.0,
                    reversal=None, sign=None, stop=None):
    """Kalman filter/RTS smoother for v driven by a, with an accelerometer offset b.

    Parameters
    ----------
    t : ndarray, (n,)
        s.
    a : ndarray, (n,)
        m/s²: the forward acceleration.
    measurements : list of tuple
        Measurements of v, each (z (n,), std (n,)) in m/s with NaN where absent, of v one ``delay``
        ago, or (z, std, own_delay) for a measurement with its own latency (s; 0: of v now); one the
        posterior is sure it cannot be (innovation > OUTLIER_GATE σ) is left out.
    cfg : ReadoutConfig
    smooth : bool
        Run the Rauch–Tung–Striebel smoother over the whole record (offline), else the forward filter.
    gravity_tau : ndarray, (n,), optional
        s: when a's gravity was estimated online by an average of time constant τ
        (lobula.imu.online_gravity), that average also takes in the platform's own acceleration,
        so the offset moves as ḃ = −a/τ (a the acceleration given): a known input to the offset state,
        not noise. None: the offset only random-walks.
    ratio : tuple of ndarray, optional
        (κ, σ_κ, a_m, shift[, e_lp[, c_κ]]), each (n,) but c_κ: vision's measurement of a/v (κ = (ṙ − r²)/r
        per field, 1/s, which needs no accelerometer) against the accelerometer's a_m (m/s², low-passed like
        κ, belonging to t − delay, where the low-passed velocity κ multiplies was v(t) − shift (m/s),
        less the offset's share): a_m = κ·(v − shift) + b. Linear in the state, it ties b to the
        accelerometer where a ≈ 0 and v to both elsewhere, so an accelerometer offset cannot scale v
        the way it scales a·r/(ṙ − r²). e_lp (m/s): the rates' timing error (see kalman_readout). c_κ
        (n, 3): where a_m is the acceleration along the material fields' κ axis (lobula.readout.field_axes),
        that axis in ``offset_axis``'s frame, along which the gravity error δ enters a_m.
    drift_std : ndarray, (n,), optional
        m/s²/s: how fast the offset may ramp — gravity seen through an attitude integrated with an
        uncertain gyro bias σ_b drifts at up to |g|·σ_b — as a fourth state ḃ whose std is held within
        drift_std at each frame (None: no ramp).
    delay : float
        s: the measurements' latency (online). They speak of v(t − D) = v(t) − shift + b·D − ḃ·D²/2
        (shift = ∫a over the last D, which holds the offset b) and of b(t − D) = b − ḃ·D, so their
        rows in the state carry those terms; the measurements' z already hold the shift.
    full : bool
        Return the whole posterior rather than v's.
    corr_frames : float
        Frames over which the low-passed measurements' errors are correlated: the smoother counts
        their floors once per that many frames.
    turn_rate : ndarray, (n,), optional
        rad/s: the gyro's |ω| (the acceleration's noise grows while turning: accel_turn_noise).
    rest_accel : tuple of ndarray, optional
        (a_s, tol), each (n,) m/s² (:func:`accelerometer_level`), when the ``measurements`` are rest
        bounds (v ≈ 0): the forward filter uses one only where the camera's reading less the offset it
        has learned could be a camera that does not accelerate, |a_s − b̂| ≤ tol + 2σ_b (kalman_readout
        gives it online only). A camera that accelerates passes through v = 0 for an instant, and a
        bound resting on an assumed depth is then wrong by however far the fields' depths exceed it
        (a ground plane with a far backdrop, the camera reversing at 1.4 m/s²: an unconditional bound
        reads v = 0 ± 0.02 at −0.14 m/s; causal RMSE 0.057 m/s with this condition against 0.074
        without, and on a corridor 0.015 against 0.047). Offline the bound is widened by the
        low-pass's smear σ_t·|a| instead (see kalman_readout).
    offset_walk : ndarray, (n,), optional
        m/s²/√s: more random walk of the offset at each frame, beyond bias_walk — online, as fast as
        the attitude's gravity leak moved while the gyro-bias estimate moved (lobula.imu.leak_walk):
        the offset learned up to then loses that much certainty (None: none).
    offset_axis : ndarray, (n, 3), optional
        The optical axis in the frame gravity was taken in (the first sample's,
        lobula.imu.forward_axis), when the error of that gravity is a vector fixed there — the
        platform's acceleration that the gravity reference averaged in — rather than an offset of the
        accelerometer's own forward axis. Its forward part is then c(t)·δ, which changes as the camera
        turns (a camera panning 25° turns a 1 m/s² start offset's forward part by 0.4 m/s², which a
        random walk of b cannot follow: ±2σ held 63 % of frames online). δ (3 more states) sits beside
        b, which keeps the accelerometer's own offset (prior bias_prior_m_s2); the gravity reference's
        drift input (gravity_tau) moves δ along c. None: the whole offset is b.
    offset_axis_prior : float or ndarray, (3,)
        m/s²: δ's prior std, one for all axes or one per axis.
    transport : ndarray, (n,), optional
        1/s: λ = ω_x·e_y − ω_y·e_x, the gyro's rate ω (rad/s, camera frame) with the heading
        e = (v_x, v_y)/v_z (the epipole, normalised). v is the velocity along the optical axis, and in
        a turning frame dv/dt = a − ω × v, whose forward part is a − λ·v: a camera panning at 0.5 rad/s
        while it moves 25° off its axis sees its forward speed change at 0.23·v beyond what the
        accelerometer's forward axis says. None: 0 (a camera that does not turn, or moves along its axis).
    lag : float
        s, with smooth False: a fixed-lag smoother. Each frame's estimate also takes the measurements
        up to ``lag`` after it (:func:`fixed_lag_smooth`), so it is known ``lag`` later. The forward
        pass is then the smoother's (vision's shared error an estimated state, the floors counted once
        per correlation time), as if the record ended ``lag`` after each frame. 0: the forward filter.
    reversal : tuple of ndarray, optional
        (shift, time_std, delay, accel), each (n,), NaN but where v is seen to have passed through 0
        (:func:`reversal_measurement`): v(t − delay) = 0, measured with std time_std·(|accel − b̂| + 2σ_b)
        — the acceleration as the posterior has it, its offset b̂ (σ_b) included — floored at
        meas_floor_m_s, and left out where its innovation exceeds OUTLIER_GATE of its standard
        deviations: a posterior sure that v was far from 0 then takes the sign change for the front
        end's fault (None: none).
    sign : ndarray, (n,), optional
        ±1 where v is known to have that sign (:func:`expansion_sign` of the newest fields online, the
        zero-phase ones offline: no latency), NaN elsewhere: a posterior of v on the other side is
        moved to it (:func:`_sign_update`; None: none).
    stop : tuple of ndarray, optional
        (shift, ratio, ratio_std, delay), each (n,), NaN but where the fields' expansion has fallen to a stop
        (:func:`stop_measurement`): v(t) = ratio·v(t − delay), with std ratio_std × (|v̂(t − delay)| + 2σ) as
        the posterior has it, floored at meas_floor_m_s and counted once per corr_frames on the smoother's
        pass; not gated (:func:`_stop_update`; None: none).

    Returns
    -------
    v : ndarray, (n,)
        m/s: the posterior mean of v; with ``full``, instead the posterior means (n, N) of the state
        (v, b, c, ḃ[, δ]), N = 4 or 7.
    v_std : ndarray, (n,)
        m/s: the posterior std of v; with ``full``, instead the state's covariances (n, N, N).
    """
    # Long only by its docstring, which states every input of the filter's model; the body is the loop.
    n = len(t)
    fixed_lag = lag > 0 and not smooth
    smooth_pass = smooth or fixed_lag  # the smoother's forward pass (whole record or fixed lag)
    rec = filter_record(t, a, offset_axis, transport, gravity_tau, drift_std, turn_rate, offset_walk)
    fp = ForwardPass(cfg, 0 if offset_axis is None else 3, drift_std, offset_axis_prior, smooth_pass, corr_frames)
    N = len(fp.x)
    xs_pred, Ps_pred, xs, Ps, Fs = (np.zeros((n, N)), np.zeros((n, N, N)), np.zeros((n, N)),
                                    np.zeros((n, N, N)), np.zeros((n, N, N)))
    for k in range(n):  # a loop over time steps; the state has 4 or 7 dimensions
        xs_pred[k], Ps_pred[k], Fs[k], xs[k], Ps[k] = fp.step(k, rec, float(delay), measurements, ratio,
                                                              rest_accel, reversal, sign, stop)
    if smooth:
        xs, Ps = rts_smooth(xs, Ps, xs_pred, Ps_pred, Fs)
    elif fixed_lag:
        xs, Ps = fixed_lag_smooth(t, xs, Ps, xs_pred, Ps_pred, Fs, lag)
    if full:  # the whole posterior: means (n, N) and covariances (n, N, N) of (v, b, ·, ḃ[, δ])
        return xs, Ps
    return xs[:, 0], np.sqrt(np.maximum(Ps[:, 0, 0], 0.0))


class ForwardPass:
    """The filter's forward pass, one frame at a time: :func:`kalman_velocity`'s loop, and what
    :class:`lobula.velocity.VelocityEstimator` runs as frames come.

    Parameters
    ----------
    cfg : ReadoutConfig
    nd : int
        3 where the start frame's gravity error δ is tracked (``offset_axis`` given), else 0.
    drift_std : ndarray, (n,), or None
        m/s²/s: its first value sets the ramp's prior std.
    offset_axis_prior : float or ndarray, (3,)
        m/s²: δ's prior std.
    smooth_pass : bool
        The smoother's forward pass (vision's shared error estimated, floors counted once per
        ``corr_frames``), else the online filter (the shared error a consider state).
    corr_frames : float
        As :func:`kalman_velocity` takes it.
    """

    def __init__(self, cfg: ReadoutConfig, nd: int, drift_std, offset_axis_prior, smooth_pass: bool,
                 corr_frames: float):
        self.cfg, self.smooth_pass, self.corr_frames = cfg, smooth_pass, corr_frames
        sv, sb = cfg.v_prior_m_s ** 2, cfg.bias_prior_m_s2 ** 2
        sd0 = float(drift_std[0]) ** 2 if drift_std is not None else 0.0
        # States: v, the offset b, vision's shared error c (online a consider state, offline estimated), the
        # ramp ḃ, and with offset_axis the start frame's gravity error δ (3).
        self.x = np.zeros(4 + nd)
        sdelta = list(np.broadcast_to(np.asarray(offset_axis_prior, float) ** 2, (nd,)))
        self.P = np.diag([sv, sb, 0.0, sd0] + sdelta)
        # the offset's prior variances (b, ḃ, δ), given back where a stop shows the posterior sure of a wrong offset
        self.offset_prior_var = np.diag([0.0, sb, 0.0, sd0] + sdelta)
        self.consider = cfg.shared_error_frac > 0 and not smooth_pass
        self.noise = _KappaNoise()
        self.cf = corr_frames if smooth_pass else 1.0

    def step(self, k: int, rec: "FilterRecord", D: float, measurements, ratio, rest_accel, reversal, sign,
             stop=None):
        """Predict to frame k (of ``rec``'s arrays) and update with its measurements (each array indexed at k,
        as :func:`kalman_velocity` takes them; D s the measurements' latency).

        Returns
        -------
        x_pred, P_pred, F, x, P : ndarray
            The prediction (N,), (N, N), the transition used (N, N) (identity at the first frame), and the
            posterior (N,), (N, N).
        """
        cfg, x, P, consider = self.cfg, self.x, self.P, self.consider
        F = np.zeros((len(x), len(x)))
        if k > 0:
            x, P, F = predict(x, P, k, rec, cfg, self.noise.shared_var(cfg.shared_error_frac))
        if (not self.smooth_pass and stop is not None and np.isfinite(stop[1][k])
                and _stop_contradicts(x, P, k, rec, stop, cfg.meas_floor_m_s, self.cf)):
            # Braking at a constant rate, κ fits any offset, and the online filter may have settled on one with a
            # confidence the data do not hold; a stop it is sure cannot be says so, and the offset is let go to
            # its prior for the stop to tell it again (online road seed 2: 0.15 → 0.05 m/s, ±2σ 87 → 99 %). The
            # smoother's forward pass keeps it: there the whole record's stop corrects the offset anyway, and
            # the widened offset lets its braking drift (0.12 → 0.26 m/s).
            P = P + self.offset_prior_var
        x_pred, P_pred = x, P
        H = rec.v_row(k, D)  # v(t − D) + shift, in the state at t
        if reversal is not None and np.isfinite(reversal[0][k]):
            x, P = _reversal_update(x, P, k, rec, reversal, cfg.meas_floor_m_s, consider)
        if sign is not None and np.isfinite(sign[k]):
            x, P = _sign_update(x, P, rec.v_row(k, 0.0), sign[k], cfg.max_std_m_s)
        x, P = _velocity_updates(x, P, k, rec, H, measurements, rest_accel, consider)
        if stop is not None and np.isfinite(stop[1][k]):
            x, P = _stop_update(x, P, k, rec, stop, cfg.meas_floor_m_s, self.cf, consider)
        if ratio is not None and all(np.all(np.isfinite(q[k])) for q in ratio):
            x, P, nu, hph, R = ratio_update(x, P, k, rec, cfg, H, D, [q[k] for q in ratio], self.noise.scale,
                                            self.cf, consider)
            self.noise.learn(k, rec.t, nu, hph, R, cfg, self.smooth_pass, self.corr_frames)
        self.x, self.P = x, P
        return x_pred, P_pred, F, x, P


@dataclass
class _KappaNoise:
    """What the filter learns of the κ measurement's errors as it runs.

    Parameters
    ----------
    ms, ms_w : float
        (m/s²)² and 1: the running sum of the κ innovations' squares and its weight (time constant
        shared_error_s), whose ratio sizes vision's shared error c.
    nis, nis_w : float
        1: the running sum of their normalised squares and its weight (time constant adapt_s).
    scale : float
        The factor on the κ measurement's noise variance (covariance matching; 1: none).
    """

    ms: float = 0.0
    ms_w: float = 0.0
    nis: float = 0.0
    nis_w: float = 0.0
    scale: float = 1.0

    def shared_var(self, frac: float) -> float:
        """(m/s²)²: the variance of vision's shared error, ``frac``² × the innovations' running mean square."""
        return frac ** 2 * self.ms / self.ms_w if self.ms_w > 0 else 0.0

    def learn(self, k: int, t, nu: float, hph: float, R: float, cfg: ReadoutConfig, smooth_pass: bool,
              corr_frames: float) -> None:
        """Take in frame k's κ innovation ``nu`` (m/s²), its prior variance ``hph`` and noise variance ``R``
        ((m/s²)²); t (n,) s; smooth_pass: the smoother's forward pass; corr_frames as in kalman_velocity."""
        if cfg.shared_error_frac > 0:
            w = np.exp(-(t[k] - t[k - 1]) / cfg.shared_error_s) if k > 0 else 0.0
            self.ms, self.ms_w = w * self.ms + nu ** 2, w * self.ms_w + 1.0
        if cfg.adapt_s > 0 and smooth_pass:
            # Covariance matching: were R honest, E[ν²] = hPh + R/corr_frames (R holds the
            # low-pass's correlation as a factor corr_frames). Innovations persistently larger
            # say vision's κ is worse than its fields' spread and the shared error claim (a
            # turning camera, near walls at speed): R is scaled up by their running mean
            # ratio (time constant adapt_s), never down. Offline only: the online filter's
            # innovations also carry its own latency bridging's model error, which this would
            # blame on vision (exact rates: causal RMSE 0.038 m/s with it, 0.030 without).
            w = np.exp(-(t[k] - t[k - 1]) / cfg.adapt_s) if k > 0 else 0.0
            self.nis = w * self.nis + nu ** 2 / (hph + R / corr_frames)
            self.nis_w = w * self.nis_w + 1.0
            self.scale = max(1.0, self.nis / self.nis_w)


def predict(x, P, k: int, rec: FilterRecord, cfg: ReadoutConfig, shared_var: float):
    """The state's prediction from frame k − 1 to frame k.

    v integrates the acceleration less the offset (and, turning, the transport λ·v); b follows its
    ramp ḃ and, with gravity_tau, the gravity reference's drift input −a/τ; vision's shared error c
    decays with time constant shared_error_s. Where drift_std says the gyro bias got better known,
    the ramp is bounded anew.

    Parameters
    ----------
    x : ndarray, (N,)
        The posterior mean at frame k − 1.
    P : ndarray, (N, N)
        Its covariance.
    k : int
        The frame predicted to (≥ 1).
    rec : FilterRecord
    cfg : ReadoutConfig
    shared_var : float
        (m/s²)²: the variance of vision's shared error c (:meth:`_KappaNoise.shared_var`).

    Returns
    -------
    x : ndarray, (N,)
    P : ndarray, (N, N)
    F : ndarray, (N, N)
        The transition used.
    """
    dt = rec.t[k] - rec.t[k - 1]
    N = len(x)
    nd = N - 4
    F = np.eye(N)
    F[0, 1], F[1, 3] = -dt, dt
    F[0, 0] = np.exp(-0.5 * (rec.lam[k] + rec.lam[k - 1]) * dt)
    c_mid = rec.c_mean(k, dt)
    if nd:
        F[0, 4:] = -dt * c_mid
    q_c = 0.0
    if cfg.shared_error_frac > 0:
        phi = np.exp(-dt / cfg.shared_error_s)
        F[2, 2] = phi
        q_c = shared_var * (1.0 - phi ** 2)
    u = 0.5 * (rec.a[k] + rec.a[k - 1]) * dt
    ub = -u / rec.gravity_tau[k] if rec.gravity_tau is not None else 0.0
    x = F @ x + (np.concatenate([[u, 0.0, 0.0, 0.0], ub * c_mid]) if nd else np.array([u, ub, 0.0, 0.0]))
    turn = None if rec.turn_rate is None else 0.5 * (rec.turn_rate[k] + rec.turn_rate[k - 1])
    q_a = _accel_density2(cfg, turn)
    q_b = cfg.bias_walk ** 2 + (rec.offset_walk[k] ** 2 if rec.offset_walk is not None else 0.0)
    P = F @ P @ F.T + np.diag([q_a * dt, q_b * dt, q_c, 0.0] + [0.0] * nd)
    if rec.drift_std is not None and P[3, 3] > rec.drift_std[k] ** 2:
        # The gyro bias got better known (still samples): the ramp is bounded anew.
        f = rec.drift_std[k] / np.sqrt(P[3, 3])
        x[3] *= f
        P[3, :] *= f
        P[:, 3] *= f
    return x, P, F


def _accel_density2(cfg: ReadoutConfig, turn_rate: float | None) -> float:
    """Squared noise density ((m/s²)²/Hz) of the acceleration given.

    accel_noise, and while the camera turns at |ω| = ``turn_rate`` (rad/s) accel_turn_noise·|ω|
    more (gravity seen through an attitude that errs more the faster it turns), |ω| counted up to
    accel_turn_rate_max.
    """
    q = cfg.accel_noise ** 2
    if turn_rate is not None:
        if cfg.accel_turn_rate_max is not None:
            turn_rate = min(turn_rate, cfg.accel_turn_rate_max)
        q += (cfg.accel_turn_noise * turn_rate) ** 2
    return q
