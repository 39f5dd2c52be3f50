"""Forward velocity frame by frame: :class:`VelocityEstimator`, the causal pipeline of
:func:`lobula.velocity.estimate_velocity` fed one camera frame and a chunk of IMU samples at a time.

Each frame's flow pair is taken once the IMU's samples reach its second frame (the gyro derotates the
pair), then pooled, and the readout's filter steps once. Its estimates equal the whole-record causal
run's (``VelocityConfig.readout.filter`` "causal") to rounding: every stage is causal, the readout's
inputs are computed on a trailing stretch of ``history_s`` seconds that holds everything they reach
back to, and the IMU's running quantities are carried sample by sample
(:class:`lobula.velocity.inertial_stream.InertialStream`). Memory stays bounded by ``history_s``
(the gyro's attitude for the heading fit keeps its samples: 128 bytes each).
"""
from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lobula.config import VelocityConfig
from lobula.flow import StaggeredFlow
from lobula.front_ends import get_front_end
from lobula.imu import HEADING_FIT_BIAS_PRIOR
from lobula.readers.core import IMU, IMU_RATE_RANGE_HZ, gravity_problem, rate_problem, to_grey
from lobula.readout import MaterialRates, acceleration_heading, gate_by_lock, kalman_inputs, vision_trusted
from lobula.readout.carry import carried_std, vision_answers
from lobula.readout.config import std_allowed
from lobula.readout.coupling import LockState
from lobula.readout.kalman import ForwardPass, filter_record
from lobula.receptive_field import tile_fields

from .fields import FieldPooling
from .inertial import responding, start_accel_prior
from .inertial_stream import Columns, InertialStream

#: the rows' columns of the material fields' (r̄, r²̄, ṙ̄, moment), MaterialRates's fields in order
MATERIAL_COLUMNS = ("m_r", "m_r2", "m_rdot", "m_moment")


@dataclass
class VelocityState:
    """The estimate after one flow pair.

    Attributes
    ----------
    t : float
        s: the estimate's time (the pair's middle, as the whole-record run stamps it).
    known_at : float
        s: the newest frame it uses (the pair's second frame).
    v : float
        m/s: forward velocity along the optical axis: where observable the filter's posterior, after that carried
        by the accelerometer (lobula.readout.carry); NaN before vision has first fixed the speed.
    v_std : float
        m/s: its std (1σ), NaN where v is.
    observable : bool
        v_std within lobula.readout.config.std_allowed, and vision has fixed the speed (lobula.readout.coupling).
    heading : ndarray, (2,)
        The epipole (v_x/v_z, v_y/v_z), normalised image coordinates.
    velocity : ndarray, (3,)
        m/s: v·(e_x, e_y, 1) in the camera frame (x right, y down, z forward); NaN where v is.
    accel : float
        m/s²: the forward acceleration the readout took (gravity removed).
    gyro_bias : ndarray, (3,)
        rad/s: the gyro bias the attitude that removes gravity used (camera frame).
    attitude : ndarray, (4,)
        The camera's orientation as a quaternion (x, y, z, w), camera to the first IMU sample's frame.
    reason : str
        Why v is not observable ("" where it is).
    """

    t: float
    known_at: float
    v: float
    v_std: float
    observable: bool
    heading: np.ndarray
    velocity: np.ndarray
    accel: float
    gyro_bias: np.ndarray
    attitude: np.ndarray
    reason: str = ""


#: IMU samples the estimator checks the units of (time_s in s, the accelerometer in m/s² with gravity) before it
#: uses any: the ones InertialStream reads the rate from
IMU_HEAD = 18
#: where a message says the IMU samples came from
IMU_SOURCE = "update()'s imu"

#: what a caller missing IMU samples is told to give
GIVE_IMU = ("give update() the IMU samples since the last frame, imu=(time_s, gyro, accel): the estimator needs "
            "the accelerometer and the gyro")


