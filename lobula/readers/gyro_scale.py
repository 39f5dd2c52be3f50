"""The gyro's rotation in the image's flow, scaled, with the translation's flow fitted alongside.

A camera that turns at ω and moves at T sees flow that is the rotational field of ω plus a translational one
radiating from the epipole e = T/T_z, each point's length set by its unknown depth. A fit of the rotation alone
takes the part of the translation that looks like a turn (a walk's sway like a pan, its bounce like a tilt) for
rotation. Here the flow is modelled as Σ_j k_j·F_j, fields F_j made from the gyro (its pan and tilt and its roll
for the focal length; each of its axes turning the image about each of the camera's for the IMU's axes), plus a
translation from one epipole per frame pair at any depths. Crossing the residual flow with the direction from a
homogeneous epipole e (a point at infinity too) leaves what no translation from e makes; for given scales the
best e of a frame pair is the smallest generalised eigenvector of the 3×3 normal matrix of those crossed
residuals, taken against the flow noise's own normal matrix (without it, noise pulls the epipoles towards the
points and the scales with them: +4 % at 0.05 1/s of noise), and its eigenvalue is what is left. The scales
minimise the sum over frame pairs (BFGS with the eigenvalues' exact gradient), with Huber weights on each
point's residual across the epipolar direction, near a fit of the rotation alone: with a narrow view or a small
image the translation can take a turn for its own, and the cost a second minimum far from the truth. Their
spread is a jackknife over contiguous blocks of time, since the translation's leak comes and goes with the
motion.
"""
from __future__ import annotations

import numpy as np

__all__ = ["rotation_field_scales", "jackknife_std", "gyro_fields", "gyro_scale_with_translation", "thinned",
           "search_bounds", "at_bound", "MIN_EPIPOLE_DISTANCE", "FIT_POINTS", "SEARCH_FACTOR"]

#: the distance (normalised, in units of the homogeneous epipole's length) from the epipole within which a point's
#: flow direction tells nothing of it (for the robust weights)
MIN_EPIPOLE_DISTANCE = 0.05
#: the most sampled points a fit uses: a few scales or angles are as well fitted on 1,500 of DIS's 3,000 points
#: (a walk's focal-length scale: 1.02875 on 3,072 points, 1.02886 on 1,536) at a third of the time
FIT_POINTS = 1500
#: how far from a fit of the rotation alone the scales are searched (a walk's sway moves that fit by up to 18 %)
SEARCH_FACTOR = 1.5


def at_bound(value: float, bounds: tuple[float, float]) -> bool:
    """Whether a fitted ``value`` ended on (within 0.1 % of the width of) either end of its search ``bounds``: the
    fit found no minimum inside them."""
    lo, hi = bounds
    return min(value - lo, hi - value) < 1e-3 * (hi - lo)


def search_bounds(scale: float) -> tuple[float, float]:
    """(low, high) of a scale's search around a fit of the rotation alone that read ``scale``
    (:data:`SEARCH_FACTOR`); 0.2-5 where that fit read none (too little rotation about the axis)."""
    return (scale / SEARCH_FACTOR, scale * SEARCH_FACTOR) if scale > 0.2 else (0.2, 5.0)


