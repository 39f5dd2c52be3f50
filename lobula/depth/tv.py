"""TV depth: z = v/d fitted to the flow under a total-variation prior, by adaptive Chambolle–Pock
primal–dual iterations in torch (coarse to fine from a cold start, or warm-started).
"""
from __future__ import annotations

import math
import time

from .._optional import require_torch, torch
from .config import DepthConfig, DepthResult
from .geometry import _check_flow, _like_input, _offsets, _speed, _to_tensor, rate_to_depth
from lobula.camera import PinholeCamera


def _grad(z: torch.Tensor, fx: float, fy: float, out: torch.Tensor) -> torch.Tensor:
    """Forward-difference gradient in normalised units into ``out`` (2, H, W); zero at the far edges."""
    torch.sub(z[:, 1:], z[:, :-1], out=out[0, :, :-1])
    out[0, :, :-1].mul_(fx)
    out[0, :, -1] = 0
    torch.sub(z[1:, :], z[:-1, :], out=out[1, :-1, :])
    out[1, :-1, :].mul_(fy)
    out[1, -1, :] = 0
    return out


def _grad_into(z: torch.Tensor, fx: float, fy: float, out: torch.Tensor) -> torch.Tensor:
    """:func:`_grad` for the solver loop: leaves ``out``'s far column/row (already 0) alone."""
    torch.sub(z[:, 1:], z[:, :-1], out=out[0, :, :-1]).mul_(fx)
    torch.sub(z[1:, :], z[:-1, :], out=out[1, :-1, :]).mul_(fy)
    return out


def _grad_adjoint(y: torch.Tensor, fx: float, fy: float, out: torch.Tensor) -> torch.Tensor:
    """Adjoint of :func:`_grad` (minus the divergence), (2, H, W) -> (H, W) into ``out``."""
    # (Dxᵀ a)[j] = a[j-1] − a[j] with a[-1] = 0 and a[W-1] treated as 0 (it is always 0).
    out.zero_()
    out[:, 1:].add_(y[0, :, :-1], alpha=fx)
    out[:, :-1].sub_(y[0, :, :-1], alpha=fx)
    out[1:, :].add_(y[1, :-1, :], alpha=fy)
    out[:-1, :].sub_(y[1, :-1, :], alpha=fy)
    return out


def _tv(z: torch.Tensor, fx: float, fy: float) -> torch.Tensor:
    """Isotropic total variation Σ|∇z| with ∇ in normalised units (a 0-d tensor)."""
    g = _grad(z, fx, fy, torch.empty((2,) + tuple(z.shape), dtype=z.dtype, device=z.device))
    return torch.sqrt((g * g).sum(0)).sum()


def tv_objective(z, flow, camera: PinholeCamera, epipole, gamma: float, weights=None) -> float:
    """The TV depth objective Σ c·|ṗ − z(p−e)|² + γ·Σ|∇z| (∇ in normalised units) at ``z`` (H, W) 1/s,
    a float in (1/s)².

    flow (2, H, W) 1/s of ``camera``; epipole (ex, ey): normalised; gamma: γ (1/s · normalised
    length). c: per-pixel data weights (``weights``, (H, W), default 1). Non-finite flow pixels
    carry no data term (as in :func:`depth_tv`).
    """
    f, _ = _check_flow(flow, camera)
    f = _to_tensor(f, dtype=torch.float64)
    zt = _to_tensor(z, device=f.device, dtype=torch.float64)
    q = _offsets(camera, epipole, f)
    ok = torch.isfinite(f).all(0)
    res = torch.where(ok, ((f - zt * q) ** 2).sum(0), torch.zeros_like(zt))
    if weights is not None:
        c = _to_tensor(weights, device=f.device, dtype=torch.float64)
        res = torch.where(ok, res * c, res)
    return float(res.sum() + gamma * _tv(zt, camera.fx, camera.fy))


