"""Ranging on footage: dense forward depth from v̂ and the flow, streamed, scored, stored.

``estimate_depth(footage, method, every=N)`` runs in two passes:

1. the velocity pipeline (:func:`experiments.velocity.estimate_velocity`) over the whole
   footage gives v̂(t) and the epipole (or pass a velocity Dataset already computed);
2. the footage is read again and, for every N-th staggered flow pair (frame k and
   k + gap, the *same* pairs and the same flow function as the velocity pass), the
   flow is derotated with the gyro (when there is an IMU) and turned into depth by
   :mod:`lobula.depth` — the ratio map, the TV fit (warm-started from the previous
   solved pair) or plane+parallax — with v̂ of that pair.

**Which frame a depth map refers to.** A pair's flow is the finite displacement over
Δt = t1 − t0 divided by Δt; a static point at forward depth d₀ at t0 is at
d₁ = d₀ − s at t1, with s = v̄·Δt the travel (v̄ the mean forward velocity over the
pair). For translational flow the fitted rate z satisfies v̄/z = d₁ exactly, so the
depth at the pair's **first** frame — on that frame's pixel grid, where the flow is
sampled — is ``d₀ = v̄/z + v̄·Δt``. Every map here is that first-frame depth, its
``time`` is t0 and its ``frame`` is the first frame's index, and it is scored against
``depth/NNNNNN.npy`` of that frame index (the exact forward depth at frame N). v̄ is v̂
of the pair (the readout's estimate for the flow of that pair, which belongs to its
middle: v̂(t_mid) = v̄ to second order), or with ``velocity="truth"`` the exact mean
velocity over the pair from truth.csv.

**What is not known is not guessed.** A pair whose velocity is NaN (unobservable) or
slower than ``min_speed_m_s`` (no usable parallax: at rest the flow is noise) gives an
all-invalid map (depth NaN, valid False), and is not solved.

Rotation: ratio and TV use the flow derotated as the velocity pass does it
(:func:`lobula.epipole.derotate` with :func:`lobula.epipole.mean_angular_velocity`, the
instantaneous model); parallax takes the raw flow and undoes the mean gyro rotation over
the pair exactly, with the plane-at-infinity homography (:func:`lobula.depth.depth_parallax`
with ``dt``). Without an IMU the three see the same flow and parallax equals ratio.

Output (xarray Dataset, dims ``time``, ``y``, ``x``, and ``ring`` for scores):
``depth`` (m, float32, NaN invalid), ``valid`` (bool), per time ``v_used``, ``v_hat``,
``v_true`` (when truth exists), ``epipole_x/y``, ``ranged`` (velocity usable),
``solve_ms``/``iterations`` (TV); when true depth exists, per time and ring
``abs_rel``, ``rmse_m``, ``delta_1_25``, ``valid_fraction``, ``n_valid``, ``n_true``, and
the same pooled over the ranged, scored maps (``pooled_*``, dim ``ring``). Rings are
bands of angle between a pixel's ray and the epipole's ray (:func:`lobula.depth.depth_metrics`);
ring ``all`` is the whole image. Attributes: units, the whole configuration (depth run,
depth solvers, velocity pipeline) as JSON and the package version
(:func:`experiments.store.provenance`).

Memory: flows are never accumulated (two frames are held at a time). A NetCDF output
holds the selected maps in memory until the atomic write (5 bytes per pixel per map:
choose ``every`` for long runs); a ``.zarr`` output is appended to on disk in batches
(bounded memory whatever the length) inside a temporary directory renamed into place
when complete.
"""
from __future__ import annotations

import argparse
import json
import math
import time as _time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import xarray as xr
from tqdm.auto import tqdm

from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.depth import DepthConfig, DepthResult, depth_metrics, depth_parallax, depth_ratio, depth_tv
from lobula.epipole import EpipoleEstimator, derotate, mean_angular_velocity
from lobula.flow import FlowConfig, make_flow_fn, pixel_to_angular
from stimuli.footage import FloUnits, Footage, FootageError, read_frame

from .store import MemorySink, ZarrSink, provenance, save_figure, write_netcdf

__all__ = ["METHODS", "DepthRunConfig", "depth_at_first_frame", "estimate_depth", "pooled_scores",
           "format_scores", "plot_depth", "depth_flo_pair", "plot_flo_pair", "add_parser", "run_depth"]

METHODS = ("ratio", "tv", "parallax")
FOOTAGE_GAMMA = 1e-6     # TV weight for dense-flow footage (see DepthRunConfig)
_MAPS = ("depth", "valid")  # per-time maps: one compressed chunk per map in the outputs
_STATIC = ("y", "x", "ring", "ring_lo_deg", "ring_hi_deg")  # written once, not appended per batch
_SCORES = ("abs_rel", "rmse_m", "delta_1_25", "valid_fraction")
_SCORE_ATTRS = dict(abs_rel=dict(units="1", long_name="mean |d̂ − d| / d over pixels valid in both"),
                    rmse_m=dict(units="m", long_name="root mean square depth error"),
                    delta_1_25=dict(units="1", long_name="fraction with max(d̂/d, d/d̂) < 1.25"),
                    valid_fraction=dict(units="1", long_name="valid pixels / pixels with true depth"),
                    n_valid=dict(units="1", long_name="pixels valid in both estimate and truth"),
                    n_true=dict(units="1", long_name="pixels with true depth"))


