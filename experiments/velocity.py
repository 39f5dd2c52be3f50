"""Velocity estimation on footage: stream frames through a front end, pool, read out, score.

``estimate_velocity(footage, config)`` returns the DESIGN.md velocity Dataset: dims
``time`` and ``field``; ``v_hat``, ``observable``, ``accel``, ``r``, ``r2``, ``r_dot``,
``v_field`` and ``v_true`` when truth exists; the whole configuration, the front end,
the filter kind, the acceleration source and the version in ``attrs``.
"""
from __future__ import annotations

import json
import time as _time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation, Slerp
from tqdm.auto import tqdm

from lobula.config import VelocityConfig
from lobula.epipole import HEADING_POINTS, EpipoleEstimator, HeadingBiasEstimator, derotate_finite, turn
from lobula.flow import FlowSample
from lobula.front_ends import FRONT_ENDS, FrontEndInput, get_front_end
from lobula.photoreceptor import MEAN_REMOVAL, mean_removal
from lobula.haltere import (GRAVITY_WINDOW_S, HEADING_FIT_BIAS_PRIOR, GyroAttitude, attitude_leak,
                            forward_acceleration, forward_axis, fused_gyro_bias, gravity_drift_std,
                            gravity_time_constant, gyro_bias, leak_walk, orientation_from_gyro, resample_to,
                            transport_rate, turn_rate, vision_gyro_bias)
from lobula.readout import MaterialRates, readout
from lobula.receptive_field import MaterialFields, ReceptiveFields, gap_correction, pool_fields, tile_fields
from lobula.readers.core import Footage, FootageError, acceleration_from_truth, footage_provenance
from lobula.readers.flo import FloUnits

from .store import provenance
from .stream import threaded


@dataclass
class FieldRates:
    """What the front end and fields give the readout, time-major.

    t (n,) s; r, r2 (n, F) at fixed pixels; epipole (n, 2) normalised; timings: seconds per
    stage; material: the rates along the content (ṙ̄ as Dr/Dt, lobula.readout.MaterialRates),
    None where the front end gives no consecutive pairs (flo, emd) or fields.material is off.
    gyro_residual: (t (m,) s, residual (m, 3) rad/s, rate (m, 3) rad/s): on non-overlapping
    pairs, the gyro bias the derotated flow says and the gyro's rate over the pair
    (lobula.haltere.vision_gyro_bias's measurements and regressors), or None.
    heading_bias: (t (m,) s, bias (m, 3) rad/s, std (m, 3) rad/s): the gyro bias the heading and
    bias fit (lobula.epipole.HeadingBiasEstimator) holds after each pair, known at the pair's
    second frame t; or None (no gyro, no estimated epipole).
    known: (n,) s, when each row's frames are all in (its pair's second frame), or None where the
    front end does not say (flo, emd).
    """

    t: np.ndarray
    r: np.ndarray
    r2: np.ndarray
    epipole: np.ndarray
    timings: dict
    fields: ReceptiveFields
    material: MaterialRates | None = None
    gyro_residual: tuple | None = None
    heading_bias: tuple | None = None
    known: np.ndarray | None = None


