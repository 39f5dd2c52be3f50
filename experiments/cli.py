"""The ``lobula`` command line: one entry point, one subcommand per protocol."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def _scene(args) -> int:
    from stimuli.scene import SceneConfig
    from stimuli.track import REAL_PROFILE, TrackRunConfig, make_track_run

    profile = args.profile
    if profile is None and not args.builtin_profile and args.constant_velocity is None and REAL_PROFILE.exists():
        profile = str(REAL_PROFILE)
    scene = SceneConfig(seed=args.seed, off_axis_yaw_deg=args.off_axis_yaw, off_axis_pitch_deg=args.off_axis_pitch,
                        rotation_amp_deg=args.rotation, noise_grey=args.noise, exposure_s=args.exposure,
                        floor=not args.no_floor, side_walls=args.side_walls, n_panels=args.panels)
    cfg = TrackRunConfig(profile=profile, start_s=args.start, duration_s=args.duration, scale=args.scale,
                         constant_velocity_m_s=args.constant_velocity, camera_json=args.camera, scene=scene)
    cfg.imu.seed = args.seed
    out = make_track_run(args.out, cfg, progress=not args.quiet)
    print(f"wrote {out} ({int(args.duration * 30)} frames; profile: {profile or 'built-in'})")
    return 0


def apply_velocity_options(cfg, args):
    """Apply the velocity options shared by `velocity` and `compare` (absent or None: unchanged)."""
    from dataclasses import replace

    opt = lambda name: getattr(args, name, None)
    if opt("filter"):
        cfg.readout.filter = args.filter
    if opt("gap"):
        cfg.flow.gap = args.gap
    if opt("field_size"):
        cfg.fields.size_deg = args.field_size
    if opt("dis_preset"):
        cfg.flow.dis_preset = args.dis_preset
    if opt("epipole"):
        cfg.epipole = args.epipole
    if opt("accel_from_truth"):
        cfg.accel_from_truth = True
    e = cfg.emd
    if opt("dphi") or opt("drho"):
        e.lattice = replace(e.lattice, dphi_deg=opt("dphi") or e.lattice.dphi_deg,
                            drho_deg=opt("drho") or e.lattice.drho_deg)
    if opt("tau"):
        e.emd = replace(e.emd, tau_s=args.tau)
    if opt("emd_calibration"):
        from experiments.calibrate import read_calibration
        e.calibration, e.latency_s = read_calibration(args.emd_calibration)
    return cfg


def _velocity_config(args):
    from lobula.config import VelocityConfig

    cfg = VelocityConfig.paper(args.front_end, args.filter) if args.paper else VelocityConfig(front_end=args.front_end)
    return apply_velocity_options(cfg, args)


def _velocity(args) -> int:
    from experiments.store import write_netcdf
    from experiments.velocity import estimate_velocity, plot_velocity, score
    from stimuli.footage import FloUnits, open_footage

    footage = open_footage(args.footage)
    cfg = _velocity_config(args)
    flo_files = None
    if args.front_end == "flo":
        if not args.flo:
            raise SystemExit("lobula velocity: --front-end flo needs --flo FILE_OR_DIR")
        p = Path(args.flo)
        flo_files = sorted(p.glob("*.flo")) if p.is_dir() else [p]
    units = FloUnits(args.flo_units, args.flo_gap, *args.flo_size)
    ds = estimate_velocity(footage, cfg, progress=not args.quiet, flo_files=flo_files, flo_units=units)
    write_netcdf(ds, args.out)
    # Short clips (the 1.2 s D435i sample) are scored after at most a quarter of their length.
    skip = min(args.skip, 0.25 * float(ds.time[-1] - ds.time[0]))
    sc = score(ds, skip)
    print(f"wrote {args.out}: {ds.sizes['time']} frames x {ds.sizes['field']} fields "
          f"[{ds.attrs['front_end']}, {ds.attrs['readout']} readout, {ds.attrs['filter']}; "
          f"acceleration: {ds.attrs['acceleration_source']}]")
    e = ds.epipole_x.values[-1], ds.epipole_y.values[-1]
    print(f"epipole: ({np.degrees(np.arctan(e[0])):+.2f}°, {np.degrees(np.arctan(e[1])):+.2f}°) from the principal point")
    print(f"observable fraction: {float(ds.observable.mean()):.3f}")
    if sc:
        print(f"after {skip:.3g} s: RMSE {sc['rmse_m_s']:.4f} m/s, median |error| {sc['median_abs_error_m_s']:.4f} m/s, "
              f"observable {sc['observable_fraction']:.3f} of {sc['n_frames']} frames")
    if ds.sizes["time"] < 3:
        med = np.nanmedian(ds.r.values, axis=1)
        print("too few flows for a velocity readout; median r̄ over fields per flow (1/s): "
              + ", ".join(f"{x:+.3f}" for x in med))
    if args.plot:
        plot_velocity(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _calibrate(args) -> int:
    from experiments.calibrate import calibrate_emd, write_calibration
    from lobula.config import VelocityConfig
    from stimuli.footage import open_footage

    fo = open_footage(args.footage)
    gains, latency, n = calibrate_emd(fo, VelocityConfig(front_end="emd"), per_field=not args.single_gain)
    write_calibration(gains, latency, args.out, str(fo.path))
    g = np.atleast_1d(gains)
    print(f"wrote {args.out}: {g.size} gain(s) from {n} frames with depth; median {np.median(g):.3f}, "
          f"range {g.min():.3f}..{g.max():.3f}; latency {1000 * latency:.0f} ms")
    return 0


def _bench(args) -> int:
    from experiments.bench import run_bench

    run_bench(frames=args.frames, scales=args.scales, presets=args.presets)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lobula", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("scene", help="render a synthetic track run (footage folder with exact truth)")
    s.add_argument("out", help="output footage folder (must not exist or be empty)")
    s.add_argument("--profile", help="velocity CSV (time_s, v_true_m_s); default: the real FLIVVER run if "
                                     "../shared is present, else a built-in profile")
    s.add_argument("--builtin-profile", action="store_true", help="use the built-in profile")
    s.add_argument("--constant-velocity", type=float, help="constant forward velocity (m/s) instead of a profile")
    s.add_argument("--start", type=float, default=0.0, help="window start in the profile (s)")
    s.add_argument("--duration", type=float, default=30.0, help="duration (s)")
    s.add_argument("--scale", type=float, default=0.5, help="image scale of the D435i camera (0.5 = 320x240)")
    s.add_argument("--camera", help="camera.json with other intrinsics")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--off-axis-yaw", type=float, default=0.0, help="angle between optical axis and motion (deg)")
    s.add_argument("--off-axis-pitch", type=float, default=0.0, help="vertical off-axis angle (deg)")
    s.add_argument("--rotation", type=float, default=0.0, help="yaw/pitch oscillation amplitude (deg)")
    s.add_argument("--noise", type=float, default=1.0, help="pixel noise std (grey levels)")
    s.add_argument("--exposure", type=float, default=0.0, help="motion-blur exposure (s)")
    s.add_argument("--panels", type=int, default=10)
    s.add_argument("--no-floor", action="store_true")
    s.add_argument("--side-walls", action="store_true")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_scene)

    v = sub.add_parser("velocity", help="estimate forward velocity from footage")
    v.add_argument("footage", help="footage folder, or the D435i sample folder")
    v.add_argument("--front-end", default="dis", choices=["dis", "farneback", "flo", "emd"])
    v.add_argument("--out", required=True, help="output NetCDF (written atomically)")
    v.add_argument("--plot", help="PNG of v̂ against truth")
    v.add_argument("--paper", action="store_true", help="the paper's configuration, as its text states it")
    v.add_argument("--filter", default="zero-phase", choices=["zero-phase", "causal"])
    v.add_argument("--gap", type=int, help="frames between the two images of a flow pair (default 6)")
    v.add_argument("--field-size", type=float, help="receptive-field size (deg, default 5)")
    v.add_argument("--dis-preset", choices=["ultrafast", "fast", "medium"])
    v.add_argument("--epipole", choices=["estimate", "principal"])
    v.add_argument("--accel-from-truth", action="store_true",
                   help="forward acceleration from truth.csv instead of imu.csv")
    v.add_argument("--flo", help=".flo file or folder of *_<first>_to_<second>.flo files (front end flo)")
    v.add_argument("--flo-units", default="rad/s", choices=["rad/s", "px"], help="units of the .flo values")
    v.add_argument("--flo-gap", type=float, default=0.2, help="time between the .flo frame pair (s)")
    v.add_argument("--flo-size", type=int, nargs=2, default=[640, 448], metavar=("W", "H"),
                   help="image size the .flo refers to")
    v.add_argument("--dphi", type=float, help="EMD front end: interommatidial angle (deg, default 0.75)")
    v.add_argument("--drho", type=float, help="EMD front end: acceptance angle (deg, default = Δφ)")
    v.add_argument("--tau", type=float, help="EMD front end: delay time constant (s, default 0.010)")
    v.add_argument("--emd-calibration", help="EMD front end: gains JSON from `lobula calibrate-emd` on another scene")
    v.add_argument("--skip", type=float, default=2.0, help="seconds ignored at the start when scoring")
    v.add_argument("--quiet", action="store_true")
    v.set_defaults(func=_velocity)

    c = sub.add_parser("calibrate-emd", help="fit the EMD front end's per-field gains on a synthetic run")
    c.add_argument("footage", help="a synthetic footage folder with depth/ and truth.csv (not a test scene)")
    c.add_argument("--out", required=True, help="gains JSON for `lobula velocity --emd-calibration`")
    c.add_argument("--single-gain", action="store_true", help="one gain for all fields")
    c.set_defaults(func=_calibrate)

    from experiments.depth import add_parser as add_depth
    from experiments.ephys import add_parser as add_ephys
    from experiments.compare import add_parser as add_compare
    from experiments.figures import add_parser as add_figures
    from experiments.sweep import add_parser as add_sweep
    add_depth(sub)
    add_ephys(sub)
    add_compare(sub)
    add_sweep(sub)
    add_figures(sub)

    b = sub.add_parser("bench", help="frames/s per stage and end to end, peak memory")
    b.add_argument("--frames", type=int, default=120)
    b.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.5], help="image scales of the D435i camera")
    b.add_argument("--presets", nargs="+", default=["fast", "medium"], help="DIS presets to time")
    b.set_defaults(func=_bench)
    return p


def main(argv=None) -> int:
    from stimuli.footage import FootageError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (FootageError, FileExistsError, FileNotFoundError, ValueError) as exc:
        print(f"lobula {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