def depth_tv(flow, camera: PinholeCamera, v: float, epipole, gamma: float | None = None,
             init=None, iters: int | None = None, tol: float | None = None,
             config: DepthConfig | None = None, weights=None) -> DepthResult:
    """TV-regularised depth: minimise Σ c·|ṗ − z(p−e)|² + γ·TV(z) over z = v/d, then d = v/z.

    flow: (2, H, W) normalised flow (1/s) of ``camera``; pixels with non-finite flow get no data term
    (TV fills them in). v: forward speed (m/s); epipole: (ex, ey) normalised.
    gamma: TV weight (1/s · normalised length; the gradient is in normalised units, so it
    is resolution independent); default ``config.gamma``.
    init: warm start — a previous :class:`DepthResult` (its rate and dual are reused:
    best), or a (H, W) z map (1/s); None is a cold start, solved coarse to fine.
    iters, tol: iteration cap (at full resolution) and tolerance on the relative
    primal–dual residuals (see :class:`DepthConfig`).
    weights: per-pixel data weights c (H, W), ≥ 0, default 1 — the flow's relative
    precision (:func:`lobula.depth_motion.precision_weights`: 1/σ² of each pixel's flow noise over its
    median), so that pixels whose flow is unreliable lean on their neighbours through
    the TV term instead of being masked. Scaled to median 1, γ keeps its meaning.

    Method: Chambolle–Pock primal–dual (θ = 1) on min_z G(z) + F(Kz) with K = ∇,
    F = γ‖·‖₂,₁ (dual prox: projection onto the ball of radius γ per pixel) and
    G(z) = Σ w z² − 2 b z + |ṗ|², w = |p−e|², b = ⟨ṗ, p−e⟩, whose prox is closed-form
    per pixel: z = (z₀ + 2τb) / (1 + 2τw). τσ‖K‖² = 1 with ‖K‖² ≤ 4(fx² + fy²); the
    ratio τ/σ adapts to balance the primal and dual residuals (Goldstein, Li & Yuan
    2015), which frees γ and the image size from hand-tuned steps. A cold start first
    solves the same problem on a pyramid of 2×-coarser grids (the quadratic data terms
    averaged over blocks, the same γ; each level stopped at 3·tol since it only
    initialises the next), because the TV-only region at the epipole fills in by slow
    diffusion at full resolution. A warm start skips the pyramid; it may come from a
    solve with another γ. Runs on the flow's device in the flow's float dtype (float32
    is the fast choice: ≈ 50 ms per 320×240 frame on one CPU core at the default tol). Returns a :class:`DepthResult` with
    ``rate`` = z, iterations (full-resolution ones; coarse ones are cheaper), the
    objective (:func:`tv_objective`), whether the tolerance was met, and the dual.
    """
    cfg = config or DepthConfig()
    gamma = cfg.gamma if gamma is None else float(gamma)
    iters = cfg.tv_iters if iters is None else int(iters)
    tol = cfg.tv_tol if tol is None else float(tol)
    if not gamma >= 0:
        raise ValueError(f"gamma must be ≥ 0, got {gamma}")
    require_torch("TV depth")
    f, as_numpy = _check_flow(flow, camera)
    f = _to_tensor(f)
    t0 = time.perf_counter()
    with torch.no_grad():
        q = _offsets(camera, epipole, f)
        ok = torch.isfinite(f).all(0)
        f0 = torch.where(ok, f, torch.zeros_like(f))
        w = (q * q).sum(0) * ok.to(f.dtype)   # data weight |p−e|², 0 where flow is missing
        b = (f0 * q).sum(0)                   # ⟨ṗ, p−e⟩, 0 where missing
        if weights is not None:
            c = _to_tensor(weights, device=f.device, dtype=f.dtype)
            if tuple(c.shape) != tuple(w.shape) or not bool(torch.all(torch.isfinite(c) & (c >= 0))):
                raise ValueError(f"weights must be finite and ≥ 0 with the flow's shape {tuple(w.shape)}")
            w, b = w * c, b * c
        fx, fy = float(camera.fx), float(camera.fy)
        coarse: list[int] = []
        if init is None:
            z, y, tau = _tv_coarse_start(w, b, gamma, fx, fy, tol, cfg, coarse)
        else:
            z, y, tau = _tv_init(init, f, tuple(w.shape))
        z, y, n_done, converged, tau = _tv_solve(w, b, gamma, fx, fy, z, y, iters, tol,
                                                 cfg.tv_check_every, tau)
        solve_s = time.perf_counter() - t0
        objective = tv_objective(z, f, camera, epipole, gamma, weights=weights)
        depth, valid = rate_to_depth(z, _speed(v), cfg.max_depth_m)
    return DepthResult(depth=_like_input(depth, as_numpy), valid=_like_input(valid, as_numpy),
                       rate=_like_input(z, as_numpy), method="tv", iterations=n_done,
                       objective=objective, converged=converged, solve_s=solve_s,
                       dual=_like_input(y, as_numpy), step=tau, coarse_iterations=tuple(coarse))