@dataclass
class DepthRunConfig:
    """Settings of a depth run on footage (the solvers' own are in ``depth``).

    method: "ratio" | "tv" | "parallax". every: solve every N-th flow pair (pairs
    k = 0, N, 2N, … by first-frame index; synthetic runs store true depth every 10
    frames, so N = 10 or 5 scores every map or every other). velocity: "estimate" (v̂
    from the velocity pipeline) or "truth" (exact mean forward velocity over each pair
    from truth.csv; the epipole still comes from the velocity pass). epipole: "final"
    (the velocity pass's last running estimate, which pools every flow: best for a
    camera mounted at a fixed angle), "running" (the estimate at the pair's time,
    causal) or "principal" (the principal point, as the paper). min_speed_m_s: pairs
    slower than this are not ranged (all invalid): at 0.03 m/s a 0.2 s pair moves the
    camera 6 mm, about a pixel of parallax at 1 m and 15° from the epipole at 320×240.
    tv_start: "cold" (each map solved coarse to fine: the default, because it is faster)
    or "warm" (from the previous solved map, z rescaled by the ratio of the speeds, its
    dual and step reused; skips the pyramid). Measured on a 320×240 synthetic run with
    DIS flow, one thread: cold ≈ 170–180 full-resolution iterations + a 3-level pyramid,
    75–90 ms; warm from the adjacent pair 470 iterations, 140 ms; from 10 pairs back
    600–670, 180–200 ms — the warm start fixes the low frequencies but the new flow's
    noise differs everywhere, and at full resolution that settles slowly.
    device: torch device of the TV solver ("cpu", "cuda"). threads: torch CPU threads
    while solving (1 by default: at 320×240 a second thread on a shared 2-core machine
    made solves 2× slower and sometimes 100× slower; 0 leaves torch's setting).
    batch: maps per Zarr append.
    depth: the solvers' settings. Its TV weight defaults here to γ = 1e-6, not
    DepthConfig's 1e-4: that one was tuned on white flow noise of 0.005–0.02 1/s, while
    DIS flow on the synthetic track scenes has a robust noise level (the flow component
    perpendicular to the epipolar direction, pure noise under translation) of
    0.001–0.003 1/s, and there γ = 1e-4 blurs the panels' depth edges into the backdrop
    (AbsRel 0.31 within 5° of the epipole against 0.26 for the ratio map, DIS "fast",
    320×240, true v), whereas γ = 1e-6 gives 0.23 with every pixel valid and equals the
    ratio map elsewhere (γ = 3e-7…3e-6 within ±0.02 of that; DIS "medium" likewise).
    """

    method: str = "tv"
    every: int = 1
    velocity: str = "estimate"
    epipole: str = "final"
    min_speed_m_s: float = 0.03
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

    def to_dict(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- one pair
def _invalid(shape, method: str) -> DepthResult:
    nan = np.full(shape, np.nan, np.float32)
    return DepthResult(depth=nan, valid=np.zeros(shape, bool), rate=nan.copy(), method=method)


def _rescaled(res: DepthResult, factor: float) -> DepthResult:
    """A TV warm start for another speed: z = v/d scales with v (depth changes little between
    nearby maps); the dual, the direction of ∇z, flips sign with it."""
    sign = 1.0 if factor >= 0 else -1.0
    return DepthResult(depth=None, valid=None, rate=res.rate * factor, method=res.method,
                       dual=None if res.dual is None else res.dual * sign, step=res.step)


def depth_at_first_frame(flow, camera: PinholeCamera, v: float, epipole, dt: float, method: str,
                         omega=None, init: DepthResult | None = None, config: DepthConfig | None = None,
                         device: str = "cpu") -> tuple[DepthResult, DepthResult | None]:
    """Depth (m) at the *first* frame of a flow pair, on that frame's pixel grid.

    flow: (2, H, W) normalised flow (1/s) = displacement over the pair / dt; v: mean
    forward velocity over the pair (m/s); epipole (ex, ey) normalised; dt: the pair's
    gap (s); omega: mean angular velocity over the pair (rad/s, camera frame) or None.
    The translational fit gives v/z = d₁ (the later frame); ``d₀ = v/z + v·dt``
    (module doc). init: a previous TV solve for a warm start.

    Returns (result with numpy ``depth``/``valid`` at the first frame, the raw TV result
    for the next warm start or None). v non-finite or 0 gives an all-invalid result.
    """
    cfg = config or DepthConfig()
    shape = (camera.height, camera.width)
    if not (math.isfinite(v) and v != 0.0):
        return _invalid(shape, method), None
    raw = None
    if method in ("ratio", "tv") and omega is not None:
        x, y = camera.normalised_grid()
        flow = derotate(np.asarray(flow), np.asarray(omega, float), x, y)
    if method == "ratio":
        res = depth_ratio(np.asarray(flow), camera, v, epipole, config=cfg)
    elif method == "parallax":
        res = depth_parallax(np.asarray(flow), camera, v, epipole, gyro=omega,
                             dt=dt if omega is not None else None, config=cfg)
    elif method == "tv":
        f = torch.as_tensor(np.asarray(flow, dtype=np.float32), device=device)
        raw = depth_tv(f, camera, v, epipole, init=init, config=cfg)
        res = raw
    else:
        raise ValueError(f"unknown depth method {method!r}; choose from {', '.join(METHODS)}")
    d1 = res.depth.detach().cpu().numpy() if isinstance(res.depth, torch.Tensor) else np.asarray(res.depth)
    ok = res.valid.detach().cpu().numpy() if isinstance(res.valid, torch.Tensor) else np.asarray(res.valid)
    d0 = d1.astype(np.float64) + v * dt
    ok = ok & np.isfinite(d0) & (d0 > 0) & (d0 <= cfg.max_depth_m)
    depth = np.where(ok, d0, np.nan).astype(np.float32)
    rate = res.rate.detach().cpu().numpy() if isinstance(res.rate, torch.Tensor) else np.asarray(res.rate)
    out = DepthResult(depth=depth, valid=ok, rate=rate, method=method, iterations=res.iterations,
                      objective=res.objective, converged=res.converged, solve_s=res.solve_s,
                      coarse_iterations=res.coarse_iterations)
    return out, raw


# ----------------------------------------------------------------------------- helpers
def _at(times: np.ndarray, values: np.ndarray, t: float) -> float:
    """values at t: the sample itself when t is a sample time, else linear between the two
    neighbours (NaN if either is NaN or t is outside)."""
    k = int(np.searchsorted(times, t))
    for j in (k - 1, k):
        if 0 <= j < len(times) and abs(times[j] - t) < 1e-6:
            return float(values[j])
    if k == 0 or k >= len(times):
        return float("nan")
    a, b = values[k - 1], values[k]
    w = (t - times[k - 1]) / (times[k] - times[k - 1])
    return float(a + w * (b - a))


def _mean_truth_velocity(truth: dict, t0: float, t1: float) -> float:
    """Mean forward (camera-axis) velocity over [t0, t1] from truth: the trapezoid integral of
    ``v_forward_m_s`` (not ``position_m``, which is along the track and differs off-axis).
    NaN outside the truth's time span."""
    tt = truth["time_s"]
    if t0 < tt[0] - 1e-6 or t1 > tt[-1] + 1e-6:
        return float("nan")
    inside = (tt > t0) & (tt < t1)
    g = np.concatenate([[t0], tt[inside], [t1]])
    v = np.interp(g, tt, truth["v_forward_m_s"])
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(g)) / (t1 - t0))


