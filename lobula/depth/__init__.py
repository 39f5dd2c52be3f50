"""Ranging: dense forward depth from optic flow once the forward velocity is known.

Geometry (see :mod:`lobula.camera`): a pixel has normalised coordinates ``p = (x, y)``;
flow ``ṗ`` is in normalised coordinates per second (1/s), shape ``(2, H, W)`` (channel 0
is x, channel 1 is y). A camera translating with ``t = v·(ex, ey, 1)`` (m/s, camera
frame; ``v`` the forward speed, ``e = (ex, ey)`` the epipole / focus of expansion in
normalised coordinates) sees a static point at forward depth ``d`` (m) move as

    ṗ = (v / d) · (p − e)          (pure translation)

plus, if the camera also rotates with ``ω`` (rad/s, camera frame), the depth-independent
rotational flow (:func:`lobula.epipole.rotational_flow`). ``z = v / d`` (1/s) is the
inverse time to contact. Three estimators are here, each returning a :class:`DepthResult`:

- :func:`depth_ratio` — per-pixel least squares ``z = ⟨ṗ, p−e⟩ / |p−e|²`` then
  ``d = v / z``. Exact for exact translational flow, but 0/0 at the epipole and
  dominated by noise near it; those pixels are marked invalid (NaN), never filled.
- :func:`depth_tv` — the paper's convex fit (FLIVVER eq. for L): fidelity to the
  measured flow plus ``γ·TV(v/d)``, here written directly over the map ``z = v/d``
  with the paper's constant offset β̂ absorbed by measuring ``p`` from the epipole::

      minimise  Σ_pixels |ṗ − z·(p − e)|²  +  γ · Σ_pixels |∇z|

  with ``∇`` the forward-difference gradient in *normalised* image units (pixel
  differences times fx, fy; zero across the last column/row), so that ``γ`` (units
  1/s · normalised length) means the same at any image resolution: the objective divided
  by ``fx·fy`` approximates ``∫|ṗ − z(p−e)|² dA + γ∫|∇z| dA``. The data weight
  ``|p − e|²`` vanishes at the epipole, so there the TV term fills ``z`` in from the
  surroundings instead of dividing noise by zero. Solved by Chambolle–Pock primal–dual
  iterations in torch (CPU or GPU), warm-startable from the previous frame.
- :func:`depth_parallax` — plane+parallax with the *plane at infinity* as reference
  plane: the gyro's rotation is exactly the homography induced by that plane, so
  derotating the flow with it (:func:`derotate_flow`) leaves the pure translational
  parallax, radial from the epipole with magnitude ∝ 1/d, and
  ``d = v·|p−e|² / ⟨ṗ_t, p−e⟩``. With ``dt`` given the flow is treated as a finite
  displacement over ``dt`` and derotated with the finite rotation homography.

Time reference: for flow measured between two frames ``dt`` apart, ``v / z`` is exactly
the depth at the *later* frame for the translational part (the displacement is
``v·dt/(d₀ − v·dt)·(p−e)``); add ``v·dt`` for the depth at the earlier frame. The
depth maps are indexed by the pixel grid the flow is sampled on.

Scoring against exact depth: :func:`depth_metrics` (mean and median AbsRel, RMSE,
RMSE(log), δ<1.25 and coverage, overall and in rings of angular distance from the
epipole) over the pixels :func:`scorable` keeps (exact depth finite and within a stated
range; sky and farther pixels are counted, not scored).

How precise each pixel's flow is, where depth is ill-conditioned, and the rotation a
gyroscope leaves: :mod:`lobula.depth_motion` (``flow_noise``, ``precision_weights`` —
the data weights :func:`depth_tv` takes —, ``translational_snr``, ``refine_motion``).

Every array input may be a numpy array or a torch tensor; outputs come back as the same
kind (torch outputs on the input's device). The ratio and parallax estimators and the scores
compute numpy inputs with numpy, so they run without torch; TV depth needs torch (the ``bio`` extra).

The package, one module per concept: :mod:`lobula.depth.config` (:class:`DepthConfig`,
:class:`DepthResult`), :mod:`lobula.depth.geometry` (offsets and angles from the epipole,
z → d, and the numpy/torch plumbing the estimators share), :mod:`lobula.depth.ratio`,
:mod:`lobula.depth.tv` (the TV solver), :mod:`lobula.depth.parallax` and
:mod:`lobula.depth.scores`; every public name is importable from ``lobula.depth`` itself.
"""
from __future__ import annotations

from .config import DepthConfig, DepthResult
from .geometry import angle_from_epipole, rate_to_depth
from .parallax import depth_parallax, derotate_flow
from .ratio import depth_ratio, radial_rate
from .scores import depth_metrics, error_stats, scorable
from .tv import depth_tv, tv_objective

__all__ = [
    "DepthConfig",
    "DepthResult",
    "angle_from_epipole",
    "radial_rate",
    "rate_to_depth",
    "depth_ratio",
    "tv_objective",
    "depth_tv",
    "derotate_flow",
    "depth_parallax",
    "depth_metrics",
    "scorable",
    "error_stats",
]
