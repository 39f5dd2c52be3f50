"""Eye footage: a world ray-cast onto the compound eye's ommatidia, written and read as a folder.

Layout of an eye-footage folder (``lobula scene OUT --eye fly``)::

    ommatidia.csv   index,eye,azimuth_deg,elevation_deg,x,y,z,drho_deg
                    one row per ommatidium; eye "right"/"left"; azimuth from +z toward +x,
                    elevation positive downward; (x, y, z) the unit axis in the camera
                    optical frame (x right, y down, z forward); Δρ the acceptance FWHM.
    luminance.npy   float32 (time, ommatidium): acceptance-weighted luminance (0..1,
                    noise-free unless the scene adds noise) at the eye's rate.
    times.csv       sample,time_s
    range.npy       float32 (time/range_every, ommatidium): distance (m) along each
                    ommatidial axis every ``range_every`` samples (inf: nothing hit).
    imu.csv         time_s,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z (camera frame, as
                    in a footage folder).
    truth.csv       time_s,v_forward_m_s,a_forward_m_s2,position_m at the eye's samples.
    head.csv        time_s,theta_x,theta_y,theta_z: only with gaze stabilisation (``--gaze haltere``): the
                    head's rotation vector (rad) relative to the body (camera) frame at every sample,
                    d_body = R(θ)·d_head (:mod:`lobula.gaze`); the ommatidial axes above are fixed in the
                    head, imu.csv and truth.csv stay the body's.
    eye.json        {"kind": "compound-eye", "rate_hz", "n_samples", "eye": CompoundEyeConfig, "cast_every",
                     "cast_rate_hz" (the world was ray-cast at that rate and interpolated),
                     "range_every", "rays_per_ommatidium", "gaze": GazeConfig or null}.
    scene.json      the full configuration (scene, trajectory, IMU, eye) and provenance.

Rendering: each ommatidium's luminance is the weighted sum of the scene's luminance
along its acceptance rays (:meth:`lobula.compound_eye.CompoundEye.rays`), cast through
the scene ray API ``scene.luminance(directions (..., 3), t)`` and
``scene.cast_rays(directions, t) -> (range, surface, tex_a, tex_b)`` (COMMON.md
contract 2) at every sample time. The luminance array is streamed into a
``.npy`` file in chunks (memory bounded by the chunk) and the folder appears only when
complete (written under a temporary name, then renamed).
"""
from __future__ import annotations

import csv
import json
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from lobula.compound_eye import CompoundEye, CompoundEyeConfig
from lobula.gaze import GazeConfig, head_angles, head_rotation
from lobula.readers.core import (IMU, FootageError, check_imu_csv, check_times as _check_times, read_imu_csv,
                                 read_csv_columns as _read_csv)

from .footage_writer import atomic_folder

__all__ = ["EyeFootage", "render_eye", "write_eye_footage", "open_eye_footage", "is_eye_footage"]

OMMATIDIA_COLUMNS = ("index", "eye", "azimuth_deg", "elevation_deg", "x", "y", "z", "drho_deg")
HEAD_COLUMNS = ("time_s", "theta_x", "theta_y", "theta_z")


