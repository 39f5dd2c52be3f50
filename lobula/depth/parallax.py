"""Plane+parallax depth: the gyro's rotation (the plane at infinity's homography) removed from the
flow, then the ratio on the translational parallax that remains.
"""
from __future__ import annotations

import math

import numpy as np

from .._optional import is_tensor, torch
from .config import DepthConfig, DepthResult
from .geometry import _check_flow, _grid, _like_input, _quiet, _xp
from .ratio import depth_ratio
from lobula.camera import PinholeCamera
from lobula.epipole import rotational_flow


def _rotational_flow(camera: PinholeCamera, omega, like=None):
    """Flow (2, H, W) in normalised units (1/s) of a pinhole camera rotating at ω (rad/s, camera frame).

    :func:`lobula.epipole.rotational_flow` on the camera's grid, of the kind, dtype (and
    device) of ``like`` (a tensor or a numpy array), else numpy float64.
    """
    wx, wy, wz = (float(c) for c in np.asarray(
        omega.detach().cpu() if is_tensor(omega) else omega, dtype=float).ravel())
    x, y = _grid(camera, np.zeros((), np.float64) if like is None else like)
    return rotational_flow((wx, wy, wz), x, y)


def _rotation_matrix(omega, dt: float) -> np.ndarray:
    """R = exp(−[ω]× dt): how camera-frame coordinates of static points rotate over dt."""
    w = -np.asarray(omega, dtype=float).ravel() * dt
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(th) / th * K + (1 - math.cos(th)) / th ** 2 * (K @ K)


def derotate_flow(flow, camera: PinholeCamera, omega, dt: float | None = None):
    """Remove the camera rotation (gyro ω = ``omega`` (3,), rad/s, camera frame) from flow (2, H, W), 1/s,
    of ``camera``; returns the translational flow (2, H, W), 1/s.

    dt None: instantaneous model, ṗ_t = ṗ − (rotational flow of ω).
    dt given: the flow is a displacement over dt seconds (ṗ·dt), static points move as
    X' = R(X − t·dt) with R = exp(−[ω]×dt); the end point p' = p + ṗ·dt is mapped back
    through the plane-at-infinity homography Rᵀ, leaving the exact translational
    displacement, returned divided by dt. Same array kind as ``flow``.
    """
    f, as_numpy = _check_flow(flow, camera)
    if dt is None:
        out = f - _rotational_flow(camera, omega, like=f)
        return _like_input(out, as_numpy)
    if not dt > 0:
        raise ValueError(f"dt must be positive seconds, got {dt}")
    xp = _xp(f)
    x, y = _grid(camera, f)
    Rt = _rotation_matrix(omega, dt).T
    Rt = torch.as_tensor(Rt, dtype=f.dtype, device=f.device) if is_tensor(f) else Rt.astype(f.dtype)
    xe, ye = x + f[0] * dt, y + f[1] * dt
    P = xp.stack([xe, ye, xp.ones_like(xe)])            # (3, H, W) end rays
    Q = xp.einsum("ij,jhw->ihw", Rt, P)
    with _quiet(f):
        out = xp.stack([Q[0] / Q[2] - x, Q[1] / Q[2] - y]) / dt
    return _like_input(out, as_numpy)


def depth_parallax(flow, camera: PinholeCamera, v: float, epipole, gyro=None,
                   dt: float | None = None, min_radius_deg: float | None = None,
                   config: DepthConfig | None = None) -> DepthResult:
    """Plane+parallax depth once v and the rotation are known.

    Reference plane: the plane at infinity, whose induced homography is the gyro
    rotation; after derotation (:func:`derotate_flow`, ``gyro`` = ω in rad/s, camera
    frame; None = no rotation) the residual parallax of a point at depth d is
    (v/d)·(p − e) for translation t = v·(ex, ey, 1), so
    d = v·|p−e|² / ⟨ṗ_t, p−e⟩ (the least-squares projection of the parallax on the
    epipolar direction; its perpendicular part is noise or non-rigidity).
    dt: seconds between the frames the flow came from; given, the finite rotation is
    undone exactly and the depth is that at the later frame (add v·dt for the earlier).
    Invalid (NaN) within ``min_radius_deg`` of the epipole, for the wrong sign, and
    beyond ``config.max_depth_m``. flow (2, H, W) 1/s of ``camera``; v: forward speed (m/s);
    epipole (ex, ey): normalised; gyro (3,) rad/s; min_radius_deg: degrees (None: ``config``'s).
    """
    f, as_numpy = _check_flow(flow, camera)
    ft = f if gyro is None else derotate_flow(f, camera, gyro, dt=dt)
    res = depth_ratio(ft, camera, v, epipole, min_radius_deg=min_radius_deg, config=config)
    return DepthResult(depth=_like_input(res.depth, as_numpy), valid=_like_input(res.valid, as_numpy),
                       rate=_like_input(res.rate, as_numpy), method="parallax")
