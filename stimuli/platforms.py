"""Real-world camera platforms: a drone, a road vehicle and a hand-held walking camera, exact to the sample.

A :class:`PlatformPlan` moves the camera of a :class:`~stimuli.scene.TrackScene` the way the platform
does, in the same interface as :class:`stimuli.flight.FlightPlan` (the scene takes either as its
``flight``). The frames are the track frame's (x right, y down, z along the track); the platform travels
along z at its speed s'(t), offset sideways by x(t) and vertically by y(t), and the camera's attitude is
R = R_y(yaw)·R_x(pitch)·R_z(roll) (positive pitch looks up, positive yaw turns right); the world's own
off-axis mount (:class:`stimuli.worlds.SceneConfig` ``off_axis_pitch_deg``: a gimbal's tilt) comes on top.

Every plan is drawn from a seed (:func:`platform_plan`; every range is a field of its config):

* **drone** (:class:`DroneConfig`): hovers near rest (``start_speed_m_s``) for ``hover_s``, accelerates
  to a cruise speed in ``cruise_m_s`` over ``accel_s``, then cruises with a slow speed wander of
  ``wander`` (a fraction of the cruise); altitude and lateral position drift by ``drift_m`` (position
  hold); the camera sits on a gimbal that leaves a residual rotation of ``gimbal_deg`` per axis at
  ``gimbal_band_hz``. The propellers' vibration is the IMU's (:class:`stimuli.imu.IMUConfig`
  ``vibration_rms_m_s2``): it moves the sensor by micrometres, which no camera resolves;
* **road** (:class:`RoadConfig`): cruises at a speed in ``cruise_m_s``, brakes to a crawl or standstill
  (``stop_speed_m_s``) at a peak deceleration in ``brake_m_s2``, stands for ``stop_s``, accelerates at a
  peak in ``accel_m_s2`` to a new cruise speed, cruises for ``cruise_s`` and stops again; the first stop
  begins at a fraction ``first_stop`` of the run (the braking is made harder, up to ``brake_max_m_s2``,
  so that the stop falls inside the run). The body pitches with the acceleration (``pitch_per_accel_deg``
  per m/s², nose down when braking), bounces on the road (``bounce_m``, ``bounce_hz``, with a pitch and
  roll of ``rough_deg``) and wanders in its lane (``lane_m``, ``lane_deg`` of yaw), each in proportion to
  the speed;
* **walking** (:class:`WalkConfig`): walks at a mean speed in ``speed_m_s`` from rest (standing for
  ``stand_s``, then setting off over ``setoff_s``) or in stride (``start``); the gait makes the forward
  speed surge by ``surge`` (a fraction) at the step rate ``step_hz``, the camera bounce by ``bounce_m`` at
  the step rate and sway by ``sway_m`` at the stride rate (half the step rate), with a gait-locked pitch
  and roll of ``gait_deg``, all in proportion to the speed; the hand turns the camera by ``hand_deg`` per
  axis at ``hand_band_hz`` (rates of a few °/s to tens of °/s), standing or walking.

Speed changes are jerk-limited ramps: the acceleration rises and falls along a quintic smooth step of
``jerk_s`` seconds each and holds its peak between, so the acceleration and its rate are continuous.
Speed, offsets, angles and their derivatives are analytic; the distance along the track is the speed
integrated on a fine grid (as :class:`stimuli.flight.FlightPlan` does, exact to rounding).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from .flight import PAD_S, PathTrajectory, _rotation, _smoothstep_unit

PLATFORMS = ("drone", "road", "walking")


# ------------------------------------------------------------------ configurations
@dataclass
class DroneConfig:
    """Ranges (lo, hi) a drone plan is drawn from (module doc); m/s, s, m, degrees, hertz."""

    start_speed_m_s: tuple = (0.0, 0.5)
    hover_s: tuple = (0.5, 1.5)
    cruise_m_s: tuple = (5.0, 15.0)
    accel_s: tuple = (2.0, 6.0)
    wander: tuple = (0.0, 0.03)
    wander_band_hz: tuple = (0.05, 0.3)
    drift_m: tuple = (0.05, 0.3)
    drift_band_hz: tuple = (0.05, 0.4)
    gimbal_deg: tuple = (0.1, 0.4)
    gimbal_band_hz: tuple = (0.1, 2.0)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RoadConfig:
    """Ranges (lo, hi) a road vehicle's plan is drawn from (module doc); m/s, m/s², s, m, degrees, hertz."""

    cruise_m_s: tuple = (5.0, 25.0)
    stop_speed_m_s: tuple = (0.0, 0.3)
    brake_m_s2: tuple = (2.5, 6.0)
    brake_max_m_s2: float = 8.0
    accel_m_s2: tuple = (1.5, 3.5)
    stop_s: tuple = (0.5, 2.0)
    cruise_s: tuple = (2.0, 6.0)
    first_stop: tuple = (0.3, 0.5)
    jerk_s: tuple = (0.4, 1.0)
    wander: tuple = (0.0, 0.02)
    wander_band_hz: tuple = (0.05, 0.3)
    pitch_per_accel_deg: tuple = (0.1, 0.3)
    bounce_m: tuple = (0.003, 0.015)
    bounce_hz: tuple = (1.0, 3.0)
    rough_deg: tuple = (0.05, 0.3)
    rough_band_hz: tuple = (1.0, 4.0)
    lane_m: tuple = (0.05, 0.3)
    lane_deg: tuple = (0.1, 0.8)
    lane_band_hz: tuple = (0.05, 0.3)
    #: m/s: the speed at which the bounce, roughness and lane wander have their drawn amplitudes
    reference_speed_m_s: float = 15.0

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class WalkConfig:
    """Ranges (lo, hi) a hand-held walk is drawn from (module doc); m/s, s, m, degrees, hertz.

    start: "rest", "motion" or "either" (each seed draws one of the two)."""

    speed_m_s: tuple = (1.0, 2.0)
    start: str = "either"
    stand_s: tuple = (0.5, 1.5)
    setoff_s: tuple = (1.5, 3.0)
    step_hz: tuple = (1.7, 2.2)
    surge: tuple = (0.05, 0.15)
    bounce_m: tuple = (0.015, 0.04)
    sway_m: tuple = (0.01, 0.04)
    gait_deg: tuple = (0.3, 1.5)
    hand_deg: tuple = (1.0, 4.0)
    hand_band_hz: tuple = (0.2, 2.5)
    wander: tuple = (0.0, 0.08)
    wander_band_hz: tuple = (0.05, 0.2)

    def __post_init__(self):
        if self.start not in ("rest", "motion", "either"):
            raise ValueError(f"walking start must be rest, motion or either, got {self.start!r}")

    def to_dict(self) -> dict:
        return asdict(self)


