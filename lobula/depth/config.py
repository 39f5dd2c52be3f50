"""What the depth estimators take and return: :class:`DepthConfig`, their settings, and
:class:`DepthResult`, a depth map with its solver's diagnostics.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass(frozen=True)
class DepthConfig:
    """Settings of the depth estimators (units in the names).

    min_radius_deg: pixels whose ray is within this angle of the epipole's ray are
        invalid for the ratio and parallax methods (there ``r`` is 0/0).
    max_depth_m: depths beyond this (|z| too small to distinguish from zero) are marked
        invalid rather than reported as enormous numbers.
    gamma: TV weight γ in 1/s · (normalised image length); see :func:`depth_tv`.
        Larger γ suppresses more flow noise but biases z toward its surroundings where
        the data weight |p−e|² is small (a region of radius ρ around the epipole is
        pulled by about γ·perimeter / Σ|p−e|², ∝ γ/ρ²). The default is chosen on
        synthetic scenes at 160×120–320×240 with flow noise 0.005–0.02 1/s (AbsRel
        within 5–10° of the epipole ≈ 0.05–0.09 where the ratio map gives 0.2–1).
    tv_iters: iteration cap of the TV solver at full resolution (each pyramid level of a
        cold start has the same cap).
    tv_tol: the solver stops when its primal and dual residuals, relative to the size of
        the terms they balance, are both below this. 3e-3 leaves z within ≈ 0.2 % RMS
        of the exact optimum (far below the depth error from flow noise); use ≤ 1e-4
        to compare with a reference solver.
    tv_check_every: iterations between residual checks (each costs about one iteration).
    tv_pyramid_min_size: a cold start solves on 2× coarser grids down to this many
        pixels on the short side.
    rings_deg: ring edges (degrees from the epipole) for :func:`depth_metrics`.
    """

    min_radius_deg: float = 2.0
    max_depth_m: float = 100.0
    gamma: float = 1e-4
    tv_iters: int = 1000
    tv_tol: float = 3e-3
    tv_check_every: int = 10
    tv_pyramid_min_size: int = 16
    rings_deg: tuple = (0.0, 5.0, 10.0, 20.0, 90.0)

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


@dataclass
class DepthResult:
    """Output of a depth estimator (arrays as numpy or torch, following the input).

    depth: (H, W) forward depth d (m), NaN where invalid.
    valid: (H, W) bool, True where ``depth`` is an estimate.
    rate: (H, W) the fitted ``z = v/d`` (1/s) before inversion (NaN where undefined).
    method: "ratio", "tv" or "parallax".
    iterations, objective, converged, solve_s: TV solver diagnostics — full-resolution
        iterations, objective as in :func:`tv_objective` ((1/s)²), whether the tolerance was
        met, seconds spent (s); None for the closed-form methods.
    coarse_iterations: TV cold start: iterations on each pyramid level, coarsest first
        (each costs about a quarter of the one above); () for a warm start.
    epipole: the epipole (ex, ey), normalised, the map was computed with, when the caller refined it
        (:func:`refine_motion`); None otherwise.
    dual, step: the TV solver's dual variable ((2, H, W), in γ's units) and its adapted primal
        step τ (a float, 1/(normalised length)²), for warm starts (pass the whole result as ``init``
        to :func:`depth_tv`); None otherwise.
    """

    depth: object
    valid: object
    rate: object
    method: str
    iterations: int | None = None
    objective: float | None = None
    converged: bool | None = None
    solve_s: float | None = None
    dual: object = field(default=None, repr=False)
    step: float | None = None
    coarse_iterations: tuple = ()
    epipole: tuple | None = None