class VelocityEstimator:
    """Forward velocity from a camera and its IMU, one frame at a time (causal).

    Parameters
    ----------
    camera : lobula.camera.PinholeCamera
        The camera's intrinsics (the reader's ``footage.camera``).
    config : VelocityConfig, optional
        None: ``VelocityConfig()`` with the causal filter. The filter must be "causal" with the kalman
        readout and no fixed lag; the front end a dense flow ("dis" or "farneback"); the IMU's own
        accelerometer (not ``accel_from_truth``), with derotation by the gyro. Others fail here.
    history_s : float
        s of frames the readout's inputs are computed on (at least 8: the rest test's 5 s vibration
        window and its 1 s bend, the low-pass, a reversal's 2 s: its gap and each sign's hold).
    frame_interval_s : float, optional
        s: the camera's frame interval (None: the first flow pair's, over its gap).
    imu_interval_s : float, optional
        s: the IMU's sample interval (None: the median of its first 17 intervals).

    Examples
    --------
    >>> est = VelocityEstimator(footage.camera, VelocityConfig(readout=ReadoutConfig(filter="causal")))
    >>> for i, t, image in footage.frames():
    ...     state = est.update(image, t, imu_between(t_prev, t))   # (time_s, gyro, accel)
    """

    def __init__(self, camera, config: VelocityConfig | None = None, history_s: float = 10.0,
                 frame_interval_s: float | None = None, imu_interval_s: float | None = None):
        if config is None:
            config = VelocityConfig()
            config.readout.filter = "causal"
        if not hasattr(camera, "normalised_grid"):
            raise TypeError(f"VelocityEstimator takes the camera (a lobula.camera.PinholeCamera, footage.camera), "
                            f"got {type(camera).__name__}")
        if not isinstance(config, VelocityConfig):
            raise TypeError(f"VelocityEstimator's config must be a VelocityConfig (VelocityConfig.from_dict reads a "
                            f"dict), got {type(config).__name__}")
        config = copy.deepcopy(config).validate()
        _check_streamable(config)
        history_s = _seconds("history_s", history_s)
        if history_s < 8.0:
            raise ValueError(f"history_s must be at least 8 s (the readout reaches that far back), got {history_s}")
        frame_interval_s = _seconds("frame_interval_s", frame_interval_s)
        imu_interval_s = _seconds("imu_interval_s", imu_interval_s)
        if imu_interval_s is not None:
            _check_imu_rate(camera, imu_interval_s, f"imu_interval_s {imu_interval_s:g} s")
        self.camera, self.config, self.history_s = camera, config, float(history_s)
        config.flow.method = config.front_end
        self.fields = tile_fields(camera, config.fields)
        self.fit_prior = min(HEADING_FIT_BIAS_PRIOR, np.radians(config.gyro_bias_prior_deg_s))
        self.imu = InertialStream(np.radians(config.gyro_bias_prior_deg_s), self.fit_prior,
                                  fitted=config.epipole == "estimate", interval_s=imu_interval_s)
        self.flow = StaggeredFlow(camera, config.flow, rotation=self._turn)
        self.pooling: FieldPooling | None = None
        self._gyro_seen: list = []  # gyro samples before the heading fit's attitude is made
        self._frames: list = []
        self._index = 0
        self._blank = 0  # blank frames left out (_leave_out_blank)
        self._t_last = -np.inf
        F = self.fields.n_fields
        self.rows = Columns(t=(), known=(), r=(F,), r2=(F,), m_r=(F,), m_r2=(F,), m_rdot=(F,), m_moment=(F, 2), a=(),
                            a_rates=(), accel=(3,), axis=(3,),
                            lam=(), drift=(), walk=(), turn=(), tau=(), epipole=(2,), bias=(3,), attitude=(4,))
        self.dt: float | None = frame_interval_s
        self.gravity_error: float | None = None
        self._todo: list[int] = []
        self._filter: ForwardPass | None = None
        self._lock = LockState(locked=self.config.readout.coupling_z <= 0)  # lobula.readout.coupling
        self._rest_depth = np.nan  # m: the scene depth learned so far (lobula.readout.scene_depth)
        self._t_answered = -np.inf  # s: the last frame vision fixed the speed at (lobula.readout.carry)
        self._out: list[VelocityState] = []
        self._head: list | None = []  # the first IMU chunks, until IMU_HEAD samples are checked
        self._finished = False

    # ---------------------------------------------------------------- input
    def update(self, frame=None, t: float | None = None, imu=None) -> VelocityState | None:
        """Take in a frame and the IMU samples that came with it; returns the newest estimate (None before any).

        Parameters
        ----------
        frame : ndarray, (H, W) or (H, W, 3), optional
            The image, as the footage's reader gives it.
        t : float, optional
            s: its time, on the IMU's clock.
        imu : tuple of ndarray, optional
            (time_s (m,) s, gyro (m, 3) rad/s, accel (m, 3) m/s²), in the camera frame, after the last chunk.

        Returns
        -------
        VelocityState or None
            The estimate of the newest pair the IMU has reached; all of them: :meth:`drain`.

        Raises
        ------
        ValueError, TypeError
            Input the estimator cannot read, naming what is wrong: a frame of another size, with NaN pixels, not
            in grey levels 0..255; a time that is not a number or does not increase; IMU samples not
            (m,) s, (m, 3) rad/s, (m, 3) m/s² or not after the last; first samples whose rate or gravity says
            they are not in s and m/s²; any update after :meth:`finish`.
        """
        if self._finished:
            raise ValueError("update() after finish(): the stream has ended; make a new VelocityEstimator for "
                             "another stream")
        if imu is not None:
            t_imu, gyro, accel = self._imu_chunk(imu)
            self.imu.extend(t_imu, gyro, accel)
            self._check_head(t_imu, gyro, accel)
            self._gyro(t_imu, gyro)
        if frame is not None:
            t = _frame_time(t)
            if t <= self._t_last:
                raise ValueError(f"frame times must be finite and increase; got {t} after {self._t_last}")
            frame, blank = self._grey(frame)
            if blank:
                self._leave_out_blank(frame, t)
            else:
                self._t_last = float(t)
                self._frames.append((self._index, float(t), frame))
                self._index += 1
        self._advance(final=False)
        self._check_imu_keeps_up()
        return self._out[-1] if self._out else None

    def _imu_chunk(self, imu) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``imu`` as (time_s (m,), gyro (m, 3), accel (m, 3)) float arrays; TypeError or ValueError saying what
        differs (InertialStream.extend checks their values and order)."""
        if not (isinstance(imu, (tuple, list)) and len(imu) == 3):
            raise TypeError(f"imu must be a tuple (time_s, gyro, accel) of arrays, got {type(imu).__name__}"
                            + (f" of {len(imu)}" if isinstance(imu, (tuple, list)) else ""))
        try:
            t, g, a = (np.asarray(x, float) for x in imu)
        except (TypeError, ValueError):
            raise TypeError(f"imu: time_s, gyro and accel must be numeric arrays, got "
                            f"{', '.join(type(x).__name__ for x in imu)}") from None
        t = t.reshape(-1)
        for name, x, unit in (("gyro", g, "rad/s"), ("accel", a, "m/s²")):
            if x.shape != (len(t), 3) and not (x.shape == (3,) and len(t) == 1):
                raise ValueError(f"imu: {name} has shape {x.shape}, for {len(t)} times; give one row of 3 axes "
                                 f"(x, y, z {unit}) per sample, shape ({len(t)}, 3)")
        return t, g.reshape(-1, 3), a.reshape(-1, 3)

    def _check_head(self, t, g, a) -> None:
        """Gather the first :data:`IMU_HEAD` samples (finite, increasing: InertialStream.extend took them), then
        check their units (:meth:`_check_imu_units`)."""
        if self._head is None or not len(t):
            return
        self._head.append((t, g, a))
        if sum(len(c[0]) for c in self._head) >= IMU_HEAD:
            head, self._head = self._head, None
            self._check_imu_units(*(np.concatenate(c) for c in zip(*head)))

    def _check_imu_units(self, t, g, a) -> None:
        """ValueError where the first IMU samples cannot be in s and m/s² with gravity: a rate no IMU has or one
        slower than the frames (time_s in ms or ns), an accelerometer that reads no gravity (readings in g, all
        zeros, gravity already removed), as :func:`lobula.readers.core.check_imu_csv` refuses an imu.csv."""
        samples = IMU(t, a, g, source=IMU_SOURCE)
        problem = gravity_problem(samples) or rate_problem(samples)
        if problem:
            raise ValueError(problem.replace("accel_x..z", "accel").replace("write time_s", "give time_s"))
        _check_imu_rate(self.camera, float(np.median(np.diff(t))), f"{IMU_SOURCE}'s samples")

    def _check_imu_keeps_up(self) -> None:
        """ValueError once the frames waiting for the IMU span more than ``history_s``: without its samples
        no estimate can be made, and the frames would pile up in memory."""
        if not self._frames or self._frames[-1][1] - self._frames[0][1] <= self.history_s:
            return
        if self.imu.rate_hz is None:
            raise ValueError(f"no IMU samples (fewer than the 18 its rate is read from) have come with "
                             f"{len(self._frames)} frames over {self.history_s:g} s: {GIVE_IMU}")
        raise ValueError(f"the IMU's last sample is at {self.imu.last_time:.3f} s, {len(self._frames)} frames "
                         f"(up to {self._frames[-1][1]:.3f} s) wait for it: {GIVE_IMU}, on the frames' clock")

    def _grey(self, frame) -> tuple[np.ndarray, bool]:
        """``frame`` as the flow reads it: grey (a colour or 16-bit image turned as the readers turn theirs,
        :func:`lobula.readers.core.to_grey`), of the camera's size, finite, in grey levels 0..255; else ValueError
        naming the frame. With it, whether it is blank (every pixel alike)."""
        img = np.asarray(frame)
        size = (self.camera.height, self.camera.width)
        if img.dtype.kind not in "uif":
            raise TypeError(f"frame {self._index}: pixels of type {img.dtype}; give grey levels 0..255 as an "
                            f"integer or float array (uint8, uint16 or float)")
        if img.ndim == 3 and img.shape[2] not in (1, 3, 4):
            raise ValueError(f"frame {self._index}: shape {img.shape}, but the camera is {size[1]}x{size[0]} (H, W "
                             f"{size}); give grey (H, W), BGR (H, W, 3) or BGRA (H, W, 4) images, channels last")
        if img.ndim == 3 or img.dtype == np.uint16:
            img = to_grey(img)
        if img.shape != size:
            raise ValueError(f"frame {self._index}: shape {img.shape}, but the camera is {size[1]}x{size[0]} (H, W "
                             f"{size}); give grey or BGR images of the camera's size")
        if img.dtype.kind == "f" and not np.isfinite(img).all():
            raise ValueError(f"frame {self._index}: NaN or infinite pixels")
        lo, hi = float(img.min()), float(img.max())
        if lo < 0 or hi > 255:
            raise ValueError(f"frame {self._index}: pixels from {lo:g} to {hi:g}, outside the grey levels 0..255 the "
                             f"flow reads; scale the image to 0..255 (a uint16 array is scaled by 1/257)")
        if img.dtype.kind == "f" and hi <= 1.0 and np.any(img != np.round(img)):
            raise ValueError(f"frame {self._index}: pixels from {lo:g} to {hi:g}, an image scaled to 0..1; the flow "
                             f"reads grey levels 0..255: multiply it by 255")
        return img, lo == hi

    def _leave_out_blank(self, frame: np.ndarray, t: float) -> None:
        """A blank frame (every pixel alike: a covered lens, a camera's first dark frames, one that failed to
        decode) has no motion to read, and read as a frame it would say the camera stopped: it is left out as a
        dropped frame, which the stream bridges; the first one is warned of."""
        self._blank += 1
        if self._blank == 1:
            warnings.warn(f"frame at t = {t:g} s: every pixel is {float(frame.flat[0]):g}, a blank image; it and any "
                          f"further blank frames are left out as dropped frames", RuntimeWarning, stacklevel=3)

    def finish(self) -> list[VelocityState]:
        """Process the frames the IMU has not reached (as the whole-record run does at the record's end);
        returns the estimates not yet drained."""
        if self._finished:
            return self.drain()
        if self._frames and self.imu.rate_hz is None:
            raise ValueError(f"{len(self._frames)} frames but no IMU to estimate from: {GIVE_IMU}")
        self._finished = True
        self._advance(final=True)
        if self._todo:  # no frame's fields ever responded: the start's prior stays the resting one
            self.gravity_error = start_accel_prior(np.full((1, 1), np.nan))
            self._run_readout()
        return self.drain()

    def drain(self) -> list[VelocityState]:
        """Every estimate made since the last drain, in time order."""
        out, self._out = self._out, []
        return out

    # ---------------------------------------------------------------- stages
    def _gyro(self, t, g) -> None:
        if self.pooling is None:
            self._gyro_seen.append((t, g))
        else:
            self.pooling.extend_gyro(t, g)

    def _turn(self, t0: float, t1: float) -> np.ndarray:
        q = self.imu.plain_attitude(np.array([t0, t1]))
        return q[0].T @ q[1]

    def _advance(self, final: bool) -> None:
        while self._frames and self.imu.rate_hz is not None and (final or self.imu.last_time >= self._frames[0][1]):
            sample = self.flow.push(self._frames.pop(0))
            if sample is not None:
                self._pair(sample)

    def _make_pooling(self) -> None:
        t = np.concatenate([s[0] for s in self._gyro_seen])
        g = np.concatenate([s[1] for s in self._gyro_seen])
        self._gyro_seen = []
        self.pooling = FieldPooling(self.camera, self.config, self.fields, True, self.imu.plain_attitude, t, g,
                                    lambda t1: self.imu.still_bias(t1, self.fit_prior))

    def _pair(self, s) -> None:
        if self.pooling is None:
            self._make_pooling()
        if self.dt is None:
            self.dt = (s.t1 - s.t0) / self.config.flow.gap
        p = self.pooling.push(s)
        if p.heading_bias is not None:
            self.imu.add_estimate(*p.heading_bias)
        q = self.imu.at_frame(p.t, p.epipole, self.dt, p.span)
        rows = self.rows
        k = rows.n
        sl = rows.append(1)
        for name, val in (("t", p.t), ("known", p.known), ("r", p.r), ("r2", p.r2), ("a", q["a"]),
                          ("a_rates", q["a_rates"]), ("accel", q["accel"]), ("axis", q["axis"]),
                          ("lam", q["transport"]), ("drift", q["drift"]), ("walk", q["walk"]),
                          ("turn", q["turn"]), ("tau", q["tau"]), ("epipole", p.epipole), ("bias", q["bias"]),
                          ("attitude", Rotation.from_matrix(q["attitude"]).as_quat())):
            rows.raw(name)[sl] = val
        for name in MATERIAL_COLUMNS:
            rows.raw(name)[sl] = np.nan
        h = self.pooling.stagger // 2
        if p.material is not None and k - h >= rows.first:
            for name, val in zip(MATERIAL_COLUMNS, p.material):
                rows.raw(name)[rows._lo + k - h - rows.first] = val
        if self.gravity_error is None and responding(p.r[None])[0]:
            self.gravity_error = start_accel_prior(p.r[None])
        self._todo.append(k)
        if self.gravity_error is not None:
            self._run_readout()

    def _run_readout(self) -> None:
        for k in self._todo:
            self._out.append(self._readout(k))
        self._todo = []
        keep = int(np.ceil(self.history_s / self.dt)) + 2
        self.rows.drop_before(self.rows.n - keep)

    def _readout(self, k: int) -> VelocityState:
        """One step of the readout's filter at row k, on the rows of the last history_s before it."""
        rows, cfg = self.rows, self.config.readout
        lo = max(rows.first, k - int(np.ceil(self.history_s / self.dt)))
        w = slice(rows._lo + lo - rows.first, rows._lo + k + 1 - rows.first)
        col = lambda name: rows.raw(name)[w]
        t, a, axis = col("t"), col("a"), col("axis")
        material = (MaterialRates(*(col(name) for name in MATERIAL_COLUMNS)) if self.pooling.material is not None
                    else None)
        kappa = None
        if material is not None and self.config.heading_motion:
            # As estimate_velocity takes it (lobula.velocity.inertial.kappa_accel_at), on these rows.
            turn_to = Rotation.from_quat(col("attitude")).as_matrix()
            accel = col("accel")
            kappa = accel, acceleration_heading(accel, self.dt, cfg.coupling_window_s, True, turn_to), turn_to
        inp = kalman_inputs(t, col("r"), col("r2"), a, cfg, material, axis, self.gravity_error, dt=self.dt,
                            rest_depth_seen=self._rest_depth, gate=False, kappa_accel=kappa, a_rates=col("a_rates"))
        rec = filter_record(t, a, axis, col("lam"), col("tau"), col("drift"), col("turn"), col("walk"))
        if self._filter is None:
            self._filter = ForwardPass(cfg, 3, col("drift"), self.gravity_error, False, inp.corr_frames)
        i = k - lo
        self._rest_depth = float(np.fmax(self._rest_depth, inp.scene_depth[i]))
        c = inp.coupling
        refuted = bool(c.refuted[i])
        locked = self._lock.step(bool(c.coupled[i]), bool(inp.still[i]), bool(inp.passed_zero[i]), bool(c.full[i]),
                                 refuted)
        # The filter reads row i only: gated by the lock as it stands there (lobula.readout.gate_by_lock).
        trusted = np.zeros(len(t), bool)
        trusted[i] = vision_trusted(locked, c.provisional[i], c.full[i])
        kappa, reversal = gate_by_lock(inp.ratio[0], inp.reversal, trusted)
        x, P = self._filter.step(i, rec, inp.delay, inp.measurements, (kappa,) + tuple(inp.ratio[1:]),
                                 inp.rest_accel, reversal, inp.sign, inp.stop)[3:]
        v = float(x[0])
        v_std = float(np.hypot(np.sqrt(max(P[0, 0], 0.0)), cfg.accel_scale_error * abs(v)))
        fixed, allowed = locked or bool(c.provisional[i]), float(std_allowed(v, cfg))
        # As lobula.readout.finish_readout: σ carried from the last frame where vision spoke and fixed the speed.
        if vision_answers(v_std, allowed, fixed, np.isfinite(kappa[i]) | inp.still[i] | inp.passed_zero[i]):
            self._t_answered = float(t[i])
        s_out = float(carried_std(v_std, t[i] - self._t_answered, inp.offset_prior))
        v_out = v if np.isfinite(s_out) else np.nan
        obs = fixed and s_out <= allowed
        e = col("epipole")[i]
        if refuted:
            reason = (f"the image's expansion has not followed the accelerometer (coupling z {c.z[i]:.1f} < "
                      f"{cfg.coupling_refute_z:g} over {cfg.coupling_window_s:g} s while the acceleration varied by "
                      f"{c.accel_std[i]:.2f} m/s²): vision cannot fix the speed")
        elif not (locked or c.provisional[i]):
            reason = (f"vision has not yet fixed the speed: the image's expansion has not followed the accelerometer "
                      f"(coupling z {c.z[i]:.1f}, {cfg.coupling_z:g} needed)")
        else:
            reason = "" if obs else (f"std {s_out:.3f} m/s above the readout's max_std "
                                     f"{allowed:.3g} m/s: the expansion and the acceleration have "
                                     f"not fixed the speed, or the accelerometer has carried it too long")
        return VelocityState(float(t[i]), float(col("known")[i]), v_out, s_out, bool(obs), e.copy(),
                             v_out * np.array([e[0], e[1], 1.0]), float(a[i]),
                             col("bias")[i].copy(), col("attitude")[i].copy(), reason)


def _number(value, what: str) -> float:
    """``value`` as a float; TypeError starting with ``what`` unless it is one real number."""
    if isinstance(value, (bool, str, bytes)) or np.ndim(value) != 0:
        raise TypeError(f"{what}; got {type(value).__name__} {value!r}"[:200])
    try:
        return float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{what}; got {type(value).__name__}") from None


def _seconds(name: str, value) -> float | None:
    """``value`` (s, or None) as a float; TypeError unless a number, ValueError unless finite and > 0."""
    if value is None:
        return None
    value = _number(value, f"{name} must be a number of seconds")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number of seconds > 0, got {value}")
    return value


def _frame_time(t) -> float:
    """A frame's time ``t`` as a float (s); TypeError unless one number, ValueError unless finite."""
    what = "each frame needs its time t, one number of seconds on the IMU's clock"
    if t is None:
        raise ValueError(f"{what}; got None")
    t = _number(t, what)
    if not np.isfinite(t):
        raise ValueError(f"frame times must be finite and increase; got {t}")
    return t


def _check_imu_rate(camera, interval_s: float, what: str) -> None:
    """ValueError unless an IMU sample interval of ``interval_s`` s is an IMU's (a rate in IMU_RATE_RANGE_HZ) and
    shorter than the camera's frame interval: the gyro derotates each frame pair from the samples between."""
    low, high = IMU_RATE_RANGE_HZ
    rate = 1.0 / interval_s
    if not low <= rate <= high:
        raise ValueError(f"{what}: a sample interval of {interval_s:.6g} s is a rate of {rate:.3g} Hz, where an IMU "
                         f"samples at {low:g} Hz to {high / 1e3:g} kHz; give time_s in seconds")
    frame_s = 1.0 / camera.frame_rate_hz
    if interval_s >= frame_s:
        raise ValueError(f"{what}: the IMU samples every {interval_s:.4g} s ({rate:.3g} Hz), no faster than the "
                         f"camera's {camera.frame_rate_hz:g} frames/s; the gyro must sample between the frames (time_s "
                         f"in seconds, and camera.frame_rate_hz the camera's)")


def _check_streamable(config: VelocityConfig) -> None:
    """Raise ValueError, saying what to change, for a configuration the frame-by-frame estimator does not run."""
    front = get_front_end(config.front_end)
    ro = config.readout
    problems = []
    if ro.filter != "causal":
        problems.append(f"readout.filter is {ro.filter!r}; frame by frame the filter is causal (set it to 'causal', "
                        f"or run estimate_velocity on the whole record for the zero-phase one)")
    if ro.method != "kalman" or ro.fusion != "kalman":
        problems.append("the readout must be the kalman filter (method and fusion 'kalman')")
    if ro.lag_s:
        problems.append(f"readout.lag_s is {ro.lag_s:g} s; the fixed-lag smoother runs on whole records only (set 0)")
    if not front.live or front.yields != "flow":
        problems.append(f"the front end {config.front_end!r} does not give each pair's flow as frames come; use 'dis' "
                        f"or 'farneback'")
    if config.accel_from_truth:
        problems.append("accel_from_truth needs the whole record's truth; give the IMU's samples")
    if not config.derotate:
        problems.append("derotate is off; frame by frame the gyro derotates the flow (set derotate True)")
    if config.gyro_bias_from_vision:
        problems.append("gyro_bias_from_vision fits the whole record's residuals; leave it off")
    if problems:
        raise ValueError("VelocityEstimator: " + "; ".join(problems))
