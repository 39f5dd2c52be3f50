"""The accelerometer's and gyro's side of the velocity pipeline on a whole footage: the gyro bias the
attitude removes gravity with, the forward acceleration at the flow's times, the turn rate, and the
priors of the start's acceleration."""
from __future__ import annotations

import numpy as np

from lobula.config import VelocityConfig
from lobula.imu import (GRAVITY_WINDOW_S, fused_gyro_bias, gravity_free_acceleration, gravity_time_constant, gyro_bias,
                        resample_to, turn_rate, vision_gyro_bias)
from lobula.readout import acceleration_heading
from lobula.readers.core import Footage, FootageError, acceleration_from_truth

from .fields import FieldRates


def frame_interval(times: np.ndarray) -> float:
    """s: the frames' interval, the median of ``times``' (n,) s differences."""
    return float(np.median(np.diff(times)))


def gyro_bias_track(footage: Footage, rates: FieldRates, causal: bool, prior: float):
    """The gyro bias and its std ((n, 3) rad/s each, at the IMU samples) for the attitude that removes
    gravity and for the readout's drift std, and what they come from; None without a gyro or a
    flow-fitted bias (then the still-camera estimate alone serves).

    With ``gyro_bias_from_vision`` (``rates.gyro_residual``): the flow's residual rotation
    (lobula.imu.vision_gyro_bias), started from the still-camera estimate. Else the heading and
    bias fit's estimate (``rates.heading_bias``) fused with the still-camera one
    (lobula.imu.fused_gyro_bias). ``prior`` (rad/s): the bias's std before the record measures
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




TRUTH_ACCEL_OFFSET_M_S2 = 0.01  # prior std of the offset of an acceleration derived from ground truth


#: m/s²: prior std of the platform's acceleration at the record's start, which the online gravity
#: reference (lobula.imu.online_gravity, set over the first GRAVITY_INIT_S) takes in: 0.1 g,
#: a priori (a walking or handheld camera's or a road vehicle's acceleration mostly stays under it).
START_ACCEL_PRIOR_M_S2 = 1.0
#: m/s²: the same where the first flow pair already shows the camera moving (:func:`start_accel_prior`):
#: 0.3 g, a platform braking or speeding up hard (a car braking, a drone) — one at rest mostly starts gently.
START_ACCEL_PRIOR_MOVING_M_S2 = 3.0


def offline_gravity_error(duration_s: float, v_prior_m_s: float) -> float:
    """m/s²: prior std of the offline gravity reference's error on a record ``duration_s`` long.

    Offline gravity is the mean specific force over up to GRAVITY_WINDOW_S of record, which also holds the
    platform's mean acceleration Δv/T there: an offset of up to ``v_prior_m_s`` (m/s) over that span
    (at least 1 s).
    """
    return v_prior_m_s / max(min(GRAVITY_WINDOW_S, duration_s), 1.0)


#: 1/s: fields that all read less than this have not responded yet (a correlator started at rest reads ~1e-8 on
#: its first frame): no camera's expansion, still or moving, is that small against the flow's noise (~1e-3 1/s
#: at rest)
NO_RESPONSE_1_S = 1e-6


def responding(r: np.ndarray, min_fields: int = 3) -> np.ndarray:
    """Frames (bool, (n,)) whose fields, r (n, F) 1/s, have read something: at least ``min_fields`` finite
    and one of them at least :data:`NO_RESPONSE_1_S` in size."""
    r = np.asarray(r, float)
    with np.errstate(invalid="ignore"):
        big = (np.abs(np.nan_to_num(r)) >= NO_RESPONSE_1_S).any(1)
    return (np.isfinite(r).sum(1) >= min_fields) & big


def start_accel_prior(r: np.ndarray, min_fields: int = 3) -> float:
    """Prior std (m/s²) of the start acceleration the online gravity reference takes in: wider where
    the camera is seen moving at the start.

    r (n, F) 1/s: the fields' expansion rates; the first frame :func:`responding` decides (``min_fields``
    finite fields, past a front end's first frames before it responds: a correlator started at rest reads
    ~1e-8 1/s on its first frame, which judged alone would start every run with the resting prior). Moving
    means the fields' signed median r̄ stands clear of its standard error
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
    first = np.flatnonzero(responding(r, min_fields))
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
                     bias: np.ndarray | None = None, orientation: np.ndarray | None = None,
                     window_s: float | None = None) -> tuple[np.ndarray, str]:
    """Forward acceleration (m/s²) at ``times`` and a label saying where it came from; arguments as
    :func:`accels_at` takes them, ``window_s`` one of its spans."""
    (a3,), label = accels_at(footage, times, config, (window_s,), bias, orientation)
    return (a3 if a3.ndim == 1 else a3[:, 2]), label


