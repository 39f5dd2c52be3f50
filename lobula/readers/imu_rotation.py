"""The rotation between the IMU's axes and the camera's, measured from the footage: the gyro against the image.

A camera and an IMU fixed to one body turn together: the image's angular velocity ω_img (camera frame; dense
flow between consecutive frames, the least-squares angular velocity of its rotational field, as for the clock
offset: :func:`lobula.readers.clock_offset.image_rotation_rates`) is R·ω_gyro, with R the rotation from the
axes the IMU's samples are given in to the camera's. A focal length off by a factor s reads the pan and tilt
rates s times too fast and the roll not at all, and the flow under-reads every axis alike, so the fit is

    ω_img ≈ D·R·ω_gyro,   D = diag(s_pan/tilt, s_pan/tilt, s_roll),

solved by alternating Wahba's problem for R (the SVD solution, Kabsch's) with least squares for the two
scales. The standard error of R's angle comes from the residuals through the problem linearised about the
solution (δθ ↦ −D·[R·ω_gyro]×·δθ), plus :data:`ROTATION_SYSTEMATIC_DEG`. It needs rotation about at least
two axes: about one axis alone, any turn about that axis fits as well.

A camera that walks, bounces and sways moves the image as a turn would, and the image's least-squares rates
take that for rotation. :func:`refine_with_translation` fits the flow itself instead: the rotational field of
D·R·ω_gyro plus a translation from one epipole per frame pair
(:func:`lobula.readers.gyro_scale.rotation_field_scales`), R's standard error a jackknife over blocks of time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .core import FootageError, rotation_deg

__all__ = ["ImuRotation", "wahba_rotation", "fit_imu_rotation", "refine_with_translation", "MIN_ROTATION_RAD_S",
           "ROTATION_SYSTEMATIC_DEG"]

#: rad/s: the RMS gyro rate the footage needs about its second most turned axis for R to be measured
MIN_ROTATION_RAD_S = 0.05
#: deg, 1σ: what the residuals' standard error leaves out (consecutive frame pairs' errors are correlated,
#: translation adds flow that seconds of footage do not average out)
ROTATION_SYSTEMATIC_DEG = 1.0
#: rad: how far :func:`refine_with_translation` may turn the axes from the image's rates' answer (a walk's sway
#: turns that answer by up to about 6°)
REFINE_TURN_RAD = 0.2


@dataclass
class ImuRotation:
    """rotation (3, 3): R, with ω_camera = R @ ω_IMU for the IMU's samples as given; angle_deg, angle_std_deg
    (deg): R's angle and its 1σ; scales (2,): the image's pan/tilt and roll rates over the rotated gyro's
    (dimensionless); correlation: of the image's rates with D·R·ω_gyro; correlation_as_given: with the gyro as
    given (R = I, the same scales); n_pairs: frame pairs used."""

    rotation: np.ndarray
    angle_deg: float
    angle_std_deg: float
    scales: tuple[float, float]
    correlation: float
    correlation_as_given: float
    n_pairs: int


def wahba_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation R (3, 3) minimising Σ |a_i − R·b_i|² over the rows of ``a`` and ``b`` (n, 3) (Kabsch's SVD
    solution of Wahba's problem; det R = +1)."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _correlation(a: np.ndarray, m: np.ndarray) -> float:
    den = np.sqrt((a ** 2).sum() * (m ** 2).sum())
    return float((a * m).sum() / den) if den > 0 else float("nan")


def _scales(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Least-squares scales of ``a`` over ``m`` (n, 3): one for the first two axes together, one for the third."""
    s_xy = (a[:, :2] * m[:, :2]).sum() / max((m[:, :2] ** 2).sum(), 1e-300)
    s_z = (a[:, 2] * m[:, 2]).sum() / max((m[:, 2] ** 2).sum(), 1e-300)
    return np.array([s_xy, s_xy, s_z])


