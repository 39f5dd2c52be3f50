"""Stimuli rendered directly on the ommatidial lattice, with their exact parameters.

Every stimulus is a function of viewing direction and time evaluated at the ommatidial
axes of a :class:`lobula.lattice.Lattice` (no camera frames, no pixels), so its
parameters are exact: an edge is where it is said to be, a looming disc subtends
exactly ``2·atan(l / (v·(t_c − t)))``. With ``acceptance=True`` (the default) each
ommatidium's Gaussian angular sensitivity (FWHM Δρ, σ = Δρ/2.355) is applied
analytically where a closed form exists:

- Gaussian blobs (spots, dots, sparse noise): a Gaussian of σ_s blurred by σ is a
  Gaussian of σ_s² + σ² with its integral kept (amplitude × σ_s²/(σ_s² + σ²)).
- Discs (looming, disc spots): the fraction of a 2-D Gaussian inside a disc of radius ρ
  at distance δ is the non-central χ² CDF ``chndtr(ρ²/σ², 2, δ²/σ²)``.
- Edges: ``Φ(signed distance / σ)``. Gratings: the Gaussian transfer
  ``exp(−2π²σ²/λ²)`` (see :mod:`stimuli.gratings`).
- 1/f panoramas: the Gaussian transfer applied to the panorama's spectrum.
All of them treat the acceptance function in the tangent plane of each ommatidium
(exact as Δρ → 0; the curvature error is O(σ²) relative).

Conventions (as :mod:`stimuli.gratings`): camera frame x right, y down, z forward;
azimuth/elevation as :func:`lobula.camera.normalised_to_angles` (elevation positive
down); a motion *direction* θ is measured in the image at the stimulus' location,
0° = rightward, 90° = downward; times ``t_k = t0 + k / frame_rate``. Luminance is
``L₀·(1 + contrast·pattern)`` with L₀ the mean (background) luminance in any units.

Each public function returns ``(luminance, params)``: a torch tensor (time, ommatidia),
or (trials, time, ommatidia) when a parameter is given per trial or ``trials`` is set,
and a dict of the exact parameters (scalars, lists and numpy arrays: per-frame ground
truth such as an edge's position, a disc's angular size, a spot's centre). Random
stimuli take a ``seed`` and are reproducible bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import asdict
from typing import TYPE_CHECKING

import numpy as np
from scipy import special

from lobula._optional import torch
from lobula.camera import angles_to_normalised
from .gratings import GratingConfig, drifting_grating_lattice, drum_coordinates, frame_times

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "drifting_grating", "GratingSource", "radial_grating", "moving_edge", "looming_disc",
    "looming_angular_size", "dot_field", "moving_spot", "sparse_noise", "noise_panorama",
    "direction_from_angles", "tangent_basis",
]

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


# --------------------------------------------------------------------------- helpers

def direction_from_angles(azimuth_deg, elevation_deg) -> np.ndarray:
    """Unit viewing directions (..., 3) for azimuth/elevation in degrees (elevation + down).

    ``(cos el·sin az, sin el, cos el·cos az)``: the pinhole convention of
    :func:`lobula.camera.normalised_to_angles` in front (|az| < 90°), and valid on the
    whole sphere (a compound eye looks sideways and backward too).
    """
    az, el = np.radians(np.asarray(azimuth_deg, float)), np.radians(np.asarray(elevation_deg, float))
    ce = np.cos(el)
    return np.stack([ce * np.sin(az), np.sin(el), ce * np.cos(az)], axis=-1)


def tangent_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local (east, south) unit vectors at unit directions d (..., 3).

    east ⟂ the camera's y axis (rightward in the image near the optical axis), south =
    d × east (downward); the same basis :mod:`lobula.lattice` uses. A direction θ in the
    image is ``cos θ·east + sin θ·south``.
    """
    d = np.asarray(d, dtype=float)
    east = np.cross(np.array([0.0, 1.0, 0.0]), d)
    norm = np.linalg.norm(east, axis=-1, keepdims=True)
    east = np.where(norm > 1e-12, east / np.where(norm > 1e-12, norm, 1.0), np.array([1.0, 0.0, 0.0]))
    return east, np.cross(d, east)


def _rate(lattice, frame_rate_hz) -> float:
    rate = float(lattice.camera.frame_rate_hz if frame_rate_hz is None else frame_rate_hz)
    if not (rate > 0 and math.isfinite(rate)):
        raise ValueError(f"frame_rate_hz must be positive, got {frame_rate_hz}")
    return rate


def _sigma(lattice, acceptance: bool) -> float:
    """σ (rad) of the acceptance function, or 0 without it."""
    return math.radians(lattice.drho_deg) / _FWHM_PER_SIGMA if acceptance else 0.0


