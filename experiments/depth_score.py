"""Scoring depth maps on footage: per-map metrics pooled over a run, in rings around the epipole.

Which pixels count (:func:`lobula.depth.scorable`): those whose exact depth is finite,
> 0 and within the stated range (``max_range_m``); the others are counted, as sky
(``n_sky``) and beyond range (``n_far``), never scored. Of the scored pixels, those the
method left without an estimate (masked near the epipole, wrong sign, unranged pair)
lower the **coverage** (``valid_fraction``), which is reported beside every error: a
method that scores only its easy pixels shows it there.

Pooling over maps keeps bounded memory: sums for the means and a fine log-spaced
histogram of |d̂ − d|/d for the median (bins 1.2 % wide, so the pooled median is exact
to about ±0.6 %).
"""
from __future__ import annotations

import math

import numpy as np
import xarray as xr

from lobula.depth import scorable

__all__ = ["SCORES", "COUNTS", "SCORE_ATTRS", "PooledScores", "ring_masks", "pooled_scores", "format_scores"]

SCORES = ("abs_rel", "median_abs_rel", "rmse_m", "rmse_log", "delta_1_25", "valid_fraction")
COUNTS = ("n_valid", "n_true", "n_sky", "n_far")
SCORE_ATTRS = dict(
    abs_rel=dict(units="1", long_name="mean |d̂ − d| / d over scored pixels with an estimate"),
    median_abs_rel=dict(units="1", long_name="median |d̂ − d| / d over scored pixels with an estimate"),
    rmse_m=dict(units="m", long_name="root mean square depth error"),
    rmse_log=dict(units="1", long_name="root mean square of ln d̂ − ln d"),
    delta_1_25=dict(units="1", long_name="fraction with max(d̂/d, d/d̂) < 1.25"),
    valid_fraction=dict(units="1", long_name="coverage: scored pixels with an estimate / scored pixels"),
    n_valid=dict(units="1", long_name="scored pixels with an estimate"),
    n_true=dict(units="1", long_name="scored pixels (exact depth finite and within max_range_m)"),
    n_sky=dict(units="1", long_name="pixels without a surface (exact depth not finite): not scored"),
    n_far=dict(units="1", long_name="pixels beyond max_range_m: not scored"))

_EDGES = np.geomspace(1e-4, 1e2, 1201)  # |d̂−d|/d histogram bins (below 1e-4: first bin)


def ring_masks(angle_deg: np.ndarray, labels: list[str], lo: np.ndarray, hi: np.ndarray) -> dict:
    """{label: (H, W) bool} for the rings [lo, hi) of angle from the epipole ('all': everything)."""
    return {lab: (np.ones(angle_deg.shape, bool) if lab == "all" else (angle_deg >= a) & (angle_deg < b))
            for lab, a, b in zip(labels, lo, hi)}


