"""Depth maps scored against exact depth: which pixels count, the error statistics, and both
overall and in rings around the epipole.
"""
from __future__ import annotations

import math

import numpy as np

from .._optional import is_tensor
from .geometry import angle_from_epipole
from lobula.camera import PinholeCamera


def scorable(true, max_depth_m: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which pixels of an exact depth map ``true`` (H, W), m, are scored: (scored, sky, far) (H, W) bool masks.

    sky: no surface (true depth non-finite or ≤ 0); far: finite but beyond
    ``max_depth_m`` (the stated range of the scores); scored: the rest.
    """
    t = np.asarray(true.detach().cpu() if is_tensor(true) else true, dtype=np.float64)
    sky = ~(np.isfinite(t) & (t > 0))
    far = ~sky & (np.where(sky, 0.0, t) > max_depth_m)
    return ~sky & ~far, sky, far


def error_stats(pred: np.ndarray, true: np.ndarray) -> dict:
    """Depth errors over paired 1-D arrays ``pred`` (n,) and ``true`` (n,) of estimated and exact depth
    (m, both > 0).

    abs_rel (mean |d̂−d|/d), median_abs_rel, rmse_m (m), rmse_log (RMS of ln d̂ − ln d),
    delta_1_25 (fraction with max(d̂/d, d/d̂) < 1.25); NaN for empty input.
    """
    if pred.size == 0:
        return dict(abs_rel=float("nan"), median_abs_rel=float("nan"), rmse_m=float("nan"),
                    rmse_log=float("nan"), delta_1_25=float("nan"))
    rel = np.abs(pred - true) / true
    lr = np.log(pred / true)
    return dict(abs_rel=float(np.mean(rel)), median_abs_rel=float(np.median(rel)),
                rmse_m=float(np.sqrt(np.mean((pred - true) ** 2))), rmse_log=float(np.sqrt(np.mean(lr * lr))),
                delta_1_25=float(np.mean(np.abs(lr) < math.log(1.25))))


def depth_metrics(pred, true, mask, epipole, camera: PinholeCamera,
                  rings_deg=(0.0, 5.0, 10.0, 20.0, 90.0), max_depth_m: float = math.inf) -> dict:
    """Score a depth map against exact depth, overall and in rings around the epipole.

    pred, true: (H, W) forward depth (m), ``camera``'s size; mask: (H, W) bool validity of ``pred`` (None:
    finite pred); epipole (ex, ey): normalised; max_depth_m: m.
    Pixels are scored where ``true`` is finite, > 0 and ≤ ``max_depth_m``
    (:func:`scorable`; the others are counted as n_sky and n_far). rings_deg: ring
    edges in degrees of angle between the pixel's ray and the epipole's ray; ring i is
    [rings_deg[i], rings_deg[i+1]).

    Returns {"all": m, "0-5": m, "5-10": m, ...} where each m is a dict with the
    :func:`error_stats` (abs_rel = mean |pred−true|/true, median_abs_rel, rmse_m,
    rmse_log, delta_1_25) over pixels valid in both, valid_fraction (the coverage:
    valid scored pixels / scored pixels), n_true (scored pixels), n_valid, n_sky, n_far.
    Metrics over no valid pixels are NaN.
    """
    def _np(a):
        return a.detach().cpu().numpy() if is_tensor(a) else np.asarray(a)

    p = _np(pred).astype(np.float64)
    t = _np(true).astype(np.float64)
    if p.shape != t.shape or p.shape != (camera.height, camera.width):
        raise ValueError(f"pred {p.shape} and true {t.shape} must both be the camera's (H, W) = "
                         f"({camera.height}, {camera.width})")
    m = np.isfinite(p) if mask is None else (_np(mask).astype(bool) & np.isfinite(p))
    has_true, sky, far = scorable(t, max_depth_m)
    ang = angle_from_epipole(camera, epipole)

    def _score(region: np.ndarray) -> dict:
        tr = region & has_true
        ok = tr & m & (p > 0)
        n_true, n_ok = int(tr.sum()), int(ok.sum())
        out = dict(n_true=n_true, n_valid=n_ok, n_sky=int((region & sky).sum()), n_far=int((region & far).sum()),
                   valid_fraction=(n_ok / n_true) if n_true else float("nan"))
        out.update(error_stats(p[ok], t[ok]))
        return out

    result = {"all": _score(np.ones_like(has_true))}
    edges = [float(r) for r in rings_deg]
    for lo, hi in zip(edges[:-1], edges[1:]):
        result[f"{lo:g}-{hi:g}"] = _score((ang >= lo) & (ang < hi))
    return result