def field_rates(footage: Footage, config: VelocityConfig, flo_files: list[Path] | None = None,
                flo_units: FloUnits | None = None, progress: bool = True) -> FieldRates:
    """Run the front end over the footage (streamed) and pool every flow into the fields.

    The front end (:func:`lobula.front_ends.get_front_end` of ``config.front_end``) yields each pair's
    flow, which is derotated and pooled here, or the fields' rates it pooled itself (its ``yields``).
    flo_files, flo_units: the precomputed flow of the ``flo`` front end.
    """
    front = get_front_end(config.front_end)
    cam = footage.camera
    fields = tile_fields(cam, config.fields)
    x, y = fields.x, fields.y
    # ~5,000 pixels are plenty for a 2-parameter fit, whatever the image size.
    est = EpipoleEstimator(x, y, stride=max(1, int(np.sqrt(cam.width * cam.height / 5000))))
    gyro = footage.imu.gyro if (footage.imu is not None and footage.imu.gyro is not None) else None
    attitude = (_attitude_track(footage.imu.time_s, gyro, causal=config.readout.filter == "causal")
                if (gyro is not None and config.derotate) else None)
    plain_attitude = attitude
    timings = dict(read=0.0, flow=0.0, fields=0.0)
    # The gyro bias the derotation removed (still-camera estimate), to add back to what vision finds left.
    b0 = (gyro_bias(footage.imu.time_s, gyro, causal=config.readout.filter == "causal")
          if attitude is not None and config.gyro_bias_from_vision else None)

    stream = front.open(FrontEndInput(footage, config, fields, timings, attitude, flo_files, flo_units,
                                      ahead=threaded))
    if front.yields == "fields":
        return _pooled_field_rates(stream, config, fields, timings, progress)
    if front.live and attitude is not None and config.epipole == "estimate":
        # The heading and the gyro's bias are fitted jointly (lobula.epipole.HeadingBiasEstimator)
        # and the fields' attitude follows the bias and the scale error E learned so far
        # (lobula.haltere.GyroAttitude); the pre-warp, a thread ahead, keeps the plain attitude.
        # E (VelocityConfig.gyro_scale_prior): the suite's rotation family (±5°, to 1.5 Hz, seeds
        # 0-2) 0.011 / 0.018 m/s zero-phase / causal with it, 0.016 / 0.039 without; a camera turning
        # ±10° at up to 2 Hz with a realistic IMU reads v̂ 40-60 % slow without it (zero-phase 0.106 m/s, zero
        # estimator 0.20, ideal IMU 0.012) and 0.013 with it.
        # The fit's own bias prior is its regulariser against the heading–bias confound, narrower than
        # the data sheet's spread (lobula.haltere.HEADING_FIT_BIAS_PRIOR).
        fit_prior = min(HEADING_FIT_BIAS_PRIOR, np.radians(config.gyro_bias_prior_deg_s))
        b_still, s_still = gyro_bias(footage.imu.time_s, gyro, causal=config.readout.filter == "causal",
                                     with_std=True, prior=fit_prior)
        attitude = GyroAttitude(footage.imu.time_s, gyro, b_still[0])
        est = HeadingBiasEstimator(x, y, b_still[0], s_still[0], scale_std=config.gyro_scale_prior or None,
                                   stride=max(1, int(np.sqrt(cam.width * cam.height / HEADING_POINTS))))
    samples, total = stream.samples, stream.total

    stagger = max(2, config.readout.stagger + config.readout.stagger % 2)
    material = (MaterialFields(fields, stagger, gap_correction=config.fields.gap_correction)
                if config.fields.material and front.live else None)
    ts, rs, r2s, es, ms, gres, hb, known = [], [], [], [], [], [], [], []
    bar = tqdm(total=total, desc=f"{config.front_end} flow → fields", unit="frame", disable=not progress,
               leave=False, mininterval=2)
    for s in samples:
        t1 = _time.perf_counter()
        flow, q = s.flow, (None, None, None)
        if attitude is not None:
            # camera → reference at t0, t1, middle: the fixed-pixel rates (inside pool_fields, on
            # the pixels it pools), the epipole and the material fields all derotate exactly
            # (finite rotation over the gap) into the middle orientation.
            q = attitude(np.array([s.t0, s.t1, s.t_mid]))
        if config.epipole == "estimate":
            if attitude is not None:
                sub = s.flow[:, ::est.stride, ::est.stride].reshape(2, -1)
                pts = derotate_finite(est.x, est.y, sub, s.dt, q[2].T @ q[0], q[2].T @ q[1])
                if isinstance(attitude, GyroAttitude):
                    if config.readout.filter == "causal":  # the still-camera estimate so far, as it accrues
                        k = min(int(np.searchsorted(footage.imu.time_s, s.t1)), len(b_still) - 1)
                        est.set_bias_prior(b_still[k], s_still[k])
                    c_app, w_bar = attitude.applied_correction(s.t0, s.t1)
                    e = est.update(None, points=pts, attitude=q[2], applied_bias=c_app, rate=w_bar)
                    attitude.bias, attitude.scale = est.bias, est.scale
                    hb.append((s.t1, est.bias, est.bias_std))
                else:
                    e = est.update(None, points=pts, attitude=q[2])
            else:
                e = est.update(flow)
        else:
            e = np.zeros(2)
        r, r2 = pool_fields(flow, fields, e, pooling=config.fields.pooling,
                            turns=None if q[0] is None else (q[2].T @ q[0], q[2].T @ q[1], s.dt))
        if config.fields.gap_correction:
            r, r2 = gap_correction(r, r2, s.dt)
        if material is not None:
            ms.append(material.update(s.t0, s.dt, s.flow, e, *q))
        if b0 is not None and len(ts) % config.flow.gap == 0:
            # Measured against the plain attitude (the still-camera bias removed), as vision_gyro_bias models it.
            qp = plain_attitude(np.array([s.t0, s.t1]))
            gres.append(_residual_rate(footage, s, qp[0].T @ qp[1], e, b0))
        timings["fields"] += _time.perf_counter() - t1
        ts.append(s.t_mid if config.timestamps == "mid" else s.t0)
        known.append(s.t1)
        rs.append(r)
        r2s.append(r2)
        es.append(e)
        bar.update(1)
    bar.close()
    if not ts:
        raise FootageError(f"{footage.path}: too few frames for a flow pair "
                           f"({len(footage)} frames, gap {config.flow.gap})")
    return FieldRates(np.array(ts), np.array(rs), np.array(r2s), np.array(es), timings, fields,
                      _material_rates(ms, len(ts), fields.n_fields, stagger) if material is not None else None,
                      tuple(np.array([g[i] for g in gres]) for i in range(3)) if gres else None,
                      tuple(np.array([h[i] for h in hb]) for i in range(3)) if hb else None,
                      np.array(known) if front.live else None)


#: pixels per pair for the residual-rotation fit: a 3-parameter fit (with a 2-parameter
#: epipole) needs far fewer than the image holds, and it runs on every gap-th pair.
RESIDUAL_POINTS = 1500


def _residual_rate(footage: Footage, s: FlowSample, r01: np.ndarray, e: np.ndarray, b0: np.ndarray):
    """(t_mid, b (3,) rad/s, ω (3,) rad/s): the gyro bias this pair's flow says, b0(t_mid) − δω,
    and the gyro's mean rate over the pair (the regressor of its scale-factor errors).

    The raw flow is derotated exactly (each point's second ray turned into the first
    frame's orientation by the gyro's r01) and lobula.depth_motion.refine_motion fits the
    rotation δω still in it jointly with the epipole (started at the running estimate e).
    The gyro read ω + b and the derotation removed ω + b − b0, so the flow is left turning
    by −(b − b0): δω = b0 − b.
    """
    from lobula.depth_motion import refine_motion  # torch-based; only --gyro-bias-from-vision needs it

    x, y = footage.camera.normalised_grid(np.float64)
    f = np.asarray(s.flow, np.float64)
    x1, y1 = turn(r01, x + f[0] * s.dt, y + f[1] * s.dt)
    fd = np.stack([(x1 - x) / s.dt, (y1 - y) / s.dt])
    _, dw, _ = refine_motion(fd, footage.camera, tuple(e), n_points=RESIDUAL_POINTS)
    tb = footage.imu.time_s
    b_then = np.array([np.interp(s.t_mid, tb, b0[:, k]) for k in range(3)])
    return s.t_mid, b_then - dw, Rotation.from_matrix(r01).as_rotvec() / s.dt


