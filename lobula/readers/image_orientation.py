"""The stabilised image's own orientation, where the camera writes it: the IMU turned into the image's frame.

A camera that stabilises electronically (GoPro HyperSmooth) warps each picture against its body, so the picture
turns as a smoothed virtual camera does, not as the gyro does: the image's rotation no longer follows the gyro,
and neither the gyro's derotation nor the self-calibration against the gyro (focal length, clock offset, IMU axes)
can work on it. GoPro's HERO8 and later and the MAX write, once per frame, the body's orientation (CORI) and the
image's relative to the body (IORI), unit quaternions (w, x, y, z) in the camera's axes.

Read as rotations of the camera frame (x right, y down, z forward), CORI is world → body and IORI body → image:

* the body, camera → world, is B = CORI⁻¹ — its angular velocity is the gyro's (:func:`body_rates`;
  :func:`gyro_agreement` checks it on each file);
* the image, image → world, is V = CORI⁻¹ · IORI⁻¹ = B · S with S = IORI⁻¹ (image → body), as Gyroflow composes
  CORI · IORI to stabilise.

On the MAX clip of ``../shared/data/gopro_walking`` the image's own least-squares rotation rates
(:func:`lobula.readers.clock_offset.image_rotation_rates`) correlate with V's at 0.95 / 0.98 / 0.83 (x, y, z), against
0.26 / 0.61 / −0.43 with the gyro's. :func:`image_frame_imu` makes the IMU the image's: its gyro V's angular
velocity (piecewise constant between the frames the quaternions belong to, so its integral over a frame
interval is V's turn there), its accelerometer the body's specific force in the image's axes, S⁻¹·a.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .core import IMU

__all__ = ["quaternion_rotations", "body_rates", "gyro_agreement", "image_frame_imu", "ImageOrientation",
           "MIN_GYRO_AGREEMENT", "MIN_CHECK_RATE"]

#: the least agreement of the body's rates read from CORI (B = CORI⁻¹) with the gyro's, 1 − Σ|ω_B − ω|²/Σ|ω|², for
#: the file's orientations to be read in the convention above: 0.90 on the MAX clip, −3.0 read the other way round
MIN_GYRO_AGREEMENT = 0.5
#: rad/s: the least RMS rate (all axes) at which that agreement means anything
MIN_CHECK_RATE = 0.02


def quaternion_rotations(q: np.ndarray) -> Rotation:
    """Rotations of unit quaternions q (n, 4) ordered w, x, y, z (any norm; normalised here)."""
    q = np.asarray(q, float)
    return Rotation.from_quat(np.c_[q[:, 1:4], q[:, :1]])


def body_rates(time_s: np.ndarray, rot: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """(interval mid-times (n − 1,) s, angular velocities (n − 1, 3) rad/s): the constant rate, in the rotating
    frame's own axes, that turns ``rot`` (n; frame → reference at ``time_s`` (n,) s) from each sample to the next."""
    t = np.asarray(time_s, float)
    return 0.5 * (t[:-1] + t[1:]), (rot[:-1].inv() * rot[1:]).as_rotvec() / np.diff(t)[:, None]


def _rates_at(time_s: np.ndarray, rot: Rotation, at: np.ndarray) -> np.ndarray:
    """(m, 3) rad/s: :func:`body_rates` of ``rot`` at times ``at`` (m,) s, held over each interval (the first and
    last interval's outside the samples)."""
    _, w = body_rates(time_s, rot)
    k = np.clip(np.searchsorted(time_s, at, side="right") - 1, 0, len(w) - 1)
    return w[k]