def _tv_solve(w: torch.Tensor, b: torch.Tensor, gamma: float, fx: float, fy: float,
              z: torch.Tensor, y: torch.Tensor, iters: int, tol: float, check_every: int,
              tau: float | None = None) -> tuple[torch.Tensor, torch.Tensor, int, bool, float]:
    """Adaptive Chambolle–Pock iterations for min Σ(w z² − 2bz) + γ Σ|∇z| (see :func:`depth_tv`).

    w, b: (H, W); z: (H, W) and y: (2, H, W) start values (z is updated in place);
    tau: initial primal step (None: a guess from the data weights).
    Returns z, y, iterations done, whether max(relative primal, dual residual) ≤ tol,
    and the adapted primal step (a good start for the next frame).
    """
    # One function: the iterations share in-place buffers and the adapted steps τ, σ, α.
    if gamma == 0:
        # No regulariser: the per-pixel least squares, undefined where w = 0.
        z.copy_(torch.where(w > 0, b / w.clamp(min=1e-30), torch.full_like(w, float("nan"))))
        return z, torch.zeros_like(y), 0, True, tau if tau is not None else float("nan")
    L2 = 4.0 * (fx * fx + fy * fy)
    # Initial split of τσ = 1/L² between primal and dual; the adaptation corrects it.
    if tau is None or not (tau > 0 and math.isfinite(tau)):
        tau = 1.0 / (8.0 * max(float(w.mean()), 1e-12))
    sigma = 1.0 / (tau * L2)
    alpha, eta, delta = 0.5, 0.95, 1.5       # Goldstein et al.'s defaults
    # The loop works on u = y/γ, whose feasible set is the unit ball per pixel (one op
    # less in the projection); Kᵀy = γ Kᵀu folds γ into the adjoint's weights.
    u = (y / gamma).contiguous()
    u[0, :, -1] = 0                          # outside the gradient's range: keep them 0
    u[1, -1, :] = 0
    u.div_(torch.sqrt(u[0] * u[0] + u[1] * u[1]).clamp_(min=1.0))
    Kz = _grad(z, fx, fy, torch.empty_like(u))
    Kz_new = Kz.clone()                      # its far edges stay 0: _grad_into skips them
    KTy = _grad_adjoint(u, fx * gamma, fy * gamma, torch.empty_like(z))
    nrm = torch.empty_like(z)
    z_prev, u_prev, KTy_prev = torch.empty_like(z), torch.empty_like(u), torch.empty_like(z)
    inv, c = _prox_coeffs(w, b, tau)
    converged, n_done = False, 0
    for k in range(1, iters + 1):
        check = (k % check_every == 0) or k == iters
        if check:
            z_prev.copy_(z); u_prev.copy_(u); KTy_prev.copy_(KTy)
        # Primal: closed-form prox of the per-pixel quadratic after a step along −Kᵀy,
        # z ← (z − τKᵀy + 2τb) / (1 + 2τw) = (z − τKᵀy)·inv + c.
        z.sub_(KTy, alpha=tau)
        torch.addcmul(c, z, inv, out=z)
        _grad_into(z, fx, fy, Kz_new)
        # Dual: ascent along K z̄ with z̄ = 2z_new − z_old, by linearity 2Kz_new − Kz_old;
        # then the projection onto the unit ball (prox of F*). |u| is computed by hand:
        # torch's vector_norm over a leading dim of 2 is ~100x slower on CPU.
        s = sigma / gamma
        u.add_(Kz_new, alpha=2.0 * s).sub_(Kz, alpha=s)
        torch.mul(u[0], u[0], out=nrm).addcmul_(u[1], u[1]).clamp_(min=1.0).rsqrt_()
        u.mul_(nrm)
        _grad_adjoint(u, fx * gamma, fy * gamma, KTy)
        if check:
            # Residuals of the optimality conditions 0 ∈ ∂G(z) + Kᵀy, 0 ∈ ∂F*(y) − Kz,
            # each relative to the size of the terms it balances.
            p = torch.linalg.vector_norm((z_prev - z) / tau - (KTy_prev - KTy))
            d = torch.linalg.vector_norm((u_prev - u) * (gamma / sigma) - (Kz - Kz_new))
            p_scale = torch.maximum(torch.linalg.vector_norm(2.0 * (w * z - b)),
                                    torch.linalg.vector_norm(KTy))
            # Floor: a near-constant solution has Kz → 0; measure against gradients of
            # 1 % of z per pixel instead of dividing by nothing.
            d_scale = torch.maximum(torch.linalg.vector_norm(Kz_new),
                                    1e-2 * math.sqrt(L2) * torch.linalg.vector_norm(z))
            p_rel = float(p / p_scale.clamp(min=1e-30))
            d_rel = float(d / d_scale.clamp(min=1e-30))
        Kz, Kz_new = Kz_new, Kz
        n_done = k
        if check:
            if not (math.isfinite(p_rel) and math.isfinite(d_rel)):
                break
            if max(p_rel, d_rel) <= tol:
                converged = True
                break
            # Balance the residuals: a large primal residual wants a longer primal step.
            if p_rel > delta * d_rel:
                tau, sigma, alpha = tau / (1 - alpha), sigma * (1 - alpha), alpha * eta
                inv, c = _prox_coeffs(w, b, tau)
            elif p_rel < d_rel / delta:
                tau, sigma, alpha = tau * (1 - alpha), sigma / (1 - alpha), alpha * eta
                inv, c = _prox_coeffs(w, b, tau)
    return z, u.mul_(gamma), n_done, converged, tau