def _flow_config(vel_cfg: VelocityConfig) -> FlowConfig:
    if vel_cfg.front_end not in ("dis", "farneback"):
        raise ValueError(f"depth needs a dense flow front end (dis or farneback); the velocity run used "
                         f"{vel_cfg.front_end!r}")
    fc = FlowConfig(**vel_cfg.flow.to_dict())
    fc.method = vel_cfg.front_end
    return fc


class _FrameReader:
    """Reads single frames by index, keeping the ``keep`` most recently used (pairs overlap)."""

    def __init__(self, footage: Footage, keep: int = 2):
        from collections import OrderedDict

        self.footage, self.keep, self.cache = footage, max(2, keep), OrderedDict()
        self.read_s = 0.0

    def __call__(self, i: int) -> np.ndarray:
        if i in self.cache:
            self.cache.move_to_end(i)
            return self.cache[i]
        t0 = _time.perf_counter()
        _, _, img = next(self.footage.frames(i, i + 1))
        self.read_s += _time.perf_counter() - t0
        self.cache[i] = img
        while len(self.cache) > self.keep:
            self.cache.popitem(last=False)
        return img


class _torch_threads:
    """Context: torch CPU threads set to ``n`` (0: unchanged), restored on exit."""

    def __init__(self, n: int):
        self.n, self.old = int(n), None

    def __enter__(self):
        if self.n > 0:
            self.old = torch.get_num_threads()
            torch.set_num_threads(self.n)
        return self

    def __exit__(self, *exc):
        if self.old is not None:
            torch.set_num_threads(self.old)
        return False


def _rings(cfg: DepthConfig) -> tuple[list[str], np.ndarray, np.ndarray]:
    edges = [float(r) for r in cfg.rings_deg]
    labels = ["all"] + [f"{lo:g}-{hi:g}" for lo, hi in zip(edges[:-1], edges[1:])]
    lo = np.array([0.0] + edges[:-1])
    hi = np.array([180.0] + edges[1:])
    return labels, lo, hi


