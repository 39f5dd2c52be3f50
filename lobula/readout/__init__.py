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
  ``observable`` is False wherever v̂'s standard deviation exceeds
  :func:`~lobula.readout.config.std_allowed`, or vision has not fixed the speed or was seen not to
  follow the accelerometer (:mod:`lobula.readout.coupling`): the readout says when vision does not
  know. Beyond the observable frames the accelerometer carries v̂, its σ growing with the offset's
  prior (:mod:`lobula.readout.carry`); before vision has ever answered, v̂ is NaN.

The package, one module per concept: :mod:`lobula.readout.config` (:class:`ReadoutConfig`,
:class:`ReadoutResult`), :mod:`lobula.readout.filters` (low-passes and differences),
:mod:`lobula.readout.measurements` (what vision and the accelerometer measure),
:mod:`lobula.readout.kalman` (the filter), :mod:`lobula.readout.smoothers` (its backward passes),
:mod:`lobula.readout.carry` (v̂ beyond the frames vision answers) and
:mod:`lobula.readout.paper` (the paper's readout); every public name is importable from
``lobula.readout`` itself.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .carry import answered_velocity, carried_std, time_from_answer, vision_answers
from .config import ReadoutConfig, ReadoutResult, std_allowed
from .coupling import CouplingTest, coupling_test, vision_locked
from .filters import (_fill_nan, _integral, _lag, butterworth, difference_mean, end_mean, gaussian_lowpass, hold_gaps,
                      staggered_difference)
from .kalman import ForwardPass, FilterRecord, _accel_density2, _axis_terms, filter_record, kalman_velocity, predict  # noqa: F401
from .updates import OUTLIER_GATE, _gated_update, _sign_update, _update, ratio_update  # noqa: F401
from .measurements import (ACCEL_HEADING_FLOOR_M_S2, NO_EXPANSION_SE, REVERSAL_MAX_GAP_S, SIGN_PERSIST_S,
                           MaterialRates, acceleration_heading, accelerometer_level, accelerometer_steady,
                           clear_expansion, expansion_sign, field_axes, field_velocity, median_and_error,
                           nanmedian_rows, physical_kappa, ratio_measurement, readout_lag, readout_terms,
                           rest_measurement, reversal_measurement, scene_depth, signed_expansion, stop_measurement,
                           vision_measurement)
from .paper import paper_readout
from .smoothers import fixed_lag_smooth, rts_smooth

__all__ = [
    "ReadoutConfig", "ReadoutResult", "MaterialRates", "readout", "kalman_readout", "paper_readout",
    "readout_terms", "readout_lag", "vision_measurement", "ratio_measurement", "physical_kappa",
    "rest_measurement", "scene_depth", "reversal_measurement", "stop_measurement", "expansion_sign",
    "clear_expansion", "signed_expansion",
    "field_velocity", "field_axes", "acceleration_heading", "ACCEL_HEADING_FLOOR_M_S2", "median_and_error",
    "accelerometer_level", "accelerometer_steady",
    "kalman_inputs", "gate_by_lock", "vision_trusted", "kalman_velocity", "predict", "ratio_update", "rts_smooth",
    "fixed_lag_smooth", "vision_answers", "answered_velocity", "time_from_answer", "carried_std",
    "butterworth", "gaussian_lowpass", "staggered_difference", "hold_gaps",
    "NO_EXPANSION_SE", "SIGN_PERSIST_S", "REVERSAL_MAX_GAP_S", "OUTLIER_GATE",
]


def readout(t, r, r2, a, config: ReadoutConfig | None = None,
            material: MaterialRates | None = None, gravity_tau=None, drift_std=None,
            turn_rate=None, offset_walk=None, offset_axis=None, offset_axis_prior=0.0,
            transport=None, kappa_accel=None, a_rates=None) -> ReadoutResult:
    """Velocity from per-frame field rates.

    Parameters
    ----------
    t : array_like, (n,)
        s, uniformly spaced.
    r, r2 : array_like, (n, F)
        1/s and 1/s²: the fields' r̄ and r²̄.
    a : array_like, (n,)
        m/s²: the forward acceleration at the same times, gravity removed.
    config : ReadoutConfig, optional
        None: ``ReadoutConfig()``.
    material : MaterialRates, optional
        The rates along the content, used by the kalman readout when given.
    gravity_tau : ndarray, (n,), optional
        s: the online gravity estimate's time constant at each frame
        (lobula.imu.gravity_time_constant; None offline).
    drift_std : ndarray, (n,), optional
        m/s²/s: how fast the accelerometer's offset may ramp (see :func:`kalman_velocity`).
    turn_rate : array_like, (n,), optional
        rad/s: the gyro's |ω| at those times (the acceleration errs more while turning; None: not turning).
    offset_walk : array_like, (n,), optional
        m/s²/√s: how fast the accelerometer's offset may wander at those times beyond
        ReadoutConfig.bias_walk (lobula.imu.leak_walk online; None: no more).
    offset_axis : array_like, (n, 3), optional
        The optical axis in the frame where gravity was removed (lobula.imu.forward_axis), whose
        gravity error δ the filter then tracks beside the accelerometer's own offset
        (:func:`kalman_velocity`; kalman readout only).
    offset_axis_prior : float or array_like, (3,)
        m/s² per axis: δ's prior std.
    transport : array_like, (n,), optional
        1/s: λ = ω_x·e_y − ω_y·e_x, how fast a turning camera's forward speed changes per m/s beyond
        its forward acceleration (lobula.imu.transport_rate; None: 0).
    kappa_accel : tuple, optional
        (A (n, 3) m/s², ê (n, 2), R (n, 3, 3) or None): the 3-D gravity-free acceleration (camera frame), the
        direction it points along (:func:`acceleration_heading`) and the camera's orientation in
        ``offset_axis``'s frame. With the material fields' moments, each field's κ then measures the
        acceleration along its own axis (:func:`field_axes`), which holds a moving heading, and the gravity
        error δ along that axis turned by R (kalman readout only; None: κ measures ``a``).
    a_rates : array_like, (n,), optional
        m/s²: the forward acceleration averaged as each row's rates average the motion (a flow pair's
        rates over its two frames' interval, :func:`lobula.velocity.inertial.accels_at`), which the vision
        terms stand beside (kalman readout only; None: ``a``). The filter's state integrates ``a``.

    Returns
    -------
    ReadoutResult
        The kalman readout's (:func:`kalman_readout`) or, with method "median", the paper's
        (:func:`paper_readout`).
    """
    cfg = config or ReadoutConfig()
    if not isinstance(cfg, ReadoutConfig):
        raise TypeError(f"config must be a ReadoutConfig, got {type(cfg).__name__}")
    t, r, r2, a = (np.asarray(x, dtype=float) for x in (t, r, r2, a))
    if t.ndim != 1 or len(t) < 3:
        raise ValueError(f"t must be (n,) with at least 3 flow frames, got shape {t.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
        raise ValueError("t must be finite and increasing (s)")
    for name, x in (("r", r), ("r2", r2)):
        if x.ndim != 2 or x.shape[0] != len(t):
            raise ValueError(f"{name} must be (n, F) with n = len(t) = {len(t)}, got shape {x.shape}")
    if r2.shape != r.shape:
        raise ValueError(f"r2 must be shaped like r {r.shape}, got {r2.shape}")
    if a.shape != t.shape:
        raise ValueError(f"a must be shaped like t {t.shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("acceleration has NaN or inf at flow times")
    if turn_rate is not None and np.shape(turn_rate) != t.shape:
        raise ValueError(f"turn_rate must be shaped like t {t.shape}, got {np.shape(turn_rate)}")
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
    if kappa_accel is not None:
        kappa_accel = _check_kappa_accel(kappa_accel, len(t), offset_axis is not None)
    if a_rates is not None:
        a_rates = np.asarray(a_rates, dtype=float)
        if a_rates.shape != t.shape or not np.all(np.isfinite(a_rates)):
            raise ValueError(f"a_rates must be finite and shaped like t {t.shape}, got {a_rates.shape}")
    if cfg.method == "kalman":
        return kalman_readout(t, r, r2, a, cfg, material, gravity_tau, drift_std,
                              None if turn_rate is None else np.asarray(turn_rate, dtype=float), offset_walk,
                              offset_axis, offset_axis_prior, transport, kappa_accel, a_rates)
    return paper_readout(t, r, r2, a, cfg)


def kalman_readout(t, r, r2, a, cfg: ReadoutConfig, material: MaterialRates | None = None,
                   gravity_tau=None, drift_std=None, turn_rate=None, offset_walk=None,
                   offset_axis=None, offset_axis_prior=0.0, transport=None, kappa_accel=None,
                   a_rates=None) -> ReadoutResult:
    """The project's readout (see the package's docstring).

    Without ``material`` ṙ̄ is the staggered difference of the pooled rates at fixed pixels
    (exact only where r is uniform, a fronto-parallel surface); with it, the material
    derivative along the content and r̄, r²̄ over the same points.

    Parameters
    ----------
    t : ndarray, (n,)
        s, uniformly spaced.
    r, r2 : ndarray, (n, F)
        1/s and 1/s².
    a : ndarray, (n,)
        m/s², finite.
    cfg : ReadoutConfig
    material : MaterialRates, optional
    gravity_tau, drift_std, turn_rate, offset_walk, transport : ndarray, (n,), optional
        As :func:`readout` takes them (turn_rate, offset_walk and transport as float arrays).
    offset_axis : ndarray, (n, 3), optional
    offset_axis_prior : float or ndarray, (3,)
    kappa_accel, a_rates : optional
        As :func:`readout` takes them.

    Returns
    -------
    ReadoutResult
    """
    zp = cfg.filter == "zero-phase"
    inp = kalman_inputs(t, r, r2, a, cfg, material, offset_axis, offset_axis_prior, kappa_accel=kappa_accel,
                        a_rates=a_rates)
    if cfg.fusion == "vision-only":
        z, s = inp.z, inp.z_std
        obs = np.isfinite(z) & (s <= std_allowed(z, cfg))
        return ReadoutResult(np.where(obs, z, np.nan), obs, np.where(obs, s, np.nan), inp.v_field, inp.r_dot, z, s, a,
                             info=dict(measurement_delay_s=inp.delay))
    v, v_std = kalman_velocity(t, a, inp.measurements, cfg, smooth=zp, gravity_tau=gravity_tau,
                               ratio=inp.ratio, drift_std=drift_std, delay=inp.delay,
                               corr_frames=inp.corr_frames, turn_rate=turn_rate, offset_walk=offset_walk,
                               offset_axis=offset_axis, offset_axis_prior=offset_axis_prior, transport=transport,
                               rest_accel=inp.rest_accel, lag=cfg.lag_s,  # the smoother (zero-phase) ignores lag
                               reversal=inp.reversal, sign=inp.sign, stop=inp.stop)
    return finish_readout(t, v, v_std, inp, a, cfg)


def finish_readout(t, v, v_std, inp: "KalmanInputs", a, cfg: ReadoutConfig) -> ReadoutResult:
    """The :class:`ReadoutResult` of the filter's posterior v, v_std ((n,) m/s at t (n,) s): v_std widened by
    the accelerometer's scale error (ReadoutConfig.accel_scale_error); observable where v_std is within
    :func:`~lobula.readout.config.std_allowed` and vision has fixed the speed (:mod:`lobula.readout.coupling`),
    v_std carried (:mod:`lobula.readout.carry`) from the frames where, so judged, a measurement of vision entered;
    v̂ NaN where vision never has."""
    v_std = np.hypot(v_std, cfg.accel_scale_error * np.abs(v))  # the accelerometer's scale (see ReadoutConfig)
    zp = cfg.filter == "zero-phase"
    fixed = inp.locked | inp.coupling.provisional
    informing = np.isfinite(inp.ratio[0]) | inp.still | inp.passed_zero
    # σ is the posterior's where vision spoke and fixed the speed; beyond, it grows as lobula.readout.carry says.
    allowed = std_allowed(v, cfg)
    spoke = vision_answers(v_std, allowed, fixed, informing)
    posterior_std, v_std = v_std, carried_std(v_std, time_from_answer(t, spoke, causal=not zp), inp.offset_prior)
    obs = (v_std <= allowed) & fixed
    # The direct measurement as the filter takes it: its latency bridged with ∫a (the accelerometer's fast path).
    z = inp.z + inp.ratio[3]
    return ReadoutResult(np.where(np.isfinite(v_std), v, np.nan), obs, v_std, inp.v_field, inp.r_dot, z, inp.z_std, a,
                         info=dict(measurement_delay_s=inp.delay, lag_s=0.0 if zp else cfg.lag_s,
                                   vision_coupling=inp.coupling.z, vision_locked=inp.locked,
                                   vision_informing=informing, posterior_mean=v, posterior_std=posterior_std,
                                   vision_refuted=inp.coupling.refuted, scene_depth=inp.scene_depth))


@dataclass
class KalmanInputs:
    """What the kalman readout's filter takes from the fields and the acceleration (:func:`kalman_inputs`).

    measurements, ratio, rest_accel, reversal, sign, stop: :func:`kalman_velocity`'s arguments of those names
    (arrays (n,)); delay: s, the measurements' latency; corr_frames: frames over which their errors are
    correlated; v_field (n, F) m/s, r_dot (n, F) 1/s², z and z_std (n,) m/s: the per-field velocities, ṙ̄ and
    the direct vision measurement (of the low-passed v one ``delay`` ago) with its std, for the result;
    coupling: :func:`lobula.readout.coupling.coupling_test`'s verdicts; still, passed_zero (n,) bool: frames the
    rest bound holds at 0 or the expansion has fallen to a stop at, and frames a reversal (taken by the filter)
    was seen at; scene_depth (n,) m: the scene's depth as learned so far (:func:`~lobula.readout.measurements.scene_depth`; NaN: none yet, inf: too far to bound), which
    the rest bound takes × ``rest_depth_margin`` unless ``rest_depth_max_m`` gives one; locked (n,) bool: where vision
    has fixed the speed over this stretch (:func:`lobula.readout.coupling.vision_locked`); offset_prior: m/s², the prior
    std of the acceleration's whole forward offset.
    """

    measurements: list
    ratio: tuple
    rest_accel: tuple | None
    reversal: tuple | None
    sign: np.ndarray | None
    stop: tuple | None
    delay: float
    corr_frames: float
    v_field: np.ndarray
    r_dot: np.ndarray
    z: np.ndarray
    z_std: np.ndarray
    coupling: CouplingTest
    still: np.ndarray
    passed_zero: np.ndarray
    scene_depth: np.ndarray
    locked: np.ndarray
    offset_prior: float


def kalman_inputs(t, r, r2, a, cfg: ReadoutConfig, material: MaterialRates | None = None, offset_axis=None,
                  offset_axis_prior=0.0, dt: float | None = None, rest_depth_seen: float = np.nan,
                  gate: bool = True, kappa_accel=None, a_rates=None) -> KalmanInputs:
    """The kalman readout's measurements from the fields' rates and the forward acceleration.

    Online (``cfg.filter`` "causal") each frame's inputs depend on that frame and those before it only,
    so they may be computed on any trailing stretch of the record long enough for the low-pass, the
    rest test's windows and the reversals' gaps (:class:`lobula.velocity.VelocityEstimator` does).

    Parameters
    ----------
    t : ndarray, (n,)
        s, uniformly spaced.
    r, r2 : ndarray, (n, F)
        1/s and 1/s².
    a : ndarray, (n,)
        m/s², finite.
    cfg : ReadoutConfig
    material : MaterialRates, optional
    offset_axis : ndarray, (n, 3), optional
    offset_axis_prior : float or ndarray, (3,)
        As :func:`readout` takes them.
    dt : float, optional
        s: the frame interval (None: the median of t's differences).
    rest_depth_seen : float
        m: the scene depth learned before ``t[0]`` (online, a stream's earlier frames; NaN: none).
    gate : bool
        Leave κ and the reversals out where vision has not fixed the speed (:func:`gate_by_lock`), as this
        stretch's verdicts say; a stream, whose lock holds from before the stretch, gates each row itself.
    kappa_accel : tuple, optional
        As :func:`readout` takes it: what κ and the fields' depths are measured against. The coupling test keeps
        the forward acceleration: whether vision follows the accelerometer at all is judged as without it (on a
        real GoPro walk, judged against the fields' own axes, a stabilised image locked on, confidently wrong).
    a_rates : ndarray, (n,), optional
        As :func:`readout` takes it: what the vision terms stand beside (None: ``a``).

    Returns
    -------
    KalmanInputs
    """
    zp = cfg.filter == "zero-phase"
    dt = float(np.median(np.diff(t))) if dt is None else float(dt)
    a_rates = a if a_rates is None else np.asarray(a_rates, float)
    terms, lag, lp, rf = readout_terms(t, r, r2, a_rates, cfg, material, dt=dt)
    r_dot = terms[2]
    axes = a_f = None
    if kappa_accel is not None and material is not None and material.moment is not None:
        # Each field's acceleration along its own κ axis (field_axes), low-passed and late as the rates are.
        accel3, heading, _ = kappa_accel
        mom = material.moment.reshape(len(t), -1)
        mom = (lp(mom) if zp else lp(mom, True)).reshape(material.moment.shape)
        axes = _lag(field_axes(mom, heading), lag)
        a_f = np.einsum("nj,nfj->nf", _lag(lp(difference_mean(accel3, cfg.difference_frames)), lag), axes)
    z, s, v_f = vision_measurement(*terms[:3], terms[3] if a_f is None else a_f, cfg)
    delay = lag * dt
    # Low-passed measurements are correlated over about 1/(2·cutoff) s; treating each
    # frame as independent would make the posterior overconfident by √(that many frames).
    s = s * np.sqrt(max(1.0, 1.0 / (2 * cfg.cutoff_hz * dt)))
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
    # κ's velocity is that of the rows' rates: averaged over each pair of frames (∫a_rates is ∫a so
    # averaged) and, for the material fields, the mean of the difference's two ends.
    cum_rates = cum if a_rates is a else _integral(a_rates, t)
    if material is not None:
        cum_rates = end_mean(cum_rates, cfg.difference_frames)
    shift = cum - _lag(lp(cum_rates), lag)
    sigma_t = np.sqrt(np.log(2.0) / 2.0) / (np.pi * cfg.cutoff_hz)  # the low-pass's Gaussian width (s)
    # The prior std of the acceleration's whole forward offset: the accelerometer's own, and the
    # start frame's gravity error where the filter tracks it apart (offset_axis).
    offset_prior = float(np.hypot(cfg.bias_prior_m_s2, np.max(offset_axis_prior) if offset_axis is not None else 0.0))
    kap, skap, e_lp, n_corr, k_f = _kappa_measurement(terms, v_f, cfg, dt, sigma_t, offset_prior)
    a_m, c_m = terms[3], None
    if a_f is not None:
        a_m, c_m = _median_field_accel(kap, k_f, a_f, axes, terms[3], kappa_accel[2], lag)
    min_fields = int(np.ceil(cfg.min_valid_fraction * r.shape[1]))  # for the reversals and the sign
    coupling = coupling_test(_field_median(terms[2] - terms[1]), terms[3], dt, cfg.coupling_window_s, cfg.cutoff_hz,
                             not zp, cfg.coupling_z, cfg.coupling_refute_z, cfg.coupling_power_m_s2)
    seen = scene_depth(terms[0], v_f, np.isfinite(z), coupling.coupled, dt, 1.0 / cfg.cutoff_hz, not zp,
                       rest_depth_seen)
    depth = (cfg.rest_depth_margin * seen if cfg.rest_depth_max_m is None  # the footage's own depth, or the user's
             else np.full(len(t), float(cfg.rest_depth_max_m)))
    # The rest bound and the stops judge the same expansion (online the newest fields', offline the low-passed).
    expansion = signed_expansion(rf if zp else r)
    zr, sr = _rest_bound(r, rf, a, terms[3], depth, cfg, dt, sigma_t, offset_prior, expansion)
    stop = stop_measurement(t, rf if zp else r, a, min_fields, expansion=expansion) if cfg.stop else None
    # A frame the rest bound holds, or one whose expansion has fallen to a stop, is a still camera's: the
    # accelerometer's changes there are its own errors (gravity leaking through a gyro bias), nothing the
    # image should have followed.
    still = np.isfinite(zr) | (np.isfinite(stop[1]) if stop is not None else False)
    coupling.refuted &= ~still
    reversal = reversal_measurement(t, r, a, min_fields, cfg.stamp_error_s) if cfg.reversal else None
    # Where the expansion was seen not to follow the acceleration, neither its κ nor its changes of sign
    # speak of v (lobula.readout.coupling): the filter carries v̂ with the accelerometer there.
    kap = np.where(coupling.refuted, np.nan, kap)
    if reversal is not None:
        reversal = (np.where(coupling.refuted, np.nan, reversal[0]),) + tuple(reversal[1:])
    passed_zero = np.isfinite(reversal[0]) if reversal is not None else np.zeros(len(t), bool)
    locked = vision_locked(coupling, still, passed_zero, causal=not zp)
    if gate:
        kap, reversal = gate_by_lock(kap, reversal, vision_trusted(locked, coupling.provisional, coupling.full))
    return KalmanInputs(coupling=coupling, still=still, scene_depth=seen, locked=locked,
        passed_zero=passed_zero, offset_prior=offset_prior,
        measurements=[(zr, sr, 0.0)], ratio=(kap, skap, a_m, shift, e_lp) + (() if c_m is None else (c_m,)),
        rest_accel=None if zp else accelerometer_level(a, dt, cfg.rest_accel_change_m_s2, causal=True),
        reversal=reversal,
        sign=expansion_sign(t, rf if zp else r, min_fields) if cfg.sign else None, stop=stop,
        delay=delay, corr_frames=n_corr, v_field=v_f, r_dot=r_dot, z=z, z_std=s)


def vision_trusted(locked, provisional, full):
    """Where the filter takes vision's κ and reversals (bool, any shape): locked, answered provisionally, or
    before the coupling window is whole (see :func:`gate_by_lock`). ``locked``, ``provisional``, ``full``:
    bools or bool arrays (:class:`lobula.readout.coupling.CouplingTest`'s, the lock's)."""
    return np.logical_or(np.logical_or(locked, provisional), np.logical_not(full))


def gate_by_lock(kappa, reversal, trusted):
    """κ (n,) and the reversals (:func:`reversal_measurement`'s arrays, or None) left out where vision has not
    fixed the speed (``trusted`` (n,) bool; :mod:`lobula.readout.coupling`).

    :func:`kalman_inputs` trusts frames that are locked, answered provisionally, or whose coupling window is
    not yet whole (:func:`vision_trusted`): a lock needs a whole window (4 s), and a filter that waited for it
    would start from nothing then (the eye's noisier κ, locked 4-5 s in: one draw of four never answered).

    Before vision follows the accelerometer its κ is as likely noise — an image stabilised against the body, a
    hovering drone's expansion at the noise floor, a walk's gait — and a filter that takes noise at its stated
    error settles on v ≈ 0 with a confident σ and pins the accelerometer's offset there. Left out, the
    accelerometer carries v̂ from the prior, and its σ says how little is known (offline, on the walking and
    drone scenes: the truth inside the filter's ±2σ on 96–100 % of the unlocked frames, against 0–20 % taking κ).
    """
    kappa = np.where(trusted, kappa, np.nan)
    if reversal is not None:
        reversal = (np.where(trusted, reversal[0], np.nan),) + tuple(reversal[1:])
    return kappa, reversal


def _rest_bound(r, rf, a, a_lp, depth, cfg: ReadoutConfig, dt: float, sigma_t: float, offset_prior: float,
                expansion=None):
    """The kalman readout's rest bound (:func:`rest_measurement`), where the accelerometer allows it.

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s: the fields' newest r̄ (what online judges on).
    rf : ndarray, (n, F)
        1/s: the low-passed r̄, not lagged (what offline judges on).
    a : ndarray, (n,)
        m/s²: the forward acceleration as read.
    a_lp : ndarray, (n,)
        m/s²: the low-passed acceleration, as the readout's terms have it.
    depth : ndarray, (n,)
        m: the farthest the fields' median depth may be (NaN or inf: unknown, no bound).
    cfg : ReadoutConfig
    dt : float
        s: the frame interval.
    sigma_t : float
        s: the low-pass's Gaussian width.
    offset_prior : float
        m/s²: the prior std of the acceleration's whole forward offset.
    expansion : tuple of ndarray, optional
        :func:`signed_expansion` of the r̄ it judges on, where the caller has it (None: computed here).

    Returns
    -------
    z : ndarray, (n,)
        m/s: 0 where the bound is used, NaN elsewhere.
    std : ndarray, (n,)
        m/s.
    """
    zp = cfg.filter == "zero-phase"
    # Whether the image expands needs no derivative and no band-limiting: online it is judged
    # on the newest fields' r̄ (no latency to bridge with an offset-laden ∫a), offline on the
    # low-passed r̄ like everything else.
    zr, sr = rest_measurement(rf if zp else r, cfg, depth, expansion)
    # A far backdrop or the sky can fill most fields and show no expansion while the camera
    # moves (suite ground family, seed 0: with a 160-px DIS grid the bound alone holds v at 0
    # ± 0.02 m/s while it reaches −0.2 and pins a wrong offset for the whole record, 0.40 m/s
    # RMSE); the accelerometer says when the camera is at least not starting or stopping.
    zr = np.where(accelerometer_steady(a, dt, cfg.rest_accel_change_m_s2, causal=not zp), zr, np.nan)
    if zp:
        # Offline r̄ is low-passed over ~σ_t either side, in which v moves by ~σ_t·|a|: where the
        # image's expansion crosses zero while the camera accelerates (v through 0, or far
        # surfaces filling the fields), the bound holds only that well (development scene ground
        # 102, a backdrop 50-200 m away: 0.004 m/s widened, 0.039 not). Online r̄ is the newest frame's.
        # |a| less what the accelerometer's offset (2 prior std) could make of a still camera
        # (a real still EuRoC sequence's offset otherwise lifts the bound off: 0.043 m/s of "motion").
        sr = np.hypot(sr, sigma_t * np.maximum(np.abs(a_lp) - 2.0 * offset_prior, 0.0))
        zr = np.where(sr <= 0.5 * cfg.max_std_m_s, zr, np.nan)
    return zr, sr


def _field_median(x: np.ndarray) -> np.ndarray:
    """The median over fields of x (n, F), NaN where a frame has no finite field."""
    ok = np.isfinite(x).any(axis=1)
    out = np.full(len(x), np.nan)
    if ok.any():
        out[ok] = nanmedian_rows(x[ok])
    return out


def _kappa_measurement(terms, v_f, cfg: ReadoutConfig, dt: float, sigma_t: float, offset_prior: float):
    """Vision's κ = a/v for the kalman readout's filter, with its full standard error and timing error.

    Parameters
    ----------
    terms : tuple of ndarray
        The readout's (r̄, r²̄, ṙ̄, a) (:func:`readout_terms`).
    v_f : ndarray, (n, F)
        m/s: the fields' velocities, NaN where rejected.
    cfg : ReadoutConfig
    dt : float
        s: the frame interval.
    sigma_t : float
        s: the low-pass's Gaussian width.
    offset_prior : float
        m/s²: the prior std of the acceleration's whole forward offset.

    Returns
    -------
    kappa : ndarray, (n,)
        1/s.
    kappa_std : ndarray, (n,)
        1/s.
    e_lp : ndarray, (n,)
        m/s: the rates' timing error (0 online).
    n_corr : float
        Frames over which the low-passed terms' errors are correlated.
    k_f : ndarray, (n, F)
        1/s: the fields' ratios κ is the median of (NaN for those left out).
    """
    kap, skap, k_f = physical_kappa(terms, v_f, cfg, offset_prior)
    n_corr = max(1.0, 1.0 / (2 * cfg.cutoff_hz * dt))
    skap = skap * np.sqrt(n_corr)
    # What the fields' spread cannot show: an error all fields share (the flow's, a residual
    # rotation's), taken as a fraction of κ itself.
    skap = np.hypot(skap, cfg.kappa_rel_error * np.abs(kap))
    # κ's pairing with lp(v) (kalman_readout) is exact for rates stamped at the right time. A front end
    # whose rates are a frame or two off (the EMD's latency is taken out only as its low-frequency group delay) pairs κ
    # with the wrong moment, an error in a_m that grows where the acceleration changes: offline it is
    # carried as noise κ·σ_t²·|ȧ|/2, sized like the readout's own low-pass (σ_t). Exact rates 2 frames
    # late: ±2σ 97 % with it, 72 % without (3 frames early: 100 / 46 %); the EMD front end on a
    # development scene (moving, seed 100) 0.035 m/s with ±2σ 80 %, 0.043 and 58 % without; DIS alike
    # (development seeds 0.0045 / 0.0046 m/s). Online it changes nothing (development seeds causal
    # 0.0119 / 0.0120): the forward filter goes without.
    zp = cfg.filter == "zero-phase"
    e_lp = (0.5 * sigma_t ** 2 * np.abs(np.gradient(_fill_nan(terms[3]), dt)) if zp else np.zeros(len(terms[3])))
    return kap, skap, e_lp, n_corr, k_f


def _median_field_accel(kap, k_f, a_f, axes, a, turn, lag: int):
    """What the median κ measures where each field measures its own acceleration (:func:`field_axes`): the
    acceleration a_m (n,) m/s² of the field whose ratio is the median (the nearer of the middle two), and its
    axis c_m (n, 3) turned by ``turn`` (n, 3, 3; camera → the gravity frame, late by ``lag`` frames like the
    terms), or None without one. Frames without κ keep the forward acceleration ``a`` (n,) and the optical axis."""
    with np.errstate(invalid="ignore"):
        gap = np.abs(k_f - kap[:, None])
    has = np.isfinite(gap).any(axis=1)
    pick = np.argmin(np.where(np.isfinite(gap), gap, np.inf), axis=1)
    rows = np.arange(len(kap))
    a_m = np.where(has, a_f[rows, pick], a)
    if turn is None:
        return a_m, None
    ax = np.where(has[:, None], axes[rows, pick], np.array([0.0, 0.0, 1.0]))
    return a_m, np.einsum("nij,nj->ni", _lag(np.asarray(turn, float), lag), ax)


def _check_kappa_accel(kappa_accel, n: int, with_axis: bool):
    """:func:`readout`'s ``kappa_accel`` as float arrays, or ValueError saying what is wrong."""
    accel3, heading, turn = (None if x is None else np.asarray(x, dtype=float) for x in kappa_accel)
    if accel3.shape != (n, 3) or not np.all(np.isfinite(accel3)):
        raise ValueError(f"kappa_accel's acceleration must be finite and shaped (n, 3) = ({n}, 3), got {accel3.shape}")
    if heading.shape != (n, 2) or not np.all(np.isfinite(heading)):
        raise ValueError(f"kappa_accel's heading must be finite and shaped (n, 2) = ({n}, 2), got {heading.shape}")
    if turn is not None and (not with_axis or turn.shape != (n, 3, 3) or not np.all(np.isfinite(turn))):
        raise ValueError(f"kappa_accel's orientation must be finite, shaped (n, 3, 3) = ({n}, 3, 3) and come with "
                         f"offset_axis, got {turn.shape}")
    return accel3, heading, turn