def accels_at(footage: Footage, times: np.ndarray, config: VelocityConfig, windows_s: tuple,
              bias: np.ndarray | None = None, orientation: np.ndarray | None = None) -> tuple[list, str]:
    """The acceleration at ``times``, averaged over each span of ``windows_s``, gravity removed once for all of
    them: (a list of arrays, one per span; a label saying where it came from). From the IMU the 3-D
    gravity-free acceleration (n, 3) m/s² in the camera frame, from the truth the forward one (n,) alone.

    windows_s: s, the spans the IMU is averaged over about each time; the span the rows' rates average the
    motion over (:attr:`FieldRates.span`: a flow pair's two frames' interval) is one, and None is one frame
    interval. A 6-frame pair at 30 frames/s sees a walker's 1.7 Hz surge at 82 % of its amplitude, and the
    acceleration set beside it must too. bias: gyro bias track (n_imu, 3) rad/s for the attitude that removes
    gravity (:func:`gyro_bias_track`); None: the still-camera estimate. orientation: that attitude
    (n_imu, 3, 3) where already integrated (:func:`lobula.imu.orientation_from_gyro`)."""
    causal = config.readout.filter == "causal"
    if config.accel_from_truth or footage.imu is None:
        if not config.accel_from_truth and footage.kind != "d435i-sample":
            where = footage.path / "imu.csv" if footage.kind == "folder" else footage.path
            raise FootageError(f"{where}: {'missing' if footage.kind == 'folder' else 'no IMU'}; velocity needs "
                               f"forward acceleration. Add the IMU log, or pass --accel-from-truth to use the truth")
        if footage.truth is None:
            raise FootageError(no_truth_for_acceleration(footage))
        tt, at = acceleration_from_truth(footage.truth)
        a = np.interp(times, tt, at)
        return [a for _ in windows_s], "ground truth (smoothed derivative of velocity; no IMU)"
    imu = footage.imu
    if times[0] < imu.time_s[0] - 0.5 or times[-1] > imu.time_s[-1] + 0.5:
        # imu.source names the file (or bag and topic) the samples came from, whatever the layout.
        realsense = footage.kind.startswith("realsense")
        raise FootageError(f"{imu.source}: the IMU covers {imu.time_s[0]:.2f}..{imu.time_s[-1]:.2f} s but the "
                           f"frames of {footage.path.name} need {times[0]:.2f}..{times[-1]:.2f} s; their time stamps "
                           f"are not on one clock: shift the IMU with --clock-offset SECONDS (or auto)"
                           + (", or read both on another --clock" if realsense else ""))
    a = gravity_free_acceleration(imu.time_s, imu.accel, imu.gyro if config.derotate else None, causal=causal,
                                  bias=bias, orientation=orientation if config.derotate else None)
    dt = frame_interval(footage.times)
    widths = [dt if w is None else float(w) for w in windows_s]
    at = {w: np.stack([resample_to(times, imu.time_s, a[:, j], w) for j in range(3)], axis=1)
          for w in dict.fromkeys(widths)}   # each distinct span once (a rows' span of None is the frame's)
    return [at[w] for w in widths], "accelerometer (gravity and bias removed)"


def no_truth_for_acceleration(footage: Footage) -> str:
    """The one line for ``accel_from_truth`` (``--accel-from-truth``) on ``footage`` without truth: it names the
    truth file a footage folder lacks, and the IMU to use instead where the footage has one."""
    where = f"{footage.path / 'truth.csv'}: missing" if footage.kind == "folder" else f"{footage.path}: no truth"
    instead = (f", or drop --accel-from-truth to use the IMU ({footage.imu.source})" if footage.imu is not None
               else "")
    return (f"{where}; --accel-from-truth derives the forward acceleration from the truth's velocity (time_s, "
            f"v_forward_m_s) and needs it: add it{instead}")


def kappa_accel_at(accel: np.ndarray, rates, time_s: np.ndarray, orientation: np.ndarray | None, causal: bool,
                   window_s: float):
    """:func:`lobula.readout.readout`'s ``kappa_accel``: (the 3-D acceleration (n, 3) m/s², its direction
    (n, 2) (:func:`lobula.readout.acceleration_heading`), the camera's orientation (n, 3, 3) or None), or None
    where the fields have no moments (no material fields) or ``accel`` is the forward acceleration alone.

    accel: :func:`accels_at`'s, at the rows' times; rates: the FieldRates; orientation (m, 3, 3) at
    time_s (m,) s: camera → the frame gravity was removed in (:func:`lobula.imu.orientation_from_gyro`), or None;
    causal, window_s: the direction over trailing (else centred) windows of window_s s."""
    m = rates.material
    if m is None or m.moment is None or accel.ndim != 2:
        return None
    from .fields import slerp_orientations

    turns = None if orientation is None else slerp_orientations(time_s, orientation, rates.t)
    return accel, acceleration_heading(accel, frame_interval(rates.t), window_s, causal, turns), turns


def turn_rate_at(footage: Footage, times: np.ndarray, accel_source: str, config: VelocityConfig) -> np.ndarray | None:
    """|ω| (rad/s, (n,)): the gyro's rate magnitude averaged over each frame interval, or None
    where the acceleration does not come from an IMU with a gyro (then nothing turns it)."""
    if not accel_source.startswith("accelerometer") or footage.imu is None or footage.imu.gyro is None:
        return None
    return turn_rate(times, footage.imu.time_s, footage.imu.gyro, frame_interval(footage.times))

