"""The focal length, estimated from the footage itself: the gyro's rotation against the image's.

A camera turning at ω (rad/s) moves the image by f·ω pixels per second near its centre, whatever
the scene; a wrong focal length f₀ for a true f reads the pan and tilt rates scaled by f/f₀ (roll, about
the optical axis, not at all). The image's flow is measured between consecutive frames
(:func:`lobula.readers.clock_offset.image_flow_samples`: DIS flow) through the camera the footage states,
and the gyro's rotation scaled by k (pan and tilt) and k_roll (roll) is fitted to it alongside the
translation's flow (:func:`lobula.readers.gyro_scale.gyro_scale_with_translation`): what is left once the rotation is taken out must
radiate from one epipole per frame pair, at whatever depths. A camera that walks, bounces and sways
moves the image as a turn would, and a fit of the rotation alone reads it as one: 2.6-18 % off on
hand-held walks where this fit reads 0.1-3.1 %. k is the ratio f/f₀; the camera is rescaled by it and measured
again until k is 1 (a distorted lens's map onto a pinhole makes the ratio hold only near the centre at
first). Too little rotation, or image and gyro rates that do not agree, is an error: the
focal length is then not identifiable from this footage and must be given.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .core import FootageError
from .gyro_scale import at_bound, gyro_scale_with_translation, search_bounds, thinned

#: rad/s: the gyro's RMS pan and tilt rate a footage needs for its focal length to be measured
MIN_ROTATION_RAD_S = 0.1
#: px: the width the flow is computed at (at 160 px DIS reads a turning panels scene's rotation 5-25 % slow)
FLOW_WIDTH_PX = 320
#: a step's scale this near 1 ends the search where it is within two standard errors of 1
CLOSE_ENOUGH = 0.05


@dataclass
class FocalEstimate:
    """fx, fy (px): the focal lengths found (their ratio kept from the camera given); scale: fx over the given
    fx; correlation: of the image's pan/tilt rates with the gyro's at the last step (dimensionless);
    slope_std: the last step's k's standard error (dimensionless); n_pairs: frame pairs used; steps: the
    k measured, one per iteration; roll_scale: k_roll at the last step (the flow's own reading of roll,
    which does not depend on the focal length)."""

    fx: float
    fy: float
    scale: float
    correlation: float
    slope_std: float
    n_pairs: int
    steps: list
    roll_scale: float = 1.0


def _slope(footage, max_frames: int) -> tuple[float, float, float, int, float]:
    """(k, its standard error, correlation, pairs, k_roll) of ``footage`` as opened
    (:func:`lobula.readers.gyro_scale.gyro_scale_with_translation`; the correlation is of the image's
    least-squares pan and tilt rates with the gyro's)."""
    import cv2

    from .clock_offset import gyro_at, image_flow_samples, rotation_rates

    samples = image_flow_samples(footage, max_frames=max_frames, width=FLOW_WIDTH_PX,
                                 preset=cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    ok, g = gyro_at(footage.imu, samples.time_s)
    if ok.sum() < 10:
        raise FootageError(f"{footage.path}: fewer than 10 frame pairs with gyro samples around them; the focal length "
                           f"cannot be measured here: give it in a camera.json (--camera FILE)")
    gc = g - g.mean(0)
    gg = float((gc[:, :2] ** 2).sum())
    rms = np.sqrt(gg / (2 * len(g)))
    if rms < MIN_ROTATION_RAD_S:
        raise FootageError(f"{footage.path}: too little pan and tilt in the footage (gyro RMS {rms:.3f} rad/s < "
                           f"{MIN_ROTATION_RAD_S}) to measure the focal length; give it in a camera.json (--camera FILE)")
    a = rotation_rates(samples)[ok]
    a = a - a.mean(0)
    corr = float((a[:, :2] * gc[:, :2]).sum() / np.sqrt((a[:, :2] ** 2).sum() * gg))
    # the rotation alone, where the search starts and near which it stays
    near_pt = float((a[:, :2] * gc[:, :2]).sum() / gg)
    gz = float((gc[:, 2] ** 2).sum())
    near_roll = float(a[:, 2] @ gc[:, 2] / gz) if np.sqrt(gz / len(g)) >= MIN_ROTATION_RAD_S else 1.0
    if not 0.2 < near_pt < 5.0:
        return near_pt, np.inf, corr, int(ok.sum()), near_roll
    k, k_std, k_roll = gyro_scale_with_translation(*thinned(samples.x, samples.y, samples.flow[ok]), g,
                                                   near=(near_pt, near_roll))
    if at_bound(k, search_bounds(near_pt)):
        raise FootageError(f"{footage.path}: the flow's translation takes the pan and tilt for its own here (the "
                           f"scale runs to {k / near_pt:.2f}× a fit of the rotation alone); the focal length is not "
                           f"identifiable from this footage: give it in a camera.json (--camera FILE)")
    return k, k_std, corr, int(ok.sum()), k_roll


def estimate_focal_length(footage, iterations: int = 4, tolerance: float = 0.02, min_correlation: float = 0.7,
                          max_frames: int = 900) -> FocalEstimate:
    """Estimate the focal length of ``footage``'s camera from its gyro (see the module doc).

    The footage is opened with a first guess (its camera.json, or ``--camera``; a distorted lens's map is remade at
    each step). ``iterations``: at most this many rescalings; ``tolerance``: stop when the scale is within this of 1
    (its last correction, applied unmeasured, then errs by a fraction of that), or within two of its standard errors
    and :data:`CLOSE_ENOUGH`; ``min_correlation``: below it the image and gyro rates are taken not to agree
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
    scale, steps, tried = 1.0, [], []
    for _ in range(max(1, iterations)):
        cam = replace(raw, fx=raw.fx * scale, fy=raw.fy * scale)
        if lens is not None:
            footage.lens_maps, footage.camera = undistortion_maps(cam, lens, dist.get("target_k", "same-k"))
        else:
            footage.camera = cam
        slope, slope_std, corr, n, roll = _slope(footage, max_frames)
        steps.append(round(slope, 5))
        if corr < min_correlation or not 0.2 < slope < 5.0:
            what = (f"correlate only {corr:.2f} with the gyro's (< {min_correlation})" if corr < min_correlation
                    else f"follow the gyro's with a slope of {slope:.3f} (outside 0.2-5)")
            raise FootageError(f"{footage.path}: the image's pan and tilt rates {what}; the focal length is not "
                               f"identifiable here "
                               f"(too much translation, electronic stabilisation, or a clock offset): give it in a "
                               f"camera.json")
        # within what the slope can tell; a step far from 1 (a fisheye's map made at a focal length far off fits the
        # model poorly, and its spread with it) is taken whatever its spread
        done = abs(slope - 1.0) < max(tolerance, min(2.0 * slope_std, CLOSE_ENOUGH))
        tried.append((np.log(scale), np.log(slope)))
        # the next scale by the secant through the last two steps: a pinhole's log slope falls one for one with the
        # log scale, a fisheye's map remade at each step steeper (about 1.4 on a 131° lens), which f ← f·k overshoots
        gain = 1.0
        if len(tried) > 1 and tried[-1][0] != tried[-2][0]:
            gain = float(np.clip((tried[-2][1] - tried[-1][1]) / (tried[-1][0] - tried[-2][0]), 0.5, 2.0))
        scale *= float(np.exp(np.log(slope) / gain))
        if done:
            break
    return FocalEstimate(raw.fx * scale, raw.fy * scale, scale, corr, slope_std, n, steps, roll)
