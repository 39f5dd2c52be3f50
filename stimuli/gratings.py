"""Drifting gratings with exact parameters: on the ommatidial lattice or as camera frames.

A grating is a *drum*: luminance depends only on the longitude ψ about an axis
perpendicular to the direction of motion, and the pattern rotates about that axis at
angular speed ``w = λ·TF`` (deg/s), exactly like a striped cylinder turning around a
tethered fly. For motion direction θ (the direction the stripes move at the optical
axis, in the image: 0° = rightward, 90° = downward since image y points down), the
camera frame is rotated by θ about z and

    ψ = atan2(x', z),  β = asin(y')     with x' = x cos θ + y sin θ, y' = −x sin θ + y cos θ,

so for θ = 0, ψ is the camera's azimuth and β its elevation. The luminance is

    L = L₀ · (1 + C · wave(2π ψ/λ − 2π·TF·t + φ₀)),   wave = sin or sign(sin),

C the Michelson contrast (for the square wave, the contrast of its ±1 levels). The
wavelength is exact along the drum's equator (β = 0); at latitude β a degree of arc
spans 1/cos β degrees of ψ, so the local wavelength is λ·cos β.

Two paths:
- :func:`drifting_grating_lattice` evaluates L directly at the ommatidial axes, optionally
  with the Gaussian acceptance function applied analytically (``acceptance=True``):
  each ommatidium sees a locally plane grating of wavelength λ·cos β blurred by a
  Gaussian of σ = Δρ/2.355, i.e. a sine is attenuated by
  ``exp(−(π Δρ/(λ cos β))² / (4 ln 2))`` and a square wave becomes an exact sum of
  error functions (to first order in Δρ/λ on the sphere).
- :func:`drifting_grating_frames` renders camera frames (pixel centres, optional
  super-sampling) for the through-the-optics path (:meth:`lobula.lattice.Lattice.sample`).

Any of the grating parameters may be a 1-D sequence: they broadcast to K trials and
the output gains a leading trials dim. Time t_k = t0 + k / frame_rate.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from lobula._optional import torch
from lobula.camera import PinholeCamera

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["GratingConfig", "drum_coordinates", "frame_times",
           "drifting_grating_lattice", "drifting_grating_frames"]

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


@dataclass(frozen=True)
class GratingConfig:
    """A drifting grating (degrees, Hz at this user-facing edge).

    direction_deg: motion direction in the image (0 right, 90 down); wavelength_deg: λ;
    temporal_freq_hz: TF (angular speed λ·TF deg/s); contrast: Michelson C in [0, 1];
    mean_luminance: L₀ (any units); phase_deg: φ₀ at t = 0 on ψ = 0; waveform: "sine"
    or "square". Defaults: a 20° sine at 2 Hz, C = 0.5 — around the optimum of the
    fly's optomotor response (Götz 1964; Buchner 1976).
    """

    direction_deg: float = 0.0
    wavelength_deg: float = 20.0
    temporal_freq_hz: float = 2.0
    contrast: float = 0.5
    mean_luminance: float = 1.0
    phase_deg: float = 0.0
    waveform: str = "sine"

    def to_dict(self) -> dict:
        return {k: (np.asarray(v).tolist() if not isinstance(v, str) else v) for k, v in asdict(self).items()}


def frame_times(n_frames: int, frame_rate_hz: float, t0_s: float = 0.0) -> np.ndarray:
    """Frame times t_k = t0 + k / frame_rate (s), shape (n_frames,)."""
    if n_frames < 1 or frame_rate_hz <= 0:
        raise ValueError(f"need n_frames >= 1 and frame_rate_hz > 0, got {n_frames}, {frame_rate_hz}")
    return t0_s + np.arange(n_frames) / float(frame_rate_hz)


def drum_coordinates(directions: np.ndarray, direction_deg) -> tuple[np.ndarray, np.ndarray]:
    """Drum longitude ψ and latitude β (radians) of unit directions (..., 3) for motion direction θ.

    direction_deg: scalar or (K,) array; the output is (..., ) or (K, ...) respectively.
    """
    d = np.asarray(directions, dtype=float)
    th = np.radians(np.asarray(direction_deg, dtype=float))
    c = np.cos(th).reshape(th.shape + (1,) * (d.ndim - 1))
    s = np.sin(th).reshape(th.shape + (1,) * (d.ndim - 1))
    xr = d[..., 0] * c + d[..., 1] * s
    yr = -d[..., 0] * s + d[..., 1] * c
    return np.arctan2(xr, d[..., 2] * np.ones_like(xr)), np.arcsin(np.clip(yr, -1.0, 1.0))


def _params(grating: GratingConfig | None, overrides: dict):
    """Grating parameters as float64 arrays broadcast to (K,), and whether trials were asked for."""
    g = asdict(grating or GratingConfig())
    unknown = set(overrides) - set(g)
    if unknown:
        raise TypeError(f"unknown grating parameter(s) {sorted(unknown)}; known: {sorted(g)}")
    g.update(overrides)
    waveform = g.pop("waveform")
    if waveform not in ("sine", "square"):
        raise ValueError(f"waveform must be 'sine' or 'square', got {waveform!r}")
    arrays = {k: np.asarray(v, dtype=float) for k, v in g.items()}
    for k, v in arrays.items():
        if v.ndim > 1:
            raise ValueError(f"grating parameter {k} must be a scalar or 1-D sequence (trials), got shape {v.shape}")
    trials = any(v.ndim == 1 for v in arrays.values())
    try:
        b = np.broadcast_arrays(*[np.atleast_1d(v) for v in arrays.values()])
    except ValueError:
        raise ValueError("grating parameters given as sequences must all have the same length (one per trial): "
                         + ", ".join(f"{k}: {np.shape(v)}" for k, v in arrays.items())) from None
    p = dict(zip(arrays, b))
    if np.any(p["wavelength_deg"] <= 0):
        raise ValueError(f"wavelength_deg must be positive, got {g['wavelength_deg']}")
    if np.any(p["contrast"] < 0) or np.any(p["contrast"] > 1):
        raise ValueError(f"contrast must be in [0, 1], got {g['contrast']}")
    return p, waveform, trials


def _phase(psi: np.ndarray, p: dict, t: np.ndarray, device, ) -> Tensor:
    """Grating phase (K, T, N), float64 torch, from drum longitude psi (K, N)."""
    psi_t = torch.as_tensor(psi, dtype=torch.float64, device=device)
    k = torch.as_tensor(2.0 * np.pi / np.radians(p["wavelength_deg"]), dtype=torch.float64, device=device)
    wt = torch.as_tensor(2.0 * np.pi * p["temporal_freq_hz"][:, None] * t[None, :] - np.radians(p["phase_deg"])[:, None],
                         dtype=torch.float64, device=device)
    return k[:, None, None] * psi_t[:, None, :] - wt[:, :, None]


def _square_blurred(phase: Tensor, s: Tensor) -> Tensor:
    """sign(sin(phase)) blurred by a Gaussian of s wavelengths (σ/λ; broadcastable); exact in 1-D.

    The ±1 square wave is 2·I − 1 with I the indicator of the half-cycles (k, k + ½)
    (in cycles); its blur is a sum of Φ differences over the few cycles within ±6σ.
    """
    c = torch.remainder(phase / (2.0 * math.pi), 1.0)
    s = torch.clamp(s, min=1e-12)
    reach = int(math.ceil(6.0 * float(s.max()))) + 1
    ind = torch.zeros_like(c)
    for k in range(-reach, reach + 1):  # a handful of neighbouring cycles, not pixels
        ind = ind + torch.special.ndtr((c - k) / s) - torch.special.ndtr((c - k - 0.5) / s)
    return 2.0 * ind - 1.0


def drifting_grating_lattice(lattice, n_frames: int, grating: GratingConfig | None = None, *,
                             acceptance: bool = False, frame_rate_hz: float | None = None, t0_s: float = 0.0,
                             dtype: torch.dtype = torch.float32, device=None, **params) -> Tensor:
    """A drifting grating evaluated at the ommatidial axes of ``lattice``.

    lattice: a :class:`lobula.lattice.Lattice` (its ``directions``, Δρ and camera frame
    rate are used); n_frames: number of frames; grating / params: the grating (any
    parameter may be a (K,) sequence); acceptance: apply the Gaussian acceptance
    function analytically (see the module docstring); frame_rate_hz: default the
    lattice camera's. Returns luminance (n_frames, n) or (K, n_frames, n).
    """
    p, waveform, trials = _params(grating, params)
    rate = lattice.camera.frame_rate_hz if frame_rate_hz is None else frame_rate_hz
    t = frame_times(n_frames, rate, t0_s)
    psi, beta = drum_coordinates(lattice.directions, p["direction_deg"])   # (K, n)
    phase = _phase(psi, p, t, device)
    dev = phase.device
    C = torch.as_tensor(p["contrast"], dtype=torch.float64, device=dev)[:, None, None]
    L0 = torch.as_tensor(p["mean_luminance"], dtype=torch.float64, device=dev)[:, None, None]
    if acceptance:
        # Blur in wavelengths of the local grating: s = σ / (λ cos β).
        sigma = math.radians(lattice.drho_deg) / _FWHM_PER_SIGMA
        lam_local = np.radians(p["wavelength_deg"])[:, None] * np.maximum(np.cos(beta), 1e-9)
        s = torch.as_tensor(sigma / lam_local, dtype=torch.float64, device=dev)[:, None, :]
        if waveform == "sine":
            wave = torch.exp(-2.0 * math.pi ** 2 * s * s) * torch.sin(phase)
        else:
            wave = _square_blurred(phase, s)
    else:
        wave = torch.sin(phase) if waveform == "sine" else torch.sign(torch.sin(phase))
    lum = (L0 * (1.0 + C * wave)).to(dtype)
    return lum if trials else lum[0]


def drifting_grating_frames(camera: PinholeCamera, n_frames: int, grating: GratingConfig | None = None, *,
                            supersample: int = 1, frame_rate_hz: float | None = None, t0_s: float = 0.0,
                            dtype: torch.dtype = torch.float32, device=None, **params) -> Tensor:
    """A drifting grating rendered as camera frames (luminance at the pixels' rays).

    supersample: average ``supersample²`` evenly spaced rays per pixel (a box pixel;
    1 = point samples at pixel centres, which is what the lattice's Gaussian transfer
    assumes). Returns (n_frames, H, W) or (K, n_frames, H, W).
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    p, waveform, trials = _params(grating, params)
    rate = camera.frame_rate_hz if frame_rate_hz is None else frame_rate_hz
    t = frame_times(n_frames, rate, t0_s)
    H, W = camera.height, camera.width
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    acc = None
    for ov in offsets:          # supersample² sub-pixel grids, each vectorised over pixels
        for ou in offsets:
            x = (np.arange(W) + ou - camera.cx) / camera.fx
            y = (np.arange(H) + ov - camera.cy) / camera.fy
            xx, yy = np.meshgrid(x, y)
            rays = np.stack([xx, yy, np.ones_like(xx)], axis=-1).reshape(-1, 3)
            rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
            psi, _ = drum_coordinates(rays, p["direction_deg"])         # (K, H·W)
            phase = _phase(psi, p, t, device)
            wave = torch.sin(phase) if waveform == "sine" else torch.sign(torch.sin(phase))
            acc = wave if acc is None else acc + wave
    dev = acc.device
    C = torch.as_tensor(p["contrast"], dtype=torch.float64, device=dev)[:, None, None]
    L0 = torch.as_tensor(p["mean_luminance"], dtype=torch.float64, device=dev)[:, None, None]
    lum = (L0 * (1.0 + C * acc / supersample ** 2)).to(dtype).reshape(-1, n_frames, H, W)
    return lum if trials else lum[0]
