"""`lobula velocity`: the command. Camera footage goes to :mod:`experiments.velocity`;
compound-eye footage (``lobula scene OUT --eye fly``) to the eye's own circuit in
:mod:`experiments.eye_velocity`, so that ``lobula velocity EYE_FOOTAGE --front-end emd``
and ``lobula eye-velocity`` give the same numbers.

The dispatch lives here, above both modules, so that neither imports the other's command:
the eye's pipeline builds on the camera's readout inputs (eye_velocity imports velocity),
and the camera's module needs nothing of the eye.
"""
from __future__ import annotations


#: `lobula velocity` options that only compound-eye footage takes (None: not given); the same as `lobula eye-velocity`'s
EYE_ONLY_OPTIONS = ("rotation", "haltere_gain", "readout", "uncertainty", "seed", "spike_model", "membrane_noise")


def add_parser(subparsers):
    """Register `lobula velocity` (see experiments.cli): the camera options of
    :func:`experiments.parsers.add_velocity_parser`, and the compound-eye options of `lobula eye-velocity`
    (refused on camera footage). Building it imports nothing heavy."""
    from .parsers import HALTERE_GAIN_HELP, INDEX, NONNEGATIVE, SPIKE_MODELS, add_velocity_parser, haltere_gain

    p = add_velocity_parser(subparsers)
    g = p.add_argument_group("compound-eye footage only (`lobula scene OUT --eye fly`; as `lobula eye-velocity`)")
    g.add_argument("--rotation", choices=["none", "haltere", "wide-field", "both"],
                   help="rotation handling of the eye's circuit (default: haltere)")
    g.add_argument("--haltere-gain", type=haltere_gain, metavar="natural|G",
                   help=HALTERE_GAIN_HELP + " (default: natural)")
    g.add_argument("--readout", choices=["kalman", "spikes", "neuron", "neuron-rate"],
                   help="the eye's readout; spikes and neuron decode causally: add --filter causal (default: kalman)")
    g.add_argument("--uncertainty", choices=["halves", "posterior"],
                   help="v_std of the kalman/spikes readouts (see `lobula eye-velocity --help`) (default: halves)")
    g.add_argument("--seed", type=INDEX, help="seed of the output neurons' spikes (--readout spikes or neuron) "
                                              "(default: 0)")
    g.add_argument("--spike-model", choices=SPIKE_MODELS,
                   help="how the output neurons spike (--readout spikes or neuron) (default: lif)")
    g.add_argument("--membrane-noise", type=NONNEGATIVE, metavar="MV",
                   help="the LIF output neurons' membrane noise SD in mV (default: 1.0)")
    p.set_defaults(func=run)


def run(args) -> int:
    from stimuli.eye import is_eye_footage

    if is_eye_footage(args.footage):
        return run_on_eye_footage(args)
    given = [f"--{k.replace('_', '-')}" for k in EYE_ONLY_OPTIONS if getattr(args, k, None) is not None]
    if given:
        raise ValueError(f"{args.footage}: {', '.join(given)} set(s) the compound eye's circuit and readout and does "
                         f"not apply to camera footage; drop it, or run on eye footage (`lobula scene OUT --eye fly`)")
    from .velocity import run_velocity
    return run_velocity(args)


#: `lobula velocity` options that carry over to eye footage (the rest must stay at their defaults)
_VELOCITY_OPTIONS_ON_EYE = ("footage", "front_end", "out", "plot", "filter", "field_size", "tau", "accel_from_truth",
                            "accel_scale_error", "mean_removal", "skip", "quiet", "func", "command") + EYE_ONLY_OPTIONS


def run_on_eye_footage(args) -> int:
    """`lobula velocity EYE_FOOTAGE --front-end emd …`: the eye's circuit, as `lobula eye-velocity`.

    --filter, --field-size, --tau, --mean-removal, --accel-from-truth, --accel-scale-error, --skip, --plot and the
    eye-only --rotation, --haltere-gain, --readout, --uncertainty, --seed, --spike-model and --membrane-noise mean
    what they mean for `lobula eye-velocity` (so the two commands give the same numbers for the same options;
    `lobula velocity`'s --filter defaults to zero-phase, eye-velocity's to causal). Every other
    option of `lobula velocity` describes a camera front end and is refused, naming the fix.
    """
    import argparse

    from . import velocity as _velocity
    from .eye_velocity import run_eye_velocity

    if args.front_end != "emd":
        raise ValueError(f"{args.footage}: compound-eye footage holds ommatidial luminance, not camera frames, "
                         f"so --front-end {args.front_end} cannot run on it; use --front-end emd (the eye's "
                         f"photoreceptors, EMDs and LC fields)")
    parser = argparse.ArgumentParser()
    _velocity.add_parser(parser.add_subparsers(dest="command"))
    defaults = vars(parser.parse_args(["velocity", "X", "--out", "Y"]))
    if getattr(args, "lag", None):
        raise ValueError(f"{args.footage}: --lag (a fixed-lag smoother) is the camera pipeline's readout option; the "
                         f"eye's readout stays online, as the fly's must: drop --lag, or run the camera "
                         f"footage of the same world")
    given = [k for k, v in vars(args).items() if k not in _VELOCITY_OPTIONS_ON_EYE and k in defaults
             and v != defaults[k]]
    # no default: present when given
    given += [k for k in ("saccade_gate", "heading_reset", "heading_walk") if hasattr(args, k)]
    if given:
        flags = ", ".join("--" + k.replace("_", "-") for k in sorted(given))
        raise ValueError(f"{args.footage}: {flags} set(s) a camera front end and does not apply to compound-eye "
                         f"footage (Δφ and Δρ are the footage's own, from eye.json: re-render with "
                         f"`lobula scene OUT --eye fly --dphi …`); drop it, or see `lobula eye-velocity --help`")
    ro = getattr(args, "readout", None)
    if ro in ("spikes", "neuron", "neuron-rate") and args.filter == "zero-phase":
        raise ValueError(f"--readout {ro} decodes causally; add --filter causal (`lobula velocity`'s --filter "
                         f"defaults to zero-phase)")
    ns = argparse.Namespace(footage=args.footage, out=args.out, plot=args.plot, rotation=getattr(args, "rotation", None),
                            haltere_gain=getattr(args, "haltere_gain", None),
                            mean_removal=getattr(args, "mean_removal", None),
                            field_size=args.field_size, tau=args.tau, filter=args.filter,
                            accel_from_truth=args.accel_from_truth, accel_scale_error=args.accel_scale_error,
                            skip=args.skip, readout=ro,
                            uncertainty=getattr(args, "uncertainty", None), seed=getattr(args, "seed", None),
                            spike_model=getattr(args, "spike_model", None),
                            membrane_noise=getattr(args, "membrane_noise", None), quiet=getattr(args, "quiet", False))
    return run_eye_velocity(ns)