# ----------------------------------------------------------------------------- the run
def estimate_depth(footage: Footage, method: str = "tv", every: int = 1,
                   velocity_config: VelocityConfig | None = None, run: DepthRunConfig | None = None,
                   velocity: xr.Dataset | None = None, out: str | Path | None = None,
                   progress: bool = True) -> xr.Dataset:
    """Dense depth over a footage, streamed (see the module doc).

    method / every: as :class:`DepthRunConfig` (ignored when ``run`` is given).
    velocity_config: the velocity pipeline's configuration (front end dis or farneback).
    velocity: a velocity Dataset from :func:`experiments.velocity.estimate_velocity` on
    this footage, to skip the first pass (its configuration, in its attrs, then fixes
    the flow). out: None (in-memory Dataset), ``*.nc`` (NetCDF, atomic) or ``*.zarr``
    (Zarr, appended in batches; returns the Dataset opened lazily from the store).
    """
    from .velocity import estimate_velocity

    run = run or DepthRunConfig(method=method, every=every)
    t_start = _time.perf_counter()
    cam = footage.camera
    if out is not None and Path(out).suffix not in (".nc", ".zarr"):
        raise ValueError(f"{out}: the output must end in .nc (NetCDF) or .zarr (Zarr)")
    if run.velocity == "truth" and footage.truth is None:
        raise FootageError(f"{footage.path}: velocity 'truth' needs truth.csv (or the D435i velocity.csv)")
    if velocity is None:
        vcfg = velocity_config or VelocityConfig()
        _flow_config(vcfg)                       # reject emd/flo before the long pass
        velocity = estimate_velocity(footage, vcfg, progress=progress)
    vcfg = VelocityConfig.from_json(velocity.attrs["config"])
    fcfg = _flow_config(vcfg)
    vt = velocity.time.values
    v_hat_all = velocity.v_hat.values.astype(float)
    if "observable" in velocity:
        v_hat_all = np.where(velocity.observable.values.astype(bool), v_hat_all, np.nan)
    ex_all, ey_all = velocity.epipole_x.values, velocity.epipole_y.values
    stamp_mid = vcfg.timestamps == "mid"

    gap = fcfg.gap
    n_pairs = len(footage) - gap
    if n_pairs < 1:
        raise FootageError(f"{footage.path}: too few frames for a flow pair ({len(footage)} frames, gap {gap})")
    t_all = np.asarray(footage.times, float)
    stamps = 0.5 * (t_all[:n_pairs] + t_all[gap:]) if stamp_mid else t_all[:n_pairs]
    if len(vt) != n_pairs or not np.allclose(vt, stamps, atol=1e-4):
        raise FootageError(f"the velocity run ({velocity.attrs.get('footage', '?')}: {len(vt)} pairs, "
                           f"{vt[0] if len(vt) else float('nan'):.3f}..{vt[-1] if len(vt) else float('nan'):.3f} s) "
                           f"does not match {footage.path} ({n_pairs} pairs of gap {gap}, {stamps[0]:.3f}.."
                           f"{stamps[-1]:.3f} s); estimate velocity on this footage, or leave --velocity-run out")
    starts = list(range(0, n_pairs, int(run.every)))
    flow_fn = make_flow_fn(fcfg)
    read = _FrameReader(footage, keep=gap + 2)
    gyro = footage.imu.gyro if (vcfg.derotate and footage.imu is not None and footage.imu.gyro is not None) else None
    dcfg = run.depth
    labels, ring_lo, ring_hi = _rings(dcfg)
    H, W = cam.height, cam.width
    out = Path(out) if out is not None else None
    sink = ZarrSink(out, run.batch, _MAPS, _STATIC) if (out is not None and out.suffix == ".zarr") else MemorySink(_MAPS)
    has_truth_v = footage.truth is not None

    def build(records: list[dict]) -> xr.Dataset:
        R = len(labels)
        data = dict(
            depth=(("time", "y", "x"), np.stack([r["depth"] for r in records]),
                   {"units": "m", "long_name": "forward depth at the pair's first frame (NaN: invalid)"}),
            valid=(("time", "y", "x"), np.stack([r["valid"] for r in records]),
                   {"long_name": "depth is an estimate"}),
            v_used=("time", [r["v_used"] for r in records],
                    {"units": "m/s", "long_name": "forward velocity used (mean over the pair)"}),
            v_hat=("time", [r["v_hat"] for r in records], {"units": "m/s", "long_name": "v̂ of the pair"}),
            epipole_x=("time", [r["e"][0] for r in records], {"units": "1", "long_name": "epipole, normalised x"}),
            epipole_y=("time", [r["e"][1] for r in records], {"units": "1", "long_name": "epipole, normalised y"}),
            ranged=("time", np.array([r["ranged"] for r in records], bool),
                    {"long_name": "velocity usable (finite, |v| ≥ min_speed_m_s): map solved"}),
            solve_ms=("time", [r["solve_ms"] for r in records],
                      {"units": "ms", "long_name": "depth solver time for this map (NaN: not solved)"}),
            iterations=("time", np.array([r["iterations"] for r in records], np.int32),
                        {"long_name": "TV iterations at full resolution (−1: none)"}),
            has_true_depth=("time", np.array([r["scores"] is not None for r in records], bool),
                            {"long_name": "exact depth exists for this frame"}),
        )
        if has_truth_v:
            data["v_true"] = ("time", [r["v_true"] for r in records],
                              {"units": "m/s", "long_name": "true mean forward velocity over the pair"})
        for k in _SCORES + ("n_valid", "n_true"):
            arr = np.full((len(records), R), np.nan)
            for i, r in enumerate(records):
                if r["scores"] is not None:
                    arr[i] = [r["scores"][lab][k] for lab in labels]
            data[k] = (("time", "ring"), arr, dict(_SCORE_ATTRS[k]))
        coords = dict(
            time=("time", [r["t0"] for r in records], {"units": "s", "long_name": "time of the pair's first frame"}),
            frame=("time", np.array([r["frame"] for r in records], np.int64),
                   {"long_name": "index of the pair's first frame (depth/NNNNNN.npy)"}),
            t1=("time", [r["t1"] for r in records], {"units": "s", "long_name": "time of the pair's second frame"}),
            y=("y", np.arange(H), {"units": "pixel"}), x=("x", np.arange(W), {"units": "pixel"}),
            ring=("ring", labels, {"long_name": "band of angle from the epipole (deg); 'all' = whole image"}),
            ring_lo_deg=("ring", ring_lo, {"units": "deg"}), ring_hi_deg=("ring", ring_hi, {"units": "deg"}),
        )
        return xr.Dataset(data, coords=coords)

    if isinstance(sink, ZarrSink):
        sink.build = build
    timings = dict(read=0.0, flow=0.0, depth=0.0, score=0.0)
    prev_tv: DepthResult | None = None
    prev_v = float("nan")
    pooled_acc = {lab: dict(n_valid=0, n_true=0, ae=0.0, se=0.0, dl=0.0) for lab in labels}
    n_scored = 0
    threads = _torch_threads(run.threads if run.device == "cpu" else 0)
    threads.__enter__()
    try:
        for k in tqdm(starts, desc=f"depth ({run.method})", unit="map", disable=not progress, leave=False,
                      mininterval=2):
            i0, i1 = k, k + gap
            t0, t1 = float(footage.times[i0]), float(footage.times[i1])
            dt = t1 - t0
            stamp = 0.5 * (t0 + t1) if stamp_mid else t0
            v_hat = _at(vt, v_hat_all, stamp)
            v_true = _mean_truth_velocity(footage.truth, t0, t1) if has_truth_v else float("nan")
            v = v_true if run.velocity == "truth" else v_hat
            if run.epipole == "final":
                e = (float(ex_all[-1]), float(ey_all[-1]))
            elif run.epipole == "running":
                e = (_at(vt, ex_all, stamp), _at(vt, ey_all, stamp))
            else:
                e = (0.0, 0.0)
            ranged = bool(math.isfinite(v) and abs(v) >= run.min_speed_m_s and all(map(math.isfinite, e)))
            rec = dict(frame=i0, t0=t0, t1=t1, v_used=v, v_hat=v_hat, v_true=v_true, e=e, ranged=ranged,
                       solve_ms=float("nan"), iterations=-1, scores=None)
            if ranged:
                r0 = read.read_s
                a, b = read(i0), read(i1)
                t_flow = _time.perf_counter()
                timings["read"] += read.read_s - r0
                flow = pixel_to_angular(flow_fn(a, b), cam, dt)
                timings["flow"] += _time.perf_counter() - t_flow
                omega = mean_angular_velocity(footage.imu.time_s, gyro, t0, t1) if gyro is not None else None
                init = None
                if run.tv_start == "warm" and prev_tv is not None:
                    init = _rescaled(prev_tv, v / prev_v)
                td = _time.perf_counter()
                res, raw = depth_at_first_frame(flow, cam, v, e, dt, run.method, omega=omega, init=init,
                                                config=dcfg, device=run.device)
                solve = _time.perf_counter() - td
                timings["depth"] += solve
                if raw is not None:
                    prev_tv, prev_v = raw, v
                    rec["iterations"] = int(raw.iterations)
                    rec["solve_ms"] = 1e3 * float(raw.solve_s)
                else:
                    rec["solve_ms"] = 1e3 * solve
                depth, valid = res.depth, res.valid
            else:
                depth, valid = np.full((H, W), np.nan, np.float32), np.zeros((H, W), bool)
            rec["depth"], rec["valid"] = depth, valid
            true = footage.depth_map(i0)
            if true is not None:
                ts = _time.perf_counter()
                if true.shape != (H, W):
                    raise FootageError(f"{footage.path / 'depth' / f'{i0:06d}.npy'}: depth map is "
                                       f"{true.shape[1]}x{true.shape[0]}, the camera {W}x{H}")
                sc = depth_metrics(depth, true, valid, e if ranged else (0.0, 0.0), cam, rings_deg=dcfg.rings_deg)
                rec["scores"] = sc
                if ranged:
                    n_scored += 1
                    for lab in labels:
                        m, acc = sc[lab], pooled_acc[lab]
                        acc["n_true"] += m["n_true"]
                        acc["n_valid"] += m["n_valid"]
                        if m["n_valid"]:
                            acc["ae"] += m["abs_rel"] * m["n_valid"]
                            acc["se"] += m["rmse_m"] ** 2 * m["n_valid"]
                            acc["dl"] += m["delta_1_25"] * m["n_valid"]
                timings["score"] += _time.perf_counter() - ts
            sink.add(rec)
        if not starts:
            raise FootageError(f"{footage.path}: no flow pairs selected")

        extra = {}
        if n_scored:
            pv = {k: np.full(len(labels), np.nan) for k in ("abs_rel", "rmse_m", "delta_1_25", "valid_fraction")}
            for j, lab in enumerate(labels):
                acc = pooled_acc[lab]
                if acc["n_true"]:
                    pv["valid_fraction"][j] = acc["n_valid"] / acc["n_true"]
                if acc["n_valid"]:
                    pv["abs_rel"][j] = acc["ae"] / acc["n_valid"]
                    pv["rmse_m"][j] = math.sqrt(acc["se"] / acc["n_valid"])
                    pv["delta_1_25"][j] = acc["dl"] / acc["n_valid"]
            for k2, arr in pv.items():
                a2 = dict(_SCORE_ATTRS[k2])
                a2["long_name"] = "pooled over the pixels of every ranged map with exact depth: " + a2["long_name"]
                extra[f"pooled_{k2}"] = (("ring",), arr, a2)
        config = dict(depth_run=run.to_dict(), velocity=json.loads(velocity.attrs["config"]))
        attrs = provenance(
            json.dumps(config, sort_keys=True, default=str),
            method=run.method, front_end=vcfg.front_end,
            velocity_source=("truth: exact mean forward velocity over each pair (truth.csv)"
                             if run.velocity == "truth" else
                             f"estimate: v̂ of the velocity pipeline ({velocity.attrs.get('readout', '?')} readout, "
                             f"{velocity.attrs.get('filter', '?')} filter)"),
            acceleration_source=velocity.attrs.get("acceleration_source", "unknown"),
            epipole_source={"final": "velocity pass, final running estimate",
                            "running": "velocity pass, running estimate at the pair's time",
                            "principal": "principal point"}[run.epipole],
            derotation=("gyro: instantaneous (ratio, tv); finite rotation homography (parallax)"
                        if gyro is not None else "none (no gyroscope)"),
            depth_reference="first frame of each flow pair: d0 = v/z + v*dt (time = t0, frame = first index)",
            gap_frames=gap, n_scored_maps=n_scored, device=run.device,
            footage=str(footage.path), footage_kind=footage.kind, notes="; ".join(footage.notes) or "none",
            velocity_config=velocity.attrs["config"],
            timings_s=json.dumps({k: round(v, 4) for k, v in timings.items()}),
            wall_s=round(_time.perf_counter() - t_start, 3))
        return sink.finish(build, extra, attrs, out)
    except BaseException:
        if isinstance(sink, ZarrSink):
            sink.abort()
        raise
    finally:
        threads.__exit__(None, None, None)


