"""Forward acceleration from an accelerometer (and gyroscope), as the fly's halteres would supply it.

An accelerometer reads specific force f = a − g (plus bias) in the camera frame.
Forward acceleration needs gravity removed, and the recording may start in motion,
so nothing assumes an initial rest. Instead: the gyroscope (its bias estimated where the
camera is still, :func:`gyro_bias`) tracks the camera's orientation, the
specific force is rotated into the first frame where gravity is a constant vector.
Offline that vector is the mean over a long centred window (the platform's mean
acceleration over a bounded track is ~0); online it is a reference set over the first
quarter second and updated slowly (:func:`online_gravity`), so its error is nearly a
constant offset (the start's acceleration) that the readout's offset state learns from
vision. The attitude that removes gravity integrates the gyro less its bias: the still-camera
estimate, fused with the one the flow's heading fit learns (:func:`fused_gyro_bias`) where the
camera turns without stopping. What the bias's error leaves (gravity ramping through the
forward axis) is the readout's ramp state, not fitted here. Samples are then averaged over
each flow interval and interpolated to the flow's time stamps.

The gyro is integrated with the rate taken linear between samples (trapezoid plus coning,
:func:`rotation_increments`). For the image (derotation, heading, fields) a turning camera's
gyro bias and scale error are learned from the flow itself
(:class:`lobula.epipole.HeadingBiasEstimator`) and :class:`GyroAttitude` integrates with
them as they are learned.
"""
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
ACCEL_CORRELATION_S = 1.0  # s: a track's accelerations stay correlated over about a second
G = 9.80665  # m/s², standard gravity


def gyro_bias(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False, window_s: float = 0.5,
              noise_density: float = GYRO_NOISE_DENSITY, with_std: bool = False,
              prior: float = GYRO_BIAS_PRIOR):
    """Gyroscope bias (rad/s, (n, 3)) estimated where the camera is still — the one implementation.

    A sample is still when, over a window of ``window_s`` around it (causal: ending at it),
    the rate's standard deviation on every axis stays within 1.5× the white noise the
    sensor's ``noise_density`` allows, i.e. the camera is not turning. The bias is the
    mean rate over the still samples: online, those seen so far (0 before the first,
    the bias's expected value); offline, all of the record's. A camera that keeps turning
    gives no estimate rather than a wrong one: a mean rate over motion is the net angle
    turned divided by the time, not the bias. with_std: also return the estimate's
    standard deviation (rad/s, (n,)): the prior ``prior`` (rad/s; default ``GYRO_BIAS_PRIOR``)
    narrowed by the still samples' white noise.
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

    The gyro bias is removed first: ``bias`` (n, 3) rad/s where given (e.g.
    :func:`vision_gyro_bias`'s), else the still-camera estimate of :func:`gyro_bias`.
    Each sample is the rate *at* its time stamp, so the rotation between samples k − 1 and
    k is integrated with the rate taken linear in between (:func:`rotation_increments`:
    the trapezoid plus the coning term), which needs nothing after sample k (causal). The
    rectangle rule ω_k·Δt it replaces runs half a sample (2 ms at 250 Hz) late: under a
    3-axis turn that left a residual rotation of the order of a MEMS gyro's bias in every
    flow pair, which biased vision's κ = a/v by 2–6 % low and the low-speed epipole by
    degrees (rotation family, development seeds, exact rate integrated both ways).
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
    (n, 3) rad/s sampled at ``time_s`` (n,) s and taken linear in between.

    For ω(τ) linear from ω₀ to ω₁ over Δt the rotation vector is, to third order in the
    angle, (ω₀ + ω₁)/2·Δt + (ω₀ × ω₁)·Δt²/12 (the trapezoid plus the coning correction;
    Bortz's equation integrated over one step).
    """
    t = np.asarray(time_s, float)
    w = np.asarray(rate, float)
    dt = np.diff(t)[:, None]
    return 0.5 * (w[1:] + w[:-1]) * dt + np.cross(w[:-1], w[1:]) * dt ** 2 / 12.0


GRAVITY_WINDOW_S = 60.0  # longer than a track's excursions (seconds), so its acceleration averages out
GRAVITY_INIT_S = 0.25  # s: online, the first gravity reference is the mean specific force over this long