def gyro_agreement(time_s: np.ndarray, cori: np.ndarray, imu: IMU) -> tuple[float, float]:
    """(agreement, RMS rate rad/s): how well the body's angular velocity read from CORI (B = CORI⁻¹) matches the
    gyro's, both averaged over the quaternions' intervals, as 1 − Σ|ω_B − ω|²/Σ|ω|² over the intervals inside the
    IMU's record and all axes (1: the same, 0: no better than none, negative: turning the other way), and the
    gyro's RMS rate there. ``cori`` (n, 4) w, x, y, z at ``time_s`` (n,) s; ``imu`` in the camera frame."""
    from lobula.imu.resample import resample_to

    mid, w = body_rates(time_s, quaternion_rotations(cori).inv())
    edges = np.asarray(time_s, float)
    g = np.stack([resample_to(mid, imu.time_s, imu.gyro[:, j], np.diff(edges)) for j in range(3)], 1)
    inside = (edges[:-1] >= imu.time_s[0]) & (edges[1:] <= imu.time_s[-1])
    power = float(np.sum(g[inside] ** 2))
    if power == 0.0:
        return float("nan"), 0.0
    return 1.0 - float(np.sum((w[inside] - g[inside]) ** 2)) / power, float(np.sqrt(power / inside.sum()))


@dataclass
class ImageOrientation:
    """What :func:`image_frame_imu` did: ``imu`` (the IMU in the image's frame), ``gyro_agreement`` (as
    :func:`gyro_agreement`), ``max_deg`` and ``mean_deg`` (how far the image turns from the body, S's angle, deg)."""

    imu: IMU
    gyro_agreement: float
    max_deg: float
    mean_deg: float


def image_frame_imu(imu: IMU, time_s: np.ndarray, cori: np.ndarray, iori: np.ndarray) -> ImageOrientation:
    """The IMU turned into the stabilised image's frame (module doc).

    Parameters
    ----------
    imu : IMU
        The body's IMU in the camera frame, with a gyro.
    time_s : ndarray, (n,)
        s: the quaternions' times (the frames', on the video's clock).
    cori, iori : ndarray, (n, 4)
        CORI and IORI, w, x, y, z.

    Returns
    -------
    ImageOrientation

    Raises
    ------
    ValueError
        Saying why the orientations cannot be used: no gyro, fewer than 3 samples, times that do not increase,
        quaternions that are not finite or have no length, a camera turning at under :data:`MIN_CHECK_RATE` (too
        still to check them against the gyro), or CORI's rates not following the gyro's (:func:`gyro_agreement`
        under :data:`MIN_GYRO_AGREEMENT`: not the convention read here).
    """
    t = np.asarray(time_s, float)
    cori, iori = np.asarray(cori, float), np.asarray(iori, float)
    if imu.gyro is None:
        raise ValueError("the IMU has no gyro to check them against")
    if len(t) < 3 or cori.shape != (len(t), 4) or iori.shape != (len(t), 4):
        raise ValueError(f"they need 3 or more samples of 4 values each, paired with their times (got {len(t)} "
                         f"times, CORI {cori.shape}, IORI {iori.shape})")
    if not np.all(np.diff(t) > 0):
        raise ValueError("their times do not increase")
    norms = np.linalg.norm(np.concatenate([cori, iori]), axis=1)
    if not np.all(np.isfinite(norms) & (norms > 0.5)):
        raise ValueError(f"{int(np.sum(~(np.isfinite(norms) & (norms > 0.5))))} of their quaternions are not unit "
                         f"quaternions (not finite, or of length under 0.5)")
    agreement, rate = gyro_agreement(t, cori, imu)
    if not rate >= MIN_CHECK_RATE:
        raise ValueError(f"the camera turns too little to check them against the gyro ({rate:.3f} rad/s RMS, "
                         f"{MIN_CHECK_RATE} needed)")
    if not agreement >= MIN_GYRO_AGREEMENT:
        raise ValueError(f"CORI's rates do not follow the gyro's (agreement {agreement:.2f}, {MIN_GYRO_AGREEMENT} "
                         f"needed)")
    body = quaternion_rotations(cori).inv()
    s = quaternion_rotations(iori).inv()  # image → body
    image = body * s
    gyro = _rates_at(t, image, imu.time_s)
    s_at = Slerp(t, s)(np.clip(imu.time_s, t[0], t[-1]))
    accel = s_at.inv().apply(imu.accel)
    ang = np.degrees(s.magnitude())
    return ImageOrientation(IMU(imu.time_s, accel, gyro, imu.source, imu.nan_counts), agreement, float(ang.max()),
                            float(ang.mean()))
