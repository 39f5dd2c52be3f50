"""The flow pairs of a depth run on footage: which pairs, their speed, heading, rotation and flow.

:func:`ranged_pairs` reads the footage again after the velocity pass, pair by pair (the
same staggered pairs and flow settings as that pass), and gives each selected pair the
speed it is ranged with, the heading seen from its first frame, the gyro's rotation over
it and, when the pair is ranged, its measured flow; :func:`experiments.depth_stream.estimate_depth`
turns each into a depth map. Units and shapes are in the functions' docstrings.
"""
from __future__ import annotations

import math
import time as _time
from collections import OrderedDict
from dataclasses import dataclass
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.flow import FlowConfig, make_flow_fn, pixel_to_angular
from lobula.imu import orientation_from_gyro
from lobula.readers.core import Footage, FootageError
from lobula.readout import answered_velocity
from lobula.rolling_shutter import global_shutter_flow, pixel_delays

__all__ = ["Pair", "attitude_track", "pair_rotation", "metric_scale", "mean_truth_velocity", "flow_config",
           "depth_flow_fn", "stabilised_average", "frames_averaged", "footage_attitude", "ranged_pairs"]


# ----------------------------------------------------------------------------- rotation
def attitude_track(time_s: np.ndarray, gyro: np.ndarray, causal: bool):
    """t (k,) -> camera orientations (k, 3, 3) (camera → the first IMU sample's frame): the
    bias-corrected integrated gyro (:func:`lobula.imu.orientation_from_gyro`, as the
    velocity pass integrates it) slerped between samples."""
    q = orientation_from_gyro(time_s, gyro, causal)
    keep = np.concatenate([[True], np.diff(time_s) > 0])
    slerp = Slerp(time_s[keep], Rotation.from_matrix(q[keep]))
    return lambda t: slerp(np.clip(np.asarray(t, float), time_s[0], time_s[-1])).as_matrix()


def pair_rotation(omega, dt: float) -> np.ndarray:
    """R₀₁ (3, 3) for a constant angular velocity ω (rad/s, camera frame) over dt: exp([ω]×·dt)."""
    return Rotation.from_rotvec(np.asarray(omega, float).ravel() * dt).as_matrix()


# ----------------------------------------------------------------------------- the pairs
@dataclass
class Pair:
    """One flow pair of a depth run. flow: (2, H, W) measured normalised flow (1/s), None
    when the pair is not ranged; rotation: R₀₁ from the gyro (None without one); e: the
    heading seen at the first frame (normalised); v_hat / v_true (NaN when absent) and v,
    the one the run uses; v_std: v̂'s posterior std (m/s; NaN when the run has none);
    metric: v_std/|v| within the run's ``max_scale_rel_std`` (:func:`metric_scale`); a pair
    is ranged only when its speed is usable *and* metric."""

    k: int
    i0: int
    i1: int
    t0: float
    t1: float
    v_hat: float
    v_true: float
    v: float
    e: tuple
    ranged: bool
    rotation: np.ndarray | None = None
    flow: np.ndarray | None = None
    v_std: float = float("nan")
    metric: bool = True

    @property
    def dt(self) -> float:
        return self.t1 - self.t0


def metric_scale(v: float, v_std: float, max_scale_rel_std: float) -> tuple[float, bool]:
    """(scale_rel_std, metric) of a map ranged with speed v (m/s) known to v_std (m/s, 1σ).

    scale_rel_std = v_std/|v|: every pixel's depth is v times what the flow says of 1/d,
    so the whole map shares this relative std. metric: it is within ``max_scale_rel_std``
    (always when that is inf; never when v is 0 or not finite, or v_std is NaN).
    """
    rel = abs(v_std / v) if (math.isfinite(v) and v != 0.0) else float("nan")
    if math.isinf(max_scale_rel_std):
        return rel, bool(math.isfinite(v) and v != 0.0)
    return rel, bool(math.isfinite(rel) and rel <= max_scale_rel_std)


def mean_truth_velocity(truth: dict, t0: float, t1: float) -> float:
    """Mean forward (camera-axis) velocity over [t0, t1] from truth: the trapezoid integral of
    ``v_forward_m_s`` (not ``position_m``, which is along the track and differs off-axis).
    NaN outside the truth's time span."""
    tt = truth["time_s"]
    if t0 < tt[0] - 1e-6 or t1 > tt[-1] + 1e-6:
        return float("nan")
    inside = (tt > t0) & (tt < t1)
    g = np.concatenate([[t0], tt[inside], [t1]])
    v = np.interp(g, tt, truth["v_forward_m_s"])
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(g)) / (t1 - t0))


def flow_config(vel_cfg: VelocityConfig) -> FlowConfig:
    """The velocity run's flow settings (dense front ends only)."""
    if vel_cfg.front_end not in ("dis", "farneback"):
        raise ValueError(f"depth needs a dense flow front end (dis or farneback); the velocity run used "
                         f"{vel_cfg.front_end!r}")
    fc = FlowConfig(**vel_cfg.flow.to_dict())
    fc.method = vel_cfg.front_end
    return fc