class PooledScores:
    """Scores pooled over the pixels of many maps, per ring (bounded memory)."""

    def __init__(self, labels, max_range_m: float = math.inf):
        self.labels, self.max_range_m = list(labels), float(max_range_m)
        self.acc = {lab: dict(n_true=0, n_valid=0, n_sky=0, n_far=0, ae=0.0, se=0.0, le=0.0, dl=0,
                              hist=np.zeros(len(_EDGES) + 1, np.int64)) for lab in self.labels}
        self.n_maps = 0

    def add(self, pred: np.ndarray, true: np.ndarray, valid: np.ndarray, rings: dict) -> None:
        """One map: estimate (H, W, m), its validity, exact depth, ring masks (:func:`ring_masks`)."""
        scored, sky, far = scorable(true, self.max_range_m)
        p = np.asarray(pred, np.float64)
        t = np.asarray(true, np.float64)
        ok = scored & np.asarray(valid, bool) & np.isfinite(p) & (p > 0)
        rel = np.zeros_like(p)
        lr = np.zeros_like(p)
        rel[ok] = np.abs(p[ok] - t[ok]) / t[ok]
        lr[ok] = np.log(p[ok] / t[ok])
        self.n_maps += 1
        for lab in self.labels:
            a, m = self.acc[lab], rings[lab]
            k = ok & m
            a["n_true"] += int((scored & m).sum())
            a["n_sky"] += int((sky & m).sum())
            a["n_far"] += int((far & m).sum())
            a["n_valid"] += int(k.sum())
            r = rel[k]
            a["ae"] += float(r.sum())
            a["se"] += float(((p[k] - t[k]) ** 2).sum())
            a["le"] += float((lr[k] ** 2).sum())
            a["dl"] += int((np.abs(lr[k]) < math.log(1.25)).sum())
            a["hist"] += np.bincount(np.searchsorted(_EDGES, r), minlength=len(_EDGES) + 1)

    def result(self) -> dict:
        """{ring: {SCORES..., COUNTS...}}; errors NaN where no pixel has an estimate."""
        out = {}
        for lab in self.labels:
            a = self.acc[lab]
            n = a["n_valid"]
            m = dict(n_true=a["n_true"], n_valid=n, n_sky=a["n_sky"], n_far=a["n_far"],
                     valid_fraction=n / a["n_true"] if a["n_true"] else float("nan"))
            if n:
                c = np.cumsum(a["hist"])
                j = int(np.searchsorted(c, 0.5 * n))
                # Geometric middle of the bin holding the median (bin j spans EDGES[j-1]..EDGES[j]).
                med = _EDGES[0] if j == 0 else (_EDGES[-1] if j >= len(_EDGES) else math.sqrt(_EDGES[j - 1] * _EDGES[j]))
                m.update(abs_rel=a["ae"] / n, median_abs_rel=float(med), rmse_m=math.sqrt(a["se"] / n),
                         rmse_log=math.sqrt(a["le"] / n), delta_1_25=a["dl"] / n)
            else:
                m.update(abs_rel=float("nan"), median_abs_rel=float("nan"), rmse_m=float("nan"),
                         rmse_log=float("nan"), delta_1_25=float("nan"))
            out[lab] = m
        return out

    def variables(self) -> dict:
        """The pooled scores as Dataset variables ``pooled_<score>`` over dim ``ring``."""
        res = self.result()
        extra = {}
        for k in SCORES + COUNTS:
            a2 = dict(SCORE_ATTRS[k])
            a2["long_name"] = "pooled over the pixels of every ranged map with exact depth: " + a2["long_name"]
            extra[f"pooled_{k}"] = (("ring",), np.array([res[lab][k] for lab in self.labels], float), a2)
        return extra


def pooled_scores(ds: xr.Dataset) -> dict:
    """{ring: {score: value}} pooled over the scored maps of a depth run ({} if none)."""
    if "pooled_abs_rel" not in ds:
        return {}
    keys = [k for k in SCORES + COUNTS if f"pooled_{k}" in ds]
    return {str(r): {k: float(ds[f"pooled_{k}"].sel(ring=r)) for k in keys} for r in ds.ring.values}


def format_scores(ds: xr.Dataset) -> str:
    """The scores table and solver timing as text (what ``lobula depth`` prints)."""
    lines = []
    n, nr = ds.sizes["time"], int(ds.ranged.sum())
    scale = ""
    if "metric" in ds:
        nm = int((~ds.metric.values.astype(bool)).sum())
        scale = (f"; {nm} of them with the speed's relative std above {ds.attrs.get('max_scale_rel_std', '?')}: "
                 f"scale unknown, reported as unobservable; metric depth on {nr}/{n} = {nr / max(n, 1):.0%} of maps")
    lines.append(f"method {ds.attrs.get('method')}: {n} maps ({nr} ranged, {n - nr} with unusable velocity: "
                 f"all invalid{scale}), depth at each pair's first frame; v: {ds.attrs.get('velocity_source', '?')}")
    sc = pooled_scores(ds)
    if sc:
        a = sc["all"]
        lines.append(f"pooled over {ds.attrs.get('n_scored_maps')} ranged maps with exact depth; scored: exact depth "
                     f"finite and ≤ {ds.attrs.get('max_range_m')} m ({a.get('n_sky', 0):.0f} sky and "
                     f"{a.get('n_far', 0):.0f} farther pixels left out)")
        lines.append(f"{'ring (deg)':>11} {'AbsRel':>8} {'median':>8} {'RMSE (m)':>9} {'RMSElog':>8} {'δ<1.25':>8} "
                     f"{'coverage':>8}")
        for ring, m in sc.items():
            lines.append(f"{ring:>11} {m['abs_rel']:8.4f} {m.get('median_abs_rel', float('nan')):8.4f} "
                         f"{m['rmse_m']:9.4f} {m.get('rmse_log', float('nan')):8.4f} {m['delta_1_25']:8.4f} "
                         f"{m['valid_fraction']:8.4f}")
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
