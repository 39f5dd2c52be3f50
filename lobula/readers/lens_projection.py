"""Which projection a lens has — pinhole or equidistant fisheye — told by the footage itself.

A camera turning at ω moves every part of a correctly undistorted (pinhole) image as the rotational field
of ω says, near the centre and at the edge alike. Read through the wrong projection it does not: an
equidistant fisheye's periphery (r = f·θ) read as a pinhole (r = f·tan θ) turns too slowly, a pinhole's
read as a fisheye too fast, more so the wider the view. So the image's angular velocity is fitted to the
flow in an inner disc and in an outer ring of the undistorted image separately
(:func:`lobula.readers.clock_offset.image_rotation_rates` with ``bands``), each regressed on the gyro's pan
and tilt, and the outer slope over the inner one — the radial ratio — is 1 for the right projection. On a
131° equidistant fisheye turning on three axes it reads 0.97 through its own projection and 0.47 as a
pinhole; on a 66° pinhole 0.99 as a pinhole and 1.13 as a fisheye.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .clock_offset import gyro_at, image_rotation_rates
from .core import FootageError

__all__ = ["RadialRatio", "radial_rotation_ratio", "INNER_BAND", "OUTER_BAND", "RATIO_SYSTEMATIC"]

#: fractions of the largest normalised radius: the inner disc and the outer ring compared
INNER_BAND, OUTER_BAND = (0.0, 0.3), (0.6, 1.01)
#: 1σ of log(ratio) beyond the slopes' standard errors (translation's flow differs between the rings; a 66°
#: pinhole through its own projection reads 0.99 with standard errors of 0.6 %)
RATIO_SYSTEMATIC = 0.02
#: rad/s: the gyro's RMS pan and tilt rate needed
MIN_ROTATION_RAD_S = 0.1


@dataclass
class RadialRatio:
    """ratio: the outer ring's pan/tilt slope on the gyro over the inner disc's (1 for the right projection);
    log_std: 1σ of log(ratio), with :data:`RATIO_SYSTEMATIC`; inner_slope, outer_slope: the two slopes
    (dimensionless); half_diagonal_deg: the angle the undistorted image's corner sees from the axis (deg);
    n_pairs: frame pairs used."""

    ratio: float
    log_std: float
    inner_slope: float
    outer_slope: float
    half_diagonal_deg: float
    n_pairs: int


def _slope(a: np.ndarray, g: np.ndarray) -> tuple[float, float]:
    """Slope through the origin of ``a`` on ``g`` (n, 2) and its standard error."""
    gg = float((g ** 2).sum())
    s = float((a * g).sum() / gg)
    res = a - s * g
    return s, float(np.sqrt((res ** 2).sum() / max(res.size - 1, 1) / gg))


def radial_rotation_ratio(footage, max_frames: int = 300, width: int = 320) -> RadialRatio:
    """The radial ratio of ``footage`` as opened (its camera and lens map; module doc).

    ``max_frames``: frames read; ``width``: px the flow is computed at. The IMU must be on the frames' clock and
    in the camera's axes. FootageError where the footage pans and tilts too little or a slope is not positive.
    """
    imu = footage.imu
    t, w = image_rotation_rates(footage, max_frames=max_frames, width=width,
                                preset=cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, bands=(INNER_BAND, OUTER_BAND))
    ok, g = gyro_at(imu, t)
    if ok.sum() < 10:
        raise FootageError(f"{footage.path}: fewer than 10 frame pairs with gyro samples around them")
    g = g[:, :2] - g[:, :2].mean(0)
    rms = float(np.sqrt((g ** 2).mean()))
    if rms < MIN_ROTATION_RAD_S:
        raise FootageError(f"{footage.path}: too little pan and tilt (gyro RMS {rms:.3f} rad/s < {MIN_ROTATION_RAD_S})")
    (s_in, e_in), (s_out, e_out) = (_slope(w[ok, k, :2] - w[ok, k, :2].mean(0), g) for k in range(2))
    if s_in <= 0 or s_out <= 0:
        raise FootageError(f"{footage.path}: the image's rotation does not follow the gyro's (slopes {s_in:.2f}, "
                           f"{s_out:.2f})")
    cam = footage.camera
    corner = np.hypot(max(cam.cx, cam.width - 1 - cam.cx) / cam.fx, max(cam.cy, cam.height - 1 - cam.cy) / cam.fy)
    return RadialRatio(ratio=s_out / s_in, log_std=float(np.sqrt((e_in / s_in) ** 2 + (e_out / s_out) ** 2
                                                                   + RATIO_SYSTEMATIC ** 2)),
                       inner_slope=s_in, outer_slope=s_out, half_diagonal_deg=float(np.degrees(np.arctan(corner))),
                       n_pairs=int(ok.sum()))

