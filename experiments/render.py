"""`lobula scene`: render a synthetic footage folder with exact ground truth (stimuli.track)."""
from __future__ import annotations


def scene_config_from_args(args):
    """The stimuli.track.TrackRunConfig that `lobula scene`'s options describe."""
    from stimuli.imu import IMUConfig
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, recorded_profile

    flight = getattr(args, "flight", "track")
    if flight != "track":
        # The flight plan draws its own speed: a velocity-profile option would be silently ignored.
        given = [flag for flag, on in (("--profile", args.profile is not None), ("--builtin-profile", args.builtin_profile),
                                       ("--constant-velocity", args.constant_velocity is not None),
                                       ("--peak-speed", args.peak_speed is not None),
                                       ("--profile-start", args.profile_start != "rest"),
                                       ("--speed-scale", args.speed_scale != 1.0), ("--start", args.start != 0.0)) if on]
        if given:
            raise ValueError(f"{', '.join(given)} {'sets' if len(given) == 1 else 'set'} the track's velocity profile; "
                             f"--flight {flight} draws its own speed: drop {'it' if len(given) == 1 else 'them'}")
    profile = args.profile
    if (flight == "track" and profile is None and not args.builtin_profile and args.constant_velocity is None
            and args.peak_speed is None and recorded_profile() is not None):
        profile = str(recorded_profile())
    mipmap = {"auto": None, "on": True, "off": False}[args.mipmap]
    scene = SceneConfig(seed=args.seed, world=args.world, off_axis_yaw_deg=args.off_axis_yaw,
                        off_axis_pitch_deg=args.off_axis_pitch, rotation_amp_deg=args.rotation,
                        rotation3_amp_deg=tuple(args.rotation3), rotation3_band_hz=tuple(args.rotation3_band),
                        noise_grey=args.noise, brightness=args.brightness, contrast=args.contrast,
                        exposure_s=args.exposure, floor=not args.no_floor, side_walls=args.side_walls,
                        n_panels=args.panels, sky_luminance=args.sky, mipmap=mipmap,
                        rolling_shutter_s=getattr(args, "rolling_shutter", 0.0))
    cfg = TrackRunConfig(profile=profile, start_s=args.start, duration_s=args.duration, scale=args.scale,
                         constant_velocity_m_s=args.constant_velocity, random_peak_m_s=args.peak_speed,
                         random_start=args.profile_start, profile_scale=args.speed_scale,
                         camera_json=args.camera, lens=getattr(args, "lens", None), scene=scene,
                         imu=IMUConfig.model(args.imu, seed=args.seed, mount=args.imu_mount), flight=flight)
    return cfg


def run_scene(args) -> int:
    from stimuli.track import make_track_run

    cfg = scene_config_from_args(args)
    from experiments.eye_scene import refuse_eye_options_for_pinhole, run_eye_scene

    if args.eye == "fly":  # compound-eye footage
        if cfg.scene.rolling_shutter_s:
            raise ValueError("--rolling-shutter is a camera sensor's row readout; the compound eye (--eye fly) "
                             "sees every ommatidium at once: drop it")
        camera_only = [o for o, on in (("--lens", cfg.lens is not None), ("--exposure", args.exposure != 0.0),
                                       ("--noise", args.noise != 1.0)) if on]
        if camera_only:  # the eye samples the world through its own optics, photoreceptors and noise
            raise ValueError(f"{', '.join(camera_only)} {'shapes' if len(camera_only) == 1 else 'shape'} the "
                             f"camera's frames; the compound eye (--eye fly) has its own optics and photoreceptor "
                             f"noise: drop {'it' if len(camera_only) == 1 else 'them'}")
        return run_eye_scene(args, cfg)
    refuse_eye_options_for_pinhole(args)
    out = make_track_run(args.out, cfg, progress=not args.quiet)
    src = ("random, peak %g m/s, from %s" % (cfg.random_peak_m_s, cfg.random_start)
           if cfg.random_peak_m_s is not None else cfg.profile or "built-in")
    if cfg.flight != "track":
        src = f"{cfg.flight} flight"
    frames = sum(1 for _ in open(out / "frames.csv")) - 1  # what was written, less the header
    print(f"wrote {out} ({frames} frames; world: {args.world}; profile: {src}; "
          f"IMU: {args.imu}, mounted {args.imu_mount})")
    return 0