def render_eye(scene, eye: CompoundEye, times: np.ndarray, chunk: int = 250,
               head: np.ndarray | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (times (k,), luminance (k, n) float32) chunks of the eye's view of ``scene``.

    One ``scene.luminance`` call per sample time over all n × m acceptance rays; the
    rays are fixed in the eye (camera) frame, the scene moves the eye through the world.
    head: (len(times), 3, 3) head-to-body rotations (:mod:`lobula.gaze`), or None: the rays are
    fixed in the head, which turns on the body (camera) frame by R_k at sample k.
    """
    import inspect

    rays = eye.rays()                                           # (n, m, 3)
    w = eye.ray_weights.astype(np.float64)
    # Scenes with a texture mip-map blur each lookup to the ray's footprint (the quadrature's
    # spacing), so texture finer than the rays cannot alias into the ommatidium's signal.
    kw = ({"footprint_rad": eye.ray_spacing}
          if "footprint_rad" in inspect.signature(scene.luminance).parameters else {})
    times = np.asarray(times, dtype=float)
    for s in range(0, len(times), chunk):
        ts = times[s:s + chunk]
        out = np.empty((len(ts), eye.n), dtype=np.float32)
        for i, t in enumerate(ts):  # the scene API takes one time; rays are vectorised
            r = rays if head is None else rays @ head[s + i].T
            out[i] = np.asarray(scene.luminance(r, float(t), **kw), dtype=np.float64) @ w
        yield ts, out


def render_eye_interpolated(scene, eye: CompoundEye, times: np.ndarray, every: int = 1,
                            chunk: int = 250, head: np.ndarray | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """As :func:`render_eye`, ray-casting only every ``every``-th sample (and the last) and filling
    the samples between by linear interpolation in time.

    Why this is allowed: the photoreceptor that reads these samples low-passes with τ = 10 ms
    (corner 16 Hz); linear interpolation between casts Δ = every/rate apart passes a frequency
    f with gain sinc²(fΔ) (at every = 2, 500 Hz: 0.987 at 16 Hz, 0.95 at 32 Hz) and puts
    its images near multiples of 1/Δ, where the photoreceptor attenuates them by
    ≥ 1/Δ·2πτ (≥ 15× at 250 Hz). The acceptance function (Δρ = 5°) leaves little above
    λ ≈ 10°, i.e. 25 Hz per 250°/s of image speed. every = 1 casts every sample (exact).
    head: (len(times), 3, 3) head-to-body rotations or None (see :func:`render_eye`).
    """
    times = np.asarray(times, dtype=float)
    every = int(every)
    if every < 1:
        raise ValueError(f"every must be a positive integer, got {every}")
    if every == 1:
        yield from render_eye(scene, eye, times, chunk, head)
        return
    cast_idx = np.unique(np.concatenate([np.arange(0, len(times), every), [len(times) - 1]]))
    prev_i, prev = None, None
    out_buf, t_buf = [], []
    for ts, lum in render_eye(scene, eye, times[cast_idx], chunk, None if head is None else head[cast_idx]):
        idx = cast_idx[np.searchsorted(times[cast_idx], ts)]
        for i, frame in zip(idx, lum):  # a loop over cast samples; ommatidia are vectorised
            if prev is None:
                out_buf.append(frame[None])
                t_buf.append(times[i:i + 1])
            else:
                w = ((np.arange(prev_i + 1, i + 1) - prev_i) / (i - prev_i)).astype(np.float32)[:, None]
                out_buf.append((1.0 - w) * prev[None] + w * frame[None])
                t_buf.append(times[prev_i + 1:i + 1])
            prev_i, prev = i, frame
        yield np.concatenate(t_buf), np.concatenate(out_buf).astype(np.float32)
        out_buf, t_buf = [], []


def eye_range(scene, eye: CompoundEye, t: float, head: np.ndarray | None = None) -> np.ndarray:
    """Distance (m) along each ommatidial axis at time t, (n,) float32 (inf where nothing is hit);
    head: the (3, 3) head-to-body rotation then, or None."""
    d = eye.directions if head is None else eye.directions @ np.asarray(head).T
    return np.asarray(scene.cast_rays(d, float(t))[0], dtype=np.float32)


def _write_csv(path: Path, header, rows) -> None:
    with open(path, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(header)
        wr.writerows(rows)


def write_eye_footage(folder: str | Path, scene, eye: CompoundEye, imu: dict, times: np.ndarray,
                      metadata: dict, range_every: int = 10, chunk: int = 250,
                      progress: Callable[[int], None] | None = None, cast_every: int = 1,
                      gaze: GazeConfig | None = None) -> Path:
    """Render ``scene`` onto ``eye`` at ``times`` (s) into an eye-footage folder, atomically.

    gaze: haltere-driven gaze stabilisation (:mod:`lobula.gaze`): the head turns against the
    gyroscope's angular velocity (the IMU's gyro, bias and noise included, latest sample at or
    before each time), the rays are fixed in the head, and ``head.csv`` records the head angles.
    None: the eyes are fixed on the body (camera) frame.

    cast_every: ray-cast every that many samples and interpolate linearly between
    (:func:`render_eye_interpolated`; 1 = every sample, exact).

    imu: dict time_s (k,), accel (k, 3), gyro (k, 3) in the camera frame (as
    :func:`stimuli.imu.synthesize_imu` returns). metadata: the configuration for scene.json.
    """
    folder = Path(folder)
    times = np.asarray(times, dtype=float)
    if len(times) < 2 or np.any(np.diff(times) <= 0):
        raise ValueError("eye footage needs at least two strictly increasing sample times")
    rate = 1.0 / float(np.median(np.diff(times)))
    t_start = _time.perf_counter()
    theta = head = None
    if gaze is not None:
        g_t, g_w = np.asarray(imu["time_s"], float), np.asarray(imu["gyro"], float)
        if imu.get("imu_to_camera") is not None:
            g_w = g_w @ np.asarray(imu["imu_to_camera"], dtype=float).T
        k = np.clip(np.searchsorted(g_t, times, side="right") - 1, 0, len(g_t) - 1)
        theta = head_angles(times, g_w[k], gaze)
        head = head_rotation(theta)
    with atomic_folder(folder) as tmp:
        tab = eye.table()
        _write_csv(tmp / "ommatidia.csv", OMMATIDIA_COLUMNS,
                   zip(tab["index"], tab["eye"], *(np.round(tab[c], 6) for c in OMMATIDIA_COLUMNS[2:])))
        lum = np.lib.format.open_memmap(tmp / "luminance.npy", mode="w+", dtype=np.float32,
                                        shape=(len(times), eye.n))
        ridx = np.arange(0, len(times), range_every) if range_every else np.zeros(0, int)
        rng = np.lib.format.open_memmap(tmp / "range.npy", mode="w+", dtype=np.float32,
                                        shape=(len(ridx), eye.n))
        pos = 0
        for ts, block in render_eye_interpolated(scene, eye, times, cast_every, chunk, head):
            lum[pos:pos + len(ts)] = block
            pos += len(ts)
            if progress is not None:
                progress(len(ts))
        for j, i in enumerate(ridx):
            rng[j] = eye_range(scene, eye, times[i], None if head is None else head[i])
        lum.flush()
        rng.flush()
        del lum, rng
        _write_csv(tmp / "times.csv", ["sample", "time_s"], ((i, f"{t:.6f}") for i, t in enumerate(times)))
        if theta is not None:
            _write_csv(tmp / "head.csv", HEAD_COLUMNS,
                       ((f"{t:.6f}", *(f"{x:.8f}" for x in th)) for t, th in zip(times, theta)))
        acc_cam, gyr_cam = np.asarray(imu["accel"]), np.asarray(imu["gyro"])
        if imu.get("imu_to_camera") is not None:  # contract 1: eye footage stores the camera frame
            r = np.asarray(imu["imu_to_camera"], dtype=float)
            acc_cam, gyr_cam = acc_cam @ r.T, gyr_cam @ r.T
        _write_csv(tmp / "imu.csv", ["time_s", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z"],
                   ([f"{t:.6f}", *(f"{x:.6f}" for x in a), *(f"{x:.7f}" for x in g)]
                    for t, a, g in zip(imu["time_s"], acc_cam, gyr_cam)))
        vel = scene.camera_velocity(times)
        acc = scene.trajectory.acceleration(times)
        # Forward (optical-axis) acceleration: the track acceleration projected on z_cam.
        a_fwd = acc * np.einsum("nji,j->ni", scene.rotation(times), np.array([0.0, 0.0, 1.0]))[:, 2]
        _write_csv(tmp / "truth.csv", ["time_s", "v_forward_m_s", "a_forward_m_s2", "position_m"],
                   ((f"{t:.6f}", f"{v:.6f}", f"{a:.6f}", f"{s:.6f}")
                    for t, v, a, s in zip(times, vel[:, 2], a_fwd, scene.trajectory.position(times))))
        info = dict(kind="compound-eye", rate_hz=rate, n_samples=len(times), n_ommatidia=eye.n,
                    eye=eye.config.to_dict(), range_every=int(range_every),
                    rays_per_ommatidium=int(len(eye.ray_weights)), cast_every=int(cast_every),
                    cast_rate_hz=rate / int(cast_every), gaze=None if gaze is None else gaze.to_dict(),
                    render_s=round(_time.perf_counter() - t_start, 2))
        (tmp / "eye.json").write_text(json.dumps(info, indent=1))
        (tmp / "scene.json").write_text(json.dumps(metadata, indent=1, default=str))
    return folder


@dataclass
class EyeFootage:
    """An eye-footage folder, opened lazily (luminance is memory-mapped).

    eye: the :class:`CompoundEye` rebuilt from eye.json (checked against ommatidia.csv);
    times (T,) s; rate_hz; imu (camera frame) or None; truth dict or None; head (T, 3) the head's
    rotation vector relative to the body (rad, head.csv) when the gaze was stabilised, else None.
    ``chunks(size)`` yields (times (k,), luminance (k, n) float32) in order.
    """

    path: Path
    eye: CompoundEye
    times: np.ndarray
    rate_hz: float
    imu: IMU | None
    truth: dict | None
    info: dict
    head: np.ndarray | None = None
    kind: str = "compound-eye"
    notes: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.times)

    @property
    def luminance(self) -> np.ndarray:
        """(T, n) float32, memory-mapped."""
        return np.load(self.path / "luminance.npy", mmap_mode="r")

    def chunks(self, size: int = 500) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        lum = self.luminance
        for s in range(0, len(self.times), size):
            yield self.times[s:s + size], np.asarray(lum[s:s + size], dtype=np.float32)

    def range_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(times (k,), range (k, n)) of the stored axial ranges (m)."""
        every = int(self.info.get("range_every", 0))
        p = self.path / "range.npy"
        if not every or not p.exists():
            return np.zeros(0), np.zeros((0, self.eye.n), np.float32)
        r = np.load(p, mmap_mode="r")
        return self.times[::every][:len(r)], np.asarray(r)