def _per_trial(**params) -> tuple[dict, bool, int]:
    """Parameters as float64 arrays broadcast to (K,), whether any was per trial, and K."""
    arrays = {k: np.asarray(v, dtype=float) for k, v in params.items()}
    for k, v in arrays.items():
        if v.ndim > 1:
            raise ValueError(f"stimulus parameter {k} must be a scalar or a 1-D sequence (one per trial), "
                             f"got shape {v.shape}")
    trials = any(v.ndim == 1 for v in arrays.values())
    try:
        b = np.broadcast_arrays(*[np.atleast_1d(v) for v in arrays.values()])
    except ValueError:
        raise ValueError("stimulus parameters given per trial must all have the same length: "
                         + ", ".join(f"{k}: {np.shape(v)}" for k, v in arrays.items())) from None
    out = dict(zip(arrays, (np.array(x, dtype=float) for x in b)))
    return out, trials, len(b[0]) if b else 1


def _finish(lum: np.ndarray | Tensor, trials: bool, dtype, device) -> Tensor:
    """(K, T, n) → tensor of dtype on device, squeezed to (T, n) when there are no trials."""
    t = torch.as_tensor(lum)
    t = t.to(device=device if device is not None else t.device, dtype=dtype)
    return t if trials else t[0]


def _listify(p: dict) -> dict:
    """Per-trial arrays of length 1 back to scalars when there are no trials."""
    return {k: (v.item() if isinstance(v, np.ndarray) and v.size == 1 else v) for k, v in p.items()}