def fit_imu_rotation(w_img: np.ndarray, w_gyro: np.ndarray, iterations: int = 20, where: str = "footage"
                     ) -> ImuRotation:
    """Fit ω_img ≈ D·R·ω_gyro (see the module doc) to matched samples.

    Parameters
    ----------
    w_img : (n, 3) rad/s
        The image's angular velocity, camera frame (x right, y down, z forward), one row per frame pair.
    w_gyro : (n, 3) rad/s
        The gyro at the same times, in the axes its samples are given in.
    iterations : int
        Alternations of R and D at most.
    where : str
        The footage, named in the error.

    Raises
    ------
    FootageError
        Too few pairs, or too little rotation about a second axis, for R to be measured.
    """
    a, g = w_img - w_img.mean(0), w_gyro - w_gyro.mean(0)
    if len(a) < 10:
        raise FootageError(f"{where}: fewer than 10 frame pairs with gyro samples around them")
    spread = np.sqrt(np.linalg.eigvalsh(g.T @ g / len(g)))   # RMS rate about the principal axes, ascending
    if spread[1] < MIN_ROTATION_RAD_S:
        raise FootageError(f"{where}: the footage turns about one axis at most (gyro RMS {spread[1]:.3f} rad/s "
                           f"about the second, < {MIN_ROTATION_RAD_S}), too little to tell the IMU's axes")
    d = np.ones(3)
    for _ in range(max(1, iterations)):
        r = wahba_rotation(a / d, g)
        d_new = _scales(a, g @ r.T)
        if np.any(d_new <= 0):
            break
        converged = np.abs(d_new - d).max() < 1e-6
        d = d_new
        if converged:
            break
    m = (g @ r.T) * d
    res = a - m
    dof = max(res.size - 5, 1)                               # three angles and two scales
    sigma2 = float((res ** 2).sum() / dof)
    jac = -d[None, :, None] * _cross_matrices(g @ r.T)        # (n, 3, 3): ∂m/∂δθ
    info = np.einsum("nij,nik->jk", jac, jac)
    cov = sigma2 * np.linalg.pinv(info)
    std = float(np.hypot(np.degrees(np.sqrt(max(np.trace(cov), 0.0))), ROTATION_SYSTEMATIC_DEG))
    return ImuRotation(rotation=r, angle_deg=rotation_deg(r), angle_std_deg=std,
                       scales=(float(d[0]), float(d[2])), correlation=_correlation(a, m),
                       correlation_as_given=_correlation(a, g * d), n_pairs=int(len(a)))


def _cross_matrices(v: np.ndarray) -> np.ndarray:
    """[v]× (n, 3, 3) for the rows of ``v`` (n, 3): [v]×·u = v × u; m + δθ × m = m − [m]×·δθ."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1),
                     np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], 1)


def refine_with_translation(start: ImuRotation, samples, w_img: np.ndarray, w_gyro: np.ndarray) -> ImuRotation:
    """R fitted to the flow with the translation alongside (module doc), from :func:`fit_imu_rotation`'s ``start``.

    Parameters
    ----------
    start : the fit to the image's least-squares rates.
    samples : :class:`lobula.readers.clock_offset.FlowSamples` of the same n frame pairs.
    w_img, w_gyro : (n, 3) rad/s, the image's least-squares rates (for the correlations) and the gyro.
    """
    from scipy.spatial.transform import Rotation

    from lobula.epipole import rotational_flow

    from .gyro_scale import at_bound, jackknife_std, rotation_field_scales, search_bounds, thinned

    x, y, flow = thinned(samples.x, samples.y, samples.flow)
    basis = [rotational_flow(e, x, y) for e in np.eye(3)]
    g = np.asarray(w_gyro, float)

    def fields(sl):       # (9, frames, 2, m): image axis i turning with gyro axis j, entry M[i, j]
        return np.stack([g[sl, j, None, None] * basis[i] for i in range(3) for j in range(3)])

    def scales(p):        # M = D·R, R a turn p[:3] (rotation vector, rad) after the start's, D = diag(p3, p3, p4)
        return (np.array([p[3], p[3], p[4]])[:, None] * (start.rotation @ Rotation.from_rotvec(p[:3]).as_matrix())
                ).ravel()

    bounds = [(-REFINE_TURN_RAD, REFINE_TURN_RAD)] * 3 + [search_bounds(s) for s in start.scales]
    p0 = np.array([0.0, 0.0, 0.0] + [float(np.clip(s, *b)) for s, b in zip(start.scales, bounds[3:])])
    p, reps = rotation_field_scales(x, y, flow, fields, k0=p0, scales=scales, bounds=bounds)
    if any(at_bound(v, b) for v, b in zip(p[:3], bounds)):
        return start          # the translation takes the turn for its own: the image's rates alone decide
    r = start.rotation @ Rotation.from_rotvec(p[:3]).as_matrix()
    std = float(np.hypot(np.degrees(np.sqrt(sum(jackknife_std(reps[:, c]) ** 2 for c in range(3)))),
                         ROTATION_SYSTEMATIC_DEG))
    d = np.array([p[3], p[3], p[4]])
    a, gc = w_img - w_img.mean(0), g - g.mean(0)
    return ImuRotation(rotation=r, angle_deg=rotation_deg(r), angle_std_deg=std, scales=(float(p[3]), float(p[4])),
                       correlation=_correlation(a, (gc @ r.T) * d), correlation_as_given=_correlation(a, gc * d),
                       n_pairs=int(len(a)))

