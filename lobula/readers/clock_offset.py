"""A constant clock offset between camera and IMU, estimated from the footage itself.

The image's rotation rate is measured from consecutive frames: dense flow at low
resolution (OpenCV DIS), and per frame pair the least-squares angular velocity ω_img whose
rotational flow field (:func:`lobula.epipole.rotational_flow`) best explains it (translation
adds flow too but does not correlate with the gyro's rotation). The gyro, on its own clock,
is compared with ω_img for every candidate offset τ (t_camera = t_imu + τ): the offset is
the τ that maximises the normalised cross-correlation summed over the three axes, refined
by a parabola through the peak. Too little rotation, or a peak correlation under
``min_correlation``, is an error: the offset is then not identifiable from this footage and
must be given.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .core import FootageError


#: s: how far either side of the best lag the correlation must have fallen (a distinct peak)
PEAK_SIDE_S = 0.1


def _side_steps(resolution_s: float) -> int:
    """Steps of resolution_s (s) in PEAK_SIDE_S."""
    return max(1, int(round(PEAK_SIDE_S / resolution_s)))


@dataclass
class ClockOffset:
    """offset_s (s): add to IMU times to put them on the camera's clock; correlation (dimensionless) at the
    peak; n_pairs: frame pairs used; lags_s (k,) s: the offsets tried; scores (k,): the correlation at each
    (NaN where the IMU does not cover the frames)."""

    offset_s: float
    correlation: float
    n_pairs: int
    lags_s: np.ndarray
    scores: np.ndarray


def gyro_at(imu, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mask (n,) of the times ``t`` (s) the IMU covers, the gyro linearly interpolated there (k, 3) rad/s)."""
    ok = (t >= imu.time_s[0]) & (t <= imu.time_s[-1])
    return ok, np.stack([np.interp(t[ok], imu.time_s, imu.gyro[:, j]) for j in range(3)], -1)


@dataclass
class FlowSamples:
    """Dense flow between consecutive frames, sampled on a fixed grid of points.

    time_s (n,) s: the frame pairs' mid times, plus half a rolling shutter's readout (the rows' mean exposure,
    lobula.camera.PinholeCamera.rolling_shutter_s); x, y (m,): the points' normalised image coordinates; flow
    (n, 2, m) 1/s: the flow (u, v) at each point per second, in normalised coordinates."""

    time_s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    flow: np.ndarray


def image_flow_samples(footage, max_frames: int = 900, width: int = 160,
                       preset: int = cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST) -> FlowSamples:
    """DIS flow (OpenCV ``preset``) between consecutive frames of ``footage`` (the first ``max_frames``),
    computed at ``width`` pixels and sampled at about 3,000 points (:class:`FlowSamples`)."""
    cam = footage.camera
    scale = min(1.0, width / cam.width)
    small = cam.scaled(scale) if scale < 1 else cam
    x, y = small.normalised_grid()
    step = max(1, int(np.sqrt(small.width * small.height / 3000)))
    xs, ys = x[::step, ::step].ravel(), y[::step, ::step].ravel()
    dis = cv2.DISOpticalFlow_create(preset)
    late = 0.5 * getattr(cam, "rolling_shutter_s", 0.0)  # a rolling shutter's rows are seen, on average, this late
    prev, out_t, out_f = None, [], []
    for _, t, img in footage.frames(0, max_frames):
        g = cv2.resize(img, (small.width, small.height), interpolation=cv2.INTER_AREA) if scale < 1 else img
        g = np.clip(np.round(g), 0, 255).astype(np.uint8)
        if prev is not None:
            dt = t - prev[0]
            f = dis.calc(prev[1], g, None)[::step, ::step]
            out_f.append(np.stack([f[..., 0].ravel() / small.fx / dt, f[..., 1].ravel() / small.fy / dt]))
            out_t.append(0.5 * (t + prev[0]) + late)
        prev = (t, g)
    flow = np.asarray(out_f, np.float32).reshape(-1, 2, len(xs))
    return FlowSamples(np.asarray(out_t, float), xs, ys, flow)


def image_rotation_rates(footage, max_frames: int = 900, width: int = 160,
                         preset: int = cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                         bands=None) -> tuple[np.ndarray, np.ndarray]:
    """(mid times (n,) s, ω_img (n, 3) rad/s): per frame pair, the least-squares angular velocity whose rotational
    field explains the flow of :func:`image_flow_samples` (same arguments).

    ``bands``: where given, a sequence of k (lo, hi) fractions of the largest normalised image radius: ω_img is
    then fitted to the flow inside each ring separately, (n, k, 3)."""
    s = image_flow_samples(footage, max_frames, width, preset)
    return s.time_s, rotation_rates(s, bands)


