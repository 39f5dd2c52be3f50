"""`lobula velocity` on camera footage: the command, its scores and its figure.

The pipeline itself is the library's (:func:`lobula.estimate_velocity`, :class:`lobula.VelocityEstimator`);
this module scores a run against truth (:func:`score`), says why a run is never observable, draws it,
and maps the command's options onto :class:`lobula.config.VelocityConfig`.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.config import VelocityConfig
from lobula.front_ends import FRONT_ENDS, get_front_end
from lobula.photoreceptor import mean_removal
from lobula.readers.flo import FloUnits
from lobula.velocity import estimate_velocity


def score(ds: xr.Dataset, skip_s: float | None = None) -> dict:
    """RMSE and median absolute error of v̂ against truth after ``skip_s`` (s; None: the ``scored_after_s`` that
    `lobula velocity` stored, else 2), the observable fraction, and the truth inside v̂ ± 2·v_std.

    Errors are over observable frames; the fraction says how many those are. ``carried_fraction``: the frames
    where v̂ is carried by the accelerometer (finite, not observable); ``coverage_2sigma_all``: the truth inside
    ±2σ over every frame after ``skip_s``, a frame without v̂ counted outside.
    """
    if "v_true" not in ds:
        return {}
    if skip_s is None:
        skip_s = float(ds.attrs.get("scored_after_s", SCORE_SKIP_S))
    keep = (ds.time >= ds.time[0] + skip_s).values
    obs = ds.observable.values[keep].astype(bool)
    e_all = (ds.v_hat - ds.v_true).values[keep]
    err = e_all[obs]
    inside = np.abs(e_all) <= 2 * ds.v_std.values[keep]
    out = dict(observable_fraction=float(obs.mean()) if obs.size else 0.0, n_frames=int(keep.sum()),
               carried_fraction=float(np.mean(np.isfinite(e_all) & ~obs)) if obs.size else 0.0,
               coverage_2sigma_all=float(inside.mean()) if obs.size else float("nan"))
    if err.size:
        out.update(rmse_m_s=float(np.sqrt(np.mean(err ** 2))), median_abs_error_m_s=float(np.median(np.abs(err))))
    else:
        out.update(rmse_m_s=float("nan"), median_abs_error_m_s=float("nan"))
    return out


#: Seconds ignored at the start when scoring a run (`lobula velocity --skip`'s default).
SCORE_SKIP_S = 2.0


def scoring_skip(ds: xr.Dataset, skip_s: float = SCORE_SKIP_S) -> float:
    """Seconds ignored at the start when scoring ``ds``: ``skip_s``, at most a quarter of the run.

    Short clips (the 1.2 s D435i sample) keep three quarters of their estimates to score.
    """
    t = ds.time.values
    return min(float(skip_s), 0.25 * float(t[-1] - t[0])) if t.size else float(skip_s)


def score_line(sc: dict, skip_s: float) -> str:
    """The one-line score of a run, as the console and the figure's title both print it.

    sc: :func:`score`'s dict (RMSE and median |error| in m/s, observable fraction);
    skip_s: the seconds it ignored.
    """
    if not sc:
        return "no truth: not scored"
    obs = f"observable {100 * sc['observable_fraction']:.1f} % of {sc['n_frames']} estimates"
    if not np.isfinite(sc["rmse_m_s"]):
        return f"scored after {skip_s:.3g} s: no observable estimate to score ({obs})"
    return (f"scored after {skip_s:.3g} s: RMSE {sc['rmse_m_s']:.4f} m/s, median |error| "
            f"{sc['median_abs_error_m_s']:.4f} m/s, {obs}")


def carried_line(sc: dict) -> str | None:
    """One line on the frames the accelerometer carries v̂ through, from :func:`score`'s dict; None where it
    carries none (or there is no truth)."""
    if not sc.get("carried_fraction"):
        return None
    return (f"v̂ carried by the accelerometer on {100 * sc['carried_fraction']:.1f} % of the estimates; the truth "
            f"inside ±2σ on {100 * sc['coverage_2sigma_all']:.0f} % of all (no v̂ counted outside)")


def _stored_readout_config(ds: xr.Dataset) -> dict:
    """The readout's configuration as the run stored it (``attrs["config"]``, JSON), {} where unreadable."""
    try:
        return json.loads(ds.attrs.get("config", "{}")).get("readout", {})
    except (TypeError, ValueError):
        return {}