def pooled_scores(ds: xr.Dataset) -> dict:
    """{ring: {abs_rel, rmse_m, delta_1_25, valid_fraction}} pooled over the scored maps ({} if none)."""
    if "pooled_abs_rel" not in ds:
        return {}
    return {str(r): {k: float(ds[f"pooled_{k}"].sel(ring=r)) for k in _SCORES} for r in ds.ring.values}


def format_scores(ds: xr.Dataset) -> str:
    """The scores table and solver timing as text (what ``lobula depth`` prints)."""
    lines = []
    n, nr = ds.sizes["time"], int(ds.ranged.sum())
    lines.append(f"method {ds.attrs.get('method')}: {n} maps ({nr} ranged, {n - nr} with unusable velocity: "
                 f"all invalid), depth at each pair's first frame")
    sc = pooled_scores(ds)
    if sc:
        lines.append(f"pooled over {ds.attrs.get('n_scored_maps')} ranged maps with exact depth:")
        lines.append(f"{'ring (deg)':>11} {'AbsRel':>8} {'RMSE (m)':>9} {'δ<1.25':>8} {'valid':>7}")
        for ring, m in sc.items():
            lines.append(f"{ring:>11} {m['abs_rel']:8.4f} {m['rmse_m']:9.4f} {m['delta_1_25']:8.4f} "
                         f"{m['valid_fraction']:7.4f}")
    elif bool(ds.has_true_depth.any()):
        lines.append("no ranged map has exact depth to score against")
    else:
        d = ds.depth.where(ds.valid)
        med = float(d.median()) if bool(ds.valid.any()) else float("nan")
        lines.append(f"no exact depth to score against; median depth of valid pixels {med:.3f} m, "
                     f"valid fraction {float(ds.valid.mean()):.3f}")
    ms = ds.solve_ms.values[np.isfinite(ds.solve_ms.values)]
    if ms.size:
        lines.append(f"solver: median {np.median(ms):.1f} ms/map, mean {ms.mean():.1f}, max {ms.max():.1f} "
                     f"({ds.sizes['x']}x{ds.sizes['y']}, {ds.attrs.get('device', 'cpu')})")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- figures