def rotation_rates(samples: FlowSamples, bands=None) -> np.ndarray:
    """ω_img (n, 3) rad/s, or (n, k, 3) within ``bands`` (see :func:`image_rotation_rates`), from ``samples``."""
    from lobula.epipole import rotational_flow

    xs, ys, flow = samples.x, samples.y, samples.flow.astype(float)
    rho = np.hypot(xs, ys)
    rings = [np.ones(len(xs), bool)] if bands is None else \
        [(rho >= lo * rho.max()) & (rho < hi * rho.max()) for lo, hi in bands]
    w = np.zeros((len(flow), len(rings), 3))
    for k, m in enumerate(rings):
        basis = np.stack([rotational_flow(e, xs[m], ys[m]).reshape(-1) for e in np.eye(3)], -1)
        if len(flow):
            w[:, k] = np.linalg.lstsq(basis, flow[:, :, m].reshape(len(flow), -1).T, rcond=None)[0].T
    return w[:, 0] if bands is None else w


def estimate_clock_offset(footage, max_offset_s: float = 0.25, resolution_s: float = 0.001,
                          min_correlation: float = 0.5, max_frames: int = 900) -> ClockOffset:
    """Estimate the camera–IMU clock offset of ``footage`` (see the module doc); FootageError when not identifiable.

    max_offset_s, resolution_s: the offsets tried, ±max_offset_s s in steps of resolution_s s;
    min_correlation: the peak correlation (dimensionless) below which the offset is refused;
    max_frames: the frames read.
    """
    imu = footage.imu
    if imu is None or imu.gyro is None:
        raise FootageError(f"{footage.path}: --clock-offset auto needs a gyroscope; give --clock-offset S")
    t_img, w_img = image_rotation_rates(footage, max_frames=max_frames)
    if len(t_img) < 10:
        raise FootageError(f"{footage.path}: too few frames ({len(t_img) + 1}) to estimate the clock offset; "
                           f"give --clock-offset S")
    w_img = w_img - w_img.mean(0)
    if np.sqrt((w_img ** 2).sum(1).mean()) < 0.02:
        raise FootageError(f"{footage.path}: too little rotation in the footage (< 0.02 rad/s RMS) to estimate "
                           f"the clock offset; give --clock-offset S")
    lags = np.arange(-max_offset_s, max_offset_s + resolution_s / 2, resolution_s)
    scores = np.full(len(lags), np.nan)
    for k, lag in enumerate(lags):
        # gyro on the camera clock: ω(t_cam) = gyro(t_cam − τ)
        ok, g = gyro_at(imu, t_img - lag)
        if ok.sum() < 0.8 * len(t_img):
            continue
        g = g - g.mean(0)
        a = w_img[ok]
        den = np.sqrt((a ** 2).sum() * (g ** 2).sum())
        scores[k] = (a * g).sum() / den if den > 0 else np.nan
    if not np.isfinite(scores).any():
        raise FootageError(f"{footage.path}: the IMU does not cover the frames within ±{max_offset_s} s; "
                           f"give --clock-offset S")
    k = int(np.nanargmax(scores))
    best, peak = float(lags[k]), float(scores[k])
    if 0 < k < len(lags) - 1 and np.isfinite(scores[k - 1]) and np.isfinite(scores[k + 1]):
        s0, s1, s2 = scores[k - 1], scores[k], scores[k + 1]
        den = s0 - 2 * s1 + s2
        if den < 0:
            best += float(0.5 * (s0 - s2) / den) * resolution_s
    if peak < min_correlation:
        raise FootageError(f"{footage.path}: gyro and image rotation correlate only {peak:.2f} at best "
                           f"(< {min_correlation}); the clock offset is not identifiable here: give --clock-offset S")
    if k in (0, len(lags) - 1):
        raise FootageError(f"{footage.path}: the best clock offset is at the edge of ±{max_offset_s} s; "
                           f"give --clock-offset S")
    # A lag that lines the rotations up stands out: a tenth of a second either side the correlation loses more
    # than what even the best lag leaves unexplained (1 − peak). A flat ridge of middling correlation (a gait's
    # periodic rotation, an image partly stabilised) says nothing of the lag.
    side = [scores[j] for j in (k - _side_steps(resolution_s), k + _side_steps(resolution_s))
            if 0 <= j < len(lags) and np.isfinite(scores[j])]
    if side and peak - max(side) < 1.0 - peak:
        raise FootageError(f"{footage.path}: gyro and image rotation correlate {peak:.2f} at {best * 1e3:+.0f} ms but "
                           f"still {max(side):.2f} {PEAK_SIDE_S * 1e3:.0f} ms away: no distinct lag, so the clock offset "
                           f"is not identifiable here; give --clock-offset S")
    return ClockOffset(best, peak, int(len(t_img)), lags, scores)
