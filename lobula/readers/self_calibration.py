"""A camera that came without its calibration, measured from its own footage: clock offset, then focal length.

A GoPro MP4 states no intrinsics; its reader assumes an equidistant fisheye from the field of view the
file states (or a nominal one), and a video with another camera's motion log an equidistant fisheye (action
cameras) or a pinhole (:mod:`lobula.readers.camera_telemetry`) — ``footage.lens_guess``. Here the gyro measures what it can:

1. the camera–IMU clock offset (:func:`lobula.readers.clock_offset.estimate_clock_offset`: the lag that
   best lines the image's rotation up with the gyro's; the correlation is scale-free, so the guessed
   focal length does not bias it);
2. the IMU's axes (:func:`lobula.readers.imu_rotation.fit_imu_rotation`: the rotation that turns the gyro's
   rates into the image's, refined on the flow with the translation alongside,
   :func:`lobula.readers.imu_rotation.refine_with_translation`). The reader's axes stand unless the image clearly says otherwise — more than
   :data:`AXES_TOLERANCE_DEG` and three standard errors off, with the rotated gyro following the image
   (correlation ≥ :data:`AXES_MIN_CORRELATION`) — as when a phone logs its motion in portrait while the video
   is landscape; the IMU is then turned (accelerometer too) and, if the clock could not be found with the
   axes as given, the clock offset estimated again;
3. the focal length (:func:`lobula.readers.focal_length.estimate_focal_length`: the scale of the gyro's pan
   and tilt in the image's flow, the translation fitted alongside, iterated to 1), with its standard error;
4. the projection, pinhole or equidistant fisheye (:func:`lobula.readers.lens_projection.radial_rotation_ratio`:
   through the right one the image's edge turns with the gyro as its centre does). The reader's guess stands
   unless its radial ratio is far from 1 (:data:`PROJECTION_MIN_LOG_RATIO`) and the other projection's is
   clearly nearer (by three standard errors); the focal length is then measured again through it.

Each is kept only where the footage shows it (enough rotation, image and gyro rates that agree);
otherwise the guess stays, and the reason is said — an image stabilised against the body (HyperSmooth)
hides both, unless the file records the image's orientation (:mod:`lobula.readers.image_orientation`). What was used is written to ``footage.calibration``, to the notes, and so to every output's
attrs (``camera_calibration``).
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from .core import FootageError, rotation_deg

__all__ = ["self_calibrate", "check_imu_axes", "FOCAL_SYSTEMATIC_REL_STD", "AXES_TOLERANCE_DEG",
           "AXES_MIN_CORRELATION", "PROJECTION_MIN_LOG_RATIO"]

#: 1σ fraction: what the scale's jackknife error leaves out of a measured focal length: the gyro's scale factors
#: (about 1 % per axis) and a clock offset left (9 ms moves a 131° fisheye's scale by 2–4 %); on the suite's walks
#: the focal length lands 0.1–3.1 % from the truth with jackknife errors of 0.2–1.6 %
FOCAL_SYSTEMATIC_REL_STD = 0.04
#: deg: the least disagreement between the IMU's axes as read and the image's rotation that turns the IMU (a
#: mounting within a few degrees of its nominal axes is not worth the risk of a wrong turn)
AXES_TOLERANCE_DEG = 5.0
#: the least correlation of the image's rotation rates with the turned gyro's for the turn to be trusted
AXES_MIN_CORRELATION = 0.7
#: |log| of the radial ratio through the guessed projection beyond which the other may replace it (the edge
#: turning 22 % off the centre): a hand-held walk's translation alone moves the ratio by up to 7 % (the suite's
#: walking scenes, where three standard errors do not cover it); a fisheye read as a pinhole is 0.37–0.62 off
PROJECTION_MIN_LOG_RATIO = 0.2


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


def check_imu_axes(footage, turned: dict | None = None) -> dict:
    """Measure ``footage``'s IMU axes against the image's rotation; turn its IMU (and ``imu_to_camera``) in place
    where they clearly disagree (see the module doc).

    The image's rates are measured as for the focal length (DIS's medium preset at
    :data:`lobula.readers.focal_length.FLOW_WIDTH_PX`: coarser flow reads a fisheye's rotation several degrees
    off). ``turned``: this function's result where it turned the IMU already; the turn is then
    refined (the focal length measured since makes the image's rates truer) whatever its size. Returns the
    ``imu_axes_*`` entries of :func:`self_calibrate`'s dict.
    """
    import cv2

    from .clock_offset import gyro_at, image_flow_samples, rotation_rates
    from .focal_length import FLOW_WIDTH_PX
    from .imu_rotation import fit_imu_rotation, refine_with_translation

    try:
        samples = image_flow_samples(footage, width=FLOW_WIDTH_PX, preset=cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    except FootageError as exc:
        return dict(imu_axes_source=f"as read, not checked: {_why(exc)}")
    ok, g = gyro_at(footage.imu, samples.time_s)
    w_img = rotation_rates(samples)[ok]
    try:
        est = fit_imu_rotation(w_img, g, where=str(footage.path))
    except FootageError as exc:
        return dict(imu_axes_source=f"as read, not checked: {_why(exc)}")
    if est.correlation >= AXES_MIN_CORRELATION:
        # the flow itself, with the translation fitted alongside: a walk's sway read as rotation turns the
        # image's rates by several degrees
        est = refine_with_translation(est, replace(samples, time_s=samples.time_s[ok], flow=samples.flow[ok]),
                                      w_img, g)
    if est.correlation < AXES_MIN_CORRELATION:
        return dict(imu_axes_source=(f"as read, not checked: even turned at best, the gyro's rates correlate only "
                                     f"{est.correlation:.2f} with the image's (< {AXES_MIN_CORRELATION}; electronic "
                                     f"stabilisation, a gimbal, or much translation)"),
                    imu_axes_correlation=round(est.correlation, 3))
    before = np.eye(3) if turned is None else np.asarray(turned["imu_axes_rotation"])
    total = est.rotation @ before                     # from the axes as read
    angle = rotation_deg(total)
    found = dict(imu_axes_angle_deg=round(angle, 2), imu_axes_angle_std_deg=round(est.angle_std_deg, 2),
                 imu_axes_correlation_as_read=round(est.correlation_as_given if turned is None
                                                    else turned["imu_axes_correlation_as_read"], 3))
    if turned is None and angle <= max(AXES_TOLERANCE_DEG, 3.0 * est.angle_std_deg):
        return dict(imu_axes_source=(f"as read: the image's rotation puts them {angle:.1f}° ± "
                                     f"{est.angle_std_deg:.1f}° off (correlation {est.correlation:.2f} turned, "
                                     f"{est.correlation_as_given:.2f} as read), within what it can tell"), **found)
    footage.imu = footage.imu.rotated(est.rotation)
    footage.imu_to_camera = est.rotation @ (footage.imu_to_camera if footage.imu_to_camera is not None else np.eye(3))
    return dict(imu_axes_source=(f"turned by {angle:.1f}° ± {est.angle_std_deg:.1f}° onto the image's rotation "
                                 f"(correlation {found['imu_axes_correlation_as_read']:.2f} as read, "
                                 f"{est.correlation:.2f} turned, over {est.n_pairs} pairs)"),
                imu_axes_rotation=np.round(total, 6).tolist(), **found)


def _focal(footage, guess: dict, prior: bool = True) -> dict:
    """The focal length's entries, measured against the gyro from ``footage``'s current one (the guess's), and
    set on ``footage``. With ``prior`` the measurement is weighed with the guess (the current focal length, at
    ``guess["rel_std"]``) by their log-normal errors: a stabilised image that barely turns measures it to ±26 %
    where the file's stated field of view gives ±5 %, and a guess is never replaced by something less sure."""
    from .focal_length import estimate_focal_length

    f0 = _raw_fx(footage)
    before = footage.camera, footage.lens_maps
    try:
        est = estimate_focal_length(footage)
    except FootageError as exc:
        footage.camera, footage.lens_maps = before  # the search leaves its last trial behind
        return dict(focal_length_px=f0, focal_length_rel_std=guess["rel_std"],
                    focal_length_source=f"{guess['source']}, not measured: {_why(exc)}")
    rel = float(np.hypot(est.slope_std, FOCAL_SYSTEMATIC_REL_STD))
    fx, rel_std = est.fx, rel
    source = (f"measured against the gyro (from {guess['source']}: {f0:.1f} px; pan/tilt correlation "
              f"{est.correlation:.2f} over {est.n_pairs} pairs")
    if prior:
        w_m, w_g = rel ** -2, guess["rel_std"] ** -2
        fx = float(np.exp((w_m * np.log(est.fx) + w_g * np.log(f0)) / (w_m + w_g)))
        rel_std = float((w_m + w_g) ** -0.5)
        source += f"; {est.fx:.1f} px ± {100 * rel:.0f} % measured, weighed with the guess's ± {100 * guess['rel_std']:.0f} %"
    _set_projection(footage, guess["model"], fx)
    return dict(focal_length_px=round(fx, 2), focal_length_rel_std=round(rel_std, 4), focal_length_source=source + ")")


def _lens_text(guess: dict) -> str:
    return ("pinhole (no distortion)" if guess["model"] == "pinhole"
            else f"equidistant fisheye ({guess['model']}, no coefficients)")


def _set_projection(footage, model: str, fx: float, source: str | None = None) -> None:
    """Read ``footage``'s frames through ``model`` ("pinhole", or "kannala-brandt": an equidistant fisheye, with the
    coefficients and resampling target it has, else none and the same K) of focal length ``fx`` (px; fy keeps its
    ratio), resampled onto a pinhole. ``source``: what the lens is said to come from (None: as it was)."""
    from dataclasses import replace

    from lobula.camera import PinholeCamera
    from lobula.lens import LensDistortion, undistortion_maps

    old = footage.distortion or {}
    raw = PinholeCamera(**old["raw_camera"]) if old else footage.camera
    raw = replace(raw, fx=fx, fy=fx * raw.fy / raw.fx)
    if model == "pinhole":
        footage.distortion, footage.lens_maps, footage.camera = None, None, raw
        return
    coeffs = list(old["coeffs"]) if old.get("model") == model else [0.0, 0.0, 0.0, 0.0]
    target = old.get("target_k", "same-k")
    footage.lens_maps, footage.camera = undistortion_maps(raw, LensDistortion(model, tuple(coeffs)), target)
    footage.distortion = dict(old, model=model, coeffs=coeffs, removed=True, target_k=target,
                              raw_camera=raw.to_dict(), source=source or old.get("source"))


def _raw_fx(footage) -> float:
    return float(footage.distortion["raw_camera"]["fx"] if footage.distortion else footage.camera.fx)


def _projection(footage, guess: dict, original: dict) -> tuple[dict, dict]:
    """(the lens guess to go on with, the projection_* entries): the radial ratio through ``guess``'s projection
    and through the other at the focal length ``footage`` has now; switches ``footage`` to the other where it is
    clearly nearer 1 (module doc). ``original``: the reader's guess, for the wording."""
    from .lens_projection import radial_rotation_ratio

    kept = footage.camera, footage.lens_maps, footage.distortion
    pinhole = guess["model"] == "pinhole"
    other = original if original["model"] != guess["model"] else \
        dict(model="kannala-brandt" if pinhole else "pinhole", coeffs=[0.0, 0.0, 0.0, 0.0] if pinhole else [],
             source=f"{guess['source']}, its projection measured", rel_std=guess["rel_std"])
    try:
        mine = radial_rotation_ratio(footage)
        _set_projection(footage, other["model"], _raw_fx(footage), other["source"])
        theirs = radial_rotation_ratio(footage)
    except FootageError as exc:
        footage.camera, footage.lens_maps, footage.distortion = kept
        kept_text = "the reader's guess" if guess is original else f"measured as {_lens_text(guess)}"
        return guess, dict(projection_source=f"{kept_text}, not checked further: {_why(exc)}")
    log_std = float(np.hypot(mine.log_std, theirs.log_std))
    ratios = {_lens_text(guess): round(mine.ratio, 3), _lens_text(other): round(theirs.ratio, 3)}
    gap = abs(np.log(mine.ratio)) - abs(np.log(theirs.ratio))
    chosen = other if gap > 3.0 * log_std and abs(np.log(mine.ratio)) > PROJECTION_MIN_LOG_RATIO else guess
    if chosen is guess:
        footage.camera, footage.lens_maps, footage.distortion = kept
    else:
        footage.lens_guess = other
        footage.notes.append(f"lens projection measured: {_lens_text(other)}; frames resampled through it")
    words = (", ".join(f"{r:.2f} read as {'a pinhole' if k.startswith('pinhole') else 'a fisheye'}"
                       for k, r in ratios.items()) + f" (± {log_std:.2f} in log; 1 for the right projection)")
    if chosen is not original:
        text = f"measured: the image's edge turns against its centre {words}"
    else:
        told = "as the image's rotation says" if -gap > 3.0 * log_std else \
            "the image's rotation cannot tell the projections apart here"
        text = f"the reader's guess, {told}: the image's edge turns against its centre {words}"
    return chosen, dict(projection_source=text, projection_radial_ratio=ratios,
                        projection_radial_ratio_log_std=round(log_std, 3))


def _why(exc: Exception) -> str:
    """The reason of a FootageError without the file's name in front (the note names the footage already)."""
    text = str(exc)
    return text.split(": ", 1)[1] if ": " in text else text


def self_calibrate(footage, clock: bool = True) -> dict:
    """Measure ``footage``'s clock offset (where ``clock``), IMU axes, focal length and projection from its gyro,
    in place.

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
        source, clock_offset_s (s) and its source, imu_axes_source (what was found of the IMU's axes) with,
        where measured, imu_axes_angle_deg and imu_axes_angle_std_deg (deg; the image's rotation against the
        axes as read), imu_axes_correlation where too low to tell and, where the IMU was turned,
        imu_axes_rotation (3×3, applied as ω ← R·ω); projection_source (whether the projection was measured)
        with, where it was, projection_radial_ratio ({projection: radial ratio}) and
        projection_radial_ratio_log_std; also set as ``footage.calibration``.
    """
    guess = footage.lens_guess
    pinhole = guess["model"] == "pinhole"
    out = dict(lens=_lens_text(guess))
    if footage.imu is None or footage.imu.gyro is None:
        out.update(focal_length_px=float(footage.camera.fx if pinhole else footage.distortion["raw_camera"]["fx"]),
                   focal_length_rel_std=guess["rel_std"],
                   focal_length_source=f"{guess['source']}, not measured: the footage has no gyro")
    else:
        if clock:
            out.update(_clock(footage))
        out.update(check_imu_axes(footage))
        if clock and "imu_axes_rotation" in out and out["clock_offset_source"].startswith("not identifiable"):
            out.update(_clock(footage))
        # the projection, checked at the guessed focal length (a fisheye read as a pinhole defeats the focal
        # length's search) and again at the measured one (where a wide pinhole and a fisheye part)
        if out.get("imu_axes_correlation", 1.0) < AXES_MIN_CORRELATION:
            chosen, projection = guess, dict(projection_source=(
                f"the reader's guess, not checked: the image's rotation does not follow the gyro's (correlation "
                f"{out['imu_axes_correlation']:.2f} at best)"))
        else:
            chosen, projection = _projection(footage, guess, guess)
        out.update(_focal(footage, chosen, prior=chosen is guess))
        if out["focal_length_source"].startswith("measured"):
            again, projection = _projection(footage, chosen, guess)
            if again is not chosen:  # the guess's focal length was one of the other projection's
                chosen = again
                out.update(_focal(footage, chosen, prior=False))
        out.update(projection, lens=_lens_text(chosen))
        if "imu_axes_rotation" in out and "measured against the gyro" in out["focal_length_source"]:
            out.update(check_imu_axes(footage, turned=out))
    footage.calibration = out
    footage.notes.append(f"camera self-calibrated (no calibration file): {json.dumps(out)}")
    return out