def gravity_time_constant(time_s: np.ndarray, t0: float, tau_s: float = GRAVITY_WINDOW_S,
                          init_s: float = GRAVITY_INIT_S) -> np.ndarray:
    """Time constant (s, like time_s) of the online gravity estimate (:func:`online_gravity`) at each time.

    Over the first ``init_s`` after ``t0`` it is a growing mean (τ = elapsed time), then an
    exponential average of time constant ``tau_s``. Its error b (the offset it leaves in
    the forward acceleration) then obeys ḃ = −a_m/τ with a_m the forward acceleration it
    gives (lobula.readout.kalman_velocity takes this as a known input).
    """
    el = np.asarray(time_s, float) - t0
    return np.where(el < init_s, np.maximum(el, 1e-3), tau_s)


def online_gravity(time_s: np.ndarray, f: np.ndarray, tau_s: float = GRAVITY_WINDOW_S,
                   init_s: float = GRAVITY_INIT_S) -> np.ndarray:
    """Causal estimate of −gravity as specific force (n, 3) from the stabilised specific force f (n, 3).

    A mean over the record's first ``init_s`` seconds (growing until then), then an
    exponential average with time constant ``tau_s``: the reference is set at the start and
    moves only slowly after, so its error is nearly a constant offset (the platform's mean
    acceleration over the first ``init_s``) plus a slow drift ḃ = −a_m/τ that the readout
    integrates exactly. A trailing window mean instead leaves −(v(t) − v(t − span))/span,
    which changes fast while the window is short and lets an accelerating start pass for
    gravity (the fast family: causal RMSE 0.67 m/s with it).
    """
    from scipy.signal import lfilter

    t = np.asarray(time_s, float)
    f = np.asarray(f, float)
    n = len(t)
    count = np.arange(1, n + 1)[:, None]
    out = np.cumsum(f, 0) / count  # growing mean
    k0 = int(np.searchsorted(t, t[0] + init_s))
    if 0 < k0 < n:
        dt = float(np.median(np.diff(t))) if n > 1 else 1.0
        alpha = min(1.0, dt / tau_s)
        zi = (1 - alpha) * out[k0 - 1]
        out[k0:] = lfilter([alpha], [1.0, -(1 - alpha)], f[k0:], axis=0, zi=zi[None, :])[0]
    return out