def depth_flow_fn(fcfg: FlowConfig, quality: str = "fine"):
    """(frame0, frame1) -> pixel displacement (2, H, W) for the depth pass (DepthRunConfig.flow)."""
    if quality == "velocity" or fcfg.method != "dis":
        return make_flow_fn(fcfg)
    import cv2

    from lobula.flow import DIS_PRESETS

    if fcfg.threads:
        cv2.setNumThreads(fcfg.threads)
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS["medium"])
    dis.setFinestScale(0)          # patches refined on the full-resolution image

    def fn(a, b):
        u8 = lambda img: img if img.dtype == np.uint8 else np.clip(np.round(img), 0, 255).astype(np.uint8)
        return dis.calc(u8(a), u8(b), None).transpose(2, 0, 1)
    return fn


def stabilised_average(read, i: int, half: int, n_frames: int, times: np.ndarray, attitude,
                       camera: PinholeCamera) -> np.ndarray:
    """Frame i (H, W) float32 as the mean of frames i−half..i+half turned into its orientation.

    read: index -> image; attitude: t -> camera orientations (k, 3, 3) (:func:`attitude_track`).
    Frame j is warped by the homography K·Q_iᵀ·Q_j·K⁻¹ (a pure rotation, which maps its
    pixels to where frame i sees the same directions); each output pixel averages the
    frames that cover it (frames past either end of the footage are left out).
    """
    import cv2

    img = np.asarray(read(i), np.float32)
    js = [j for j in range(i - half, i + half + 1) if 0 <= j < n_frames and j != i]
    if not js:
        return img
    q = attitude(np.asarray(times, float)[[i] + js])
    total, count = img.copy(), np.ones_like(img)
    size = (img.shape[1], img.shape[0])
    for j, qj in zip(js, q[1:]):  # a loop over the 2·half neighbours; each warp is vectorised
        h = camera.rotation_homography(q[0].T @ qj)
        total += cv2.warpPerspective(np.asarray(read(j), np.float32), h, size, flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        count += cv2.warpPerspective(np.ones_like(img), h, size, flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return total / count


def frames_averaged(run, attitude) -> int:
    """The half-width of :func:`stabilised_average` a run (an :class:`experiments.depth_stream.DepthRunConfig`) uses (its average_frames)."""
    if run.average_frames is None:
        return 2 if attitude is not None else 0
    if run.average_frames > 0 and attitude is None:
        raise ValueError("averaging frames needs a gyroscope to turn them into one orientation (this footage has "
                         "none, or derotation is off): use --average-frames 0")
    return int(run.average_frames)


class _FrameReader:
    """Reads single frames by index, keeping the ``keep`` most recently used (pairs overlap)."""

    def __init__(self, footage: Footage, keep: int = 2):
        self.footage, self.keep, self.cache = footage, max(2, keep), OrderedDict()
        self.read_s = 0.0

    def __call__(self, i: int) -> np.ndarray:
        if i in self.cache:
            self.cache.move_to_end(i)
            return self.cache[i]
        t0 = _time.perf_counter()
        _, _, img = next(self.footage.frames(i, i + 1))
        self.read_s += _time.perf_counter() - t0
        self.cache[i] = img
        while len(self.cache) > self.keep:
            self.cache.popitem(last=False)
        return img


def _heading_at_first_frames(footage: Footage, velocity, vcfg: VelocityConfig, run,
                             attitude, starts: list[int], gap: int) -> np.ndarray:
    """Epipole (normalised, (len(starts), 2)) of each selected pair, seen from its first frame.

    The velocity pass reports the heading seen at each pair's middle when it had the gyro
    (its EpipoleEstimator accumulates it in the gyro-stabilised frame); rotated back into
    that frame with the same attitude and out into the camera at t0.
    """
    n = len(starts)
    if run.epipole == "principal":
        return np.zeros((n, 2))
    ex, ey = velocity.epipole_x.values.astype(float), velocity.epipole_y.values.astype(float)
    t = np.asarray(footage.times, float)
    idx = np.array(starts)
    sel = np.full(n, len(ex) - 1) if run.epipole == "final" else idx
    e = np.stack([ex[sel], ey[sel]], -1)
    if attitude is None or vcfg.epipole != "estimate":
        return e
    t_mid = 0.5 * (t[sel] + t[sel + gap])
    h_ref = np.einsum("nij,nj->ni", attitude(t_mid), np.concatenate([e, np.ones((n, 1))], -1))
    h0 = np.einsum("nji,nj->ni", attitude(t[idx]), h_ref)       # Q(t0)ᵀ·h
    with np.errstate(divide="ignore", invalid="ignore"):
        return h0[:, :2] / h0[:, 2:3]


def footage_attitude(footage: Footage, vcfg: VelocityConfig):
    """The attitude track (:func:`attitude_track`) the velocity run with ``vcfg`` used, or None
    (no gyroscope, or derotation off)."""
    imu = footage.imu
    if not (vcfg.derotate and imu is not None and imu.gyro is not None):
        return None
    return attitude_track(imu.time_s, imu.gyro, causal=vcfg.readout.filter == "causal")


def ranged_pairs(footage: Footage, velocity, run, timings: dict | None = None,
                 starts: list[int] | None = None):
    """The selected flow pairs of a depth run, in order, each with its flow when ranged.

    velocity: the velocity Dataset of this footage (its configuration fixes the flow and
    the attitude's causality); run: the :class:`experiments.depth_stream.DepthRunConfig`. starts: first-frame indices of the pairs (default every
    ``run.every``-th). Yields :class:`Pair`; ``timings`` (dict) gains read/flow seconds.
    """
    vcfg = VelocityConfig.from_json(velocity.attrs["config"])
    fcfg = flow_config(vcfg)
    cam = footage.camera
    gap = fcfg.gap
    n_pairs = len(footage) - gap
    if n_pairs < 1:
        raise FootageError(f"{footage.path}: too few frames for a flow pair ({len(footage)} frames, gap {gap})")
    t_all = np.asarray(footage.times, float)
    vt = velocity.time.values
    stamps = 0.5 * (t_all[:n_pairs] + t_all[gap:]) if vcfg.timestamps == "mid" else t_all[:n_pairs]
    if len(vt) != n_pairs or not np.allclose(vt, stamps, atol=1e-4):
        raise FootageError(f"the velocity run ({velocity.attrs.get('footage', '?')}: {len(vt)} pairs, "
                           f"{vt[0] if len(vt) else float('nan'):.3f}..{vt[-1] if len(vt) else float('nan'):.3f} s) "
                           f"does not match {footage.path} ({n_pairs} pairs of gap {gap}, {stamps[0]:.3f}.."
                           f"{stamps[-1]:.3f} s); estimate velocity on this footage, or leave --velocity-run out")
    if run.velocity == "truth" and footage.truth is None:
        raise FootageError(f"{footage.path}: velocity 'truth' needs truth.csv (or the D435i velocity.csv)")
    v_hat_all = answered_velocity(velocity) if "observable" in velocity else velocity.v_hat.values.astype(float)
    v_std_all = velocity.v_std.values.astype(float) if "v_std" in velocity else np.full(n_pairs, np.nan)
    attitude = footage_attitude(footage, vcfg)
    starts = list(range(0, n_pairs, int(run.every))) if starts is None else [int(k) for k in starts]
    if any(not 0 <= k < n_pairs for k in starts):
        raise ValueError(f"pair start frames must lie in 0..{n_pairs - 1}, got {starts}")
    heads = _heading_at_first_frames(footage, velocity, vcfg, run, attitude, starts, gap)
    flow_fn = depth_flow_fn(fcfg, run.flow)
    # A rolling shutter's rows, put back on the frames' times for the rotation as the velocity run did
    # (lobula.rolling_shutter).
    shutter = None
    if attitude is not None and getattr(cam, "rolling_shutter_s", 0.0) > 0:
        gx, gy = cam.normalised_grid(np.float64)
        shutter = gx, gy, pixel_delays(gy, cam, cam.rolling_shutter_s, getattr(footage, "lens_maps", None))
    half = frames_averaged(run, attitude)
    read = _FrameReader(footage, keep=gap + 2 + 2 * half)
    image = (lambda i: read(i)) if half == 0 else (
        lambda i: stabilised_average(read, i, half, len(footage), t_all, attitude, cam))
    timings = timings if timings is not None else {}
    timings.setdefault("read", 0.0)
    timings.setdefault("flow", 0.0)
    for k, e in zip(starts, heads):
        i0, i1 = k, k + gap
        t0, t1 = float(t_all[i0]), float(t_all[i1])
        v_hat = float(v_hat_all[k])
        v_true = mean_truth_velocity(footage.truth, t0, t1) if footage.truth is not None else float("nan")
        v = v_true if run.velocity == "truth" else v_hat
        e = (float(e[0]), float(e[1]))
        usable = bool(math.isfinite(v) and abs(v) >= run.min_speed_m_s and all(map(math.isfinite, e)))
        v_std = 0.0 if run.velocity == "truth" else float(v_std_all[k])
        _, metric = metric_scale(v, v_std, run.max_scale_rel_std)
        # A map whose scale the speed cannot fix is unobservable, like a pair without a speed.
        ranged = usable and metric
        pair = Pair(k, i0, i1, t0, t1, v_hat, v_true, v, e, ranged, v_std=v_std, metric=metric)
        if ranged:
            r0, tf = read.read_s, _time.perf_counter()
            a, b = image(i0), image(i1)
            pair.flow = pixel_to_angular(flow_fn(a, b), cam, t1 - t0)
            if shutter is not None:
                pair.flow = global_shutter_flow(shutter[0], shutter[1], pair.flow, t0, t1, shutter[2], attitude)
            reading = read.read_s - r0
            timings["read"] += reading
            timings["flow"] += _time.perf_counter() - tf - reading   # the frame average included
            if attitude is not None:
                q0, q1 = attitude(np.array([t0, t1]))
                pair.rotation = q0.T @ q1
        yield pair
