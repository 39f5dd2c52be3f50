"""``lobula depth``: dense forward depth from v and the flow, on any footage the readers open.

The work is split by concern: :mod:`experiments.depth_stream` (the run: exact finite
derotation from the gyro, the three estimators, the streamed NetCDF/Zarr output),
:mod:`experiments.depth_pairs` (the flow pairs: their speed, the gyro's rotation over
each, the gyro-stabilised epipole), :mod:`experiments.depth_score` (pooled scores with
truth masking and coverage), :mod:`experiments.depth_figure` (the panel figure) and
:mod:`experiments.depth_suite` (families × seeds beside baselines). This module holds
the command line and the single precomputed ``.flo`` pair, and re-exports the public
names so ``from experiments.depth import estimate_depth`` keeps working.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.config import VelocityConfig
from lobula.depth import DepthConfig
from lobula.epipole import EpipoleEstimator
from lobula.readers.core import Footage, FootageError
from lobula.readers.flo import FloUnits

from .depth_figure import plot_depth, plot_flo_pair
from .depth_score import format_scores, pooled_scores
from .depth_stream import (FOOTAGE_GAMMA, METHODS, DepthRunConfig, depth_at_first_frame, estimate_depth,
                           mean_truth_velocity, torch_threads)
from .store import provenance, write_netcdf

__all__ = ["METHODS", "DepthRunConfig", "depth_at_first_frame", "estimate_depth", "pooled_scores",
           "format_scores", "plot_depth", "depth_flo_pair", "plot_flo_pair", "add_parser", "run_depth"]


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
    from lobula.front_ends.flo import flo_samples

    units = units or FloUnits()
    cfg = config or DepthConfig(gamma=FOOTAGE_GAMMA)
    if footage.truth is None:
        raise FootageError(f"{footage.path}: depth from a .flo pair needs the true velocity (truth.csv / velocity.csv)")
    sample = next(iter(flo_samples(footage, [Path(flo_path)], units)))
    cam = footage.camera
    flow, t0, t1 = sample.flow, sample.t0, sample.t1
    v = mean_truth_velocity(footage.truth, t0, t1)
    if epipole == "estimate":
        x, y = cam.normalised_grid()
        est = EpipoleEstimator(x, y, stride=max(1, int(np.sqrt(cam.width * cam.height / 5000))))
        e = tuple(float(c) for c in est.update(flow))
    elif epipole == "principal":
        e = (0.0, 0.0)
    else:
        raise ValueError(f"epipole must be 'estimate' or 'principal', got {epipole!r}")
    with torch_threads(1 if device == "cpu" else 0):
        res = {m: depth_at_first_frame(flow, cam, v, e, t1 - t0, m, config=cfg, device=device)[0]
               for m in methods}
    med = [float(np.median(r.depth[r.valid])) if r.valid.any() else float("nan") for r in res.values()]
    ds = xr.Dataset(
        dict(depth=(("estimator", "y", "x"), np.stack([r.depth for r in res.values()]),
                    {"units": "m", "long_name": "forward depth at the pair's first frame (NaN: invalid)"}),
             valid=(("estimator", "y", "x"), np.stack([r.valid for r in res.values()]),
                    {"units": "1", "long_name": "depth is an estimate"}),
             median_depth_m=("estimator", med, {"units": "m", "long_name": "median depth of valid pixels"}),
             valid_fraction=("estimator", [float(r.valid.mean()) for r in res.values()],
                             {"units": "1", "long_name": "fraction of pixels with an estimate"})),
        coords=dict(estimator=("estimator", list(res), {"long_name": "depth estimator"}),
                    y=("y", np.arange(cam.height), {"units": "1", "long_name": "image row (pixel index, down)"}),
                    x=("x", np.arange(cam.width), {"units": "1", "long_name": "image column (pixel index, right)"})))
    ds.attrs.update(provenance(json.dumps(dict(depth=cfg.to_dict(), flo_units=asdict(units), epipole=epipole),
                                          sort_keys=True, default=str),
                               flo=str(flo_path), first_frame=int(sample.index), t0=t0, t1=t1, v_m_s=v,
                               velocity_source="truth: mean over the pair", epipole_x=e[0], epipole_y=e[1],
                               depth_reference="first frame of the pair: d0 = v/z + v*dt",
                               derotation="none (no gyroscope)", footage=str(footage.path),
                               notes="; ".join(footage.notes) or "none"))
    return ds


# ----------------------------------------------------------------------------- command line
def add_parser(subparsers):
    """Register ``lobula depth`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_depth_parser`'s, built without importing this module."""
    from .parsers import add_depth_parser

    return add_depth_parser(subparsers)