def gyro_bias_track(footage: Footage, rates: FieldRates, causal: bool, prior: float):
    """The gyro bias and its std ((n, 3) rad/s each, at the IMU samples) for the attitude that removes
    gravity and for the readout's drift std, and what they come from; None without a gyro or a
    flow-fitted bias (then the still-camera estimate alone serves).

    With ``gyro_bias_from_vision`` (``rates.gyro_residual``): the flow's residual rotation
    (lobula.haltere.vision_gyro_bias), started from the still-camera estimate. Else the heading and
    bias fit's estimate (``rates.heading_bias``) fused with the still-camera one
    (lobula.haltere.fused_gyro_bias). ``prior`` (rad/s): the bias's std before the record measures
    it (VelocityConfig.gyro_bias_prior_deg_s). Without it a turning camera that never stops (the suite's
    rotation family) removes gravity through an attitude drifting at the whole bias: its forward
    acceleration ramps by 0.05-0.09 m/s² per second; with it ≤ 0.005. The suite's development
    scenes (nine families × seeds 100-103, 320×240, 10 s), without → with: rotation zero-phase RMSE 0.017 / 0.026 /
    0.020 / 0.016 → 0.005 / 0.011 / 0.014 / 0.013 m/s, causal 0.018 / 0.057 / 0.039 / 0.035 →
    0.015 / 0.042 / 0.033 / 0.039; the other 32 scenes within ±0.002; all 36 zero-phase 0.0073 →
    0.0063, causal 0.0149 → 0.0144.
    """
    if (footage.imu is None or footage.imu.gyro is None
            or (rates.gyro_residual is None and rates.heading_bias is None)):
        return None
    tb = footage.imu.time_s
    b_still, s_still = gyro_bias(tb, footage.imu.gyro, causal, with_std=True, prior=prior)
    if rates.gyro_residual is not None:
        t_m, res, rate = rates.gyro_residual
        return (*vision_gyro_bias(t_m, res, tb, b_still[0], s_still[0], causal, rate=rate),
                "the flow's residual rotation (camera frame)")
    return (*fused_gyro_bias(tb, b_still, s_still, *rates.heading_bias, causal),
            "the heading and bias fit fused with the still-camera estimate (camera frame)")


def _attitude_track(time_s: np.ndarray, gyro: np.ndarray, causal: bool):
    """A function t (k,) -> camera orientations (k, 3, 3) (camera → the first sample's frame)
    from the bias-corrected integrated gyro (lobula.haltere), interpolated by slerp."""
    q = orientation_from_gyro(time_s, gyro, causal)
    keep = np.concatenate([[True], np.diff(time_s) > 0])
    slerp = Slerp(time_s[keep], Rotation.from_matrix(q[keep]))
    return lambda t: slerp(np.clip(t, time_s[0], time_s[-1])).as_matrix()


def _material_rates(items: list, n: int, n_fields: int, stagger: int) -> MaterialRates:
    """Place each difference (returned at pair k, over k − s … k) at its centre k − s/2."""
    out = [np.full((n, n_fields), np.nan) for _ in range(3)]
    h = stagger // 2
    for k, item in enumerate(items):
        if item is not None:
            for arr, val in zip(out, item):
                arr[k - h] = val
    return MaterialRates(*out)


def _pooled_field_rates(stream, config: VelocityConfig, fields: ReceptiveFields, timings: dict,
                        progress: bool) -> FieldRates:
    """FieldRates of a front end that pools its own fields (``yields`` "fields", the EMD): its
    FieldSamples in order, the epipole at the principal point (zeros)."""
    ts, rs, r2s = [], [], []
    with tqdm(total=stream.total, desc=f"{config.front_end} → fields", unit="frame", disable=not progress,
              leave=False, mininterval=2) as bar:
        for s in stream.samples:
            ts.append(s.t)
            rs.append(s.r)
            r2s.append(s.r2)
            bar.update(1)
    return FieldRates(np.array(ts), np.array(rs), np.array(r2s), np.zeros((len(ts), 2)), timings, fields)


TRUTH_ACCEL_OFFSET_M_S2 = 0.01  # prior std of the offset of an acceleration derived from ground truth


#: m/s²: prior std of the platform's acceleration at the record's start, which the online gravity
#: reference (lobula.haltere.online_gravity, set over the first GRAVITY_INIT_S) takes in: 0.1 g,
#: a priori (a walking or handheld camera's or a road vehicle's acceleration mostly stays under it).
START_ACCEL_PRIOR_M_S2 = 1.0
#: m/s²: the same where the first flow pair already shows the camera moving (:func:`start_accel_prior`):
#: 0.3 g, a platform braking or speeding up hard (a car braking, a drone) — one at rest mostly starts gently.
START_ACCEL_PRIOR_MOVING_M_S2 = 3.0


