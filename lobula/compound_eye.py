"""Two compound eyes on the sphere: ommatidial lattice, neighbour pairs and Gaussian acceptance rays.

Frame
-----
The eyes sit at the origin of the camera optical frame (x right, y down, z forward,
the body's long axis pointing along z). A viewing direction is given by its azimuth
``az`` (from +z toward +x, i.e. positive to the right) and elevation ``el`` (positive
*downward*, as :func:`lobula.camera.normalised_to_angles` defines it):
``d = (cos el · sin az, sin el, cos el · cos az)``.

Layout (a hexagonal lattice on the sphere)
------------------------------------------
Rows of constant elevation are ``(√3/2)·Δφ`` apart; along a row ommatidia are spaced
``Δφ / cos el`` in azimuth (so Δφ apart in true angle) and every other row is shifted
by half a spacing, which makes each ommatidium's six nearest neighbours Δφ away on the
equator. Rows are anchored at the middle of the eye's azimuth range; toward ±60° the
changing row spacing shears the packing, as real eyes' lattices bend and carry defects
(Stavenga 2003, J Comp Physiol A 189:1–17 review the fly's ommatidial geometry).
Neighbour pairs are every two ommatidia of one eye closer than ``1.25·Δφ``, found
with a k-d tree (about three pairs per ommatidium), so the EMD array runs along the
lattice's three axes whatever the local shear.

Defaults (Drosophila; the figures are orders of magnitude across studies):

- Δφ = 5°, Δρ = Δφ: Drosophila's interommatidial angle ≈ 4.6–5° and acceptance angle
  of the same size, Δρ/Δφ ≈ 1 (Land 1997, Annu Rev Entomol 42:147–177; Stavenga 2003).
  Blowflies (Calliphora) have Δφ ≈ 1–2° (Land 1997; Borst & Haag 2002, J Comp Physiol A
  188:419 on the blowfly's motion-vision system), i.e. ~5,000 ommatidia per eye.
- Each eye covers azimuth −15°…160° (15° across the midline: a small frontal binocular
  overlap; the two eyes together ≈ ±160°, leaving a blind sector behind) and elevation
  ±60°. At Δφ = 5° this gives ≈ 800 ommatidia per eye (Drosophila: ~750–800).

The left eye is the mirror image of the right one (x → −x), ommatidium for
ommatidium, so left–right sums of mirror fields are exact.

Optics
------
Each ommatidium weights light with a Gaussian angular sensitivity of FWHM Δρ
(σ = Δρ/2.355; Götz 1964, Kybernetik 2:77; Land 1997). It is sampled by a fixed
quadrature of rays: the points of a hexagonal grid of ``rings`` rings around the
axis (1 + 3·rings·(rings+1) rays), laid on the tangent plane through the exponential
map, with Gaussian weights whose width is chosen (by bisection) so that the rule's
variance is exactly σ² per axis (:func:`acceptance_rule`). The rule reproduces the Gaussian's contrast
transfer ``exp(−(πΔρ/λ)²/(4 ln 2))`` (:func:`lobula.lattice.acceptance_attenuation`)
within a few per cent down to λ ≈ 1.5·Δρ. Texture finer than the ray spacing aliases
into the ommatidium's signal, and a 1/f world has much of it: point-sampled with 2 rings
(19 rays, spacing 1.25σ) the aliased texture decorrelates neighbouring ommatidia and
inflates the EMDs' contrast pool (measured on a panels world: the LC fields' correlation
with the exact v/D falls from 0.84 with 3 rings to 0.34). :func:`stimuli.eye.render_eye`
therefore passes each ray's footprint (the grid spacing) to a scene with a texture
mip-map, which blurs every lookup to it; with that, 2 rings (the default) give a
correlation of 0.97 on the panels family. Without a mip-map use 3 rings (37 rays).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "CompoundEyeConfig", "CompoundEye", "eye_directions", "acceptance_rule", "hex_points",
    "expected_count",
]

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
EYES = ("right", "left")


@dataclass(frozen=True)
class CompoundEyeConfig:
    """Layout and optics of the two eyes (degrees at this user-facing edge).

    dphi_deg: interommatidial angle Δφ (Drosophila ≈ 5°, Land 1997).
    drho_deg: acceptance angle Δρ (FWHM); None means Δρ = Δφ.
    azimuth_deg: (medial, lateral) azimuth limits of the right eye; the left eye mirrors it.
    elevation_deg: (lower, upper) limit of |elevation| span, symmetric by default (±60°).
    rings: rings of the hexagonal ray grid sampling each acceptance function
        (1: 7 rays, 2: 19, 3: 37; with a mip-mapped scene 2 suffice, without one use 3: see
        the module docstring).
    eyes: "both", "right" or "left".
    neighbour_factor: ommatidia of one eye closer than this many Δφ are EMD neighbours.
    """

    dphi_deg: float = 5.0
    drho_deg: float | None = None
    azimuth_deg: tuple = (-15.0, 160.0)
    elevation_deg: tuple = (-60.0, 60.0)
    rings: int = 2
    eyes: str = "both"
    neighbour_factor: float = 1.25

    def __post_init__(self):
        if not (0.5 <= self.dphi_deg <= 30.0):
            raise ValueError(f"dphi_deg (interommatidial angle) must be in [0.5, 30] degrees, got {self.dphi_deg}")
        if self.drho_deg is not None and not (0.0 < self.drho_deg <= 60.0):
            raise ValueError(f"drho_deg (acceptance angle) must be in (0, 60] degrees or None, got {self.drho_deg}")
        a0, a1 = self.azimuth_deg
        e0, e1 = self.elevation_deg
        if not (-90.0 <= a0 < a1 <= 180.0):
            raise ValueError(f"azimuth_deg must be (medial, lateral) with -90 <= medial < lateral <= 180, got "
                             f"{self.azimuth_deg}")
        if not (-85.0 <= e0 < e1 <= 85.0):
            raise ValueError(f"elevation_deg must be (low, high) within ±85°, got {self.elevation_deg}")
        if not (isinstance(self.rings, (int, np.integer)) and 0 <= self.rings <= 6):
            raise ValueError(f"rings must be an integer 0..6, got {self.rings!r}")
        if self.eyes not in ("both", "right", "left"):
            raise ValueError(f"eyes must be 'both', 'right' or 'left', got {self.eyes!r}")
        if not (1.0 < self.neighbour_factor < math.sqrt(3.0)):
            raise ValueError(f"neighbour_factor must lie in (1, √3) so that only nearest neighbours pair, "
                             f"got {self.neighbour_factor}")

    @property
    def acceptance_deg(self) -> float:
        """Δρ in degrees (Δφ when drho_deg is None)."""
        return float(self.dphi_deg if self.drho_deg is None else self.drho_deg)

    def to_dict(self) -> dict:
        """Every field as a dict (the angle limits as lists)."""
        d = asdict(self)
        d["azimuth_deg"], d["elevation_deg"] = list(self.azimuth_deg), list(self.elevation_deg)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "CompoundEyeConfig":
        """The configuration :meth:`to_dict` wrote as ``d``."""
        d = dict(d)
        for k in ("azimuth_deg", "elevation_deg"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)


# --------------------------------------------------------------------------- geometry

def eye_directions(az, el) -> np.ndarray:
    """Unit directions (..., 3) in the camera frame for azimuth ``az`` and elevation ``el`` (radians, any one
    shape (...); el positive down)."""
    az, el = np.asarray(az, dtype=float), np.asarray(el, dtype=float)
    ce = np.cos(el)
    return np.stack([ce * np.sin(az), np.sin(el), ce * np.cos(az)], axis=-1)


def expected_count(config: CompoundEyeConfig) -> float:
    """Ommatidia per eye expected from area: the solid angle of the region ``config`` gives over a hexagon's
    (√3/2)Δφ²."""
    a0, a1 = np.radians(config.azimuth_deg)
    e0, e1 = np.radians(config.elevation_deg)
    solid = (a1 - a0) * (np.sin(e1) - np.sin(e0))
    return float(solid / (math.sqrt(3.0) / 2.0 * math.radians(config.dphi_deg) ** 2))


def _right_eye_angles(config: CompoundEyeConfig) -> tuple[np.ndarray, np.ndarray]:
    """Azimuths and elevations (radians, (n,)) of the right eye's ommatidia, row by row."""
    dphi = math.radians(config.dphi_deg)
    a0, a1 = np.radians(config.azimuth_deg)
    e0, e1 = np.radians(config.elevation_deg)
    row = dphi * math.sqrt(3.0) / 2.0
    j = np.arange(math.ceil(e0 / row), math.floor(e1 / row) + 1)
    el_rows = j * row
    step = dphi / np.cos(el_rows)                       # azimuth spacing per row
    centre = 0.5 * (a0 + a1)
    shift = 0.5 * (j % 2)
    k_lo = np.ceil((a0 - centre) / step - shift).astype(int)
    k_hi = np.floor((a1 - centre) / step - shift).astype(int)
    counts = k_hi - k_lo + 1
    # Vectorised ragged rows: one (row, k) entry per ommatidium.
    row_of = np.repeat(np.arange(len(j)), counts)
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + k_lo[row_of]
    az = centre + (k + shift[row_of]) * step[row_of]
    return az, el_rows[row_of]


