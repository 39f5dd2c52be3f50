"""Fly-like saccadic flight: straight segments joined by fast body saccades in yaw, exact to the sample.

A :class:`FlightPlan` moves the camera of a :class:`~stimuli.scene.TrackScene` through its world the
way a fly cruises: it flies straight for 0.2-2 s, turns by a body saccade of 20-90° in yaw lasting
50-100 ms, flies straight again, and so on. The frames are the track frame's (x right, y down,
z along the track); the heading ψ(t) is a yaw about the down axis y (positive turns right, towards +x),
and the body flies along its own axis, so the world velocity is v(t)·(sin ψ, 0, cos ψ) and the
position its integral. The camera is the body's, turned by a small residual yaw/pitch/roll wobble.

The plan (:func:`saccadic_flight`, seeded; every range is a :class:`FlightConfig` field):

* **segments**: straight flight, durations uniform in ``segment_s``, cut short (never below the
  shortest segment) where flying on would carry the fly more than ``lateral_limit_m`` off the track
  axis;
* **saccades**: amplitude A and duration d, d rising with A across ``saccade_s`` (larger turns take
  longer, as in flies) with a jitter of ``saccade_jitter_s``; the yaw rate is a raised cosine,
  ψ̇(τ) = (A/d)·(1 − cos 2πτ/d) for 0 ≤ τ ≤ d, so the angular acceleration is continuous, the peak
  rate is 2A/d and the heading turns by exactly A;
* **direction rule**: each saccade turns the opposite way to the one before (the fly's zig-zag), and
  the heading after it must lie within ±``heading_limit_deg`` of the track axis and, when the fly is
  more than ``centre_m`` off the axis, point back towards the axis by at least ``return_deg``. The
  amplitude is drawn uniformly among those that meet this for the alternating direction; where none
  does, the saccade turns the same way as the one before, amplitude drawn likewise (one direction or
  the other always has room while saccade_deg[0] ≤ heading_limit_deg − return_deg). This keeps the heading within ±60° and the path
  inside the corridor and panels worlds;
* **speed**: forward speed within ``speed_m_s``; each segment draws a new target speed and reaches it
  by a quintic smooth step over the middle 80% of the segment (acceleration continuous and zero at
  the ends, peak 1.875·Δv/T), the change bounded so the peak acceleration stays within
  ``max_accel_m_s2`` (the flight motor's); the speed holds through saccades;
* **wobble**: yaw, pitch and roll each a sum of ``wobble_components`` sinusoids with frequencies in
  ``wobble_band_hz`` and random phases, weights summing to one so |angle| ≤ ``wobble_deg``.

Heading, speed, their derivatives, the world velocity and acceleration (tangential plus centripetal)
and the body angular velocity are analytic. The position is the velocity integrated on a fine grid
(3-point Gauss–Legendre per interval of 1/``grid_hz`` s, exact to rounding for these smooth
profiles) and interpolated by cubic Hermite segments that take the exact velocity as their slope.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.interpolate import CubicHermiteSpline

#: How far (s) the plan reaches beyond [0, duration]: blur sub-frames and the IMU's derivatives look
#: slightly outside the run.
PAD_S = 1.0


@dataclass
class FlightConfig:
    """Parameters of a saccadic flight plan (module doc); seconds, metres, degrees, hertz.

    segment_s: (shortest, longest) straight segment (s). saccade_deg: (smallest, largest) saccade
    amplitude (deg). saccade_s: (shortest, longest) saccade duration (s), reached at the smallest
    and largest amplitude; saccade_jitter_s: uniform jitter (±, s) on it, clipped to the range.
    heading_limit_deg: the largest |heading| (deg) off the track axis. centre_m: lateral offset (m)
    beyond which the next heading must point back towards the axis by at least return_deg (deg).
    lateral_limit_m: a segment heading away from the axis ends before the fly passes this offset (m)
    (not before segment_s[0]). speed_m_s: (lowest, highest) forward speed (m/s). max_accel_m_s2: the
    largest forward acceleration (m/s²). wobble_deg: (yaw, pitch, roll) peak residual wobble (deg);
    wobble_band_hz: its frequency band (Hz); wobble_components: sinusoids per axis. grid_hz: rate
    (Hz) of the grid the position is integrated on.
    """

    segment_s: tuple = (0.2, 2.0)
    saccade_deg: tuple = (20.0, 90.0)
    saccade_s: tuple = (0.05, 0.1)
    saccade_jitter_s: float = 0.01
    heading_limit_deg: float = 60.0
    centre_m: float = 0.15
    return_deg: float = 10.0
    lateral_limit_m: float = 0.4
    speed_m_s: tuple = (0.1, 1.0)
    max_accel_m_s2: float = 4.0
    wobble_deg: tuple = (1.5, 1.5, 1.5)
    wobble_band_hz: tuple = (2.0, 8.0)
    wobble_components: int = 3
    grid_hz: float = 1000.0

    def __post_init__(self):
        lo, hi = self.saccade_deg
        if not 0 < lo <= hi or hi > 2 * self.heading_limit_deg:
            raise ValueError(f"saccade_deg must be 0 < lo <= hi <= 2·heading_limit_deg, got {self.saccade_deg}")
        if lo > self.heading_limit_deg - self.return_deg:
            raise ValueError("the smallest saccade must fit between the heading limit and return_deg "
                             f"(saccade_deg[0] <= heading_limit_deg - return_deg), got {self.saccade_deg}")
        for name in ("segment_s", "saccade_s", "speed_m_s", "wobble_band_hz"):
            a, b = getattr(self, name)
            if not 0 < a <= b:
                raise ValueError(f"{name} must be 0 < lo <= hi, got {getattr(self, name)}")
        if len(tuple(self.wobble_deg)) != 3:
            raise ValueError(f"wobble_deg needs 3 amplitudes (yaw, pitch, roll), got {self.wobble_deg}")
        if self.max_accel_m_s2 <= 0 or self.grid_hz <= 0 or self.wobble_components < 1:
            raise ValueError("max_accel_m_s2 and grid_hz must be positive and wobble_components >= 1")
        if not 0 <= self.centre_m <= self.lateral_limit_m:
            raise ValueError(f"need 0 <= centre_m <= lateral_limit_m, got {self.centre_m}, {self.lateral_limit_m}")

    def to_dict(self) -> dict:
        """The parameters as a plain dict (tuples stay tuples)."""
        return asdict(self)


# ------------------------------------------------------------------ smooth unit profiles
def _saccade_unit(x: np.ndarray, order: int = 0) -> np.ndarray:
    """The raised-cosine saccade on unit time and amplitude: P(x) for order 0, P'(x), P''(x) for 1, 2.

    P(x) = x − sin(2πx)/(2π) on [0, 1], 0 before and 1 after; x any shape (dimensionless).
    """
    xc = np.clip(x, 0.0, 1.0)
    inside = (x > 0) & (x < 1)
    if order == 0:
        return xc - np.sin(2 * np.pi * xc) / (2 * np.pi)
    if order == 1:
        return np.where(inside, 1.0 - np.cos(2 * np.pi * xc), 0.0)
    return np.where(inside, 2 * np.pi * np.sin(2 * np.pi * xc), 0.0)


def _smoothstep_unit(x: np.ndarray, order: int = 0) -> np.ndarray:
    """The quintic smooth step S(x) = 6x⁵ − 15x⁴ + 10x³ on [0, 1] (0 before, 1 after), or S'(x) for order 1."""
    xc = np.clip(x, 0.0, 1.0)
    if order == 0:
        return xc ** 3 * (10 - 15 * xc + 6 * xc ** 2)
    return np.where((x > 0) & (x < 1), 30 * xc ** 2 * (1 - xc) ** 2, 0.0)