def _prox_coeffs(w: torch.Tensor, b: torch.Tensor, tau: float) -> tuple[torch.Tensor, torch.Tensor]:
    """inv = 1/(1 + 2τw) and c = 2τb·inv, so that prox_τG(x) = x·inv + c."""
    inv = 1.0 / (1.0 + 2.0 * tau * w)
    return inv, (2.0 * tau) * b * inv


def _tv_coarse_start(w: torch.Tensor, b: torch.Tensor, gamma: float, fx: float, fy: float,
                     tol: float, cfg: DepthConfig, counts: list
                     ) -> tuple[torch.Tensor, torch.Tensor, float | None]:
    """Cold start for the TV solver: solve on a 2× pyramid, coarsest first, and upsample.

    Block averages of w and b give the data term of a constant z over the block (up to
    the factor 1/4, which the same γ with halved fx, fy matches), so every level
    approximates the same continuous problem. Appends each level's iteration count to
    ``counts`` (coarsest first); returns the upsampled z, y and the adapted step.
    """
    import torch.nn.functional as F

    H, W = w.shape
    if min(H, W) < 2 * cfg.tv_pyramid_min_size:
        # Too small for a pyramid: the ratio map where it is defined, else its median.
        r = torch.where(w > 0, b / w.clamp(min=1e-30), torch.zeros_like(w))
        good = w > 0
        med = r[good].median() if bool(good.any()) else torch.zeros((), dtype=w.dtype, device=w.device)
        return torch.where(good, r, med), torch.zeros((2, H, W), dtype=w.dtype, device=w.device), None
    wc = F.avg_pool2d(w[None, None], 2, ceil_mode=True, count_include_pad=False)[0, 0]
    bc = F.avg_pool2d(b[None, None], 2, ceil_mode=True, count_include_pad=False)[0, 0]
    fxc, fyc = fx * wc.shape[1] / W, fy * wc.shape[0] / H
    zc, yc, tau = _tv_coarse_start(wc, bc, gamma, fxc, fyc, tol, cfg, counts)
    zc, yc, n, _, tau = _tv_solve(wc, bc, gamma, fxc, fyc, zc, yc, cfg.tv_iters, 3.0 * tol,
                                  cfg.tv_check_every, tau)
    counts.append(n)
    z = F.interpolate(zc[None, None], size=(H, W), mode="bilinear", align_corners=False)[0, 0]
    # Bilinear weights are convex, so the upsampled dual stays inside the γ-ball.
    y = F.interpolate(yc[None], size=(H, W), mode="bilinear", align_corners=False)[0]
    return z.contiguous(), y.contiguous(), tau


def _tv_init(init, f: torch.Tensor, shape: tuple) -> tuple[torch.Tensor, torch.Tensor, float | None]:
    """Warm start (z, y, τ) for the TV solver from a previous result or a z map (copies)."""
    y = torch.zeros((2,) + shape, dtype=f.dtype, device=f.device)
    tau = None
    if isinstance(init, DepthResult):
        z = _to_tensor(init.rate, device=f.device, dtype=f.dtype).clone()
        tau = init.step
        if init.dual is not None:
            yd = _to_tensor(init.dual, device=f.device, dtype=f.dtype)
            if tuple(yd.shape) == (2,) + shape:
                y = yd.clone()
    else:
        z = _to_tensor(init, device=f.device, dtype=f.dtype).clone()
    if tuple(z.shape) != shape:
        raise ValueError(f"init has shape {tuple(z.shape)} but the flow is {shape}; "
                         "warm starts need the same image size")
    # A warm start with holes (NaN) would poison every iteration: fill them with the median.
    bad = ~torch.isfinite(z)
    if bool(bad.any()):
        fill = z[~bad].median() if bool((~bad).any()) else torch.zeros((), dtype=z.dtype, device=z.device)
        z[bad] = fill
    y[~torch.isfinite(y)] = 0
    return z, y, tau