def _panel(frame: np.ndarray, true: np.ndarray | None, results: dict, camera: PinholeCamera, epipole,
           path, title: str) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401

    if true is not None:
        vals = true[np.isfinite(true) & (true > 0)]
    else:
        vals = np.concatenate([np.asarray(r.depth)[np.asarray(r.valid)] for r in results.values()] or [np.ones(1)])
    if vals.size == 0:
        vals = np.array([0.5, 3.0])
    # Depth spans a decade or more (panels to backdrop): a log scale, 2nd to 95th percentile.
    vmin, vmax = np.percentile(vals, [2, 95])
    if not vmax > vmin * 1.01:
        vmin, vmax = vmin / 1.2, vmin * 1.2 + 1e-3
    norm = matplotlib.colors.LogNorm(vmin=vmin, vmax=vmax, clip=True)
    cmap = matplotlib.colormaps["viridis_r"].with_extremes(bad="0.6")
    panels = [("frame", frame, None)]
    if true is not None:
        panels.append(("true depth", np.where(np.isfinite(true) & (true > 0), true, np.nan), None))
    for m, r in results.items():
        panels.append((m, np.where(r.valid, r.depth, np.nan), r))
    aspect = frame.shape[0] / frame.shape[1]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels) + 1.0, 3.0 * aspect + 1.0), squeeze=False,
                             layout="constrained")
    im = None
    for ax, (name, img, r) in zip(axes.ravel(), panels):
        if name == "frame":
            ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        else:
            im = ax.imshow(np.ma.masked_invalid(img), cmap=cmap, norm=norm)
        ax.plot(*camera.normalised_to_pixel(*epipole), "r+", ms=12, mew=1.5)
        sub = name
        if r is not None:
            sub += f"\nvalid {100 * np.mean(r.valid):.0f}%"
            if true is not None:
                m = depth_metrics(r.depth, true, r.valid, epipole, camera)
                inner = next((k for k in m if k != "all"), None)
                sub += f", AbsRel {m['all']['abs_rel']:.3f}"
                if inner is not None and np.isfinite(m[inner]["abs_rel"]):
                    sub += f" ({inner}°: {m[inner]['abs_rel']:.3f})"
            else:
                sub += f", median {np.median(r.depth[r.valid]):.2f} m" if np.any(r.valid) else ""
        elif name == "true depth":
            sub += f"\nmedian {np.nanmedian(img):.2f} m"
        ax.set_title(sub, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    if im is not None:
        cb = fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.9, pad=0.01, aspect=15,
                          label="forward depth (m, log scale); grey: invalid")
        cb.ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        cb.set_ticks(np.unique(np.round(np.geomspace(vmin, vmax, 5), 2)))
        cb.ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.2g"))
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def plot_depth(ds: xr.Dataset, footage: Footage, path, time: float | None = None,
               methods=METHODS, device: str = "cpu") -> Path:
    """PNG panel for one pair: the frame, its exact depth (when known) and every method's depth.

    Same colour scale for all (2–98 % of the true depth, or of the estimates), invalid
    pixels grey, the epipole marked. The pair is the map of ``ds`` nearest ``time``
    (default: the ranged map with exact depth and the largest |v|, else the largest |v|).
    Flow, derotation, v and epipole are those of the run (the flow is recomputed for
    that one pair; TV is solved cold).
    """
    cam = footage.camera
    if time is None:
        score = np.abs(np.nan_to_num(ds.v_used.values)) * ds.ranged.values
        if bool((ds.ranged & ds.has_true_depth).any()):
            score = score * ds.has_true_depth.values
        k = int(np.argmax(score))
    else:
        k = int(np.argmin(np.abs(ds.time.values - time)))
    rec = ds.isel(time=k)
    vcfg = VelocityConfig.from_json(ds.attrs["velocity_config"])
    fcfg = _flow_config(vcfg)
    i0 = int(rec.frame)
    i1 = i0 + fcfg.gap
    t0, t1 = float(footage.times[i0]), float(footage.times[i1])
    read = _FrameReader(footage)
    a, b = read(i0), read(i1)
    flow = pixel_to_angular(make_flow_fn(fcfg)(a, b), cam, t1 - t0)
    gyro_ok = vcfg.derotate and footage.imu is not None and footage.imu.gyro is not None
    omega = mean_angular_velocity(footage.imu.time_s, footage.imu.gyro, t0, t1) if gyro_ok else None
    v = float(rec.v_used)
    e = (float(rec.epipole_x), float(rec.epipole_y))
    dcfg = DepthConfig(**{k: (tuple(v2) if isinstance(v2, list) else v2) for k, v2 in
                          json.loads(ds.attrs["config"])["depth_run"]["depth"].items()})
    with _torch_threads(1 if device == "cpu" else 0):
        results = {m: depth_at_first_frame(flow, cam, v, e, t1 - t0, m, omega=omega, config=dcfg,
                                           device=device)[0] for m in methods}
    true = footage.depth_map(i0)
    return _panel(a, true, results, cam, e, path,
                  f"{footage.path.name}: frame {i0} (t = {t0:.2f} s), pair gap {t1 - t0:.3f} s, "
                  f"v = {v:+.3f} m/s ({ds.attrs.get('velocity_source', '').split(':')[0]})")