def add_parser(subparsers):
    """Register `lobula scene` (see experiments.cli)."""
    from stimuli.worlds import SceneConfig

    from .parsers import CAMERA_SCALE, FINITE, FRACTION, INDEX, NONNEGATIVE, POSITIVE, Number

    s = subparsers.add_parser("scene", help="render a synthetic track run (footage folder with exact truth)")
    s.add_argument("out", help="output footage folder (must not exist or be empty)")
    s.add_argument("--world", default="panels", choices=list(SceneConfig.WORLDS),
                   help="panels: frontal textured panels, backdrop, floor; corridor: floor, ceiling, side walls "
                        "and end wall; ground: ground plane to the horizon, objects, a backdrop 50-200 m away, sky; "
                        "meadow: outdoors at a fly's scale, the ground 0.1-0.4 m below, stems and leaves 0.05-2 m "
                        "from the path, a hedge 2-6 m ahead, sky (default: panels)")
    s.add_argument("--flight", default="track", choices=["track", "saccadic"],
                   help="track: along the straight track at the profile's velocity; saccadic: a seeded fly-like "
                        "flight, straight segments of 0.2-2 s joined by 20-90° body saccades of 50-100 ms, heading "
                        "within ±60° of the track, speed 0.1-1 m/s (stimuli.flight) (default: track)")
    s.add_argument("--profile", help="velocity CSV (time_s, v_true_m_s) (default: the real FLIVVER run if "
                                     "../shared is present, else a built-in profile)")
    s.add_argument("--builtin-profile", action="store_true", help="use the built-in profile")
    s.add_argument("--constant-velocity", type=FINITE,
                   help="constant forward velocity (m/s) instead of a profile (default: none, the profile)")
    s.add_argument("--peak-speed", type=POSITIVE,
                   help="a seeded random smooth profile with this peak |v| (m/s) instead of a CSV profile "
                        "(default: none, the profile)")
    s.add_argument("--profile-start", default="rest", choices=["rest", "motion"],
                   help="with --peak-speed: start at rest (1 s still, then easing in) or in motion")
    s.add_argument("--speed-scale", type=POSITIVE, default=1.0, help="multiply the profile's velocity by this")
    s.add_argument("--start", type=NONNEGATIVE, default=0.0, help="window start in the profile (s)")
    s.add_argument("--duration", type=POSITIVE, default=30.0, help="duration (s)")
    s.add_argument("--scale", type=CAMERA_SCALE, default=0.5, help="image scale of the D435i camera (0.5 = 320x240)")
    s.add_argument("--camera", help="camera.json with other intrinsics (default: the D435i's)")
    s.add_argument("--lens", type=_lens, metavar="MODEL:C1,C2,...",
                   help="render through a distorted lens: kannala-brandt:k1,k2,k3,k4 (OpenCV's fisheye, equidistant) or "
                        "radtan:k1,k2,p1,p2[,k3]; camera.json then carries the distortion, which readers remove "
                        "(default: a pinhole)")
    s.add_argument("--seed", type=INDEX, default=0, help="seeds layout, textures, rotation, profile, noise and IMU")
    s.add_argument("--off-axis-yaw", type=FINITE, default=0.0, help="angle between optical axis and motion (deg)")
    s.add_argument("--off-axis-pitch", type=FINITE, default=0.0, help="vertical off-axis angle (deg)")
    s.add_argument("--rotation", type=NONNEGATIVE, default=0.0, help="yaw/pitch oscillation amplitude (deg)")
    s.add_argument("--rotation3", type=NONNEGATIVE, nargs=3, default=[0.0, 0.0, 0.0], metavar=("YAW", "PITCH", "ROLL"),
                   help="peak amplitudes (deg) of a seeded 3-axis rotation, several incommensurate sinusoids each")
    s.add_argument("--rotation3-band", type=POSITIVE, nargs=2, default=[0.3, 1.5], metavar=("LO", "HI"),
                   help="frequency band (Hz) of the 3-axis rotation's components, LO ≤ HI")
    s.add_argument("--noise", type=NONNEGATIVE, default=1.0, help="pixel noise std (grey levels)")
    s.add_argument("--brightness", type=POSITIVE, default=1.0, help="luminance gain (< 1: a dim scene)")
    s.add_argument("--contrast", type=NONNEGATIVE, default=1.0, help="texture contrast gain (< 1: low contrast)")
    s.add_argument("--sky", type=FRACTION, help="luminance (0..1) where no surface is hit (default: 0.8 for the "
                                            "ground and meadow worlds, else 0)")
    s.add_argument("--mipmap", default="auto", choices=["auto", "on", "off"],
                   help="texture mip-mapping by ray footprint (auto: on for every world but panels)")
    s.add_argument("--exposure", type=NONNEGATIVE, default=0.0, help="motion-blur exposure (s)")
    s.add_argument("--rolling-shutter", type=NONNEGATIVE, default=0.0, metavar="SECONDS",
                   help="rolling shutter: the readout time from the top row to the bottom; row r of a frame "
                        "stamped t is seen at t + r/height·SECONDS, and camera.json records it as "
                        "rolling_shutter_s (default: 0, a global shutter)")
    s.add_argument("--panels", type=Number(1, integer=True), default=10, help="number of frontal panels (panels world)")
    s.add_argument("--no-floor", action="store_true", help="no floor (panels world)")
    s.add_argument("--side-walls", action="store_true", help="add side walls (panels world)")
    # Realistic by default: a constant bias that a whole-record mean removes exactly would let
    # an estimator work only because the IMU is too kind; ideal stays for checks that need known biases.
    s.add_argument("--imu", default="realistic", choices=["ideal", "realistic"],
                   help="IMU errors: realistic (BMI055-like bias random walk, scale-factor and misalignment "
                        "errors; see stimuli.imu) or ideal (constant bias + white noise)")
    s.add_argument("--imu-mount", default="rotated", choices=["camera", "rotated"],
                   help="camera: imu.csv in the camera frame; rotated: IMU x forward/y left/z up plus a seeded "
                        "~1° mount error, imu.csv in the IMU frame and camera.json gets imu_to_camera")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    __import__("experiments.eye_scene").eye_scene.add_eye_scene_options(s)  # --eye fly
    s.set_defaults(func=run_scene)


def _lens(text: str) -> str:
    """``--lens``: checked as :meth:`lobula.lens.LensDistortion.parse` reads it; kept as given."""
    import argparse

    from lobula.lens import LensDistortion

    try:
        LensDistortion.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text
