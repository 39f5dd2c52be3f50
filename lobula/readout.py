"""The readout: absolute forward velocity from pooled r̄_f, r²̄_f, their derivative and acceleration.

Geometry (DESIGN.md): ṙ = a/d + r², so for each receptive field
``v_f = a·r̄_f / (ṙ̄_f − r²̄_f)`` and ``d_f = a / (ṙ̄_f − r²̄_f)``.

Two readouts share this arithmetic:

* ``"median"`` — the paper's text, step by step: first-order Butterworth
  (wn = 0.04·Nyquist) on r̄_f, a 5-frame staggered difference for ṙ̄_f, v_f per field,
  the median across fields, a final Butterworth. Its error concentrates where a
  changes sign or stays near zero, because v_f is then a ratio of two small numbers.
* ``"kalman"`` — the project's default. r̄, r²̄ and a pass through the *same*
  low-pass so the three terms stay in phase (offline a zero-phase Butterworth; online a
  linear-phase Gaussian FIR, so every term is delayed by the same, known latency); vision
  measures a/v without the accelerometer, κ = median over fields of (ṙ̄ − r²̄)/r̄, with a
  standard error from the fields' spread plus an error all fields share
  (``kappa_rel_error``); and a Kalman filter on (v, accelerometer offset b, offset ramp
  ḃ) integrates the acceleration and fuses a_m = κ·lp(v) + b (the remedy the paper's
  discussion proposes; an offset in a cannot scale v; κ is a ratio of low-passed terms, so it
  multiplies the low-passed velocity, which online the state and ∫a give exactly). The ramp is
  gravity leaking through an attitude integrated with an uncertain gyro bias. When nothing moves in the image,
  ``v = r·d`` with ``d`` bounded says the camera is still, and where the fields' expansion
  changes sign v passed through 0 (``reversal``: no depth, no κ). The zero-phase variant is a
  Rauch–Tung–Striebel smoother; the causal one is the forward filter, whose measurements
  speak of v and b one latency ago, bridged by integrating acceleration; online, vision's
  error that all fields share and that persists for seconds is a Schmidt–Kalman consider
  state (accounted for, never estimated), so the forward filter cannot average it into a
  confident, wrong offset; offline the smoother estimates it. The acceleration's own noise
  grows while the camera turns (``accel_turn_noise``), and offline every error of a low-passed
  term counts once per correlation time of the low-pass, not once per frame.
  v̂ is NaN (``observable`` False) wherever the posterior standard deviation exceeds
  ``max_std_m_s``: the readout says when it does not know.
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import signal
from scipy.special import log_ndtr


@dataclass
class ReadoutConfig:
    """Readout parameters (SI units).

    Parameters
    ----------
    method : {"kalman", "median"}
        "kalman" (the project's default) or "median" (the paper's text).
    filter : {"zero-phase", "causal"}
        "zero-phase" (offline, the paper's) or "causal" (online).
    paper_wn : float
        The paper's Butterworth cutoff, as a fraction of Nyquist.
    paper_order : int
        The paper's Butterworth order.
    stagger : int
        Frames between the two samples of the staggered difference for ṙ̄.
    cutoff_hz : float
        Hz: cutoff of the kalman readout's common low-pass of r̄, r²̄ and a.
    online_window_sigma : float
        Online, that low-pass is a symmetric Gaussian FIR (gain ½ at ``cutoff_hz``) cut at this
        many of its σ either side, so every term reaches the filter this many σ late (plus half
        the stagger): the measurement latency the forward filter bridges with ∫a and its
        uncertain offset. 1.5 (0.30 s at 30 frames/s) lies in a broad optimum on the suite's
        development scenes (causal RMSE 0.0104 m/s; 1.0 / 2.5 read 0.0109 / 0.0119): the
        bridge's error grows with the latency, the cut kernel's leakage of noise as it shortens.
        Unused offline.
    order : int
        Order of the offline (zero-phase Butterworth) common low-pass.
    accel_min_m_s2 : float
        m/s²: |a| below this carries no depth information (the noise floor of a filtered
        accelerometer).
    depth_min_m, depth_max_m : float
        m: the physical range of depths a field may imply.
    min_valid_fraction : float
        Fraction of the fields that must agree on a physical depth.
    rest_depth_max_m : float
        m: the farthest depth assumed in view when judging that no flow means no motion.
    rest_accel_change_m_s2 : float
        m/s²: that judgement is made only where the accelerometer's forward reading (smoothed over
        5 frames) stays within this of a line (an offset and its ramp) over the last second
        (offline: the second around the frame; :func:`accelerometer_steady`) and, online, where
        that reading less the learned offset lies within this (plus 2σ of the offset) of zero
        (:func:`kalman_velocity`'s ``rest_accel``): a camera that starts, stops or keeps
        accelerating is not at rest, whatever the image shows. 0.05 is ~8× the smoothed reading's
        white noise at the synthetic IMU's 150 µg/√Hz and under the 0.1 m/s² a gentle start
        reaches in a fraction of a second; not fitted (0.03 and 0.1 read the same).
    accel_noise : float
        m/s²/√Hz: white acceleration noise driving v. 0.01 is measured, not fitted: on the suite's
        development scenes the accelerometer-derived a less the truth's derivative, its offset and
        ramp removed, averages over 1 s to 0.001–0.009 m/s² on the families that do not turn;
        0.05 makes the posterior 2–3× wider than the errors and the estimate worse.
    accel_turn_noise : float
        m/s²/√Hz per rad/s of |ω|: more acceleration noise while the camera turns. 0.1: on the
        rotation family's development scenes that 1 s average is 0.08–0.12 × the rms |ω|. Used
        where :func:`readout` is given ``turn_rate``.
    bias_walk : float
        m/s²/√s: random walk of the accelerometer offset.
    bias_prior_m_s2 : float
        m/s²: prior std of the accelerometer offset.
    v_prior_m_s : float
        m/s: prior std of v.
    meas_floor_m_s : float
        m/s: the smallest standard deviation granted to one frame's measurement.
    kappa_rel_error : float
        Error of vision's κ = a/v that all fields share (flow error, residual rotation), as a
        fraction of |κ|, added in quadrature to the fields' standard error. 0.25 is fitted on one
        world only — the suite's "moving" family, development seed 100, where it brings the online
        filter's ±2σ coverage to ~95 % (0.1: 71 %) — and tested on the other families and seeds.
        The finer flow grid (:attr:`lobula.flow.FlowConfig.dis_grid_px`) would allow 0.125 there,
        but 0.125 fails three known-answer tests (the band widening while turning, a shared error
        covered offline, fields drowned in noise).
    adapt_s : float
        s: time constant of the offline filter's covariance matching, which scales the κ
        measurement's noise up by the running mean of its normalised squared innovations where
        they show it worse than claimed (0: off, the default). 2 s helps offline on the panels,
        fast and corridor families, but widens the corridor's band past 99.5 % coverage on the
        6 s scene of tests/test_families.py and doubles the ground family's seed-1 error.
    accel_scale_error : float
        Fraction (1σ): the accelerometer's scale-factor error. Vision measures only κ = a/v, so
        v̂ = a/κ takes the accelerometer's scale whole and nothing the camera sees corrects it; it
        adds ``accel_scale_error``·|v̂| to the posterior std. 0.01 is the sensitivity tolerance of a
        consumer MEMS accelerometer such as the D435i's BMI055, and what the realistic synthetic
        IMU draws per axis (stimuli.imu.IMUConfig.realistic); set it from a calibration where one
        exists.
    max_std_m_s : float
        m/s: posterior std above which v̂ is reported unobservable (NaN).
    shared_error_frac, shared_error_s : float
        Vision's a_m = κ·v + b also carries an error all fields share that persists for seconds
        (fast family: +0.07–0.11 m/s² for seconds on end), which per-frame white noise cannot
        describe. Online it is a Schmidt–Kalman "consider" state: a Gauss–Markov error of time
        constant ``shared_error_s`` (s) whose std is ``shared_error_frac`` × the running RMS (same
        time constant) of the κ measurement's innovations — accounted for in the gain and the
        covariance, never estimated, so the forward filter can neither average it into a
        confident, wrong offset b nor let it run away. The RMS also takes in the start's large
        innovations (v still unknown), which keeps the offset from locking in during the first
        seconds. Offline the same error is an estimated state of the smoother, which has the whole
        record. 0.5 balances the fast family (whose error falls as the fraction grows) against
        the dim one (whose error rises) on the development scenes; 0: off.
    r2_term : {"field", "mean_squared"}
        "field": the field's mean of r² (the geometry); "mean_squared": r̄² (the ablation).
    fusion : {"kalman", "vision-only"}
        "kalman": vision's measurements fused with integrated acceleration; "vision-only": the
        per-frame robust median of v_f through the same low-pass, no acceleration integrated.
    reversal : bool
        Use the moments the image's expansion changes sign (:func:`reversal_measurement`): every
        field's r̄ = v/d has the sign of v whatever its depth, so where the fields' median r̄ goes
        from clearly negative to clearly positive (or back), v passed through 0 in between — a
        measurement v(t*) = 0 that needs neither depth nor κ, exactly where κ = a/v is
        ill-conditioned and a reversing camera loses its lock. On by default: on the development
        scenes it lowers the causal RMSE on all twelve fast-family seeds (0.0169 m/s against
        0.0174) and leaves the other families' errors, ±2σ coverage and observable fraction as
        they are.
    sign : bool
        Use the sign of the image's expansion (:func:`expansion_sign`): where the fields' signed
        median r̄ has been clearly of one sign (beyond NO_EXPANSION_SE standard errors) for
        SIGN_PERSIST_S, v has that sign whatever the depths, and a reported posterior (std ≤
        ``max_std_m_s``) of the other sign is moved to it, widened first where it is sure
        (:func:`_sign_update`). It needs no κ, so it guards against a κ that errs for seconds (an
        EMD front end whose gains drift as texture flows) and carries v̂ through zero against what
        every field sees. Off by default: on the camera's DIS readout (22 development scenes,
        causal) it changes nothing on 21 and costs one (mixed 101: 0.0155 m/s against 0.0138),
        as DIS's κ does not drift so.
    stamp_error_s : float
        s (1σ): how far the fields' rates may be off the times they are stamped with, added to
        each reversal's timing (a front end whose latency is taken out only roughly, as the EMD's,
        moves the crossing it shows). One frame at 30 frames/s: with none the development scenes
        gain a little more, but rates stamped 2 frames late push the offline band below 90 %
        (tests/test_readout.py).
    lag_s : float
        s: with filter "causal", a fixed-lag smoother (0: the forward filter, the default). Every
        input stays online (causal low-passes, the online gravity reference); each frame's v̂ also
        takes the measurements up to ``lag_s`` after it, so it is known ``lag_s`` (plus the
        measurement latency) after the moment it describes — a declared delay, as in fixed-lag
        smoothing for odometry. The forward filter averages vision's errors over the past only,
        and its causal estimate stays ~2× the smoother's on the development scenes; 0.5–1 s of
        look-ahead recovers most of that.
    """

    method: str = "kalman"
    filter: str = "zero-phase"
    paper_wn: float = 0.04
    paper_order: int = 1
    stagger: int = 4
    cutoff_hz: float = 1.0
    online_window_sigma: float = 1.5
    order: int = 2
    accel_min_m_s2: float = 0.03
    depth_min_m: float = 0.1
    depth_max_m: float = 20.0
    min_valid_fraction: float = 0.25
    rest_depth_max_m: float = 5.0
    rest_accel_change_m_s2: float = 0.05
    accel_noise: float = 0.01
    accel_turn_noise: float = 0.1
    bias_walk: float = 0.002
    bias_prior_m_s2: float = 0.1
    v_prior_m_s: float = 1.0
    meas_floor_m_s: float = 0.02
    kappa_rel_error: float = 0.25
    adapt_s: float = 0.0
    accel_scale_error: float = 0.01
    max_std_m_s: float = 0.1
    shared_error_frac: float = 0.5
    shared_error_s: float = 3.0
    r2_term: str = "field"
    fusion: str = "kalman"
    reversal: bool = True
    sign: bool = False
    stamp_error_s: float = 0.033
    lag_s: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.lag_s) and self.lag_s >= 0):
            raise ValueError(f"lag_s must be a finite number of seconds >= 0, got {self.lag_s}")
        if self.lag_s > 0 and (self.filter != "causal" or self.method != "kalman" or self.fusion != "kalman"):
            raise ValueError(f"lag_s (a fixed-lag smoother, {self.lag_s:g} s) needs the kalman readout's causal "
                             f"filter with kalman fusion, got method {self.method!r}, filter {self.filter!r}, "
                             f"fusion {self.fusion!r}; the zero-phase filter already sees the whole record")
        if self.r2_term not in ("field", "mean_squared"):
            raise ValueError(f"unknown r2_term {self.r2_term!r}; use 'field' or 'mean_squared'")
        if self.fusion not in ("kalman", "vision-only"):
            raise ValueError(f"unknown fusion {self.fusion!r}; use 'kalman' or 'vision-only'")
        if self.method not in ("kalman", "median"):
            raise ValueError(f"unknown readout method {self.method!r}; use 'kalman' or 'median'")
        if self.filter not in ("zero-phase", "causal"):
            raise ValueError(f"unknown filter kind {self.filter!r}; use 'zero-phase' or 'causal'")
        if not (np.isfinite(self.online_window_sigma) and self.online_window_sigma > 0):
            raise ValueError(f"online_window_sigma must be a positive number of σ, got {self.online_window_sigma}")
        if not (np.isfinite(self.stamp_error_s) and self.stamp_error_s >= 0):
            raise ValueError(f"stamp_error_s must be a finite number of seconds >= 0, got {self.stamp_error_s}")
        if not 0.0 <= self.accel_scale_error < 1.0:
            raise ValueError(f"accel_scale_error is a fraction in [0, 1), got {self.accel_scale_error}")

    @classmethod
    def paper(cls, filter: str = "zero-phase") -> "ReadoutConfig":
        """The paper's readout as its text states it."""
        return cls(method="median", filter=filter, stagger=5)

    #: κ's shared error (kappa_rel_error, shared_error_frac) for EMD fields, in place of DIS flow's 0.25 / 0.5
    EMD_KAPPA_ERRORS = (0.5, 0.8)

    @classmethod
    def emd(cls, **kw) -> "ReadoutConfig":
        """The readout for EMD fields: κ's shared error as the compound eye's readout carries it
        (:data:`EMD_KAPPA_ERRORS`; experiments.eye_velocity.EyeVelocityConfig says why: each field's EMD
        gain drifts as texture flows through it, an error the fields share and that lasts). On the camera's
        EMD front end (development suite worlds, seeds 100 / 101, causal, fixating gaze), DIS's 0.25 / 0.5 →
        these: ±2σ rotation 53 / 100 → 89 / 100 %, dim 67 → 100 %, offaxis 79 → 97 %, mixed 58 → 70 %,
        panels 90 / 96 → 96 / 100 %; RMSE rotation 0.110 / 0.036 → 0.120 / 0.027 m/s, panels 0.045 / 0.032 →
        0.054 / 0.032, dim 0.044 → 0.036, moving 0.057 → 0.047, offaxis 0.074 → 0.067, the rest within
        0.004; observable under rotation 75 / 84 → 58 / 65 % (the wider band says so)."""
        k, s = cls.EMD_KAPPA_ERRORS
        return cls(**{"kappa_rel_error": k, "shared_error_frac": s, **kw})

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ReadoutResult:
    """Per-frame outputs, time-major: v_hat (n,) m/s (NaN where unobservable), observable (n,),
    v_std (n,), v_field (n, F), r_dot (n, F) 1/s², measurement (n,) and its std (n,), accel used (n,)."""

    v_hat: np.ndarray
    observable: np.ndarray
    v_std: np.ndarray
    v_field: np.ndarray
    r_dot: np.ndarray
    measurement: np.ndarray
    measurement_std: np.ndarray
    accel: np.ndarray
    info: dict = field(default_factory=dict)