def local_linear(time_s: np.ndarray, values: np.ndarray, window_s: float, causal: bool,
                 slope_std: np.ndarray | float = np.inf, correlation_s: float = ACCEL_CORRELATION_S) -> np.ndarray:
    """A straight line in time fitted to ``values`` (n, k) over a sliding window, evaluated at each sample.

    Zero-phase: the window is centred on each sample (clipped to the record); causal: it
    ends at the sample. The slope has a zero-mean Gaussian prior of std ``slope_std``
    (per sample, (n,) or scalar; units of values per second) against the residual
    variance in the window, whose samples count as independent once per
    ``correlation_s``: a slope the data cannot tell from their own wander stays near 0.
    Vectorised with cumulative sums; returns (n, k).
    """
    t = np.asarray(time_s, float) - float(np.mean(time_s))
    y = np.asarray(values, float)
    z = lambda a: np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, 0)])
    c0, c1, c2 = z(np.ones_like(t)), z(t), z(t * t)
    y0, y1, y2 = z(y), z(t[:, None] * y), z(y * y)
    n = len(t)
    if causal:
        hi = np.arange(1, n + 1)
        lo = np.searchsorted(t, t - window_s, side="left")
    else:
        lo = np.searchsorted(t, t - window_s / 2, side="left")
        hi = np.searchsorted(t, t + window_s / 2, side="right")
    m = (c0[hi] - c0[lo])[:, None]
    tm = (c1[hi] - c1[lo])[:, None] / m
    s2c = (c2[hi] - c2[lo])[:, None] - m * tm ** 2
    ym = (y0[hi] - y0[lo]) / m
    q1c = (y1[hi] - y1[lo]) - m * tm * ym
    var = np.maximum((y2[hi] - y2[lo]) / m - ym ** 2, 0.0)
    rate = 1.0 / float(np.median(np.diff(time_s))) if n > 1 else 1.0
    prior = np.broadcast_to(np.asarray(slope_std, float), (n,))[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(np.isfinite(prior), var * max(correlation_s * rate, 1.0) / prior ** 2, 0.0)
        slope = np.where(s2c + lam > 0, q1c / (s2c + lam), 0.0)
    return ym + slope * (t[:, None] - tm)


def forward_acceleration(time_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray | None = None,
                         causal: bool = False, window_s: float = GRAVITY_WINDOW_S,
                         bias: np.ndarray | None = None, orientation: np.ndarray | None = None) -> np.ndarray:
    """Gravity-free acceleration along the optical axis (m/s², (n,)) from specific force (n, 3).

    Raises ValueError for non-finite input. With ``gyro`` (n, 3) rad/s the gravity
    direction follows the camera's rotation; without it the orientation is taken as fixed.
    Gravity in the gyro-stabilised frame is, offline, the mean specific force there over
    ``window_s`` centred on each sample (a bounded track's acceleration averages out);
    online, a reference set over the first seconds and updated with time constant
    ``window_s`` (:func:`online_gravity`), whose offset the readout tracks. What is left of the gyro bias turns that frame at a near-constant rate, so
    gravity leaks into the forward axis as a ramp of up to |g|·σ_b (σ_b the bias
    estimate's own uncertainty, :func:`gyro_bias`). That ramp is NOT fitted here: a
    straight line fitted blind to the specific force also takes the platform's own
    acceleration trend (ablation, rotation family with a perfect IMU and exact flow:
    0.048 m/s RMSE with a fitted slope, 0.024 without). It is left for the readout's ramp
    state, where vision tells the two apart (:func:`gravity_drift_std`, offline and online).
    bias: the gyro bias track (n, 3) rad/s to stabilise with (:func:`orientation_from_gyro`).
    orientation: those rotations (n, 3, 3) where already integrated from the same gyro, ``causal``
    and ``bias`` (:func:`orientation_from_gyro`; e.g. shared with :func:`forward_axis`).
    """
    if not (np.all(np.isfinite(accel)) and np.all(np.isfinite(time_s))):
        raise ValueError("accelerometer samples contain NaN or inf")
    n = len(time_s)
    if orientation is not None:
        rot = np.asarray(orientation, float)
        if rot.shape != (n, 3, 3):
            raise ValueError(f"orientation must be shaped ({n}, 3, 3) like the samples, got {rot.shape}")
    elif gyro is not None:
        rot = orientation_from_gyro(time_s, gyro, causal, bias)
    else:
        rot = np.broadcast_to(np.eye(3), (n, 3, 3))
    f0 = np.einsum("nij,nj->ni", rot, accel)  # specific force in the first frame
    g0 = -(online_gravity(time_s, f0, window_s) if causal else local_linear(time_s, f0, window_s, False, slope_std=0.0))
    g_cam = np.einsum("nji,nj->ni", rot, g0)
    return (accel + g_cam)[:, 2]


def forward_axis(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False,
                 bias: np.ndarray | None = None, orientation: np.ndarray | None = None) -> np.ndarray:
    """The optical axis (n, 3), unit vectors in the first sample's frame: the frame in which
    :func:`forward_acceleration` takes gravity (same ``gyro``, ``causal`` and ``bias``).

    That gravity's error is a vector fixed in that frame (the platform's acceleration that the
    gravity reference averaged in), so its share of the forward acceleration is axis(t)·δ, which
    changes as the camera turns; the readout tracks δ (lobula.readout.kalman_velocity's offset_axis).
    orientation: :func:`orientation_from_gyro`'s rotations where already integrated (as for
    :func:`forward_acceleration`); else integrated here.
    """
    rot = orientation_from_gyro(time_s, gyro, causal, bias) if orientation is None else np.asarray(orientation, float)
    return rot[:, :, 2]


def transport_rate(times: np.ndarray, time_s: np.ndarray, gyro: np.ndarray, bias: np.ndarray | None,
                   heading: np.ndarray, window_s: float, causal: bool = False) -> np.ndarray:
    """λ = ω_x·e_y − ω_y·e_x (1/s, (n,)) at ``times``: how fast the velocity along the optical axis
    changes, per m/s of it, beyond the forward acceleration, in a camera that turns.

    In the camera's (turning) frame dv/dt = a − ω × v, and with the heading e = (v_x, v_y)/v_z the
    forward part of ω × v is λ·v_z. gyro (m, 3) rad/s in the camera frame at ``time_s`` (m,), bias
    (m, 3) rad/s removed where given (else the still-camera estimate, causal or not), averaged over ``window_s``
    about each time (:func:`resample_to`); heading (n, 2) normalised (the epipole), NaN read as 0.
    """
    w = gyro - (gyro_bias(time_s, gyro, causal) if bias is None else np.asarray(bias, float))
    wx, wy = (resample_to(times, time_s, w[:, j], window_s) for j in (0, 1))
    e = np.nan_to_num(np.asarray(heading, float))
    return wx * e[:, 1] - wy * e[:, 0]


def gravity_drift_std(time_s: np.ndarray, gyro: np.ndarray, causal: bool = True,
                      bias_std: np.ndarray | None = None, accel: np.ndarray | None = None,
                      prior: float = GYRO_BIAS_PRIOR) -> np.ndarray:
    """How fast (m/s²/s, (n,)) gravity may drift through the forward axis: |g|·σ_b.

    σ_b: that of :func:`gyro_bias` (its prior ``prior``, rad/s) — causal: from the still samples seen
    so far (online); else from the whole record's — or ``bias_std`` (n, 3) rad/s per camera axis where given
    (e.g. :func:`vision_gyro_bias`'s). A bias error δb turns gravity g at δb × g, whose
    forward (z) part is δb_x·g_y − δb_y·g_x: with ``accel`` (n, 3), the specific force whose
    mean (expanding, causal; whole record, offline) gives g's direction in the camera,
    the std is |g|·√(σ_x²ĝ_y² + σ_y²ĝ_x²); without it, |g|·max σ (any orientation).
    """
    if bias_std is None:
        return G * gyro_bias(time_s, gyro, causal, with_std=True, prior=prior)[1]
    b = np.asarray(bias_std, float)
    if accel is None:
        return G * b.max(axis=-1)
    g = gravity_direction(accel, causal)
    return G * np.sqrt(b[:, 0] ** 2 * g[:, 1] ** 2 + b[:, 1] ** 2 * g[:, 0] ** 2)


def gravity_direction(accel: np.ndarray, causal: bool = True) -> np.ndarray:
    """Unit vectors (n, 3) along the specific force's mean, accel (n, 3): expanding (causal) or the whole
    record's — the direction gravity takes in the camera, near enough for its leak through small angles."""
    f = np.asarray(accel, float)
    g = np.cumsum(f, 0) / np.arange(1, len(f) + 1)[:, None] if causal else np.broadcast_to(f.mean(0), f.shape)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)


