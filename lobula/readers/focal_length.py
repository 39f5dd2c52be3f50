"""The focal length, estimated from the footage itself: the gyro's rotation against the image's.

A camera turning at ω (rad/s) moves the image by f·ω pixels per second near its centre, whatever
the scene. The image's rotation rate is measured as for the clock offset
(:func:`lobula.readers.clock_offset.image_rotation_rates`: dense flow between consecutive frames,
the least-squares angular velocity of its rotational field), with the focal length the footage's
camera states; a wrong focal length f₀ for a true f reads the pan and tilt rates scaled by f/f₀
(roll, about the optical axis, not at all). The slope of the image's pan and tilt rates against the
gyro's, through the origin, is that ratio; the camera is rescaled by it and measured again until the
slope is 1 (a distorted lens's map onto a pinhole makes the ratio hold only near the centre at first).
Too little rotation, or image and gyro rates that do not agree, is an error: the focal length is then
not identifiable from this footage and must be given.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .core import FootageError

#: rad/s: the gyro's RMS pan and tilt rate a footage needs for its focal length to be measured (and its roll
#: rate, for the roll to serve as the flow's own scale)
MIN_ROTATION_RAD_S = 0.1
#: px: the width the flow is computed at (at 160 px DIS reads a turning panels scene's rotation 5-25 % slow)
FLOW_WIDTH_PX = 320


@dataclass
class FocalEstimate:
    """fx, fy (px): the focal lengths found (their ratio kept from the camera given); scale: fx over the given
    fx; correlation: of the image's pan/tilt rates with the gyro's at the last step (dimensionless);
    slope_std: the last slope's standard error (dimensionless); n_pairs: frame pairs used; steps: the
    slopes measured, one per iteration; by_roll: the slopes are relative to the roll's (see :func:`_slope`)."""

    fx: float
    fy: float
    scale: float
    correlation: float
    slope_std: float
    n_pairs: int
    steps: list
    by_roll: bool = False


def _slope(footage, max_frames: int) -> tuple[float, float, float, int, bool]:
    """(slope, its standard error, correlation, pairs, by roll) of the image's pan/tilt rates against the gyro's,
    divided by the roll rates' own slope where the footage rolls enough (the flow's own under-reading, the same on
    every axis, cancels there; roll does not depend on the focal length)."""
    import cv2

    from .clock_offset import gyro_at, image_rotation_rates

    imu = footage.imu
    t_img, w_img = image_rotation_rates(footage, max_frames=max_frames, width=FLOW_WIDTH_PX,
                                        preset=cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    ok, g = gyro_at(imu, t_img)
    if ok.sum() < 10:
        raise FootageError(f"{footage.path}: fewer than 10 frame pairs with gyro samples around them; the focal length "
                           f"cannot be measured here: give it in a camera.json (--camera FILE)")
    a = w_img[ok]
    g, a = g - g.mean(0), a - a.mean(0)
    gg = float((g[:, :2] ** 2).sum())
    rms = np.sqrt(gg / (2 * len(g)))
    if rms < MIN_ROTATION_RAD_S:
        raise FootageError(f"{footage.path}: too little pan and tilt in the footage (gyro RMS {rms:.3f} rad/s < "
                           f"{MIN_ROTATION_RAD_S}) to measure the focal length; give it in a camera.json (--camera FILE)")
    slope = float((a[:, :2] * g[:, :2]).sum() / gg)
    res = a[:, :2] - slope * g[:, :2]
    slope_std = float(np.sqrt((res ** 2).sum() / max(res.size - 1, 1) / gg))
    corr = float((a[:, :2] * g[:, :2]).sum() / np.sqrt((a[:, :2] ** 2).sum() * gg))
    gz = float((g[:, 2] ** 2).sum())
    by_roll = np.sqrt(gz / len(g)) >= MIN_ROTATION_RAD_S
    if by_roll:
        roll = float(a[:, 2] @ g[:, 2] / gz)
        slope, slope_std = slope / roll, slope_std / roll
    return slope, slope_std, corr, int(ok.sum()), bool(by_roll)


def estimate_focal_length(footage, iterations: int = 4, tolerance: float = 0.002, min_correlation: float = 0.7,
                          max_frames: int = 900) -> FocalEstimate:
    """Estimate the focal length of ``footage``'s camera from its gyro (see the module doc).

    The footage is opened with a first guess (its camera.json, or ``--camera``; a distorted lens's
    map is remade at each step). ``iterations``: at most this many rescalings; ``tolerance``: stop when the
    slope is within this of 1, or within two of its standard errors; ``min_correlation``: below it the image and gyro rates are taken not to agree
    (FootageError); ``max_frames``: the frames read at each step. The clock offset must already be applied
    (``--clock-offset``): a lag between the two rates lowers the slope.
    """
    from lobula.lens import undistortion_maps

    if footage.imu is None or footage.imu.gyro is None:
        raise FootageError(f"{footage.path}: the focal length is measured against the gyro, and this footage has "
                           f"none; give it in a camera.json (--camera FILE)")
    from lobula.camera import PinholeCamera
    from lobula.lens import LensDistortion

    dist = footage.distortion if (footage.distortion or {}).get("removed") and "raw_camera" in footage.distortion \
        else None
    raw = PinholeCamera(**dist["raw_camera"]) if dist else footage.camera
    lens = LensDistortion(dist["model"], tuple(dist["coeffs"])) if dist else None
    scale, steps = 1.0, []
    for _ in range(max(1, iterations)):
        cam = replace(raw, fx=raw.fx * scale, fy=raw.fy * scale)
        if lens is not None:
            footage.lens_maps, footage.camera = undistortion_maps(cam, lens, dist.get("target_k", "same-k"))
        else:
            footage.camera = cam
        slope, slope_std, corr, n, by_roll = _slope(footage, max_frames)
        steps.append(round(slope, 5))
        if corr < min_correlation or not 0.2 < slope < 5.0:
            what = (f"correlate only {corr:.2f} with the gyro's (< {min_correlation})" if corr < min_correlation
                    else f"follow the gyro's with a slope of {slope:.3f} (outside 0.2-5)")
            raise FootageError(f"{footage.path}: the image's pan and tilt rates {what}; the focal length is not "
                               f"identifiable here "
                               f"(too much translation, electronic stabilisation, or a clock offset): give it in a "
                               f"camera.json")
        scale *= slope
        if abs(slope - 1.0) < max(tolerance, 2.0 * slope_std):  # within what the slope can tell
            break
    return FocalEstimate(raw.fx * scale, raw.fy * scale, scale, corr, slope_std, n, steps, by_roll)