CONFIGS = {"drone": DroneConfig, "road": RoadConfig, "walking": WalkConfig}


# ------------------------------------------------------------------ analytic pieces
class Ramps:
    """A speed made of jerk-limited ramps: v(t) = v0 + Σ Δv_i·U_i(t) (m/s), with derivatives.

    Ramp i starts at t0_i (s), lasts T_i (s), changes the speed by Δv_i (m/s); its acceleration
    rises over the first jt_i seconds along a quintic smooth step, holds its peak Δv_i/(T_i − jt_i)
    and falls over the last jt_i seconds (jt_i ≤ T_i/2).
    """

    def __init__(self, v0: float, ramps):
        """ramps: (k, 4) rows of t0 (s), T (s), Δv (m/s), jt (s)."""
        self.v0 = float(v0)
        self.ramps = np.asarray(ramps, float).reshape(-1, 4)

    @staticmethod
    def _int_smoothstep(x):
        """∫₀ˣ S(u) du of the quintic smooth step: x⁶ − 3x⁵ + 2.5x⁴ on [0, 1], 0 before, x − ½ after."""
        xc = np.clip(x, 0.0, 1.0)
        return xc ** 4 * (2.5 - 3 * xc + xc ** 2) + np.maximum(x - 1.0, 0.0)

    def __call__(self, t, order: int = 0) -> np.ndarray:
        """v(t) (m/s) for order 0, dv/dt (m/s²) for 1, d²v/dt² (m/s³) for 2; shaped like t (s)."""
        t = np.asarray(t, dtype=float)
        base = np.full(t.shape, self.v0) if order == 0 else np.zeros(t.shape)
        if not len(self.ramps):
            return base
        t0, dur, dv, jt = self.ramps.T
        tau = t[..., None] - t0
        if order == 0:
            g = (jt * self._int_smoothstep(tau / jt) + jt * self._int_smoothstep(dur / jt)
                 - jt * self._int_smoothstep((dur - tau) / jt) - tau)
        elif order == 1:
            g = _smoothstep_unit(tau / jt) + _smoothstep_unit((dur - tau) / jt) - 1.0
        else:
            g = (_smoothstep_unit(tau / jt, 1) - _smoothstep_unit((dur - tau) / jt, 1)) / jt
        return base + np.sum(dv / (dur - jt) * g, axis=-1)