def scene_depth_line(ds: xr.Dataset) -> str | None:
    """One line on the depth the rest bound took, from the stored ``scene_depth`` (m), or None where the run
    stores none or was given a depth (``readout.rest_depth_max_m``)."""
    ro = _stored_readout_config(ds)
    if "scene_depth" not in ds or ro.get("rest_depth_max_m") is not None:
        return None
    d = ds.scene_depth.values.astype(float)
    if np.isnan(d).all():
        return ("scene depth: none measured (vision never locked on to the accelerometer), so no flow is not read as "
                "standing still; --rest-depth M gives one")
    last = float(d[np.isfinite(d) | np.isinf(d)][-1])
    if np.isinf(last):
        return "scene depth: the fields' median lies beyond what the acceleration shows; no flow bounds no speed"
    return (f"scene depth: the fields' median {last:.1f} m as measured (the rest bound takes "
            f"{float(ro.get('rest_depth_margin', 2.0)):g}× that)")


def never_observable_reason(ds: xr.Dataset) -> str | None:
    """One sentence saying why a run's v̂ is never observable, or None where it is observable somewhere.

    Computed from what the run stores: its forward acceleration ``accel`` (m/s²) low-passed as the
    readout low-passes it (a zero-phase Butterworth of the configuration's ``readout.order`` at
    ``readout.cutoff_hz``) against ``readout.accel_min_m_s2``; else the expansion rates ``r``
    (none finite: the fields measured nothing); else the filter's ``posterior_std`` (``v_std`` in a run
    without it) against ``readout.max_std_m_s``.
    """
    if "observable" not in ds or bool(ds.observable.values.astype(bool).any()):
        return None
    ro = _stored_readout_config(ds)
    accel_min = float(ro.get("accel_min_m_s2", 0.03))
    max_std = float(ro.get("max_std_m_s", 0.1))
    t, a = ds.time.values.astype(float), ds.accel.values.astype(float)
    ok = np.isfinite(a)
    a_lp = a[ok]
    if ok.sum() > 12 and t.size > 1:
        from scipy import signal

        fs = (t.size - 1) / float(t[-1] - t[0])
        wn = float(ro.get("cutoff_hz", 1.0)) / (fs / 2)
        if 0 < wn < 1:
            a_lp = signal.filtfilt(*signal.butter(int(ro.get("order", 2)), wn), a[ok], padlen=min(ok.sum() - 1, 12))
    peak = float(np.max(np.abs(a_lp))) if a_lp.size else 0.0
    if peak < accel_min:
        return (f"never observable: the forward acceleration never exceeded the readout's accel_min "
                f"({accel_min:g} m/s²; at most {peak:.3f} m/s² here, low-passed at "
                f"{float(ro.get('cutoff_hz', 1.0)):g} Hz) — speed cannot be told from vision while it does not "
                f"change; v̂ is NaN throughout")
    if "r" in ds and not np.isfinite(ds.r.values).any():
        return ("never observable: no receptive field measured an expansion rate (r is NaN throughout: too "
                "little texture in view, or the flow failed) — without it vision says nothing of speed; v̂ is NaN "
                "throughout")
    if "vision_locked" in ds and not bool(ds.vision_locked.values.astype(bool).any()):
        z = ds.vision_coupling.values.astype(float)
        refuted = float(ds.vision_refuted.values.astype(bool).mean()) if "vision_refuted" in ds else 0.0
        seen = (f"; refuted on {100 * refuted:.0f} % of the frames, where the acceleration varied and the expansion "
                f"showed no positive correlation" if refuted > 0 else "")
        return (f"never observable: the image's expansion never followed the accelerometer (the fields' ṙ − r² "
                f"against the forward acceleration: Fisher z at most {np.nanmax(z, initial=0.0):.1f}, "
                f"{float(ro.get('coupling_z', 3.0)):g} needed{seen}; lobula.readout.coupling) — vision's κ = a/v is "
                f"noise here (an image stabilised against the body, a scene that moves, or a steady pace with nothing "
                f"to follow), so the speed cannot be told; v̂ is NaN throughout")
    std = ds["posterior_std" if "posterior_std" in ds else "v_std"].values.astype(float) \
        if "v_std" in ds else np.full(1, np.nan)
    low = float(np.nanmin(std)) if np.isfinite(std).any() else float("nan")
    return (f"never observable: the posterior std of v̂ never fell below the readout's max_std ({max_std:g} m/s; "
            f"at best {low:.3f} m/s) — the forward acceleration (up to {peak:.3f} m/s², low-passed) and the "
            f"expansion rates were too weak or too noisy to fix the speed; v̂ is NaN throughout")


