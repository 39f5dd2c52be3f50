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

import sys

import numpy as np


def _is_tensor(a) -> bool:
    """Whether a is a torch tensor, without importing torch (only a caller that has it can pass one)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(a, torch.Tensor)


def rotational_flow(omega: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Flow (1/s), (2, ...), of a pinhole camera rotating at ω = (ωx, ωy, ωz) rad/s (camera frame).

    x, y: normalised coordinates (numpy arrays or torch tensors; the result follows).
    Derived from Ṗ = −ω × P for static points.
    """
    wx, wy, wz = (float(w) for w in omega)
    u = wx * x * y - wy * (1 + x * x) + wz * y
    v = wx * (1 + y * y) - wy * x * y - wz * x
    if _is_tensor(u):
        return sys.modules["torch"].stack([u, v])
    return np.stack([u, v])


def derotate(flow: np.ndarray, omega: np.ndarray, x: np.ndarray, y: np.ndarray,
             squares: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Subtract the gyro-predicted rotational flow from flow (2, H, W), both in 1/s.

    Runs on every frame pair, so for float32 flow and grid it is done into one output with
    few temporaries; ``squares`` = (1 + x², 1 + y²) lets a caller that keeps its grid (the
    field pooling) compute those ω-free terms once. The operations and their order are
    those of :func:`rotational_flow`, so the result is bit-identical to ``flow − rotational_flow``.
    """
    flow = np.asarray(flow)
    if not (flow.dtype == np.float32 and isinstance(x, np.ndarray) and isinstance(y, np.ndarray)
            and x.dtype == np.float32 and y.dtype == np.float32 and flow.shape[1:] == x.shape == y.shape):
        return flow - rotational_flow(omega, x, y).astype(flow.dtype)
    wx, wy, wz = (float(w) for w in omega)
    opx2, opy2 = squares if squares is not None else (1 + x * x, 1 + y * y)
    out = np.empty(flow.shape, np.float32)
    t = np.empty(x.shape, np.float32)
    u, v = out[0], out[1]
    # u = wx·x·y − wy·(1 + x²) + wz·y, evaluated left to right as rotational_flow does.
    np.multiply(x, wx, out=u)
    u *= y
    np.multiply(opx2, wy, out=t)
    u -= t
    np.multiply(y, wz, out=t)
    u += t
    np.subtract(flow[0], u, out=u)
    # v = wx·(1 + y²) − wy·x·y − wz·x
    np.multiply(opy2, wx, out=v)
    np.multiply(x, wy, out=t)
    t *= y
    v -= t
    np.multiply(x, wz, out=t)
    v -= t
    np.subtract(flow[1], v, out=v)
    return out


def turn(r: np.ndarray, x, y):
    """Normalised coordinates of the rays (x, y, 1) after the rotation r (3, 3): the pixel
    where a camera turned by r sees the same directions."""
    qx = r[0, 0] * x + r[0, 1] * y + r[0, 2]
    qy = r[1, 0] * x + r[1, 1] * y + r[1, 2]
    qz = r[2, 0] * x + r[2, 1] * y + r[2, 2]
    return qx / qz, qy / qz


def derotate_finite(x, y, flow, dt: float, r_m0: np.ndarray, r_m1: np.ndarray):
    """Exact derotation of a frame pair into the orientation at its middle.

    x, y: normalised coordinates of points in the first frame (any shape); flow: their
    image flow (2, ...) in 1/s over the pair's gap dt (s); r_m0, r_m1 (3, 3): rotations
    taking camera vectors at the first / second frame into the camera frame at the pair's
    middle (from the integrated gyro, e.g. Q(t_m)ᵀ·Q(t0)). A point's two rays are turned
    into that one orientation, so what is left is the finite translation between them:
    returns (X, Y) — where the points are in the middle orientation — and the
    translational flow (2, ...) 1/s there. Exact for any rotation angle (the first-order
    :func:`derotate` is not: at 0.8 rad/s over 0.2 s its error rivals the translational flow).
    """
    X0, Y0 = turn(r_m0, x, y)
    X1, Y1 = turn(r_m1, x + flow[0] * dt, y + flow[1] * dt)
    return X0, Y0, np.stack([(X1 - X0) / dt, (Y1 - Y0) / dt])


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
        self.prior = np.asarray(prior, float)
        self.n_frames = 0

    def update(self, flow: np.ndarray, points=None, attitude: np.ndarray | None = None) -> np.ndarray:
        """Add one derotated flow field (2, H, W) (1/s) and return the epipole (2,).

        points: (X, Y, flow_at_points (2, N)) at the strided pixels instead, e.g. from
        :func:`derotate_finite`, whose points sit where the pair's middle orientation sees them.
        attitude (3, 3): the camera's orientation for this flow (camera → a fixed reference,
        from the integrated gyro). The heading is then accumulated in that reference, where it
        stays put while the camera turns, and the returned epipole is the heading seen from
        the camera now; without it the camera is taken as not turning.
        """
        if points is None:
            u = flow[0, ::self.stride, ::self.stride].ravel().astype(float)
            v = flow[1, ::self.stride, ::self.stride].ravel().astype(float)
            x, y = self.x, self.y
        else:
            x, y = np.asarray(points[0], float).ravel(), np.asarray(points[1], float).ravel()
            u, v = (np.asarray(c, float).ravel() for c in points[2])
        ok = np.isfinite(u) & np.isfinite(v)
        u, v, x, y = u[ok], v[ok], x[ok], y[ok]
        a = np.stack([v, -u], -1)
        b = v * x - u * y
        if attitude is not None:
            # The line through a point along its flow, l = (−v, u, b), has the epipole on it
            # (l·(e, 1) = 0); lines turn with the camera, so l_ref = R·l holds the heading.
            l_ref = np.stack([-v, u, b], -1) @ np.asarray(attitude, float).T
            a, b = -l_ref[:, :2], l_ref[:, 2]
            x, y = self._seen(attitude, x, y)
        # IRLS about this frame's own fit, started from the running estimate; where that start
        # is so far off that the fit degenerates, from the prior instead (a wrong running
        # estimate must not lock every later frame out).
        fit = self._frame_fit(a, b, x, y, self.e)
        if fit is None:
            fit = self._frame_fit(a, b, x, y, self.prior)
        if fit is not None:
            self.ata += fit[0]
            self.atb += fit[1]
            self.n_frames += 1
        self.e = np.linalg.solve(self.ata, self.atb)
        if attitude is not None:
            h = np.asarray(attitude, float).T @ np.array([self.e[0], self.e[1], 1.0])
            return h[:2] / h[2]
        return self.e.copy()

    @staticmethod
    def _frame_fit(a, b, x, y, start, iters: int = 3, t_min: float = 3.0):
        """One frame's noise-corrected normal equations (ata (2, 2), atb (2,)), or None.

        None where the frame says nothing about the heading: the fit degenerates, or the
        flow is not significantly radial about the frame's own epipole. Each line's residual
        a·e − b is its flow's component across the ray from the epipole (times |p − e|); the
        flow along it (−a₁, a₀) gives the radial component. Noise alone (a camera at rest)
        makes both alike; translation makes the radial one dominate. The test is the
        t-statistic of d = radial² − across² over the points, which is about N(0, 1) for
        noise: below ``t_min`` the frame is not counted — one such frame must not move the
        heading, and a heading placed by noise must not lock later frames out.
        """
        e = np.asarray(start, float)
        for _ in range(iters):
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
                return None
            e = np.linalg.solve(ata, atb)
        radial = (x - e[0]) * -a[:, 1] + (y - e[1]) * a[:, 0]
        d = radial ** 2 - (a @ e - b) ** 2
        if np.sum(d) < t_min * np.sqrt(np.sum(d ** 2)):
            return None
        return ata, atb

    @staticmethod
    def _seen(attitude, x, y):
        """Points (x, y) of the camera as the reference frame sees them (for the noise-bias terms)."""
        q = np.stack([x, y, np.ones_like(x)], -1) @ np.asarray(attitude, float).T
        return q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
