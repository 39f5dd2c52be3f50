"""The worlds a :class:`~stimuli.scene.TrackScene` ray-casts, as data: their parameters and their surfaces.

:class:`SceneConfig` holds every parameter of a scene (world, layout, camera motion, gravity,
texture, rendering); :func:`world_surfaces` lays out the textured rectangles (:class:`Surface`) of
the panels, corridor or ground world (described in :mod:`stimuli.scene`) from the scene's seeded
random stream, and :func:`band_limited_texture` draws the 1/f texture each surface shows.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from lobula.camera import PinholeCamera


@dataclass
class SceneConfig:
    """Scene and camera-motion parameters (SI units, angles in degrees).

    seed: seeds layout, textures and the 3-axis rotation. world: "panels", "corridor",
    "ground" or "meadow" (module doc). Panels world: near_m/far_m: panel distances beyond the
    camera's farthest position; backdrop_m: backdrop wall distance beyond it; floor,
    side_walls: optional floor and side walls. off_axis_yaw_deg/off_axis_pitch_deg:
    fixed angle between the optical axis and the track (0 = translation along the
    optical axis). rotation_amp_deg/rotation_hz: sinusoidal yaw and pitch of the camera
    (0 = none). rotation3_amp_deg: (yaw, pitch, roll) peak amplitudes of the seeded
    3-axis rotation, each a sum of rotation3_components sinusoids with frequencies drawn
    in rotation3_band_hz (incommensurate: independent uniform draws) and random phases;
    the weights sum to 1 so |angle| never exceeds the amplitude.
    gravity_pitch_deg/gravity_roll_deg: tilt of gravity in the track frame.
    texture_wavelengths_m: band of the 1/f texture (shortest, longest wavelength).
    supersample: rays per pixel side. noise_grey: pixel noise std (grey levels, 8-bit).
    brightness: luminance gain (1 = today's; < 1 dims). contrast: texture contrast gain.
    exposure_s: motion-blur exposure (0 = none), sampled with blur_samples sub-frames.
    Corridor world: corridor_halfwidth_m, corridor_floor_m (floor below the camera),
    corridor_ceiling_m (ceiling above it): (lo, hi) ranges drawn uniformly per seed;
    corridor_end_m: end wall distance beyond the farthest camera position.
    Ground world: ground_height_m (camera height above the ground), ground_backdrop_m
    (backdrop distance), ground_backdrop_height_m: (lo, hi) ranges drawn per seed;
    ground_objects: upright panels standing on the ground 3-40 m ahead.
    sky_luminance: luminance where no surface is hit (None: 0.8 for the ground world,
    else 0). mipmap: sample textures from a mip-map chosen by each ray's footprint
    (None: on for corridor and ground, off for panels, which stays point-sampled).
    roadside_spacing_m: ground world: upright objects line both sides of the path every
    roadside_spacing_m metres on average (0 = none), from 5 m past the start to roadside_ahead_m beyond
    the farthest camera position, roadside_lateral_m off the path (m, (lo, hi)), roadside_width_m wide
    and roadside_height_m tall (m, (lo, hi)): a road's posts, trees and buildings, or what a drone
    flies over. rolling_shutter_s: the sensor's readout time from the top row to the bottom (s; 0 = a
    global shutter): row r of a frame stamped t is seen at t + r/height·rolling_shutter_s.
    Meadow world (outdoors at a fly's scale): meadow_height_m (the ground below the camera),
    meadow_backdrop_m (a hedge beyond the farthest camera position) and meadow_backdrop_height_m: (lo, hi)
    ranges drawn per seed; stems and leaves stand on the ground along both sides of the path every
    meadow_spacing_m metres on average, their inner edge meadow_lateral_m off the track axis (beyond a
    saccadic flight's lateral limit, 0.4 m, so the fly never flies through one), meadow_width_m wide and
    meadow_stem_height_m tall (m, (lo, hi)).
    """

    seed: int = 0
    world: str = "panels"
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
    rotation3_amp_deg: tuple = (0.0, 0.0, 0.0)
    rotation3_band_hz: tuple = (0.3, 1.5)
    rotation3_components: int = 3
    gravity_pitch_deg: float = 3.0
    gravity_roll_deg: float = 1.0
    texture_wavelengths_m: tuple = (0.03, 0.4)
    texture_texel_m: float = 0.004
    texture_size: int = 512
    supersample: int = 2
    noise_grey: float = 1.0
    brightness: float = 1.0
    contrast: float = 1.0
    exposure_s: float = 0.0
    blur_samples: int = 5
    corridor_halfwidth_m: tuple = (0.8, 1.5)
    corridor_floor_m: tuple = (0.9, 1.4)
    corridor_ceiling_m: tuple = (0.9, 1.6)
    corridor_end_m: float = 12.0
    ground_height_m: tuple = (0.8, 1.6)
    ground_backdrop_m: tuple = (50.0, 200.0)
    ground_backdrop_height_m: tuple = (8.0, 30.0)
    ground_objects: int = 8
    sky_luminance: float | None = None
    mipmap: bool | None = None
    roadside_spacing_m: float = 0.0
    roadside_ahead_m: float = 100.0
    roadside_lateral_m: tuple = (3.0, 15.0)
    roadside_width_m: tuple = (0.5, 8.0)
    roadside_height_m: tuple = (1.0, 10.0)
    rolling_shutter_s: float = 0.0
    meadow_height_m: tuple = (0.1, 0.4)
    meadow_backdrop_m: tuple = (2.0, 6.0)
    meadow_backdrop_height_m: tuple = (0.3, 1.5)
    meadow_spacing_m: float = 0.1
    meadow_lateral_m: tuple = (0.45, 2.0)
    meadow_width_m: tuple = (0.005, 0.15)
    meadow_stem_height_m: tuple = (0.05, 1.0)

    WORLDS = ("panels", "corridor", "ground", "meadow")
    #: fields :meth:`to_dict` leaves out while they hold their defaults, so a scene without roadside objects or a
    #: rolling shutter, and any world but the meadow, reads (and is cached) as it does without the fields
    QUIET_FIELDS = ("roadside_spacing_m", "roadside_ahead_m", "roadside_lateral_m", "roadside_width_m",
                    "roadside_height_m", "rolling_shutter_s", "meadow_height_m", "meadow_backdrop_m",
                    "meadow_backdrop_height_m", "meadow_spacing_m", "meadow_lateral_m", "meadow_width_m",
                    "meadow_stem_height_m")

    def __post_init__(self):
        if self.world not in self.WORLDS:
            raise ValueError(f"unknown world {self.world!r}; choose one of {', '.join(self.WORLDS)}")
        if len(tuple(self.rotation3_amp_deg)) != 3:
            raise ValueError(f"rotation3_amp_deg needs 3 amplitudes (yaw, pitch, roll), got {self.rotation3_amp_deg}")
        lo, hi = self.rotation3_band_hz
        if not 0 < lo <= hi:
            raise ValueError(f"rotation3_band_hz must be 0 < lo <= hi, got {self.rotation3_band_hz}")
        if self.rotation3_components < 1:
            raise ValueError("rotation3_components must be >= 1")
        if self.brightness <= 0 or self.contrast < 0:
            raise ValueError(f"brightness must be > 0 and contrast >= 0, got {self.brightness}, {self.contrast}")
        if self.meadow_spacing_m <= 0:
            raise ValueError(f"meadow_spacing_m must be > 0, got {self.meadow_spacing_m}")
        if self.roadside_spacing_m < 0 or self.rolling_shutter_s < 0:
            raise ValueError(f"roadside_spacing_m and rolling_shutter_s must be >= 0, got "
                             f"{self.roadside_spacing_m}, {self.rolling_shutter_s}")

    @property
    def sky(self) -> float:
        outdoors = self.world in ("ground", "meadow")
        return (0.8 if outdoors else 0.0) if self.sky_luminance is None else float(self.sky_luminance)

    @property
    def use_mipmap(self) -> bool:
        return self.world != "panels" if self.mipmap is None else bool(self.mipmap)

    def to_dict(self) -> dict:
        """Every parameter as a plain dict, less the QUIET_FIELDS that hold their defaults (a meadow keeps its
        own: they are what it is)."""
        d = asdict(self)
        for k in self.QUIET_FIELDS:
            if self.world == "meadow" and k.startswith("meadow_"):
                continue
            default = self.__dataclass_fields__[k].default
            if d[k] == default or (isinstance(default, tuple) and tuple(d[k]) == default):
                del d[k]
        return d


@dataclass
class Surface:
    """A textured axis-aligned rectangle: coordinate ``axis`` equals ``offset``.

    bounds: ((lo, hi) on the first in-plane axis, (lo, hi) on the second), metres.
    in_plane: the two world axes that index the texture. texture: atlas tile index.
    gain: luminance gain. texel_scale: the texture is stretched by this factor (a
    backdrop 100 m away gets coarse texture, as a tree line would).
    """

    axis: int
    offset: float
    in_plane: tuple[int, int]
    bounds: tuple[tuple[float, float], tuple[float, float]]
    texture: int
    gain: float = 1.0
    texel_scale: float = 1.0  # texture metres per texel, relative to SceneConfig.texture_texel_m


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


def world_surfaces(config: SceneConfig, camera: PinholeCamera, rng: np.random.Generator, s_min: float,
                   s_max: float) -> list[Surface]:
    """The surfaces of ``config.world`` for a camera whose track positions span [s_min, s_max] (m).

    rng: the scene's seeded stream (:class:`SceneConfig` ``seed``), which draws the layout here and the
    textures after it. Surface i shows texture tile i (Surface.texture), but for roadside objects, which
    share ROADSIDE_TILES tiles.
    """
    layout = {"panels": _panels, "corridor": _corridor, "ground": _ground, "meadow": _meadow}
    return layout[config.world](config, camera, rng, s_min, s_max)


def _panels(cfg: SceneConfig, camera: PinholeCamera, rng: np.random.Generator, s_min: float,
            s_max: float) -> list[Surface]:
    """n_panels panels at random depths between near_m and far_m beyond the farthest camera position, a
    backdrop wall at backdrop_m, and the optional floor and side walls."""
    hx, hy = [np.tan(np.radians(a / 2)) for a in camera.fov_deg]
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


def _corridor(cfg: SceneConfig, camera: PinholeCamera, rng: np.random.Generator, s_min: float,
              s_max: float) -> list[Surface]:
    """Floor, ceiling, two side walls, an end wall and a back wall 20 m behind the start: a closed box."""
    w = rng.uniform(*cfg.corridor_halfwidth_m)
    fl = rng.uniform(*cfg.corridor_floor_m)
    ce = rng.uniform(*cfg.corridor_ceiling_m)
    z_end = s_max + cfg.corridor_end_m
    z_back = s_min - 20.0
    surf = [Surface(1, fl, (0, 2), ((-w, w), (z_back, z_end)), 0, float(rng.uniform(0.7, 0.95))),
            Surface(1, -ce, (0, 2), ((-w, w), (z_back, z_end)), 1, float(rng.uniform(0.7, 0.95))),
            Surface(0, -w, (2, 1), ((z_back, z_end), (-ce, fl)), 2, float(rng.uniform(0.7, 0.95))),
            Surface(0, w, (2, 1), ((z_back, z_end), (-ce, fl)), 3, float(rng.uniform(0.7, 0.95))),
            Surface(2, z_end, (0, 1), ((-w, w), (-ce, fl)), 4, float(rng.uniform(0.7, 0.95)),
                    texel_scale=2.0),
            Surface(2, z_back, (0, 1), ((-w, w), (-ce, fl)), 5, float(rng.uniform(0.7, 0.95)),
                    texel_scale=2.0)]
    return surf


def _ground(cfg: SceneConfig, camera: PinholeCamera, rng: np.random.Generator, s_min: float,
            s_max: float) -> list[Surface]:
    """A ground plane to the horizon, upright panels on it, a distant backdrop band; sky elsewhere."""
    h = rng.uniform(*cfg.ground_height_m)
    zb = s_max + rng.uniform(*cfg.ground_backdrop_m)
    hb = rng.uniform(*cfg.ground_backdrop_height_m)
    far = 1e5  # to the horizon
    surf = [Surface(1, h, (0, 2), ((-far, far), (-far, zb)), 0, float(rng.uniform(0.6, 0.8)),
                    texel_scale=2.0),
            Surface(2, zb, (0, 1), ((-far, far), (h - hb, h)), 1, float(rng.uniform(0.4, 0.6)),
                    texel_scale=zb / 4.0)]
    for i in range(cfg.ground_objects):
        z = s_max + rng.uniform(3.0, 40.0)
        x = rng.choice([-1, 1]) * rng.uniform(0.5, 0.5 + 0.4 * (z - s_max))
        wd, ht = rng.uniform(0.5, 3.0), rng.uniform(0.8, 4.0)
        surf.append(Surface(2, float(z), (0, 1), ((x - wd / 2, x + wd / 2), (h - ht, h)), len(surf),
                            float(rng.uniform(0.5, 1.0)), texel_scale=float(rng.uniform(1.0, 3.0))))
    if cfg.roadside_spacing_m > 0:
        surf += _roadside(cfg, np.random.default_rng([cfg.seed, 8]), h, s_min, min(s_max + cfg.roadside_ahead_m, zb),
                          len(surf))
    # Nearest first among equal ranges does not matter: the ray caster keeps the nearest hit.
    return surf


#: texture tiles the roadside objects share (the renderer's atlas holds some 30 mip-mapped tiles)
ROADSIDE_TILES = 12


def _roadside(cfg: SceneConfig, rng: np.random.Generator, h: float, s_min: float, z_end: float,
              first: int) -> list[Surface]:
    """Upright objects on the ground (at y = h, m) along both sides of the path (SceneConfig roadside_*),
    from s_min + 5 m to z_end (m: roadside_ahead_m beyond the farthest camera position, or the backdrop
    if nearer); surface indices from ``first``.

    Their own random stream: the world's other surfaces and the textures drawn after them stay as they
    are without roadside objects. Each faces along the track, so it is seen while ahead and leaves the
    image at its side as it is passed (:func:`_upright_objects`).
    """
    return _upright_objects(rng, h, s_min + 5.0, z_end, cfg.roadside_spacing_m, cfg.roadside_lateral_m,
                            cfg.roadside_width_m, cfg.roadside_height_m, first, texel=lambda ht: max(1.0, ht / 4))


def _upright_objects(rng: np.random.Generator, h: float, z0: float, z_end: float, spacing: float, lateral: tuple,
                     width: tuple, height: tuple, first: int, texel) -> list[Surface]:
    """Upright rectangles standing on the ground (y = h, m), facing along the track, on both sides of the
    path from z0 to z_end (m): spacings jittered ±50 % around ``spacing`` (m), the inner edge ``lateral``
    (m, (lo, hi)) off the path, ``width`` wide and ``height`` tall (m, (lo, hi)). They share ROADSIDE_TILES
    texture tiles (from tile ``first`` on), each at its own texel scale (uniform 1–3, × texel(height))."""
    surf = []
    for side in (-1, 1):
        z = z0 + rng.uniform(0.0, spacing)
        while z < z_end:
            inner = rng.uniform(*lateral)
            wd, ht = rng.uniform(*width), rng.uniform(*height)
            x = side * (inner + wd / 2)
            surf.append(Surface(2, float(z), (0, 1), ((x - wd / 2, x + wd / 2), (h - ht, h)),
                                first + len(surf) % ROADSIDE_TILES,
                                float(rng.uniform(0.5, 1.0)),
                                texel_scale=float(rng.uniform(1.0, 3.0) * texel(ht))))  # coarser on big ones
            z += spacing * rng.uniform(0.5, 1.5)
    return surf


def _meadow(cfg: SceneConfig, camera: PinholeCamera, rng: np.random.Generator, s_min: float,
            s_max: float) -> list[Surface]:
    """Outdoors at a fly's scale: a ground plane just below the camera, stems and leaves along both sides of
    the path from 0.5 m behind the start to the hedge, a hedge a few metres beyond the farthest camera
    position; sky elsewhere. Surfaces 0.05–2 m from a fly that flies the path (SceneConfig meadow_*)."""
    h = rng.uniform(*cfg.meadow_height_m)
    zb = s_max + rng.uniform(*cfg.meadow_backdrop_m)
    hb = rng.uniform(*cfg.meadow_backdrop_height_m)
    far = 1e3  # the meadow runs on past the hedge to the horizon's few degrees
    surf = [Surface(1, h, (0, 2), ((-far, far), (-far, far)), 0, float(rng.uniform(0.6, 0.8)), texel_scale=0.5),
            Surface(2, zb, (0, 1), ((-far, far), (h - hb, h)), 1, float(rng.uniform(0.4, 0.6)), texel_scale=1.0)]
    return surf + _upright_objects(rng, h, s_min - 0.5, zb, cfg.meadow_spacing_m, cfg.meadow_lateral_m,
                                   cfg.meadow_width_m, cfg.meadow_stem_height_m, len(surf), texel=lambda ht: 0.5)