def _angle_between(d: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Angle (rad) between unit vectors d (..., 3) and c (..., 3), stable at small angles."""
    cross = np.linalg.norm(np.cross(d, c), axis=-1)
    return np.arctan2(cross, np.sum(d * c, axis=-1))


def _angles_to(directions: np.ndarray, centres: np.ndarray) -> Tensor:
    """Angles (rad, float64 tensor) between ommatidial directions (n, 3) and centres (..., 3): (..., n).

    One float64 matrix product and the chord formula ``δ = 2·asin(|d − c|/2)``, with
    ``|d − c|² = 2 − 2 d·c`` (accurate to ~1e-8 rad at small angles); in place, because
    these arrays are the largest a stimulus makes.
    """
    c = torch.as_tensor(np.ascontiguousarray(centres), dtype=torch.float64)
    d = torch.as_tensor(np.ascontiguousarray(directions), dtype=torch.float64)
    x = c.reshape(-1, 3) @ d.t()
    x.mul_(-2.0).add_(2.0).clamp_(min=0.0).sqrt_().mul_(0.5).clamp_(max=1.0).asin_().mul_(2.0)
    return x.reshape(tuple(centres.shape[:-1]) + (d.shape[0],))


def _blob(delta, size_deg, sigma_acc: float, shape: str) -> Tensor:
    """Profile (peak 1) of a Gaussian (FWHM size) or a disc (diameter size) at angular distance delta (rad),
    seen through a Gaussian acceptance of σ = sigma_acc (rad). delta: tensor (consumed in place) or array;
    size_deg broadcasts against it."""
    delta = torch.as_tensor(delta, dtype=torch.float64)
    size = torch.as_tensor(np.radians(np.asarray(size_deg, dtype=float)), dtype=torch.float64)
    if shape == "gaussian":
        s2 = (size / _FWHM_PER_SIGMA) ** 2
        tot = s2 + sigma_acc ** 2
        return delta.square_().mul_(-0.5 / tot).exp_().mul_(s2 / tot)
    if shape == "disc":
        return torch.as_tensor(_disc_fraction(delta.numpy(), size.numpy() / 2.0, sigma_acc))
    raise ValueError(f"spot shape must be 'gaussian' or 'disc', got {shape!r}")


def _disc_fraction(delta: np.ndarray, radius: np.ndarray, sigma_acc: float) -> np.ndarray:
    """Fraction of a 2-D Gaussian (σ) centred at distance delta that lies inside a disc of ``radius``.

    Non-central χ² with 2 degrees of freedom: ``chndtr(ρ²/σ², 2, δ²/σ²)``; σ = 0 gives
    the indicator δ < ρ.
    """
    radius = np.broadcast_to(radius, np.broadcast_shapes(np.shape(radius), np.shape(delta)))
    if sigma_acc <= 0:
        return (delta < radius).astype(float)
    s2 = sigma_acc ** 2
    return special.chndtr(radius ** 2 / s2, 2.0, delta ** 2 / s2)


# --------------------------------------------------------------------------- gratings

def drifting_grating(lattice, n_frames: int, *, acceptance: bool = True, frame_rate_hz: float | None = None,
                     t0_s: float = 0.0, dtype=torch.float32, device=None, **params):
    """A drifting sine or square grating on the lattice (:func:`stimuli.gratings.drifting_grating_lattice`).

    params: any :class:`stimuli.gratings.GratingConfig` field (direction_deg,
    wavelength_deg, temporal_freq_hz, contrast, mean_luminance, phase_deg, waveform),
    scalars or (K,) sequences. Returns (luminance (T, n) or (K, T, n), params).
    """
    rate = _rate(lattice, frame_rate_hz)
    lum = drifting_grating_lattice(lattice, n_frames, acceptance=acceptance, frame_rate_hz=rate, t0_s=t0_s,
                                   dtype=dtype, device=device, **params)
    g = {**asdict(GratingConfig()), **params}
    info = {"kind": "drifting_grating", **{k: (np.asarray(v).tolist() if k != "waveform" else v) for k, v in g.items()},
            "angular_speed_deg_s": (np.asarray(g["wavelength_deg"], float) * np.asarray(g["temporal_freq_hz"], float)).tolist(),
            "frame_rate_hz": rate, "n_frames": n_frames, "t0_s": t0_s, "acceptance": acceptance}
    return lum, info


class GratingSource:
    """Streaming, separable renderer of drifting sine gratings for K conditions at once.

    ``src(start, stop)`` returns luminance (K, stop − start, n) for frames start…stop−1,
    so a long high-rate sweep never holds its whole stimulus. Uses the exact identity
    ``sin(kψ − ωt + φ) = sin kψ·cos(ωt − φ) − cos kψ·sin(ωt − φ)``: per frame one
    (K, 2) × (K, 2, n) batched product instead of a sine per ommatidium (float64
    coefficients, float32 result; identical to :func:`drifting_grating` up to rounding).

    kind: "drum" (a planar drifting grating, :mod:`stimuli.gratings`' geometry) or
    "radial" (concentric rings about ``centre_deg``, drifting outward for TF > 0; the
    preferred stimulus of an expansion unit). Parameters may be (K,) sequences:
    temporal_freq_hz, wavelength_deg, contrast, mean_luminance, direction_deg (drum),
    phase_deg. ``acceptance``: the Gaussian transfer of the ommatidial optics
    (local wavelength λ·cos β for the drum; λ for rings, exact away from their centre).
    """

    def __init__(self, lattice, *, kind: str = "drum", temporal_freq_hz=2.0, wavelength_deg=20.0, contrast=0.5,
                 mean_luminance=1.0, direction_deg=0.0, phase_deg=0.0, centre_deg=(0.0, 0.0),
                 acceptance: bool = True, frame_rate_hz: float | None = None, t0_s: float = 0.0,
                 dtype=torch.float32, device=None):
        if kind not in ("drum", "radial"):
            raise ValueError(f"GratingSource kind must be 'drum' or 'radial', got {kind!r}")
        p, trials, K = _per_trial(temporal_freq_hz=temporal_freq_hz, wavelength_deg=wavelength_deg, contrast=contrast,
                                  mean_luminance=mean_luminance, direction_deg=direction_deg, phase_deg=phase_deg)
        if np.any(p["wavelength_deg"] <= 0):
            raise ValueError(f"wavelength_deg must be positive, got {wavelength_deg}")
        if np.any(np.abs(p["contrast"]) > 1):
            raise ValueError(f"contrast must be in [-1, 1], got {contrast}")
        self.kind, self.trials, self.K, self.params = kind, trials, K, p
        self.rate = _rate(lattice, frame_rate_hz)
        self.t0_s = float(t0_s)
        self.dtype, self.device = dtype, torch.device(device) if device is not None else torch.device("cpu")
        sigma = _sigma(lattice, acceptance)
        lam = np.radians(p["wavelength_deg"])[:, None]
        if kind == "drum":
            coord, beta = drum_coordinates(lattice.directions, p["direction_deg"])          # (K, n)
            local = lam * np.maximum(np.cos(beta), 1e-9)
        else:
            c = direction_from_angles(*centre_deg)
            coord = np.broadcast_to(_angle_between(lattice.directions, c[None, :]), (K, lattice.n))
            local = np.broadcast_to(lam, (K, lattice.n))
        atten = np.exp(-2.0 * math.pi ** 2 * sigma ** 2 / local ** 2)
        amp = p["mean_luminance"][:, None] * p["contrast"][:, None] * atten
        kx = 2.0 * math.pi * coord / lam
        basis = np.stack([amp * np.sin(kx), -amp * np.cos(kx)], axis=1)                       # (K, 2, n)
        self._basis = torch.as_tensor(basis, dtype=dtype, device=self.device)
        self._mean = torch.as_tensor(p["mean_luminance"][:, None, None], dtype=dtype, device=self.device)
        self.info = {"kind": f"{kind}_grating", **_listify(p), "centre_deg": list(centre_deg) if kind == "radial" else None,
                     "angular_speed_deg_s": _listify({"w": p["wavelength_deg"] * p["temporal_freq_hz"]})["w"],
                     "frame_rate_hz": self.rate, "t0_s": self.t0_s, "acceptance": acceptance, "waveform": "sine"}

    def __call__(self, start: int, stop: int) -> Tensor:
        t = self.t0_s + np.arange(start, stop) / self.rate
        wt = 2.0 * math.pi * self.params["temporal_freq_hz"][:, None] * t[None, :] - np.radians(self.params["phase_deg"])[:, None]
        coef = torch.as_tensor(np.stack([np.cos(wt), np.sin(wt)], axis=-1), dtype=self.dtype, device=self.device)
        out = torch.bmm(coef, self._basis).add_(self._mean)                                   # (K, T, n)
        return out if self.trials else out[0]

    def render(self, n_frames: int) -> Tensor:
        """All frames 0…n_frames−1 at once."""
        return self(0, n_frames)


def radial_grating(lattice, n_frames: int, *, temporal_freq_hz=2.0, wavelength_deg=20.0, contrast=0.5,
                   mean_luminance=1.0, phase_deg=0.0, centre_deg=(0.0, 0.0), acceptance: bool = True,
                   frame_rate_hz: float | None = None, t0_s: float = 0.0, dtype=torch.float32, device=None):
    """Concentric sine rings about ``centre_deg`` (az, el) drifting outward (TF > 0) or inward (TF < 0).

    ``L = L₀(1 + C·M·sin(2π δ/λ − 2π·TF·t + φ))`` with δ the angle from the centre: every
    ommatidium pair sees the rings move radially at ``λ·TF`` deg/s, so an expansion
    unit's EMDs all see the same temporal frequency. Returns (luminance, params).
    """
    src = GratingSource(lattice, kind="radial", temporal_freq_hz=temporal_freq_hz, wavelength_deg=wavelength_deg,
                        contrast=contrast, mean_luminance=mean_luminance, phase_deg=phase_deg, centre_deg=centre_deg,
                        acceptance=acceptance, frame_rate_hz=frame_rate_hz, t0_s=t0_s, dtype=dtype, device=device)
    return src.render(n_frames), {**src.info, "n_frames": n_frames}


# --------------------------------------------------------------------------- edges

def moving_edge(lattice, n_frames: int, *, polarity: str = "on", direction_deg=0.0, speed_deg_s=50.0,
                start_deg=None, contrast=1.0, mean_luminance=1.0, acceptance: bool = True,
                frame_rate_hz: float | None = None, t0_s: float = 0.0, dtype=torch.float32, device=None):
    """A straight luminance edge sweeping across the eye at constant angular speed.

    The edge is a meridian of the drum about the axis perpendicular to the motion
    direction θ (the geometry of :mod:`stimuli.gratings`): at time t it lies at drum
    longitude ``ψ_e(t) = start + w·(t − t0)`` (degrees; ψ = azimuth for θ = 0). Behind
    the edge (ψ < ψ_e, the region it has passed) the luminance is ``L₀(1 + C)`` for an
    ON edge and ``L₀(1 − C)`` for an OFF edge; ahead, the opposite. start_deg: default
    just outside the eye on the side the edge comes from. Per-trial sequences allowed
    for direction_deg, speed_deg_s, start_deg, contrast, mean_luminance.
    params["edge_position_deg"] (K, T) is ψ_e at every frame.
    """
    if polarity not in ("on", "off"):
        raise ValueError(f"edge polarity must be 'on' or 'off', got {polarity!r}")
    rate = _rate(lattice, frame_rate_hz)
    p, trials, K = _per_trial(direction_deg=direction_deg, speed_deg_s=speed_deg_s, contrast=contrast,
                              mean_luminance=mean_luminance, start_deg=np.nan if start_deg is None else start_deg)
    psi, beta = drum_coordinates(lattice.directions, p["direction_deg"])                   # (K, n)
    sigma = _sigma(lattice, acceptance)
    margin = 3.0 * math.degrees(sigma) + 1.0
    first = np.degrees(np.where(p["speed_deg_s"] >= 0, psi.min(axis=1), psi.max(axis=1)))
    start = np.where(np.isnan(p["start_deg"]), first - np.sign(p["speed_deg_s"] + 1e-300) * margin, p["start_deg"])
    t = frame_times(n_frames, rate, t0_s)
    pos = start[:, None] + p["speed_deg_s"][:, None] * (t - t0_s)[None, :]               # (K, T) degrees
    # Signed arc distance behind the edge, along the direction of motion (rad).
    dist = (np.radians(pos)[:, :, None] - psi[:, None, :]) * np.cos(beta)[:, None, :]
    dist = dist * np.sign(p["speed_deg_s"] + 1e-300)[:, None, None]
    behind = special.ndtr(dist / sigma) if sigma > 0 else (dist > 0).astype(float)
    sign = 1.0 if polarity == "on" else -1.0
    lum = p["mean_luminance"][:, None, None] * (1.0 + sign * p["contrast"][:, None, None] * (2.0 * behind - 1.0))
    info = {"kind": "moving_edge", "polarity": polarity, **_listify({k: v for k, v in p.items() if k != "start_deg"}),
            "start_deg": _listify({"s": start})["s"], "edge_position_deg": pos if trials else pos[0],
            "frame_rate_hz": rate, "n_frames": n_frames, "t0_s": t0_s, "acceptance": acceptance}
    return _finish(lum, trials, dtype, device), info


# --------------------------------------------------------------------------- looming

def looming_angular_size(t_s, l_over_v_s: float, t_collision_s: float, max_size_deg: float = 180.0) -> np.ndarray:
    """Exact angular size (deg) of an approaching disc: ``2·atan((l/|v|)/(t_c − t))``.

    l: the disc's half-size (radius, m), v: approach speed (m/s), t_c: time of
    collision. Capped at ``max_size_deg`` (and 180° at and after collision).
    """
    t = np.asarray(t_s, dtype=float)
    ttc = t_collision_s - t
    with np.errstate(divide="ignore"):
        size = np.where(ttc > 0, np.degrees(2.0 * np.arctan(l_over_v_s / np.where(ttc > 0, ttc, 1.0))), 180.0)
    return np.minimum(size, max_size_deg)


def looming_disc(lattice, n_frames: int, *, l_over_v_s=0.04, t_collision_s=None, centre_deg=(0.0, 0.0),
                 contrast=1.0, polarity: str = "dark", receding: bool = False, max_size_deg: float = 90.0,
                 mean_luminance=1.0, acceptance: bool = True, frame_rate_hz: float | None = None,
                 t0_s: float = 0.0, dtype=torch.float32, device=None):
    """A disc approaching at constant speed (or receding: the exact time reversal).

    Angular size ``θ(t) = 2·atan((l/|v|)/(t_c − t))`` (:func:`looming_angular_size`),
    l/|v| in seconds (per-trial sequences allowed), capped at ``max_size_deg`` (a
    screen's edge). t_collision_s: default the last frame's time (collision at the end).
    A dark disc has luminance ``L₀(1 − C)`` on a background L₀ (bright: ``L₀(1 + C)``).
    receding: frame k shows the approach's frame T−1−k (the disc shrinks, its edges
    move inward at the mirrored speeds). params["angular_size_deg"] (K, T).
    """
    if polarity not in ("dark", "bright"):
        raise ValueError(f"disc polarity must be 'dark' or 'bright', got {polarity!r}")
    rate = _rate(lattice, frame_rate_hz)
    p, trials, K = _per_trial(l_over_v_s=l_over_v_s, contrast=contrast, mean_luminance=mean_luminance)
    if np.any(p["l_over_v_s"] <= 0):
        raise ValueError(f"l_over_v_s must be positive seconds, got {l_over_v_s}")
    t = frame_times(n_frames, rate, t0_s)
    tc = float(t[-1] if t_collision_s is None else t_collision_s)
    size = np.stack([looming_angular_size(t, lv, tc, max_size_deg) for lv in p["l_over_v_s"]])   # (K, T); K values
    if receding:
        size = size[:, ::-1].copy()
    c = direction_from_angles(*centre_deg)
    delta = _angle_between(lattice.directions, c[None, :])                                   # (n,)
    frac = _disc_fraction(delta[None, None, :], np.radians(size)[:, :, None] / 2.0, _sigma(lattice, acceptance))
    sign = -1.0 if polarity == "dark" else 1.0
    lum = p["mean_luminance"][:, None, None] * (1.0 + sign * p["contrast"][:, None, None] * frac)
    info = {"kind": "looming_disc", "receding": receding, "polarity": polarity, **_listify(p),
            "t_collision_s": tc, "centre_deg": list(centre_deg), "max_size_deg": max_size_deg,
            "angular_size_deg": size if trials else size[0], "frame_rate_hz": rate, "n_frames": n_frames,
            "t0_s": t0_s, "acceptance": acceptance}
    return _finish(lum, trials, dtype, device), info


# --------------------------------------------------------------------------- dot fields

def dot_field(lattice, n_frames: int, *, r_per_s: float = 1.0, epipole_deg=(0.0, 0.0), n_dots: int = 150,
              dot_size_deg: float | None = None, contrast: float = 1.0, lifetime_s: float = 0.25,
              mean_luminance: float = 1.0, seed: int = 0, trials: int | None = None, acceptance: bool = True,
              frame_rate_hz: float | None = None, t0_s: float = 0.0, max_elements: int = 20_000_000,
              dtype=torch.float32, device=None):
    """Expanding (r > 0) or contracting (r < 0) field of limited-lifetime dots: an exact flow field.

    Each dot lives ``lifetime_s`` (ages staggered at random), is born at a uniformly
    random point of the normalised image plane within the disc about the epipole e that
    covers the eye, and moves as forward translation toward a fronto-parallel plane at
    constant r = v/d: ``p(t) = e + (p_birth − e)·exp(r·(t − t_birth))``, so its image
    flow is exactly ``ṗ = r·(p − e)`` (1/s). Dots are Gaussian blobs of FWHM
    ``dot_size_deg`` (default 2Δφ) and peak contrast C (> 0 bright, < 0 dark); blobs add.
    trials: None for one field (T, n), or K independent fields (seeds derived from seed).
    params: "r_per_s", "epipole_deg", dot positions "dot_xy" ((K,) T, N, 2) normalised.
    """
    rate = _rate(lattice, frame_rate_hz)
    if lifetime_s <= 0 or n_dots < 1:
        raise ValueError(f"need lifetime_s > 0 and n_dots >= 1, got {lifetime_s}, {n_dots}")
    size = 2.0 * lattice.dphi_deg if dot_size_deg is None else float(dot_size_deg)
    t = frame_times(n_frames, rate, t0_s)
    e = np.array(angles_to_normalised(*np.radians(epipole_deg)), dtype=float)
    reach = np.linalg.norm(lattice.normalised - e[None, :], axis=1).max() + math.tan(math.radians(2 * size))
    K = 1 if trials is None else int(trials)
    sigma = _sigma(lattice, acceptance)
    lum_all, xy_all = [], []
    for k in range(K):  # independent realisations (a handful), each vectorised over dots and frames
        rng = np.random.default_rng([seed, k])
        age0 = rng.uniform(0.0, lifetime_s, n_dots)
        gens = int(math.ceil((t[-1] - t[0] + lifetime_s) / lifetime_s)) + 1
        rad = reach * np.sqrt(rng.uniform(0.0, 1.0, (gens, n_dots)))
        ang = rng.uniform(0.0, 2.0 * np.pi, (gens, n_dots))
        births = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=-1)                   # (G, N, 2) about e
        life = (t - t0_s)[:, None] + age0[None, :]                                            # (T, N)
        g = np.floor(life / lifetime_s).astype(np.int64)
        since = life - g * lifetime_s
        xy = e + births[g, np.arange(n_dots)[None, :]] * np.exp(r_per_s * since)[..., None]  # (T, N, 2)
        dirs = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        lum = np.empty((n_frames, lattice.n))
        step = max(1, max_elements // (lattice.n * n_dots))
        for i in range(0, n_frames, step):  # frame chunks bound the (T, n, N) distance array
            delta = _angles_to(lattice.directions, dirs[i:i + step])                      # (t, N, n)
            lum[i:i + step] = _blob(delta, size, sigma, "gaussian").sum(-2).numpy()
        lum_all.append(mean_luminance * (1.0 + contrast * lum))
        xy_all.append(xy)
    lum = np.stack(lum_all)
    info = {"kind": "dot_field", "r_per_s": r_per_s, "epipole_deg": list(epipole_deg), "n_dots": n_dots,
            "dot_size_deg": size, "contrast": contrast, "lifetime_s": lifetime_s, "mean_luminance": mean_luminance,
            "seed": seed, "trials": trials, "dot_xy": np.stack(xy_all) if trials is not None else xy_all[0],
            "frame_rate_hz": rate, "n_frames": n_frames, "t0_s": t0_s, "acceptance": acceptance}
    return _finish(lum, trials is not None, dtype, device), info


# --------------------------------------------------------------------------- spots

def moving_spot(lattice, n_frames: int, *, centre_deg=(0.0, 0.0), direction_deg=0.0, speed_deg_s=50.0,
                path_deg=None, t_mid_s=None, size_deg=None, contrast=1.0, shape: str = "gaussian",
                mean_luminance=1.0, acceptance: bool = True, frame_rate_hz: float | None = None,
                t0_s: float = 0.0, dtype=torch.float32, device=None):
    """A small spot moving along a great circle through ``centre_deg`` at constant angular speed.

    The spot passes its path's midpoint ``centre_deg`` = (az, el) at ``t_mid_s``
    (default: the middle frame) moving in image direction ``direction_deg``; it is
    visible only while within ``path_deg``/2 of the midpoint (None: always). Profile:
    Gaussian of FWHM ``size_deg`` (default Δφ) or a disc of that diameter; peak contrast
    C (> 0 bright, < 0 dark). Per-trial sequences: centre_deg as (K, 2), and any of
    direction_deg, speed_deg_s, path_deg, t_mid_s, size_deg, contrast, mean_luminance —
    so K spots of a receptive-field map run as K trials of one batch.
    params["spot_centre_deg"] ((K,) T, 2): the spot's (az, el) at every frame.
    """
    rate = _rate(lattice, frame_rate_hz)
    t = frame_times(n_frames, rate, t0_s)
    cen = np.asarray(centre_deg, dtype=float)
    if cen.shape[-1] != 2 or cen.ndim > 2:
        raise ValueError(f"centre_deg must be (az, el) or (K, 2), got shape {cen.shape}")
    size = lattice.dphi_deg if size_deg is None else size_deg
    p, trials, K = _per_trial(az=cen[..., 0], el=cen[..., 1], direction_deg=direction_deg, speed_deg_s=speed_deg_s,
                              path_deg=np.inf if path_deg is None else path_deg,
                              t_mid_s=t[len(t) // 2] if t_mid_s is None else t_mid_s, size_deg=size,
                              contrast=contrast, mean_luminance=mean_luminance)
    q = direction_from_angles(p["az"], p["el"])                                               # (K, 3)
    east, south = tangent_basis(q)
    th = np.radians(p["direction_deg"])[:, None]
    m = np.cos(th) * east + np.sin(th) * south
    arc = np.radians(p["speed_deg_s"][:, None] * (t[None, :] - p["t_mid_s"][:, None]))      # (K, T)
    c = np.cos(arc)[..., None] * q[:, None, :] + np.sin(arc)[..., None] * m[:, None, :]      # (K, T, 3)
    visible = np.abs(arc) <= np.radians(p["path_deg"])[:, None] / 2.0 + 1e-12
    delta = _angles_to(lattice.directions, c)                                                # (K, T, n)
    prof = _blob(delta, p["size_deg"][:, None, None], _sigma(lattice, acceptance), shape)
    prof.mul_(torch.as_tensor(visible[..., None] * p["contrast"][:, None, None])).add_(1.0)
    lum = prof.mul_(torch.as_tensor(p["mean_luminance"][:, None, None]))
    # Spherical angles (as normalised_to_angles in front, and valid behind the eye).
    az, el = np.arctan2(c[..., 0], c[..., 2]), np.arctan2(c[..., 1], np.hypot(c[..., 0], c[..., 2]))
    track = np.degrees(np.stack([az, el], axis=-1))
    track[~visible] = np.nan
    info = {"kind": "moving_spot", "shape": shape, "centre_deg": cen.tolist(),
            **_listify({k: v for k, v in p.items() if k not in ("az", "el")}),
            "spot_centre_deg": track if trials else track[0], "frame_rate_hz": rate, "n_frames": n_frames,
            "t0_s": t0_s, "acceptance": acceptance}
    return _finish(lum, trials, dtype, device), info


# --------------------------------------------------------------------------- sparse noise

def sparse_noise(lattice, n_frames: int, *, frame_s: float = 0.05, n_spots: int = 1, grid_deg: float | None = None,
                 size_deg: float | None = None, contrast: float = 1.0, mean_luminance: float = 1.0, seed: int = 0,
                 trials: int | None = None, acceptance: bool = True, frame_rate_hz: float | None = None,
                 t0_s: float = 0.0, dtype=torch.float32, device=None):
    """Sparse noise for receptive-field mapping: brief ON/OFF spots at random grid positions.

    Every ``frame_s`` seconds a new noise frame shows ``n_spots`` Gaussian spots (FWHM
    ``size_deg``, default Δφ) centred on random points of an (azimuth, elevation) grid
    of spacing ``grid_deg`` (default Δφ) covering the eye, each ON (+C) or OFF (−C) at
    random, on a background L₀. Seeded: the same seed gives the same sequence.
    params: "onset_s" (F,), "spot_azimuth_deg", "spot_elevation_deg", "polarity"
    ((K,) F, n_spots), "grid_azimuth_deg", "grid_elevation_deg".
    """
    rate = _rate(lattice, frame_rate_hz)
    if frame_s <= 0 or n_spots < 1:
        raise ValueError(f"need frame_s > 0 and n_spots >= 1, got {frame_s}, {n_spots}")
    grid = lattice.dphi_deg if grid_deg is None else float(grid_deg)
    size = lattice.dphi_deg if size_deg is None else float(size_deg)
    t = frame_times(n_frames, rate, t0_s)
    az_g = np.arange(np.ceil(lattice.azimuth_deg.min() / grid), np.floor(lattice.azimuth_deg.max() / grid) + 1) * grid
    el_g = np.arange(np.ceil(lattice.elevation_deg.min() / grid), np.floor(lattice.elevation_deg.max() / grid) + 1) * grid
    frame_idx = np.floor((t - t0_s) / frame_s + 1e-9).astype(np.int64)
    n_noise = int(frame_idx.max()) + 1
    sigma = _sigma(lattice, acceptance)
    K = 1 if trials is None else int(trials)
    lum_all, ev = [], {"spot_azimuth_deg": [], "spot_elevation_deg": [], "polarity": []}
    for k in range(K):  # independent realisations
        rng = np.random.default_rng([seed, k])
        az = az_g[rng.integers(0, len(az_g), (n_noise, n_spots))]
        el = el_g[rng.integers(0, len(el_g), (n_noise, n_spots))]
        pol = rng.choice([-1.0, 1.0], (n_noise, n_spots))
        d = direction_from_angles(az, el)                                                     # (F, S, 3)
        delta = _angles_to(lattice.directions, d)                                            # (F, S, n)
        frames = (torch.as_tensor(pol[:, :, None]) * _blob(delta, size, sigma, "gaussian")).sum(-2).numpy()
        lum_all.append(mean_luminance * (1.0 + contrast * frames[frame_idx]))
        ev["spot_azimuth_deg"].append(az)
        ev["spot_elevation_deg"].append(el)
        ev["polarity"].append(pol)
    ev = {k: (np.stack(v) if trials is not None else v[0]) for k, v in ev.items()}
    info = {"kind": "sparse_noise", "frame_s": frame_s, "n_spots": n_spots, "grid_deg": grid, "size_deg": size,
            "contrast": contrast, "mean_luminance": mean_luminance, "seed": seed, "trials": trials,
            "onset_s": t0_s + np.arange(n_noise) * frame_s, **ev, "grid_azimuth_deg": az_g,
            "grid_elevation_deg": el_g, "frame_rate_hz": rate, "n_frames": n_frames, "t0_s": t0_s,
            "acceptance": acceptance}
    return _finish(np.stack(lum_all), trials is not None, dtype, device), info


# --------------------------------------------------------------------------- 1/f panoramas

def noise_panorama(lattice, n_frames: int = 1, *, exponent: float = 1.0, rms_contrast: float = 0.3,
                   yaw_speed_deg_s: float = 0.0, resolution_deg: float | None = None, mean_luminance: float = 1.0,
                   seed: int = 0, trials: int | None = None, acceptance: bool = True,
                   frame_rate_hz: float | None = None, t0_s: float = 0.0, dtype=torch.float32, device=None):
    """A seeded 1/f^α noise panorama on a cylinder around the fly, optionally rotating in yaw.

    The texture lives on a cylinder (coordinates: drum longitude ψ = atan2(x, z), periodic
    over 360°, and height h = y/√(x² + z²)); its amplitude spectrum is ``|f|^−α``
    (α = 1: natural-scene statistics, Field 1987) with random phases, scaled to
    ``rms_contrast`` before the optics. The ommatidial acceptance multiplies the spectrum
    by ``exp(−2π²σ²|f|²)`` (exact at the equator). Rotation at ``yaw_speed_deg_s``
    (> 0: the pattern moves rightward). Luminance ``L₀(1 + texture)``, floored at 0.
    """
    rate = _rate(lattice, frame_rate_hz)
    res = math.radians(lattice.dphi_deg / 4.0 if resolution_deg is None else resolution_deg)
    sigma = _sigma(lattice, acceptance)
    d = lattice.directions
    psi = np.arctan2(d[:, 0], d[:, 2])
    h = d[:, 1] / np.hypot(d[:, 0], d[:, 2])
    n_psi = int(math.ceil(2.0 * math.pi / res))
    span = 2.0 * (np.abs(h).max() + 6.0 * max(sigma, res) + 0.2)
    n_h = int(math.ceil(span / res))
    dpsi, dh = 2.0 * math.pi / n_psi, span / n_h
    fp = np.fft.fftfreq(n_psi, d=dpsi)
    fh = np.fft.fftfreq(n_h, d=dh)
    f = np.hypot(fh[:, None], fp[None, :])
    amp = np.where(f > 0, np.power(np.where(f > 0, f, 1.0), -exponent), 0.0)
    t = frame_times(n_frames, rate, t0_s)
    K = 1 if trials is None else int(trials)
    out = []
    for k in range(K):  # independent panoramas
        rng = np.random.default_rng([seed, k])
        spec = np.fft.fft2(rng.standard_normal((n_h, n_psi))) * amp
        tex = np.real(np.fft.ifft2(spec))
        scale = rms_contrast / tex.std()
        tex = np.real(np.fft.ifft2(spec * np.exp(-2.0 * math.pi ** 2 * sigma ** 2 * f ** 2))) * scale
        # Bilinear sampling at (ψ − w t, h), periodic in ψ.
        u = ((psi[None, :] - np.radians(yaw_speed_deg_s) * (t - t0_s)[:, None]) / dpsi) % n_psi
        v = (h + span / 2.0) / dh
        i0 = np.floor(u).astype(np.int64)
        j0 = np.floor(v).astype(np.int64)
        fu, fv = u - i0, (v - j0)[None, :]
        # A float's modulo can round up to n_psi itself (e.g. −1e-17 % 288 == 288.0): wrap the index too.
        i0 %= n_psi
        i1 = (i0 + 1) % n_psi
        val = ((1 - fu) * (1 - fv) * tex[j0, i0] + fu * (1 - fv) * tex[j0, i1]
               + (1 - fu) * fv * tex[j0 + 1, i0] + fu * fv * tex[j0 + 1, i1])
        out.append(mean_luminance * np.maximum(1.0 + val, 0.0))
    info = {"kind": "noise_panorama", "exponent": exponent, "rms_contrast": rms_contrast,
            "yaw_speed_deg_s": yaw_speed_deg_s, "resolution_deg": math.degrees(res), "mean_luminance": mean_luminance,
            "seed": seed, "trials": trials, "frame_rate_hz": rate, "n_frames": n_frames, "t0_s": t0_s,
            "acceptance": acceptance}
    return _finish(np.stack(out), trials is not None, dtype, device), info