def _integral(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """∫x dt from t[0] to each t (trapezoid rule), (n,)."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (x[1:] + x[:-1]) * np.diff(t))])


def hold_gaps(x: np.ndarray) -> np.ndarray:
    """x (n, ...) with each NaN replaced by the last finite value before it along axis 0 (a
    leading gap by the first finite value; an all-NaN column stays NaN): what a causal stage
    knows through a silent stretch, never a value from after it."""
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


def butterworth(x: np.ndarray, wn: float, order: int, zero_phase: bool) -> np.ndarray:
    """Butterworth low-pass along axis 0 (wn: fraction of Nyquist); NaNs bridged, then restored."""
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
                     causal: bool = False) -> tuple[np.ndarray, int]:
    """Linear-phase (symmetric Gaussian FIR) low-pass along axis 0, centred; NaNs bridged, then restored.

    The Gaussian's gain is ½ at ``cutoff_hz``, as for the zero-phase (forward–backward)
    Butterworth of order 2. Returns the centred smoothing (n, ...) and its half-width M
    (frames): the value at k needs data up to k + M, so lagged by M it is causal, and every
    frequency is delayed by the same M frames. (A causal IIR delays each frequency by a
    different amount, so ratios of filtered signals such as (ṙ̄ − r²̄)/r̄ are biased.)
    Edges are padded with the edge values. causal: NaN gaps hold their last value (see
    :func:`_fill_nan`), so the output lagged by M reads nothing after its own time.
    """
    sigma = np.sqrt(np.log(2.0) / 2.0) / (np.pi * cutoff_hz) / dt  # frames
    m = max(1, int(np.ceil(truncate * sigma)))
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


def staggered_difference(x: np.ndarray, stagger: int, dt: float, centred: bool) -> np.ndarray:
    """Derivative by a difference ``stagger`` frames wide, along axis 0.

    centred: (x[k + s/2] − x[k − s/2]) / (s·dt), which belongs to frame k (s even);
    otherwise the paper's (x[k] − x[k − s]) / (s·dt), which belongs to k − s/2.
    Frames without a partner are NaN.
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


def field_velocity(r, r2, r_dot, a):
    """Per-field velocity v_f = a·r̄/(ṙ̄ − r²̄) and implied depth d_f = a/(ṙ̄ − r²̄), (n, F) each."""
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = r_dot - r2
        depth = a[:, None] / denom
        return r * depth, depth


def paper_readout(t, r, r2, a, cfg: ReadoutConfig) -> ReadoutResult:
    """The paper's readout (see module docstring)."""
    zp = cfg.filter == "zero-phase"
    dt = float(np.median(np.diff(t)))
    rf = butterworth(r, cfg.paper_wn, cfg.paper_order, zp)
    r_dot = staggered_difference(rf, cfg.stagger, dt, centred=False)
    v_f, _ = field_velocity(r, r2, r_dot, a)
    v_f = np.where(np.isfinite(v_f), v_f, np.nan)
    with warnings.catch_warnings():  # all-NaN frames are expected: no field has a finite v_f
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(v_f, axis=1)
    v = butterworth(med, cfg.paper_wn, cfg.paper_order, zp) if np.isfinite(med).any() else med
    # The paper has no notion of observability; we add only the honest minimum:
    # without acceleration the ratio carries no speed information.
    a_s = butterworth(a, cfg.paper_wn, cfg.paper_order, zp)
    obs = np.isfinite(v) & (np.abs(a_s) >= cfg.accel_min_m_s2)
    return ReadoutResult(np.where(obs, v, np.nan), obs, np.full(len(t), np.nan), v_f, r_dot, med,
                         np.full(len(t), np.nan), a)


def median_and_error(values: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over fields of values (n_frames, F), NaN left out, and its standard error
    1.253·1.4826·MAD/√n (n (n_frames,) the fields counted; 1.253: the median's efficiency
    for Gaussian samples, 1.4826: MAD to σ)."""
    with warnings.catch_warnings():  # all-NaN frames are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(values, axis=1)
        mad = np.nanmedian(np.abs(values - med[:, None]), axis=1)
    return med, 1.253 * 1.4826 * mad / np.sqrt(np.maximum(n, 1))


def vision_measurement(r, r2, r_dot, a, cfg: ReadoutConfig):
    """One velocity measurement per frame from the fields, with its standard deviation.

    Fields are kept when their implied depth lies in [depth_min, depth_max] (d > 0 is
    geometry, not a tuning); a frame is informative when |a| ≥ accel_min and at least
    min_valid_fraction of fields are kept. The std is the median's standard error
    (1.253·1.4826·MAD/√n), floored. Returns z, std (n,) with NaN where uninformative,
    and v_f (n, F) (NaN for rejected fields).
    """
    v_f, depth = field_velocity(r, r2, r_dot, a)
    ok = np.isfinite(v_f) & (depth >= cfg.depth_min_m) & (depth <= cfg.depth_max_m)
    ok &= (np.abs(a) >= cfg.accel_min_m_s2)[:, None]
    v_f = np.where(ok, v_f, np.nan)
    n_ok = ok.sum(1)
    z, se = median_and_error(v_f, n_ok)
    std = np.maximum(se, cfg.meas_floor_m_s)
    enough = n_ok >= max(3, cfg.min_valid_fraction * r.shape[1])
    return np.where(enough, z, np.nan), np.where(enough, std, np.nan), v_f


def ratio_measurement(r, r2, r_dot, cfg: ReadoutConfig, keep=None):
    """Vision's a/v per frame, κ = median over fields of (ṙ̄ − r²̄)/r̄ (1/s), and its standard error.

    No accelerometer enters: ṙ − r² = a/d and r = v/d, so their ratio is a/v for every
    field whatever its depth. Fields whose |r̄| is under a fifth of the frame's median
    |r̄| (nothing expanding there to measure) are left out, and so are fields outside
    ``keep`` (n, F) bool (e.g. those whose implied depth is not physical); a frame needs at
    least min_valid_fraction of the fields. Returns κ, std (n,), NaN where uninformative.
    """
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        ra = np.abs(r)
        ok = np.isfinite(r) & np.isfinite(r2) & np.isfinite(r_dot) & (ra >= 0.2 * np.nanmedian(ra, axis=1)[:, None])
        if keep is not None:
            ok &= keep
        k = np.where(ok, (r_dot - r2) / r, np.nan)
    n_ok = ok.sum(1)
    kap, std = median_and_error(k, n_ok)
    enough = (n_ok >= max(3, cfg.min_valid_fraction * r.shape[1])) & np.isfinite(kap)
    return np.where(enough, kap, np.nan), np.where(enough, std, np.nan)


def signed_expansion(r: np.ndarray):
    """The fields' signed median expansion r̄ per frame, its standard error and the fields counted.

    r (n, F) 1/s with NaN where a field has none. Returns (n,) each: what the rest bound and the
    reversals judge "expansion detected" on (|r̄| > NO_EXPANSION_SE·SE)."""
    n = np.isfinite(r).sum(1)
    r_med, se = median_and_error(r, n)
    return r_med, se, n


#: the fields' signed median r̄ within this many standard errors of 0: no expansion detected (see rest_measurement)
NO_EXPANSION_SE = 3.0


def clear_expansion(r: np.ndarray, min_fields: int):
    """The fields' signed median r̄ (n,) and where it stands clear of zero (n,) bool: beyond
    NO_EXPANSION_SE standard errors, with at least max(3, ``min_fields``) fields (r (n, F) 1/s, NaN where a
    field has none) — "expansion detected", as the reversals and the expansion's sign judge it."""
    r_med, se, n = signed_expansion(r)
    return r_med, np.isfinite(r_med) & (n >= max(3, min_fields)) & (np.abs(r_med) > NO_EXPANSION_SE * se)


#: s: how long the fields' expansion must have held one clear sign before it counts as v's (expansion_sign)
SIGN_PERSIST_S = 0.5


def expansion_sign(t: np.ndarray, r: np.ndarray, min_fields: int, persist_s: float = SIGN_PERSIST_S) -> np.ndarray:
    """The sign of v (n,) that the fields' expansion shows: ±1 where their signed median r̄ (r (n, F) 1/s,
    NaN where a field has none) has lain beyond NO_EXPANSION_SE standard errors of 0, with that sign and at
    least ``min_fields`` fields, at every frame of the last ``persist_s`` seconds (t (n,) s; causal); NaN
    elsewhere. Every field's r̄ = v/d has the sign of v whatever its depth d > 0; the persistence keeps a
    moment's front-end fault (an expansion read with the wrong sign for 0.3 s, tests/test_readout.py) out."""
    r_med, clear = clear_expansion(r, min_fields)
    sgn = np.where(clear, np.sign(r_med), 0.0)
    t = np.asarray(t, float)
    start = np.searchsorted(t, t - persist_s, side="left")
    out = np.full(len(t), np.nan)
    for s in (-1.0, 1.0):
        # frames with this clear sign, counted: the window [start, k] must hold nothing else
        c = np.concatenate([[0], np.cumsum(sgn == s)])
        whole = (c[np.arange(1, len(t) + 1)] - c[start]) == (np.arange(len(t)) - start + 1)
        out[whole & (t - t[0] >= persist_s)] = s
    return out


def rest_measurement(r, cfg: ReadoutConfig):
    """v = r·d with 0 < d ≤ rest_depth_max: no detectable expansion bounds |v| (returns z = 0, std (n,)).

    Translation makes every field's r̄ = v/d_f of one sign (v's), while flow noise and residual
    rotation scatter the fields' r̄ about zero (rotation's divergence is odd across the image).
    So the fields' *signed* median r̄_m, known to within its standard error SE
    (1.253·1.4826·MAD/√n), tells: where |r̄_m| ≤ 3·SE no expansion is detected (3·SE, not 2·SE:
    r̄ also carries small non-translational biases — an epipole that wanders while nothing
    moves, a derotation with a biased gyro — which on the real still EuRoC sequence 2·SE calls
    motion on a third of the frames), and the speed
    is bounded by |v| ≤ d_max·(|r̄_m| + 2·SE) at 95%, that bound being the measurement's 2σ.
    (The median of |r̄| would count the noise as motion: a still camera's DIS flow noise alone
    is ~0.02 1/s per field, which at 5 m is 0.1 m/s.) Where expansion is detected the camera
    moves, and a bound resting on an assumed depth would only pull v̂ toward 0: not used.
    """
    r_med, se, n = signed_expansion(r)
    std = np.maximum(0.5 * cfg.rest_depth_max_m * (np.abs(r_med) + 2.0 * se), cfg.meas_floor_m_s)
    # It is a bound, not a noisy sample: repeating a loose bound frame after frame must
    # not add up to confidence, so it only counts where it alone would be decisive.
    use = (np.isfinite(r_med) & (n >= max(3, cfg.min_valid_fraction * r.shape[1]))
           & (np.abs(r_med) <= NO_EXPANSION_SE * se) & (std <= 0.5 * cfg.max_std_m_s))
    return np.where(use, 0.0, np.nan), np.where(use, std, np.nan)


#: s: the longest stretch without a clear expansion sign across which a reversal is read (see reversal_measurement)
REVERSAL_MAX_GAP_S = 1.0
#: a reversal or rest bound whose innovation exceeds this many of its standard deviations is taken for the front
#: end's fault, not a fact about v (kalman_velocity): an expansion read with the wrong sign for a moment gives two
#: false reversals and, low-passed offline, frames of "no expansion" (tests/test_readout.py)
OUTLIER_GATE = 4.0


def reversal_measurement(t, r, a, min_fields: int = 3, stamp_error_s: float = 0.0):
    """Where v passed through 0: the frames at which the fields' expansion is seen to change sign.

    t (n,) s; r (n, F) 1/s, the fields' expansion rates at fixed pixels (the newest, not low-passed);
    a (n,) m/s², the forward acceleration as read (offset and all); min_fields: the fields a frame
    needs for its median to count.

    Every field's r̄ = v/d has v's sign (d > 0), so where the fields' signed median r̄ stands clear
    of zero (|r̄| > 3·SE, as :func:`rest_measurement` judges "expansion detected") at frame i and
    again at a later frame j with the other sign, and nowhere clearly in between, v was 0 at some
    t* in [t_i, t_j] — whatever the depths (a far backdrop only makes r̄ small, never of the
    wrong sign). t* is interpolated linearly in r̄ between the two, and is uncertain by the gap's
    uniform spread (t_j − t_i)/√12 and by how far the rates' stamps may be off (``stamp_error_s``,
    1σ, in quadrature), which turns into a velocity error of |a|·that: the
    acceleration's own offset is still unknown here, so :func:`kalman_velocity` takes |a| as its
    posterior has it. Gaps longer than REVERSAL_MAX_GAP_S are skipped (v may have crossed more
    than once). Each reversal is known at frame j (online: once the new sign is clear).

    Returns (shift, time_std, delay, accel), each (n,), NaN except at those frames j: the
    integrated reading from t* to t_j (m/s: the measurement of v(t_j − delay) + ∫a, as the
    filter's rows take it), t*'s std (s), t_j − t* (s) and the mean reading over [t_i, t_j] (m/s²).
    """
    r_med, clear = clear_expansion(r, min_fields)
    idx = np.flatnonzero(clear)
    flip = np.flatnonzero(np.sign(r_med[idx[1:]]) != np.sign(r_med[idx[:-1]]))
    i, j = idx[flip], idx[flip + 1]
    keep = t[j] - t[i] <= REVERSAL_MAX_GAP_S
    i, j = i[keep], j[keep]
    t_star = t[i] + (t[j] - t[i]) * np.abs(r_med[i]) / (np.abs(r_med[i]) + np.abs(r_med[j]))
    cum = _integral(a, t)
    out = tuple(np.full(len(t), np.nan) for _ in range(4))
    out[0][j] = cum[j] - np.interp(t_star, t, cum)
    out[1][j] = np.hypot((t[j] - t[i]) / np.sqrt(12.0), stamp_error_s)
    out[2][j] = t[j] - t_star
    a_sum = np.concatenate([[0.0], np.cumsum(a)])
    out[3][j] = (a_sum[j + 1] - a_sum[i]) / (j - i + 1)  # the mean reading over frames i..j
    return out


def accelerometer_level(a: np.ndarray, dt: float, change_max: float, causal: bool = False):
    """The forward accelerometer reading averaged over 5 frames (trailing when causal, else
    centred) and how far it may stray while nothing happens, ((n,), (n,)) m/s²: ``change_max``,
    or 5× the reading's own vibration where that is more.

    A vibrating platform (a real drone's running rotors) shakes the reading far beyond the
    sensor's own noise: the bar is raised to 5× the rms of what the 5-frame average leaves out
    of white noise of the reading's own level (≈ 11σ of the average, ~2.7× the range white noise
    spans in a 1 s window), over the last 5 s online, the 5 s around the frame offline. (EuRoC
    V1_01's still start ends in a −0.1 → −0.29 m/s² step over 0.8 s — rotors spinning up or the
    take-off beginning; the copy has no ground truth to tell; at 3× that bar loses the rest bound
    and v̂ drifts to an RMS of 0.011 m/s.) That level is read from the second differences
    (E[(Δ²a)²] = 6σ² for white noise), which a smooth trajectory barely enters; what the average
    itself leaves out also holds the flight's own jerk, which on a corridor at 2 m/s would raise
    the bar to 0.5 m/s² and let a rest bound through while the camera accelerates at 0.3 m/s²
    (causal RMSE 0.047 m/s that way, 0.033 from the second differences; the real EuRoC start
    the same either way).

    Second differences see white noise at the frame rate, not a slow wobble: a hovering platform's
    3 Hz, 0.1 m/s² wobble leaves the bar at change_max, so the wobble reads as motion and the rest
    bound is not used through it. That is the cautious side. Counting such a wobble as vibration
    (what a half-second quadratic leaves) gives the rest bound back on 20 % of the replay of the
    real FLIVVER run, but with the EMD front end's weak expansion at coarse resolution a wrongly
    applied bound is confidently wrong (Δφ = 3°: 0.105 m/s against 0.045), while losing it costs
    little (τ = 5 ms at full contrast: 0.032 m/s against 0.026; DIS the same, 0.0052).
    """
    from scipy.ndimage import uniform_filter1d

    a = np.asarray(a, float)
    sm = uniform_filter1d(a, 5, mode="nearest", origin=2 if causal else 0)  # trailing when causal
    k = max(3, int(round(5.0 / dt)))
    d2 = np.diff(a, 2) if len(a) >= 3 else np.zeros(1)
    d2 = np.concatenate([d2[:1], d2[:1], d2] if causal else [d2[:1], d2, d2[-1:]])[:len(a)]
    # 0.8σ²: the variance white noise leaves after its 5-frame average is taken away.
    hf = 0.8 * uniform_filter1d(d2 ** 2 / 6.0, k, mode="nearest", origin=(k - 1) // 2 if causal else 0)
    return sm, np.maximum(change_max, 5.0 * np.sqrt(np.maximum(hf, 0.0)))


def accelerometer_steady(a: np.ndarray, dt: float, change_max: float, window_s: float = 1.0,
                         causal: bool = False) -> np.ndarray:
    """Where the forward acceleration a (n,) m/s² stayed within ``change_max`` (m/s², or 5× the
    reading's own vibration where that is more: :func:`accelerometer_level`) of a straight line
    over ``window_s`` (causal: the window ending at each frame; else centred), each reading first
    averaged over 5 frames, (n,) bool.

    A still camera's accelerometer reads its offset, gravity's residue — a constant, or a ramp while
    an uncorrected gyro bias turns gravity into the forward axis (a real still EuRoC sequence: 0.17
    m/s² per second). A reading that bends away from a line says the camera starts or stops
    accelerating: not at rest, whatever the image shows. The converse does not hold (constant
    velocity reads the same as rest): that the image must tell. No offset or ramp enters the test
    (the online filter also asks the reading less its learned offset: :func:`kalman_velocity`).
    """
    from numpy.lib.stride_tricks import sliding_window_view

    n = len(a)
    w = min(max(3, int(round(window_s / dt))), n)
    sm, change_max = accelerometer_level(a, dt, change_max, causal)
    # Window j covers frames j .. j + w − 1; causal frame k takes the window ending at k, offline the
    # one centred on it (both clipped at the record's ends).
    win = sliding_window_view(sm, w)                                       # (n − w + 1, w)
    x = np.arange(w) - 0.5 * (w - 1)
    slope = win @ x / (x @ x)
    res = win - win.mean(1, keepdims=True) - slope[:, None] * x
    bend = res.max(1) - res.min(1)                                         # (n − w + 1,)
    j = np.arange(n) - (w - 1 if causal else w // 2)
    return bend[np.clip(j, 0, len(bend) - 1)] <= change_max


def kalman_velocity(t, a, measurements, cfg: ReadoutConfig, smooth: bool, gravity_tau=None,
                    ratio=None, drift_std=None, delay: float = 0.0, full: bool = False,
                    corr_frames: float = 1.0, turn_rate=None, rest_accel=None, offset_walk=None,
                    offset_axis=None, offset_axis_prior=0.0, transport=None, lag: float = 0.0,
                    reversal=None, sign=None):
    """Kalman filter/RTS smoother for v driven by a, with an accelerometer offset b.

    t (n,) s; a (n,) m/s²; measurements: list of (z (n,), std (n,)) of v with NaN where
    absent, each of v one ``delay`` ago, or (z, std, own_delay) for a measurement with its own
    latency (s; 0: of v now); one the posterior is sure it cannot be (innovation > OUTLIER_GATE σ) is left
    out. Returns posterior mean and std of v, (n,) each.

    gravity_tau (n,) s: when a's gravity was estimated online by an average of time constant
    τ (lobula.haltere.online_gravity), that average also takes in the platform's own
    acceleration, so the offset moves as ḃ = −a/τ (a the acceleration given): a known
    input to the offset state, not noise. None: the offset only random-walks.

    ratio: (κ, σ_κ, a_m, shift), each (n,): vision's measurement of a/v (κ = (ṙ − r²)/r per
    field, which needs no accelerometer) against the accelerometer's a_m (low-passed like
    κ, belonging to t − delay, where the low-passed velocity κ multiplies was v(t) − shift,
    less the offset's share): a_m = κ·(v − shift) + b. Linear
    in the state, it ties b to the accelerometer where a ≈ 0 and v to both elsewhere, so
    an accelerometer offset cannot scale v the way it scales a·r/(ṙ − r²).

    delay (s): the measurements' latency (online). They speak of v(t − D) = v(t) − shift + b·D −
    ḃ·D²/2 (shift = ∫a over the last D, which holds the offset b) and of b(t − D) = b − ḃ·D,
    so their rows in the state carry those terms; the measurements' z already hold the shift.

    drift_std (n,) m/s²/s: how fast the offset may ramp — gravity seen through an attitude
    integrated with an uncertain gyro bias σ_b drifts at up to |g|·σ_b — as a fourth state
    ḃ whose std is held within drift_std at each frame (None: no ramp).

    offset_walk (n,) m/s²/√s: more random walk of the offset at each frame, beyond bias_walk —
    online, as fast as the attitude's gravity leak moved while the gyro-bias estimate moved
    (lobula.haltere.leak_walk): the offset learned up to then loses that much certainty (None: none).

    rest_accel: (a_s, tol), each (n,) m/s² (:func:`accelerometer_level`), when the
    ``measurements`` are rest bounds (v ≈ 0): the forward filter uses one only where the camera's
    reading less the offset it has learned could be a camera that does not accelerate,
    |a_s − b̂| ≤ tol + 2σ_b (kalman_readout gives it online only). A camera that accelerates passes through v = 0 for an instant, and a
    bound resting on an assumed depth is then wrong by however far the fields' depths exceed it
    (a ground plane with a far backdrop, the camera reversing at 1.4 m/s²: an unconditional bound
    reads v = 0 ± 0.02 at −0.14 m/s; causal RMSE 0.057 m/s with this condition against 0.074
    without, and on a corridor 0.015 against 0.047).
    Offline the bound is widened by the low-pass's smear σ_t·|a| instead (see kalman_readout).

    offset_axis (n, 3): the optical axis in the frame gravity was taken in (the first sample's,
    lobula.haltere.forward_axis), when the error of that gravity is a vector fixed there — the
    platform's acceleration that the gravity reference averaged in — rather than an offset of
    the accelerometer's own forward axis. Its forward part is then c(t)·δ, which changes as the
    camera turns (a camera panning 25° turns a 1 m/s² start offset's forward part by 0.4 m/s²,
    which a random walk of b cannot follow: ±2σ held 63 % of frames online). δ (3 more states,
    prior std ``offset_axis_prior`` m/s², one for all axes or (3,) per axis) sits beside b, which
    keeps the accelerometer's own offset (prior bias_prior_m_s2); the gravity reference's drift
    input (gravity_tau) moves δ along c. None: the whole offset is b.

    transport (n,) 1/s: λ = ω_x·e_y − ω_y·e_x, the gyro's rate ω (rad/s, camera frame) with the
    heading e = (v_x, v_y)/v_z (the epipole, normalised). v is the velocity along the optical axis, and
    in a turning frame dv/dt = a − ω × v, whose forward part is a − λ·v: a camera panning at 0.5 rad/s
    while it moves 25° off its axis sees its forward speed change at 0.23·v beyond what the
    accelerometer's forward axis says. None: 0 (a camera that does not turn, or moves along its axis).

    reversal: (shift, time_std, delay, accel), each (n,), NaN but where v is seen to have passed
    through 0 (:func:`reversal_measurement`): v(t − delay) = 0, measured with std time_std·(|accel − b̂|
    + 2σ_b) — the acceleration as the posterior has it, its offset b̂ (σ_b) included — floored at
    meas_floor_m_s, and left out where its innovation exceeds OUTLIER_GATE of its standard deviations: a
    posterior sure that v was far from 0 then takes the sign change for the front end's fault (None: none).

    sign (n,): ±1 where v is known to have that sign (:func:`expansion_sign` of the newest fields online,
    the zero-phase ones offline: no latency), NaN elsewhere: a posterior of v on the other side is moved
    to it (:func:`_sign_update`; None: none).

    lag (s, with smooth False): a fixed-lag smoother. Each frame's estimate also takes the
    measurements up to ``lag`` after it (:func:`fixed_lag_smooth`), so it is known ``lag`` later. The
    forward pass is then the smoother's (vision's shared error an estimated state, the floors
    counted once per correlation time), as if the record ended ``lag`` after each frame. 0: the
    forward filter.
    """
    n = len(t)
    fixed_lag = lag > 0 and not smooth
    smooth_pass = smooth or fixed_lag  # the smoother's forward pass (whole record or fixed lag)
    nd = 0 if offset_axis is None else 3
    N = 4 + nd
    sv, sb = cfg.v_prior_m_s ** 2, cfg.bias_prior_m_s2 ** 2
    sd0 = float(drift_std[0]) ** 2 if drift_std is not None else 0.0
    x = np.zeros(N)
    # States: v, the offset b, vision's shared error c (online a consider state, offline estimated), the
    # ramp ḃ, and with offset_axis the start frame's gravity error δ (3).
    P = np.diag([sv, sb, 0.0, sd0] + list(np.broadcast_to(np.asarray(offset_axis_prior, float) ** 2, (nd,))))
    shared = cfg.shared_error_frac > 0
    consider = shared and not smooth_pass
    tc = cfg.shared_error_s
    innov_ms, innov_w = 0.0, 0.0  # running mean square of the κ innovations (time constant tc)
    xs_pred, Ps_pred, xs, Ps, Fs = (np.zeros((n, N)), np.zeros((n, N, N)), np.zeros((n, N)),
                                    np.zeros((n, N, N)), np.zeros((n, N, N)))
    D = float(delay)
    c_at, c_mean = _axis_terms(t, offset_axis)
    lam = np.zeros(n) if transport is None else np.asarray(transport, float)
    cum_lam = _integral(lam, t)

    def v_row(k, d):
        """Row giving v(t_k − d) + ∫a over the last d from the state at t_k:
        v(t − d) = v − ∫(a − offset − λv), v taken constant over d in the λ term."""
        lam_d = cum_lam[k] - np.interp(t[k] - d, t, cum_lam)
        return np.concatenate([[1.0 + lam_d, d, 0.0, -0.5 * d * d], d * c_mean(k, d)])

    def offset_row(k):
        """Row giving the acceleration's whole offset at t_k."""
        return np.concatenate([[0.0, 1.0, 0.0, 0.0], c_at(k, 0.0)])

    def accel_reach(k, reading, n_sigma):
        """|reading − b̂| + n_sigma·σ_b: the acceleration a reading stands for, as the posterior (x, P, read
        when called) has the whole offset at t_k; n_sigma 2 its most, −2 its least."""
        o = offset_row(k)
        return abs(reading - o @ x) + n_sigma * np.sqrt(o @ P @ o)

    nis_sum, nis_w, r_scale = 0.0, 0.0, 1.0
    for k in range(n):  # a loop over time steps; the state has 4 or 7 dimensions
        if k > 0:
            dt = t[k] - t[k - 1]
            F = np.eye(N)
            F[0, 1], F[1, 3] = -dt, dt
            F[0, 0] = np.exp(-0.5 * (lam[k] + lam[k - 1]) * dt)
            c_mid = c_mean(k, dt)
            if nd:
                F[0, 4:] = -dt * c_mid
            q_c = 0.0
            if shared:
                phi = np.exp(-dt / tc)
                F[2, 2] = phi
                q_c = (cfg.shared_error_frac ** 2 * innov_ms / innov_w if innov_w > 0 else 0.0) * (1.0 - phi ** 2)
            u = 0.5 * (a[k] + a[k - 1]) * dt
            ub = -u / gravity_tau[k] if gravity_tau is not None else 0.0
            x = F @ x + (np.concatenate([[u, 0.0, 0.0, 0.0], ub * c_mid]) if nd else np.array([u, ub, 0.0, 0.0]))
            q_a = _accel_density2(cfg, None if turn_rate is None else 0.5 * (turn_rate[k] + turn_rate[k - 1]))
            q_b = cfg.bias_walk ** 2 + (offset_walk[k] ** 2 if offset_walk is not None else 0.0)
            P = F @ P @ F.T + np.diag([q_a * dt, q_b * dt, q_c, 0.0] + [0.0] * nd)
            if drift_std is not None and P[3, 3] > drift_std[k] ** 2:
                # The gyro bias got better known (still samples): the ramp is bounded anew.
                f = drift_std[k] / np.sqrt(P[3, 3])
                x[3] *= f
                P[3, :] *= f
                P[:, 3] *= f
            Fs[k] = F
        xs_pred[k], Ps_pred[k] = x, P
        H = v_row(k, D)  # v(t − D) + shift, in the state at t
        if reversal is not None and np.isfinite(reversal[0][k]):
            Hr = v_row(k, reversal[2][k])
            s_rev = max(reversal[1][k] * accel_reach(k, reversal[3][k], 2.0), cfg.meas_floor_m_s)
            # gated: a posterior sure that v was far from 0 takes the sign change for a front-end fault
            x, P = _gated_update(x, P, Hr, reversal[0][k] - Hr @ x, s_rev ** 2, consider)
        if sign is not None and np.isfinite(sign[k]):
            x, P = _sign_update(x, P, v_row(k, 0.0), sign[k], cfg.max_std_m_s)
        for m in measurements:
            z, sd = m[0], m[1]
            Hm = H if len(m) < 3 else v_row(k, m[2])
            if np.isfinite(z[k]) and np.isfinite(sd[k]):
                if rest_accel is not None and accel_reach(k, rest_accel[0][k], -2.0) > rest_accel[1][k]:
                    continue
                x, P = _gated_update(x, P, Hm, z[k] - Hm @ x, sd[k] ** 2, consider)
        if ratio is not None and all(np.isfinite(q[k]) for q in ratio):
            kap, skap, am, shift = (q[k] for q in ratio[:4])
            e_lp = ratio[4][k] if len(ratio) > 4 else 0.0  # the rates' timing error (m/s), see kalman_readout
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
            h = kv * H + np.concatenate([[0.0, 1.0, 1.0 if shared else 0.0, -D], c_at(k, D)])
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
            cf = corr_frames if smooth_pass else 1.0
            R = ((vd ** 2 + pd) * skap ** 2 + cf * ((kap * cfg.meas_floor_m_s) ** 2
                 + (cfg.meas_floor_m_s * skap) ** 2 + cfg.accel_min_m_s2 ** 2 + (kap * e_lp) ** 2))
            hph, nu = h @ P @ h, zk - h @ x
            if shared:
                w = np.exp(-(t[k] - t[k - 1]) / tc) if k > 0 else 0.0
                innov_ms, innov_w = w * innov_ms + nu ** 2, w * innov_w + 1.0
            x, P = _update(x, P, h, nu, r_scale * R, consider)
            if cfg.adapt_s > 0 and smooth_pass:
                # Covariance matching: were R honest, E[ν²] = hPh + R/corr_frames (R holds the
                # low-pass's correlation as a factor corr_frames). Innovations persistently larger
                # say vision's κ is worse than its fields' spread and the shared error claim (a
                # turning camera, near walls at speed): R is scaled up by their running mean
                # ratio (time constant adapt_s), never down. Offline only: the online filter's
                # innovations also carry its own latency bridging's model error, which this would
                # blame on vision (exact rates: causal RMSE 0.038 m/s with it, 0.030 without).
                w = np.exp(-(t[k] - t[k - 1]) / cfg.adapt_s) if k > 0 else 0.0
                nis_sum = w * nis_sum + nu ** 2 / (hph + R / corr_frames)
                nis_w = w * nis_w + 1.0
                r_scale = max(1.0, nis_sum / nis_w)
        xs[k], Ps[k] = x, P
    if smooth:
        for k in range(n - 2, -1, -1):
            C = Ps[k] @ Fs[k + 1].T @ np.linalg.pinv(Ps_pred[k + 1])
            xs[k] = xs[k] + C @ (xs[k + 1] - xs_pred[k + 1])
            Ps[k] = Ps[k] + C @ (Ps[k + 1] - Ps_pred[k + 1]) @ C.T
    elif fixed_lag:
        xs, Ps = fixed_lag_smooth(t, xs, Ps, xs_pred, Ps_pred, Fs, lag)
    if full:  # the whole posterior: means (n, N) and covariances (n, N, N) of (v, b, ·, ḃ[, δ])
        return xs, Ps
    return xs[:, 0], np.sqrt(np.maximum(Ps[:, 0, 0], 0.0))


def fixed_lag_smooth(t, xf, Pf, xp, Pp, F, lag: float):
    """Fixed-lag Rauch–Tung–Striebel smoothing: each frame's state given the measurements up to ``lag`` s after it.

    t (n,) s; xf, Pf (n, N), (n, N, N): the forward filter's posterior means and covariances;
    xp, Pp: its predictions (before each frame's measurements); F (n, N, N): the transition
    into each frame. Frame k's estimate is the RTS smoother's of the record cut at the last
    frame e_k ≤ t_k + lag (the end of the record where that comes first), exactly: the
    backward gains C_i = Pf_i F_{i+1}ᵀ Pp_{i+1}⁻¹ do not depend on where the record ends, so
    they are computed once and every frame's backward pass runs at once, one step of depth at a
    time (vectorised over frames; the loop runs over the lag's frames). Returns (xs, Ps).
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


def _axis_terms(t, axis):
    """For the start frame's gravity error δ (kalman_velocity's offset_axis (n, 3) or None): functions
    of (k, d) giving the axis c at t_k − d and its mean over [t_k − d, t_k] (3,) — c·δ is the forward
    offset then, and its integral over the latency what ∫a bridging that latency holds of it — or
    empty rows where there is no axis."""
    if axis is None:
        empty = np.zeros(0)
        return (lambda k, d: empty), (lambda k, d: empty)
    c = np.asarray(axis, float)
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (c[1:] + c[:-1]) * np.diff(t)[:, None], 0)])
    at = lambda tq, y: np.array([np.interp(tq, t, y[:, j]) for j in range(3)])  # held at the record's start

    def c_at(k, d):
        return c[k] if d == 0 else at(t[k] - d, c)

    def c_mean(k, d):
        if d <= 0:
            return c[k]
        t0 = max(t[k] - d, t[0])
        return (cum[k] - at(t0, cum)) / d + (d - (t[k] - t0)) / d * c[0]  # before the start: c held at c[0]

    return c_at, c_mean


def _accel_density2(cfg: ReadoutConfig, turn_rate: float | None) -> float:
    """Squared noise density ((m/s²)²/Hz) of the acceleration given: accel_noise, and while the
    camera turns at |ω| (rad/s) accel_turn_noise·|ω| more (gravity seen through an attitude that
    errs more the faster it turns)."""
    q = cfg.accel_noise ** 2
    if turn_rate is not None:
        q += (cfg.accel_turn_noise * turn_rate) ** 2
    return q


def _update(x, P, h, nu, r, consider: bool):
    """One scalar measurement update (row h, innovation ν, noise variance r) of state x, covariance P.

    consider: state 2 (vision's shared error) is a Schmidt–Kalman consider state: its gain is
    zeroed, and the covariance takes the Joseph form, exact for that suboptimal gain.
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


@dataclass
class MaterialRates:
    """Field rates taken along the image content (the material derivative), time-major (n, F).

    For each frame k: r̄, r²̄ (1/s, 1/s²) averaged over the *same scene points* at both ends
    of a difference and ṙ̄ = Dr/Dt (1/s²) over those points, all in the camera's orientation
    at frame k (lobula.receptive_field.MaterialFields); NaN where no difference exists.
    """

    r: np.ndarray
    r2: np.ndarray
    r_dot: np.ndarray


def _lag(x: np.ndarray, h: int) -> np.ndarray:
    """x delayed by h frames along axis 0 (NaN-filled): what an online stage has at each step."""
    return np.concatenate([np.full((h,) + x.shape[1:], np.nan), x[:-h]]) if h else x


def readout_lag(cfg: ReadoutConfig, dt: float) -> int:
    """Frames by which the kalman readout's terms are late (:func:`readout_terms`): 0 offline; online the
    centred low-pass's half-width plus half the stagger of ṙ̄'s difference (11 at 30 frames/s by default)."""
    if cfg.filter == "zero-phase":
        return 0
    stagger = max(2, cfg.stagger + cfg.stagger % 2)
    return gaussian_lowpass(np.zeros(3), cfg.cutoff_hz, dt, truncate=cfg.online_window_sigma)[1] + stagger // 2


def physical_kappa(terms, v_f, cfg: ReadoutConfig, offset_prior: float):
    """κ and its standard error (:func:`ratio_measurement`) from the readout's terms, a field left out where its
    implied depth is not physical (v_f NaN, :func:`vision_measurement`) — judged only where |a| is beyond what
    the accelerometer's offset (prior std ``offset_prior``, m/s²) could make of nothing: an offset (the online
    gravity reference's, up to the start's acceleration) would otherwise make every field look unphysical
    exactly when κ ≈ 0 is what pins it down. Elsewhere κ ≈ 0 ties the offset down."""
    judge = np.abs(terms[3]) >= cfg.accel_min_m_s2 + 2.0 * offset_prior
    return ratio_measurement(*terms[:3], cfg, keep=np.isfinite(v_f) | ~judge[:, None])


def readout_terms(t, r, r2, a, cfg: ReadoutConfig, material: MaterialRates | None = None):
    """The kalman readout's low-passed inputs: (r̄, r²̄, ṙ̄, a) and how late they are.

    t (n,) s, uniformly spaced; r, r2 (n, F) 1/s and 1/s²; a (n,) m/s²; material: the rates along the
    content (then r̄, r²̄ and ṙ̄ are its own). Offline (``cfg.filter`` "zero-phase") a zero-phase
    Butterworth, no latency; online the same centred (linear-phase) computation, known ``lag`` frames
    later, every term delayed alike so the ratios the readout takes stay unbiased. Returns (terms, lag,
    lp, rf): the four (n, F) or (n,) terms as of ``lag`` frames ago, lag (frames, including half the
    stagger of ṙ̄'s difference), the low-pass used (a callable on (n, ...) arrays) and the low-passed
    fixed-pixel r̄ as of now (not lagged).
    """
    dt = float(np.median(np.diff(t)))
    stagger = max(2, cfg.stagger + cfg.stagger % 2)
    lag = readout_lag(cfg, dt)
    if cfg.filter == "zero-phase":
        wn = cfg.cutoff_hz / (0.5 / dt)
        lp = lambda x: butterworth(x, wn, cfg.order, True)
    else:
        lp = lambda x: gaussian_lowpass(x, cfg.cutoff_hz, dt, truncate=cfg.online_window_sigma, causal=True)[0]
    rf = lp(r)
    if material is None:
        r2f = lp(r2) if cfg.r2_term == "field" else rf ** 2
        terms = (rf, r2f, staggered_difference(rf, stagger, dt, centred=True), lp(a))
    else:
        m = material
        rm = lp(m.r)
        r2m = rm ** 2 if cfg.r2_term == "mean_squared" else lp(m.r2)
        terms = (rm, r2m, lp(m.r_dot), lp(a))
    return tuple(_lag(x, lag) for x in terms), lag, lp, rf


def kalman_readout(t, r, r2, a, cfg: ReadoutConfig, material: MaterialRates | None = None,
                   gravity_tau=None, drift_std=None, turn_rate=None, offset_walk=None,
                   offset_axis=None, offset_axis_prior=0.0, transport=None) -> ReadoutResult:
    """The project's readout (see module docstring).

    Without ``material`` ṙ̄ is the staggered difference of the pooled rates at fixed pixels
    (exact only where r is uniform, a fronto-parallel surface); with it, the material
    derivative along the content and r̄, r²̄ over the same points.
    """
    zp = cfg.filter == "zero-phase"
    dt = float(np.median(np.diff(t)))
    terms, lag, lp, rf = readout_terms(t, r, r2, a, cfg, material)
    r_dot = terms[2]
    z, s, v_f = vision_measurement(*terms, cfg)
    delay = lag * dt
    # Low-passed measurements are correlated over about 1/(2·cutoff) s; treating each
    # frame as independent would make the posterior overconfident by √(that many frames).
    s = s * np.sqrt(max(1.0, 1.0 / (2 * cfg.cutoff_hz * dt)))
    if cfg.fusion == "vision-only":
        obs = np.isfinite(z) & (s <= cfg.max_std_m_s)
        return ReadoutResult(np.where(obs, z, np.nan), obs, np.where(obs, s, np.nan), v_f, r_dot, z, s, a,
                             info=dict(measurement_delay_s=delay))
    cum = _integral(a, t)
    # What the measurements speak of. κ = lp(a/d)/lp(v/d) is a ratio of low-passed signals, so
    # κ·lp(v) = lp(a) (exactly, for a depth constant over the filter's span): the velocity it
    # multiplies is the low-passed lp(v) at t − delay, not v itself. The accelerometer's integral
    # gives it from the state: v(s) = v(t) − (cum(t) − cum(s)) + ∫_s^t b, and the low-pass is
    # symmetric about t − delay, so lp(v)(t − delay) = v(t) − shift + b·delay with
    # shift = cum(t) − lp(cum)(t − delay). Pairing κ with v(t − delay) instead errs by
    # κ·(lp(v) − v) ≈ κ·σ_t²·v̈/2, a bias wherever v bends (exact tracked-point rates: causal RMSE
    # 0.014 m/s against 0.007). Offline (delay 0, the zero-phase low-pass) the same pairing is as
    # exact, shift = cum − lp(cum); pairing κ with v(t) and carrying the mismatch as noise instead
    # reads the suite's 20 development scenes (seeds 100-101) at 0.0052 m/s zero-phase RMSE, 0.0045
    # with this pairing (the worst 0.0094 against 0.0092; exact rates 0.0036 against 0.0002).
    shift = cum - _lag(lp(cum), lag)
    # Bridge the measurement's latency with ∫a (the haltere's fast path).
    z = z + shift
    # Whether the image expands needs no derivative and no band-limiting: online it is judged
    # on the newest fields' r̄ (no latency to bridge with an offset-laden ∫a), offline on the
    # low-passed r̄ like everything else.
    zr, sr = rest_measurement(rf if zp else r, cfg)
    # A far backdrop or the sky can fill most fields and show no expansion while the camera
    # moves (suite ground family, seed 0: with a 160-px DIS grid the bound alone holds v at 0
    # ± 0.02 m/s while it reaches −0.2 and pins a wrong offset for the whole record, 0.40 m/s
    # RMSE); the accelerometer says when the camera is at least not starting or stopping.
    zr = np.where(accelerometer_steady(a, dt, cfg.rest_accel_change_m_s2, causal=not zp), zr, np.nan)
    sigma_t = np.sqrt(np.log(2.0) / 2.0) / (np.pi * cfg.cutoff_hz)  # the low-pass's Gaussian width (s)
    # The prior std of the acceleration's whole forward offset: the accelerometer's own, and the
    # start frame's gravity error where the filter tracks it apart (offset_axis).
    offset_prior = float(np.hypot(cfg.bias_prior_m_s2, np.max(offset_axis_prior) if offset_axis is not None else 0.0))
    if zp:
        # Offline r̄ is low-passed over ~σ_t either side, in which v moves by ~σ_t·|a|: where the
        # image's expansion crosses zero while the camera accelerates (v through 0, or far
        # surfaces filling the fields), the bound holds only that well (development scene ground
        # 102, a backdrop 50-200 m away: 0.004 m/s widened, 0.039 not). Online r̄ is the newest frame's.
        # |a| less what the accelerometer's offset (2 prior std) could make of a still camera
        # (a real still EuRoC sequence's offset otherwise lifts the bound off: 0.043 m/s of "motion").
        sr = np.hypot(sr, sigma_t * np.maximum(np.abs(terms[3]) - 2.0 * offset_prior, 0.0))
        zr = np.where(sr <= 0.5 * cfg.max_std_m_s, zr, np.nan)
    kap, skap = physical_kappa(terms, v_f, cfg, offset_prior)
    n_corr = max(1.0, 1.0 / (2 * cfg.cutoff_hz * dt))
    skap = skap * np.sqrt(n_corr)
    # What the fields' spread cannot show: an error all fields share (the flow's, a residual
    # rotation's), taken as a fraction of κ itself.
    skap = np.hypot(skap, cfg.kappa_rel_error * np.abs(kap))
    # The pairing above is exact for rates stamped at the right time. A front end whose rates are a
    # frame or two off (the EMD's latency is taken out only as its low-frequency group delay) pairs κ
    # with the wrong moment, an error in a_m that grows where the acceleration changes: offline it is
    # carried as noise κ·σ_t²·|ȧ|/2, sized like the readout's own low-pass (σ_t). Exact rates 2 frames
    # late: ±2σ 97 % with it, 72 % without (3 frames early: 100 / 46 %); the EMD front end on a
    # development scene (moving, seed 100) 0.035 m/s with ±2σ 80 %, 0.043 and 58 % without; DIS alike
    # (development seeds 0.0045 / 0.0046 m/s). Online it changes nothing (development seeds causal
    # 0.0119 / 0.0120): the forward filter goes without.
    e_lp = (0.5 * sigma_t ** 2 * np.abs(np.gradient(_fill_nan(terms[3]), dt)) if zp else np.zeros(len(t)))
    min_fields = int(np.ceil(cfg.min_valid_fraction * r.shape[1]))  # for the reversals and the sign
    v, v_std = kalman_velocity(t, a, [(zr, sr, 0.0)], cfg, smooth=zp, gravity_tau=gravity_tau,
                               ratio=(kap, skap, terms[3], shift, e_lp), drift_std=drift_std, delay=delay,
                               corr_frames=n_corr, turn_rate=turn_rate, offset_walk=offset_walk,
                               offset_axis=offset_axis, offset_axis_prior=offset_axis_prior, transport=transport,
                               rest_accel=None if zp else accelerometer_level(a, dt, cfg.rest_accel_change_m_s2,
                                                                              causal=True),
                               lag=cfg.lag_s,  # the smoother (zero-phase) ignores it
                               reversal=(reversal_measurement(t, r, a, min_fields, cfg.stamp_error_s)
                                         if cfg.reversal else None),
                               sign=expansion_sign(t, rf if zp else r, min_fields) if cfg.sign else None)
    v_std = np.hypot(v_std, cfg.accel_scale_error * np.abs(v))  # the accelerometer's scale (see ReadoutConfig)
    obs = v_std <= cfg.max_std_m_s
    return ReadoutResult(np.where(obs, v, np.nan), obs, v_std, v_f, r_dot, z, s, a,
                         info=dict(measurement_delay_s=delay, lag_s=0.0 if zp else cfg.lag_s))


def readout(t, r, r2, a, config: ReadoutConfig | None = None,
            material: MaterialRates | None = None, gravity_tau=None, drift_std=None,
            turn_rate=None, offset_walk=None, offset_axis=None, offset_axis_prior=0.0,
            transport=None) -> ReadoutResult:
    """Velocity from per-frame field rates.

    t (n,) s, uniformly spaced; r, r2 (n, F) in 1/s and 1/s²; a (n,) forward
    acceleration at the same times (m/s², gravity removed); material: the rates along
    the content (:class:`MaterialRates`), used by the kalman readout when given;
    gravity_tau (n,) s: the online gravity estimate's time constant at each frame
    (lobula.haltere.gravity_time_constant; None offline), and drift_std (n,) m/s²/s, how
    fast the accelerometer's offset may ramp (see :func:`kalman_velocity`); turn_rate (n,) rad/s:
    the gyro's |ω| at those times (the acceleration errs more while turning; None: not turning);
    offset_walk (n,) m/s²/√s: how fast the accelerometer's offset may wander at those times beyond
    ReadoutConfig.bias_walk (lobula.haltere.leak_walk online; None: no more); offset_axis (n, 3): the
    optical axis in the frame where gravity was removed (lobula.haltere.forward_axis), whose gravity
    error δ (prior std offset_axis_prior m/s² per axis) the filter then tracks beside the accelerometer's
    own offset (:func:`kalman_velocity`; kalman readout only); transport (n,) 1/s: λ = ω_x·e_y − ω_y·e_x,
    how fast a turning camera's forward speed changes per m/s beyond its forward acceleration
    (lobula.haltere.transport_rate; None: 0).
    """
    cfg = config or ReadoutConfig()
    t, r, r2, a = (np.asarray(x, dtype=float) for x in (t, r, r2, a))
    if len(t) < 3:
        raise ValueError(f"need at least 3 flow frames for a readout, got {len(t)}")
    if not np.all(np.isfinite(a)):
        raise ValueError("acceleration has NaN or inf at flow times")
    if offset_walk is not None:
        offset_walk = np.asarray(offset_walk, dtype=float)
        if offset_walk.shape != t.shape or not np.all(np.isfinite(offset_walk) & (offset_walk >= 0)):
            raise ValueError(f"offset_walk must be finite, ≥ 0 and shaped like t {t.shape}, got {offset_walk.shape}")
    if offset_axis is not None:
        offset_axis = np.asarray(offset_axis, dtype=float)
        if offset_axis.shape != (len(t), 3) or not np.all(np.isfinite(offset_axis)):
            raise ValueError(f"offset_axis must be finite and shaped (n, 3) = ({len(t)}, 3), got {offset_axis.shape}")
        if not np.all(np.isfinite(offset_axis_prior) & (np.asarray(offset_axis_prior) >= 0)):
            raise ValueError(f"offset_axis_prior must be finite and ≥ 0, got {offset_axis_prior}")
    if transport is not None:
        transport = np.asarray(transport, dtype=float)
        if transport.shape != t.shape or not np.all(np.isfinite(transport)):
            raise ValueError(f"transport must be finite and shaped like t {t.shape}, got {transport.shape}")
    if cfg.method == "kalman":
        return kalman_readout(t, r, r2, a, cfg, material, gravity_tau, drift_std,
                              None if turn_rate is None else np.asarray(turn_rate, dtype=float), offset_walk,
                              offset_axis, offset_axis_prior, transport)
    return paper_readout(t, r, r2, a, cfg)
