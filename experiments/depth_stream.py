"""Ranging on footage: dense forward depth from v and the flow, streamed pair by pair.

``estimate_depth(footage, run=DepthRunConfig(...))`` runs in two passes:

1. the velocity pipeline (:func:`lobula.velocity.estimate_velocity`) over the whole
   footage gives v̂(t) and the epipole (or pass a velocity Dataset already computed);
2. the footage is read again (:func:`experiments.depth_pairs.ranged_pairs`) and, for every
   N-th staggered flow pair (frame k and k + gap: the *same* pairs and the same flow function
   as the velocity pass), the flow is derotated and turned into depth by :mod:`lobula.depth`
   — the ratio map, the TV fit or plane+parallax — with the pair's speed.

**Geometry, the same as the velocity pass.** The camera's attitude is the integrated,
bias-corrected gyro (:func:`lobula.imu.orientation_from_gyro`, slerped between
samples; causal when the velocity run was), so a pair's rotation is the exact finite
rotation R₀₁ = Q(t0)ᵀ·Q(t1) over its gap, not mean rate × gap. The flow's end points are
turned back into the *first* frame's orientation (:func:`lobula.epipole.derotate_finite`
with the identity at t0: the ratio and TV methods; :func:`lobula.depth.depth_parallax`
undoes the same rotation through the plane-at-infinity homography: the parallax method,
a second implementation that must agree). The epipole is the velocity pass's
gyro-stabilised heading (:class:`lobula.epipole.EpipoleEstimator` with attitude), taken
back into the reference frame with the attitude at the pair's middle, where the velocity
pass saw it, and seen from the camera at the pair's first frame.

**Which frame a depth map refers to.** After derotation into the first frame a static
point at forward depth d₀ moves by v̄·Δt/(d₀ − v̄·Δt)·(p − e), so the fitted rate z gives
v̄/z = d₁ = d₀ − v̄·Δt exactly: the depth at the **first** frame, on its pixel grid, is
``d₀ = v̄/z + v̄·Δt``; its ``time`` is t0, its ``frame`` the first frame's index, and it
is scored against ``depth/NNNNNN.npy`` of that frame. v̄ is, by default, v̂ of the pair
(the readout's estimate for that flow pair, whose time is its middle: v̂(t_mid) = v̄ to
second order); with ``velocity="truth"`` it is the exact mean forward velocity over the
pair from truth.csv, which shows what the geometry gives when the speed is right. The
output's ``velocity_source`` says which.

**Where the flow cannot tell depth.** Each pixel's flow noise σ is estimated from the
flow itself (:func:`lobula.depth_motion.flow_noise`: the component perpendicular to the
epipolar direction). The TV fit weights its data term by the flow's relative precision
1/σ² (:func:`lobula.depth_motion.precision_weights`) and lets the TV term fill in where it is
poor; the ratio and parallax maps report nothing where the translational flow a typical
scene point would make is below ``snr_min``·σ (:func:`lobula.depth_motion.translational_snr`:
σ_d/d ≈ 1/SNR, so SNR 3 is a depth good to about ⅓). What is not known is not guessed:
a pair whose speed is NaN (unobservable) or below ``min_speed_m_s`` gives an all-invalid
map and is not solved; so does a pair whose speed is known only to a relative std
v_std/|v̂| above ``max_scale_rel_std`` (0.2): every pixel shares that scale error, so the
map's metric scale is not known (``metric`` False) — NaN, not confidently wrong.

**Which v̂.** ``lobula depth`` is offline (it reads the footage twice: the velocity pass,
then the ranging), so it uses the velocity pipeline's default zero-phase v̂ (the RTS
smoother): depth inherits v̂'s relative error one to one, and the smoother's error is the
smaller (in the README's velocity suite, causal RMSE is 0.7–3.0× the zero-phase one per
family, 2.6× on ``rotation`` and 3.0× on ``dim``, the two families where depth's scale is
worst). An online user
can pass a causal run with ``--velocity-run``; its larger v_std then masks more maps.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from lobula._optional import is_tensor, optional_torch, require_torch, torch
from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.depth import DepthConfig, DepthResult, depth_parallax, depth_ratio, depth_tv
from lobula.depth_motion import flow_noise, precision_weights, refine_motion, translational_snr
from lobula.epipole import derotate_finite
from lobula.readers.core import Footage, FootageError, footage_provenance

# The pairs of a run live in experiments.depth_pairs; the public ones are named from here as well.
from .depth_pairs import (Pair, attitude_track, depth_flow_fn, flow_config, footage_attitude, frames_averaged,
                          mean_truth_velocity, metric_scale, pair_rotation, ranged_pairs, stabilised_average)

__all__ = ["METHODS", "FOOTAGE_GAMMA", "DepthRunConfig", "Pair", "estimate_depth", "metric_scale", "attitude_track", "pair_rotation",
           "depth_at_first_frame", "ranged_pairs", "depth_flow_fn", "footage_attitude", "flow_config", "mean_truth_velocity", "torch_threads",
           "ring_edges"]

METHODS = ("ratio", "tv", "parallax")
FOOTAGE_GAMMA = 1e-6     # TV weight for dense-flow footage (see DepthRunConfig)


@dataclass
class DepthRunConfig:
    """Settings of a depth run on footage (the solvers' own are in ``depth``).

    method: "ratio" | "tv" | "parallax". every: solve every N-th flow pair (pairs
    k = 0, N, 2N, … by first-frame index; synthetic runs store true depth every 10
    frames, so N = 10 or 5 scores every map or every other). velocity: "estimate" (v̂
    from the velocity pipeline: the default, what a user without ground truth has) or
    "truth" (exact mean forward velocity over each pair from truth.csv; the epipole
    still comes from the velocity pass). epipole: "final" (the velocity pass's last
    running heading, which pools every flow: best for a heading fixed in the world),
    "running" (the heading at the pair's time, causal) or "principal" (the principal
    point, as the paper). min_speed_m_s: pairs slower than this are not ranged (all
    invalid): at 0.03 m/s a 0.2 s pair moves the camera 6 mm, about a pixel of parallax
    at 1 m and 15° from the epipole at 320×240.
    average_frames: half-width k of the gyro-stabilised frame average each flow image is
    made of: frames i−k..i+k, each turned into frame i's orientation by the integrated gyro
    (a pure-rotation homography; the few tenths of a pixel of parallax between neighbours
    stay), then averaged pixel by pixel — the pixel noise of each image falls by √(2k+1)
    while the flow between the two averages still spans the pair (its centre frames). None
    (default): k = 2 with a gyroscope, 0 without (unturned neighbours of a turning camera
    smear the image: median flow error 0.87 px against 0.08 turned, on a development rotation
    scene). Against exact flow on development seeds (100, 101; 160×120, "fine" flow), k = 0 → 2:
    median error 0.30/0.28 → 0.17/0.15 px on ``dim``, 0.05 → 0.05 panels, 0.09 → 0.07 fast,
    0.05 → 0.04 corridor, 0.08 → 0.08 rotation; TV median AbsRel with the exact speed
    (``lobula depth-suite``, the same seeds, 6 s): dim 0.205 → 0.124, panels 0.044 → 0.042,
    corridor 0.033 → 0.031, rotation 0.077 → 0.082 (the one loss: bilinear resampling of
    the turned neighbours). It adds k frames of latency to each map.
    flow: "fine" (default): the depth pass computes its flow with DIS at the "medium"
    preset refined down to full resolution (finest scale 0) — measured against exact
    flow on a development corridor (seed 100, 160×120, 0.2 s pairs): median error
    0.07 px (90th percentile 0.24) against 0.53 (1.44) for the velocity pass's "fast"
    preset, at 15 ms instead of 1 ms a pair; the velocity pass pools thousands of pixels
    per field and can afford the fast flow, a per-pixel depth cannot. "velocity": the
    velocity run's own flow settings. Farneback runs stay Farneback either way.
    refine: estimate per pair the rotation the gyro left (scale-factor and misalignment
    errors: tenths of a degree a pair while turning) jointly with the epipole, started at
    the gyro-stabilised heading (:func:`lobula.depth_motion.refine_motion`); the maps and the
    rings are then about that epipole.
    weighted: TV data term weighted by the flow's relative precision (default) or
    uniform (the paper's). snr_min: ratio and parallax report depth only where the
    predicted translational flow is at least this many flow-noise σ (module doc).
    noise_window_deg: the window (degrees of view) over which σ is estimated locally.
    max_range_m: scores count pixels whose exact depth is within this range (sky and
    farther pixels are counted apart): at 20 m a pair of 0.2 s at 1 m/s moves a point 30°
    from the epipole by about one pixel at 160×120, the flow's noise is a few tenths.
    tv_start: "cold" (each map solved coarse to fine: the default, because it is faster)
    or "warm" (from the previous solved map, z rescaled by the ratio of the speeds, its
    dual and step reused; skips the pyramid).
    device: torch device of the TV solver ("cpu", "cuda"). threads: torch CPU threads
    while solving (1 by default: at 320×240 a second thread on a shared 2-core machine
    made solves 2× slower; 0 leaves torch's setting). batch: maps per Zarr append.
    max_scale_rel_std: the largest relative std of the speed, v_std/|v| (the map's scale
    uncertainty, 1σ), at which a map is still reported in metres. Depth is v times what the
    flow says of 1/d, so a speed known to ±30 % gives every pixel of the map the same ±30 %:
    such a map is *not metric*, and it is reported as unobservable (depth NaN, ``valid``
    False, ``metric`` False) rather than confidently wrong, as v̂ itself is NaN where its
    std exceeds 0.1 m/s. 0.2 (default): a scale good to 20 % at 1σ, i.e. a median scale
    error of about 0.13 — the most a map can carry and still meet a median AbsRel of 0.2
    with the TV fit's own error of about 0.05 beside it (the project's bound on depth maps;
    this is a statement of that bound, not a value fitted to scenes). ``math.inf`` disables it; the
    true speed (``velocity="truth"``) has std 0 and is always metric. A NaN std (a velocity
    run without one) counts as unknown scale, hence not metric, unless the bound is inf.
    depth: the solvers' settings. Its TV weight defaults here to γ = 1e-6, not
    DepthConfig's 1e-4 (tuned on white flow noise of 0.005–0.02 1/s): DIS flow on the
    synthetic track scenes has a robust noise level of 0.001–0.003 1/s, where γ = 1e-4
    blurs the panels' depth edges into the backdrop.
    """

    method: str = "tv"
    every: int = 1
    velocity: str = "estimate"
    epipole: str = "final"
    min_speed_m_s: float = 0.03
    flow: str = "fine"
    average_frames: int | None = None
    refine: bool = True
    weighted: bool = True
    snr_min: float = 3.0
    noise_window_deg: float = 3.0
    max_range_m: float = 20.0
    max_scale_rel_std: float = 0.2
    tv_start: str = "cold"
    device: str = "cpu"
    threads: int = 1
    batch: int = 16
    depth: DepthConfig = field(default_factory=lambda: DepthConfig(gamma=FOOTAGE_GAMMA))

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown depth method {self.method!r}; choose from {', '.join(METHODS)}")
        if int(self.every) < 1:
            raise ValueError(f"every must be a positive number of flow pairs, got {self.every}")
        if self.velocity not in ("estimate", "truth"):
            raise ValueError(f"velocity must be 'estimate' or 'truth', got {self.velocity!r}")
        if self.epipole not in ("final", "running", "principal"):
            raise ValueError(f"epipole must be 'final', 'running' or 'principal', got {self.epipole!r}")
        if self.tv_start not in ("cold", "warm"):
            raise ValueError(f"tv_start must be 'cold' or 'warm', got {self.tv_start!r}")
        if not self.min_speed_m_s >= 0:
            raise ValueError(f"min_speed_m_s must be ≥ 0, got {self.min_speed_m_s}")
        if self.average_frames is not None and int(self.average_frames) < 0:
            raise ValueError(f"average_frames must be ≥ 0 (a half-width in frames) or None, got {self.average_frames}")
        if self.flow not in ("fine", "velocity"):
            raise ValueError(f"flow must be 'fine' or 'velocity', got {self.flow!r}")
        if not self.snr_min >= 0:
            raise ValueError(f"snr_min must be ≥ 0, got {self.snr_min}")
        if not self.noise_window_deg > 0:
            raise ValueError(f"noise_window_deg must be > 0 degrees, got {self.noise_window_deg}")
        if not self.max_range_m > 0:
            raise ValueError(f"max_range_m must be > 0 m, got {self.max_range_m}")
        if not self.max_scale_rel_std > 0:
            raise ValueError(f"max_scale_rel_std must be > 0 (a relative std; inf disables), got "
                             f"{self.max_scale_rel_std}")

    def to_dict(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- one pair
def _invalid(shape, method: str) -> DepthResult:
    nan = np.full(shape, np.nan, np.float32)
    return DepthResult(depth=nan, valid=np.zeros(shape, bool), rate=nan.copy(), method=method)


def _np(a) -> np.ndarray:
    return a.detach().cpu().numpy() if is_tensor(a) else np.asarray(a)


def depth_at_first_frame(flow, camera: PinholeCamera, v: float, epipole, dt: float, method: str,
                         rotation=None, omega=None, init: DepthResult | None = None,
                         config: DepthConfig | None = None, device: str = "cpu", weighted: bool = True,
                         snr_min: float = 3.0, noise_window_deg: float = 3.0, refine: bool = True
                         ) -> tuple[DepthResult, DepthResult | None]:
    """Depth (m) at the *first* frame of a flow pair, on that frame's pixel grid.

    flow: (2, H, W) normalised flow (1/s) = displacement over the pair / dt, as
    measured (rotation included); v: mean forward velocity over the pair (m/s); epipole
    (ex, ey) normalised, the heading seen at the first frame; dt: the pair's gap (s).
    rotation: R₀₁ (3, 3), taking camera vectors at the second frame into the first
    frame's camera frame (from the integrated gyro: Q(t0)ᵀ·Q(t1)); or omega: a constant
    angular velocity (rad/s) over the pair, turned into R₀₁ = exp([ω]×dt); neither: no
    rotation. The derotation is exact (finite rotation, module doc); ``d₀ = v/z + v·dt``.
    refine: then estimate what rotation the gyro left and the epipole from this flow
    (:func:`lobula.depth_motion.refine_motion`, started at ``epipole``); the result's
    ``epipole`` is the one used.
    weighted, snr_min, noise_window_deg: as :class:`DepthRunConfig`. init: a previous TV
    solve for a warm start.

    Returns (result with numpy ``depth``/``valid``/``rate`` at the first frame and the
    per-pixel flow noise in ``sigma``-less form — see :func:`lobula.depth_motion.flow_noise` —,
    the raw TV result for the next warm start or None). v non-finite or 0 gives an
    all-invalid result.
    """
    cfg = config or DepthConfig()
    shape = (camera.height, camera.width)
    if not (math.isfinite(v) and v != 0.0):
        return _invalid(shape, method), None
    if method not in METHODS:
        raise ValueError(f"unknown depth method {method!r}; choose from {', '.join(METHODS)}")
    flow = np.asarray(flow, np.float64)
    if rotation is None and omega is not None:
        rotation = pair_rotation(omega, dt)
    x, y = camera.normalised_grid(np.float64)
    if rotation is not None:
        _, _, ft = derotate_finite(x, y, flow, dt, np.eye(3), np.asarray(rotation, float))
    else:
        ft = flow
    if refine:
        e_ref, dw, ft = refine_motion(ft, camera, epipole)
        epipole = (float(e_ref[0]), float(e_ref[1]))
        # The same residual rotation, composed with the gyro's for the homography route.
        rotation = (np.eye(3) if rotation is None else np.asarray(rotation, float)) @ pair_rotation(dw, dt)
    sigma = flow_noise(ft, camera, epipole, window_deg=noise_window_deg)
    raw = None
    if method == "tv":
        require_torch("TV depth")
        f = torch.as_tensor(ft.astype(np.float32), device=device)
        wts = torch.as_tensor(precision_weights(sigma).astype(np.float32), device=device) if weighted else None
        raw = depth_tv(f, camera, v, epipole, init=init, config=cfg, weights=wts)
        res = raw
        keep = None
    else:
        if method == "ratio":
            res = depth_ratio(ft, camera, v, epipole, config=cfg)
        else:
            # The rotation as the plane-at-infinity homography: a rotation vector over dt.
            gyro = None if rotation is None else Rotation.from_matrix(np.asarray(rotation, float)).as_rotvec() / dt
            res = depth_parallax(flow, camera, v, epipole, gyro=gyro, dt=dt if gyro is not None else None,
                                 config=cfg)
        keep = translational_snr(ft, camera, epipole, sigma) >= snr_min
    d1 = _np(res.depth).astype(np.float64)
    ok = _np(res.valid).astype(bool)
    if keep is not None:
        ok &= keep
    d0 = d1 + v * dt
    ok = ok & np.isfinite(d0) & (d0 > 0) & (d0 <= cfg.max_depth_m)
    depth = np.where(ok, d0, np.nan).astype(np.float32)
    out = DepthResult(depth=depth, valid=ok, rate=_np(res.rate), method=method, iterations=res.iterations,
                      objective=res.objective, converged=res.converged, solve_s=res.solve_s,
                      coarse_iterations=res.coarse_iterations, epipole=tuple(_epipole_pair(epipole)))
    return out, raw


def _epipole_pair(e) -> tuple[float, float]:
    return float(np.asarray(e, float).ravel()[0]), float(np.asarray(e, float).ravel()[1])


# ----------------------------------------------------------------------------- the run
class torch_threads:
    """Context: torch CPU threads set to ``n`` (0: unchanged), restored on exit; nothing without torch
    (then only the ratio and parallax methods run, on numpy)."""

    def __init__(self, n: int):
        self.n, self.old, self.torch = int(n), None, None

    def __enter__(self):
        self.torch = optional_torch() if self.n > 0 else None
        if self.torch is not None:
            self.old = self.torch.get_num_threads()
            self.torch.set_num_threads(self.n)
        return self

    def __exit__(self, *exc):
        if self.old is not None:
            self.torch.set_num_threads(self.old)
        return False


def ring_edges(cfg: DepthConfig) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Ring labels ('all' first) and their lower / upper edges (deg from the epipole)."""
    edges = [float(r) for r in cfg.rings_deg]
    labels = ["all"] + [f"{lo:g}-{hi:g}" for lo, hi in zip(edges[:-1], edges[1:])]
    return labels, np.array([0.0] + edges[:-1]), np.array([180.0] + edges[1:])


_MAPS = ("depth", "valid")  # per-time maps: one compressed chunk per map in the outputs
_STATIC = ("y", "x", "ring", "ring_lo_deg", "ring_hi_deg")  # written once, not appended per batch


def _rescaled(res: DepthResult, factor: float) -> DepthResult:
    """A TV warm start for another speed: z = v/d scales with v (depth changes little between
    nearby maps); the dual, the direction of ∇z, flips sign with it."""
    sign = 1.0 if factor >= 0 else -1.0
    return DepthResult(depth=None, valid=None, rate=res.rate * factor, method=res.method,
                       dual=None if res.dual is None else res.dual * sign, step=res.step)


def _build_dataset(records: list[dict], labels, ring_lo, ring_hi, H: int, W: int, has_truth_v: bool):
    import xarray as xr

    from .depth_score import COUNTS, SCORE_ATTRS, SCORES

    R = len(labels)
    data = dict(
        depth=(("time", "y", "x"), np.stack([r["depth"] for r in records]),
               {"units": "m", "long_name": "forward depth at the pair's first frame (NaN: invalid)"}),
        valid=(("time", "y", "x"), np.stack([r["valid"] for r in records]), {"units": "1", "long_name": "depth is an estimate"}),
        v_used=("time", [r["v_used"] for r in records],
                {"units": "m/s", "long_name": "forward velocity used (mean over the pair)"}),
        v_hat=("time", [r["v_hat"] for r in records], {"units": "m/s", "long_name": "v̂ of the pair"}),
        # Depth is v times what the flow says of 1/d, so v's relative error scales every pixel
        # alike: the map's scale is known to within v_std/|v| (1σ), whatever the solver's own error.
        scale_rel_std=("time", [abs(r["v_std"] / r["v_used"]) if r["v_used"] else np.nan for r in records],
                       {"units": "1", "long_name": "relative std of the map's scale, from the speed used "
                        "(v_std/|v|; 0 with the true speed, NaN when the velocity run gives no std)"}),
        epipole_x=("time", [r["e"][0] for r in records],
                   {"units": "1", "long_name": "epipole seen at the pair's first frame, normalised x"}),
        epipole_y=("time", [r["e"][1] for r in records],
                   {"units": "1", "long_name": "epipole seen at the pair's first frame, normalised y"}),
        ranged=("time", np.array([r["ranged"] for r in records], bool),
                {"units": "1", "long_name": "velocity usable (finite, |v| ≥ min_speed_m_s) and metric: map solved"}),
        metric=("time", np.array([r["metric"] for r in records], bool),
                {"units": "1", "long_name": "the map's scale is known: scale_rel_std ≤ max_scale_rel_std (else the map is "
                 "unobservable: all NaN)"}),
        solve_ms=("time", [r["solve_ms"] for r in records],
                  {"units": "ms", "long_name": "depth solver time for this map (NaN: not solved)"}),
        iterations=("time", np.array([r["iterations"] for r in records], np.int32),
                    {"units": "1", "long_name": "TV iterations at full resolution (−1: none)"}),
        has_true_depth=("time", np.array([r["scores"] is not None for r in records], bool),
                        {"units": "1", "long_name": "exact depth exists for this frame"}),
    )
    if has_truth_v:
        data["v_true"] = ("time", [r["v_true"] for r in records],
                          {"units": "m/s", "long_name": "true mean forward velocity over the pair"})
    for k in SCORES + COUNTS:
        arr = np.full((len(records), R), np.nan)
        for i, r in enumerate(records):
            if r["scores"] is not None:
                arr[i] = [r["scores"][lab][k] for lab in labels]
        data[k] = (("time", "ring"), arr, dict(SCORE_ATTRS[k]))
    coords = dict(
        time=("time", [r["t0"] for r in records], {"units": "s", "long_name": "time of the pair's first frame"}),
        frame=("time", np.array([r["frame"] for r in records], np.int64),
               {"units": "1", "long_name": "index of the pair's first frame (depth/NNNNNN.npy)"}),
        t1=("time", [r["t1"] for r in records], {"units": "s", "long_name": "time of the pair's second frame"}),
        y=("y", np.arange(H), {"units": "1", "long_name": "image row (pixel index, down)"}),
        x=("x", np.arange(W), {"units": "1", "long_name": "image column (pixel index, right)"}),
        ring=("ring", labels, {"long_name": "band of angle from the epipole (deg); 'all' = whole image"}),
        ring_lo_deg=("ring", ring_lo, {"units": "degree", "long_name": "ring's lower angle from the epipole"}),
        ring_hi_deg=("ring", ring_hi, {"units": "degree", "long_name": "ring's upper angle from the epipole "
                                                                      "(exclusive)"}),
    )
    return xr.Dataset(data, coords=coords)


def _run_attrs(footage: Footage, run: DepthRunConfig, velocity, vcfg: VelocityConfig, gyro_used: bool, n_maps: int,
               timings: dict, t_start: float) -> dict:
    """The depth run's attributes: the whole configuration (JSON), where the speed, the epipole and the
    rotation came from, the frames averaged, the masks, ``n_maps`` scored maps, the stages' seconds
    (``timings``), the wall time since ``t_start`` (s, perf_counter) and the footage's provenance."""
    import json

    from .store import provenance

    config = dict(depth_run=run.to_dict(), velocity=json.loads(velocity.attrs["config"]))
    return provenance(
        json.dumps(config, sort_keys=True, default=str),
        method=run.method, front_end=vcfg.front_end,
        velocity_source=("truth: exact mean forward velocity over each pair (truth.csv)"
                         if run.velocity == "truth" else
                         f"estimate: v̂ of the velocity pipeline ({velocity.attrs.get('readout', '?')} readout, "
                         f"{velocity.attrs.get('filter', '?')} filter)"),
        acceleration_source=velocity.attrs.get("acceleration_source", "unknown"),
        epipole_source={"final": "velocity pass, final gyro-stabilised heading, seen at each pair's first frame",
                        "running": "velocity pass, heading at the pair's time, seen at its first frame",
                        "principal": "principal point"}[run.epipole],
        derotation=("gyro: exact finite rotation over each pair from the integrated, bias-corrected gyro, "
                    "into the first frame's orientation" if gyro_used else "none (no gyroscope)"),
        frames_averaged=(f"{2 * frames_averaged(run, footage_attitude(footage, vcfg)) + 1} (frames i-k..i+k "
                         "turned into frame i's orientation by the gyro, then averaged)"),
        depth_reference="first frame of each flow pair: d0 = v/z + v*dt (time = t0, frame = first index)",
        max_range_m=run.max_range_m, max_scale_rel_std=run.max_scale_rel_std,
        near_epipole=("tv: data weighted by the flow's relative precision 1/sigma^2, TV fills in"
                      if run.method == "tv" else
                      f"{run.method}: invalid where predicted translational flow < {run.snr_min:g} sigma"),
        gap_frames=flow_config(vcfg).gap, n_scored_maps=n_maps, device=run.device,
        footage=str(footage.path), footage_kind=footage.kind, notes="; ".join(footage.notes) or "none",
        velocity_config=velocity.attrs["config"],
        timings_s=json.dumps({k: round(v, 4) for k, v in timings.items()}),
        wall_s=round(_time.perf_counter() - t_start, 3), **footage_provenance(footage))


def estimate_depth(footage: Footage, method: str = "tv", every: int = 1,
                   velocity_config: VelocityConfig | None = None, run: DepthRunConfig | None = None,
                   velocity=None, out=None, progress: bool = True):
    """Dense depth over a footage, streamed (see the module doc); returns an xarray Dataset.

    method / every: as :class:`DepthRunConfig` (ignored when ``run`` is given).
    velocity_config: the velocity pipeline's configuration (front end dis or farneback).
    velocity: a velocity Dataset from :func:`lobula.velocity.estimate_velocity` on
    this footage, to skip the first pass (its configuration, in its attrs, then fixes
    the flow). out: None (in-memory Dataset), ``*.nc`` (NetCDF, atomic) or ``*.zarr``
    (Zarr, appended in batches; returns the Dataset opened lazily from the store).

    Output: dims ``time``, ``y``, ``x`` and ``ring``: ``depth`` (m, float32, NaN invalid),
    ``valid``, per time ``v_used``, ``v_hat``, ``v_true`` (with truth), ``epipole_x/y``
    (seen at the first frame), ``ranged``, ``metric`` (the speed's v_std/|v| ≤
    ``run.max_scale_rel_std``: else the map's scale is unknown and the map all NaN),
    ``scale_rel_std``, ``solve_ms``/``iterations`` (TV); with exact
    depth, per time and ring the :mod:`experiments.depth_score` scores and counts, and
    the same pooled over the ranged, scored maps (``pooled_*``, dim ``ring``).
    Attributes: units, the whole configuration (depth run, solvers, velocity pipeline) as
    JSON, ``velocity_source``, ``derotation``, ``max_range_m`` and the provenance.
    """
    # Long by its docstring and its one loop over the pairs, which carries the warm start, the timings and the scores.
    from pathlib import Path

    from tqdm.auto import tqdm

    from lobula.depth import angle_from_epipole, depth_metrics

    from .depth_score import PooledScores, ring_masks
    from .store import MemorySink, ZarrSink
    from lobula.velocity import estimate_velocity

    run = run or DepthRunConfig(method=method, every=every)
    t_start = _time.perf_counter()
    cam = footage.camera
    if out is not None and Path(out).suffix not in (".nc", ".zarr"):
        raise ValueError(f"{out}: the output must end in .nc (NetCDF) or .zarr (Zarr)")
    if run.velocity == "truth" and footage.truth is None:
        raise FootageError(f"{footage.path}: velocity 'truth' needs truth.csv (or the D435i velocity.csv)")
    if velocity is None:
        vcfg = velocity_config or VelocityConfig()
        flow_config(vcfg)                        # reject emd/flo before the long pass
        velocity = estimate_velocity(footage, vcfg, progress=progress)
    if run.velocity == "estimate" and "v_std" not in velocity and math.isfinite(run.max_scale_rel_std):
        raise FootageError(f"the velocity run ({velocity.attrs.get('footage', '?')}) has no v_std, so no map's "
                           "metric scale can be judged; re-run `lobula velocity`, or pass --max-scale-rel-std inf")
    vcfg = VelocityConfig.from_json(velocity.attrs["config"])
    dcfg = run.depth
    labels, ring_lo, ring_hi = ring_edges(dcfg)
    H, W = cam.height, cam.width
    out = Path(out) if out is not None else None
    sink = ZarrSink(out, run.batch, _MAPS, _STATIC) if (out is not None and out.suffix == ".zarr") else MemorySink(_MAPS)
    has_truth_v = footage.truth is not None

    def build(records):
        return _build_dataset(records, labels, ring_lo, ring_hi, H, W, has_truth_v)

    if isinstance(sink, ZarrSink):
        sink.build = build
    timings = dict(read=0.0, flow=0.0, depth=0.0, score=0.0)
    prev_tv, prev_v = None, float("nan")
    pooled = PooledScores(labels, run.max_range_m)
    n_pairs = max(len(footage) - flow_config(vcfg).gap, 0)
    gyro_used = False
    threads = torch_threads(run.threads if run.device == "cpu" else 0)
    threads.__enter__()
    try:
        pairs = ranged_pairs(footage, velocity, run, timings)
        for p in tqdm(pairs, total=math.ceil(n_pairs / int(run.every)), desc=f"depth ({run.method})", unit="map",
                      disable=not progress, leave=False, mininterval=2):
            rec = dict(frame=p.i0, t0=p.t0, t1=p.t1, v_used=p.v, v_hat=p.v_hat, v_std=p.v_std, v_true=p.v_true, e=p.e,
                       ranged=p.ranged, metric=p.metric, solve_ms=float("nan"), iterations=-1, scores=None)
            if p.ranged:
                gyro_used |= p.rotation is not None
                init = _rescaled(prev_tv, p.v / prev_v) if (run.tv_start == "warm" and prev_tv is not None) else None
                td = _time.perf_counter()
                res, raw = depth_at_first_frame(p.flow, cam, p.v, p.e, p.dt, run.method, rotation=p.rotation,
                                                init=init, config=dcfg, device=run.device, weighted=run.weighted,
                                                snr_min=run.snr_min, noise_window_deg=run.noise_window_deg,
                                                refine=run.refine)
                if res.epipole is not None:
                    rec["e"] = res.epipole
                solve = _time.perf_counter() - td
                timings["depth"] += solve
                if raw is not None:
                    prev_tv, prev_v = raw, p.v
                    rec["iterations"] = int(raw.iterations)
                    rec["solve_ms"] = 1e3 * float(raw.solve_s)
                else:
                    rec["solve_ms"] = 1e3 * solve
                depth, valid = res.depth, res.valid
            else:
                depth, valid = np.full((H, W), np.nan, np.float32), np.zeros((H, W), bool)
            rec["depth"], rec["valid"] = depth, valid
            true = footage.depth_map(p.i0)
            if true is not None:
                ts = _time.perf_counter()
                if true.shape != (H, W):
                    raise FootageError(f"{footage.path / 'depth' / f'{p.i0:06d}.npy'}: depth map is "
                                       f"{true.shape[1]}x{true.shape[0]}, the camera {W}x{H}")
                e = rec["e"] if p.ranged else (0.0, 0.0)
                rec["scores"] = depth_metrics(depth, true, valid, e, cam, rings_deg=dcfg.rings_deg,
                                              max_depth_m=run.max_range_m)
                if p.ranged:
                    pooled.add(depth, true, valid, ring_masks(angle_from_epipole(cam, e), labels, ring_lo, ring_hi))
                timings["score"] += _time.perf_counter() - ts
            sink.add(rec)
        extra = pooled.variables() if pooled.n_maps else {}
        attrs = _run_attrs(footage, run, velocity, vcfg, gyro_used, pooled.n_maps, timings, t_start)
        return sink.finish(build, extra, attrs, out)
    except BaseException:
        if isinstance(sink, ZarrSink):
            sink.abort()
        raise
    finally:
        threads.__exit__(None, None, None)