# ----------------------------------------------------------------------------- the real .flo pair
def depth_flo_pair(footage: Footage, flo_path: str | Path, units: FloUnits | None = None,
                   methods=METHODS, epipole: str = "estimate", config: DepthConfig | None = None,
                   device: str = "cpu") -> xr.Dataset:
    """Depth maps from a precomputed flow pair (e.g. the FLIVVER FlowNet2 ``.flo``), every method.

    footage: the footage the pair belongs to (its camera, frame times and truth; the
    D435i sample gives times by raw frame number through velocity.csv, raw_frame =
    sample + 3). flo_path: ``*_<first>_to_<second>.flo``. v: the exact mean forward
    velocity over the pair from the ground truth (one pair cannot give v̂: that needs
    acceleration and a time series). epipole: "estimate" (the robust fit of
    :class:`lobula.epipole.EpipoleEstimator` to this flow) or "principal". No IMU, so no
    derotation (parallax then equals ratio). Depth refers to the pair's first frame.

    Returns a Dataset with dims (estimator, y, x) — ``estimator`` holds the method names
    ("method" would clash with ``Dataset.sel``'s own keyword) — : ``depth`` (m), ``valid``,
    per estimator ``median_depth_m`` and ``valid_fraction``; v, the epipole and provenance
    in attrs.
    """
    from .velocity import flo_samples

    units = units or FloUnits()
    cfg = config or DepthConfig(gamma=FOOTAGE_GAMMA)
    if footage.truth is None:
        raise FootageError(f"{footage.path}: depth from a .flo pair needs the true velocity (truth.csv / velocity.csv)")
    sample = next(iter(flo_samples(footage, [Path(flo_path)], units)))
    cam = footage.camera
    flow, t0, t1 = sample.flow, sample.t0, sample.t1
    v = _mean_truth_velocity(footage.truth, t0, t1)
    if epipole == "estimate":
        x, y = cam.normalised_grid()
        est = EpipoleEstimator(x, y, stride=max(1, int(np.sqrt(cam.width * cam.height / 5000))))
        e = tuple(float(c) for c in est.update(flow))
    elif epipole == "principal":
        e = (0.0, 0.0)
    else:
        raise ValueError(f"epipole must be 'estimate' or 'principal', got {epipole!r}")
    with _torch_threads(1 if device == "cpu" else 0):
        res = {m: depth_at_first_frame(flow, cam, v, e, t1 - t0, m, config=cfg, device=device)[0]
               for m in methods}
    med = [float(np.median(r.depth[r.valid])) if r.valid.any() else float("nan") for r in res.values()]
    ds = xr.Dataset(
        dict(depth=(("estimator", "y", "x"), np.stack([r.depth for r in res.values()]),
                    {"units": "m", "long_name": "forward depth at the pair's first frame (NaN: invalid)"}),
             valid=(("estimator", "y", "x"), np.stack([r.valid for r in res.values()])),
             median_depth_m=("estimator", med, {"units": "m", "long_name": "median depth of valid pixels"}),
             valid_fraction=("estimator", [float(r.valid.mean()) for r in res.values()], {"units": "1"})),
        coords=dict(estimator=list(res), y=("y", np.arange(cam.height), {"units": "pixel"}),
                    x=("x", np.arange(cam.width), {"units": "pixel"})))
    ds.attrs.update(provenance(json.dumps(dict(depth=cfg.to_dict(), flo_units=asdict(units), epipole=epipole),
                                          sort_keys=True, default=str),
                               flo=str(flo_path), first_frame=int(sample.index), t0=t0, t1=t1, v_m_s=v,
                               velocity_source="truth: mean over the pair", epipole_x=e[0], epipole_y=e[1],
                               depth_reference="first frame of the pair: d0 = v/z + v*dt",
                               derotation="none (no gyroscope)", footage=str(footage.path),
                               notes="; ".join(footage.notes) or "none"))
    return ds


def plot_flo_pair(ds: xr.Dataset, footage: Footage, path) -> Path:
    """PNG panel of a :func:`depth_flo_pair` result: the first frame and each method's depth."""
    flo = Path(ds.attrs["flo"])
    first = int(ds.attrs["first_frame"])
    img_path = next((p for p in (flo.parent / f"{first}.png", flo.parent / f"{first:04d}.png") if p.exists()), None)
    cam = footage.camera
    frame = read_frame(img_path) if img_path is not None else np.zeros((cam.height, cam.width), np.float32)
    if frame.shape != (cam.height, cam.width):
        import cv2
        frame = cv2.resize(frame, (cam.width, cam.height))
    results = {str(m): DepthResult(depth=ds.depth.sel(estimator=m).values, valid=ds.valid.sel(estimator=m).values,
                                   rate=None, method=str(m)) for m in ds.estimator.values}
    e = (float(ds.attrs["epipole_x"]), float(ds.attrs["epipole_y"]))
    meds = ", ".join(f"{m} {float(ds.median_depth_m.sel(estimator=m)):.2f} m" for m in ds.estimator.values)
    return _panel(frame, None, results, cam, e, path,
                  f"{flo.name}: v = {float(ds.attrs['v_m_s']):+.3f} m/s (truth); medians {meds}")


