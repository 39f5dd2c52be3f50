"""The focus of expansion (epipole) and derotation by the gyro.

Rotation adds flow that carries no depth information; a gyroscope predicts it for a
pinhole camera exactly (to first order in the rotation angle), so it is subtracted
first. What remains, for pure translation with velocity (Vx, Vy, Vz), radiates from
the epipole e = (Vx/Vz, Vy/Vz): ṗ = (Vz/d)(p − e). Each pixel then gives one linear
equation in e, ṗ_y·e_x − ṗ_x·e_y = ṗ_y·x − ṗ_x·y, and the epipole is the robust
least-squares solution pooled over pixels and frames. Real footage seldom moves along
the optical axis, so r must be measured about this point, not the principal point.
A gyro's bias and scale error leave a rotation in the derotated flow that a slow camera's
heading fit mistakes for a shifted epipole; :class:`HeadingBiasEstimator` fits the heading,
the bias and the scale error jointly (:func:`residual_rotation` fits the rotation alone,
given the heading).
"""
from __future__ import annotations

import sys

import numpy as np


def _is_tensor(a) -> bool:
    """Whether a is a torch tensor, without importing torch (only a caller that has it can pass one)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(a, torch.Tensor)


def rotational_flow(omega: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Flow (1/s), (2, ...), of a pinhole camera rotating at ``omega`` = (ωx, ωy, ωz) (3,) rad/s (camera frame).

    x, y: normalised coordinates, any one shape (numpy arrays or torch tensors; the result follows).
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

    omega (3,) rad/s: the camera's rotation rate (camera frame); x, y (H, W): the pixels' normalised
    coordinates. Returns the derotated flow (2, H, W) 1/s.
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
    where a camera turned by r sees the same directions. x, y: normalised coordinates, any one
    shape; returns (x', y') of that shape."""
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
    """Mean gyro reading (rad/s, (3,)) over [t0, t1] s: the rotation a frame pair saw, divided by its gap.

    gyro_t (n,) s and gyro (n, 3) rad/s: the gyro's samples; with none inside the span, the rate
    interpolated at its middle.
    """
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

    x, y (H, W): the pixels' normalised coordinates; prior (2,): normalised; prior_weight
    ((1/s)², the units of one pixel's equation): the prior's weight in the normal equations;
    stride: pixels. ``e`` (2,) is the running epipole (normalised, in the reference frame when
    updates carry an attitude) and ``n_frames`` the frames that counted.

    A vehicle's velocity turns with its body (a fly's saccade, a car's bend); a hand-held camera's
    need not. The heading is held fixed in the reference between turns and re-learned after a fast
    one (:meth:`forget_heading`).
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
        self.prior_weight = float(prior_weight)
        self.n_frames = 0
        #: (3, 3): the orientation (camera → the updates' reference) the heading is held in
        self.anchor = np.eye(3)

    def update(self, flow: np.ndarray, points=None, attitude: np.ndarray | None = None) -> np.ndarray:
        """Add one derotated flow field (2, H, W) (1/s) and return the epipole (2,), normalised.

        points: (X, Y, flow_at_points (2, N)) at the strided pixels instead, e.g. from
        :func:`derotate_finite`, whose points sit where the pair's middle orientation sees them.
        attitude (3, 3): the camera's orientation for this flow (camera → a fixed reference,
        from the integrated gyro). The heading is then accumulated in that reference, where it
        stays put while the camera turns, and the returned epipole is the heading seen from
        the camera now; without it the camera is taken as not turning.
        """
        if attitude is not None:
            attitude = self.anchor.T @ np.asarray(attitude, float)
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

    def forget_heading(self, attitude, seen) -> None:
        """Start the heading afresh after the camera turned fast (a saccade, a bend).

        Whether the velocity turned with the body is for the flow after the turn to tell: the
        heading's information so far is dropped, its prior mean becomes ``seen`` (2,), normalised,
        the epipole as the camera saw it before the turn (a vehicle's velocity follows its body),
        and from now on it is held in the camera's orientation ``attitude`` (3, 3, camera → the
        updates' reference): a heading 90° off the start's axis has no normalised coordinates there.
        """
        self.anchor = np.asarray(attitude, float).copy()
        self.e = np.asarray(seen, float).copy()
        self.ata = np.eye(2) * self.prior_weight
        self.atb = self.e * self.prior_weight
        self.n_frames = 0

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
        def normal_equations(e):
            res = a @ e - b
            scale = 1.4826 * np.median(np.abs(res)) + 1e-12
            w = 1.0 / (1.0 + (res / (2.385 * scale)) ** 2)
            aw = a * w[:, None]
            return aw.T @ a, aw.T @ b, w, res

        e = np.asarray(start, float)
        # About a start far from this frame's heading the residuals hold the model's error, and
        # σ² taken from them (below) overcorrects: from the principal point a heading 20° off the
        # axis would come out at 75°, and one 30° off makes the system indefinite so that the frame
        # is dropped and such a heading never found. Plain steps first, while they move the heading far.
        neq = normal_equations(e)
        for _ in range(WARMUP_ITERS):
            if not _well_posed(neq[0]):
                return None
            step = np.linalg.solve(neq[0], neq[1])
            if np.hypot(*(step - e)) < WARMUP_STEP:
                break  # near already: the corrected steps start from these equations
            e = step
            neq = normal_equations(e)
        for k in range(iters):
            ata, atb, w, res = neq if k == 0 else normal_equations(e)
            # Flow noise (std σ) sits in both sides of the equations and biases the fit
            # toward the image centre by σ²·Σw·I and σ²·Σw·p; remove that, with σ²
            # estimated from the residuals, whose variance is σ²|p − e|².
            r2 = (x - e[0]) ** 2 + (y - e[1]) ** 2
            s2 = np.sum(w * res ** 2) / max(np.sum(w * r2), 1e-20)
            ata = ata - s2 * np.sum(w) * np.eye(2)
            atb = atb - s2 * np.array([np.sum(w * x), np.sum(w * y)])
            if not _well_posed(ata):
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


#: plain (uncorrected) IRLS steps a frame's heading fit may take first, from a start far off it,
#: while a step moves the heading by more than WARMUP_STEP (normalised; 0.05 ≈ 3° at the centre).
WARMUP_ITERS = 6
WARMUP_STEP = 0.05


def _well_posed(ata: np.ndarray) -> bool:
    return bool(np.linalg.cond(ata) <= 1e8 and np.all(np.linalg.eigvalsh(ata) > 0))


def residual_rotation(x, y, flow, epipole, iters: int = 3):
    """The rotation rate δω (3,) rad/s still in derotated flow, given the heading, and its variance (3,) (rad/s)².

    x, y: normalised coordinates of points (any shape); flow (2, ...) 1/s: their flow after
    the gyro's derotation (e.g. :func:`derotate_finite`'s, in the pair's middle orientation);
    epipole (2,) normalised: the heading seen in that orientation; iters: IRLS iterations.
    What a rigid scene's translation
    leaves is radial from the epipole, so the flow's component across the ray from it,
    (ṗ − B(p)·δω) × (p − e), must vanish: with e given that is *linear* in δω (B the
    rotational flow per unit rate, :func:`rotational_flow`) and needs no depth. Solved by
    least squares on the perpendicular residuals (each equation divided by |p − e|), with
    Cauchy weights against failed flow. The variance is the fit's σ²·(AᵀWA)⁻¹; flow errors
    are correlated across pixels, so it is a lower bound (callers use the scatter of
    successive fits instead, :class:`lobula.imu.GyroAttitude`). NaN where too few points.
    """
    x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
    u, v = (np.asarray(c, float).ravel() for c in flow)
    ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(x) & np.isfinite(y)
    x, y, u, v = x[ok], y[ok], u[ok], v[ok]
    dx, dy = x - float(epipole[0]), y - float(epipole[1])
    rho = np.hypot(dx, dy)
    keep = rho > 1e-3  # at the epipole the perpendicular direction is undefined
    if keep.sum() < 10:
        return np.full(3, np.nan), np.full(3, np.nan)
    x, y, u, v, dx, dy, rho = x[keep], y[keep], u[keep], v[keep], dx[keep], dy[keep], rho[keep]
    # Rotational flow per unit rate about x, y, z at each point (as rotational_flow).
    bu = np.stack([x * y, -(1 + x * x), y], -1)
    bv = np.stack([1 + y * y, -x * y, -x], -1)
    # (u − bu·δω)·dy − (v − bv·δω)·dx = 0  →  (bu·dy − bv·dx)·δω = u·dy − v·dx.
    a = (bu * dy[:, None] - bv * dx[:, None]) / rho[:, None]
    b = (u * dy - v * dx) / rho
    w = np.ones_like(b)
    sol = np.zeros(3)
    for _ in range(iters):
        aw = a * w[:, None]
        ata = aw.T @ a
        if np.linalg.cond(ata) > 1e10:
            return np.full(3, np.nan), np.full(3, np.nan)
        sol = np.linalg.solve(ata, aw.T @ b)
        res = b - a @ sol
        scale = 1.4826 * np.median(np.abs(res)) + 1e-12
        w = 1.0 / (1.0 + (res / (2.385 * scale)) ** 2)
    s2 = np.sum(w * res ** 2) / max(np.sum(w) - 3, 1.0)
    return sol, s2 * np.diag(np.linalg.inv((a * w[:, None]).T @ a))


#: normalised: a heading further than this from the optical axis (~63°) is no fit to a forward camera.
MAX_HEADING = 2.0
#: a frame's expansion must move the view (at its median distance from the centre) by at least
#: this many times the flow's residual noise before it may place the heading.
MIN_EXPANSION_SNR = 1.0
#: normalised (~3°): a frame places the heading only if the bias's remaining std moves it less.
HEADING_TOL = 0.05
#: independent points a frame's flow is worth: its errors are correlated over the whole view
#: (DIS at large displacements, texture-poor regions), so thousands of pixels tell about as much
#: as a handful. Development scenes (rotation and fast corridor, seeds 100–102): 100 let a fast
#: corridor's first frames set a bias 2 mrad/s off that the still-camera estimate could not undo.
FRAME_POINTS = 5
#: points per frame the joint fit needs (a 14-parameter fit worth FRAME_POINTS independent ones):
#: callers stride the image to about this many (the cost per pair grows with it).
HEADING_POINTS = 2000


class HeadingBiasEstimator(EpipoleEstimator):
    """The heading and the gyro's bias, jointly, from gyro-derotated flow of a turning camera.

    A gyro bias b left in the derotation turns the flow by δω = b̂ − b (b̂ the bias removed).
    Given the heading that is linear (:func:`residual_rotation`), but the heading is itself
    fitted to the same flow, and a frontal scene confounds the two: at speed r = v/d a
    residual rotation looks like an epipole shift of δω/r — degrees at walking speed, with
    a BMI055's ±0.25 °/s. Fitted one after the other, each absorbs the other's error (on a
    development scene the bias settles at the wrong sign). Fitted jointly over frames they
    separate, because the heading stays put in a fixed reference while r changes: a slow
    frame's flow is mostly the residual rotation (it pins b), a fast one's mostly radial (it
    pins e). Each point gives, linearised about the running estimate e₀,
    l_ref·(e_ref, 1) + s₀·C·(b̂ − b) = 0, with l the line through the point along its flow
    turned into the reference (as :class:`EpipoleEstimator`), C = B_u·(y − e₀y) − B_v·(x − e₀x)
    the rotational flow's component across the ray from e₀ and s₀ the homogeneous scale.
    Each frame's equations (divided by its own residual scale, Cauchy-weighted about the
    running solution, the flow-noise bias of the heading block removed as in the parent) are
    added to normal equations in (e_ref, b) that start from the bias prior ``bias0`` ±
    ``bias0_std`` (rad/s, e.g. :func:`lobula.imu.gyro_bias`'s still-camera estimate).
    ``update`` needs ``attitude`` and ``applied_bias`` (the b̂ the derotation removed);
    ``bias`` is the current estimate (3,) rad/s and ``bias_std`` its formal std.

    x, y (H, W), prior (2,) and stride as for :class:`EpipoleEstimator`; bias0 (3,) rad/s and
    bias0_std (rad/s, scalar or (3,)): the bias prior; heading_std (normalised): the heading
    prior's std about ``prior``; scale_std (dimensionless): the prior std of each entry of the
    gyro's scale-factor and misalignment error E (3, 3), which is then fitted too (None: not fitted).
    """

    def __init__(self, x, y, bias0, bias0_std, prior=(0.0, 0.0), stride: int = 4, heading_std: float = 1.0,
                 scale_std: float | None = None):
        super().__init__(x, y, prior=prior, stride=stride)
        b0 = np.broadcast_to(np.asarray(bias0, float), (3,))
        info = [np.full(2, 1.0 / heading_std ** 2), 1.0 / np.broadcast_to(np.asarray(bias0_std, float), (3,)) ** 2]
        self.n_scale = 0 if scale_std is None else 9
        if self.n_scale:
            info.append(np.full(9, 1.0 / scale_std ** 2))
        self.ata = np.diag(np.concatenate(info))
        self.theta = np.concatenate([self.prior, b0, np.zeros(self.n_scale)])
        self.atb = self.ata @ self.theta
        self._heading_info = 1.0 / heading_std ** 2
        self._bias_prior = (self.ata[2:5, 2:5].diagonal().copy(), b0.copy())  # (information (3,), mean (3,))
        self.e = self.theta[:2].copy()
        self._scales: list = []  # each frame's robust residual scale (the rotation-only fit's)

    @property
    def bias(self) -> np.ndarray:
        """(3,) rad/s: the gyro bias estimate."""
        return self.theta[2:5].copy()

    def set_bias_prior(self, bias0, bias0_std) -> None:
        """Replace the bias prior (e.g. by the still-camera estimate as it accrues online): bias0 (3,)
        rad/s, bias0_std rad/s (scalar or (3,))."""
        info, mean = self._bias_prior
        new_info = 1.0 / np.broadcast_to(np.asarray(bias0_std, float), (3,)) ** 2
        new_mean = np.broadcast_to(np.asarray(bias0, float), (3,)).copy()
        idx = np.arange(2, 5)
        self.ata[idx, idx] += new_info - info
        self.atb[2:5] += new_info * new_mean - info * mean
        self._bias_prior = (new_info, new_mean)
        self.theta = np.linalg.solve(self.ata, self.atb)
        self.e = self.theta[:2].copy()

    def forget_heading(self, attitude, seen) -> None:
        """As :meth:`EpipoleEstimator.forget_heading`; the gyro's bias and scale keep what the frames
        told of them (the heading marginalised out of the normal equations), the heading its prior std."""
        info = self.ata
        keep = info[2:, 2:] - info[2:, :2] @ np.linalg.solve(info[:2, :2], info[:2, 2:])
        self.ata = np.zeros_like(info)
        self.ata[:2, :2] = np.eye(2) * self._heading_info
        self.ata[2:, 2:] = keep
        self.theta = np.concatenate([np.asarray(seen, float), self.theta[2:]])
        self.atb = self.ata @ self.theta
        self.e = self.theta[:2].copy()
        self.anchor = np.asarray(attitude, float).copy()
        self.n_frames = 0

    def walk_heading(self, var: float) -> None:
        """Let the heading walk: add ``var`` (normalised coordinates², e.g. q²·Δt) to its variance.

        A platform's velocity turns between the camera's turns (a drone drifting sideways as it gathers
        speed, a car changing lanes, a walker's bounce), so the frames to come outweigh the old ones by
        what the heading may have moved since; the gyro's bias and scale keep what the frames told of them.
        The normal equations here are information (each frame's divided by its noise variance), so a
        variance adds to them as it should.
        """
        if not var > 0:
            return
        cov = np.linalg.inv(self.ata)
        cov[:2, :2] += var * np.eye(2)
        info = np.linalg.inv(cov)
        self.ata = 0.5 * (info + info.T)
        self.atb = self.ata @ self.theta

    @property
    def scale(self) -> np.ndarray:
        """(3, 3) the gyro's scale-factor and misalignment error E (zeros unless fitted)."""
        return self.theta[5:].reshape(3, 3).copy() if self.n_scale else np.zeros((3, 3))

    @property
    def bias_std(self) -> np.ndarray:
        """(3,) rad/s: the bias estimate's formal std."""
        return np.sqrt(np.diag(np.linalg.inv(self.ata))[2:5])

    def update(self, flow, points=None, attitude=None, applied_bias=None, rate=None, iters: int = 3) -> np.ndarray:
        """Add one pair (points = (X, Y, flow (2, N)) in its middle orientation, derotated with
        ``applied_bias`` (3,) rad/s removed from the gyro's mean reading ``rate`` (3,) over the pair
        — bias plus E·rate where E is fitted, :meth:`lobula.imu.GyroAttitude.applied_correction`)
        and return the epipole (2,), normalised, seen from the camera.

        X, Y (N,) normalised, flow 1/s; ``flow`` itself is not read. attitude (3, 3): the pair's
        middle orientation (camera → the reference); iters: IRLS iterations per fit (at most 2).
        """
        if points is None or attitude is None or applied_bias is None or (self.n_scale and rate is None):
            raise ValueError("HeadingBiasEstimator.update needs points, attitude, applied_bias (and rate with E)")
        x, y = np.asarray(points[0], float).ravel(), np.asarray(points[1], float).ravel()
        u, v = (np.asarray(c, float).ravel() for c in points[2])
        ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(x) & np.isfinite(y)
        x, y, u, v = x[ok], y[ok], u[ok], v[ok]
        R = self.anchor.T @ np.asarray(attitude, float)
        if x.size < 10:
            return self._seen_epipole(R)
        b_app = np.asarray(applied_bias, float)
        a, rhs, c, e0 = self._pair_equations(R, b_app, rate, x, y, u, v)
        xr, yr = self._seen(R, x, y)
        iters = min(iters, 2)
        # 1. The rotation alone, the heading held at the running estimate. Every frame says this
        #    much; a slow or still camera's flow says little else (its flow is mostly δω's).
        rot = slice(2, None)
        e_cur = self.theta[:2].copy()
        theta_b, ata_b, atb_b = self._rotation_fit(a, rhs, e_cur, iters)
        # 2. Is what is left radial about a heading of its own (translation), beyond the flow's noise?
        joint = None
        own = self._radial(x, y, u, v, c, theta_b, b_app, rate, e0)
        if own is not None:
            theta = np.concatenate([e_cur, theta_b])
            if np.hypot(*(own - e0)) > HEADING_TOL:
                # This frame's own heading lies far from the running one (a heading 30° off the axis
                # against the principal point, the prior): about that start the residuals hold the
                # model's error, and the noise correction below, taken from them, overcorrects until
                # the system is indefinite, which would refuse every such frame and hold the heading
                # at the prior for the whole record. Plain steps from the frame's own heading first,
                # as the parent's warm-up does.
                theta = self._warm_start(a, rhs, theta, own, R)
            joint = self._joint_fit(a, rhs, theta, xr, yr, iters)
        if joint is not None:
            self.ata = self.ata + joint[0]
            self.atb = self.atb + joint[1]
            self.n_frames += 1
        else:  # the rotation's equations only, given the heading
            self.ata[rot, rot] += ata_b
            self.atb[rot] += atb_b
        self.theta = np.linalg.solve(self.ata, self.atb)
        self.e = self.theta[:2].copy()
        return self._seen_epipole(R)

    def _pair_equations(self, R, b_app, rate, x, y, u, v):
        """(A (N, 5 [+ 9]), b (N,), C (N, 3), e₀ (2,)): the pair's linear equations in (e_ref, b [, E])
        about the running heading e₀ as seen in orientation ``R`` (3, 3)."""
        # Lines along the flow, turned into the reference.
        l_ref = np.stack([-v, u, v * x - u * y], -1) @ R.T
        h = R.T @ np.array([self.theta[0], self.theta[1], 1.0])
        s0, e0 = h[2], h[:2] / h[2]  # the running heading seen in this orientation
        bu = np.stack([x * y, -(1 + x * x), y], -1)
        bv = np.stack([1 + y * y, -x * y, -x], -1)
        c = bu * (y - e0[1])[:, None] - bv * (x - e0[0])[:, None]
        cols = [-l_ref[:, :2], s0 * c]
        if self.n_scale:
            g = np.asarray(rate, float) - self.theta[2:5]  # E's regressor: the bias-free rate
            cols.append(s0 * (c[:, :, None] * g[None, None, :]).reshape(-1, 9))
        a = np.concatenate(cols, axis=1)
        rhs = l_ref[:, 2] + s0 * (c @ b_app)
        return a, rhs, c, e0

    def _rotation_fit(self, a, rhs, e_cur, iters):
        """(θ_b, AᵀWA, AᵀWb) of the rotation block alone, the heading held at ``e_cur`` (2,); this
        frame's robust residual scale appended to the record's."""
        rot = slice(2, None)
        ab, rhs_b = a[:, rot], rhs - a[:, :2] @ e_cur
        prior_b = self.atb[rot] - self.ata[rot, :2] @ e_cur
        theta_b = self.theta[rot].copy()
        for _ in range(iters):
            w = self._weights(ab @ theta_b - rhs_b)
            aw = ab * w[:, None]
            ata_b, atb_b = aw.T @ ab, aw.T @ rhs_b
            theta_b = np.linalg.solve(self.ata[rot, rot] + ata_b, prior_b + atb_b)
        self._scales.append(1.4826 * float(np.median(np.abs(ab @ theta_b - rhs_b))) + 1e-12)
        return theta_b, ata_b, atb_b

    def _warm_start(self, a, rhs, theta, own, R):
        """θ after plain reweighted steps from this frame's own heading ``own`` (2,), seen in ``R``."""
        h_ref = R @ np.array([own[0], own[1], 1.0])
        theta[:2] = h_ref[:2] / h_ref[2]
        for _ in range(WARMUP_ITERS):
            w = self._weights(a @ theta - rhs)
            aw = a * w[:, None]
            step = np.linalg.solve(self.ata + aw.T @ a, self.atb + aw.T @ rhs)
            if not np.all(np.isfinite(step)):
                break  # keep the last finite start; the corrected steps below judge it
            moved, theta = np.hypot(*(step[:2] - theta[:2])), step
            if moved < WARMUP_STEP:
                break
        return theta

    def _joint_fit(self, a, rhs, theta, xr, yr, iters):
        """(AᵀWA, AᵀWb) of the joint fit in (e_ref, b [, E]) from ``theta``, the heading block's
        flow-noise bias removed; None where the system turns indefinite or the heading runs off."""
        for _ in range(iters):
            res = a @ theta - rhs
            w = self._weights(res)
            aw = a * w[:, None]
            ata, atb = aw.T @ a, aw.T @ rhs
            # Flow noise in the heading's coefficients biases it toward the image centre (parent).
            r2 = (xr - theta[0]) ** 2 + (yr - theta[1]) ** 2
            s2 = np.sum(w * res ** 2) / max(np.sum(w * r2), 1e-20)
            ata[:2, :2] -= s2 * np.sum(w) * np.eye(2)
            atb[:2] -= s2 * np.array([np.sum(w * xr), np.sum(w * yr)])
            if np.any(np.linalg.eigvalsh(ata[:2, :2]) <= 0):
                break
            tot = self.ata + ata
            theta = np.linalg.solve(tot, self.atb + atb)
            if not (np.all(np.isfinite(theta)) and np.hypot(*theta[:2]) < MAX_HEADING):
                break
        else:
            return ata, atb
        return None

    def _weights(self, res):
        """Cauchy weights of residuals (about this frame's robust scale), divided by the noise
        variance: this frame's scale squared, but at least the median over the frames so far.
        A slow frame's residuals are small because its flow is, and by its own scale its
        few-pixel heading information would outweigh every fast frame's; a fast frame's flow
        errs more (large displacements), and by the median alone its errors would pass for
        rotation (the causal fast corridor's bias until the still-camera estimate arrives)."""
        scale = 1.4826 * np.median(np.abs(res)) + 1e-12
        noise = max(scale, float(np.median(self._scales))) if self._scales else scale
        # Flow errors are correlated over many pixels: a frame counts as FRAME_POINTS independent ones.
        return 1.0 / (1.0 + (res / (2.385 * scale)) ** 2) / noise ** 2 * min(1.0, FRAME_POINTS / res.size)

    def _radial(self, x, y, u, v, c, theta_b, b_app, rate, e0, t_min: float = 3.0) -> np.ndarray | None:
        """This frame's own heading (2,) where the flow left after the fitted rotation shows
        translation — an expansion whose flow across the view stands above the flow's noise, and
        radial about that heading beyond its spread (the parent's test: Σ(radial² − across²) over
        t_min of its spread) — else None.

        The expansion r comes from d = r·p + k fitted to the remaining flow (k = −r·e absorbs the
        heading). A rotation left over has no such term (its divergence is odd across the view),
        but with r ≈ 0 it fits a heading far off the axis as well as a rotation does — which is
        how a slow camera's frames dragged the heading and the bias together the wrong way.
        """
        dw = b_app - theta_b[:3]
        if self.n_scale:
            dw = dw - theta_b[3:].reshape(3, 3) @ (np.asarray(rate, float) - theta_b[:3])
        ru, rv = rotational_flow(dw, x, y)
        du, dv = u - ru, v - rv
        xc, yc = x - x.mean(), y - y.mean()
        r = (np.sum(xc * du) + np.sum(yc * dv)) / max(np.sum(xc * xc + yc * yc), 1e-20)
        res = np.concatenate([du - du.mean() - r * xc, dv - dv.mean() - r * yc])
        noise = 1.4826 * np.median(np.abs(res)) + 1e-12
        if abs(r) * np.median(np.hypot(xc, yc)) < MIN_EXPANSION_SNR * noise:
            return None
        # The bias still unknown shifts the heading by about its std / r: place it only where that is
        # small (~3°), or where this frame's own heading (−k/r from the fit above) lies farther from
        # the running one than 3× that shift (a camera panning 25° to the side otherwise keeps the
        # principal point, its prior, for seconds, and the fields read about it show a forward run
        # as a retreat; relaxing the shift's bound instead lets slow frames drag a heading near the
        # axis and the bias the wrong way: development rotation seed 100, 0.15 m/s against 0.014).
        shift = np.linalg.norm(self.bias_std) / abs(r)
        own = np.array([x.mean() - du.mean() / r, y.mean() - dv.mean() / r])
        if shift > HEADING_TOL and np.hypot(*(own - e0)) < 3.0 * shift:
            return None
        # Radial about the frame's own heading, not the running one: about a running heading far off
        # (the prior, before any frame placed it) a translation's flow is not radial, and the test
        # would refuse the very frames that could move it.
        dx, dy = x - own[0], y - own[1]
        d = (dx * du + dy * dv) ** 2 - (dx * dv - dy * du) ** 2
        return own if np.sum(d) >= t_min * np.sqrt(np.sum(d ** 2)) else None

    def _seen_epipole(self, attitude) -> np.ndarray:
        h = np.asarray(attitude, float).T @ np.array([self.theta[0], self.theta[1], 1.0])
        return h[:2] / h[2]