def start_accel_prior(r: np.ndarray, min_fields: int = 3) -> float:
    """Prior std (m/s²) of the start acceleration the online gravity reference takes in: wider where
    the camera is seen moving at the start.

    r (n, F) 1/s: the fields' expansion rates; the first frame with ``min_fields`` finite fields
    decides. Moving means the fields' signed median r̄ stands clear of its standard error
    (|r̄| > 3·SE, as :func:`lobula.readout.rest_measurement` judges "no detectable expansion").
    Why: a camera already moving may be braking or accelerating hard while the reference is set.
    The suite's fast family starts in motion at up to 2 m/s decelerating at 2–3.7 m/s² (seeds
    0–2; development seeds −1.1 / −0.4 / +1.8), 2–3.7σ of the 0.1 g prior: a second-late
    (fixed-lag) estimate held the truth within ±2σ on 46 % of its first 2 s (22 % on one seed),
    100 % online and 99 % a second late with this prior. A camera seen at rest keeps 0.1 g: a
    wider prior there cost a development ground world (far backdrop, the rest bound) 0.015 →
    0.023 m/s online.
    """
    from lobula.readout import NO_EXPANSION_SE, median_and_error

    n = np.isfinite(r).sum(1)
    first = np.flatnonzero(n >= min_fields)
    if not len(first):
        return START_ACCEL_PRIOR_M_S2
    k = first[0]
    med, se = median_and_error(r[k:k + 1], n[k:k + 1])
    return START_ACCEL_PRIOR_MOVING_M_S2 if abs(med[0]) > NO_EXPANSION_SE * se[0] else START_ACCEL_PRIOR_M_S2


def gravity_tau(footage: Footage, times: np.ndarray, config: VelocityConfig) -> np.ndarray | None:
    """Time constant (s) of the online gravity estimate at each time (causal, IMU only; else None)."""
    if config.readout.filter != "causal" or config.accel_from_truth or footage.imu is None:
        return None
    return gravity_time_constant(times, float(footage.imu.time_s[0]))


