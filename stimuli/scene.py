"""Ray-cast 3D track scenes with exact ground truth (depth, flow, r = v/d).

The world frame is the *track frame*: z along the track (the direction of motion),
y down, x right. Gravity may be tilted in it (a sloped track or a tilted mount),
which is what makes gravity leak into the forward accelerometer axis. The camera
sits at ``s(t)·ẑ`` looking along z, optionally yawed/pitched off the track
direction by a fixed angle (the epipole then leaves the principal point) and
optionally rotating (yaw/pitch oscillation, for derotation tests). Or it flies a
:class:`stimuli.flight.FlightPlan`: a fly-like path of straight segments and body saccades.

Worlds (``SceneConfig.world``):

* ``panels`` (the default): textured rectangular panels facing the camera at several
  depths ahead of the farthest camera position, a backdrop wall, and optional floor and
  side walls;
* ``corridor``: floor, ceiling, side walls and a textured end wall, dimensions drawn per
  seed, extending behind the camera;
* ``ground``: an outdoor-like ground plane to the horizon, a distant backdrop (a tree
  line / hills band 50-200 m away), scattered upright panels on the ground and a sky
  (no surface; background luminance).
* ``meadow``: outdoors at a fly's scale: the ground 0.1-0.4 m below the camera, stems and
  leaves standing along both sides of the path 0.45-2 m off its axis (beyond a saccadic
  flight's reach), a hedge a few metres ahead and a sky.

A rolling shutter (``SceneConfig.rolling_shutter_s``, the readout time from the top row to the bottom)
renders each pixel row at its own time: row r of the frame stamped t at t + r/height·readout, so a
turning or moving camera's frames shear and stretch as a CMOS sensor's do; the depth maps follow the
same row times (0: a global shutter, every row at t).

Camera rotation: a yaw/pitch oscillation (``rotation_amp_deg``) and a seeded
3-axis rotation (yaw, pitch, roll) made of several incommensurate sinusoids
(``rotation3_amp_deg``). Distant and grazing surfaces are sampled from a mip-map of
their texture (``mipmap``) so the ground near the horizon does not alias.
Textures are seeded, band-limited 1/f noise defined in metres, so the image of a
surface changes scale correctly with distance. Rendering is vectorised over pixels
(one loop over the handful of surfaces) and super-sampled to avoid aliasing.

The worlds' parameters and surfaces are :mod:`stimuli.worlds`; this module moves the camera through
them and casts its rays.
"""
from __future__ import annotations

import cv2
import numpy as np

from lobula.camera import PinholeCamera, ray_directions

from .worlds import SceneConfig, Surface, band_limited_texture, world_surfaces


