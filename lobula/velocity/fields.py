"""The camera's front half of the velocity pipeline: each flow pair derotated by the gyro, its epipole
estimated and its expansion pooled into the receptive fields (:class:`FieldPooling`), over a whole
footage (:func:`field_rates`) or one pair at a time (:class:`lobula.velocity.VelocityEstimator`)."""
from __future__ import annotations

import time as _time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm.auto import tqdm

from lobula.config import VelocityConfig
from lobula.epipole import HEADING_POINTS, EpipoleEstimator, HeadingBiasEstimator, derotate_finite, turn
from lobula.flow import FlowSample
from lobula.front_ends import FrontEndInput, get_front_end
from lobula.imu import HEADING_FIT_BIAS_PRIOR, GyroAttitude, gyro_bias, orientation_from_gyro
from lobula.readers.core import Footage, FootageError
from lobula.readers.flo import FloUnits
from lobula.readout import MaterialRates
from lobula.receptive_field import MaterialFields, ReceptiveFields, gap_correction, pool_fields, tile_fields
from lobula.rolling_shutter import global_shutter_flow, pixel_delays
from lobula.threads import threaded


@dataclass
class FieldRates:
    """What the front end and fields give the readout, time-major.

    t (n,) s; r, r2 (n, F) at fixed pixels; epipole (n, 2) normalised; timings: seconds per
    stage; material: the rates along the content (ṙ̄ as Dr/Dt, lobula.readout.MaterialRates),
    None where the front end gives no consecutive pairs (flo, emd) or fields.material is off.
    gyro_residual: (t (m,) s, residual (m, 3) rad/s, rate (m, 3) rad/s): on non-overlapping
    pairs, the gyro bias the derotated flow says and the gyro's rate over the pair
    (lobula.imu.vision_gyro_bias's measurements and regressors), or None.
    heading_bias: (t (m,) s, bias (m, 3) rad/s, std (m, 3) rad/s): the gyro bias the heading and
    bias fit (lobula.epipole.HeadingBiasEstimator) holds after each pair, known at the pair's
    second frame t; or None (no gyro, no estimated epipole).
    known: (n,) s, when each row's frames are all in (its pair's second frame), or None where the
    front end does not say (flo, emd). span: s, how long each row's rates average over (a pair's two
    frames' interval; None: one frame interval, the flo and EMD front ends' rates at frames).
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
    span: float | None = None


@dataclass
class PooledPair:
    """One flow pair pooled (:meth:`FieldPooling.push`).

    t: s, the row's time stamp; known: s, when its frames were all in (the pair's second frame); span: s, the
    pair's two frames' interval, over which its flow averages the motion;
    r, r2: (F,) 1/s and 1/s²; epipole: (2,) normalised; material: the material fields' (r̄, r²̄, ṙ̄)
    (each (F,)) of the pair ``stagger // 2`` before this one, or None; heading_bias: (t s, bias (3,)
    rad/s, std (3,) rad/s) of the heading and bias fit after this pair, or None; residual: the pair's
    (t s, bias (3,) rad/s, rate (3,) rad/s) for lobula.imu.vision_gyro_bias, or None.
    """

    t: float
    known: float
    r: np.ndarray
    r2: np.ndarray
    epipole: np.ndarray
    material: tuple | None = None
    heading_bias: tuple | None = None
    residual: tuple | None = None
    span: float | None = None


def slerp_orientations(time_s: np.ndarray, q: np.ndarray, t) -> np.ndarray:
    """Orientations (k, 3, 3) at times t (k,) s, slerped between the samples' q (n, 3, 3) at time_s (n,) s.

    Times outside the samples take the edge sample's orientation.
    """
    time_s = np.asarray(time_s, float)
    t = np.clip(np.atleast_1d(np.asarray(t, float)), time_s[0], time_s[-1])
    if len(time_s) < 2:
        return np.repeat(q[:1], len(t), 0)
    k0 = np.clip(np.searchsorted(time_s, t, side="left") - 1, 0, len(time_s) - 2)
    k1 = k0 + 1
    span = time_s[k1] - time_s[k0]
    frac = np.clip(np.where(span > 0, (t - time_s[k0]) / np.where(span > 0, span, 1.0), 0.0), 0.0, 1.0)
    q0, q1 = q[k0], q[k1]
    step = Rotation.from_matrix(np.einsum("kji,kjl->kil", q0, q1)).as_rotvec() * frac[:, None]
    return q0 @ Rotation.from_rotvec(step).as_matrix()


def attitude_track(time_s: np.ndarray, gyro: np.ndarray, causal: bool):
    """A function t (k,) -> camera orientations (k, 3, 3) (camera → the first sample's frame)
    from the bias-corrected integrated gyro (lobula.imu.orientation_from_gyro), slerped between samples."""
    q = orientation_from_gyro(time_s, gyro, causal)
    return lambda t: slerp_orientations(time_s, q, t)


#: s: how long the heading fit must have counted pairs, since it was (re)started, before the motion of its
#: heading is read (:class:`lobula.receptive_field.MaterialFields`): before, its heading moves as it learns.
#: With the heading let walk (VelocityConfig.heading_walk 0.15) on development drones and road vehicles
#: (seeds 100-105), reading it from the first counted pair leaves a car braking at once 2.6 m/s off offline,
#: ±2σ 0 %; 0.5 s and 1 s read it 0.22 / 0.18 (±2σ 100 %).
HEADING_SETTLE_S = 1.0

#: pixels per pair for the residual-rotation fit: a 3-parameter fit (with a 2-parameter
#: epipole) needs far fewer than the image holds, and it runs on every gap-th pair.
RESIDUAL_POINTS = 1500


class FieldPooling:
    """The state carried from one flow pair to the next: the epipole (or the joint heading and
    gyro-bias fit), the gyro's attitude that derotates, the material fields' buffer, and which of the
    last pairs held a fast turn (``VelocityConfig.saccade_gate_deg_s``: their rates are NaN and the
    heading is fitted afresh after them, and after every ``heading_reset_deg`` turned), and, with
    ``heading_walk``, how long the fit has counted pairs (the material fields read each end about its own
    heading once that is HEADING_SETTLE_S).

    Parameters
    ----------
    camera : lobula.camera.PinholeCamera
    config : VelocityConfig
    fields : ReceptiveFields
    live : bool
        The front end yields each pair's dense flow in order (dis, farneback), which the material
        fields and the heading and bias fit need.
    attitude : callable, optional
        t (k,) s -> camera → reference rotations (k, 3, 3): the plain gyro attitude (still-camera bias
        removed), or None (no gyro, or ``config.derotate`` off).
    imu_time, gyro : ndarray, (m,) and (m, 3), optional
        s and rad/s: the gyro's samples, for the heading and bias fit's own attitude
        (:class:`lobula.imu.GyroAttitude`; frame by frame it is extended as samples come).
    still_bias : callable, optional
        t1 s -> (bias (3,) rad/s, std (3,) or scalar rad/s): the still-camera estimate (lobula.imu.gyro_bias,
        with the heading fit's prior) at the first gyro sample at or after t1; with it and ``attitude``
        and ``config.epipole`` "estimate" the heading and the gyro's bias are fitted jointly.
    residual_bias : callable, optional
        With ``config.gyro_bias_from_vision``: t s -> (3,) rad/s, the still-camera bias the derotation removed;
        each gap-th pair's residual rotation (:func:`residual_rate`) is then fitted.
    lens_maps : tuple of ndarray, optional
        (map_x, map_y) px: where a resampled lens's pinhole pixels lie on the raw sensor, whose rows set a rolling
        shutter's delays (``camera.rolling_shutter_s``, :mod:`lobula.rolling_shutter`; each pair's flow is put back
        on the frames' times first).
    """

    def __init__(self, camera, config: VelocityConfig, fields: ReceptiveFields, live: bool, attitude=None,
                 imu_time=None, gyro=None, still_bias=None, residual_bias=None, lens_maps=None):
        self.camera, self.config, self.fields = camera, config, fields
        x, y = fields.x, fields.y
        # A rolling shutter's rows are exposed at their own times: each pair's flow is put back on the frames'
        # times for the rotation before anything reads it (lobula.rolling_shutter).
        self.delays = (pixel_delays(y, camera, camera.rolling_shutter_s, lens_maps)
                       if attitude is not None and getattr(camera, "rolling_shutter_s", 0.0) > 0 else None)
        # ~5,000 pixels are plenty for a 2-parameter fit, whatever the image size.
        self.est = EpipoleEstimator(x, y, stride=max(1, int(np.sqrt(camera.width * camera.height / 5000))))
        self.attitude = self.plain_attitude = attitude
        self.still_bias = still_bias
        self.residual_bias = residual_bias
        self.fitted = False
        if live and attitude is not None and config.epipole == "estimate" and still_bias is not None:
            # The heading and the gyro's bias are fitted jointly (lobula.epipole.HeadingBiasEstimator)
            # and the fields' attitude follows the bias and the scale error E learned so far
            # (lobula.imu.GyroAttitude); the pre-warp keeps the plain attitude.
            # E (VelocityConfig.gyro_scale_prior): the suite's rotation family (±5°, to 1.5 Hz, seeds
            # 0-2) 0.011 / 0.018 m/s zero-phase / causal with it, 0.016 / 0.039 without; a camera turning
            # ±10° at up to 2 Hz with a realistic IMU reads v̂ 40-60 % slow without it (zero-phase 0.106 m/s,
            # zero estimator 0.20, ideal IMU 0.012) and 0.013 with it.
            b, s = still_bias(None)
            self.attitude = GyroAttitude(imu_time, gyro, b)
            self.est = HeadingBiasEstimator(x, y, b, s, scale_std=config.gyro_scale_prior or None,
                                            stride=max(1, int(np.sqrt(camera.width * camera.height / HEADING_POINTS))))
            self.fitted = True
        if config.heading_walk > 0 and not self.fitted:
            raise ValueError("heading_walk lets the heading of the joint heading-and-bias fit walk, and that fit runs only "
                             "with a gyro, an estimated epipole and a flow front end that gives every pair (dis, "
                             "farneback); this run has no such fit: drop --heading-walk (VelocityConfig.heading_walk)")
        self.stagger = config.readout.difference_frames
        # A heading let walk moves over a material difference: each end is then read about its own, unless
        # the readout takes the heading's motion from the accelerometer instead (heading_motion).
        self.material = (MaterialFields(fields, self.stagger, gap_correction=config.fields.gap_correction,
                                        own_heading=config.heading_walk > 0 and not config.heading_motion)
                         if config.fields.material and live else None)
        self._t_fit = None  # the last pair the heading fit took (s): its walk since
        self._counting_since = None  # the first pair the fit counted since it was (re)started (s)
        self.count = 0
        self._e_seen = np.zeros(2)  # the epipole the last pair saw
        self._turned = False  # a fast turn since the heading was last fitted
        self._fast = deque(maxlen=self.stagger + 1)  # the last pairs' fast_turn flags (a material difference's span)

    def _settled(self, t: float) -> bool:
        """Whether the heading fit has counted pairs for HEADING_SETTLE_S by time t (s); a heading that is
        not estimated (the principal point) is settled."""
        if self.config.epipole != "estimate":
            return True
        if self.est.n_frames == 0:  # not started, or started afresh (forget_heading, which also clears the clock)
            return False
        if self._counting_since is None:
            self._counting_since = t
        return t - self._counting_since >= HEADING_SETTLE_S

    def extend_gyro(self, time_s: np.ndarray, gyro: np.ndarray) -> None:
        """Take in more gyro samples (k,) s and (k, 3) rad/s, for the fit's own attitude."""
        if self.fitted:
            self.attitude.extend(time_s, gyro)

    def push(self, s: FlowSample) -> PooledPair:
        """Derotate, locate the epipole in and pool pair ``s``; returns its :class:`PooledPair`."""
        config, est, attitude = self.config, self.est, self.attitude
        if self.delays is not None:
            s = FlowSample(s.index, s.t0, s.t1, global_shutter_flow(self.fields.x, self.fields.y, s.flow, s.t0, s.t1,
                                                                    self.delays, self.plain_attitude))
        flow, q = s.flow, (None, None, None)
        hb = res = None
        if attitude is not None:
            # camera → reference at t0, t1, middle: the fixed-pixel rates (inside pool_fields, on
            # the pixels it pools), the epipole and the material fields all derotate exactly
            # (finite rotation over the gap) into the middle orientation.
            q = attitude(np.array([s.t0, s.t1, s.t_mid]))
        fast = (attitude is not None and config.saccade_gate_deg_s is not None
                and fast_turn(np.linspace(s.t0, s.t1, config.flow.gap + 1), attitude, config.saccade_gate_deg_s))
        self._fast.append(fast)
        if config.epipole == "estimate" and fast:
            e = self._e_seen  # the flow of a fast turn is not read; the heading is re-learned after it
            self._turned = True
            if self.fitted:
                hb = (s.t1, est.bias, est.bias_std)
        elif config.epipole == "estimate":
            if self._turned or (q[2] is not None and config.heading_reset_deg is not None
                                and np.degrees(_angle(est.anchor, q[2])) > config.heading_reset_deg):
                est.forget_heading(q[2], self._e_seen)
                self._turned = False
                self._counting_since = None
            if self.fitted and config.heading_walk > 0 and self._t_fit is not None:
                est.walk_heading(config.heading_walk ** 2 * max(s.t1 - self._t_fit, 0.0))
            self._t_fit = s.t1
            if attitude is not None:
                sub = s.flow[:, ::est.stride, ::est.stride].reshape(2, -1)
                pts = derotate_finite(est.x, est.y, sub, s.dt, q[2].T @ q[0], q[2].T @ q[1])
                if self.fitted:
                    if config.readout.filter == "causal":  # the still-camera estimate so far, as it accrues
                        est.set_bias_prior(*self.still_bias(s.t1))
                    c_app, w_bar = attitude.applied_correction(s.t0, s.t1)
                    e = est.update(None, points=pts, attitude=q[2], applied_bias=c_app, rate=w_bar)
                    attitude.bias, attitude.scale = est.bias, est.scale
                    hb = (s.t1, est.bias, est.bias_std)
                else:
                    e = est.update(None, points=pts, attitude=q[2])
            else:
                e = est.update(flow)
        else:
            e = np.zeros(2)
        r, r2 = pool_fields(flow, self.fields, e, pooling=config.fields.pooling,
                            turns=None if q[0] is None else (q[2].T @ q[0], q[2].T @ q[1], s.dt))
        if config.fields.gap_correction:
            r, r2 = gap_correction(r, r2, s.dt)
        self._e_seen = np.asarray(e, float)
        m = (self.material.update(s.t0, s.dt, s.flow, e, *q,
                                  settled=self._settled(s.t1) if self.material.own_heading else True)
             if self.material is not None else None)
        if fast:
            r, r2 = np.full_like(r, np.nan), np.full_like(r2, np.nan)
        if m is not None and any(self._fast):
            m = tuple(np.full_like(x, np.nan) for x in m)
        if self.residual_bias is not None and self.count % config.flow.gap == 0 and not fast:
            # Measured against the plain attitude (the still-camera bias removed), as vision_gyro_bias models it.
            qp = self.plain_attitude(np.array([s.t0, s.t1]))
            res = residual_rate(self.camera, s, qp[0].T @ qp[1], e, self.residual_bias(s.t_mid))
        self.count += 1
        return PooledPair(s.t_mid if config.timestamps == "mid" else s.t0, s.t1, r, r2, e, m, hb, res, s.dt)


def _angle(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """The angles (rad, (...)) between orientations q0 and q1 (..., 3, 3)."""
    turn = np.einsum("...ji,...jl->...il", q0, q1)  # q0ᵀ q1
    return np.arccos(np.clip((np.trace(turn, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


def fast_turn(times: np.ndarray, attitude, gate_deg_s: float) -> bool:
    """Whether the camera turned faster than ``gate_deg_s`` (°/s) between two consecutive ``times`` (k,) s
    (a pair's frames), its orientation given by ``attitude`` (times -> (k, 3, 3), camera → reference).

    The flow of a pair that holds such a turn is not measured: the image moves by tens of pixels a
    frame, past what the flow resolves, blurs, and turns onto other surfaces (a fly's body saccade,
    20-90° in 50-100 ms; a whip pan).
    """
    q = attitude(times)
    return bool(np.any(np.degrees(_angle(q[:-1], q[1:])) > gate_deg_s * np.diff(times)))


def residual_rate(camera, s: FlowSample, r01: np.ndarray, e: np.ndarray, b_then: np.ndarray):
    """(t_mid, b (3,) rad/s, ω (3,) rad/s): the gyro bias this pair's flow says, b0(t_mid) − δω,
    and the gyro's mean rate over the pair (the regressor of its scale-factor errors).

    The raw flow is derotated exactly (each point's second ray turned into the first
    frame's orientation by the gyro's r01) and lobula.depth_motion.refine_motion fits the
    rotation δω still in it jointly with the epipole (started at the running estimate e).
    The gyro read ω + b and the derotation removed ω + b − b0 (b_then: b0 at the pair's middle,
    (3,) rad/s), so the flow is left turning by −(b − b0): δω = b0 − b.
    """
    from lobula.depth_motion import refine_motion  # torch-based; only --gyro-bias-from-vision needs it

    x, y = camera.normalised_grid(np.float64)
    f = np.asarray(s.flow, np.float64)
    x1, y1 = turn(r01, x + f[0] * s.dt, y + f[1] * s.dt)
    fd = np.stack([(x1 - x) / s.dt, (y1 - y) / s.dt])
    _, dw, _ = refine_motion(fd, camera, tuple(e), n_points=RESIDUAL_POINTS)
    return s.t_mid, b_then - dw, Rotation.from_matrix(r01).as_rotvec() / s.dt


def material_rates(items: list, n: int, n_fields: int, stagger: int) -> MaterialRates:
    """Place each difference (returned at pair k, over k − s … k) at its centre k − s/2."""
    out = [np.full((n, n_fields), np.nan) for _ in range(3)] + [np.full((n, n_fields, 2), np.nan)]
    h = stagger // 2
    for k, item in enumerate(items):
        if item is not None:
            for arr, val in zip(out, item):
                arr[k - h] = val
    return MaterialRates(*out)


def footage_pooling(footage: Footage, config: VelocityConfig, fields: ReceptiveFields, live: bool) -> FieldPooling:
    """The :class:`FieldPooling` of a whole footage: its gyro's attitude and still-camera bias from all samples."""
    causal = config.readout.filter == "causal"
    imu = footage.imu
    gyro = imu.gyro if (imu is not None and imu.gyro is not None) else None
    attitude = attitude_track(imu.time_s, gyro, causal) if (gyro is not None and config.derotate) else None
    still_at = residual = None
    if attitude is not None:
        # The fit's own bias prior is its regulariser against the heading–bias confound, narrower than
        # the data sheet's spread (lobula.imu.HEADING_FIT_BIAS_PRIOR).
        fit_prior = min(HEADING_FIT_BIAS_PRIOR, np.radians(config.gyro_bias_prior_deg_s))
        b_still, s_still = gyro_bias(imu.time_s, gyro, causal=causal, with_std=True, prior=fit_prior)

        def still_at(t1):
            k = 0 if t1 is None else min(int(np.searchsorted(imu.time_s, t1)), len(b_still) - 1)
            return b_still[k], s_still[k]
        if config.gyro_bias_from_vision:
            # The gyro bias the derotation removed (still-camera estimate), to add back to what vision finds left.
            b0 = gyro_bias(imu.time_s, gyro, causal=causal)
            residual = lambda t: np.array([np.interp(t, imu.time_s, b0[:, k]) for k in range(3)])
    try:
        return FieldPooling(footage.camera, config, fields, live, attitude,
                            None if gyro is None else imu.time_s, gyro, still_at, residual,
                            getattr(footage, "lens_maps", None))
    except ValueError as exc:  # an option this footage cannot serve: name the footage
        raise ValueError(f"{footage.path}: {exc}") from None


def field_rates(footage: Footage, config: VelocityConfig, flo_files: list[Path] | None = None,
                flo_units: FloUnits | None = None, progress: bool = True) -> FieldRates:
    """Run the front end over the footage (streamed) and pool every flow into the fields.

    The front end (:func:`lobula.front_ends.get_front_end` of ``config.front_end``) yields each pair's
    flow, which :class:`FieldPooling` derotates and pools, or the fields' rates it pooled itself (its
    ``yields``). flo_files, flo_units: the precomputed flow of the ``flo`` front end.
    """
    front = get_front_end(config.front_end)
    fields = tile_fields(footage.camera, config.fields)
    timings = dict(read=0.0, flow=0.0, fields=0.0)
    pooling = footage_pooling(footage, config, fields, front.live)
    stream = front.open(FrontEndInput(footage, config, fields, timings, pooling.plain_attitude, flo_files,
                                      flo_units, ahead=threaded))
    if front.yields == "fields":
        return _pooled_field_rates(stream, config, fields, timings, progress)
    rows = []
    bar = tqdm(total=stream.total, desc=f"{config.front_end} flow → fields", unit="frame", disable=not progress,
               leave=False, mininterval=2)
    for s in stream.samples:
        t1 = _time.perf_counter()
        rows.append(pooling.push(s))
        timings["fields"] += _time.perf_counter() - t1
        bar.update(1)
    bar.close()
    if not rows:
        raise FootageError(f"{footage.path}: too few frames for a flow pair "
                           f"({len(footage)} frames, gap {config.flow.gap})")
    return rates_from_rows(rows, fields, timings, pooling, front.live)


def rates_from_rows(rows: list[PooledPair], fields: ReceptiveFields, timings: dict, pooling: FieldPooling,
                    live: bool) -> FieldRates:
    """The :class:`FieldRates` of pooled pairs in order."""
    stack = lambda items: tuple(np.array([g[i] for g in items]) for i in range(3)) if items else None
    return FieldRates(np.array([p.t for p in rows]), np.array([p.r for p in rows]), np.array([p.r2 for p in rows]),
                      np.array([p.epipole for p in rows]), timings, fields,
                      (material_rates([p.material for p in rows], len(rows), fields.n_fields, pooling.stagger)
                       if pooling.material is not None else None),
                      stack([p.residual for p in rows if p.residual is not None]),
                      stack([p.heading_bias for p in rows if p.heading_bias is not None]),
                      np.array([p.known for p in rows]) if live else None,
                      float(np.median([p.span for p in rows])) if rows else None)


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
