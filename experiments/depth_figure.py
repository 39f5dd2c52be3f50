"""Figures of depth runs: a panel of the frame, its exact depth and each method's depth map.

Same logarithmic colour scale for all (2–95 % of the exact depth, or of the estimates),
invalid pixels grey, the epipole marked; each panel's title gives coverage and AbsRel.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.depth import DepthConfig, DepthResult, depth_metrics
from lobula.flow import pixel_to_angular
from lobula.readers.core import Footage, read_frame

from .depth_pairs import _FrameReader
from .depth_stream import (METHODS, DepthRunConfig, depth_at_first_frame, depth_flow_fn, flow_config, footage_attitude,
                           torch_threads)
from .store import save_figure

__all__ = ["plot_depth", "plot_flo_pair", "depth_panel"]


def depth_panel(frame: np.ndarray, true: np.ndarray | None, results: dict, camera: PinholeCamera, epipole,
                path, title: str, max_range_m: float = float("inf"), provenance: dict | None = None) -> Path:
    """PNG: the frame, the exact depth (when given) and each result's depth map (dict name -> DepthResult);
    ``provenance``, the run's attributes, goes into its metadata.

    Titles: coverage of the scored pixels (exact depth ≤ ``max_range_m``) and AbsRel
    (mean; median in brackets), with the innermost ring's AbsRel."""
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
            if true is not None:
                m = depth_metrics(r.depth, true, r.valid, epipole, camera, max_depth_m=max_range_m)
                inner = next((k for k in m if k != "all"), None)
                sub += (f"\ncoverage {100 * m['all']['valid_fraction']:.0f}%, AbsRel {m['all']['abs_rel']:.2f} "
                        f"(median {m['all']['median_abs_rel']:.2f})")
                if inner is not None and np.isfinite(m[inner]["abs_rel"]):
                    sub += f"\n{inner}° from epipole: {m[inner]['abs_rel']:.2f}"
            else:
                sub += f"\nvalid {100 * np.mean(r.valid):.0f}%"
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
    save_figure(fig, path, provenance=provenance, dpi=150, bbox_inches="tight")
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
    fcfg = flow_config(vcfg)
    i0 = int(rec.frame)
    i1 = i0 + fcfg.gap
    t0, t1 = float(footage.times[i0]), float(footage.times[i1])
    read = _FrameReader(footage)
    a, b = read(i0), read(i1)
    conf = json.loads(ds.attrs["config"])["depth_run"]
    dcfg = DepthConfig(**{k: (tuple(v2) if isinstance(v2, list) else v2) for k, v2 in conf["depth"].items()})
    run = DepthRunConfig(**{k: v2 for k, v2 in conf.items() if k != "depth"}, depth=dcfg)
    flow = pixel_to_angular(depth_flow_fn(fcfg, run.flow)(a, b), cam, t1 - t0)
    attitude = footage_attitude(footage, vcfg)
    rotation = None
    if attitude is not None:
        q0, q1 = attitude(np.array([t0, t1]))
        rotation = q0.T @ q1
    v = float(rec.v_used)
    e = (float(rec.epipole_x), float(rec.epipole_y))
    with torch_threads(1 if device == "cpu" else 0):
        results = {m: depth_at_first_frame(flow, cam, v, e, t1 - t0, m, rotation=rotation, config=dcfg,
                                           device=device, weighted=run.weighted, snr_min=run.snr_min,
                                           noise_window_deg=run.noise_window_deg,
                                           refine=run.refine)[0] for m in methods}
    true = footage.depth_map(i0)
    e = next(iter(results.values())).epipole or e
    title = (f"{footage.path.name}: frame {i0} (t = {t0:.2f} s), pair gap {t1 - t0:.3f} s, "
             f"v = {v:+.3f} m/s ({ds.attrs.get('velocity_source', '').split(':')[0]}); scored ≤ {run.max_range_m:g} m")
    return depth_panel(a, true, results, cam, e, path, title, max_range_m=run.max_range_m, provenance=ds.attrs)


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
    return depth_panel(frame, None, results, cam, e, path,
                  f"{flo.name}: v = {float(ds.attrs['v_m_s']):+.3f} m/s (truth); medians {meds}",
                       provenance=ds.attrs)


