"""Ray-cast 3D track scenes with exact ground truth (depth, flow, r = v/d).

The world frame is the *track frame*: z along the track (the direction of motion),
y down, x right. Gravity may be tilted in it (a sloped track or a tilted mount),
which is what makes gravity leak into the forward accelerometer axis. The camera
sits at ``s(t)·ẑ`` looking along z, optionally yawed/pitched off the track
direction by a fixed angle (the epipole then leaves the principal point) and
optionally rotating (yaw/pitch oscillation, for derotation tests).

Scene content: textured rectangular panels facing the camera at several depths ahead
of the farthest camera position, a backdrop wall, and optional floor and side walls.
Textures are seeded, band-limited 1/f noise defined in metres, so the image of a
surface changes scale correctly with distance. Rendering is vectorised over pixels
(one loop over the handful of surfaces) and super-sampled to avoid aliasing.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from lobula.camera import PinholeCamera


def rotation_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rotation_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rotation_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@dataclass
class SceneConfig:
    """Scene and camera-motion parameters (SI units, angles in degrees).

    seed: seeds panel layout and textures. near_m/far_m: panel distances beyond the
    camera's farthest position. off_axis_yaw_deg/off_axis_pitch_deg: fixed angle
    between the optical axis and the track (0 = translation along the optical axis).
    rotation_amp_deg/rotation_hz: sinusoidal yaw and pitch of the camera (0 = none).
    gravity_pitch_deg/gravity_roll_deg: tilt of gravity in the track frame.
    texture_wavelengths_m: band of the 1/f texture (shortest, longest wavelength).
    supersample: rays per pixel side. noise_grey: pixel noise std (grey levels, 8-bit).
    exposure_s: motion-blur exposure (0 = none), sampled with blur_samples sub-frames.
    """

    seed: int = 0
    n_panels: int = 10
    near_m: float = 0.5
    far_m: float = 3.0
    backdrop_m: float = 4.5
    floor: bool = True
    floor_height_m: float = 0.6
    side_walls: bool = False
    wall_halfwidth_m: float = 1.5
    off_axis_yaw_deg: float = 0.0
    off_axis_pitch_deg: float = 0.0
    rotation_amp_deg: float = 0.0
    rotation_hz: float = 0.5
    gravity_pitch_deg: float = 3.0
    gravity_roll_deg: float = 1.0
    texture_wavelengths_m: tuple = (0.03, 0.4)
    texture_texel_m: float = 0.004
    texture_size: int = 512
    supersample: int = 2
    noise_grey: float = 1.0
    exposure_s: float = 0.0
    blur_samples: int = 5

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Surface:
    """A textured axis-aligned rectangle: coordinate ``axis`` equals ``offset``.

    bounds: ((lo, hi) on the first in-plane axis, (lo, hi) on the second), metres.
    in_plane: the two world axes that index the texture. texture: atlas tile index.
    """

    axis: int
    offset: float
    in_plane: tuple[int, int]
    bounds: tuple[tuple[float, float], tuple[float, float]]
    texture: int
    gain: float = 1.0


def band_limited_texture(rng: np.random.Generator, size: int, texel_m: float,
                         wavelengths_m: tuple[float, float]) -> np.ndarray:
    """A periodic (size, size) texture with a 1/f amplitude spectrum between two wavelengths.

    Returns float32 luminance with zero mean and unit standard deviation.
    """
    f = np.fft.fftfreq(size, d=texel_m)  # cycles per metre
    fr = np.hypot(*np.meshgrid(f, f))
    lo, hi = 1.0 / wavelengths_m[1], 1.0 / wavelengths_m[0]
    amp = np.where((fr >= lo) & (fr <= hi), 1.0 / np.maximum(fr, 1e-9), 0.0)
    spec = amp * np.exp(2j * np.pi * rng.random((size, size)))
    tex = np.real(np.fft.ifft2(spec))
    tex -= tex.mean()
    return (tex / tex.std()).astype(np.float32)


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of a 2-D float32 image at pixel coordinates (u, v) of any shape.

    cv2.remap takes 2-D maps under 32767 per side, so other shapes are laid out as
    rows of 4096 samples (padded) and put back.
    """
    shape = np.shape(u)
    if len(shape) == 2 and max(shape) < 32767:
        return cv2.remap(image, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
    n = int(np.prod(shape))
    cols = 4096 if n > 4096 else max(n, 1)
    rows = -(-n // cols)
    uu = np.zeros(rows * cols, np.float32)
    vv = np.zeros(rows * cols, np.float32)
    uu[:n], vv[:n] = np.ravel(u), np.ravel(v)
    out = cv2.remap(image, uu.reshape(rows, cols), vv.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].reshape(shape)


class TrackScene:
    """A rendered world plus camera motion along a :class:`~stimuli.trajectory.Trajectory`.

    Methods give, for any time t (s): the camera pose, the rendered frame (H, W) in
    grey levels 0..255, the forward-depth map (m), and the exact normalised flow
    between two times.
    """

    def __init__(self, camera: PinholeCamera, trajectory, config: SceneConfig | None = None):
        self.camera = camera
        self.trajectory = trajectory
        self.config = config = config or SceneConfig()
        rng = np.random.default_rng(config.seed)
        s_min, s_max = trajectory.position_range()
        self.position_range = (s_min, s_max)
        self.base_rotation = rotation_y(np.radians(config.off_axis_yaw_deg)) @ rotation_x(
            -np.radians(config.off_axis_pitch_deg))
        g = rotation_z(np.radians(config.gravity_roll_deg)) @ rotation_x(
            -np.radians(config.gravity_pitch_deg)) @ np.array([0.0, 9.80665, 0.0])
        self.gravity_world = g
        self.surfaces = self._layout(rng, s_max)
        self.textures = [band_limited_texture(rng, config.texture_size, config.texture_texel_m,
                                              config.texture_wavelengths_m)
                         for _ in range(len(self.surfaces))]
        self._atlas = self._build_atlas()
        self._rays = self._sub_pixel_rays()

    # ---------------------------------------------------------------- layout
    def _layout(self, rng, s_max) -> list[Surface]:
        cfg = self.config
        hx, hy = [np.tan(np.radians(a / 2)) for a in self.camera.fov_deg]
        z0 = s_max + cfg.near_m
        surfaces = []
        depths = np.sort(rng.uniform(z0, s_max + cfg.far_m, cfg.n_panels))[::-1]
        for i, z in enumerate(depths):
            # Panels are sized and placed so each is seen from the start of the run.
            dist = z
            w = rng.uniform(0.15, 0.5) * dist * hx * 2
            h = rng.uniform(0.2, 0.6) * dist * hy * 2
            cx = rng.uniform(-1, 1) * dist * hx
            cy = rng.uniform(-1, 0.6) * dist * hy
            surfaces.append(Surface(2, float(z), (0, 1), ((cx - w / 2, cx + w / 2), (cy - h / 2, cy + h / 2)),
                                    i, gain=float(rng.uniform(0.6, 1.0))))
        zb = s_max + cfg.backdrop_m
        big = 100.0
        surfaces.append(Surface(2, float(zb), (0, 1), ((-big, big), (-big, big)), len(surfaces), 0.8))
        if cfg.floor:
            surfaces.append(Surface(1, cfg.floor_height_m, (0, 2), ((-big, big), (-big, zb)), len(surfaces), 0.9))
        if cfg.side_walls:
            for sgn in (-1, 1):
                surfaces.append(Surface(0, sgn * cfg.wall_halfwidth_m, (2, 1), ((-big, zb), (-big, big)),
                                        len(surfaces), 0.85))
        return surfaces

    def _build_atlas(self) -> np.ndarray:
        # Each tile gets a one-texel wrap border so bilinear lookups never bleed
        # into the neighbouring tile.
        n = self.config.texture_size
        tiles = [np.pad(t, 1, mode="wrap") for t in self.textures]
        return np.concatenate(tiles, axis=0).astype(np.float32)

    def _sub_pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        ss = self.config.supersample
        cam = self.camera
        off = (np.arange(ss) + 0.5) / ss - 0.5
        u = (np.arange(cam.width)[:, None] + off[None, :]).ravel()
        v = (np.arange(cam.height)[:, None] + off[None, :]).ravel()
        x, y = np.meshgrid((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
        return x, y  # (H*ss, W*ss)

    # ---------------------------------------------------------------- motion
    def rotation(self, t) -> np.ndarray:
        """Camera-to-track rotation matrices, shape (..., 3, 3) for times t (s)."""
        t = np.asarray(t, dtype=float)
        cfg = self.config
        a = np.radians(cfg.rotation_amp_deg) * np.sin(2 * np.pi * cfg.rotation_hz * t)
        b = np.radians(cfg.rotation_amp_deg) * np.sin(2 * np.pi * cfg.rotation_hz * 0.7 * t + 1.0)
        ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        o, z = np.ones_like(a), np.zeros_like(a)
        ry = np.stack([np.stack([ca, z, sa], -1), np.stack([z, o, z], -1), np.stack([-sa, z, ca], -1)], -2)
        rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cb, -sb], -1), np.stack([z, sb, cb], -1)], -2)
        return self.base_rotation @ ry @ rx

    def position(self, t) -> np.ndarray:
        """Camera centre in the track frame, shape (..., 3) (m)."""
        s = self.trajectory.position(t)
        return np.stack([np.zeros_like(s), np.zeros_like(s), s], axis=-1)

    def camera_velocity(self, t) -> np.ndarray:
        """Camera velocity in its own frame, shape (..., 3) (m/s); index 2 is the forward velocity."""
        v = self.trajectory.velocity(t)
        vw = np.stack([np.zeros_like(v), np.zeros_like(v), v], axis=-1)
        return np.einsum("...ji,...j->...i", self.rotation(t), vw)

    def epipole(self, t=0.0) -> tuple[float, float]:
        """Focus of expansion (normalised coordinates) of the translation at time t."""
        r = self.rotation(t)
        d = r.T @ np.array([0.0, 0.0, 1.0])
        return float(d[0] / d[2]), float(d[1] / d[2])

    # ---------------------------------------------------------------- ray casting
    def _intersect(self, d_world: np.ndarray, origin: np.ndarray):
        """Nearest surface hit along rays ``origin + λ·d_world`` (λ > 0), one loop over surfaces.

        d_world: (..., 3) ray directions in the track frame, any length. Returns λ
        (inf where nothing is hit), surface index (-1 where nothing is hit) and the two
        texture coordinates (m), each shaped like d_world[..., 0].
        """
        shape = d_world.shape[:-1]
        best = np.full(shape, np.inf)
        idx = np.full(shape, -1, dtype=np.int32)
        tex_a = np.zeros(shape)
        tex_b = np.zeros(shape)
        c = origin
        with np.errstate(divide="ignore", invalid="ignore"):
            for i, s in enumerate(self.surfaces):
                lam = (s.offset - c[s.axis]) / d_world[..., s.axis]
                a = c[s.in_plane[0]] + lam * d_world[..., s.in_plane[0]]
                b = c[s.in_plane[1]] + lam * d_world[..., s.in_plane[1]]
                (a0, a1), (b0, b1) = s.bounds
                hit = (lam > 1e-6) & (lam < best) & (a >= a0) & (a <= a1) & (b >= b0) & (b <= b1)
                best = np.where(hit, lam, best)
                idx = np.where(hit, i, idx)
                tex_a = np.where(hit, a, tex_a)
                tex_b = np.where(hit, b, tex_b)
        return best, idx, tex_a, tex_b

    def cast_rays(self, directions_cam, t: float):
        """Nearest surface along rays from the camera centre at time t (s).

        directions_cam: (..., 3) unit direction vectors in the camera optical frame (x right,
        y down, z forward), anywhere on the sphere (backward too). Returns ``(range_m,
        surface_index, tex_a, tex_b)``, each shaped (...): distance along the ray (m; inf
        where nothing is hit), the index into ``self.surfaces`` (-1 where nothing is hit)
        and the hit's two in-plane texture coordinates (m). Directions that are not unit
        length give λ in units of their length (range = λ·|d|).
        """
        d = np.asarray(directions_cam, dtype=float)
        if d.shape[-1:] != (3,):
            raise ValueError(f"directions_cam must have shape (..., 3), got {d.shape}")
        return self._intersect(d @ self.rotation(t).T, self.position(t))

    def luminance(self, directions_cam, t: float) -> np.ndarray:
        """Noise-free luminance (0..1) seen along unit directions (..., 3) at time t (s).

        0 where nothing is hit. The pinhole frames of :meth:`render` are this, averaged
        over each pixel's sub-pixel rays.
        """
        _, idx, a, b = self.cast_rays(directions_cam, t)
        return self._shade(idx, a, b)

    def _cast(self, x, y, t):
        """Nearest surface hit for normalised ray coordinates at time t.

        Returns forward depth (camera z, m), surface index and the two texture
        coordinates (m), each shaped like x: the rays (x, y, 1) have unit forward
        component, so the ray parameter λ is the forward depth.
        """
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return self.cast_rays(d, t)

    def _shade(self, idx, tex_a, tex_b) -> np.ndarray:
        cfg = self.config
        n = cfg.texture_size
        u = np.mod(tex_a / cfg.texture_texel_m, n) + 1.0
        v = np.mod(tex_b / cfg.texture_texel_m, n) + 1.0 + np.maximum(idx, 0) * (n + 2)
        tex = _bilinear(self._atlas, u, v)
        gain = np.array([s.gain for s in self.surfaces])[np.maximum(idx, 0)]
        lum = gain * (0.5 + 0.16 * tex)
        return np.where(idx >= 0, lum, 0.0)

    def _render_clean(self, t: float) -> np.ndarray:
        ss = self.config.supersample
        x, y = self._rays
        _, idx, a, b = self._cast(x, y, t)
        img = self._shade(idx, a, b)
        h, w = self.camera.height, self.camera.width
        return img.reshape(h, ss, w, ss).mean(axis=(1, 3))

    def render(self, t: float, frame_index: int = 0) -> np.ndarray:
        """The 8-bit grey frame (H, W) seen at time t (s), with blur and seeded pixel noise."""
        cfg = self.config
        if cfg.exposure_s > 0 and cfg.blur_samples > 1:
            times = t + cfg.exposure_s * (np.arange(cfg.blur_samples) / (cfg.blur_samples - 1) - 0.5)
            lum = np.mean([self._render_clean(float(s)) for s in times], axis=0)
        else:
            lum = self._render_clean(t)
        img = 255.0 * np.clip(lum, 0, 1)
        if cfg.noise_grey > 0:
            rng = np.random.default_rng([cfg.seed, 1, frame_index])
            img = img + rng.normal(0.0, cfg.noise_grey, img.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    def depth(self, t: float) -> np.ndarray:
        """Forward depth (camera z, m) at each pixel centre, (H, W) float32."""
        x, y = self.camera.normalised_grid()
        return self._cast(x, y, t)[0].astype(np.float32)

    def flow(self, t0: float, t1: float) -> np.ndarray:
        """Exact displacement (normalised coordinates) of each pixel of frame t0 by time t1, (2, H, W).

        Divide by (t1 - t0) for flow in 1/s. Occlusions are ignored (a point keeps
        its identity even if hidden at t1).
        """
        x, y = self.camera.normalised_grid()
        lam = self._cast(x, y, t0)[0]
        p_world = self.position(t0) + (np.stack([x, y, np.ones_like(x)], -1) @ self.rotation(t0).T) * lam[..., None]
        pc = (p_world - self.position(t1)) @ self.rotation(t1)
        return np.stack([pc[..., 0] / pc[..., 2] - x, pc[..., 1] / pc[..., 2] - y])

    def r_exact(self, t: float) -> np.ndarray:
        """r = v_forward / d at each pixel (1/s), (H, W)."""
        return self.camera_velocity(t)[2] / self.depth(t)
