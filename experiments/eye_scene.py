"""`lobula scene OUT --eye fly`: the compound-eye options and branch of the scene command.

Kept apart from experiments.eye_velocity so that building the `scene` parser imports nothing heavy.
"""
from __future__ import annotations

import time as _time


def add_eye_scene_options(parser) -> None:
    """The compound-eye options of `lobula scene` (experiments.render calls this)."""
    from .parsers import FRACTION, POSITIVE, Number

    parser.add_argument("--eye", default="pinhole", choices=["pinhole", "fly"],
                        help="pinhole: a camera footage folder; fly: two compound eyes' footage (ommatidia × time)")
    parser.add_argument("--dphi", type=Number(0.5, 30), default=5.0,
                        help="--eye fly: interommatidial angle Δφ (deg)")
    parser.add_argument("--drho", type=Number(0, 60, above=True),
                        help="--eye fly: acceptance angle Δρ (deg) (default: Δφ)")
    parser.add_argument("--rate-hz", type=Number(20, 5000), default=500.0,
                        help="--eye fly: sampling rate of the eye (Hz)")
    parser.add_argument("--rays", type=Number(0, 6, integer=True), default=2,
                        help="--eye fly: rings of acceptance rays (0: 1 ray, 1: 7, 2: 19, 3: 37)")
    parser.add_argument("--cast-rate-hz", type=POSITIVE,
                        help="--eye fly: ray-cast the world at this rate (--rate-hz divided by a whole number) and "
                             "interpolate linearly to --rate-hz (default: half of --rate-hz from 200 Hz up, which halves the "
                             "rendering; see stimuli.eye.render_eye_interpolated for why the 10 ms photoreceptors "
                             "allow it; equal to --rate-hz casts every sample)")
    parser.add_argument("--gaze", default="none", choices=["none", "haltere"],
                        help="--eye fly: none: the eyes are fixed on the body; haltere: the head counter-rotates on the "
                             "gyroscope's angular velocity (lobula.gaze: haltere-driven gaze stabilisation), and "
                             "head.csv records the head angles")
    parser.add_argument("--gaze-gain", type=FRACTION, default=0.8,
                        help="--eye fly --gaze haltere: fraction of the body's angular velocity the neck cancels")
    parser.add_argument("--gaze-return", type=POSITIVE, default=0.5, metavar="S",
                        help="--eye fly --gaze haltere: time constant (s) with which the head relaxes back to the "
                             "body axis (lobula.gaze.GazeConfig.tau_return_s; with --gaze-gain 1 and a long return, "
                             "an ideal neck reflex)")
    parser.set_defaults(_eye_only_defaults={a.dest: a.default for a in parser._actions if a.dest in EYE_ONLY})


EYE_ONLY = ("dphi", "drho", "rate_hz", "rays", "cast_rate_hz", "gaze", "gaze_gain", "gaze_return")  # options that mean nothing to the pinhole camera


def refuse_eye_options_for_pinhole(args) -> None:
    """ValueError naming any --eye fly option given with the (default) pinhole camera: it would be ignored."""
    given = [f"--{k.replace('_', '-')}" for k, d in args._eye_only_defaults.items() if getattr(args, k) != d]
    if given:
        raise ValueError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} only to compound-eye "
                         f"footage; add --eye fly, or drop {'it' if len(given) == 1 else 'them'}")


def run_eye_scene(args, cfg) -> int:
    """`lobula scene OUT --eye fly`: the run configuration ``cfg`` rendered onto the compound eye."""
    from lobula.compound_eye import CompoundEye, CompoundEyeConfig
    from lobula.gaze import GazeConfig
    from stimuli.eye import make_eye_run

    eye_cfg = CompoundEyeConfig(dphi_deg=args.dphi, drho_deg=args.drho, rings=args.rays)
    every = 2 if args.rate_hz >= 200.0 else 1   # below 200 Hz the samples are already ≥ 5 ms apart
    if getattr(args, "cast_rate_hz", None) is not None:
        k = args.rate_hz / args.cast_rate_hz
        if not (args.cast_rate_hz > 0 and abs(k - round(k)) < 1e-9 and round(k) >= 1):
            raise ValueError(f"--cast-rate-hz {args.cast_rate_hz:g} must divide --rate-hz {args.rate_hz:g} "
                             f"(e.g. {args.rate_hz / 2:g})")
        every = int(round(k))
    for opt in ("gaze_gain", "gaze_return"):
        if args.gaze == "none" and getattr(args, opt) != args._eye_only_defaults[opt]:
            flag = "--" + opt.replace("_", "-")
            raise ValueError(f"{flag} applies to --gaze haltere; add it, or drop {flag}")
    gaze = GazeConfig(gain=args.gaze_gain, tau_return_s=args.gaze_return) if args.gaze == "haltere" else None
    t0 = _time.perf_counter()
    out = make_eye_run(args.out, cfg, eye_cfg, args.rate_hz, progress=not args.quiet, cast_every=every, gaze=gaze)
    print(f"wrote {out}: {CompoundEye(eye_cfg).summary()}, {int(round(args.duration * args.rate_hz))} samples at "
          f"{args.rate_hz:g} Hz (ray-cast at {args.rate_hz / every:g} Hz) in {_time.perf_counter() - t0:.1f} s")
    return 0