class Sines:
    """Sums of sinusoids, one sum per channel: Σ_k A_ck·sin(2π f_ck t + φ_ck), with derivatives."""

    def __init__(self, freq, phase, amp):
        """freq (c, k) Hz, phase (c, k) rad, amp (c, k) in the channel's unit."""
        self.freq, self.phase, self.amp = (np.asarray(a, float) for a in (freq, phase, amp))

    @classmethod
    def draw(cls, rng: np.random.Generator, peaks, band_hz, k: int = 3) -> "Sines":
        """Channels with peak |value| at most peaks (c,) (weights summing to one), k frequencies each
        drawn uniformly in band_hz (Hz), random phases."""
        peaks = np.atleast_1d(np.asarray(peaks, float))
        c = len(peaks)
        freq = rng.uniform(*band_hz, (c, k))
        phase = rng.uniform(0, 2 * np.pi, (c, k))
        w = rng.dirichlet(np.ones(k), c)
        return cls(freq, phase, peaks[:, None] * w)

    def __call__(self, t, order: int = 0) -> np.ndarray:
        """Values (..., c) at times t (...) (s); order n gives the n-th time derivative."""
        t = np.asarray(t, dtype=float)
        w = 2 * np.pi * self.freq
        arg = w * t[..., None, None] + self.phase + order * np.pi / 2  # d/dt sin = sin(· + π/2)·w
        return np.sum(self.amp * w ** order * np.sin(arg), axis=-1)


def _product(f, g, order: int):
    """The order-th derivative (order ≤ 2) of f·g, given f(order) and g(order) as functions of the order."""
    if order == 0:
        return f(0) * g(0)
    if order == 1:
        return f(1) * g(0) + f(0) * g(1)
    return f(2) * g(0) + 2 * f(1) * g(1) + f(0) * g(2)


