"""The focal length, estimated from the footage itself: the gyro's rotation against the image's.

A camera turning at ω (rad/s) moves the image by f·ω pixels per second near its centre, whatever
the scene; a wrong focal length f₀ for a true f reads the pan and tilt rates scaled by f/f₀ (roll, about
the optical axis, not at all). The image's flow is measured between consecutive frames
(:func:`lobula.readers.clock_offset.image_flow_samples`: DIS flow) through the camera the footage states,
and the gyro's rotation scaled by k (pan and tilt) and k_roll (roll) is fitted to it alongside the
translation's flow (:func:`gyro_scale_with_translation`): what is left once the rotation is taken out must
radiate from one epipole per frame pair, at whatever depths. A camera that walks, bounces and sways
moves the image as a turn would, and a fit of the rotation alone reads it as one: 2.6-18 % off on
hand-held walks where this fit reads 0.1-3.1 %. k is the ratio f/f₀; the camera is rescaled by it and measured
again until k is 1 (a distorted lens's map onto a pinhole makes the ratio hold only near the centre at
first). Its standard error is a jackknife over blocks of time, since the translation's leak into k comes
and goes with the motion. Too little rotation, or image and gyro rates that do not agree, is an error: the
focal length is then not identifiable from this footage and must be given.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .core import FootageError

#: rad/s: the gyro's RMS pan and tilt rate a footage needs for its focal length to be measured
MIN_ROTATION_RAD_S = 0.1
#: px: the width the flow is computed at (at 160 px DIS reads a turning panels scene's rotation 5-25 % slow)
FLOW_WIDTH_PX = 320
#: a step's scale this near 1 ends the search where it is within two standard errors of 1
CLOSE_ENOUGH = 0.05
#: the distance (normalised, in units of the homogeneous epipole's length) from the epipole within which a point's
#: flow direction tells nothing of it (for the robust weights)
MIN_EPIPOLE_DISTANCE = 0.05


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


def _cross(x, y, field):
    """(n, m, 3): per point the vector whose dot product with a homogeneous epipole (e_x, e_y, e_z) is the flow
    ``field`` (n, 2, m) 1/s crossed with the direction from that epipole — the part no translation from it makes."""
    u, v = field[:, 0], field[:, 1]
    return np.stack([v, -u, u * y - v * x], -1)


def _profiled_cost(k, normal, whiten):
    """Σ over frame pairs of the smallest generalised eigenvalue of the residual flow's 3×3 normal matrix (for
    flow − k[0]·rot_pt − k[1]·rot_roll, from ``normal`` (n, 3, 3, 3, 3)) against the flow noise's (whitened by
    ``whiten`` (n, 3, 3), the inverse of its Cholesky factor); also the epipoles (n, 3)."""
    kap = np.array([1.0, -k[0], -k[1]])
    m = np.einsum("a,b,nabpq->npq", kap, kap, normal)
    lam, vec = np.linalg.eigh(whiten @ m @ whiten.transpose(0, 2, 1))
    return float(lam[:, 0].sum()), (whiten.transpose(0, 2, 1) @ vec[:, :, :1])[:, :, 0]


def _minimise(normal, whiten, k0):
    from scipy.optimize import minimize

    return minimize(lambda k: _profiled_cost(k, normal, whiten)[0], k0, method="Nelder-Mead",
                    options=dict(xatol=1e-5, fatol=0.0, maxiter=400)).x


def gyro_scale_with_translation(x: np.ndarray, y: np.ndarray, flow: np.ndarray, gyro: np.ndarray,
                                blocks: int = 12, robust_iters: int = 5) -> tuple[float, float, float]:
    """The scale of the gyro's rotation in the image's flow, with the translation's flow fitted alongside.

    Parameters
    ----------
    x, y : (m,) normalised coordinates of the sampled points.
    flow : (n, 2, m) 1/s, the flow at the points per frame pair.
    gyro : (n, 3) rad/s, the gyro at the frame pairs' mid times, in the camera's axes.
    blocks : contiguous blocks of frame pairs for the jackknife (its standard error is widened by Student's t for
        ``blocks`` − 1 degrees of freedom over the normal's, so that ±2σ holds about 95 %).
    robust_iters : reweightings of the points (Huber weights on the epipolar residual).

    Returns
    -------
    (k, k_std, k_roll): the pan/tilt scale (f/f₀ for a camera opened at focal length f₀), its jackknife
    standard error, and the roll's scale. The flow is modelled as the rotational field of (k·ω_x, k·ω_y,
    k_roll·ω_z) plus a translation radiating from one epipole per frame pair (a homogeneous point, so at
    infinity too) at any depths. For given scales the best epipole of a frame pair is the smallest eigenvector
    of its residual's 3×3 normal matrix, whose eigenvalue is what is left; the scales minimise its sum.
    """
    from lobula.epipole import rotational_flow

    x, y = np.asarray(x, float), np.asarray(y, float)
    g = np.asarray(gyro, float)
    bx, by, bz = (rotational_flow(e, x, y) for e in np.eye(3))
    fields = (np.asarray(flow, float), g[:, 0, None, None] * bx + g[:, 1, None, None] * by,
              g[:, 2, None, None] * bz)
    c = np.stack([_cross(x, y, f) for f in fields], 2)                  # (n, m, 3 fields, 3)
    n, m = c.shape[:2]
    # the crossed flow's covariance per unit of isotropic flow noise, point by point: dividing by it (a generalised
    # eigenproblem) keeps the noise from pulling the epipoles towards the points, and the scales with them
    q = np.zeros((m, 3, 3))
    q[:, 0, 0] = q[:, 1, 1] = 1.0
    q[:, 0, 2] = q[:, 2, 0] = -x
    q[:, 1, 2] = q[:, 2, 1] = -y
    q[:, 2, 2] = x * x + y * y
    k, w = np.ones(2), np.ones((n, m))
    for _ in range(robust_iters):
        cw = (c * np.sqrt(w)[..., None, None]).reshape(n, m, 9)
        normal = (cw.transpose(0, 2, 1) @ cw).reshape(n, 3, 3, 3, 3).transpose(0, 1, 3, 2, 4)
        whiten = np.linalg.inv(np.linalg.cholesky(np.einsum("nm,mpq->npq", w, q)))
        k = _minimise(normal, whiten, k)
        e = _profiled_cost(k, normal, whiten)[1]
        # the residual flow's component across the direction from the epipole, 1/s
        dist2 = np.maximum((e[:, 0, None] - x * e[:, 2, None]) ** 2 + (e[:, 1, None] - y * e[:, 2, None]) ** 2,
                           MIN_EPIPOLE_DISTANCE ** 2 * (e ** 2).sum(1, keepdims=True))
        res = np.abs(np.einsum("nmap,a,np->nm", c, np.array([1.0, -k[0], -k[1]]), e)) / np.sqrt(dist2)
        # Huber weights: flow at occlusions and on the fastest, nearest surfaces reads worst
        w = 1.0 / np.maximum(1.0, res / (2.0 * 1.4826 * np.median(res) + 1e-12))
    ks = np.array([_minimise(np.delete(normal, p, 0), np.delete(whiten, p, 0), k)
                   for p in np.array_split(np.arange(n), blocks)])
    from scipy.stats import norm, t

    widen = t.ppf(0.975, blocks - 1) / norm.ppf(0.975)
    k_std = float(widen * np.sqrt((blocks - 1) / blocks * ((ks[:, 0] - ks[:, 0].mean()) ** 2).sum()))
    return float(k[0]), k_std, float(k[1])


def _slope(footage, max_frames: int) -> tuple[float, float, float, int, float]:
    """(k, its standard error, correlation, pairs, k_roll) of ``footage`` as opened
    (:func:`gyro_scale_with_translation`; the correlation is of the image's least-squares pan and tilt rates
    with the gyro's)."""
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
    k, k_std, k_roll = gyro_scale_with_translation(samples.x, samples.y, samples.flow[ok], g)
    return k, k_std, corr, int(ok.sum()), k_roll


def estimate_focal_length(footage, iterations: int = 4, tolerance: float = 0.002, min_correlation: float = 0.7,
                          max_frames: int = 900) -> FocalEstimate:
    """Estimate the focal length of ``footage``'s camera from its gyro (see the module doc).

    The footage is opened with a first guess (its camera.json, or ``--camera``; a distorted lens's
    map is remade at each step). ``iterations``: at most this many rescalings; ``tolerance``: stop when the
    scale is within this of 1, or within two of its standard errors and :data:`CLOSE_ENOUGH`; ``min_correlation``:
    below it the image and gyro rates are taken not to agree (FootageError); ``max_frames``: the frames read at each step. The clock offset must already be applied
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
        slope, slope_std, corr, n, roll = _slope(footage, max_frames)
        steps.append(round(slope, 5))
        if corr < min_correlation or not 0.2 < slope < 5.0:
            what = (f"correlate only {corr:.2f} with the gyro's (< {min_correlation})" if corr < min_correlation
                    else f"follow the gyro's with a slope of {slope:.3f} (outside 0.2-5)")
            raise FootageError(f"{footage.path}: the image's pan and tilt rates {what}; the focal length is not "
                               f"identifiable here "
                               f"(too much translation, electronic stabilisation, or a clock offset): give it in a "
                               f"camera.json")
        scale *= slope
        # within what the slope can tell; a step far from 1 (a fisheye's map made at a focal length far off fits the
        # model poorly, and its spread with it) is taken whatever its spread
        if abs(slope - 1.0) < max(tolerance, min(2.0 * slope_std, CLOSE_ENOUGH)):
            break
    return FocalEstimate(raw.fx * scale, raw.fy * scale, scale, corr, slope_std, n, steps, roll)