def thinned(x: np.ndarray, y: np.ndarray, flow: np.ndarray, most: int = FIT_POINTS):
    """(x, y, flow) at every k-th of the m points, the least k leaving at most ``most``: x, y (m,), flow (n, 2, m)."""
    step = -(-len(x) // most)
    return x[::step], y[::step], flow[:, :, ::step]


def _cross(x, y, field):
    """(n, m, 3): per point the vector whose dot product with a homogeneous epipole (e_x, e_y, e_z) is the flow
    ``field`` (n, 2, m) 1/s crossed with the direction from that epipole — the part no translation from it makes."""
    u, v = field[:, 0], field[:, 1]
    return np.stack([v, -u, u * y - v * x], -1)


def _profiled_cost(k, normal, whiten):
    """Σ over frame pairs of the smallest generalised eigenvalue of the residual flow's 3×3 normal matrix (for
    flow − Σ_j k[j]·field_j, from ``normal`` (n, J+1, J+1, 3, 3)) against the flow noise's (whitened by ``whiten``
    (n, 3, 3), the inverse of its Cholesky factor); its gradient in k (J,) and the epipoles (n, 3)."""
    kap = np.concatenate([[1.0], -np.asarray(k, float)])
    m = np.einsum("a,b,nabpq->npq", kap, kap, normal)
    lam, vec = np.linalg.eigh(whiten @ m @ whiten.transpose(0, 2, 1))
    e = (whiten.transpose(0, 2, 1) @ vec[:, :, :1])[:, :, 0]
    # an eigenvalue's derivative is the matrix's derivative between its eigenvectors
    grad = -2.0 * (np.einsum("np,nabpq,nq->ab", e, normal, e) @ kap)[1:]
    return float(lam[:, 0].sum()), grad, e


def _identity(p):
    return p


def _minimise(normal, whiten, p0, scales=_identity, bounds=None):
    """The parameters p minimising :func:`_profiled_cost` of k = ``scales(p)`` (BFGS, L-BFGS-B within ``bounds``;
    the gradient through the map's Jacobian, by central differences where the map is not the identity)."""
    from scipy.optimize import minimize

    def cost(p):
        c, grad, _ = _profiled_cost(scales(p), normal, whiten)
        if scales is _identity:
            return c, grad
        h = 1e-6
        jac = np.stack([(scales(p + h * d) - scales(p - h * d)) / (2 * h) for d in np.eye(len(p))], -1)
        return c, grad @ jac

    p0 = np.asarray(p0, float)
    c0 = _profiled_cost(scales(p0), normal, whiten)[0]
    if bounds is not None:
        return minimize(cost, p0, jac=True, method="L-BFGS-B", bounds=bounds,
                        options=dict(ftol=1e-13, gtol=1e-9 * c0)).x
    return minimize(cost, p0, jac=True, method="BFGS", options=dict(gtol=1e-9 * c0, xrtol=1e-7)).x


def rotation_field_scales(x: np.ndarray, y: np.ndarray, flow: np.ndarray, fields, k0=None, blocks: int = 12,
                          robust_iters: int = 5, chunk: int = 64, scales=None,
                          bounds=None) -> tuple[np.ndarray, np.ndarray]:
    """The scales k (J,) with which rotational ``fields`` explain ``flow``, a translation from one epipole per frame
    pair fitted alongside (module doc).

    Parameters
    ----------
    x, y : (m,) normalised coordinates of the sampled points.
    flow : (n, 2, m) 1/s, the flow at the points per frame pair.
    fields : callable
        ``fields(frames)`` for a slice of the n frame pairs: (J, frames, 2, m) 1/s, the rotational fields (from
        the gyro) the flow is made of, up to their scales; made a chunk of frame pairs at a time, so that many
        fields of a long record need little memory.
    k0 : the scales (J,) to start from (ones where None), or the parameters (P,) where ``scales`` is given.
    blocks : contiguous blocks of frame pairs left out in turn for the jackknife.
    robust_iters : reweightings of the points (Huber weights on the epipolar residual).
    chunk : frame pairs crossed at a time.
    scales : callable, optional
        ``scales(p)``: the J scales made of P parameters (a rotation and two scales, say), fitted in their stead.
    bounds : sequence of (low, high), optional
        Per scale (or parameter), where the search stays: a fit of the rotation alone put near, since with a
        narrow view or a small image the translation can take a turn for itself far from it.

    Returns
    -------
    (k (J,) or p (P,), replicates (blocks, J or P)): the scales (or parameters), and the jackknife's without each
    block (:func:`jackknife_std`).
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    n, m = len(flow), len(x)
    parts = [slice(i, min(i + chunk, n)) for i in range(0, n, chunk)]
    to_k = scales or _identity

    def crossed(sl):                                  # (frames, m, J + 1, 3)
        return np.stack([_cross(x, y, np.asarray(f, float)) for f in (flow[sl], *fields(sl))], 2)

    # the crossed flow's covariance per unit of isotropic flow noise, point by point: dividing by it (a generalised
    # eigenproblem) keeps the noise from pulling the epipoles towards the points, and the scales with them
    q = np.zeros((m, 3, 3))
    q[:, 0, 0] = q[:, 1, 1] = 1.0
    q[:, 0, 2] = q[:, 2, 0] = -x
    q[:, 1, 2] = q[:, 2, 1] = -y
    q[:, 2, 2] = x * x + y * y
    w = np.ones((n, m))
    k = None if k0 is None else np.asarray(k0, float)
    for _ in range(robust_iters):
        normal = []
        for sl in parts:
            c = crossed(sl)
            nf = c.shape[2]
            cw = (c * np.sqrt(w[sl])[..., None, None]).reshape(len(c), m, 3 * nf)
            normal.append((cw.transpose(0, 2, 1) @ cw).reshape(len(c), nf, 3, nf, 3).transpose(0, 1, 3, 2, 4))
        normal = np.concatenate(normal)
        k = np.ones(nf - 1) if k is None else k
        whiten = np.linalg.inv(np.linalg.cholesky(np.einsum("nm,mpq->npq", w, q)))
        k = _minimise(normal, whiten, k, to_k, bounds)
        e = _profiled_cost(to_k(k), normal, whiten)[2]
        # the residual flow's component across the direction from the epipole, 1/s
        dist2 = np.maximum((e[:, 0, None] - x * e[:, 2, None]) ** 2 + (e[:, 1, None] - y * e[:, 2, None]) ** 2,
                           MIN_EPIPOLE_DISTANCE ** 2 * (e ** 2).sum(1, keepdims=True))
        kap = np.concatenate([[1.0], -to_k(k)])
        res = np.concatenate([np.abs(np.einsum("nmap,a,np->nm", crossed(sl), kap, e[sl])) for sl in parts])
        res /= np.sqrt(dist2)
        # Huber weights: flow at occlusions and on the fastest, nearest surfaces reads worst
        w = 1.0 / np.maximum(1.0, res / (2.0 * 1.4826 * np.median(res) + 1e-12))
    replicates = np.array([_minimise(np.delete(normal, p, 0), np.delete(whiten, p, 0), k, to_k, bounds)
                           for p in np.array_split(np.arange(n), blocks)])
    return k, replicates


def jackknife_std(replicates: np.ndarray) -> float:
    """The jackknife standard error from a quantity's B leave-one-block-out ``replicates`` (B,), widened by
    Student's t for B − 1 degrees of freedom over the normal's, so that ±2σ holds about 95 %."""
    from scipy.stats import norm, t

    b = len(replicates)
    widen = t.ppf(0.975, b - 1) / norm.ppf(0.975)
    return float(widen * np.sqrt((b - 1) / b * ((replicates - replicates.mean()) ** 2).sum()))


def gyro_fields(x: np.ndarray, y: np.ndarray, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotational fields (n, 2, m) 1/s of the gyro's pan and tilt and of its roll, at points x, y (m,)
    (normalised) for gyro (n, 3) rad/s in the camera's axes."""
    from lobula.epipole import rotational_flow

    g = np.asarray(gyro, float)
    bx, by, bz = (rotational_flow(e, x, y) for e in np.eye(3))
    return g[:, 0, None, None] * bx + g[:, 1, None, None] * by, g[:, 2, None, None] * bz


def gyro_scale_with_translation(x: np.ndarray, y: np.ndarray, flow: np.ndarray, gyro: np.ndarray,
                                blocks: int = 12, near=None) -> tuple[float, float, float]:
    """The gyro's pan/tilt scale in the image's flow, with its standard error and the roll's scale.

    x, y (m,): normalised coordinates of the points; flow (n, 2, m) 1/s; gyro (n, 3) rad/s at the frame pairs'
    mid times, in the camera's axes; blocks: for the jackknife; near: (pan/tilt, roll) scales of a fit of the
    rotation alone, where given the start and the bounds of the search (:func:`search_bounds`). Returns (k, k_std, k_roll): the flow is the rotational field of (k·ω_x, k·ω_y, k_roll·ω_z) plus a
    translation (:func:`rotation_field_scales`); k is f/f₀ for a camera opened at focal length f₀.
    """
    g = np.asarray(gyro, float)
    bounds = None if near is None else [search_bounds(s) for s in near]
    k0 = None if near is None else [float(np.clip(s, *b)) for s, b in zip(near, bounds)]
    k, reps = rotation_field_scales(x, y, flow, lambda sl: np.stack(gyro_fields(x, y, g[sl])), k0=k0,
                                    blocks=blocks, bounds=bounds)
    return float(k[0]), jackknife_std(reps[:, 0]), float(k[1])
