"""The focus of expansion (epipole) and gyro derotation ("haltere" rotation signal).

Rotation adds flow that carries no depth information; a gyroscope predicts it for a
pinhole camera exactly (to first order in the rotation angle), so it is subtracted
first. What remains, for pure translation with velocity (Vx, Vy, Vz), radiates from
the epipole e = (Vx/Vz, Vy/Vz): ṗ = (Vz/d)(p − e). Each pixel then gives one linear
equation in e, ṗ_y·e_x − ṗ_x·e_y = ṗ_y·x − ṗ_x·y, and the epipole is the robust
least-squares solution pooled over pixels and frames. Real footage seldom moves along
the optical axis, so r must be measured about this point, not the principal point.
"""
from __future__ import annotations

import numpy as np
import torch


def rotational_flow(omega: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Flow (1/s), (2, ...), of a pinhole camera rotating at ω = (ωx, ωy, ωz) rad/s (camera frame).

    x, y: normalised coordinates (numpy arrays or torch tensors; the result follows).
    Derived from Ṗ = −ω × P for static points.
    """
    wx, wy, wz = (float(w) for w in omega)
    u = wx * x * y - wy * (1 + x * x) + wz * y
    v = wx * (1 + y * y) - wy * x * y - wz * x
    return torch.stack([u, v]) if isinstance(u, torch.Tensor) else np.stack([u, v])


def derotate(flow: np.ndarray, omega: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Subtract the gyro-predicted rotational flow from flow (2, H, W), both in 1/s."""
    return flow - rotational_flow(omega, x, y).astype(flow.dtype)


def mean_angular_velocity(gyro_t: np.ndarray, gyro: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Mean gyro reading (rad/s, (3,)) over [t0, t1]: the rotation a frame pair saw, divided by its gap."""
    m = (gyro_t >= t0) & (gyro_t <= t1)
    if not np.any(m):
        return np.array([np.interp(0.5 * (t0 + t1), gyro_t, gyro[:, k]) for k in range(3)])
    return gyro[m].mean(axis=0)


class EpipoleEstimator:
    """Running robust estimate of the epipole from derotated flow.

    The normal equations of every frame are accumulated with robust (Cauchy) weights
    about the current estimate, plus a weak prior at ``prior`` (default the principal
    point) so frames without motion leave the estimate there. Pixels are subsampled
    with ``stride`` because the estimate is a 2-parameter fit to thousands of pixels.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray, prior=(0.0, 0.0), prior_weight: float = 1e-6,
                 stride: int = 4):
        self.x = x[::stride, ::stride].ravel()
        self.y = y[::stride, ::stride].ravel()
        self.stride = stride
        self.ata = np.eye(2) * prior_weight
        self.atb = np.asarray(prior, float) * prior_weight
        self.e = np.asarray(prior, float)
        self.n_frames = 0

    def update(self, flow: np.ndarray) -> np.ndarray:
        """Add one flow field (2, H, W) (1/s) and return the updated epipole (2,)."""
        u = flow[0, ::self.stride, ::self.stride].ravel().astype(float)
        v = flow[1, ::self.stride, ::self.stride].ravel().astype(float)
        ok = np.isfinite(u) & np.isfinite(v)
        u, v, x, y = u[ok], v[ok], self.x[ok], self.y[ok]
        a = np.stack([v, -u], -1)
        b = v * x - u * y
        e = self.e
        for _ in range(3):  # IRLS about this frame's own fit, started from the running estimate
            res = a @ e - b
            scale = 1.4826 * np.median(np.abs(res)) + 1e-12
            w = 1.0 / (1.0 + (res / (2.385 * scale)) ** 2)
            aw = a * w[:, None]
            ata, atb = aw.T @ a, aw.T @ b
            # Flow noise (std σ) sits in both sides of the equations and biases the fit
            # toward the image centre by σ²·Σw·I and σ²·Σw·p; remove that, with σ²
            # estimated from the residuals, whose variance is σ²|p − e|².
            r2 = (x - e[0]) ** 2 + (y - e[1]) ** 2
            s2 = np.sum(w * res ** 2) / max(np.sum(w * r2), 1e-20)
            ata = ata - s2 * np.sum(w) * np.eye(2)
            atb = atb - s2 * np.array([np.sum(w * x), np.sum(w * y)])
            if np.linalg.cond(ata) > 1e8 or np.any(np.linalg.eigvalsh(ata) <= 0):
                break
            e = np.linalg.solve(ata, atb)
        else:
            self.ata += ata
            self.atb += atb
            self.n_frames += 1
        self.e = np.linalg.solve(self.ata, self.atb)
        return self.e.copy()