#: Each readout in words, for figure captions (each front end's: lobula.front_ends.FrontEnd.description).
READOUT_WORDS = {"kalman": "Kalman filter fusing the expansion rates with the forward acceleration a",
                 "median": "median over fields of the expansion ratio (the paper's readout)"}


def describe_run(ds: xr.Dataset) -> str:
    """The run's front end, then (on a second line) its readout and filter, in words (from ``ds.attrs``)."""
    fe, ro = str(ds.attrs.get("front_end", "?")), str(ds.attrs.get("readout", "?"))
    filt = str(ds.attrs.get("filter", "?"))
    when = ("zero-phase: offline, each estimate uses the whole record" if filt.startswith("zero-phase") else
            "causal: online, each estimate uses only what came before it" + (
                " and a fixed lag" if "fixed lag" in filt else "") if filt.startswith("causal") else filt)
    words = FRONT_ENDS[fe].description if fe in FRONT_ENDS else fe
    return f"front end: {words}\nreadout: {READOUT_WORDS.get(ro, ro)} ({when})"


def velocity_figure(ds: xr.Dataset, skip_s: float | None = None, title: str | None = None):
    """The figure of a velocity run: v̂ with its ±2σ band against truth (top), forward acceleration (bottom).

    ds: the velocity Dataset (:func:`estimate_velocity`, or its NetCDF read back); ``v_std`` is v̂'s
    1σ std (m/s), drawn as v̂ ± 2·v_std; v̂ solid where observable, dotted where the accelerometer carries it.
    skip_s: seconds not scored (default :func:`scoring_skip`, as `lobula velocity` prints it); the title's
    numbers are :func:`score_line` of :func:`score` on ``ds`` with it, the console's numbers, after ``title``
    (default "forward velocity"); below them the front end, readout and filter in words (:func:`describe_run`).
    Returns the matplotlib Figure.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    skip = scoring_skip(ds) if skip_s is None else float(skip_s)
    t = ds.time.values
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6.2), sharex=True, layout="constrained",
                                  gridspec_kw=dict(height_ratios=[3, 1]))
    v, s = ds.v_hat.values, ds.v_std.values
    if np.isfinite(s).any():
        ax.fill_between(t, v - 2 * s, v + 2 * s, color="m", alpha=0.18, lw=0, label="±2σ (2 × v_std)", zorder=2)
    unobs = ~ds.observable.values.astype(bool)
    ax.plot(t, np.where(unobs, np.nan, v), color="m", lw=2.2, label="v̂ estimate", zorder=3)
    if np.isfinite(v[unobs]).any():
        ax.plot(t, np.where(unobs, v, np.nan), color="m", lw=1.4, ls=":", zorder=3,
                label="v̂ carried by the accelerometer (not observable)")
    if "v_true" in ds:
        # Drawn over v̂, thinner and dashed, so it stays visible where the two agree.
        ax.plot(t, ds.v_true.values, color="k", ls="--", lw=1.2, label="truth", zorder=4)
    # Runs stored without the coupling test's flags read as never refuted, locked and informed.
    flag = lambda name, absent: ds[name].values.astype(bool) if name in ds else np.full(len(t), absent)
    refuted, unlocked = flag("vision_refuted", False), ~flag("vision_locked", True)
    bridged = ~unobs & ~flag("vision_informing", True)
    for where, grey, words in ((unobs & refuted, "0.7", "unobservable: expansion not following a"),
                               (unobs & unlocked & ~refuted, "0.8", "unobservable: vision has not fixed v"),
                               (unobs & ~unlocked, "0.88", "unobservable: std too large")):
        if where.any():
            ax.fill_between(t, 0, 1, where=where, transform=ax.get_xaxis_transform(), color=grey, lw=0, label=words,
                            step="mid", zorder=0)
    if bridged.any():
        ax.fill_between(t, 0, 0.04, where=bridged, transform=ax.get_xaxis_transform(), color="tab:cyan", lw=0,
                        label="no vision measurement at this frame (the accelerometer bridges it)", step="mid")
    if skip > 0 and "v_true" in ds:
        ax.axvspan(t[0], t[0] + skip, color="0.5", alpha=0.08, lw=0, label=f"not scored (first {skip:.3g} s)")
    ax.axhline(0, color="0.4", lw=0.8, zorder=1)
    ax.set_ylabel("forward velocity (m/s)\nbelow 0: moving backwards")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    sc = score(ds, skip)
    # A caller's title gets a line of its own: with the scores after it, it ran past the figure's edge.
    head = f"{title}\n{score_line(sc, skip)}" if title else f"forward velocity: {score_line(sc, skip)}"
    if (carried := carried_line(sc)) is not None:
        head += "\n" + carried
    fig.suptitle(f"{head}\n{describe_run(ds)}", fontsize=9)
    ax2.plot(t, ds.accel.values, color="tab:blue", lw=1, label="a")
    ax2.axhline(0, color="0.4", lw=0.8)
    src = str(ds.accel.attrs.get("source", ds.attrs.get("acceleration_source", "")))
    where = ("the IMU's accelerometer, gravity and bias removed" if src.startswith("accelerometer")
             else src or "unknown source")
    ax2.set_title(f"a: forward acceleration (m/s², from {where}), the readout's input beside the flow",
                  fontsize=8, loc="left")
    ax2.set_ylabel("a (m/s²)")
    ax2.set_xlabel("time (s)")
    return fig


def plot_velocity(ds: xr.Dataset, path, title: str | None = None, skip_s: float | None = None):
    """Write :func:`velocity_figure` of ``ds`` as a PNG (atomically); returns ``path``."""
    import matplotlib.pyplot as plt

    from .store import save_figure

    fig = velocity_figure(ds, skip_s, title)
    save_figure(fig, path, provenance=ds.attrs, dpi=120)
    plt.close(fig)
    return path


def apply_velocity_options(cfg, args):
    """Apply the velocity options shared by `velocity` and `compare` (absent or None: unchanged)."""

    opt = lambda name: getattr(args, name, None)
    if opt("filter"):
        cfg.readout.filter = args.filter
    if opt("gap"):
        cfg.flow.gap = args.gap
    if opt("field_size"):
        cfg.fields.size_deg = args.field_size
    for name in ("dis_preset", "dis_grid_px"):
        if opt(name) is not None and cfg.front_end != "dis":
            raise ValueError(f"--{name.replace('_', '-')} sets the DIS flow, but the front end is "
                             f"{cfg.front_end}; drop it or use --front-end dis")
    if opt("dis_preset"):
        cfg.flow.dis_preset = args.dis_preset
    if opt("dis_grid_px") is not None:
        if args.dis_grid_px < 0:
            raise ValueError(f"--dis-grid-px must be ≥ 0 (0: the preset's finest level), got {args.dis_grid_px}")
        cfg.flow.dis_grid_px = args.dis_grid_px
    if opt("epipole"):
        cfg.epipole = args.epipole
    if opt("accel_from_truth"):
        cfg.accel_from_truth = True
    if opt("gyro_bias_from_vision"):
        cfg.gyro_bias_from_vision = True
    if opt("heading_motion"):
        cfg.heading_motion = True
    if opt("lag") is not None:
        if args.lag > 0 and (cfg.readout.filter != "causal" or cfg.readout.method != "kalman"):
            raise ValueError(f"--lag {args.lag:g} is a fixed-lag smoother of the online filter: give --filter causal "
                             f"(the zero-phase filter already sees the whole record; --paper has none)")
        cfg.readout = replace(cfg.readout, lag_s=args.lag)  # validated there (causal kalman readout only)
    if opt("speed_prior") is not None:
        if cfg.readout.method != "kalman":
            raise ValueError("--speed-prior is the kalman readout's prior on v; the paper's median readout (--paper) "
                             "has none: drop one of them")
        cfg.readout = replace(cfg.readout, v_prior_m_s=args.speed_prior)
    if opt("coupling") is not None:
        if cfg.readout.method != "kalman":
            raise ValueError("--coupling gates the kalman readout on vision's coupling to the accelerometer; the "
                             "paper's median readout (--paper) has no such test: drop one of them")
        cfg.readout = replace(cfg.readout, coupling_z=args.coupling)
    if opt("rest_depth") is not None:
        if cfg.readout.method != "kalman":
            raise ValueError("--rest-depth bounds the kalman readout's speed where nothing expands; the paper's median "
                             "readout (--paper) has no rest bound: drop one of them")
        cfg.readout = replace(cfg.readout, rest_depth_max_m=args.rest_depth)
    for name, field in (("saccade_gate", "saccade_gate_deg_s"), ("heading_reset", "heading_reset_deg"),
                        ("heading_walk", "heading_walk")):
        if hasattr(args, name):  # given (None: off)
            if get_front_end(cfg.front_end).derotation == "gaze":
                raise ValueError(f"--{name.replace('_', '-')} sets how the flow front ends read a turning camera; the "
                                 f"{cfg.front_end} front end holds its gaze instead: drop it or use --front-end dis")
            setattr(cfg, field, getattr(args, name))
    if opt("accel_scale_error") is not None:
        cfg.readout = replace(cfg.readout, accel_scale_error=args.accel_scale_error)  # validated there
        if cfg.readout.method != "kalman":
            raise ValueError("--accel-scale-error widens the kalman readout's posterior std; the paper's "
                             "median readout (--paper) states none: drop one of them")
    e = cfg.emd
    front = get_front_end(cfg.front_end)
    if opt("dphi") or opt("drho"):
        e.lattice = replace(e.lattice, dphi_deg=opt("dphi") or e.lattice.dphi_deg,
                            drho_deg=opt("drho") or e.lattice.drho_deg)
    if opt("tau"):
        e.emd = replace(e.emd, tau_s=args.tau)
    if opt("mean_removal"):
        if "emd" not in front.sections:   # the option sets VelocityConfig.emd
            raise ValueError(f"--mean-removal sets the EMD front end's columns, but the front end is {cfg.front_end}; "
                             f"drop it or use --front-end emd")
        e.surround, e.photoreceptor = mean_removal(args.mean_removal, e.photoreceptor)
    if opt("emd_gaze"):
        if front.derotation != "gaze":
            raise ValueError(f"--emd-gaze sets the EMD front end's gaze, but the front end is {cfg.front_end} (the flow "
                             f"front ends derotate their flow exactly); drop it or use --front-end emd")
        e.gaze = args.emd_gaze
    if opt("emd_calibration"):
        from experiments.calibrate import read_calibration
        e.calibration, e.latency_s = read_calibration(args.emd_calibration)
    return cfg


def _velocity_config(args):
    from .parsers import FLO_OPTION_DEFAULTS  # the .flo files' options, which only --front-end flo reads

    cfg = VelocityConfig.paper(args.front_end, args.filter) if args.paper else VelocityConfig(front_end=args.front_end)
    # One front end runs here (compare runs several, each reading the options that are its own).
    emd_only = [f"--{k.replace('_', '-')}" for k in ("dphi", "drho", "tau", "emd_calibration")
                if getattr(args, k, None)]
    if emd_only and "emd" not in get_front_end(cfg.front_end).sections:   # they set VelocityConfig.emd
        raise ValueError(f"{', '.join(emd_only)} set{'s' * (len(emd_only) == 1)} the EMD front end, but the front end "
                         f"is {cfg.front_end}: drop {'it' if len(emd_only) == 1 else 'them'} or use --front-end emd")
    flo_only = [f"--{k.replace('_', '-')}" for k, default in FLO_OPTION_DEFAULTS.items()
                if getattr(args, k, default) != default]
    if flo_only and cfg.front_end != "flo":
        raise ValueError(f"{', '.join(flo_only)} describe{'s' * (len(flo_only) == 1)} the .flo files of --front-end "
                         f"flo, but the front end is {cfg.front_end}: drop {'it' if len(flo_only) == 1 else 'them'}")
    return apply_velocity_options(cfg, args)


def run_velocity(args) -> int:
    from .info import open_footage_from_args
    from .store import write_netcdf

    footage = open_footage_from_args(args)
    cfg = _velocity_config(args)
    if getattr(args, "tum", None) and (footage.imu is None or footage.imu.gyro is None or cfg.accel_from_truth
                                       or not cfg.derotate):
        raise ValueError(f"--tum needs the camera's attitude from the IMU's gyro, which {footage.path} does not give "
                         f"this run (no gyro, --accel-from-truth, or derotation off); drop --tum")
    flo_files = None
    if args.front_end == "flo":
        if not args.flo:
            raise ValueError("--front-end flo needs --flo FILE_OR_DIR")
        p = Path(args.flo)
        flo_files = sorted(p.glob("*.flo")) if p.is_dir() else [p]
    units = FloUnits(args.flo_units, args.flo_gap, *args.flo_size)
    ds = estimate_velocity(footage, cfg, progress=not args.quiet, flo_files=flo_files, flo_units=units)
    # Short clips (the 1.2 s D435i sample) are scored after at most a quarter of their length; the file keeps the
    # skip, so score(ds) reads the numbers printed below from it.
    skip = scoring_skip(ds, args.skip)
    ds.attrs["scored_after_s"] = skip
    write_netcdf(ds, args.out)
    sc = score(ds, skip)
    print(f"wrote {args.out}: {ds.sizes['time']} frames x {ds.sizes['field']} fields "
          f"[{ds.attrs['front_end']}, {ds.attrs['readout']} readout, {ds.attrs['filter']}; "
          f"acceleration: {ds.attrs['acceleration_source']}]")
    for line in calibration_lines(getattr(footage, "calibration", None)):
        print(line)
    if skipped := int(ds.attrs.get("frames_skipped", 0)):
        first = json.loads(ds.attrs.get("frames_skipped_indices", "[]"))[:5]
        print(f"left out {skipped} frame(s) that could not be decoded (--skip-bad-frames): "
              f"{', '.join(map(str, first))}{', ...' if skipped > len(first) else ''}")
    e = ds.epipole_x.values[-1], ds.epipole_y.values[-1]
    print(f"epipole: ({np.degrees(np.arctan(e[0])):+.2f}°, {np.degrees(np.arctan(e[1])):+.2f}°) from the principal point")
    print(f"observable: {100 * float(ds.observable.mean()):.1f} % of all {ds.sizes['time']} estimates")
    if (line := scene_depth_line(ds)) is not None:
        print(line)
    if sc:
        print(score_line(sc, skip))
        if (carried := carried_line(sc)) is not None:
            print(carried)
    why = never_observable_reason(ds) if ds.sizes["time"] >= 3 else None
    if why:
        print(why)
    if ds.sizes["time"] < 3:
        med = np.nanmedian(ds.r.values, axis=1)
        print("too few flows for a velocity readout; median r̄ over fields per flow (1/s): "
              + ", ".join(f"{x:+.3f}" for x in med))
    if args.plot:
        plot_velocity(ds, args.plot, skip_s=skip)
        print(f"wrote {args.plot}")
    if getattr(args, "tum", None):
        n = write_tum(ds, args.tum)
        print(f"wrote {args.tum}: {n} poses (TUM: timestamp tx ty tz qx qy qz qw)")
    return 0


def calibration_lines(cal: dict | None) -> list[str]:
    """The lens, projection, clock offset and IMU axes a self-calibrated camera used
    (:mod:`lobula.readers.self_calibration`), in words."""
    if not cal:
        return []
    out = [f"lens: {cal['lens']}, fx {cal['focal_length_px']:.1f} px ± {100 * cal['focal_length_rel_std']:.0f} % "
           f"({cal['focal_length_source']})"]
    if "clock_offset_s" in cal:
        out.append(f"clock offset: {1e3 * cal['clock_offset_s']:+.1f} ms ({cal['clock_offset_source']})")
    if "projection_source" in cal:
        out.append(f"projection: {cal['projection_source']}")
    if "imu_axes_source" in cal:
        out.append(f"IMU axes: {cal['imu_axes_source']}")
    return out


def write_tum(ds: xr.Dataset, path) -> int:
    """Write the run's trajectory (:func:`lobula.velocity.trajectory.tum_rows`) as a TUM file, atomically;
    returns the number of poses. Raises ValueError where the run has no attitude (no gyro)."""
    from lobula.velocity.trajectory import tum_rows

    from .store import write_text

    if "attitude" not in ds:
        raise ValueError(f"--tum needs the camera's attitude from a gyro, and {ds.attrs.get('footage', 'the footage')} "
                         f"has none; drop --tum")
    rows = tum_rows(ds.time.values, ds.v_hat.values, np.column_stack([ds.epipole_x.values, ds.epipole_y.values]),
                    ds.attitude.values)
    head = (f"# lobula {ds.attrs.get('lobula_version', '')} commit {ds.attrs.get('git_commit', '')}: "
            f"{ds.attrs.get('command_line', '')}\n# timestamp tx ty tz qx qy qz qw\n")
    write_text(path, head + "".join(" ".join(f"{x:.9f}" for x in r) + "\n" for r in rows))
    return len(rows)


def add_parser(subparsers):
    """Register `lobula velocity`'s camera options (:func:`experiments.parsers.add_velocity_parser`, built without
    importing this module; experiments.velocity_command adds the compound eye's)."""
    from .parsers import add_velocity_parser

    return add_velocity_parser(subparsers)
