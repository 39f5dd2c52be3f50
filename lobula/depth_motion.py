"""What the flow can tell about depth: per-pixel flow precision, ill-conditioning near the
epipole, and the rotation a gyroscope leaves behind.

Used by the depth estimators of :mod:`lobula.depth` (TV's data weights, the ratio map's
mask) and by the ranging pass (:mod:`experiments.depth_stream`). Shapes and units as
there: flow (2, H, W) in normalised coordinates per second (1/s), epipole (ex, ey)
normalised. Every array input may be numpy or torch; outputs follow the input's kind (numpy
inputs are computed with numpy: no torch needed).
"""
from __future__ import annotations

import math

import numpy as np

from ._optional import is_tensor, torch
from lobula.camera import PinholeCamera
from lobula.depth.geometry import (_as_array, _check_flow, _clamp, _epipole, _grid, _like_input, _median_low, _offsets,
                                   _quiet, _xp)
from lobula.epipole import EpipoleEstimator, rotational_flow

__all__ = ["flow_noise", "precision_weights", "translational_snr", "refine_motion"]

# ----------------------------------------------------------------------------- flow precision
def flow_noise(flow, camera: PinholeCamera, epipole, window_deg: float = 3.0):
    """Per-pixel flow noise σ (1/s, (H, W)) of derotated flow, from the flow itself.

    Under rigid translation the (derotated) flow is radial from the epipole, so its
    component perpendicular to p − e, n = ⟨ṗ, (p−e)⊥⟩/|p−e|, is pure error: flow noise,
    what is left of the rotation, a wrong epipole, non-rigid motion. Its local mean
    square over a square window of ``window_deg`` (degrees of view) estimates σ² of
    each flow component there (isotropic noise); pixels where the direction is
    undefined (at the epipole) or the flow is not finite do not contribute. A floor of
    (σ_image / 2)², σ_image = 1.4826·median|n| over the image, keeps a locally lucky
    patch from claiming perfect flow. Same array kind as ``flow``.

    flow (2, H, W) 1/s: derotated normalised flow (numpy or torch); camera: its (H, W) camera;
    epipole (2,): normalised.
    """
    f, as_numpy = _check_flow(flow, camera)
    xp = _xp(f)
    q = _offsets(camera, epipole, f)
    nq = xp.sqrt((q * q).sum(0))
    ok = xp.isfinite(f).all(0) & (nq > 0)
    with _quiet(f):
        n = xp.where(ok, (f[1] * q[0] - f[0] * q[1]) / _clamp(nq, 1e-30), xp.zeros_like(nq))
    if not bool(ok.any()):
        return _like_input(xp.full_like(nq, float("nan")), as_numpy)
    k = max(3, int(round(math.radians(window_deg) * float(camera.fx))) | 1)
    if is_tensor(f):
        import torch.nn.functional as F

        m = ok.to(f.dtype)
        num = F.avg_pool2d((n * n)[None, None], k, stride=1, padding=k // 2, count_include_pad=False)[0, 0]
        den = F.avg_pool2d(m[None, None], k, stride=1, padding=k // 2, count_include_pad=False)[0, 0]
        local = num / den.clamp(min=1e-12)
    else:
        # Window sums: the window's mean square over its valid pixels is their ratio; den counts
        # the valid pixels exactly (sums of 0/1), so den > 0 means at least one.
        num, den = _window_sum(n * n, k), _window_sum(ok.astype(f.dtype), k)
        local = num / np.maximum(den, 1.0)
    s_img = 1.4826 * _median_low(abs(n[ok]))
    floor = (0.5 * s_img) ** 2
    var = xp.where(den > 0, xp.maximum(local, floor), xp.full_like(local, float(s_img) ** 2))
    return _like_input(xp.sqrt(var), as_numpy)


def _window_sum(a: np.ndarray, k: int) -> np.ndarray:
    """Sum of ``a`` (H, W) over the k×k window centred on each pixel (k odd; outside the image counts 0).

    Direct sums along each axis (no running sums), so sums of integers are exact.
    """
    from scipy.ndimage import correlate1d

    ones = np.ones(k, a.dtype)
    return correlate1d(correlate1d(a, ones, axis=0, mode="constant"), ones, axis=1, mode="constant")


def precision_weights(sigma, clip: float = 1e3):
    """Relative precision c = median(σ²)/σ² (dimensionless, (H, W)) of each pixel's flow (``sigma`` (H, W)
    1/s, from :func:`flow_noise`), clipped to [1/clip, clip]; the data weights of :func:`depth_tv`. Same
    array kind."""
    as_numpy = not is_tensor(sigma)
    s = _as_array(sigma)
    xp = _xp(s)
    v = s * s
    good = xp.isfinite(v) & (v > 0)
    if not bool(good.any()):
        return _like_input(xp.ones_like(s), as_numpy)
    med = _median_low(v[good])
    if not bool(med > 0):
        return _like_input(xp.ones_like(s), as_numpy)
    # Relative floor (not an absolute one): exact synthetic flow has σ² ~ 1e-32.
    with _quiet(s):
        c = _clamp(xp.where(good, med / xp.maximum(v, med / clip), xp.ones_like(v)), 1.0 / clip, clip)
    return _like_input(c, as_numpy)


def translational_snr(flow, camera: PinholeCamera, epipole, sigma):
    """Predicted translational flow over flow noise, per pixel ((H, W), dimensionless).

    The prediction is |z̄|·|p − e| with z̄ = Σ⟨ṗ, p−e⟩ / Σ|p−e|² the image's pooled
    expansion rate (a typical scene point's v/d; the least-squares pooling of the
    receptive fields over the whole image): how far a typical point at that pixel moves
    per second. Its ratio to the pixel's flow noise σ (1/s) is the inverse relative
    precision of the pixel's depth: σ_d/d ≈ 1/SNR. It falls to 0 at the epipole, where
    depth from flow is ill-conditioned. Same array kind as ``flow``.

    flow (2, H, W) 1/s: derotated normalised flow of ``camera``; epipole (2,): normalised;
    sigma (H, W) 1/s: the flow noise (:func:`flow_noise`).
    """
    f, as_numpy = _check_flow(flow, camera)
    xp = _xp(f)
    q = _offsets(camera, epipole, f)
    ok = xp.isfinite(f).all(0)
    w = (q * q).sum(0)
    s = (torch.as_tensor(sigma, device=f.device, dtype=f.dtype) if is_tensor(f)
         else np.asarray(sigma.detach().cpu() if is_tensor(sigma) else sigma, dtype=f.dtype))
    with _quiet(f):
        z_bar = (xp.where(ok, (f * q).sum(0), xp.zeros_like(w)).sum()
                 / _clamp(xp.where(ok, w, xp.zeros_like(w)).sum(), 1e-30))
        snr = abs(z_bar) * xp.sqrt(w) / _clamp(s, 1e-30)
    return _like_input(xp.where(xp.isfinite(snr), snr, xp.zeros_like(snr)), as_numpy)


# ----------------------------------------------------------------------------- ego-motion refinement
def refine_motion(flow, camera: PinholeCamera, epipole, iters: int = 6, n_points: int = 5000,
                  rate_prior: float = 0.05):
    """Residual rotation and epipole of (gyro-)derotated flow, jointly, robustly.

    A gyroscope's scale-factor and misalignment errors leave a rotation of a few tenths of
    a degree over a pair while the camera turns; its flow B(p)·δω (δω rad/s,
    :func:`lobula.epipole.rotational_flow`) then bends the translational field and biases
    the epipole and every depth. What is left after removing it is radial from e:
    (ṗ − Bδω) × (p − e) = 0 at every pixel — bilinear in (δω, e), solved by alternating
    a weighted least-squares step in δω (Cauchy weights, a ridge prior of ``rate_prior``
    rad/s against the residuals' scale) and a fresh :class:`lobula.epipole.EpipoleEstimator`
    fit of e (started at, and falling back to, the given epipole) on ``n_points`` pixels.

    flow: (2, H, W) normalised flow (1/s) of ``camera`` after the gyro's derotation; epipole: start
    (ex, ey), normalised; iters: alternations from each start.
    Near-frontal scenes confound a rotation with an epipole shift, so the
    alternation is started twice — at the given epipole (e.g. the gyro-stabilised
    heading) and at this flow's own epipole fit — and the motion whose flow is most
    nearly radial (the smaller median perpendicular residual) is kept.
    Returns (e (2,), δω (3,) rad/s, flow with Bδω removed (same kind as flow)).
    """
    f, as_numpy = _check_flow(flow, camera)
    fn = (f.detach().cpu().numpy() if is_tensor(f) else f).astype(np.float64)
    x, y = camera.normalised_grid(np.float64)
    stride = max(1, int(math.sqrt(camera.width * camera.height / max(n_points, 1))))
    xs, ys = x[::stride, ::stride].ravel(), y[::stride, ::stride].ravel()
    us, vs = fn[0, ::stride, ::stride].ravel(), fn[1, ::stride, ::stride].ravel()
    ok = np.isfinite(us) & np.isfinite(vs)
    xs, ys, us, vs = xs[ok], ys[ok], us[ok], vs[ok]
    # Rotational flow basis per unit rate about x, y, z (columns), at the points.
    bu = np.stack([xs * ys, -(1 + xs * xs), ys], -1)
    bv = np.stack([1 + ys * ys, -xs * ys, -xs], -1)
    starts = [np.array(_epipole(epipole), float)]
    own = EpipoleEstimator(xs[None], ys[None], prior=starts[0], stride=1).update(np.stack([us, vs])[:, None, :])
    if np.all(np.isfinite(own)):
        starts.append(own)
    best = None
    for e0 in starts:
        e, dw = _alternate(xs, ys, us, vs, bu, bv, e0, iters, rate_prior)
        dx, dy = xs - e[0], ys - e[1]
        u2, v2 = us - bu @ dw, vs - bv @ dw
        perp = np.median(np.abs(v2 * dx - u2 * dy) / np.maximum(np.hypot(dx, dy), 1e-9))
        if best is None or perp < best[0]:
            best = (perp, e, dw)
    _, e, dw = best
    rot = rotational_flow(tuple(dw), *_grid(camera, f))
    return e, dw, _like_input(f - rot, as_numpy)


def _alternate(xs, ys, us, vs, bu, bv, e_start, iters, rate_prior):
    """The alternation of :func:`refine_motion` from one start: returns (e, δω)."""
    e = e_start.copy()
    dw = np.zeros(3)
    for _ in range(max(1, iters)):
        dx, dy = xs - e[0], ys - e[1]
        a = bv * dx[:, None] - bu * dy[:, None]            # (N, 3)
        b = vs * dx - us * dy
        res = b - a @ dw
        scale = 1.4826 * np.median(np.abs(res)) + 1e-12
        w = 1.0 / (1.0 + (res / (2.385 * scale)) ** 2)
        ata = (a * w[:, None]).T @ a
        # Gaussian prior δω ~ N(0, rate_prior²) against residuals of std `scale`: ridge (scale/prior)².
        dw = np.linalg.solve(ata + (scale / max(rate_prior, 1e-12)) ** 2 * np.eye(3), (a * w[:, None]).T @ b)
        u2, v2 = us - bu @ dw, vs - bv @ dw
        est = EpipoleEstimator(xs[None], ys[None], prior=e_start, stride=1)
        e = est.update(np.stack([u2, v2])[:, None, :])
        if not np.all(np.isfinite(e)):
            e = e_start.copy()
    return e, dw