def rotation_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rotation_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rotation_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _rot_stack(angle, axis: int) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about camera axis 0 (x), 1 (y) or 2 (z) by angles (...) (rad)."""
    c, sn = np.cos(angle), np.sin(angle)
    r = np.zeros(np.shape(angle) + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r[..., axis, axis] = 1.0
    r[..., i, i] = c
    r[..., j, j] = c
    r[..., i, j] = -sn
    r[..., j, i] = sn
    return r


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


def _mod_pow2(x: np.ndarray, period) -> np.ndarray:
    """x modulo period, for periods that are powers of 2: np.mod's result to the bit, at a quarter of its cost.

    A power-of-2 period makes x/period and floor(x/period)·period exact, so the one subtraction
    rounds as np.mod's final step does (the result can round up to the period, as np.mod's can).
    """
    return x - np.floor(x / period) * period


NEAR_CLIP_M = 1e-9  # below every hit's forward depth: _intersect counts a hit only at λ > 1e-6


def _grid_window(s: Surface, xs: np.ndarray, ys: np.ndarray, rot: np.ndarray, origin: np.ndarray):
    """The block of an image grid's rays that can hit surface s: (row slice, column slice); None where
    none can; (Ellipsis,) (every ray) where a bound is infinite.

    xs (W,), ys (H,): the grid's normalised coordinates, ascending; rot (3, 3): camera-to-track
    rotation; origin (3,): the camera centre (m). The rectangle is clipped to the half-space in front
    of the camera (forward depth ≥ NEAR_CLIP_M, which every hit exceeds); what is left projects to the
    convex hull of its vertices' images, so a ray outside their bounding box cannot reach it. The box
    is widened by two rays a side, far beyond rounding; a surface that reaches behind the camera gets
    a box open on that side (its clipped vertices project far out).
    """
    (a0, a1), (b0, b1) = s.bounds
    corners = np.zeros((4, 3))
    corners[:, s.axis] = s.offset
    corners[:, s.in_plane[0]] = [a0, a0, a1, a1]
    corners[:, s.in_plane[1]] = [b0, b1, b1, b0]  # in order around the rectangle
    pc = (corners - origin) @ rot  # camera frame
    if not np.all(np.isfinite(pc)):
        return (Ellipsis,)
    kept = []  # Sutherland–Hodgman against z ≥ NEAR_CLIP_M
    for p, q in zip(pc, np.roll(pc, -1, axis=0)):
        if p[2] >= NEAR_CLIP_M:
            kept.append(p)
        if (p[2] >= NEAR_CLIP_M) != (q[2] >= NEAR_CLIP_M):
            kept.append(p + (NEAR_CLIP_M - p[2]) / (q[2] - p[2]) * (q - p))
    if not kept:
        return None
    pc = np.array(kept)
    px, py = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    c0, c1 = np.searchsorted(xs, px.min(), "left") - 2, np.searchsorted(xs, px.max(), "right") + 2
    r0, r1 = np.searchsorted(ys, py.min(), "left") - 2, np.searchsorted(ys, py.max(), "right") + 2
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, len(xs)), min(r1, len(ys))
    if c0 >= c1 or r0 >= r1:
        return None
    return slice(r0, r1), slice(c0, c1)


def _band_window(window, rows: slice):
    """A grid window (:func:`_grid_window`) cut to the grid rows ``rows``, in the band's own row numbers."""
    if window is None or window[0] is Ellipsis:
        return window
    r0, r1 = max(window[0].start, rows.start), min(window[0].stop, rows.stop)
    return (slice(r0 - rows.start, r1 - rows.start), window[1]) if r0 < r1 else None


