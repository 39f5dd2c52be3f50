"""`lobula scene`: render a synthetic footage folder with exact ground truth (stimuli.track)."""
from __future__ import annotations


def run_scene(args) -> int:
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
    if args.eye == "fly":  # compound-eye footage (issue 11): experiments.eye_velocity
        from experiments.eye_scene import run_eye_scene; return run_eye_scene(args, cfg)
    out = make_track_run(args.out, cfg, progress=not args.quiet)
    print(f"wrote {out} ({int(args.duration * 30)} frames; profile: {profile or 'built-in'})")
    return 0


def add_parser(subparsers):
    """Register `lobula scene` (see experiments.cli)."""
    s = subparsers.add_parser("scene", help="render a synthetic track run (footage folder with exact truth)")
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
    __import__("experiments.eye_scene").eye_scene.add_eye_scene_options(s)  # --eye fly (issue 11)
    s.set_defaults(func=run_scene)