# ------------------------------------------------------------------ the plan
class PlatformPlan:
    """A seeded platform motion (module doc) in the interface of :class:`stimuli.flight.FlightPlan`.

    speed(t) = base(t)·(1 + gait(t)): base the jerk-limited ramps (m/s), gait a fractional modulation
    (surge, wander). offsets(t) = envelope(t)·sway(t) + drift(t): (x, y) in metres, envelope the base
    speed over the platform's reference speed (motion that stops when the platform stops). angles(t) =
    envelope(t)·gait_angles(t) + free_angles(t) + (0, k·a(t), 0): (yaw, pitch, roll) in radians, the
    last the pitch that follows the forward acceleration a (rad per m/s²).
    """

    def __init__(self, kind: str, duration_s: float, seed: int, config, base: Ramps, reference_m_s: float,
                 gait: Sines | None = None, sway: Sines | None = None, drift: Sines | None = None,
                 gait_angles: Sines | None = None, free_angles: Sines | None = None,
                 pitch_per_accel: float = 0.0, info: dict | None = None, grid_hz: float = 1000.0):
        """kind: "drone", "road" or "walking"; base: the speed's ramps; reference_m_s: the speed (m/s) at
        which the enveloped motions have their drawn amplitudes; gait: 1 channel (fraction); sway, drift:
        2 channels (x, y) m; gait_angles, free_angles: 3 channels (yaw, pitch, roll) rad; pitch_per_accel:
        rad per m/s²; info: the drawn values, for scene.json."""
        self.kind = kind
        self.duration_s = float(duration_s)
        self.seed = seed
        self.config = config
        self.base = base
        self.reference_m_s = float(reference_m_s)
        self._gait, self._sway, self._drift = gait, sway, drift
        self._gait_angles, self._free_angles = gait_angles, free_angles
        self.pitch_per_accel = float(pitch_per_accel)
        self.info = dict(info or {})
        self._build_path(grid_hz)

    # ---------------------------------------------------------- speed and offsets
    def envelope(self, t, order: int = 0) -> np.ndarray:
        """The base speed over the reference speed (dimensionless), or its derivatives; shaped like t."""
        return self.base(t, order) / self.reference_m_s

    def speed(self, t, order: int = 0) -> np.ndarray:
        """Speed along the track (m/s), shaped like t (s); order 1 gives m/s², order 2 m/s³."""
        t = np.asarray(t, dtype=float)
        if self._gait is None:
            return self.base(t, order)
        return _product(lambda o: self.base(t, o), lambda o: (o == 0) + self._gait(t, o)[..., 0], order)

    def _gait_and_free(self, t, order: int, width: int, gait, free) -> np.ndarray:
        """A gait term scaled by the stride's envelope plus a free term, shape (..., width), or their derivatives;
        either term may be None (none)."""
        out = np.zeros(t.shape + (width,))
        if gait is not None:
            out = out + _product(lambda o: self.envelope(t, o)[..., None], lambda o: gait(t, o), order)
        if free is not None:
            out = out + free(t, order)
        return out

    def offsets(self, t, order: int = 0) -> np.ndarray:
        """Lateral and vertical offset (x, y) of the camera (m), shape (..., 2), or its derivatives."""
        return self._gait_and_free(np.asarray(t, dtype=float), order, 2, self._sway, self._drift)

    def angles(self, t, order: int = 0) -> np.ndarray:
        """Camera (yaw, pitch, roll) (rad), shape (..., 3); order 1 gives their rates (rad/s)."""
        t = np.asarray(t, dtype=float)
        out = self._gait_and_free(t, order, 3, self._gait_angles, self._free_angles)
        if self.pitch_per_accel:
            out[..., 1] += self.pitch_per_accel * self.speed(t, order + 1)
        return out

    # ---------------------------------------------------------- the path (FlightPlan's interface)
    def velocity_world(self, t) -> np.ndarray:
        """World (track-frame) velocity (ẋ, ẏ, s') (m/s), shape (..., 3)."""
        return np.concatenate([self.offsets(t, 1), self.speed(t)[..., None]], axis=-1)

    def acceleration_world(self, t) -> np.ndarray:
        """World acceleration (ẍ, ÿ, s'') (m/s²), shape (..., 3)."""
        return np.concatenate([self.offsets(t, 2), self.speed(t, 1)[..., None]], axis=-1)

    def _build_path(self, grid_hz: float):
        """The distance along the track: the speed integrated by 3-point Gauss–Legendre on a grid of
        1/grid_hz s from PAD_S before t = 0 to PAD_S after the run, 0 at t = 0, joined by cubic Hermite
        segments whose slopes are the exact speed."""
        h = 1.0 / grid_hz
        n0, n1 = int(np.ceil(PAD_S / h)), int(np.ceil((self.duration_s + PAD_S) / h))
        knots = np.arange(-n0, n1 + 1) * h
        gl = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
        wts = np.array([5.0, 8.0, 5.0]) / 18.0
        tq = 0.5 * (knots[:-1] + knots[1:])[:, None] + 0.5 * h * gl
        s = np.concatenate([[0.0], np.cumsum(h * self.speed(tq) @ wts)])
        s = s - s[n0]
        s[n0] = 0.0
        self._along = CubicHermiteSpline(knots, s, self.speed(knots))

    def distance(self, t) -> np.ndarray:
        """Distance travelled along the track since t = 0 (m), shaped like t (s)."""
        return self._along(np.asarray(t, dtype=float))

    def position(self, t) -> np.ndarray:
        """Camera centre in the track frame (m), shape (..., 3); (x(0), y(0), 0) at t = 0."""
        t = np.asarray(t, dtype=float)
        return np.concatenate([self.offsets(t), self.distance(t)[..., None]], axis=-1)

    def z_range(self, dt: float = 0.01) -> tuple[float, float]:
        """The smallest and largest track coordinate z (m) over [0, duration_s]."""
        z = self.distance(np.arange(0.0, self.duration_s + dt, dt))
        return float(z.min()), float(z.max())

    def rotation(self, t) -> np.ndarray:
        """Camera-to-track rotation R_y(yaw)·R_x(pitch)·R_z(roll), shape (..., 3, 3)."""
        a = self.angles(t)
        return _rotation(a[..., 0], 1) @ _rotation(a[..., 1], 0) @ _rotation(a[..., 2], 2)

    def angular_velocity(self, t) -> np.ndarray:
        """Camera-frame angular velocity ω (rad/s), the vee of Rᵀ·dR/dt, shape (..., 3)."""
        a, da = self.angles(t), self.angles(t, 1)
        rz, rxz = _rotation(a[..., 2], 2), _rotation(a[..., 1], 0) @ _rotation(a[..., 2], 2)
        return (rxz[..., 1, :] * da[..., 0, None] + rz[..., 0, :] * da[..., 1, None]
                + np.array([0.0, 0.0, 1.0]) * da[..., 2, None])

    def trajectory(self) -> "PlatformTrajectory":
        """The speed along the track as a :class:`~stimuli.trajectory.Trajectory`-like object."""
        return PlatformTrajectory(self)

    def metadata(self) -> dict:
        """The plan's kind, seed and drawn values, for a run's scene.json."""
        return dict(flight=self.kind, flight_seed=self.seed, platform=self.info)