def attitude_leak(time_s: np.ndarray, bias: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Gravity that an online attitude has let into the forward axis, by the newest gyro-bias
    estimate (m/s², (n,)).

    Online, the attitude at each sample s was integrated with the bias known then, b̂(s) (``bias``
    (n, 3) rad/s, camera frame, e.g. :func:`fused_gyro_bias`'s causal track). By the estimate
    at t that attitude is off by ε(t) = ∫_{t0}^{t} (b̂(t) − b̂(s)) ds, which turns gravity into the
    forward (z) axis by |g|·(ε_x·ĝ_y − ε_y·ĝ_x) (ĝ: the specific force's expanding mean direction,
    ``accel`` (n, 3), as in :func:`gravity_drift_std`). It stays 0 while the estimate stays put and
    grows when the estimate moves — a bias outside the prior being learned. A 1°/s pitch bias
    learned over ~3 s leaves ~0.4 m/s² (rotation family, 160×120); the suite's 0.25°/s, ≤ 0.15.
    """
    t = np.asarray(time_s, float)
    b = np.asarray(bias, float)
    g = gravity_direction(accel, causal=True)
    turned = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (b[1:] + b[:-1]) * np.diff(t)[:, None], 0)])
    eps = b * (t - t[0])[:, None] - turned
    return G * (eps[:, 0] * g[:, 1] - eps[:, 1] * g[:, 0])


LEAK_WINDOW_S = 1.0  # s: how far back leak_walk looks at the attitude leak's change


def leak_walk(times: np.ndarray, time_s: np.ndarray, leak: np.ndarray, window_s: float = LEAK_WINDOW_S) -> np.ndarray:
    """Random-walk density (m/s²/√s, like ``times``) that lets the readout's accelerometer offset move
    as fast as the attitude leak (:func:`attitude_leak`, at ``time_s``) moved over the last
    ``window_s``: |L(t) − L(t − window_s)|/√window_s (so over that window the offset's variance grows
    by the leak's change squared).

    The leak is not subtracted from the acceleration: the flow-fitted bias also wanders on its own,
    and re-integrating the attitude with its newest value turns that wander into offset steps the
    filter takes for motion (development seeds 100–102, causal RMSE 0.0145 m/s subtracted against
    0.0138 not; rotation seed 102 0.037 against 0.013). As uncertainty it costs nothing where the
    estimate stays put and, where it moves, says the offset is less well known (1°/s gyro bias:
    0.025 m/s RMSE with ±2σ 100 %, against 0.25 with 54 % without it).
    """
    now = np.interp(times, time_s, leak)
    before = np.interp(np.asarray(times, float) - window_s, time_s, leak)
    return np.abs(now - before) / np.sqrt(window_s)


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
    """The gyro bias (rad/s, (n, 3)) and its std at the IMU samples ``time_s`` (n,): the still-camera
    estimate (still_bias (n, 3), still_std (n,) or (n, 3); :func:`gyro_bias`) and the flow's
    (est_bias, est_std (m, 3), known at t_est (m,) s; :class:`lobula.epipole.HeadingBiasEstimator`,
    its std times ``est_std_scale``) combined by inverse variance.

    Causal: each sample takes the flow's newest estimate known by then (the still one alone before
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
    rad/s²/√Hz) started at ``prior_bias`` (3,) ± ``prior_std`` (the still-camera estimate
    and its std at the start), the row E_i· constant with prior std ``scale_std``. Its
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
    # Measurement variance per pair (m, 3).
    dz = np.abs(np.diff(z, axis=0)) if m > 1 else np.zeros((0, 3))
    r = np.full((m, 3), RESIDUAL_RATE_PRIOR_STD ** 2)
    if causal:
        for k in range(MIN_RESIDUALS, m):  # m ~ 5 per second: a short loop over pairs, not pixels
            r[k] = (1.4826 * np.median(dz[:k], axis=0) / np.sqrt(2)) ** 2
    elif m > MIN_RESIDUALS:
        r[:] = (1.4826 * np.median(dz, axis=0) / np.sqrt(2)) ** 2
    r = np.maximum(r, 1e-12)
    # State per axis (3 axes batched): [b, E_i0, E_i1, E_i2]; measurement h = [1, ω].
    q_rate = walk ** 2
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
    if causal:
        j = np.searchsorted(t_meas, time_s, side="right") - 1
        before = j < 0
        jj = np.maximum(j, 0)
        gap = np.where(before, time_s - time_s[0], time_s - t_meas[jj])
        bias = np.where(before[:, None], b0, xf[jj, :, 0])
        var = np.where(before[:, None], p0, Pf[jj, :, 0, 0]) + q_rate * np.maximum(gap, 0.0)[:, None]
        return bias, np.sqrt(var)
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


def turn_rate(times: np.ndarray, sample_t: np.ndarray, gyro: np.ndarray, window_s: float) -> np.ndarray:
    """The body's turn rate |ω| (rad/s, (n,)) at ``times``: the gyro's (haltere's) rate magnitude,
    gyro (m, 3) rad/s sampled at ``sample_t`` (m,) s, averaged over ``window_s`` about each time
    (:func:`resample_to`). The readout widens its acceleration noise by it
    (``ReadoutConfig.accel_turn_noise``): gravity leaks into the accelerometer through attitude
    error while turning."""
    return resample_to(times, sample_t, np.linalg.norm(gyro, axis=1), window_s)


def resample_to(times: np.ndarray, sample_t: np.ndarray, values: np.ndarray, window_s: float) -> np.ndarray:
    """Mean of ``values`` over [t − window/2, t + window/2] for each t in ``times``.

    Uses the integral of the linearly interpolated signal, so it works for any
    sample rate relative to the window and never reads outside the recording
    (times beyond it get the edge value).
    """
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (values[1:] + values[:-1]) * np.diff(sample_t))])
    lo = np.clip(times - window_s / 2, sample_t[0], sample_t[-1])
    hi = np.clip(times + window_s / 2, sample_t[0], sample_t[-1])
    integral = np.interp(hi, sample_t, cum) - np.interp(lo, sample_t, cum)
    width = hi - lo
    return np.where(width > 0, integral / np.where(width > 0, width, 1), np.interp(times, sample_t, values))