def run_depth(args) -> int:
    """Handler of ``lobula depth``: returns the exit code; bad input raises FootageError/ValueError."""
    from lobula._optional import torch_device

    from .info import open_footage_from_args

    out = Path(args.out)
    if out.suffix not in (".nc", ".zarr"):
        raise ValueError(f"{out}: --out must end in .nc (NetCDF) or .zarr (Zarr)")
    if args.device != "cpu":  # before the velocity pass, not after it (the cpu needs no torch without TV)
        torch_device(args.device)
    gamma = FOOTAGE_GAMMA if getattr(args, "gamma", None) is None else args.gamma
    dcfg = DepthConfig(gamma=gamma)
    # The reader options, applied as `lobula velocity` applies them; the .flo route needs no IMU.
    footage = open_footage_from_args(args, require_imu=not args.flo)
    if args.flo:
        unused = [f"--{k.replace('_', '-')}" for k, v in getattr(args, "flo_ignores", {}).items()
                  if getattr(args, k) != v] + (["--epipole running"] if args.epipole == "running" else [])
        if unused:
            raise ValueError(f"{', '.join(unused)} apply to depth along footage, not to one --flo pair: leave "
                             "them out or drop --flo")
        if out.suffix == ".zarr":
            raise ValueError("--flo writes one map: use a .nc output")
        units = FloUnits(args.flo_units, args.flo_gap, *args.flo_size)
        pair = depth_flo_pair(footage, args.flo, units, config=dcfg, device=args.device,
                              epipole="principal" if args.epipole == "principal" else "estimate")
        one = pair.sel(estimator=args.method).drop_vars("estimator").expand_dims(time=[float(pair.attrs["t0"])])
        one["frame"] = ("time", [int(pair.attrs["first_frame"])])
        one = one.set_coords("frame")
        one["time"].attrs.update(units="s", long_name="time of the pair's first frame")
        one["frame"].attrs.update(units="1", long_name="index of the pair's first frame")
        one.attrs.update(method=args.method)
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
    if getattr(args, "dis_preset", None):
        vcfg.flow.dis_preset = args.dis_preset
    velocity = None
    if args.velocity_run:
        p = Path(args.velocity_run)
        if not p.exists():
            raise FootageError(f"{p}: velocity run not found")
        try:
            velocity = xr.load_dataset(p)
        except (OSError, ValueError) as exc:  # not a NetCDF (xarray finds no engine), or a damaged one
            raise FootageError(f"{p}: not a readable NetCDF velocity run of `lobula velocity` "
                               f"({str(exc).splitlines()[0]})") from None
        if "config" not in velocity.attrs or "v_hat" not in velocity:
            raise FootageError(f"{p}: not a velocity run of `lobula velocity` (no v_hat / config)")
    run = DepthRunConfig(method=args.method, every=args.every, velocity=args.velocity, epipole=args.epipole,
                         min_speed_m_s=args.min_speed, tv_start=args.tv_start, device=args.device,
                         weighted=not args.unweighted, snr_min=args.snr_min, max_range_m=args.max_range,
                         average_frames=args.average_frames, max_scale_rel_std=args.max_scale_rel_std,
                         depth=dcfg)
    ds = estimate_depth(footage, velocity_config=vcfg, run=run, velocity=velocity, out=out,
                        progress=not args.quiet)
    print(f"wrote {out}: {ds.sizes['time']} maps of {ds.sizes['x']}x{ds.sizes['y']} "
          f"[{args.method}, {ds.attrs['front_end']}; v: {ds.attrs['velocity_source']}; "
          f"acceleration: {ds.attrs['acceleration_source']}]")
    print(format_scores(ds))
    if args.plot:
        t = ds.time.values
        if args.plot_time is not None and not t[0] - 0.5 <= args.plot_time <= t[-1] + 0.5:
            raise ValueError(f"--plot-time {args.plot_time:g} s lies outside the maps' {t[0]:.2f}–{t[-1]:.2f} s")
        plot_depth(ds, footage, args.plot, time=args.plot_time, device=args.device)
        print(f"wrote {args.plot}")
    return 0