class PlatformTrajectory(PathTrajectory):
    """:class:`stimuli.flight.PathTrajectory` of a platform: speed, its rate and the distance along z."""

    def __init__(self, plan: PlatformPlan):
        super().__init__(plan)
        self.source = f"{plan.kind} (seed={plan.seed})"


# ------------------------------------------------------------------ drawing the plans
def _u(rng, lo_hi) -> float:
    """One uniform draw in the range (lo, hi)."""
    return float(rng.uniform(*lo_hi))


def _drone(rng, duration_s, cfg: DroneConfig, seed) -> PlatformPlan:
    v0, hover, cruise, acc = (_u(rng, r) for r in (cfg.start_speed_m_s, cfg.hover_s, cfg.cruise_m_s, cfg.accel_s))
    jt = acc * _u(rng, (0.25, 0.5))
    base = Ramps(v0, [(hover, acc, cruise - v0, jt)])
    # A fraction of the speed: it grows in with the cruise (a hovering drone hardly wanders in speed).
    wander = Sines.draw(rng, [_u(rng, cfg.wander)], cfg.wander_band_hz, 2)
    drift = Sines.draw(rng, [_u(rng, cfg.drift_m), _u(rng, cfg.drift_m)], cfg.drift_band_hz)
    gimbal = Sines.draw(rng, np.radians([_u(rng, cfg.gimbal_deg) for _ in range(3)]), cfg.gimbal_band_hz)
    info = dict(start_speed_m_s=v0, hover_s=hover, cruise_m_s=cruise, accel_s=acc, jerk_s=jt)
    return PlatformPlan("drone", duration_s, seed, cfg, base, cruise, gait=wander, drift=drift, free_angles=gimbal,
                        info=info)


def _road(rng, duration_s, cfg: RoadConfig, seed) -> PlatformPlan:
    v = _u(rng, cfg.cruise_m_s)
    ramps, stops = [], []
    first = _u(rng, cfg.first_stop) * duration_s  # the first stop begins here
    stop_v = _u(rng, cfg.stop_speed_m_s)
    jt = _u(rng, cfg.jerk_s)
    # Braking hard enough that the speed is down by the first stop (never past the vehicle's limit).
    need = (v - stop_v) / max(first - jt, 1e-3)
    brake = float(np.clip(max(_u(rng, cfg.brake_m_s2), need), None, cfg.brake_max_m_s2))
    dur = (v - stop_v) / brake + jt
    t = first - dur
    v0 = v
    end = duration_s + PAD_S
    while t < end:
        dur = (v - stop_v) / brake + jt
        ramps.append((t, dur, stop_v - v, min(jt, dur / 2)))
        t += dur
        hold = _u(rng, cfg.stop_s)
        stops.append((t, t + hold))
        t += hold
        v_next, acc = _u(rng, cfg.cruise_m_s), _u(rng, cfg.accel_m_s2)
        dur = (v_next - stop_v) / acc + jt
        ramps.append((t, dur, v_next - stop_v, min(jt, dur / 2)))
        t += dur + _u(rng, cfg.cruise_s)
        v, stop_v = v_next, _u(rng, cfg.stop_speed_m_s)
        brake, jt = _u(rng, cfg.brake_m_s2), _u(rng, cfg.jerk_s)
    ref = cfg.reference_speed_m_s
    wander = Sines.draw(rng, [_u(rng, cfg.wander)], cfg.wander_band_hz, 2)
    # x: lane wander; y: the suspension's bounce; both grow with the speed (zero at a standstill).
    lane = Sines.draw(rng, [_u(rng, cfg.lane_m)], cfg.lane_band_hz)
    bounce = Sines.draw(rng, [_u(rng, cfg.bounce_m)], cfg.bounce_hz)
    sway = Sines(np.concatenate([lane.freq, bounce.freq]), np.concatenate([lane.phase, bounce.phase]),
                 np.concatenate([lane.amp, bounce.amp]))
    yaw = Sines.draw(rng, np.radians([_u(rng, cfg.lane_deg)]), cfg.lane_band_hz)
    rough = Sines.draw(rng, np.radians([_u(rng, cfg.rough_deg), _u(rng, cfg.rough_deg)]), cfg.rough_band_hz)
    gait_angles = Sines(np.concatenate([yaw.freq, rough.freq]), np.concatenate([yaw.phase, rough.phase]),
                        np.concatenate([yaw.amp, rough.amp]))
    k = np.radians(_u(rng, cfg.pitch_per_accel_deg))
    info = dict(start_speed_m_s=v0, first_stop_s=first, stops_s=[list(s) for s in stops if s[0] < duration_s],
                pitch_per_accel_deg=float(np.degrees(k)))
    return PlatformPlan("road", duration_s, seed, cfg, Ramps(v0, ramps), ref, gait=wander, sway=sway,
                        gait_angles=gait_angles, pitch_per_accel=k, info=info)


