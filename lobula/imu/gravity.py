"""The accelerometer: gravity removed in the gyro-stabilised frame (offline a long centred mean, online a
reference set at the start), the forward acceleration along the optical axis, and the bounds on what the
gyro bias's error lets gravity leak into it. Specific force m/s², times s."""
from __future__ import annotations

import numpy as np

from .gyro import GYRO_BIAS_PRIOR, gyro_bias, orientation_from_gyro
from .resample import resample_to

ACCEL_CORRELATION_S = 1.0  # s: a track's accelerations stay correlated over about a second
G = 9.80665  # m/s², standard gravity


GRAVITY_WINDOW_S = 60.0  # longer than a track's excursions (seconds), so its acceleration averages out
GRAVITY_INIT_S = 0.25  # s: online, the first gravity reference is the mean specific force over this long


def gravity_time_constant(time_s: np.ndarray, t0: float, tau_s: float = GRAVITY_WINDOW_S,
                          init_s: float = GRAVITY_INIT_S) -> np.ndarray:
    """Time constant (s, like time_s) of the online gravity estimate (:func:`online_gravity`) at each time.

    time_s (n,) s; t0: the record's start, s; tau_s, init_s: s.
    Over the first ``init_s`` after ``t0`` it is a growing mean (τ = elapsed time), then an
    exponential average of time constant ``tau_s``. Its error b (the offset it leaves in
    the forward acceleration) then obeys ḃ = −a_m/τ with a_m the forward acceleration it
    gives (lobula.readout.kalman_velocity takes this as a known input).
    """
    el = np.asarray(time_s, float) - t0
    return np.where(el < init_s, np.maximum(el, 1e-3), tau_s)


def online_gravity(time_s: np.ndarray, f: np.ndarray, tau_s: float = GRAVITY_WINDOW_S,
                   init_s: float = GRAVITY_INIT_S) -> np.ndarray:
    """Causal estimate of −gravity as specific force (n, 3) m/s² from the stabilised specific force f (n, 3) m/s².

    time_s (n,) s: the samples' times; tau_s, init_s: s.
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

    time_s (n,) s: the samples' times; window_s: the window's length, s; correlation_s: s.
    Zero-phase: the window is centred on each sample (clipped to the record); causal: it
    ends at the sample. The slope has a zero-mean Gaussian prior of std ``slope_std``
    (per sample, (n,) or scalar; units of values per second) against the residual
    variance in the window, whose samples count as independent once per
    ``correlation_s``: a slope the data cannot tell from their own wander stays near 0.
    Vectorised with cumulative sums; returns (n, k) in the units of values.
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
    """Gravity-free acceleration along the optical axis (m/s², (n,)): :func:`gravity_free_acceleration`'s third
    component (the arguments are its own)."""
    return gravity_free_acceleration(time_s, accel, gyro, causal, window_s, bias, orientation)[:, 2]


def gravity_free_acceleration(time_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray | None = None,
                              causal: bool = False, window_s: float = GRAVITY_WINDOW_S,
                              bias: np.ndarray | None = None, orientation: np.ndarray | None = None) -> np.ndarray:
    """Gravity-free acceleration in the camera frame (m/s², (n, 3)) from specific force ``accel`` (n, 3) m/s²
    sampled at ``time_s`` (n,) s.

    window_s: s. Raises ValueError for non-finite input. With ``gyro`` (n, 3) rad/s the gravity
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
    return accel + g_cam


def forward_axis(time_s: np.ndarray, gyro: np.ndarray, causal: bool = False,
                 bias: np.ndarray | None = None, orientation: np.ndarray | None = None) -> np.ndarray:
    """The optical axis (n, 3), unit vectors in the first sample's frame: the frame in which
    :func:`forward_acceleration` takes gravity (same ``gyro``, ``causal`` and ``bias``).

    That gravity's error is a vector fixed in that frame (the platform's acceleration that the
    gravity reference averaged in), so its share of the forward acceleration is axis(t)·δ, which
    changes as the camera turns; the readout tracks δ (lobula.readout.kalman_velocity's offset_axis).
    orientation: :func:`orientation_from_gyro`'s rotations where already integrated (as for
    :func:`forward_acceleration`); else integrated here. time_s (n,) s, gyro (n, 3) rad/s, bias
    (n, 3) rad/s.
    """
    rot = orientation_from_gyro(time_s, gyro, causal, bias) if orientation is None else np.asarray(orientation, float)
    return rot[:, :, 2]


def transport_rate(times: np.ndarray, time_s: np.ndarray, gyro: np.ndarray, bias: np.ndarray | None,
                   heading: np.ndarray, window_s: float, causal: bool = False) -> np.ndarray:
    """λ = ω_x·e_y − ω_y·e_x (1/s, (n,)) at ``times`` (n,) s: how fast the velocity along the optical axis
    changes, per m/s of it, beyond the forward acceleration, in a camera that turns.

    In the camera's (turning) frame dv/dt = a − ω × v, and with the heading e = (v_x, v_y)/v_z the
    forward part of ω × v is λ·v_z. gyro (m, 3) rad/s in the camera frame at ``time_s`` (m,), bias
    (m, 3) rad/s removed where given (else the still-camera estimate, causal or not), averaged over ``window_s`` (s)
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

    time_s (n,) s and gyro (n, 3) rad/s: the gyro's samples.
    σ_b: that of :func:`gyro_bias` (its prior ``prior``, rad/s) — causal: from the still samples seen
    so far (online); else from the whole record's — or ``bias_std`` (n, 3) rad/s per camera axis where given
    (e.g. :func:`vision_gyro_bias`'s). A bias error δb turns gravity g at δb × g, whose
    forward (z) part is δb_x·g_y − δb_y·g_x: with ``accel`` (n, 3) m/s², the specific force whose
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
    """Unit vectors (n, 3) along the specific force's mean, accel (n, 3) m/s²: expanding (causal) or the whole
    record's — the direction gravity takes in the camera, near enough for its leak through small angles."""
    f = np.asarray(accel, float)
    g = np.cumsum(f, 0) / np.arange(1, len(f) + 1)[:, None] if causal else np.broadcast_to(f.mean(0), f.shape)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)


def attitude_leak(time_s: np.ndarray, bias: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Gravity that an online attitude has let into the forward axis, by the newest gyro-bias
    estimate (m/s², (n,)).

    Online, the attitude at each sample s is integrated with the bias known then, b̂(s) (``bias``
    (n, 3) rad/s, camera frame, e.g. :func:`fused_gyro_bias`'s causal track, at ``time_s`` (n,) s). By the estimate
    at t that attitude is off by ε(t) = ∫_{t0}^{t} (b̂(t) − b̂(s)) ds, which turns gravity into the
    forward (z) axis by |g|·(ε_x·ĝ_y − ε_y·ĝ_x) (ĝ: the specific force's expanding mean direction,
    ``accel`` (n, 3) m/s², as in :func:`gravity_drift_std`). It stays 0 while the estimate stays put and
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
    """Random-walk density (m/s²/√s, like ``times``, s) that lets the readout's accelerometer offset move
    as fast as the attitude leak (``leak`` (m,) m/s², :func:`attitude_leak`, at ``time_s`` (m,) s) moves
    over the last ``window_s`` (s): |L(t) − L(t − window_s)|/√window_s (so over that window the offset's variance grows
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
