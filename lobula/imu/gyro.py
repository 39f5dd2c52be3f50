"""The gyroscope: its bias (where the camera is still, fused with the flow's heading fit, or from the flow's
residual rotation), the orientation it integrates to, and :class:`GyroAttitude`, which integrates with a
bias learned as it goes. Rates rad/s in the camera frame, times s."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

GYRO_NOISE_DENSITY = np.radians(0.014)  # rad/s/√Hz, Bosch BMI055 (the D435i's IMU) datasheet
#: rad/s: prior spread of a MEMS gyro's zero-rate offset before anything in the record has measured it, as
#: consumer data sheets give it (Bosch BMI055, the D435i's IMU: ±1°/s). A narrower prior leaves a camera
#: that starts moving and turning, with a bias of that size, confidently wrong: the attitude integrated
#: meanwhile lets gravity into the forward axis faster than the readout's offset is allowed to move.
GYRO_BIAS_PRIOR = np.radians(1.0)
#: rad/s: the bias prior of the flow's heading and bias fit (lobula.epipole.HeadingBiasEstimator), a
#: regulariser rather than a belief about the gyro: on frontal scenes a pitch/yaw bias is nearly
#: confounded with a shift of the epipole, and a fit that starts at the data sheet's spread trades one
#: for the other (the suite's mixed family: zero-phase RMSE ×4). The fit still moves its bias where the
#: flow tells the two apart (a 1°/s bias is learned within ~3 s), and its estimate is fused, std
#: scaled by HEADING_BIAS_STD_SCALE, with the still-camera estimate, whose prior is GYRO_BIAS_PRIOR.
HEADING_FIT_BIAS_PRIOR = np.radians(0.2)


def gyro_bias(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False, window_s: float = 0.5,
              noise_density: float = GYRO_NOISE_DENSITY, with_std: bool = False,
              prior: float = GYRO_BIAS_PRIOR):
    """Gyroscope bias (rad/s, (n, 3)) estimated where the camera is still — the one implementation.

    time_s (n,) s and gyro (n, 3) rad/s: the gyro's samples.
    A sample is still when, over a window of ``window_s`` around it (causal: ending at it),
    the rate's standard deviation on every axis stays within 1.5× the white noise the
    sensor's ``noise_density`` allows, i.e. the camera is not turning. The bias is the
    mean rate over the still samples: online, those seen so far (0 before the first,
    the bias's expected value); offline, all of the record's. A camera that keeps turning
    gives no estimate rather than a wrong one: a mean rate over motion is the net angle
    turned divided by the time, not the bias. window_s: s; noise_density: rad/s/√Hz.
    with_std: also return the estimate's standard deviation (rad/s, (n,)): the prior ``prior``
    (rad/s; default ``GYRO_BIAS_PRIOR``) narrowed by the still samples' white noise.
    """
    time_s, gyro = np.asarray(time_s, float), np.asarray(gyro, float)
    n = len(time_s)
    if n < 3:
        return (np.zeros((n, 3)), np.full(n, prior)) if with_std else np.zeros((n, 3))
    rate = 1.0 / float(np.median(np.diff(time_s)))
    sigma = noise_density * np.sqrt(rate / 2)
    k = max(3, int(round(window_s * rate)))
    c1 = np.concatenate([np.zeros((1, 3)), np.cumsum(gyro, 0)])
    c2 = np.concatenate([np.zeros((1, 3)), np.cumsum(gyro ** 2, 0)])
    hi = np.arange(1, n + 1) if causal else np.minimum(np.arange(n) + k // 2 + 1, n)
    lo = np.maximum(hi - k, 0)
    m = (hi - lo)[:, None]
    mean = (c1[hi] - c1[lo]) / m
    var = np.maximum((c2[hi] - c2[lo]) / m - mean ** 2, 0.0)
    still = (m[:, 0] >= k) & np.all(var <= (1.5 * sigma) ** 2, axis=1)
    if causal:
        count = np.cumsum(still)[:, None]
        total = np.cumsum(gyro * still[:, None], 0)
        bias = np.where(count > 0, total / np.maximum(count, 1), 0.0)
        count = count[:, 0]
    else:
        bias = np.broadcast_to(gyro[still].mean(0) if still.any() else np.zeros(3), (n, 3)).copy()
        count = np.full(n, still.sum())
    if not with_std:
        return bias
    return bias, 1.0 / np.sqrt(1.0 / prior ** 2 + count / sigma ** 2)


def orientation_from_gyro(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False,
                          bias: np.ndarray | None = None) -> np.ndarray:
    """Rotations (n, 3, 3) taking camera-frame vectors at each sample into the first sample's frame.

    time_s (n,) s and gyro (n, 3) rad/s: the gyro's samples.
    The gyro bias is removed first: ``bias`` (n, 3) rad/s where given (e.g.
    :func:`vision_gyro_bias`'s), else the still-camera estimate of :func:`gyro_bias`.
    Each sample is the rate *at* its time stamp, so the rotation between samples k − 1 and
    k is integrated with the rate taken linear in between (:func:`rotation_increments`:
    the trapezoid plus the coning term), which needs nothing after sample k (causal). The
    rectangle rule ω_k·Δt runs half a sample (2 ms at 250 Hz) late: under a 3-axis turn it
    leaves a residual rotation of the order of a MEMS gyro's bias in every flow pair, which
    biases vision's κ = a/v by 2–6 % low and the low-speed epipole by degrees (rotation
    family, development seeds, exact rate integrated both ways).
    """
    n = len(time_s)
    w = gyro - (gyro_bias(time_s, gyro, causal) if bias is None else np.asarray(bias, float))
    steps = Rotation.from_rotvec(rotation_increments(time_s, w)).as_matrix()
    out = np.empty((n, 3, 3))
    r = np.eye(3)
    out[0] = r
    for k in range(1, n):  # composition is sequential; 3x3 products, ~µs each
        r = r @ steps[k - 1]
        out[k] = r
    return out


def rotation_increments(time_s: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """Rotation vectors (n − 1, 3) rad of the body frame from sample k − 1 to k, for rates
    ``rate`` (n, 3) rad/s sampled at ``time_s`` (n,) s and taken linear in between.

    For ω(τ) linear from ω₀ to ω₁ over Δt the rotation vector is, to third order in the
    angle, (ω₀ + ω₁)/2·Δt + (ω₀ × ω₁)·Δt²/12 (the trapezoid plus the coning correction;
    Bortz's equation integrated over one step).
    """
    t = np.asarray(time_s, float)
    w = np.asarray(rate, float)
    dt = np.diff(t)[:, None]
    return 0.5 * (w[1:] + w[:-1]) * dt + np.cross(w[:-1], w[1:]) * dt ** 2 / 12.0


#: The flow-fitted gyro bias (lobula.epipole.HeadingBiasEstimator) claims a formal std that its
#: error exceeds: over the development rotation scenes (suite seeds 100-103, realistic IMU, causal,
#: the final estimate against the scene's true bias in the camera frame) |error|/std per axis is
#: 0.1-15, RMS 6.1 (a constant-bias model of a bias that walks, flow errors taken as independent).
#: Its std is scaled by this much before it is fused with the still-camera estimate. (3 and 10 give
#: the same development results within 0.0003 m/s; on the real EuRoC start, whose 1.7 / 0.2 /
#: 4.7°/s bias lies far outside the 0.2°/s prior the fit starts from, its 4.7 s estimate is off by
#: 10-18 formal std.)
HEADING_BIAS_STD_SCALE = 6.0


def fused_gyro_bias(time_s: np.ndarray, still_bias: np.ndarray, still_std: np.ndarray, t_est: np.ndarray,
                    est_bias: np.ndarray, est_std: np.ndarray, causal: bool,
                    est_std_scale: float = HEADING_BIAS_STD_SCALE) -> tuple[np.ndarray, np.ndarray]:
    """The gyro bias and its std (rad/s, both (n, 3)) at the IMU samples ``time_s`` (n,) s: the still-camera
    estimate (still_bias (n, 3), still_std (n,) or (n, 3); :func:`gyro_bias`) and the flow's
    (est_bias, est_std (m, 3), known at t_est (m,) s; :class:`lobula.epipole.HeadingBiasEstimator`,
    its std times ``est_std_scale``, dimensionless) combined by inverse variance; biases and stds rad/s.

    causal: each sample takes the flow's newest estimate known by then (the still one alone before
    the first); offline: the flow's last, which has seen the whole record. A camera that never stops
    has no still estimate (std the prior, GYRO_BIAS_PRIOR), and its attitude then drifts at the whole bias,
    turning gravity into the forward axis at up to |g|·1°/s ≈ 0.17 m/s² per second.
    """
    n = len(time_s)
    ss = np.broadcast_to(np.reshape(np.asarray(still_std, float), (n, -1)), (n, 3))
    est_bias, est_std = np.asarray(est_bias, float), np.asarray(est_std, float) * est_std_scale
    if len(t_est) == 0:
        return np.array(still_bias, float), np.array(ss)
    if causal:
        k = np.searchsorted(t_est, time_s, side="right") - 1
        seen = (k >= 0)[:, None]
        eb = np.where(seen, est_bias[np.maximum(k, 0)], 0.0)
        es = np.where(seen, est_std[np.maximum(k, 0)], np.inf)
    else:
        eb, es = np.broadcast_to(est_bias[-1], (n, 3)), np.broadcast_to(est_std[-1], (n, 3))
    w_still, w_est = 1.0 / ss ** 2, 1.0 / es ** 2
    return (still_bias * w_still + eb * w_est) / (w_still + w_est), 1.0 / np.sqrt(w_still + w_est)


#: rad/s²/√Hz: how fast a MEMS gyro's bias may wander (random walk), a generous figure for
#: consumer units (Allan-variance fits for the BMI055 give a few 1e-5; temperature adds more).
GYRO_BIAS_WALK = 1e-4
#: rad/s: a single pair's residual rate before the record has told its own scatter
#: (first-order: flow noise ~0.5 px over a 0.2 s pair across a ~0.5 rad field of view).
RESIDUAL_RATE_PRIOR_STD = 0.02
MIN_RESIDUALS = 5  # residuals needed before their own scatter sets the measurement noise
#: fraction: prior std of each entry of a gyro's scale-factor and misalignment error E
#: (data sheets: sensitivity ±1–2 %, cross-axis ±1–2 %).
GYRO_SCALE_PRIOR = 0.02
RESIDUAL_GATE = 4.0  # innovations beyond this many σ are taken as failed pairs, not as the bias


def vision_gyro_bias(t_meas: np.ndarray, residual: np.ndarray, time_s: np.ndarray, prior_bias: np.ndarray,
                     prior_std: np.ndarray | float, causal: bool, rate: np.ndarray | None = None,
                     walk: float = GYRO_BIAS_WALK, scale_std: float = GYRO_SCALE_PRIOR):
    """The gyro bias (rad/s) from what vision says the gyro-derotated flow still turns by.

    A camera that never stops turning gives :func:`gyro_bias` nothing. Vision does: after
    derotation with the gyro (bias b₀ removed), the flow of a rigid scene is radial from the
    epipole except for the rotation the gyro got wrong, δω = b − b₀ + E·ω, with E the
    gyro's scale-factor and misalignment errors; :func:`lobula.depth_motion.refine_motion`
    fits it per flow pair. ``t_meas`` (m,) s and ``residual`` (m, 3) rad/s: those fits (use
    pairs that do not overlap, so their flow errors are independent), with b₀ already added
    back (residual = b₀(t) + δω); ``rate`` (m, 3) rad/s: the gyro's mean rate over each
    pair, the regressor of E (None: E·ω is left in the noise, where it is not white).

    Per camera axis i, a Kalman filter on (b_i, E_i·) — b a random walk (``walk``
    rad/s²/√Hz) started at ``prior_bias`` (3,) ± ``prior_std`` (rad/s, scalar or (3,); the
    still-camera estimate and its std at the start), the row E_i· constant with prior std
    ``scale_std`` (dimensionless). Its
    measurement noise is the residuals' own scatter, 1.4826·MAD of successive differences
    / √2 (robust to the slow drift and to outlying pairs; it also holds the part of E·ω that
    changes between pairs, so it errs wide), from the pairs seen so far (causal) or all of
    them (offline; followed by an RTS smoother); a residual more than ``RESIDUAL_GATE`` σ
    from the prediction is left out. Returns (bias (n, 3), std (n, 3)) at ``time_s`` (n,):
    causal values hold until the next pair, with the walk's variance growing in between.
    """
    t_meas = np.asarray(t_meas, float)
    z = np.asarray(residual, float).reshape(-1, 3)
    w = np.zeros_like(z) if rate is None else np.asarray(rate, float).reshape(-1, 3)
    time_s = np.asarray(time_s, float)
    n = len(time_s)
    b0 = np.broadcast_to(np.asarray(prior_bias, float), (3,)).copy()
    p0 = np.broadcast_to(np.asarray(prior_std, float) ** 2, (3,)).copy()
    ok = np.all(np.isfinite(z), axis=1) & np.all(np.isfinite(w), axis=1)
    t_meas, z, w = t_meas[ok], z[ok], w[ok]
    m = len(t_meas)
    if m == 0:
        return np.broadcast_to(b0, (n, 3)).copy(), np.broadcast_to(np.sqrt(p0), (n, 3)).copy()
    r = _residual_variance(z, causal)
    q_rate = walk ** 2
    xf, xp, Pf, Pp = _bias_filter(t_meas, z, w, r, time_s, b0, p0, q_rate, scale_std)
    if causal:
        j = np.searchsorted(t_meas, time_s, side="right") - 1
        before = j < 0
        jj = np.maximum(j, 0)
        gap = np.where(before, time_s - time_s[0], time_s - t_meas[jj])
        bias = np.where(before[:, None], b0, xf[jj, :, 0])
        var = np.where(before[:, None], p0, Pf[jj, :, 0, 0]) + q_rate * np.maximum(gap, 0.0)[:, None]
        return bias, np.sqrt(var)
    return _smoothed_bias(t_meas, time_s, xf, xp, Pf, Pp, q_rate)


def _residual_variance(z: np.ndarray, causal: bool) -> np.ndarray:
    """Measurement variance (m, 3) (rad/s)² of each residual ``z`` (m, 3) rad/s: the prior until
    ``MIN_RESIDUALS`` are seen, then their successive differences' robust scatter."""
    m = len(z)
    dz = np.abs(np.diff(z, axis=0)) if m > 1 else np.zeros((0, 3))
    r = np.full((m, 3), RESIDUAL_RATE_PRIOR_STD ** 2)
    if causal:
        for k in range(MIN_RESIDUALS, m):  # m ~ 5 per second: a short loop over pairs, not pixels
            r[k] = (1.4826 * np.median(dz[:k], axis=0) / np.sqrt(2)) ** 2
    elif m > MIN_RESIDUALS:
        r[:] = (1.4826 * np.median(dz, axis=0) / np.sqrt(2)) ** 2
    return np.maximum(r, 1e-12)


def _bias_filter(t_meas, z, w, r, time_s, b0, p0, q_rate, scale_std):
    """The Kalman filter's filtered and predicted states (m, 3, 4) and covariances (m, 3, 4, 4) at
    the pairs ``t_meas`` (m,) s."""
    m, n = len(t_meas), len(time_s)
    # State per axis (3 axes batched): [b, E_i0, E_i1, E_i2]; measurement h = [1, ω].
    x = np.zeros((3, 4))
    x[:, 0] = b0
    P = np.zeros((3, 4, 4))
    P[:, 0, 0] = p0
    P[:, 1:, 1:] = np.eye(3) * max(scale_std, 1e-6) ** 2  # without rate, ω = 0: E never enters
    xf, xp = np.empty((m, 3, 4)), np.empty((m, 3, 4))
    Pf, Pp = np.empty((m, 3, 4, 4)), np.empty((m, 3, 4, 4))
    t_prev = float(time_s[0]) if n else float(t_meas[0])
    for k in range(m):
        P = P.copy()
        P[:, 0, 0] += q_rate * max(t_meas[k] - t_prev, 0.0)
        xp[k], Pp[k] = x, P
        h = np.concatenate([[1.0], w[k]])
        s = np.einsum("i,aij,j->a", h, P, h) + r[k]
        innov = z[k] - x @ h
        # A pair whose flow failed (occlusion, a moving object) claims a wild rotation: gate it.
        use = np.abs(innov) <= RESIDUAL_GATE * np.sqrt(s)
        g = np.einsum("aij,j->ai", P, h) / s[:, None] * use[:, None]
        x = x + g * innov[:, None]
        P = P - np.einsum("ai,j,ajk->aik", g, h, P)
        xf[k], Pf[k], t_prev = x, P, t_meas[k]
    return xf, xp, Pf, Pp


def _smoothed_bias(t_meas, time_s, xf, xp, Pf, Pp, q_rate):
    """(bias (n, 3), std (n, 3)) rad/s at ``time_s`` (n,) s from the RTS-smoothed filter."""
    m = len(t_meas)
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(m - 2, -1, -1):  # Rauch–Tung–Striebel smoother (transition: identity)
        c = Pf[k] @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + np.einsum("aij,aj->ai", c, xs[k + 1] - xp[k + 1])
        Ps[k] = Pf[k] + c @ (Ps[k + 1] - Pp[k + 1]) @ np.swapaxes(c, -1, -2)
    bias = np.stack([np.interp(time_s, t_meas, xs[:, i, 0]) for i in range(3)], -1)
    # Between pairs the walk adds at most its variance over half the spacing; beyond the ends, over the distance.
    if m == 1:
        d = np.abs(time_s - t_meas[0])
    else:
        j = np.clip(np.searchsorted(t_meas, time_s), 1, m - 1)
        d = np.minimum(np.abs(time_s - t_meas[j - 1]), np.abs(t_meas[j] - time_s))
    var = np.stack([np.interp(time_s, t_meas, Ps[:, i, 0, 0]) for i in range(3)], -1) + q_rate * d[:, None]
    return bias, np.sqrt(var)


class GyroAttitude:
    """The camera's orientation from the gyro, integrated causally with a bias that may change.

    A camera that keeps turning gives :func:`gyro_bias` no still samples, so the gyro's bias
    (a BMI055's: ±0.25 °/s, wandering) stays in every pair's derotation; vision can learn it
    (:class:`lobula.epipole.HeadingBiasEstimator`) and set ``bias`` (3,) rad/s here as it goes.
    ``__call__(t)`` integrates the gyro (:func:`rotation_increments`) with the bias current
    when a sample is first needed, up to the latest time asked, and never revises what it has
    integrated (causal: nothing after t is used). Orientations are camera → the first sample's
    frame, slerped between samples; times before the latest asked are served from what is
    integrated. :meth:`applied_correction` says which correction a stretch is integrated with.

    time_s (n,) s and gyro (n, 3) rad/s: the gyro's samples (at least two; :meth:`extend` adds
    more); bias0 (3,) rad/s: the starting bias; scale (3, 3) dimensionless: the starting
    scale-factor and misalignment error E (None: zero).
    """

    def __init__(self, time_s: np.ndarray, gyro: np.ndarray, bias0, scale=None):
        self._t = np.array(time_s, float)
        self._w = np.array(gyro, float).reshape(-1, 3)
        self._n = len(self._t)
        if len(self.t) < 2:
            raise ValueError("GyroAttitude needs at least two gyro samples")
        self.bias = np.broadcast_to(np.asarray(bias0, float), (3,)).copy()
        #: (3, 3): the gyro's scale-factor and misalignment error E (reading = (I + E)·ω + b);
        #: the rate used is (w − b) − E·(w − b), (I + E)⁻¹ to first order.
        self.scale = np.zeros((3, 3)) if scale is None else np.asarray(scale, float).copy()
        self._q = np.empty((len(self.t), 3, 3))
        self._q[0] = np.eye(3)
        self._corr = np.zeros((len(self.t), 3))  # w − rate used, at each integrated sample
        self._done = -1  # samples whose correction is fixed: 0.._done (orientation known to max(0, _done))

    @property
    def t(self) -> np.ndarray:
        """(m,) s: the gyro's sample times so far."""
        return self._t[:self._n]

    @property
    def w(self) -> np.ndarray:
        """(m, 3) rad/s: its readings so far."""
        return self._w[:self._n]

    def extend(self, time_s: np.ndarray, gyro: np.ndarray) -> None:
        """Append gyro samples, ``time_s`` (k,) s after the last one and ``gyro`` (k, 3) rad/s
        (frame-by-frame use)."""
        time_s, gyro = np.asarray(time_s, float).reshape(-1), np.asarray(gyro, float).reshape(-1, 3)
        k, n = len(time_s), self._n
        if not k:
            return
        if n + k > len(self._t):  # room doubles: appending stays linear in the samples
            grow = max(n + k, 2 * len(self._t))
            pad = lambda a: np.concatenate([a, np.zeros((grow - len(a),) + a.shape[1:])])
            self._t, self._w, self._q, self._corr = (pad(a) for a in (self._t, self._w, self._q, self._corr))
        self._t[n:n + k], self._w[n:n + k] = time_s, gyro
        self._n = n + k

    def _integrate_to(self, k: int):
        k = min(k, len(self.t) - 1)
        if k <= self._done:
            return
        j = max(self._done, 0)
        lo = self._done + 1  # samples whose correction is set now
        wb = self.w[lo:k + 1] - self.bias
        self._corr[lo:k + 1] = self.bias + wb @ self.scale.T
        rate = self.w[j:k + 1] - self._corr[j:k + 1]
        steps = Rotation.from_rotvec(rotation_increments(self.t[j:k + 1], rate)).as_matrix()
        r = self._q[j]
        for i in range(k - j):  # sequential composition, 3x3 products
            r = r @ steps[i]
            self._q[j + 1 + i] = r
        self._done = k

    def __call__(self, t) -> np.ndarray:
        """Orientations (k, 3, 3) at times t (k,) s."""
        t = np.clip(np.atleast_1d(np.asarray(t, float)), self.t[0], self.t[-1])
        hi = np.searchsorted(self.t, t, side="left")
        k0 = np.clip(hi - 1, 0, len(self.t) - 2)
        k1 = k0 + 1
        self._integrate_to(int(k1.max()))
        span = self.t[k1] - self.t[k0]
        frac = np.clip(np.where(span > 0, (t - self.t[k0]) / np.where(span > 0, span, 1.0), 0.0), 0.0, 1.0)
        q0, q1 = self._q[k0], self._q[k1]
        step = Rotation.from_matrix(np.einsum("kji,kjl->kil", q0, q1)).as_rotvec() * frac[:, None]
        return q0 @ Rotation.from_rotvec(step).as_matrix()

    def applied_correction(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """(c (3,), w (3,)) rad/s: the mean correction removed from the gyro over [t0, t1] s (bias plus
        E·rate) and its mean reading there. Call for t1 first, so the stretch is integrated."""
        lo, hi = np.searchsorted(self.t, [t0, t1], side="left")
        lo, hi = min(lo, self._done), min(max(hi, lo + 1), self._done + 1)
        if hi <= lo:
            return self.bias.copy(), self.w[max(lo, 0)].copy()
        return self._corr[lo:hi].mean(0), self.w[lo:hi].mean(0)