def hex_points(rings: int) -> np.ndarray:
    """Points (m, 2) of a unit-spacing hexagonal grid within ``rings`` rings of the origin."""
    i, j = np.meshgrid(np.arange(-rings, rings + 1), np.arange(-rings, rings + 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    keep = (np.abs(i) <= rings) & (np.abs(j) <= rings) & (np.abs(i + j) <= rings)  # hex distance
    i, j = i[keep], j[keep]
    return np.stack([i + 0.5 * j, j * math.sqrt(3.0) / 2.0], axis=-1)


def acceptance_rule(drho_rad: float, rings: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Tangent-plane offsets (m, 2) in radians and weights (m,) (summing to 1) sampling a Gaussian of FWHM Δρ
    (``drho_rad``, radians).

    A hexagonal grid reaching R = (2 + (rings − 1)/2)·σ (capped at 3σ; σ = Δρ/2.355) with
    Gaussian weights ``exp(−|q|²/2s²)`` whose width s is set by bisection so that the
    rule's variance per axis is exactly σ². rings = 1 is the classic 7-point rule for a
    2-D Gaussian (centre weight ½, six rays at 2σ: exact to degree 5); rings = 0 is one
    axial ray.
    """
    sigma = drho_rad / _FWHM_PER_SIGMA
    if rings == 0:
        return np.zeros((1, 2)), np.ones(1)
    q = hex_points(rings) * min(2.0 + 0.5 * (rings - 1), 3.0) / rings   # units of σ
    r2 = (q * q).sum(1)

    def variance(s):  # per-axis variance (units of σ²) with weight width s (units of σ); increasing in s
        w = np.exp(-0.5 * r2 / (s * s))
        return float((w * q[:, 0] ** 2).sum() / w.sum())

    lo, hi = 0.05, 1e3
    for _ in range(100):  # bisection on a monotone scalar function
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if variance(mid) < 1.0 else (lo, mid)
    w = np.exp(-0.5 * r2 / (lo * hi))
    return q * sigma, w / w.sum()


def tangent_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local (east, down) unit vectors, each (..., 3), at directions d (..., 3): east = ŷ × d normalised."""
    east = np.cross(np.array([0.0, 1.0, 0.0]), d)
    norm = np.linalg.norm(east, axis=-1, keepdims=True)
    east = np.where(norm > 1e-9, east / np.where(norm > 1e-9, norm, 1.0), np.array([1.0, 0.0, 0.0]))
    return east, np.cross(d, east)


def exp_map(d: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Directions (n, m, 3) at tangent-plane offsets (m, 2) (radians, east/down) around d (n, 3)."""
    e1, e2 = tangent_basis(d)
    r = np.linalg.norm(offsets, axis=-1)                     # (m,)
    s = np.sinc(r / np.pi)                                   # sin r / r, finite at 0
    t = offsets[:, 0, None] * e1[:, None, :] + offsets[:, 1, None] * e2[:, None, :]  # (n, m, 3)
    return np.cos(r)[None, :, None] * d[:, None, :] + s[None, :, None] * t


# --------------------------------------------------------------------------- the eyes

class CompoundEye:
    """Both eyes' ommatidia, neighbour pairs and acceptance rays (numpy, built once).

    Attributes (n ommatidia, P pairs, m rays per ommatidium):
    directions (n, 3) unit axes in the camera frame; azimuth, elevation (n,) radians;
    eye (n,) 0 = right, 1 = left; pairs_a, pairs_b (P,) indices (a pair never crosses
    eyes; within a pair A precedes B in index order); ray_offsets (m, 2) rad and
    ray_weights (m,).

    config: the :class:`CompoundEyeConfig` (None: the default).
    """

    def __init__(self, config: CompoundEyeConfig | None = None):
        self.config = cfg = config or CompoundEyeConfig()
        az, el = _right_eye_angles(cfg)
        if cfg.eyes == "both":
            az_all, el_all = np.concatenate([az, -az]), np.concatenate([el, el])
            eye = np.concatenate([np.zeros(len(az), int), np.ones(len(az), int)])
        else:
            sign = 1.0 if cfg.eyes == "right" else -1.0
            az_all, el_all = sign * az, el
            eye = np.full(len(az), 0 if cfg.eyes == "right" else 1)
        self.azimuth, self.elevation, self.eye = az_all, el_all, eye
        self.directions = eye_directions(az_all, el_all)
        self.dphi = math.radians(cfg.dphi_deg)
        self.drho = math.radians(cfg.acceptance_deg)
        self.ray_offsets, self.ray_weights = acceptance_rule(self.drho, cfg.rings)
        self.pairs_a, self.pairs_b = self._pairs()

    @property
    def n(self) -> int:
        """Number of ommatidia (both eyes)."""
        return len(self.directions)

    @property
    def n_pairs(self) -> int:
        """Number of neighbour pairs, P."""
        return len(self.pairs_a)

    def _pairs(self) -> tuple[np.ndarray, np.ndarray]:
        tree = cKDTree(self.directions)
        chord = 2.0 * math.sin(0.5 * self.config.neighbour_factor * self.dphi)
        pairs = tree.query_pairs(chord, output_type="ndarray")   # (P, 2), i < j
        pairs = pairs[self.eye[pairs[:, 0]] == self.eye[pairs[:, 1]]]
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        return pairs[order, 0].astype(np.int64), pairs[order, 1].astype(np.int64)

    @property
    def ray_spacing(self) -> float:
        """Spacing (rad) of the acceptance rays' grid (Δρ for a single axial ray)."""
        o = self.ray_offsets
        if len(o) < 2:
            return self.drho
        r = np.linalg.norm(o, axis=1)
        return float(r[r > 0].min())

    def rays(self) -> np.ndarray:
        """Acceptance rays (n, m, 3), unit vectors in the camera frame."""
        return exp_map(self.directions, self.ray_offsets)

    # ---------------------------------------------------------------- pair geometry
    @cached_property
    def pair_midpoint(self) -> np.ndarray:
        """Unit midpoints (P, 3) of every pair."""
        m = self.directions[self.pairs_a] + self.directions[self.pairs_b]
        return m / np.linalg.norm(m, axis=1, keepdims=True)

    @cached_property
    def pair_separation(self) -> np.ndarray:
        """Angle (P,) between A and B (radians)."""
        c = np.einsum("pk,pk->p", self.directions[self.pairs_a], self.directions[self.pairs_b])
        return np.arccos(np.clip(c, -1.0, 1.0))

    @cached_property
    def pair_direction(self) -> np.ndarray:
        """Unit tangent vectors (P, 3) at the midpoint, pointing from A to B."""
        t = self.directions[self.pairs_b] - self.directions[self.pairs_a]
        m = self.pair_midpoint
        t = t - np.einsum("pk,pk->p", t, m)[:, None] * m
        return t / np.linalg.norm(t, axis=1, keepdims=True)

    def table(self) -> dict[str, np.ndarray]:
        """Columns of the ommatidia table (index, eye, azimuth_deg, elevation_deg, x, y, z, drho_deg)."""
        return dict(index=np.arange(self.n), eye=np.array(EYES)[self.eye],
                    azimuth_deg=np.degrees(self.azimuth), elevation_deg=np.degrees(self.elevation),
                    x=self.directions[:, 0], y=self.directions[:, 1], z=self.directions[:, 2],
                    drho_deg=np.full(self.n, self.config.acceptance_deg))

    def summary(self) -> str:
        """One line: ommatidia per eye, Δφ, Δρ (degrees), pairs and rays per ommatidium."""
        per_eye = np.bincount(self.eye, minlength=2)
        return (f"{self.n} ommatidia (right {per_eye[0]}, left {per_eye[1]}), Δφ = {self.config.dphi_deg}°, "
                f"Δρ = {self.config.acceptance_deg}°, {self.n_pairs} neighbour pairs, "
                f"{len(self.ray_weights)} rays per ommatidium")