def is_eye_footage(path: str | Path) -> bool:
    """True for a folder holding eye.json and luminance.npy."""
    path = Path(path)
    return path.is_dir() and (path / "eye.json").exists() and (path / "luminance.npy").exists()


def open_eye_footage(path: str | Path) -> EyeFootage:
    """Open an eye-footage folder, checking its parts against each other up front."""
    path = Path(path)
    if not is_eye_footage(path):
        raise FootageError(f"{path}: not an eye-footage folder (needs eye.json and luminance.npy); "
                           f"make one with `lobula scene OUT --eye fly`")
    try:
        info = json.loads((path / "eye.json").read_text())
        eye = CompoundEye(CompoundEyeConfig.from_dict(info["eye"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise FootageError(f"{path / 'eye.json'}: not a valid eye description ({exc}); re-render the folder") from None
    tab = _read_csv(path / "ommatidia.csv", OMMATIDIA_COLUMNS)
    xyz = np.stack([tab["x"], tab["y"], tab["z"]], -1)
    if len(xyz) != eye.n or np.max(np.abs(xyz - eye.directions)) > 1e-4:
        raise FootageError(f"{path / 'ommatidia.csv'}: does not match the eye described in eye.json "
                           f"({len(xyz)} rows, {eye.n} expected); re-render the folder")
    tt = _read_csv(path / "times.csv", ("sample", "time_s"))["time_s"]
    _check_times(path / "times.csv", tt)
    try:
        lum = np.load(path / "luminance.npy", mmap_mode="r")
    except (OSError, ValueError) as exc:  # cut short (its header promises more than the file holds), or no .npy
        raise FootageError(f"{path / 'luminance.npy'}: not a readable array ({exc}); render the eye footage "
                           f"again (lobula scene OUT --eye fly)") from None
    if lum.ndim == 2 and lum.shape[1] == eye.n and lum.shape[0] != len(tt):  # one of the two cut short
        short = "times.csv" if len(tt) < lum.shape[0] else "luminance.npy"
        rows = f"{len(tt)} row{'s' * (len(tt) != 1)}"
        raise FootageError(f"{path / short}: times.csv has {rows} and luminance.npy {lum.shape[0]} frames, one per "
                           f"sample each, so {short} is cut short; render the eye footage again "
                           f"(lobula scene OUT --eye fly)")
    if lum.shape != (len(tt), eye.n):
        raise FootageError(f"{path / 'luminance.npy'}: shape {lum.shape}, expected ({len(tt)}, {eye.n}) from "
                           f"times.csv and ommatidia.csv; re-render the folder")
    bad = sum(int(np.count_nonzero(~np.isfinite(lum[k:k + 4096]))) for k in range(0, len(lum), 4096))
    if bad:  # a photoreceptor fed NaN turns every field and the readout NaN
        raise FootageError(f"{path / 'luminance.npy'}: {bad} NaN or infinite samples; render the eye footage "
                           f"again (lobula scene OUT --eye fly)")
    imu = None
    if (path / "imu.csv").exists():  # read and checked as a camera footage folder's (the same layout)
        imu = read_imu_csv(path / "imu.csv")
        check_imu_csv(imu, tt, [])
    truth = None
    if (path / "truth.csv").exists():
        truth = _read_csv(path / "truth.csv", ("time_s", "v_forward_m_s"))
    head = None
    if (path / "head.csv").exists():
        h = _read_csv(path / "head.csv", HEAD_COLUMNS)
        if len(h["time_s"]) != len(tt) or np.max(np.abs(h["time_s"] - tt)) > 1e-5:
            raise FootageError(f"{path / 'head.csv'}: its times do not match times.csv; re-render the folder")
        head = np.stack([h["theta_x"], h["theta_y"], h["theta_z"]], -1)
    return EyeFootage(path, eye, tt, float(info.get("rate_hz", 1.0 / np.median(np.diff(tt)))), imu, truth, info,
                      head)


def make_eye_run(folder, cfg, eye_config: CompoundEyeConfig | None = None, rate_hz: float = 500.0,
                 range_every: int = 10, progress: bool = True, cast_every: int = 1,
                 gaze: GazeConfig | None = None) -> Path:
    """Render a track run (:class:`stimuli.track.TrackRunConfig`: the same world, trajectory and IMU
    as the pinhole footage of that configuration) onto the compound eye at ``rate_hz``.

    500 Hz default: the photoreceptor model's 2 ms step (τ = 10 ms is resolved five times over).
    gaze: haltere-driven head stabilisation (:func:`write_eye_footage`), or None (head fixed on the body).
    """
    from tqdm.auto import tqdm

    from lobula.version import provenance_attrs

    from .track import build_track

    if not (20.0 <= rate_hz <= 5000.0):
        raise ValueError(f"eye rate must be in [20, 5000] Hz, got {rate_hz}")
    eye = CompoundEye(eye_config or CompoundEyeConfig())
    if getattr(cfg.scene, "mipmap", False) is None:
        # Texture filtering, not world content: the eye's rays carry their footprint (see render_eye).
        cfg = replace(cfg, scene=replace(cfg.scene, mipmap=True))
    scene, imu = build_track(cfg)
    times = np.arange(0.0, cfg.duration_s - 1e-9, 1.0 / rate_hz)
    meta = dict(**provenance_attrs(), config=cfg.to_dict(), eye=eye.config.to_dict(), rate_hz=rate_hz,
                accel_bias=imu["accel_bias"].tolist(), gyro_bias=imu["gyro_bias"].tolist(),
                trajectory=scene.trajectory.source, world_camera=scene.camera.to_dict(),
                note="the world is laid out for the pinhole camera named in world_camera (same seed, same world)",
                gaze=None if gaze is None else gaze.to_dict())
    with tqdm(total=len(times), desc="rendering eye", unit="sample", disable=not progress, leave=False,
              mininterval=2) as bar:
        return write_eye_footage(folder, scene, eye, imu, times, meta, range_every, progress=bar.update,
                                 cast_every=cast_every, gaze=gaze)
