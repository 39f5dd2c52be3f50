"""The IMU's side of the velocity pipeline, sample by sample: what :mod:`lobula.imu` computes causally on a
whole record (the still-camera gyro bias, the attitudes, the online gravity reference, the forward
acceleration, the gravity-drift bound and the attitude leak), carried as running state, so that a
:class:`lobula.velocity.VelocityEstimator` fed samples in any chunks gets the same numbers as the
whole-record functions.

Samples pass two stages. On arrival (:meth:`InertialStream.extend`): the still-camera bias and the plain
attitude, which need nothing but the gyro. Once the gyro bias that the flow's heading fit learns is
known for them (:meth:`InertialStream.finalise`): the attitude that removes gravity, and everything
downstream of it. Only the last ``keep_s`` seconds are held.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from lobula.imu import (G, GRAVITY_INIT_S, GRAVITY_WINDOW_S, GYRO_NOISE_DENSITY, HEADING_BIAS_STD_SCALE,
                            gravity_time_constant, leak_walk, resample_to, rotation_increments)


class Columns:
    """Per-sample arrays that grow at the end and drop their oldest rows, with absolute row numbers.

    ``self[name]`` is the held rows of one column ((m, ...)); ``first`` is the absolute number of the
    first held row and ``n`` one past the last.
    """

    def __init__(self, **shapes):
        self._data = {k: np.zeros((256,) + tuple(s)) for k, s in shapes.items()}
        self.first, self.n = 0, 0
        self._lo = 0  # the first held row's place in the arrays

    def __getitem__(self, name: str) -> np.ndarray:
        return self._data[name][self._lo:self._lo + self.n - self.first]

    def at(self, name: str, k: int):
        """Column ``name`` at absolute row k (held)."""
        return self._data[name][self._lo + k - self.first]

    def append(self, m: int) -> slice:
        """Room for m more rows; returns their slice in the arrays (fill them through :meth:`raw`)."""
        held = self.n - self.first
        cap = len(next(iter(self._data.values())))
        if self._lo + held + m > cap:
            new_cap = max(cap, 2 * (held + m))
            for k, a in self._data.items():
                b = np.zeros((new_cap,) + a.shape[1:])
                b[:held] = a[self._lo:self._lo + held]
                self._data[k] = b
            self._lo = 0
        sl = slice(self._lo + held, self._lo + held + m)
        self.n += m
        return sl

    def raw(self, name: str) -> np.ndarray:
        return self._data[name]

    def drop_before(self, k: int) -> None:
        """Forget rows before absolute row k."""
        k = min(max(k, self.first), self.n)
        self._lo += k - self.first
        self.first = k


def _accumulate(last, values):
    """Running sums continuing from ``last`` ((...) or None at the start), sample by sample as np.cumsum adds."""
    if last is None:
        return np.cumsum(values, 0)
    return np.cumsum(np.concatenate([np.asarray(last)[None], values]), 0)[1:]


class InertialStream:
    """The causal IMU quantities of :func:`lobula.velocity.estimate_velocity`, one chunk of samples at a time.

    Parameters
    ----------
    prior : float
        rad/s: the gyro bias's prior std (VelocityConfig.gyro_bias_prior_deg_s).
    fit_prior : float
        rad/s: the heading and bias fit's prior (its regulariser).
    fitted : bool
        The heading and bias fit runs: its estimates (:meth:`add_estimate`) are fused with the still-camera
        one for the attitude that removes gravity (lobula.imu.fused_gyro_bias); else the still-camera
        estimate alone serves.
    interval_s : float, optional
        s: the IMU's sample interval (None: the median of its first 17 samples' intervals).
    keep_s : float
        s of samples held for the per-frame queries.
    window_s, noise_density : float
        As lobula.imu.gyro_bias takes them (the still test's window, s; the gyro's noise, rad/s/√Hz).
    """

    def __init__(self, prior: float, fit_prior: float, fitted: bool, interval_s: float | None = None,
                 keep_s: float = 3.0, window_s: float = 0.5, noise_density: float = GYRO_NOISE_DENSITY):
        self.prior, self.fit_prior, self.fitted = prior, fit_prior, fitted
        self.interval_s, self.keep_s, self.window_s, self.noise_density = interval_s, keep_s, window_s, noise_density
        self.cols = Columns(t=(), gyro=(3,), accel=(3,), s1=(3,), s2=(3,), still=(), count=(), total=(3,),
                            bias_still=(3,), q_plain=(3, 3), bias=(3,), bias_std=(3,), rot=(3, 3), a_cam=(3,),
                            axis=(3,), drift=(), leak=(), w_corr=(3,), turned=(3,), f_sum=(3,), g_ref=(3,),
                            accel_sum=(3,))
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._done = 0  # samples finalised (stage two): absolute rows 0.._done − 1
        self.estimates: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.t0 = None
        self._zi = None  # the gravity reference's exponential average, once past its start

    @property
    def rate_hz(self) -> float | None:
        """Hz: the IMU's sample rate (None until known)."""
        return None if self.interval_s is None else 1.0 / self.interval_s

    # ---------------------------------------------------------------- stage one: on arrival
    @property
    def last_time(self) -> float:
        """s: the newest sample's time (−inf before any)."""
        return float(self.cols.at("t", self.cols.n - 1)) if self.cols.n else -np.inf

    def extend(self, time_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Take in samples: time_s (m,) s after the last, gyro (m, 3) rad/s, accel (m, 3) m/s² (camera frame)."""
        t = np.asarray(time_s, float).reshape(-1)
        g, a = np.asarray(gyro, float).reshape(-1, 3), np.asarray(accel, float).reshape(-1, 3)
        if not (len(t) == len(g) == len(a)):
            raise ValueError(f"IMU chunk: {len(t)} times, {len(g)} gyro and {len(a)} accelerometer rows; give one per sample")
        if not len(t):
            return
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            raise ValueError("IMU samples contain NaN or inf; drop those samples before passing them")
        if np.any(np.diff(t) <= 0) or t[0] <= self.last_time:
            raise ValueError("IMU sample times must increase strictly, each chunk after the last")
        if self.interval_s is None:
            self._pending.append((t, g, a))
            held = np.concatenate([p[0] for p in self._pending])
            if len(held) < 17:
                return
            self.interval_s = float(np.median(np.diff(held[:17])))
            chunks, self._pending = self._pending, []
            for c in chunks:
                self._arrive(*c)
            return
        self._arrive(t, g, a)

    def _arrive(self, t, g, a) -> None:
        c = self.cols
        prev = c.n - 1
        first = c.n == 0
        sl = c.append(len(t))
        c.raw("t")[sl], c.raw("gyro")[sl], c.raw("accel")[sl] = t, g, a
        if first:
            self.t0 = float(t[0])
        rate = self.rate_hz
        sigma = self.noise_density * np.sqrt(rate / 2)
        k = max(3, int(round(self.window_s * rate)))
        # The still test (lobula.imu.gyro_bias, causal): the window of k samples ending at each.
        s1 = _accumulate(None if first else c.at("s1", prev), g)
        s2 = _accumulate(None if first else c.at("s2", prev), g ** 2)
        c.raw("s1")[sl], c.raw("s2")[sl] = s1, s2
        hi = np.arange(c.n - len(t) + 1, c.n + 1)  # absolute, one past each sample
        lo = np.maximum(hi - k, 0)
        m = (hi - lo)[:, None]
        if np.any((lo > 0) & (lo - 1 < c.first)):
            raise RuntimeError("the still test's window reaches before the samples held; hold more (keep_s)")
        c_at = lambda name, idx: np.where((idx > 0)[:, None], c.raw(name)[c._lo + np.maximum(idx, 1) - 1 - c.first], 0.0)
        mean = (c_at("s1", hi) - c_at("s1", lo)) / m
        var = np.maximum((c_at("s2", hi) - c_at("s2", lo)) / m - mean ** 2, 0.0)
        still = (m[:, 0] >= k) & np.all(var <= (1.5 * sigma) ** 2, axis=1)
        count = _accumulate(None if first else c.at("count", prev), still.astype(float))
        total = _accumulate(None if first else c.at("total", prev), g * still[:, None])
        c.raw("still")[sl], c.raw("count")[sl], c.raw("total")[sl] = still, count, total
        bias = np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], 0.0)
        c.raw("bias_still")[sl] = bias
        # The plain attitude (lobula.imu.orientation_from_gyro, causal, the still-camera bias removed).
        c.raw("q_plain")[sl] = self._integrate(t, g - bias, None if first else prev, "q_plain", "bias_still")

    def _integrate(self, t, w, prev, column: str, bias_column: str) -> np.ndarray:
        """Orientations (m, 3, 3) at the new samples, continuing ``column`` from row prev (None: identity
        first) with rates w (m, 3) rad/s (the gyro less the bias in ``bias_column``)."""
        c = self.cols
        if prev is None:
            if len(t) < 2:
                return np.eye(3)[None]
            steps = Rotation.from_rotvec(rotation_increments(t, w)).as_matrix()
            r, out, start = np.eye(3), [np.eye(3)], 0
        else:
            tt = np.concatenate([[c.at("t", prev)], t])
            ww = np.concatenate([(c.at("gyro", prev) - c.at(bias_column, prev))[None], w])
            steps = Rotation.from_rotvec(rotation_increments(tt, ww)).as_matrix()
            r, out, start = c.at(column, prev), [], 0
        for i in range(start, len(steps)):  # composition is sequential; 3x3 products
            r = r @ steps[i]
            out.append(r)
        return np.array(out)

    def still_bias(self, t1: float | None, prior: float):
        """(bias (3,) rad/s, std rad/s): the still-camera estimate at the first sample at or after t1
        (None: the first sample), its prior ``prior``."""
        c = self.cols
        if t1 is None:
            k = 0
        else:
            k = c.first + int(np.searchsorted(c["t"], t1))
            k = min(k, c.n - 1)
        sigma = self.noise_density * np.sqrt(self.rate_hz / 2)
        return c.at("bias_still", k).copy(), 1.0 / np.sqrt(1.0 / prior ** 2 + c.at("count", k) / sigma ** 2)

    def plain_attitude(self, t) -> np.ndarray:
        """Orientations (k, 3, 3) at times t (k,) s from the plain attitude, slerped between samples."""
        from .fields import slerp_orientations

        return slerp_orientations(self.cols["t"], self.cols["q_plain"], t)

    # ---------------------------------------------------------------- stage two: with the fitted bias
    def add_estimate(self, t_est: float, bias: np.ndarray, std: np.ndarray) -> None:
        """The heading fit's gyro bias (3,) rad/s and std (3,) rad/s, known from t_est s on."""
        if self._done and self.cols.at("t", self._done - 1) >= t_est:
            raise ValueError(f"the frames at {t_est:.3f} s have no IMU samples about them (the IMU's first sample is "
                             f"at {self.t0:.3f} s, and those up to {self.cols.at('t', self._done - 1):.3f} s are "
                             f"used): frames before the IMU's first sample, or a gap in the IMU longer than a frame "
                             f"pair; give the frames from the IMU's first sample on, and its samples without gaps")
        self.estimates.append((float(t_est), np.asarray(bias, float).copy(),
                               np.asarray(std, float).copy() * HEADING_BIAS_STD_SCALE))

    def finalise(self, upto: float) -> None:
        """Finish every sample up to the first at or after ``upto`` s (all there are if none is)."""
        c = self.cols
        t = c["t"]
        end = c.first + min(int(np.searchsorted(t, upto, side="left")) + 1, len(t))
        if end <= self._done:
            return
        rows = np.arange(self._done, end)
        idx = rows - c.first + c._lo
        tt, g, a = c.raw("t")[idx], c.raw("gyro")[idx], c.raw("accel")[idx]
        b_still = c.raw("bias_still")[idx]
        sigma = self.noise_density * np.sqrt(self.rate_hz / 2)
        ss = np.broadcast_to((1.0 / np.sqrt(1.0 / self.prior ** 2 + c.raw("count")[idx] / sigma ** 2))[:, None],
                             (len(rows), 3))
        if self.fitted and self.estimates:
            t_est = np.array([e[0] for e in self.estimates])
            j = np.searchsorted(t_est, tt, side="right") - 1
            seen = (j >= 0)[:, None]
            eb = np.where(seen, np.array([e[1] for e in self.estimates])[np.maximum(j, 0)], 0.0)
            es = np.where(seen, np.array([e[2] for e in self.estimates])[np.maximum(j, 0)], np.inf)
            w_still, w_est = 1.0 / ss ** 2, 1.0 / es ** 2
            bias, bias_std = (b_still * w_still + eb * w_est) / (w_still + w_est), 1.0 / np.sqrt(w_still + w_est)
        else:
            bias, bias_std = b_still, np.array(ss)
        c.raw("bias")[idx], c.raw("bias_std")[idx] = bias, bias_std
        prev = self._done - 1 if self._done else None
        rot = self._integrate(tt, g - bias, prev, "rot", "bias")
        c.raw("rot")[idx] = rot
        self._gravity(rows, idx, tt, a, rot, prev)
        # The gravity-drift bound and the attitude leak (lobula.imu.gravity_drift_std, attitude_leak).
        acc_sum = _accumulate(None if prev is None else c.at("accel_sum", prev), a)
        c.raw("accel_sum")[idx] = acc_sum
        gd = acc_sum / (rows + 1)[:, None]
        gd = gd / np.maximum(np.linalg.norm(gd, axis=1, keepdims=True), 1e-9)
        if self.fitted and self.estimates:
            c.raw("drift")[idx] = G * np.sqrt(bias_std[:, 0] ** 2 * gd[:, 1] ** 2 + bias_std[:, 1] ** 2 * gd[:, 0] ** 2)
        else:
            c.raw("drift")[idx] = G * ss[:, 0]
        if prev is None:
            inc = 0.5 * (bias[1:] + bias[:-1]) * np.diff(tt)[:, None]
            turned = np.concatenate([np.zeros((1, 3)), np.cumsum(inc, 0)])
        else:
            bb = np.concatenate([c.at("bias", prev)[None], bias])
            inc = 0.5 * (bb[1:] + bb[:-1]) * np.diff(np.concatenate([[c.at("t", prev)], tt]))[:, None]
            turned = _accumulate(c.at("turned", prev), inc)
        c.raw("turned")[idx] = turned
        eps = bias * (tt - self.t0)[:, None] - turned
        c.raw("leak")[idx] = G * (eps[:, 0] * gd[:, 1] - eps[:, 1] * gd[:, 0])
        c.raw("w_corr")[idx] = g - bias
        self._done = end

    def _gravity(self, rows, idx, tt, a, rot, prev) -> None:
        """The online gravity reference (lobula.imu.online_gravity) and the forward acceleration."""
        c = self.cols
        f0 = np.einsum("nij,nj->ni", rot, a)  # specific force in the first frame
        f_sum = _accumulate(None if prev is None else c.at("f_sum", prev), f0)
        c.raw("f_sum")[idx] = f_sum
        out = f_sum / (rows + 1)[:, None]  # growing mean
        start = tt >= self.t0 + GRAVITY_INIT_S
        if start.any():
            i = int(np.argmax(start))
            alpha = min(1.0, self.interval_s / GRAVITY_WINDOW_S)
            if self._zi is None:
                before = out[i - 1] if i > 0 else c.at("g_ref", prev)
                self._zi = ((1 - alpha) * before)[None, :]
            out[i:], self._zi = lfilter([alpha], [1.0, -(1 - alpha)], f0[i:], axis=0, zi=self._zi)
        c.raw("g_ref")[idx] = out
        g_cam = np.einsum("nji,nj->ni", rot, -out)
        c.raw("a_cam")[idx] = a + g_cam
        c.raw("axis")[idx] = rot[:, :, 2]

    # ---------------------------------------------------------------- at a frame's time
    def at_frame(self, t: float, epipole: np.ndarray, frame_interval: float, span: float | None = None) -> dict:
        """What the readout takes at a frame of time t s (its heading ``epipole`` (2,) normalised):
        a (m/s²), the 3-D gravity-free acceleration accel (3,) m/s² (camera frame), axis (3,), transport λ (1/s),
        drift (m/s²/s), walk (m/s²/√s), turn |ω| (rad/s) and tau (s), as :func:`lobula.velocity.estimate_velocity`
        computes them on the whole record; a_rates (m/s²) and accel (3,) averaged over ``span`` s about t, as the
        row's rates average the motion (a flow pair's interval, whose second frame is in; None: frame_interval),
        for the vision terms (:func:`lobula.velocity.inertial.accels_at`)."""
        span = frame_interval if span is None else float(span)
        self.finalise(t + max(frame_interval, span) / 2)
        c = self.cols
        end = self._done - c.first
        ts = c["t"][:end]
        at = lambda name: c[name][:end]
        one = np.array([t])
        axis = np.array([np.interp(t, ts, at("axis")[:, j]) for j in range(3)])
        w = at("w_corr")
        e = np.nan_to_num(np.asarray(epipole, float))
        wx, wy = (resample_to(one, ts, w[:, j], frame_interval)[0] for j in (0, 1))
        from .fields import slerp_orientations

        accel = np.array([resample_to(one, ts, at("a_cam")[:, j], span)[0] for j in range(3)])
        out = dict(attitude=slerp_orientations(ts, at("rot"), one)[0],
                   a=resample_to(one, ts, at("a_cam")[:, 2], frame_interval)[0], a_rates=accel[2], accel=accel,
                   axis=axis / np.linalg.norm(axis),
                   transport=wx * e[1] - wy * e[0], drift=float(np.interp(t, ts, at("drift"))),
                   walk=float(leak_walk(one, ts, at("leak"))[0]),
                   turn=resample_to(one, ts, np.linalg.norm(c["gyro"][:end], axis=1), frame_interval)[0],
                   tau=float(gravity_time_constant(one, self.t0)[0]),
                   bias=np.array([np.interp(t, ts, at("bias")[:, j]) for j in range(3)]),
                   bias_std=np.array([np.interp(t, ts, at("bias_std")[:, j]) for j in range(3)]))
        # Hold what the next frames' queries and the still test's window still reach.
        self.cols.drop_before(min(self._done - 1, c.first + int(np.searchsorted(ts, t - self.keep_s))))
        return out