class GyroAttitude:
    """The camera's orientation from the gyro, integrated causally with a bias that may change.

    A camera that keeps turning gives :func:`gyro_bias` no still samples, so the gyro's bias
    (a BMI055's: ±0.25 °/s, wandering) stays in every pair's derotation; vision can learn it
    (:class:`lobula.epipole.HeadingBiasEstimator`) and set ``bias`` (3,) rad/s here as it goes.
    ``__call__(t)`` integrates the gyro (:func:`rotation_increments`) with the bias current
    when a sample is first needed, up to the latest time asked, and never revises what it has
    integrated (causal: nothing after t is used). Orientations are camera → the first sample's
    frame, slerped between samples; times before the latest asked are served from what is
    integrated. :meth:`applied_bias` says which bias a stretch was integrated with.
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
        """Append gyro samples (k,) s after the last one and (k, 3) rad/s (frame-by-frame use)."""
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
        """(c (3,), w (3,)) rad/s: the mean correction removed from the gyro over [t0, t1] (bias plus
        E·rate) and its mean reading there. Call for t1 first, so the stretch is integrated."""
        lo, hi = np.searchsorted(self.t, [t0, t1], side="left")
        lo, hi = min(lo, self._done), min(max(hi, lo + 1), self._done + 1)
        if hi <= lo:
            return self.bias.copy(), self.w[max(lo, 0)].copy()
        return self._corr[lo:hi].mean(0), self.w[lo:hi].mean(0)