class TrackScene:
    """A rendered world plus camera motion along a :class:`~stimuli.trajectory.Trajectory`.

    Methods give, for any time t (s): the camera pose, the rendered frame (H, W) in
    grey levels 0..255, the forward-depth map (m), and the exact normalised flow
    between two times.
    """

    def __init__(self, camera: PinholeCamera, trajectory, config: SceneConfig | None = None, lens=None,
                 flight=None):
        """lens: a :class:`lobula.lens.LensDistortion` the camera sees through (None: a pinhole): each
        pixel's rays are the lens's, so the frames come out as that lens draws them.

        flight: a :class:`stimuli.flight.FlightPlan` the camera flies (None: along the straight track,
        at ``s(t)·ẑ``). With a plan the camera centre is the plan's position, its rotation the plan's
        body rotation times the configured one (off-axis mount, oscillations), the world is laid out
        over the path's z range, and ``trajectory`` is the speed along the path
        (:meth:`stimuli.flight.FlightPlan.trajectory`).
        """
        self.camera = camera
        self.lens = lens
        self.trajectory = trajectory
        self.flight = flight
        self.config = config = config or SceneConfig()
        rng = np.random.default_rng(config.seed)
        s_min, s_max = trajectory.position_range() if flight is None else flight.z_range()
        self.position_range = (s_min, s_max)
        self.base_rotation = rotation_y(np.radians(config.off_axis_yaw_deg)) @ rotation_x(
            -np.radians(config.off_axis_pitch_deg))
        g = rotation_z(np.radians(config.gravity_roll_deg)) @ rotation_x(
            -np.radians(config.gravity_pitch_deg)) @ np.array([0.0, 9.80665, 0.0])
        self.gravity_world = g
        self.surfaces = world_surfaces(config, camera, rng, s_min, s_max)
        # Each surface shows its texture tile (Surface.texture): its own, or one a row of roadside objects
        # shares (cv2.remap reads atlases under 32767 rows: some 30 mip-mapped tiles of 512).
        self._tile = np.array([s.texture for s in self.surfaces])
        self.textures = [band_limited_texture(rng, config.texture_size, config.texture_texel_m,
                                              config.texture_wavelengths_m)
                         for _ in range(int(self._tile.max()) + 1)]
        self._atlas = self._build_atlas()
        self._texel_scale = np.array([s.texel_scale for s in self.surfaces])  # (surfaces,), gathered per ray
        if config.use_mipmap:
            self._mip_atlas, rows, sizes = self._build_mipmap()
            # Per-level tables, gathered per ray by index (level k, texture i at k·textures + i).
            self._mip_rows = rows.astype(float).ravel()
            self._mip_sizes = sizes.astype(float)
            self._mip_scale = 2.0 ** np.arange(self.MIP_LEVELS)
        n = config.texture_size
        # Texture coordinates wrap on tiles of n >> k texels (mip level k), all powers of 2 when n is.
        self._mod = _mod_pow2 if n & (n - 1) == 0 else np.mod
        self._rays = self._sub_pixel_rays()
        # (H*ss, W*ss, 3) each, fixed in the camera and cast every frame: (x, y, 1) and its unit vector
        self._forward_rays = np.stack([*self._rays, np.ones_like(self._rays[0])], axis=-1)
        self._unit_rays = ray_directions(*self._rays)
        self._rotation3 = self._draw_rotation3()

    # ---------------------------------------------------------------- textures
    def _build_atlas(self) -> np.ndarray:
        # Each tile gets a one-texel wrap border so bilinear lookups never bleed
        # into the neighbouring tile.
        n = self.config.texture_size
        tiles = [np.pad(t, 1, mode="wrap") for t in self.textures]
        return np.concatenate(tiles, axis=0).astype(np.float32)

    MIP_LEVELS = 7
    RENDER_BAND_SAMPLES = 32768  # rays cast and shaded together (a band of rows, 256 kB per float64 array)

    def _build_mipmap(self):
        """Texture pyramid: level k is each texture low-passed and decimated by 2**k.

        Returns the stacked atlas (rows, n + 2), the first row of each (level, texture)
        tile (levels, textures) and each level's tile size.
        """
        n = self.config.texture_size
        f = np.fft.fftfreq(n)
        fr2 = np.add.outer(f ** 2, f ** 2)
        tiles, rows, sizes, row = [], [], [], 0
        spectra = [np.fft.fft2(tex) for tex in self.textures]
        for k in range(self.MIP_LEVELS):
            m = max(n >> k, 2)
            sizes.append(m)
            level_rows = []
            # Gaussian low-pass (σ = half the decimation, in texels), then decimate (periodic: FFT).
            gauss = np.exp(-2 * (np.pi * 0.5 * 2 ** k) ** 2 * fr2)
            for tex, spectrum in zip(self.textures, spectra):
                if k:
                    spec = spectrum * gauss
                    sm = np.real(np.fft.ifft2(spec))[:: n // m, :: n // m]
                else:
                    sm = tex
                t = np.zeros((m + 2, n + 2), np.float32)
                t[:, : m + 2] = np.pad(sm, 1, mode="wrap")
                tiles.append(t)
                level_rows.append(row)
                row += m + 2
            rows.append(level_rows)
        return np.concatenate(tiles, 0), np.array(rows), np.array(sizes)

    def _sub_pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        ss = self.config.supersample
        cam = self.camera
        off = (np.arange(ss) + 0.5) / ss - 0.5
        u = (np.arange(cam.width)[:, None] + off[None, :]).ravel()
        v = (np.arange(cam.height)[:, None] + off[None, :]).ravel()
        uu, vv = np.meshgrid(u, v)
        if self.lens is not None:
            from lobula.lens import pixel_rays

            x, y = pixel_rays(cam, self.lens, uu, vv)
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
                raise ValueError(f"the lens {self.lens.to_dict()} sees 90° or more off its axis at this camera's edge; "
                                 f"give a longer focal length or a narrower lens")
            return x, y  # (H*ss, W*ss)
        return (uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy  # (H*ss, W*ss)

    # ---------------------------------------------------------------- motion
    def rotation(self, t) -> np.ndarray:
        """Camera-to-track rotation matrices, shape (..., 3, 3) for times t (s)."""
        if self.flight is not None:
            return self.flight.rotation(t) @ self._mount_rotation(t)
        return self._mount_rotation(t)

    def _mount_rotation(self, t) -> np.ndarray:
        """The configured rotation (off-axis mount, oscillations), shape (..., 3, 3): the camera-to-track
        rotation on the straight track, the camera-to-body rotation in flight."""
        t = np.asarray(t, dtype=float)
        cfg = self.config
        a = np.radians(cfg.rotation_amp_deg) * np.sin(2 * np.pi * cfg.rotation_hz * t)
        b = np.radians(cfg.rotation_amp_deg) * np.sin(2 * np.pi * cfg.rotation_hz * 0.7 * t + 1.0)
        ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        o, z = np.ones_like(a), np.zeros_like(a)
        ry = np.stack([np.stack([ca, z, sa], -1), np.stack([z, o, z], -1), np.stack([-sa, z, ca], -1)], -2)
        rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cb, -sb], -1), np.stack([z, sb, cb], -1)], -2)
        r = self.base_rotation @ ry @ rx
        if self._rotation3 is not None:
            # Yaw about y (down), pitch about x (right), roll about z (forward), applied in that order.
            ang = self.rotation3_angles(t)
            r = r @ _rot_stack(ang[..., 0], 1) @ _rot_stack(ang[..., 1], 0) @ _rot_stack(ang[..., 2], 2)
        return r

    def _draw_rotation3(self):
        """Frequencies (3, K) Hz, phases (3, K) rad and amplitudes (3, K) rad of the 3-axis rotation."""
        cfg = self.config
        if not any(cfg.rotation3_amp_deg):
            return None
        rng = np.random.default_rng([cfg.seed, 3])  # its own stream: the layout does not depend on it
        k = cfg.rotation3_components
        freq = rng.uniform(*cfg.rotation3_band_hz, (3, k))
        phase = rng.uniform(0, 2 * np.pi, (3, k))
        w = rng.dirichlet(np.ones(k), 3)
        return freq, phase, np.radians(np.asarray(cfg.rotation3_amp_deg, float))[:, None] * w

    def rotation3_angles(self, t) -> np.ndarray:
        """(yaw, pitch, roll) of the seeded 3-axis rotation (rad), shape (..., 3)."""
        t = np.asarray(t, dtype=float)
        if self._rotation3 is None:
            return np.zeros(t.shape + (3,))
        freq, phase, amp = self._rotation3
        return np.sum(amp * np.sin(2 * np.pi * freq * t[..., None, None] + phase), axis=-1)

    def position(self, t) -> np.ndarray:
        """Camera centre in the track frame, shape (..., 3) (m)."""
        if self.flight is not None:
            return self.flight.position(t)
        s = self.trajectory.position(t)
        return np.stack([np.zeros_like(s), np.zeros_like(s), s], axis=-1)

    def world_velocity(self, t) -> np.ndarray:
        """Camera velocity in the track frame, shape (..., 3) (m/s)."""
        if self.flight is not None:
            return self.flight.velocity_world(t)
        v = self.trajectory.velocity(t)
        return np.stack([np.zeros_like(v), np.zeros_like(v), v], axis=-1)

    def world_acceleration(self, t) -> np.ndarray:
        """Camera acceleration in the track frame, shape (..., 3) (m/s²); in flight it holds the
        centripetal part of the saccades."""
        if self.flight is not None:
            return self.flight.acceleration_world(t)
        a = self.trajectory.acceleration(t)
        return np.stack([np.zeros_like(a), np.zeros_like(a), a], axis=-1)

    def angular_velocity(self, t) -> np.ndarray:
        """Camera-frame angular velocity ω (rad/s), the vee of Rᵀ·dR/dt of :meth:`rotation`, shape (n, 3)
        for times t (n,) (s).

        In flight, ω = Mᵀ·ω_body + ω_mount for R = R_body·M: the plan's exact body rate, carried into
        the camera by the mount rotation M, plus the mount's own rate (a central difference).
        """
        from .imu import angular_velocity

        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.flight is None:
            return angular_velocity(self.rotation, t)
        w_mount = angular_velocity(self._mount_rotation, t)
        return np.einsum("nji,nj->ni", self._mount_rotation(t), self.flight.angular_velocity(t)) + w_mount

    def camera_velocity(self, t) -> np.ndarray:
        """Camera velocity in its own frame, shape (..., 3) (m/s); index 2 is the forward velocity."""
        if self.flight is not None:
            return np.einsum("...ji,...j->...i", self.rotation(t), self.flight.velocity_world(t))
        v = self.trajectory.velocity(t)
        vw = np.stack([np.zeros_like(v), np.zeros_like(v), v], axis=-1)
        return np.einsum("...ji,...j->...i", self.rotation(t), vw)

    def epipole(self, t=0.0) -> tuple[float, float]:
        """Focus of expansion (normalised coordinates) of the translation at time t."""
        if self.flight is not None:
            d = self.camera_velocity(float(t))
            return float(d[0] / d[2]), float(d[1] / d[2])
        r = self.rotation(t)
        d = r.T @ np.array([0.0, 0.0, 1.0])
        return float(d[0] / d[2]), float(d[1] / d[2])

    # ---------------------------------------------------------------- ray casting
    def _intersect(self, d_world: np.ndarray, origin: np.ndarray, windows=None):
        """Nearest surface hit along rays ``origin + λ·d_world`` (λ > 0), one loop over surfaces.

        d_world: (..., 3) ray directions in the track frame, any length. Returns λ
        (inf where nothing is hit), surface index (-1 where nothing is hit) and the two
        texture coordinates (m), each shaped like d_world[..., 0].
        windows: for rays on an image grid, d_world (H, W, 3), one block of rays per surface that
        holds every ray able to reach it (:func:`_grid_window`; None: none can). Each surface is then
        tested only there; the result is the same to the bit.
        """
        shape = d_world.shape[:-1]
        # origin: one camera centre (3,), or one per ray ((..., 3), broadcast against d_world; windows None)
        best = np.full(shape, np.inf)
        idx = np.full(shape, -1, dtype=np.int32)
        tex_a = np.zeros(shape)
        tex_b = np.zeros(shape)
        c = origin
        with np.errstate(divide="ignore", invalid="ignore"):
            for i, s in enumerate(self.surfaces):
                w = (Ellipsis,) if windows is None else windows[i]
                if w is None:
                    continue
                d = d_world[w]
                lam = (s.offset - c[..., s.axis]) / d[..., s.axis]
                a = c[..., s.in_plane[0]] + lam * d[..., s.in_plane[0]]
                b = c[..., s.in_plane[1]] + lam * d[..., s.in_plane[1]]
                (a0, a1), (b0, b1) = s.bounds
                hit = (lam > 1e-6) & (lam < best[w]) & (a >= a0) & (a <= a1) & (b >= b0) & (b <= b1)
                best[w] = np.where(hit, lam, best[w])
                idx[w] = np.where(hit, i, idx[w])
                tex_a[w] = np.where(hit, a, tex_a[w])
                tex_b[w] = np.where(hit, b, tex_b[w])
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
        return self._intersect(self._to_track(directions_cam, t), self.position(t))

    def _to_track(self, directions_cam, t: float) -> np.ndarray:
        """Camera-frame directions (..., 3) as track-frame directions at time t (s)."""
        d = np.asarray(directions_cam, dtype=float)
        if d.shape[-1:] != (3,):
            raise ValueError(f"directions_cam must have shape (..., 3), got {d.shape}")
        return d @ self.rotation(t).T

    def luminance(self, directions_cam, t: float, footprint_rad: float | np.ndarray | None = None) -> np.ndarray:
        """Noise-free luminance (0..1) seen along unit directions (..., 3) at time t (s).

        Where nothing is hit: the sky level (0 unless the world has a sky). The pinhole
        frames of :meth:`render` are this, averaged over each pixel's sub-pixel rays.
        footprint_rad: angular size (rad) of each sample, scalar or (...); with the
        scene's mip-map on it picks the texture's blur level from the footprint on the
        surface (range x angle / √cos incidence). None: the finest level.
        """
        d_world = self._to_track(directions_cam, t)
        rng_m, idx, a, b = self._intersect(d_world, self.position(t))
        foot = None
        if footprint_rad is not None and self.config.use_mipmap:
            foot = self._footprint_m(d_world, rng_m, idx, footprint_rad)
        return self._shade(idx, a, b, foot)

    def _footprint_m(self, d_world, rng_m, idx, footprint_rad):
        """Size (m) on the surface of a sample of angular size footprint_rad: range·angle/√|cos incidence|.

        d_world: (..., 3) the samples' ray directions in the track frame."""
        axis = np.array([s.axis for s in self.surfaces])[np.maximum(idx, 0)]
        cos_inc = np.abs(np.take_along_axis(d_world, axis[..., None], -1)[..., 0]) / np.linalg.norm(d_world, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            # Geometric mean of the two axes of the footprint ellipse (r·θ and r·θ/cos): less blur
            # at grazing incidence than the long axis, less aliasing than the short one.
            return np.where(idx >= 0, rng_m * footprint_rad / np.sqrt(np.maximum(cos_inc, 1e-6)), 0.0)

    def _cast(self, x, y, t, unit=None, rolling: bool = True):
        """Nearest surface hit for the rays of an image grid at time t.

        x, y (H, W): normalised coordinates, a meshgrid (x constant down each column, y along each
        row, both ascending). Returns forward depth (camera z, m), surface index and the two texture
        coordinates (m), each (H, W): the rays (x, y, 1) have unit forward component, so the ray
        parameter λ is the forward depth. unit: the grid's rays (x, y, 1) normalised, (H, W, 3), cast
        instead (λ is then the range, m); their track-frame directions are then returned too.
        rolling: each pixel row at its own time under a rolling shutter (:meth:`_row_bands`); False: every
        row at t.
        """
        cast = self._row_bands if rolling and self.config.rolling_shutter_s > 0 else self._cast_bands
        _, *hits = next(cast(x, y, t, unit, band_rows=len(y)))
        return tuple(hits) if unit is not None else tuple(hits[:4])

    def row_times(self, t: float, n_rows: int | None = None) -> np.ndarray:
        """The time (s) each grid row of a frame stamped t is seen at, shape (n_rows,): grid row i lies in
        pixel row r = i·height // n_rows (n_rows: a multiple of the image height, height·supersample for
        the sub-pixel grid; None: the pixel rows), seen at t + r/height·rolling_shutter_s."""
        h = self.camera.height
        n_rows = h if n_rows is None else int(n_rows)
        return t + (np.arange(n_rows) * h // n_rows) / h * self.config.rolling_shutter_s

    def _row_bands(self, x, y, t, rays=None, band_rows: int = 1):
        """:meth:`_cast_bands` under a rolling shutter: every grid row cast from the pose at its own time
        (:meth:`row_times`). No surface is culled to a window (a window holds for one pose)."""
        times = self.row_times(t, len(y))
        rot, origin = self.rotation(times), self.position(times)  # (n, 3, 3), (n, 3)
        for r0 in range(0, len(y), band_rows):
            rows = slice(r0, min(len(y), r0 + band_rows))
            d = rays[rows] if rays is not None else np.stack([x[rows], y[rows], np.ones_like(x[rows])], axis=-1)
            d_world = np.einsum("rwj,rij->rwi", d, rot[rows])
            yield rows, *self._intersect(d_world, origin[rows][:, None, :]), d_world

    def _cast_bands(self, x, y, t, rays=None, band_rows: int = 1):
        """:meth:`_cast` a band of ``band_rows`` grid rows at a time: yields (rows, λ, surface, tex_a,
        tex_b, d_world) per band, rows the band's slice of the grid. rays: the grid's rays (H, W, 3) in the
        camera (None: (x, y, 1)). The surfaces' windows are found once for the whole grid."""
        rot, origin = self.rotation(t), self.position(t)
        windows = [_grid_window(s, x[0], y[:, 0], rot, origin) for s in self.surfaces]
        for r0 in range(0, len(y), band_rows):
            rows = slice(r0, min(len(y), r0 + band_rows))
            d = rays[rows] if rays is not None else np.stack([x[rows], y[rows], np.ones_like(x[rows])], axis=-1)
            d_world = d @ rot.T
            yield rows, *self._intersect(d_world, origin, [_band_window(w, rows) for w in windows]), d_world

    def _shade(self, idx, tex_a, tex_b, footprint_m=None) -> np.ndarray:
        cfg = self.config
        n = cfg.texture_size
        safe = np.maximum(idx, 0)
        if footprint_m is None or not cfg.use_mipmap:
            texel = cfg.texture_texel_m
            if np.any(self._texel_scale != 1.0):
                texel = texel * self._texel_scale[safe]
            u = self._mod(tex_a / texel, float(n)) + 1.0
            v = self._mod(tex_b / texel, float(n)) + 1.0 + self._tile[safe] * (n + 2)
            tex = _bilinear(self._atlas, u, v)
        else:
            tex = self._mip_sample(safe, tex_a, tex_b, footprint_m)
        gain = np.array([s.gain for s in self.surfaces])[safe]
        if cfg.contrast != 1.0:
            tex = cfg.contrast * tex
        lum = gain * (0.5 + 0.16 * tex)
        if cfg.brightness != 1.0:
            lum = cfg.brightness * lum
        return np.where(idx >= 0, lum, cfg.brightness * cfg.sky)

    def _mip_sample(self, safe, tex_a, tex_b, footprint_m):
        """Texture values blended between the two mip levels that bracket each footprint.

        Beyond the coarsest level the texture's contrast falls as 1/footprint, which is
        how the standard deviation of 1/f texture averaged over a patch falls.
        """
        texel = self.config.texture_texel_m * self._texel_scale[safe]
        top = self.MIP_LEVELS - 1
        lev = np.log2(np.maximum(footprint_m / texel, 1.0))
        k0 = np.minimum(np.floor(lev).astype(int), top)
        frac = np.where(lev >= top, 0.0, lev - k0)
        out = np.zeros(np.shape(safe))
        for dk, wgt in ((0, 1.0 - frac), (1, frac)):
            k = np.minimum(k0 + dk, top)
            m = self._mip_sizes[k]
            tx = texel * self._mip_scale[k]
            u = self._mod(tex_a / tx, m) + 1.0
            v = self._mod(tex_b / tx, m) + 1.0 + self._mip_rows[k * len(self.textures) + self._tile[safe]]
            out += wgt * _bilinear(self._mip_atlas, u, v)
        return out * np.minimum(1.0, 2.0 ** top / np.maximum(footprint_m / texel, 1e-12))

    def _render_clean(self, t: float) -> np.ndarray:
        ss = self.config.supersample
        h, w = self.camera.height, self.camera.width
        x, y = self._rays
        img = np.empty((h, w))
        # A band of pixel rows at a time: the per-ray arrays of a band stay in the CPU's cache through
        # the chain of casting and shading (~2x faster than whole frames; the same numbers to the bit).
        band = ss * max(1, self.RENDER_BAND_SAMPLES // (ss * ss * w))
        mip = self.config.use_mipmap
        rays = self._unit_rays if mip else self._forward_rays
        cast = self._row_bands if self.config.rolling_shutter_s > 0 else self._cast_bands
        for rows, rng_m, idx, a, b, d_world in cast(x, y, t, rays, band):
            if mip:  # luminance() on the grid's unit rays
                lum = self._shade(idx, a, b, self._footprint_m(d_world, rng_m, idx, 1.0 / (self.camera.fx * ss)))
            else:
                lum = self._shade(idx, a, b)
            img[rows.start // ss: rows.stop // ss] = lum.reshape(-1, ss, w, ss).mean(axis=(1, 3))
        return img

    def render(self, t: float, frame_index: int = 0) -> np.ndarray:
        """The 8-bit grey frame (H, W) seen at time t (s), with blur and seeded pixel noise; under a
        rolling shutter t is the top row's time (:meth:`row_times`)."""
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
        """Forward depth (camera z, m) at each pixel centre, (H, W) float32; under a rolling shutter each
        row's at its own time, as the frame stamped t sees it."""
        x, y = self.camera.normalised_grid()
        return self._cast(x, y, t)[0].astype(np.float32)

    def flow(self, t0: float, t1: float) -> np.ndarray:
        """Exact displacement (normalised coordinates) of each pixel of frame t0 by time t1, (2, H, W).

        Divide by (t1 - t0) for flow in 1/s. Occlusions are ignored (a point keeps
        its identity even if hidden at t1). NaN where no surface is hit (the ground world's sky).
        The flow between the poses at t0 and t1, every row at those instants (a global shutter's).
        """
        x, y = self.camera.normalised_grid()
        lam = self._cast(x, y, t0, rolling=False)[0]
        with np.errstate(invalid="ignore"):  # sky: an infinite depth has no scene point to follow
            p_world = self.position(t0) + (np.stack([x, y, np.ones_like(x)], -1) @ self.rotation(t0).T) * lam[..., None]
            pc = (p_world - self.position(t1)) @ self.rotation(t1)
            return np.stack([pc[..., 0] / pc[..., 2] - x, pc[..., 1] / pc[..., 2] - y])

    def r_exact(self, t: float) -> np.ndarray:
        """r = v_forward / d at each pixel (1/s), (H, W), every row at t (a global shutter's)."""
        x, y = self.camera.normalised_grid()
        return self.camera_velocity(t)[2] / self._cast(x, y, t, rolling=False)[0].astype(np.float32)
