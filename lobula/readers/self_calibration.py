"""A camera that came without its calibration, measured from its own footage: clock offset, then focal length.

A GoPro MP4 states no intrinsics; its reader assumes an equidistant fisheye from the field of view the
file states (or a nominal one), and a video with another camera's motion log an equidistant fisheye (action
cameras) or a pinhole (:mod:`lobula.readers.camera_telemetry`) — ``footage.lens_guess``. Here the gyro measures what it can:

1. the camera–IMU clock offset (:func:`lobula.readers.clock_offset.estimate_clock_offset`: the lag that
   best lines the image's rotation up with the gyro's; the correlation is scale-free, so the guessed
   focal length does not bias it);
2. the focal length (:func:`lobula.readers.focal_length.estimate_focal_length`: the slope of the image's
   pan and tilt rates against the gyro's, iterated to 1), with its standard error.

Each is kept only where the footage shows it (enough rotation, image and gyro rates that agree);
otherwise the guess stays, and the reason is said — an image stabilised against the body (HyperSmooth)
hides both. What was used is written to ``footage.calibration``, to the notes, and so to every output's
attrs (``camera_calibration``).
"""
from __future__ import annotations

import json

import numpy as np

from .core import FootageError

__all__ = ["self_calibrate", "FOCAL_SYSTEMATIC_REL_STD"]

#: 1σ fraction: what the slope's own standard error leaves out of a measured focal length, the translation's flow
#: that a record of seconds does not average out (synthetic scenes turning on three axes while moving: a 131°
#: fisheye from guesses 22 % short and 25 % long within 3 %; a 160×120 pinhole from a 75° guess 5 % long, where
#: the slope's error said 0.6 %)
FOCAL_SYSTEMATIC_REL_STD = 0.04


def _clock(footage) -> dict:
    from .clock_offset import estimate_clock_offset

    try:
        est = estimate_clock_offset(footage)
    except FootageError as exc:
        return dict(clock_offset_s=0.0, clock_offset_source=f"not identifiable, 0 assumed: {_why(exc)}")
    footage.imu = footage.imu.shifted(est.offset_s)
    source = f"estimated: gyro vs image rotation, correlation {est.correlation:.2f} over {est.n_pairs} frame pairs"
    footage.clock_offset_s, footage.clock_offset_source = float(est.offset_s), source
    return dict(clock_offset_s=round(float(est.offset_s), 4), clock_offset_source=source)


def _focal(footage, guess: dict) -> dict:
    from .focal_length import estimate_focal_length

    from dataclasses import replace

    from lobula.camera import PinholeCamera
    from lobula.lens import LensDistortion, undistortion_maps

    dist = footage.distortion if guess["model"] != "pinhole" else None
    f0 = float(dist["raw_camera"]["fx"] if dist else footage.camera.fx)
    before = footage.camera, footage.lens_maps
    try:
        est = estimate_focal_length(footage)
    except FootageError as exc:
        footage.camera, footage.lens_maps = before  # the search leaves its last trial behind
        return dict(focal_length_px=f0, focal_length_rel_std=guess["rel_std"],
                    focal_length_source=f"{guess['source']}, not measured: {_why(exc)}")
    if dist is None:  # a pinhole: nothing to resample
        footage.camera = replace(before[0], fx=est.fx, fy=est.fy)
    else:
        raw = replace(PinholeCamera(**dist["raw_camera"]), fx=est.fx, fy=est.fy)
        footage.lens_maps, footage.camera = undistortion_maps(raw, LensDistortion(dist["model"],
                                                                                  tuple(dist["coeffs"])),
                                                              dist.get("target_k", "same-k"))
        dist["raw_camera"] = raw.to_dict()
    rel_std = float(np.hypot(est.slope_std, FOCAL_SYSTEMATIC_REL_STD))
    return dict(focal_length_px=round(est.fx, 2), focal_length_rel_std=round(rel_std, 4),
                focal_length_source=(f"measured against the gyro (from {guess['source']}: {f0:.1f} px; pan/tilt "
                                     f"correlation {est.correlation:.2f} over {est.n_pairs} pairs)"))


def _why(exc: Exception) -> str:
    """The reason of a FootageError without the file's name in front (the note names the footage already)."""
    text = str(exc)
    return text.split(": ", 1)[1] if ": " in text else text


def self_calibrate(footage, clock: bool = True) -> dict:
    """Measure ``footage``'s clock offset (where ``clock``) and focal length from its gyro, in place.

    Parameters
    ----------
    footage : lobula.readers.core.Footage
        Opened with a lens guess (``footage.lens_guess``: the reader's) and an IMU with a gyro.
    clock : bool
        Estimate the clock offset too (False where the user gave one).

    Returns
    -------
    dict
        lens (the projection), focal_length_px (px) with focal_length_rel_std (1σ fraction) and its
        source, clock_offset_s (s) and its source; also set as ``footage.calibration``.
    """
    guess = footage.lens_guess
    pinhole = guess["model"] == "pinhole"
    out = dict(lens="pinhole (no distortion)" if pinhole else f"equidistant fisheye ({guess['model']}, no coefficients)")
    if footage.imu is None or footage.imu.gyro is None:
        out.update(focal_length_px=float(footage.camera.fx if pinhole else footage.distortion["raw_camera"]["fx"]),
                   focal_length_rel_std=guess["rel_std"],
                   focal_length_source=f"{guess['source']}, not measured: the footage has no gyro")
    else:
        if clock:
            out.update(_clock(footage))
        out.update(_focal(footage, guess))
    footage.calibration = out
    footage.notes.append(f"camera self-calibrated (no calibration file): {json.dumps(out)}")
    return out