def _rotation(angle: np.ndarray, axis: int) -> np.ndarray:
    """Rotation matrices (..., 3, 3) by angles (...) (rad) about axis 0 (x), 1 (y) or 2 (z)."""
    c, s = np.cos(angle), np.sin(angle)
    r = np.zeros(np.shape(angle) + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r[..., axis, axis] = 1.0
    r[..., i, i] = c
    r[..., j, j] = c
    r[..., i, j] = -s
    r[..., j, i] = s
    return r


# ------------------------------------------------------------------ the plan
class FlightPlan:
    """A seeded saccadic flight (module doc): heading, speed, wobble and the path they make.

    Every method takes times t (s) of any shape (...) and is exact (analytic) except
    :meth:`position`, which is the analytic velocity integrated on a fine grid. Attributes:
    duration_s (s); saccades (k, 2) start and end times (s); saccade_amplitudes_deg (k,) signed
    (positive: a right turn, towards +x); segments (k + 1, 2) start and end times (s) of the straight
    segments (the last one as drawn: the path goes on straight after it); seed; config (:class:`FlightConfig`).
    """

    def __init__(self, duration_s: float, seed: int, config: FlightConfig, segments, saccades, amplitudes_deg,
                 speed0: float, ramps, wobble):
        """segments (k + 1, 2) s; saccades (k, 2) s; amplitudes_deg (k,) signed deg; speed0 (m/s) at
        t = 0; ramps (m, 3): start (s), end (s), speed change (m/s) of each smooth step; wobble: frequencies (3, K) Hz, phases (3, K)
        rad, amplitudes (3, K) rad."""
        self.duration_s = float(duration_s)
        self.seed = seed
        self.config = config
        self.saccades = np.asarray(saccades, float).reshape(-1, 2)
        self.saccade_amplitudes_deg = np.asarray(amplitudes_deg, float)
        self.segments = np.asarray(segments, float).reshape(-1, 2)
        self._amp = np.radians(self.saccade_amplitudes_deg)
        self._speed0 = float(speed0)
        self._ramps = np.asarray(ramps, float).reshape(-1, 3)
        self._wobble = wobble
        self._build_path()

    # ---------------------------------------------------------- heading and speed
    def heading(self, t, order: int = 0) -> np.ndarray:
        """Heading ψ (rad) off the track axis, a yaw about y (positive: right), shape (...); order 1
        gives ψ̇ (rad/s), order 2 ψ̈ (rad/s²)."""
        t = np.asarray(t, dtype=float)
        if not len(self._amp):
            return np.zeros(t.shape)
        t0, d = self.saccades[:, 0], self.saccades[:, 1] - self.saccades[:, 0]
        x = (t[..., None] - t0) / d
        return np.sum(self._amp / d ** order * _saccade_unit(x, order), axis=-1)

    def speed(self, t, order: int = 0) -> np.ndarray:
        """Forward speed v (m/s) along the body axis, shape (...); order 1 gives dv/dt (m/s²)."""
        t = np.asarray(t, dtype=float)
        base = np.full(t.shape, self._speed0) if order == 0 else np.zeros(t.shape)
        if not len(self._ramps):
            return base
        a, b, dv = self._ramps.T
        x = (t[..., None] - a) / (b - a)
        return base + np.sum(dv / (b - a) ** order * _smoothstep_unit(x, order), axis=-1)

    def wobble(self, t, order: int = 0) -> np.ndarray:
        """Residual (yaw, pitch, roll) wobble (rad), shape (..., 3); order 1 gives its rates (rad/s)."""
        t = np.asarray(t, dtype=float)
        freq, phase, amp = self._wobble
        w = 2 * np.pi * freq
        arg = w * t[..., None, None] + phase
        if order == 0:
            return np.sum(amp * np.sin(arg), axis=-1)
        return np.sum(amp * w * np.cos(arg), axis=-1)

    # ---------------------------------------------------------- the path
    def velocity_world(self, t) -> np.ndarray:
        """World (track-frame) velocity v·(sin ψ, 0, cos ψ) (m/s), shape (..., 3)."""
        v, psi = self.speed(t), self.heading(t)
        return np.stack([v * np.sin(psi), np.zeros_like(v), v * np.cos(psi)], axis=-1)

    def acceleration_world(self, t) -> np.ndarray:
        """World acceleration (m/s²), shape (..., 3): tangential v̇·(sin ψ, 0, cos ψ) plus centripetal
        v·ψ̇·(cos ψ, 0, −sin ψ)."""
        v, dv = self.speed(t), self.speed(t, 1)
        psi, dpsi = self.heading(t), self.heading(t, 1)
        s, c = np.sin(psi), np.cos(psi)
        return np.stack([dv * s + v * dpsi * c, np.zeros_like(v), dv * c - v * dpsi * s], axis=-1)

    def _build_path(self):
        """Integrate the world velocity and the speed on the fine grid (module doc), from PAD_S before
        t = 0 to PAD_S after duration_s; position and path length are 0 at t = 0."""
        h = 1.0 / self.config.grid_hz
        n0, n1 = int(np.ceil(PAD_S / h)), int(np.ceil((self.duration_s + PAD_S) / h))
        knots = np.arange(-n0, n1 + 1) * h  # t = 0 is knot n0
        gl = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
        wts = np.array([5.0, 8.0, 5.0]) / 18.0
        mid = 0.5 * (knots[:-1] + knots[1:])
        tq = mid[:, None] + 0.5 * h * gl  # (n, 3) quadrature times
        vq = self.velocity_world(tq)      # (n, 3 nodes, 3 axes)
        sq = self.speed(tq)
        steps = h * np.einsum("q,nqa->na", wts, vq)
        arc = h * sq @ wts
        pos = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
        s = np.concatenate([[0.0], np.cumsum(arc)])
        pos, s = pos - pos[n0], s - s[n0]
        pos[n0], s[n0] = 0.0, 0.0
        self._path = CubicHermiteSpline(knots, pos, self.velocity_world(knots), axis=0)
        self._arc = CubicHermiteSpline(knots, s, self.speed(knots))

    def position(self, t) -> np.ndarray:
        """Camera centre in the track frame (m), shape (..., 3); (0, 0, 0) at t = 0."""
        return self._path(np.asarray(t, dtype=float))

    def distance(self, t) -> np.ndarray:
        """Path length flown since t = 0 (m), shape (...)."""
        return self._arc(np.asarray(t, dtype=float))

    def z_range(self, dt: float = 0.01) -> tuple[float, float]:
        """The smallest and largest track coordinate z (m) of the path over [0, duration_s]."""
        z = self.position(np.arange(0.0, self.duration_s + dt, dt))[:, 2]
        return float(z.min()), float(z.max())

    # ---------------------------------------------------------- attitude
    def _angles(self, t, order: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Body yaw (heading plus yaw wobble), pitch and roll (rad), each shaped like t; their rates
        (rad/s) for order 1."""
        w = self.wobble(t, order)
        return self.heading(t, order) + w[..., 0], w[..., 1], w[..., 2]

    def rotation(self, t) -> np.ndarray:
        """Body(camera)-to-track rotation R = R_y(ψ + yaw wobble)·R_x(pitch)·R_z(roll), shape (..., 3, 3)."""
        yaw, pitch, roll = self._angles(t)
        return _rotation(yaw, 1) @ _rotation(pitch, 0) @ _rotation(roll, 2)

    def angular_velocity(self, t) -> np.ndarray:
        """Body-frame angular velocity ω (rad/s), the vee of Rᵀ·dR/dt, shape (..., 3).

        For R = R_y(α)·R_x(β)·R_z(γ): ω = (R_x R_z)ᵀ·ŷ·α̇ + R_zᵀ·x̂·β̇ + ẑ·γ̇.
        """
        _, pitch, roll = self._angles(t)
        da, db, dg = self._angles(t, 1)
        rz, rxz = _rotation(roll, 2), _rotation(pitch, 0) @ _rotation(roll, 2)
        return (rxz[..., 1, :] * da[..., None] + rz[..., 0, :] * db[..., None]
                + np.array([0.0, 0.0, 1.0]) * dg[..., None])

    # ---------------------------------------------------------- the speed as a Trajectory
    def trajectory(self) -> "PathTrajectory":
        """The speed along the path as a :class:`~stimuli.trajectory.Trajectory`-like object."""
        return PathTrajectory(self)

    def metadata(self) -> dict:
        """Saccade intervals (s) and signed amplitudes (deg) within [0, duration_s], for a run's scene.json."""
        keep = self.saccades[:, 0] < self.duration_s
        return dict(flight="saccadic", flight_seed=self.seed,
                    saccades=self.saccades[keep].round(6).tolist(),
                    saccade_amplitudes_deg=self.saccade_amplitudes_deg[keep].round(4).tolist())


class PathTrajectory:
    """Motion along a flight path in the :class:`~stimuli.trajectory.Trajectory` interface.

    velocity(t): forward speed (m/s); acceleration(t): its rate of change dv/dt (m/s², the
    tangential acceleration); position(t): path length flown since t = 0 (m); each shaped like t.
    """

    def __init__(self, plan: FlightPlan):
        self.plan = plan
        self.duration_s = plan.duration_s
        self.source = f"saccadic flight (seed={plan.seed})"

    def velocity(self, t):
        """Forward speed (m/s), shaped like t (s)."""
        return self.plan.speed(t)

    def acceleration(self, t):
        """Tangential acceleration dv/dt (m/s²), shaped like t (s)."""
        return self.plan.speed(t, 1)

    def position(self, t):
        """Path length flown since t = 0 (m), shaped like t (s)."""
        return self.plan.distance(t)

    def position_range(self, dt: float = 0.01) -> tuple[float, float]:
        """The smallest and largest path length (m) over [0, duration_s], sampled every dt (s)."""
        s = self.position(np.arange(0.0, self.duration_s + dt, dt))
        return float(s.min()), float(s.max())


# ------------------------------------------------------------------ drawing a plan
def _amplitude_window(psi: float, direction: int, lo: float, hi: float, a_min: float, a_max: float):
    """Amplitudes A (deg) in [a_min, a_max] with lo ≤ psi + direction·A ≤ hi (deg); None if there are none."""
    if direction > 0:
        a0, a1 = lo - psi, hi - psi
    else:
        a0, a1 = psi - hi, psi - lo
    a0, a1 = max(a0, a_min), min(a1, a_max)
    return (a0, a1) if a0 <= a1 else None


def saccadic_flight(seed: int, duration_s: float, config: FlightConfig | None = None) -> FlightPlan:
    """Draw a saccadic flight plan (module doc) over [0, duration_s] s from ``seed``.

    Returns a :class:`FlightPlan`; the same seed and configuration give the same plan. The plan
    starts at the origin heading along the track (ψ = 0) in a straight segment, at a speed drawn in
    config.speed_m_s.
    """
    cfg = config or FlightConfig()
    rng = np.random.default_rng([seed, 7])  # its own stream: scene layout and IMU draws do not move
    v_lo, v_hi = cfg.speed_m_s
    a_min, a_max = cfg.saccade_deg
    d_min, d_max = cfg.saccade_s
    lim, back = cfg.heading_limit_deg, cfg.return_deg
    speed0 = v = float(rng.uniform(v_lo, v_hi))
    t, psi, x = 0.0, 0.0, 0.0
    direction = int(rng.choice([-1, 1]))  # the turn before the first one, so the first goes the other way
    saccades, amps, ramps, segments = [], [], [], []
    end = duration_s + PAD_S
    while t < end:
        # ---- a straight segment at heading psi from lateral offset x
        seg = float(rng.uniform(*cfg.segment_s))
        target = float(rng.uniform(v_lo, v_hi))
        sin_psi = np.sin(np.radians(psi))
        v_bound = max(v, target)  # the segment's speed never exceeds this
        if abs(sin_psi) > 1e-12:
            # stop before passing the lateral limit on the side the heading points to
            room = (cfg.lateral_limit_m - np.sign(sin_psi) * x) / (v_bound * abs(sin_psi))
            seg = float(np.clip(room, cfg.segment_s[0], seg))
        # the speed change fits the flight motor over the middle 80% of the segment
        dv_max = cfg.max_accel_m_s2 * 0.8 * seg / 1.875
        target = float(np.clip(target, v - dv_max, v + dv_max))
        if target != v:
            ramps.append((t + 0.1 * seg, t + 0.9 * seg, target - v))
        x += sin_psi * 0.5 * (v + target) * seg  # the smooth step's mean is the midpoint speed
        segments.append((t, t + seg))
        t, v = t + seg, target
        if t >= end:
            break
        # ---- a saccade: alternate, within the heading limit, back towards the axis when off it
        lo, hi = -lim, lim
        if x > cfg.centre_m:
            hi = -back
        elif x < -cfg.centre_m:
            lo = back
        window = _amplitude_window(psi, -direction, lo, hi, a_min, a_max)
        if window is not None:
            direction = -direction
        else:
            window = _amplitude_window(psi, direction, lo, hi, a_min, a_max)
        if window is None:  # cannot happen for a valid FlightConfig (see the module doc)
            raise RuntimeError(f"no saccade fits heading {psi:.1f}° at offset {x:.2f} m")
        amp = float(rng.uniform(*window))
        frac = (amp - a_min) / (a_max - a_min) if a_max > a_min else 0.5
        dur = d_min + (d_max - d_min) * frac + float(rng.uniform(-1, 1)) * cfg.saccade_jitter_s
        dur = float(np.clip(dur, d_min, d_max))
        # lateral travel over the saccade (the raised-cosine heading sampled finely)
        tau = (np.arange(64) + 0.5) / 64
        x += v * dur * np.mean(np.sin(np.radians(psi + direction * amp * _saccade_unit(tau))))
        saccades.append((t, t + dur))
        amps.append(direction * amp)
        psi += direction * amp
        t += dur
    k = cfg.wobble_components
    freq = rng.uniform(*cfg.wobble_band_hz, (3, k))
    phase = rng.uniform(0, 2 * np.pi, (3, k))
    weights = rng.dirichlet(np.ones(k), 3)
    wobble = (freq, phase, np.radians(np.asarray(cfg.wobble_deg, float))[:, None] * weights)
    return FlightPlan(duration_s, seed, cfg, segments, saccades, amps, speed0, ramps, wobble)