def forward_accel_at(footage: Footage, times: np.ndarray, config: VelocityConfig,
                     bias: np.ndarray | None = None, orientation: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """Forward acceleration (m/s²) at ``times`` and a label saying where it came from.

    bias: gyro bias track (n_imu, 3) rad/s for the attitude that removes gravity
    (:func:`gyro_bias_track`); None: the still-camera estimate. orientation: that attitude
    (n_imu, 3, 3) where already integrated (:func:`lobula.haltere.orientation_from_gyro`)."""
    causal = config.readout.filter == "causal"
    if config.accel_from_truth or footage.imu is None:
        if not config.accel_from_truth and footage.kind != "d435i-sample":
            where = footage.path / "imu.csv" if footage.kind == "folder" else footage.path
            raise FootageError(f"{where}: {'missing' if footage.kind == 'folder' else 'no IMU'}; velocity needs "
                               f"forward acceleration. Add the IMU log, or pass --accel-from-truth to use the truth")
        if footage.truth is None:
            raise FootageError(f"{footage.path}: no IMU and no truth to derive acceleration from")
        tt, at = acceleration_from_truth(footage.truth)
        return np.interp(times, tt, at), "ground truth (smoothed derivative of velocity; no IMU)"
    imu = footage.imu
    if times[0] < imu.time_s[0] - 0.5 or times[-1] > imu.time_s[-1] + 0.5:
        # imu.source names the file (or bag and topic) the samples came from, whatever the layout.
        realsense = footage.kind.startswith("realsense")
        raise FootageError(f"{imu.source}: the IMU covers {imu.time_s[0]:.2f}..{imu.time_s[-1]:.2f} s but the "
                           f"frames of {footage.path.name} need {times[0]:.2f}..{times[-1]:.2f} s; their time stamps "
                           f"are not on one clock: shift the IMU with --clock-offset SECONDS (or auto)"
                           + (", or read both on another --clock" if realsense else ""))
    a = forward_acceleration(imu.time_s, imu.accel, imu.gyro if config.derotate else None, causal=causal,
                             bias=bias, orientation=orientation if config.derotate else None)
    dt = float(np.median(np.diff(footage.times)))
    return resample_to(times, imu.time_s, a, dt), "accelerometer (gravity and bias removed)"


def turn_rate_at(footage: Footage, times: np.ndarray, accel_source: str, config: VelocityConfig) -> np.ndarray | None:
    """|ω| (rad/s, (n,)): the gyro's rate magnitude averaged over each frame interval, or None
    where the acceleration does not come from an IMU with a gyro (then nothing turns it)."""
    if not accel_source.startswith("accelerometer") or footage.imu is None or footage.imu.gyro is None:
        return None
    return turn_rate(times, footage.imu.time_s, footage.imu.gyro, float(np.median(np.diff(footage.times))))


def estimate_velocity(footage: Footage, config: VelocityConfig | None = None, progress: bool = True,
                      flo_files: list[Path] | None = None, flo_units: FloUnits | None = None) -> xr.Dataset:
    """Estimate forward velocity over a footage; returns the velocity Dataset (see module doc)."""
    config = config or VelocityConfig()
    front = get_front_end(config.front_end)
    if config.epipole not in front.epipoles:
        others = [f.name for f in FRONT_ENDS.values() if config.epipole in f.epipoles]
        raise ValueError(f"the {front.name} front end has no epipole {config.epipole} (it runs with epipole "
                         f"{' or '.join(front.epipoles)}); use epipole {front.epipoles[0]!r} (--epipole "
                         f"{front.epipoles[0]}) or another front end ({', '.join(others)})")
    t_start = _time.perf_counter()
    rates = field_rates(footage, config, flo_files, flo_units, progress)
    causal = config.readout.filter == "causal"
    prior = np.radians(config.gyro_bias_prior_deg_s)
    vb = gyro_bias_track(footage, rates, causal, prior)
    # The attitude that removes gravity, integrated once for the acceleration and the axis its error turns with.
    imu = footage.imu if not config.accel_from_truth else None
    rot = (orientation_from_gyro(imu.time_s, imu.gyro, causal, None if vb is None else vb[0])
           if imu is not None and imu.gyro is not None and config.derotate else None)
    a, accel_source = forward_accel_at(footage, rates.t, config, bias=None if vb is None else vb[0], orientation=rot)
    fields = rates.fields
    t0 = _time.perf_counter()
    rcfg = config.readout
    axis, gravity_error = None, 0.0
    if not accel_source.startswith("accelerometer"):
        # A derivative of the true velocity has noise but no accelerometer offset to learn.
        rcfg = replace(rcfg, bias_prior_m_s2=min(rcfg.bias_prior_m_s2, TRUTH_ACCEL_OFFSET_M_S2))
    else:
        if not causal:
            # Offline gravity is the mean specific force over up to GRAVITY_WINDOW_S of record, which
            # also holds the platform's mean acceleration Δv/T there: an offset of up to v/T.
            span = min(GRAVITY_WINDOW_S, float(footage.imu.time_s[-1] - footage.imu.time_s[0]))
            gravity_error = rcfg.v_prior_m_s / max(span, 1.0)
        else:
            # Online, the gravity reference is set at the start and holds the acceleration there.
            gravity_error = start_accel_prior(rates.r)
        if footage.imu.gyro is not None and config.derotate:
            # That error is a vector in the frame gravity was taken in; its forward share turns with the
            # camera, so the readout tracks it there beside the accelerometer's own offset.
            axis = forward_axis(footage.imu.time_s, footage.imu.gyro, causal=causal,
                                bias=None if vb is None else vb[0], orientation=rot)
            axis = np.stack([np.interp(rates.t, footage.imu.time_s, axis[:, j]) for j in range(3)], -1)
            axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        else:
            rcfg = replace(rcfg, bias_prior_m_s2=float(np.hypot(rcfg.bias_prior_m_s2, gravity_error)))
    if len(rates.t) >= 3:
        tau = gravity_tau(footage, rates.t, config)
        drift = walk = lam = None
        if accel_source.startswith("accelerometer") and footage.imu.gyro is not None and config.derotate:
            # A turning camera's forward speed changes by −λ·v beyond its forward acceleration.
            lam = transport_rate(rates.t, footage.imu.time_s, footage.imu.gyro, None if vb is None else vb[0],
                                 rates.epipole, float(np.median(np.diff(footage.times))),
                                 causal=causal)
            # Gravity seen through a gyro-integrated attitude ramps at up to |g|·σ_b (lobula.haltere):
            # a state of the readout's filter, offline and online alike.
            drift = np.interp(rates.t, footage.imu.time_s,
                              gravity_drift_std(footage.imu.time_s, footage.imu.gyro, causal=causal,
                                                bias_std=None if vb is None else vb[1], accel=footage.imu.accel,
                                                prior=prior))
            if causal:
                # Online the attitude took each sample's bias estimate; where that estimate moves, the
                # gravity it let in moves the offset the filter had learned (lobula.haltere.leak_walk).
                tb = footage.imu.time_s
                used = vb[0] if vb is not None else gyro_bias(tb, footage.imu.gyro, causal=True)
                walk = leak_walk(rates.t, tb, attitude_leak(tb, used, footage.imu.accel))
        res = readout(rates.t, rates.r, rates.r2, a, rcfg, material=rates.material, gravity_tau=tau,
                      drift_std=drift, turn_rate=turn_rate_at(footage, rates.t, accel_source, config),
                      offset_walk=walk, offset_axis=axis, offset_axis_prior=gravity_error, transport=lam)
    else:
        res = None
    rates.timings["readout"] = _time.perf_counter() - t0
    n, F = rates.r.shape
    nan_nf = np.full((n, F), np.nan)
    data = dict(
        v_hat=("time", res.v_hat if res else np.full(n, np.nan), {"units": "m/s", "long_name": "estimated forward velocity"}),
        observable=("time", res.observable if res else np.zeros(n, bool), {"units": "1", "long_name": "velocity observable"}),
        v_std=("time", res.v_std if res else np.full(n, np.nan), {"units": "m/s", "long_name": "posterior std of v_hat"}),
        accel=("time", a, {"units": "m/s2", "long_name": "forward acceleration", "source": accel_source}),
        r=(("time", "field"), rates.r, {"units": "1/s", "long_name": "pooled expansion rate v/d"}),
        r2=(("time", "field"), rates.r2, {"units": "1/s2", "long_name": "pooled mean of r squared"}),
        r_dot=(("time", "field"), res.r_dot if res else nan_nf,
               {"units": "1/s2", "long_name": "time derivative of the pooled expansion rate r"}),
        v_field=(("time", "field"), res.v_field if res else nan_nf,
                 {"units": "m/s", "long_name": "per-field forward velocity a·r/(r_dot − r2)"}),
        epipole_x=("time", rates.epipole[:, 0], {"units": "1", "long_name": "epipole, normalised x"}),
        epipole_y=("time", rates.epipole[:, 1], {"units": "1", "long_name": "epipole, normalised y"}),
    )
    if footage.truth is not None:
        data["v_true"] = ("time", np.interp(rates.t, footage.truth["time_s"], footage.truth["v_forward_m_s"]),
                          {"units": "m/s", "long_name": "ground-truth forward velocity"})
    coords = dict(time=("time", rates.t, {"units": "s", "long_name": "time of the estimate on the footage clock"}),
                  azimuth_deg=("field", fields.centres_deg[:, 0],
                               {"units": "degree", "long_name": "LC field centre azimuth"}),
                  elevation_deg=("field", fields.centres_deg[:, 1],
                                 {"units": "degree", "long_name": "LC field centre elevation (positive down)"}),
                  size_deg=("field", np.full(F, fields.size_deg),
                            {"units": "degree", "long_name": "LC field size (Gaussian FWHM, or box side)"}))
    if vb is not None:
        tb = footage.imu.time_s
        at_t = lambda b: np.stack([np.interp(rates.t, tb, b[:, k]) for k in range(3)], -1)
        data["gyro_bias"] = (("time", "axis"), at_t(vb[0]), {"units": "rad/s", "long_name":
                             "gyro bias from " + vb[2]})
        data["gyro_bias_std"] = (("time", "axis"), at_t(vb[1]), {"units": "rad/s", "long_name":
                                 "std of the gyro bias estimate"})
        coords["axis"] = ("axis", ["x", "y", "z"], {"long_name": "camera axis (x right, y down, z forward)"})
    ds = xr.Dataset(data, coords=coords)
    lag = config.readout.lag_s if config.readout.filter == "causal" else 0.0
    online = {}
    if config.readout.filter == "causal" and rates.known is not None and res is not None:
        # When each v̂ is known after the time it is stamped with: its pair's second frame (half the
        # flow gap after the pair's middle) plus any declared look-ahead. The vision measurements speak
        # of the moment measurement_delay_s before that stamp, bridged by the integrated accelerometer.
        online = dict(output_latency_s=round(float(np.median(rates.known - rates.t)) + lag, 4))
        if "measurement_delay_s" in res.info:  # the kalman readout's (the paper's has no bridge)
            online["measurement_delay_s"] = round(float(res.info["measurement_delay_s"]), 4)
    filt = config.readout.filter + (f", fixed lag {lag:g} s" if lag else "")
    if online:
        filt += f" (each v_hat known {online['output_latency_s']:g} s after its time)"
    gyro = footage.imu is not None and footage.imu.gyro is not None
    if front.derotation == "gaze":
        derotation = (f"gaze stabilised by the integrated gyro (fixations, saccades beyond "
                      f"{config.emd.saccade_limit_deg:g} deg: {int(rates.timings.get('n_saccades', 0))})"
                      if config.derotate and gyro and config.emd.gaze == "fixate" else
                      "none: the EMD front end's image is not stabilised (the gyro serves the accelerometer's "
                      "attitude only)")
    else:
        derotation = "exact finite rotation from the integrated gyro" if config.derotate and gyro else "none"
    ds.attrs.update(provenance(config.to_json(), front_end=config.front_end, filter=filt, **online,
                               derotation=derotation, epipole=config.epipole,
                               readout=config.readout.method, acceleration_source=accel_source,
                               footage=str(footage.path), footage_kind=footage.kind,
                               notes="; ".join(footage.notes) or "none",
                               timings_s=json.dumps({k: round(v, 4) for k, v in rates.timings.items()}),
                               wall_s=round(_time.perf_counter() - t_start, 3), **footage_provenance(footage)))
    return ds


def score(ds: xr.Dataset, skip_s: float = 2.0) -> dict:
    """RMSE and median absolute error of v̂ against truth after ``skip_s``, and the observable fraction.

    Errors are over observable frames; the fraction says how many those are.
    """
    if "v_true" not in ds:
        return {}
    keep = (ds.time >= ds.time[0] + skip_s).values
    obs = ds.observable.values[keep]
    err = (ds.v_hat - ds.v_true).values[keep][obs]
    out = dict(observable_fraction=float(obs.mean()) if obs.size else 0.0, n_frames=int(keep.sum()))
    if err.size:
        out.update(rmse_m_s=float(np.sqrt(np.mean(err ** 2))), median_abs_error_m_s=float(np.median(np.abs(err))))
    else:
        out.update(rmse_m_s=float("nan"), median_abs_error_m_s=float("nan"))
    return out


#: Seconds ignored at the start when scoring a run (`lobula velocity --skip`'s default).
SCORE_SKIP_S = 2.0


def scoring_skip(ds: xr.Dataset, skip_s: float = SCORE_SKIP_S) -> float:
    """Seconds ignored at the start when scoring ``ds``: ``skip_s``, at most a quarter of the run.

    Short clips (the 1.2 s D435i sample) keep three quarters of their estimates to score.
    """
    t = ds.time.values
    return min(float(skip_s), 0.25 * float(t[-1] - t[0])) if t.size else float(skip_s)


def score_line(sc: dict, skip_s: float) -> str:
    """The one-line score of a run, as the console and the figure's title both print it.

    sc: :func:`score`'s dict (RMSE and median |error| in m/s, observable fraction);
    skip_s: the seconds it ignored.
    """
    if not sc:
        return "no truth: not scored"
    obs = f"observable {100 * sc['observable_fraction']:.1f} % of {sc['n_frames']} estimates"
    if not np.isfinite(sc["rmse_m_s"]):
        return f"scored after {skip_s:.3g} s: no observable estimate to score ({obs})"
    return (f"scored after {skip_s:.3g} s: RMSE {sc['rmse_m_s']:.4f} m/s, median |error| "
            f"{sc['median_abs_error_m_s']:.4f} m/s, {obs}")


def never_observable_reason(ds: xr.Dataset) -> str | None:
    """One sentence saying why a run's v̂ is never observable, or None where it is observable somewhere.

    Computed from what the run stores: its forward acceleration ``accel`` (m/s²) low-passed as the
    readout low-passes it (a zero-phase Butterworth of the configuration's ``readout.order`` at
    ``readout.cutoff_hz``) against ``readout.accel_min_m_s2``; else the expansion rates ``r``
    (none finite: the fields measured nothing); else ``v_std`` against ``readout.max_std_m_s``.
    """
    if "observable" not in ds or bool(ds.observable.values.astype(bool).any()):
        return None
    try:
        ro = json.loads(ds.attrs.get("config", "{}")).get("readout", {})
    except (TypeError, ValueError):
        ro = {}
    accel_min = float(ro.get("accel_min_m_s2", 0.03))
    max_std = float(ro.get("max_std_m_s", 0.1))
    t, a = ds.time.values.astype(float), ds.accel.values.astype(float)
    ok = np.isfinite(a)
    a_lp = a[ok]
    if ok.sum() > 12 and t.size > 1:
        from scipy import signal

        fs = (t.size - 1) / float(t[-1] - t[0])
        wn = float(ro.get("cutoff_hz", 1.0)) / (fs / 2)
        if 0 < wn < 1:
            a_lp = signal.filtfilt(*signal.butter(int(ro.get("order", 2)), wn), a[ok], padlen=min(ok.sum() - 1, 12))
    peak = float(np.max(np.abs(a_lp))) if a_lp.size else 0.0
    if peak < accel_min:
        return (f"never observable: the camera's forward acceleration never exceeded the readout's accel_min "
                f"({accel_min:g} m/s²; at most {peak:.3f} m/s² here, low-passed at "
                f"{float(ro.get('cutoff_hz', 1.0)):g} Hz) — speed cannot be told from vision while it does not "
                f"change; v̂ is NaN throughout")
    if "r" in ds and not np.isfinite(ds.r.values).any():
        return ("never observable: no receptive field measured an expansion rate (r is NaN throughout: too "
                "little texture in view, or the flow failed) — without it vision says nothing of speed; v̂ is NaN "
                "throughout")
    std = ds.v_std.values.astype(float) if "v_std" in ds else np.full(1, np.nan)
    low = float(np.nanmin(std)) if np.isfinite(std).any() else float("nan")
    return (f"never observable: the posterior std of v̂ never fell below the readout's max_std ({max_std:g} m/s; "
            f"at best {low:.3f} m/s) — the forward acceleration (up to {peak:.3f} m/s², low-passed) and the "
            f"expansion rates were too weak or too noisy to fix the speed; v̂ is NaN throughout")


#: Each readout in words, for figure captions (each front end's: lobula.front_ends.FrontEnd.description).
READOUT_WORDS = {"kalman": "Kalman filter fusing the expansion rates with the forward acceleration a",
                 "median": "median over fields of the expansion ratio (the paper's readout)"}


def describe_run(ds: xr.Dataset) -> str:
    """The run's front end, then (on a second line) its readout and filter, in words (from ``ds.attrs``)."""
    fe, ro = str(ds.attrs.get("front_end", "?")), str(ds.attrs.get("readout", "?"))
    filt = str(ds.attrs.get("filter", "?"))
    when = ("zero-phase: offline, each estimate uses the whole record" if filt.startswith("zero-phase") else
            "causal: online, each estimate uses only what came before it" + (
                " and a fixed lag" if "fixed lag" in filt else "") if filt.startswith("causal") else filt)
    words = FRONT_ENDS[fe].description if fe in FRONT_ENDS else fe
    return f"front end: {words}\nreadout: {READOUT_WORDS.get(ro, ro)} ({when})"


def velocity_figure(ds: xr.Dataset, skip_s: float | None = None, title: str | None = None):
    """The figure of a velocity run: v̂ with its ±2σ band against truth (top), forward acceleration (bottom).

    ds: the velocity Dataset (:func:`estimate_velocity`, or its NetCDF read back); ``v_std`` is the
    1σ posterior std (m/s), drawn as v̂ ± 2·v_std. skip_s: seconds not scored (default
    :func:`scoring_skip`, as `lobula velocity` prints it); the title's numbers are :func:`score_line` of
    :func:`score` on ``ds`` with it, the console's numbers, after ``title`` (default "forward velocity");
    below them the front end, readout and filter in words (:func:`describe_run`).
    Returns the matplotlib Figure.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    skip = scoring_skip(ds) if skip_s is None else float(skip_s)
    t = ds.time.values
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6.2), sharex=True, layout="constrained",
                                  gridspec_kw=dict(height_ratios=[3, 1]))
    v, s = ds.v_hat.values, ds.v_std.values
    if np.isfinite(s).any():
        ax.fill_between(t, v - 2 * s, v + 2 * s, color="m", alpha=0.18, lw=0, label="±2σ (2 × v_std)")
    ax.plot(t, v, color="m", lw=2.2, label="v̂ estimate", zorder=3)
    if "v_true" in ds:
        # Drawn over v̂, thinner and dashed, so it stays visible where the two agree.
        ax.plot(t, ds.v_true.values, color="k", ls="--", lw=1.2, label="truth", zorder=4)
    unobs = ~ds.observable.values.astype(bool)
    if unobs.any():
        ax.fill_between(t, 0, 1, where=unobs, transform=ax.get_xaxis_transform(), color="0.85", lw=0,
                        label="unobservable (std too large: no v̂)")
    if skip > 0 and "v_true" in ds:
        ax.axvspan(t[0], t[0] + skip, color="0.5", alpha=0.08, lw=0, label=f"not scored (first {skip:.3g} s)")
    ax.axhline(0, color="0.4", lw=0.8, zorder=1)
    ax.set_ylabel("forward velocity (m/s)\nbelow 0: moving backwards")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    sc = score(ds, skip)
    # A caller's title gets a line of its own: with the scores after it, it ran past the figure's edge.
    head = f"{title}\n{score_line(sc, skip)}" if title else f"forward velocity: {score_line(sc, skip)}"
    fig.suptitle(f"{head}\n{describe_run(ds)}", fontsize=9)
    ax2.plot(t, ds.accel.values, color="tab:blue", lw=1, label="a")
    ax2.axhline(0, color="0.4", lw=0.8)
    src = str(ds.accel.attrs.get("source", ds.attrs.get("acceleration_source", "")))
    where = ("the IMU's accelerometer, gravity and bias removed" if src.startswith("accelerometer")
             else src or "unknown source")
    ax2.set_title(f"a: forward acceleration (m/s², from {where}), the readout's input beside the flow",
                  fontsize=8, loc="left")
    ax2.set_ylabel("a (m/s²)")
    ax2.set_xlabel("time (s)")
    return fig


def plot_velocity(ds: xr.Dataset, path, title: str | None = None, skip_s: float | None = None):
    """Write :func:`velocity_figure` of ``ds`` as a PNG (atomically); returns ``path``."""
    import matplotlib.pyplot as plt

    from .store import save_figure

    fig = velocity_figure(ds, skip_s, title)
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def apply_velocity_options(cfg, args):
    """Apply the velocity options shared by `velocity` and `compare` (absent or None: unchanged)."""

    opt = lambda name: getattr(args, name, None)
    if opt("filter"):
        cfg.readout.filter = args.filter
    if opt("gap"):
        cfg.flow.gap = args.gap
    if opt("field_size"):
        cfg.fields.size_deg = args.field_size
    for name in ("dis_preset", "dis_grid_px"):
        if opt(name) is not None and cfg.front_end != "dis":
            raise ValueError(f"--{name.replace('_', '-')} sets the DIS flow, but the front end is "
                             f"{cfg.front_end}; drop it or use --front-end dis")
    if opt("dis_preset"):
        cfg.flow.dis_preset = args.dis_preset
    if opt("dis_grid_px") is not None:
        if args.dis_grid_px < 0:
            raise ValueError(f"--dis-grid-px must be ≥ 0 (0: the preset's finest level), got {args.dis_grid_px}")
        cfg.flow.dis_grid_px = args.dis_grid_px
    if opt("epipole"):
        cfg.epipole = args.epipole
    if opt("accel_from_truth"):
        cfg.accel_from_truth = True
    if opt("gyro_bias_from_vision"):
        cfg.gyro_bias_from_vision = True
    if opt("lag") is not None:
        cfg.readout = replace(cfg.readout, lag_s=args.lag)  # validated there (causal kalman readout only)
    if opt("accel_scale_error") is not None:
        cfg.readout = replace(cfg.readout, accel_scale_error=args.accel_scale_error)  # validated there
        if cfg.readout.method != "kalman":
            raise ValueError("--accel-scale-error widens the kalman readout's posterior std; the paper's "
                             "median readout (--paper) states none: drop one of them")
    e = cfg.emd
    if opt("dphi") or opt("drho"):
        e.lattice = replace(e.lattice, dphi_deg=opt("dphi") or e.lattice.dphi_deg,
                            drho_deg=opt("drho") or e.lattice.drho_deg)
    if opt("tau"):
        e.emd = replace(e.emd, tau_s=args.tau)
    front = get_front_end(cfg.front_end)
    if opt("mean_removal"):
        if "emd" not in front.sections:   # the option sets VelocityConfig.emd
            raise ValueError(f"--mean-removal sets the EMD front end's columns, but the front end is {cfg.front_end}; "
                             f"drop it or use --front-end emd")
        e.surround, e.photoreceptor = mean_removal(args.mean_removal, e.photoreceptor)
    if opt("emd_gaze"):
        if front.derotation != "gaze":
            raise ValueError(f"--emd-gaze sets the EMD front end's gaze, but the front end is {cfg.front_end} (the flow "
                             f"front ends derotate their flow exactly); drop it or use --front-end emd")
        e.gaze = args.emd_gaze
    if opt("emd_calibration"):
        from experiments.calibrate import read_calibration
        e.calibration, e.latency_s = read_calibration(args.emd_calibration)
    return cfg


def _velocity_config(args):
    cfg = VelocityConfig.paper(args.front_end, args.filter) if args.paper else VelocityConfig(front_end=args.front_end)
    return apply_velocity_options(cfg, args)


def run_velocity(args) -> int:
    from .info import open_footage_from_args
    from .store import write_netcdf

    footage = open_footage_from_args(args)
    cfg = _velocity_config(args)
    flo_files = None
    if args.front_end == "flo":
        if not args.flo:
            raise ValueError("--front-end flo needs --flo FILE_OR_DIR")
        p = Path(args.flo)
        flo_files = sorted(p.glob("*.flo")) if p.is_dir() else [p]
    units = FloUnits(args.flo_units, args.flo_gap, *args.flo_size)
    ds = estimate_velocity(footage, cfg, progress=not args.quiet, flo_files=flo_files, flo_units=units)
    write_netcdf(ds, args.out)
    # Short clips (the 1.2 s D435i sample) are scored after at most a quarter of their length.
    skip = scoring_skip(ds, args.skip)
    sc = score(ds, skip)
    print(f"wrote {args.out}: {ds.sizes['time']} frames x {ds.sizes['field']} fields "
          f"[{ds.attrs['front_end']}, {ds.attrs['readout']} readout, {ds.attrs['filter']}; "
          f"acceleration: {ds.attrs['acceleration_source']}]")
    e = ds.epipole_x.values[-1], ds.epipole_y.values[-1]
    print(f"epipole: ({np.degrees(np.arctan(e[0])):+.2f}°, {np.degrees(np.arctan(e[1])):+.2f}°) from the principal point")
    print(f"observable: {100 * float(ds.observable.mean()):.1f} % of all {ds.sizes['time']} estimates")
    if sc:
        print(score_line(sc, skip))
    why = never_observable_reason(ds) if ds.sizes["time"] >= 3 else None
    if why:
        print(why)
    if ds.sizes["time"] < 3:
        med = np.nanmedian(ds.r.values, axis=1)
        print("too few flows for a velocity readout; median r̄ over fields per flow (1/s): "
              + ", ".join(f"{x:+.3f}" for x in med))
    if args.plot:
        plot_velocity(ds, args.plot, skip_s=skip)
        print(f"wrote {args.plot}")
    return 0


def add_parser(subparsers):
    """Register `lobula velocity`'s camera options (:func:`experiments.parsers.add_velocity_parser`, built without
    importing this module; experiments.velocity_command adds the compound eye's)."""
    from .parsers import add_velocity_parser

    return add_velocity_parser(subparsers)