# ----------------------------------------------------------------------------- command line
def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``lobula depth`` on an argparse subparsers object; returns the subparser."""
    d = subparsers.add_parser(
        "depth", help="dense depth maps from footage (ratio, TV, plane+parallax), scored against exact depth",
        description="Estimate v̂ with the velocity pipeline, then dense forward depth at the first frame of "
                    "every N-th flow pair; scores against depth/NNNNNN.npy when the footage has it.")
    d.add_argument("footage", help="footage folder, or the D435i sample folder")
    d.add_argument("--method", default="tv", choices=list(METHODS),
                   help="ratio map v/r, TV-regularised fit (default), or plane+parallax with finite derotation")
    d.add_argument("--every", type=int, default=1, help="solve every N-th flow pair (default 1; 10 matches "
                                                        "the synthetic runs' depth/ maps)")
    d.add_argument("--out", required=True, help="output .nc (NetCDF, written atomically) or .zarr (streamed)")
    d.add_argument("--plot", help="PNG panel: frame, true depth, each method's depth")
    d.add_argument("--plot-time", type=float, help="time (s) of the panel's pair (default: fastest scored pair)")
    d.add_argument("--front-end", default="dis", choices=["dis", "farneback"],
                   help="dense flow of both passes (with --velocity-run, that run's flow is reused)")
    d.add_argument("--velocity", default="estimate", choices=["estimate", "truth"],
                   help="v̂ from the velocity pipeline (default) or the exact velocity from truth.csv")
    d.add_argument("--velocity-run", help="a velocity NetCDF of this footage (from `lobula velocity`) to reuse")
    d.add_argument("--epipole", default="final", choices=["final", "running", "principal"])
    d.add_argument("--accel-from-truth", action="store_true",
                   help="velocity pass: forward acceleration from truth.csv instead of imu.csv")
    d.add_argument("--gamma", type=float, help=f"TV weight (default {FOOTAGE_GAMMA:g}, tuned for DIS flow)")
    d.add_argument("--tv-start", default="cold", choices=["cold", "warm"],
                   help="TV: coarse-to-fine per map (default, faster) or warm start from the previous map")
    d.add_argument("--min-speed", type=float, default=DepthRunConfig().min_speed_m_s,
                   help="pairs slower than this (m/s) are not ranged (all invalid)")
    d.add_argument("--device", default="cpu", help="torch device for TV (cpu, cuda); on cpu it uses one thread")
    d.add_argument("--flo", help="instead: depth from one precomputed .flo pair (*_<first>_to_<second>.flo), "
                                 "v from the ground truth")
    d.add_argument("--flo-units", default="rad/s", choices=["rad/s", "px"])
    d.add_argument("--flo-gap", type=float, default=0.2)
    d.add_argument("--flo-size", type=int, nargs=2, default=[640, 448], metavar=("W", "H"))
    d.add_argument("--quiet", action="store_true")
    d.set_defaults(func=run_depth)
    return d


def run_depth(args) -> int:
    """Handler of ``lobula depth``: returns the exit code; bad input raises FootageError/ValueError."""
    from stimuli.footage import open_footage

    footage = open_footage(args.footage)
    dcfg = DepthConfig(gamma=FOOTAGE_GAMMA if args.gamma is None else args.gamma)
    out = Path(args.out)
    if out.suffix not in (".nc", ".zarr"):
        raise ValueError(f"{out}: --out must end in .nc (NetCDF) or .zarr (Zarr)")
    if args.flo:
        units = FloUnits(args.flo_units, args.flo_gap, *args.flo_size)
        pair = depth_flo_pair(footage, args.flo, units, config=dcfg, device=args.device)
        one = pair.sel(estimator=args.method).drop_vars("estimator").expand_dims(time=[float(pair.attrs["t0"])])
        one["frame"] = ("time", [int(pair.attrs["first_frame"])])
        one = one.set_coords("frame")
        one.attrs.update(method=args.method)
        if out.suffix == ".zarr":
            raise ValueError("--flo writes one map: use a .nc output")
        write_netcdf(one, out)
        print(f"wrote {out}: depth from {Path(args.flo).name} at v = {float(pair.attrs['v_m_s']):+.3f} m/s "
              f"(truth), epipole ({pair.attrs['epipole_x']:+.4f}, {pair.attrs['epipole_y']:+.4f})")
        for m in pair.estimator.values:
            print(f"  {m:>8}: median depth {float(pair.median_depth_m.sel(estimator=m)):.3f} m, "
                  f"valid {float(pair.valid_fraction.sel(estimator=m)):.3f}")
        if args.plot:
            plot_flo_pair(pair, footage, args.plot)
            print(f"wrote {args.plot}")
        return 0
    vcfg = VelocityConfig(front_end=args.front_end)
    vcfg.accel_from_truth = args.accel_from_truth
    velocity = None
    if args.velocity_run:
        p = Path(args.velocity_run)
        if not p.exists():
            raise FootageError(f"{p}: velocity run not found")
        velocity = xr.load_dataset(p)
        if "config" not in velocity.attrs or "v_hat" not in velocity:
            raise FootageError(f"{p}: not a velocity run of `lobula velocity` (no v_hat / config)")
    run = DepthRunConfig(method=args.method, every=args.every, velocity=args.velocity, epipole=args.epipole,
                         min_speed_m_s=args.min_speed, tv_start=args.tv_start, device=args.device,
                         depth=dcfg)
    ds = estimate_depth(footage, velocity_config=vcfg, run=run, velocity=velocity, out=out,
                        progress=not args.quiet)
    print(f"wrote {out}: {ds.sizes['time']} maps of {ds.sizes['x']}x{ds.sizes['y']} "
          f"[{args.method}, {ds.attrs['front_end']}; v: {ds.attrs['velocity_source']}; "
          f"acceleration: {ds.attrs['acceleration_source']}]")
    print(format_scores(ds))
    if args.plot:
        plot_depth(ds, footage, args.plot, time=args.plot_time, device=args.device)
        print(f"wrote {args.plot}")
    return 0