def _walking(rng, duration_s, cfg: WalkConfig, seed) -> PlatformPlan:
    v = _u(rng, cfg.speed_m_s)
    start = cfg.start if cfg.start != "either" else str(rng.choice(["rest", "motion"]))
    if start == "rest":
        t0, dur = _u(rng, cfg.stand_s), _u(rng, cfg.setoff_s)
        base = Ramps(0.0, [(t0, dur, v, dur / 2)])
    else:
        base = Ramps(v, [])
    f = _u(rng, cfg.step_hz)
    surge, bounce, sway = _u(rng, cfg.surge), _u(rng, cfg.bounce_m), _u(rng, cfg.sway_m)
    ph = rng.uniform(0, 2 * np.pi, 5)
    wander = Sines.draw(rng, [_u(rng, cfg.wander)], cfg.wander_band_hz, 2)
    # The surge at the step rate plus a slow wander of the walking speed.
    gait = Sines(np.concatenate([[[f]], wander.freq], axis=1), np.concatenate([[[ph[0]]], wander.phase], axis=1),
                 np.concatenate([[[surge]], wander.amp], axis=1))
    # Sway (x) at the stride rate, bounce (y) at the step rate.
    body = Sines(np.array([[f / 2], [f]]), ph[1:3, None], np.array([[sway], [bounce]]))
    # Gait-locked pitch at the step rate and roll at the stride rate (no yaw: that is the hand's).
    g_pitch, g_roll = np.radians(_u(rng, cfg.gait_deg)), np.radians(_u(rng, cfg.gait_deg))
    gait_angles = Sines(np.array([[f], [f], [f / 2]]), np.array([[0.0], [ph[3]], [ph[4]]]),
                        np.array([[0.0], [g_pitch], [g_roll]]))
    hand = Sines.draw(rng, np.radians([_u(rng, cfg.hand_deg) for _ in range(3)]), cfg.hand_band_hz)
    info = dict(speed_m_s=v, start=start, step_hz=f, surge=surge, bounce_m=bounce, sway_m=sway,
                gait_pitch_deg=float(np.degrees(g_pitch)), gait_roll_deg=float(np.degrees(g_roll)),
                hand_deg=np.degrees(hand.amp.sum(1)).tolist())
    return PlatformPlan("walking", duration_s, seed, cfg, base, v, gait=gait, sway=body, gait_angles=gait_angles,
                        free_angles=hand, info=info)


def platform_plan(kind: str, seed: int, duration_s: float, config=None) -> PlatformPlan:
    """Draw a ``kind`` plan ("drone", "road", "walking") over [0, duration_s] s from ``seed``; config: its
    :class:`DroneConfig`, :class:`RoadConfig` or :class:`WalkConfig` (None: the defaults). The same seed
    and configuration give the same plan."""
    if kind not in PLATFORMS:
        raise ValueError(f"unknown platform {kind!r}; choose one of {', '.join(PLATFORMS)}")
    cfg = config or CONFIGS[kind]()
    rng = np.random.default_rng([seed, 11])  # its own stream: scene layout and IMU draws do not move
    return {"drone": _drone, "road": _road, "walking": _walking}[kind](rng, duration_s, cfg, seed)
