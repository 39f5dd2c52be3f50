"""Ratio depth: the per-pixel least-squares radial rate z = ⟨ṗ, p−e⟩ / |p−e|², then d = v / z.
"""
from __future__ import annotations

from .._optional import is_tensor, torch
from .config import DepthConfig, DepthResult
from .geometry import _check_flow, _like_input, _offsets, _quiet, _speed, _xp, angle_from_epipole, rate_to_depth
from lobula.camera import PinholeCamera


def radial_rate(flow, camera: PinholeCamera, epipole) -> object:
    """Per-pixel least-squares radial rate r = ⟨ṗ, p−e⟩ / |p−e|² (1/s), shape (H, W).

    NaN where |p−e| = 0 or the flow is not finite. Same array kind as ``flow``. flow (2, H, W) 1/s:
    normalised flow of ``camera``; epipole (ex, ey): normalised.
    """
    f, as_numpy = _check_flow(flow, camera)
    xp = _xp(f)
    q = _offsets(camera, epipole, f)
    w = (q * q).sum(0)
    with _quiet(f):
        r = (f * q).sum(0) / w
    r = xp.where(w > 0, r, xp.full_like(r, float("nan")))
    return _like_input(r, as_numpy)


def depth_ratio(flow, camera: PinholeCamera, v: float, epipole,
                min_radius_deg: float | None = None, config: DepthConfig | None = None) -> DepthResult:
    """Ratio depth d = v / r with r = ⟨ṗ, p−e⟩ / |p−e|² per pixel.

    flow: (2, H, W) normalised flow (1/s) of ``camera``; v: forward speed (m/s, > 0 approaching);
    epipole: (ex, ey) normalised; min_radius_deg: degrees (None: ``config``'s).
    Pixels within ``min_radius_deg`` of the epipole, with r
    non-finite, of the wrong sign for v (contraction while approaching), or beyond
    ``config.max_depth_m`` are invalid (NaN) — the per-pixel ratio has no pooling to
    fall back on, so near the epipole it reports nothing rather than nonsense.
    """
    cfg = config or DepthConfig()
    radius = cfg.min_radius_deg if min_radius_deg is None else float(min_radius_deg)
    f, as_numpy = _check_flow(flow, camera)
    r = radial_rate(f, camera, epipole)
    far = angle_from_epipole(camera, epipole) > radius
    if is_tensor(f):
        far = torch.as_tensor(far, device=f.device)
    depth, valid = rate_to_depth(r, _speed(v), cfg.max_depth_m, extra_valid=far)
    return DepthResult(depth=_like_input(depth, as_numpy), valid=_like_input(valid, as_numpy),
                       rate=_like_input(r, as_numpy), method="ratio")
