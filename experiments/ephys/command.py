"""``lobula ephys PROTOCOL``: options, checks that name the fix, outputs (NetCDF, NWB, figure) and a
summary printed from the stored data.

Every option either changes what a protocol does (and is written to the file) or, given to a
protocol it does not apply to, fails with a message naming the protocols it applies to.
Protocol-specific options have no argparse default (their help states the protocol's own
default), so the command knows which ones were given.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

PROTOCOLS = ("tf-tuning", "rf-map", "looming", "velocity-replay", "edges", "current-injection", "white-noise")
ALL = PROTOCOLS
LC_RIG = ("tf-tuning", "rf-map", "looming", "edges")
NEURONS = ("tf-tuning", "looming", "velocity-replay", "edges")

#: option dest → protocols it applies to
APPLIES = {
    # rf-map maps LC field variables, before the neurons: trials, seed and the neuron model do not apply
    # current-injection holds the eye at rest (no EMD, lattice or field option acts on it); white-noise's
    # trials are noise segments and it records no LC unit
    "record": ALL, "trials": NEURONS + ("current-injection", "white-noise"),
    "seed": NEURONS + ("current-injection", "white-noise"), "neuron_model": NEURONS + ("current-injection",),
    "tau": tuple(p for p in ALL if p != "current-injection"), "dphi": tuple(p for p in ALL if p != "current-injection"),
    "field_size": tuple(p for p in ALL if p not in ("current-injection", "white-noise")),
    "device": LC_RIG + ("current-injection", "white-noise"),
    "duration": ("tf-tuning", "looming", "velocity-replay", "edges", "current-injection", "white-noise"),
    "contrast": LC_RIG + ("white-noise",),
    "tf": ("tf-tuning",), "wavelength": ("tf-tuning",), "stimulus": ("tf-tuning",), "settle": ("tf-tuning",),
    "direction": ("tf-tuning",),
    "fields": ("rf-map",), "directions": ("rf-map",), "spacing": ("rf-map",), "extent": ("rf-map",),
    "spot_size": ("rf-map",), "spot_path": ("rf-map",), "spot_speed": ("rf-map",),
    "l_over_v": ("looming",), "max_size": ("looming",), "collision_time": ("looming",),
    "baseline": ("tf-tuning", "looming"),
    "footage": ("velocity-replay",), "rotation": ("velocity-replay",), "haltere_gain": ("velocity-replay",),
    "speed": ("edges",), "bar_width": ("edges",),
    "amplitudes": ("current-injection",), "membrane_noise": ("current-injection",), "noise_std": ("current-injection",),
    "noise": ("white-noise",), "pixel": ("white-noise",), "frame": ("white-noise",), "max_lag": ("white-noise",),
    "strf_extent": ("white-noise",),
    # the compound eye's rig has no lobula plate
    "eye": ("tf-tuning", "rf-map", "looming", "velocity-replay"),
}

#: the lobula plate's physiology protocols (experiments.ephys.contrast, .flicker, .adaptation): no LC units
PLATE = ("contrast", "flicker", "adaptation")
PROTOCOLS = PROTOCOLS + PLATE
APPLIES.update({"photon_rate": PLATE, "channel_noise": PLATE, "c50": PLATE, "adapter": ("adaptation",),
                "gaps": ("adaptation",), "test_duration": ("adaptation",), "adapt_tau": ("adaptation",),
                "adapt_half_g": ("adaptation",)})
for _opt, _which in (("record", PLATE), ("trials", PLATE), ("seed", PLATE), ("tau", PLATE), ("dphi", PLATE),
                     ("device", PLATE), ("contrast", PLATE), ("tf", PLATE), ("wavelength", PLATE),
                     ("duration", ("contrast", "flicker")), ("settle", ("contrast", "flicker"))):
    APPLIES[_opt] = APPLIES[_opt] + _which

S = argparse.SUPPRESS
#: the most --trials a command line may ask for: far beyond any recording's repeats, and a mistyped
#: count (an extra zero or three) is refused at parse time instead of running for days
MAX_TRIALS = 10_000


def _add_rig_options(e) -> None:
    """The recording and rig options of ``lobula ephys`` (every protocol unless marked)."""
    from ..parsers import EMD_TAU, EMD_TAU_RANGE, INDEX, LATTICE_ANGLE, POSITIVE, Number

    g = e.add_argument_group("recording and rig (every protocol unless marked)")
    g.add_argument("--record", nargs="+", metavar="POP.VAR", default=S,
                   help="monitors, e.g. lc.rate lc.spikes[expansion] emd.response[0:10] photoreceptor.v "
                        "t4.response[front-to-back] t5.response[0:20] hs.v vs.v; "
                        "velocity-replay: readout.v readout.rate readout.spikes readout.confidence lc.r lc.rdot "
                        "(default: tf-tuning: probe EMD pairs + the neuron model's variables; rf-map: lc.input; "
                        "looming: the neuron model's variables (rate: lc.rate; poisson: lc.rate lc.spikes; "
                        "lif: lc.v lc.spikes); velocity-replay: all readout variables; edges: T4 and T5 of the "
                        "central column and its neighbours, hs.v, vs.v)")
    g.add_argument("--trials", type=Number(1, MAX_TRIALS, integer=True), default=S,
                   help="[tf-tuning, looming, velocity-replay, edges, current-injection, white-noise] repeats per "
                        f"condition, 1 to {MAX_TRIALS}; white-noise: noise segments, each its own noise (default: 4 "
                        "for spiking models and white-noise; 1 for the deterministic rate model, which refuses more: "
                        "its trials would be identical)")
    g.add_argument("--seed", type=INDEX, default=S,
                   help="[tf-tuning, looming, velocity-replay, edges, current-injection, white-noise] seed of the "
                        "neurons' noise, of the built-in replay scene and of white-noise's stimulus (default: 0)")
    g.add_argument("--neuron-model", choices=["rate", "lif", "poisson"], default=S,
                   help="[tf-tuning, looming, velocity-replay, edges, current-injection] LC units: rate "
                        "(Naka-Rushton), poisson "
                        "(spikes from rates), lif (integrate-and-fire) (default: rate; velocity-replay's readout "
                        "neuron: poisson, or rate; with --eye fly its output neurons: lif, or poisson, or rate)")
    g.add_argument("--tau", type=EMD_TAU, default=S,
                   help=f"[all but current-injection] EMD delay τ (s), {EMD_TAU_RANGE}; edges, white-noise: also "
                        "T4's and T5's (default: 0.035; velocity-replay's EMD front end: 0.01; --eye fly: 0.035 "
                        "everywhere)")
    g.add_argument("--dphi", type=LATTICE_ANGLE, default=S,
                   help="[all but current-injection] interommatidial angle Δφ (degree) (default: 2; "
                        "velocity-replay's front end: 0.75; "
                        "--eye fly: 5)")
    g.add_argument("--field-size", type=POSITIVE, default=S,
                   help="[all but current-injection, white-noise] LC receptive-field size (degree) (default: 10; "
                        "velocity-replay's fields: 5; --eye fly: 30)")
    g.add_argument("--eye", choices=["pinhole", "fly"], default=S,
                   help="the eye recorded: pinhole (the lattice over the D435i's field "
                        "of view and its LC population) or fly (the two compound eyes and the very circuit "
                        "`lobula eye-velocity` estimates velocity with: Δφ 5°, 500 Hz, 30° LC matched filters; "
                        "tf-tuning, rf-map and looming record photoreceptor.v, emd.response, lc.input, lc.pool, lc.r, "
                        "lc.grad, lc.r2; velocity-replay replays eye footage (--footage, from `lobula scene OUT --eye "
                        "fly`) and records lc.r, lc.rdot and the spiking output neurons over trials) (default: pinhole)")
    g.add_argument("--device", default=S, help="[tf-tuning, rf-map, looming, edges, current-injection, white-noise] "
                                               "torch device (default: cpu)")
    g.add_argument("--duration", type=POSITIVE, default=S,
                   help="stimulus duration (s); velocity-replay: the built-in run's only; current-injection: the "
                        "step's; white-noise: each trial's (default: tf-tuning: 2; looming: 1; velocity-replay: 10; "
                        "edges: until the edge has left the eye, plus 0.3; current-injection: 1; white-noise: 5)")
    g.add_argument("--contrast", type=Number(0, 1, above=True), nargs="+", default=S,
                   help="stimulus contrast; several allowed for tf-tuning (default: tf-tuning: 0.5; rf-map: the "
                        "spot's 1.0; looming: the disc's 1.0; edges: 0.5; white-noise: 0.5, binary ±c or the "
                        "Gaussian's SD over the mean)")


def _add_protocol_options(e) -> None:
    """The options of ``lobula ephys`` that belong to one protocol, one group each."""
    from ..parsers import FINITE, INDEX, POSITIVE, Number, haltere_gain

    t = e.add_argument_group("tf-tuning")
    t.add_argument("--tf", type=Number(0, 500, above=True, below=True,
                                       note="below the 500 Hz Nyquist limit of the 1 kHz stimulus"),
                   nargs="+", default=S,
                   help="temporal frequencies (Hz), below the stimulus' Nyquist limit: 500 Hz (1 kHz steps); "
                        "--eye fly: 250 Hz (500 Hz) (default: 16 log-spaced from 0.5 to 32)")
    t.add_argument("--wavelength", type=POSITIVE, default=S, help="grating wavelength (degree) (default: 20)")
    t.add_argument("--stimulus", choices=["rings", "grating"], default=S,
                   help="rings expanding about the epipole, or a planar drum grating (default: rings)")
    t.add_argument("--settle", type=Number(0), default=S,
                   help="time (s) left out before the steady-state mean (default: 0.5)")
    t.add_argument("--direction", type=FINITE, default=S,
                   help="drum grating's motion direction (degree, image: 0 right, 90 down) (default: 0)")
    t.add_argument("--baseline", type=Number(0), default=S,
                   help="[tf-tuning, looming] uniform luminance (no grating, no disc) before stimulus onset (s), "
                        "the PSTH's pre-stimulus baseline; stored times stay relative to onset (looming: "
                        "collision) (default: 0.3)")
    r = e.add_argument_group("rf-map")
    r.add_argument("--fields", type=INDEX, nargs="+", default=S, help="LC field indices to map (default: all)")
    r.add_argument("--directions", type=Number(3, integer=True), default=S,
                   help="spot motion directions, ≥ 3 (default: 4)")
    r.add_argument("--spacing", type=POSITIVE, default=S, help="mapping grid spacing (degree) (default: Δφ)")
    r.add_argument("--extent", type=POSITIVE, default=S,
                   help="mapping grid half-width about each field (degree) (default: 1.6 × field size)")
    r.add_argument("--spot-size", type=POSITIVE, default=S, help="spot FWHM (degree) (default: Δφ)")
    r.add_argument("--spot-path", type=POSITIVE, default=S,
                   help="spot path length per passage (degree) (default: 2Δφ)")
    r.add_argument("--spot-speed", type=POSITIVE, default=S, help="spot speed (degree/s) (default: 50Δφ per s)")
    lo = e.add_argument_group("looming")
    lo.add_argument("--l-over-v", type=POSITIVE, nargs="+", default=S,
                    help="disc half-size over approach speed l/|v| (s) (default: 0.01 0.02 0.04 0.08)")
    lo.add_argument("--max-size", type=Number(0, 180, above=True), default=S,
                    help="disc's angular size cap (degree) (default: 60)")
    lo.add_argument("--collision-time", type=POSITIVE, default=S,
                    help="collision time after stimulus onset (s); the stored time is relative to it "
                         "(default: 0.8 × duration)")
    ed = e.add_argument_group("edges")
    ed.add_argument("--speed", type=POSITIVE, default=S,
                    help="edge (or bar) speed across the eye (degree/s) (default: 50)")
    ed.add_argument("--bar-width", type=POSITIVE, default=S,
                    help="move bars of this width (degree; bright for ON, dark for OFF) instead of edges "
                         "(default: edges)")
    ci = e.add_argument_group("current-injection")
    ci.add_argument("--amplitudes", type=FINITE, nargs="+", default=S,
                    help="current steps into the LC units, the eye at rest: nA for lif units, drive (lc.drive's "
                         "units) for rate and poisson units (default: lif: 0 to 3 nA in 0.25 nA steps; rate, "
                         "poisson: 0 to 3 in steps of 0.25)")
    ci.add_argument("--membrane-noise", choices=["none", "white", "ou"], default=S,
                    help="lif units' membrane noise: none, white (the f-I curve then has Siegert's theory), ou "
                         "(Ornstein-Uhlenbeck, 5 ms) (default: ou, the LC units' own)")
    ci.add_argument("--noise-std", type=Number(0), default=S,
                    help="lif units' membrane noise SD (nA) (default: 0.2)")
    wn = e.add_argument_group("white-noise")
    wn.add_argument("--noise", choices=["binary", "gaussian"], default=S,
                    help="luminance L0(1 + c·ξ) per pixel and frame, ξ = ±1 or a standard normal (default: binary)")
    wn.add_argument("--pixel", type=POSITIVE, default=S,
                    help="square noise pixels on the lattice plane (degree) (default: one per ommatidium)")
    wn.add_argument("--frame", type=POSITIVE, default=S,
                    help="noise frame duration (s), a whole number of the 1 ms model steps (default: 0.001)")
    wn.add_argument("--max-lag", type=POSITIVE, default=S,
                    help="longest lag of the receptive fields (s) (default: 0.15)")
    wn.add_argument("--strf-extent", type=POSITIVE, default=S,
                    help="receptive fields' offsets reach ± this along each cell's axis (degree) (default: 4Δφ)")
    pl = e.add_argument_group(
        "contrast, flicker, adaptation (the lobula plate: lamina, T4/T5, HS/VS; no LC units)",
        "Shared options here: --contrast (contrast: 13 log-spaced from 0.01 to 1; flicker, adaptation: one, 0.5), "
        "--tf (contrast, adaptation: one, 1/(2πτ) of T4's delay; flicker: 1 2 4 8 16), --wavelength (the "
        "grating's, degree: contrast: 60; adaptation: 40; flicker's motion: 20), --duration (contrast: 2; flicker: 3), --settle (contrast: "
        "1; flicker: 1.5), --tau (T4's and T5's delay: 0.035), --trials (with noise: 4; without: 1), --seed (the "
        "noise's: 0)")
    pl.add_argument("--c50", type=Number(0, 1, above=True), default=S,
                    help="the lamina's contrast gain: semi-saturation contrast c50 of the T4/T5 drive, at the "
                         "lamina (default: off)")
    pl.add_argument("--photon-rate", type=POSITIVE, default=S,
                    help="photon shot noise: photons per ommatidium per second at the mean luminance 1 "
                         "(default: no photon noise)")
    pl.add_argument("--channel-noise", type=Number(0), default=S,
                    help="channel noise on the HS/VS membranes: SD of the potential at rest (mV) (default: 0)")
    pl.add_argument("--adapter", type=POSITIVE, default=S,
                    help="[adaptation] adapter duration (s) (default: 3)")
    pl.add_argument("--gaps", type=Number(0), nargs="+", default=S,
                    help="[adaptation] blank gaps between adapter and test (s) (default: 0 0.5 1 1.5 2 3 4 6)")
    pl.add_argument("--test-duration", type=POSITIVE, default=S,
                    help="[adaptation] test duration (s) (default: 0.3)")
    pl.add_argument("--adapt-tau", type=POSITIVE, default=S,
                    help="[adaptation] the HS/VS cells' adaptation time constant τa (s) (default: 1.5)")
    pl.add_argument("--adapt-half-g", type=POSITIVE, default=S,
                    help="[adaptation] conductance (units of g_leak) that halves the adaptation gain (default: 1)")
    v = e.add_argument_group("velocity-replay")
    v.add_argument("--footage", default=S, help="footage folder (default: render a built-in run of --duration)")
    v.add_argument("--rotation", choices=["none", "haltere", "wide-field", "both"], default=S,
                   help="with --eye fly: the eye circuit's rotation handling, as `lobula eye-velocity --rotation` "
                        "(default: haltere)")
    v.add_argument("--haltere-gain", type=haltere_gain, metavar="natural|G", default=S,
                   help="with --eye fly: the haltere gain's prior, as `lobula eye-velocity --haltere-gain` "
                        "(default: natural)")


def add_parser(subparsers):
    """Register ``lobula ephys PROTOCOL ...`` on an argparse subparsers object."""
    e = subparsers.add_parser(
        "ephys", help="virtual electrophysiology: record LC/EMD/photoreceptor/readout neurons",
        description="Virtual electrophysiology: show the model fly a stimulus, record any neuron, get labelled, "
                    "self-describing data (NetCDF with CF-1.10 attributes and/or NWB) and a figure.\n"
                    "Options marked [tf-tuning] etc. apply to those protocols only; giving them to another "
                    "protocol is an error.")
    e.add_argument("protocol", choices=PROTOCOLS, help="tf-tuning | rf-map | looming | velocity-replay | edges | "
                                                        "current-injection | white-noise | contrast | flicker | "
                                                        "adaptation")
    e.add_argument("--out", nargs="+", required=True, metavar="PATH", default=S,
                   help="outputs, by suffix: .nc (NetCDF, CF-1.10) and/or .nwb (Neurodata Without Borders); "
                        "each written atomically")
    e.add_argument("--experimenter", nargs="+", metavar="'LAST, FIRST'", default=S,
                   help="the NWB file's experimenter(s) (default: none written)")
    e.add_argument("--institution", default=S, help="the NWB file's institution (default: none written)")
    e.add_argument("--plot", default=S,
                   help="the protocol's figure: PNG (200 dpi) and a vector PDF beside it (.png or .pdf) "
                        "(default: no figure)")
    _add_rig_options(e)
    _add_protocol_options(e)
    e.add_argument("--quiet", action="store_true", help="no progress bars (velocity-replay's rendering and circuit)")
    e.set_defaults(func=main)
    return e


# =========================================================================== checks

def given(args) -> dict:
    """The options the user gave (protocol-specific ones have no argparse default)."""
    return {k: getattr(args, k) for k in APPLIES if hasattr(args, k)}


def check_applicable(protocol: str, opts: dict) -> None:
    """Refuse options that do not apply to ``protocol``, naming the protocols they apply to."""
    for k in opts:
        if protocol not in APPLIES[k]:
            flag = "--" + k.replace("_", "-")
            raise ValueError(f"{flag} does not apply to {protocol}; it applies to {', '.join(APPLIES[k])}")


def check_outputs(paths) -> list[Path]:
    out = [Path(p) for p in paths]
    bad = [str(p) for p in out if p.suffix.lower() not in (".nc", ".nwb")]
    if bad:
        raise ValueError(f"--out {' '.join(bad)}: use a .nc (NetCDF) or .nwb (Neurodata Without Borders) file name")
    return out


def _one(opts, key, protocol):
    v = opts[key]
    if len(v) != 1:
        raise ValueError(f"{protocol} takes one --{key.replace('_', '-')} value, got {v}")
    return v[0]


def rig_config(protocol: str, opts: dict):
    """The :class:`EphysConfig` of an LC-rig protocol from the given options."""
    from dataclasses import replace

    from lobula._optional import torch_device
    from lobula.population import LCNeurons

    from .rig import EphysConfig

    device = torch_device(opts.get("device", "cpu"))
    cfg = EphysConfig(seed=opts.get("seed", 0), device=device)

    if "dphi" in opts:
        cfg = replace(cfg, lattice=replace(cfg.lattice, dphi_deg=opts["dphi"]))
    if "field_size" in opts:
        cfg = cfg.with_fields(size_deg=opts["field_size"])
    cfg = cfg.with_tau(opts.get("tau")).with_neurons(opts.get("neuron_model"))
    stochastic = LCNeurons(cfg.circuit.population.neurons).stochastic  # from the neuron config alone
    trials = opts.get("trials", 4 if stochastic else 1)
    if not stochastic and trials != 1:
        raise ValueError(f"--trials {trials}: the {cfg.circuit.population.neurons.model} model is deterministic, "
                         f"so every trial would be identical; use --trials 1, or --neuron-model poisson or lif "
                         f"for trial-to-trial variability")
    return replace(cfg, trials=trials)


# =========================================================================== running

def run_protocol(protocol: str, opts: dict, progress: bool = False):
    """Run one protocol from a dict of given options (the command line's, or a test's); returns the Dataset.
    progress: progress bars where a protocol runs long (velocity-replay's rendering and circuit)."""
    from lobula._optional import require_torch

    check_applicable(protocol, opts)
    require_torch("virtual electrophysiology")
    if protocol == "velocity-replay" and opts.get("eye", "pinhole") == "fly":
        return _eye_replay(opts, progress)
    if protocol == "velocity-replay":
        from experiments.replay_protocol import velocity_replay

        footage = Path(opts["footage"]) if "footage" in opts else None
        if footage is not None and footage.is_dir() and (footage / "eye.json").is_file():
            raise ValueError(f"--footage {footage}: compound-eye footage (eye.json, from `lobula scene OUT --eye "
                             f"fly`), which the camera's EMD front end cannot read; add --eye fly to replay it through "
                             f"the compound eye's circuit")
        eye_only = [f"--{k.replace('_', '-')}" for k in ("rotation", "haltere_gain") if k in opts]
        if eye_only:
            raise ValueError(f"{', '.join(eye_only)} set(s) the compound eye's circuit; the camera's EMD front end "
                             f"has no haltere subtraction (add --eye fly)")
        model = opts.get("neuron_model", "poisson")
        if model == "lif":
            raise ValueError("velocity-replay's readout neuron is a rate or Poisson neuron; use --neuron-model "
                             "rate or poisson")
        if "footage" in opts and "duration" in opts:
            raise ValueError("--duration sets the built-in run's length; footage has its own (drop --duration)")
        if model == "rate" and opts.get("trials", 1) != 1:
            raise ValueError(f"--trials {opts['trials']}: the rate readout is deterministic, so every trial would "
                             f"be identical; use --trials 1, or --neuron-model poisson")
        return velocity_replay(opts.get("footage"), trials=opts.get("trials", 4 if model == "poisson" else 1),
                               progress=progress,
                               seed=opts.get("seed", 0), spiking=model == "poisson",
                               duration_s=opts.get("duration", 10.0), tau_s=opts.get("tau"),
                               dphi_deg=opts.get("dphi"), field_size_deg=opts.get("field_size"),
                               record=opts.get("record"))
    if protocol == "current-injection":
        from .injection import run_from_options
        return run_from_options(opts)
    if protocol == "white-noise":
        from .white_noise import run_from_options
        return run_from_options(opts)
    if protocol in PLATE:
        from .plate import run_plate_protocol
        return run_plate_protocol(protocol, opts)
    kw = stimulus_kwargs(protocol, opts)
    if opts.get("eye", "pinhole") == "fly":
        from .eye_rig import run_eye_protocol

        if "baseline" in opts:
            raise ValueError("--baseline: the compound eye's protocols start at stimulus onset; drop it, or "
                             "record the pinhole eye")

        return run_eye_protocol(protocol, opts, kw)
    from .edges import edges
    from .protocols import looming, rf_map, tf_tuning

    run = {"tf-tuning": tf_tuning, "rf-map": rf_map, "looming": looming, "edges": edges}[protocol]
    return run(rig_config(protocol, opts), record=opts.get("record"), **kw)


def _eye_replay(opts: dict, progress: bool = False):
    """``lobula ephys velocity-replay --eye fly``: the compound eye's circuit on eye footage (or a built-in run)."""
    from experiments.replay_protocol import eye_velocity_replay

    model = opts.get("neuron_model", "lif")
    if "footage" in opts and "duration" in opts:
        raise ValueError("--duration sets the built-in run's length; footage has its own (drop --duration)")
    if "footage" in opts and "dphi" in opts:
        raise ValueError("--dphi: eye footage keeps the Δφ it was rendered at; render it with `lobula scene OUT --eye "
                         "fly --dphi …`, or drop --footage for the built-in run")
    if model == "rate" and opts.get("trials", 1) != 1:
        raise ValueError(f"--trials {opts['trials']}: the output neurons' rates are deterministic, so every trial "
                         f"would be identical; use --trials 1, or --neuron-model lif or poisson")
    return eye_velocity_replay(opts.get("footage"), trials=opts.get("trials", 1 if model == "rate" else 4),
                               progress=progress,
                               seed=opts.get("seed", 0), spike_model=None if model == "rate" else model,
                               duration_s=opts.get("duration", 10.0), tau_s=opts.get("tau"),
                               dphi_deg=opts.get("dphi"), field_size_deg=opts.get("field_size"),
                               rotation=opts.get("rotation"), haltere_gain=opts.get("haltere_gain"),
                               record=opts.get("record"))


#: command-line option -> protocol keyword, per protocol (the same for the pinhole lattice and the fly eye)
_STIMULUS_OPTIONS = {
    "tf-tuning": (("tf", "temporal_frequencies_hz"), ("contrast", "contrasts"), ("duration", "duration_s"),
                  ("wavelength", "wavelength_deg"), ("stimulus", "stimulus"), ("settle", "settle_s"),
                  ("direction", "direction_deg"), ("baseline", "baseline_s")),
    "rf-map": (("fields", "fields"), ("directions", "directions"), ("spacing", "spacing_deg"),
               ("extent", "extent_deg"), ("spot_size", "spot_size_deg"), ("spot_path", "path_deg"),
               ("spot_speed", "speed_deg_s")),
    "looming": (("l_over_v", "l_over_v_s"), ("duration", "duration_s"), ("max_size", "max_size_deg"),
                ("collision_time", "t_collision_s"), ("baseline", "baseline_s")),
    "edges": (("speed", "speed_deg_s"), ("bar_width", "bar_width_deg"), ("duration", "duration_s")),
}


def stimulus_kwargs(protocol: str, opts: dict) -> dict:
    """The stimulus keywords of tf-tuning, rf-map, looming or edges from the given options (checked)."""
    kw = {k2: opts[k] for k, k2 in _STIMULUS_OPTIONS[protocol] if k in opts}
    if protocol == "tf-tuning" and "direction" in opts and opts.get("stimulus", "rings") != "grating":
        raise ValueError("--direction moves the drum grating; rings expand about the epipole "
                         "(add --stimulus grating)")
    if protocol != "tf-tuning" and "contrast" in opts:
        kw["contrast"] = _one(opts, "contrast", protocol)
    return kw


# =========================================================================== summary from the stored data

def _med(x) -> str:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return "n/a (none recorded)" if x.size == 0 else f"{np.median(x):.3g} (range {x.min():.3g}–{x.max():.3g})"


def summary(ds) -> list[str]:
    """Lines that describe a stored recording, each naming its selection; computed from ``ds`` only."""
    p = ds.attrs.get("protocol")
    lines = ["sizes: " + ", ".join(f"{k}={v}" for k, v in ds.sizes.items())]
    for d in ("temporal_frequency_hz", "contrast", "l_over_v_s", "motion"):
        if d in ds.coords:
            vals = ds[d].values
            lines.append(f"{d} values: " + ", ".join(f"{v:g}" if np.issubdtype(vals.dtype, np.number) else str(v)
                                                     for v in vals))
    # Only a recording of neurons (LC units, readout neurons) has a neuron model: rf-map maps field variables,
    # before any neuron; the plate's protocols, white-noise and edges' default monitors record none.
    neurons = any("neuron" in ds[v].dims or "unit" in ds[v].dims for v in ds.data_vars)
    if p != "rf-map" and neurons:
        lines.append(f"neuron model {ds.attrs.get('neuron_model')}, {ds.attrs.get('trials')} trial(s) stored"
                     + (f" ({ds.attrs['trials_note']})" if ds.attrs.get("trials_note") else ""))
    if p == "tf-tuning":
        lines.append(f"optimum 1/(2πτ) = {ds.attrs['optimum_hz']:.3g} Hz (τ = {ds.attrs['emd_tau_s'] * 1e3:g} ms)")
        for v in ds.data_vars:
            if not v.endswith("_peak_temporal_frequency_hz"):
                continue
            da = ds[v]
            base = v.replace("_peak_temporal_frequency_hz", "")
            if base == "lc_v":  # a LIF unit's mean membrane potential falls as its rate rises: no tuning peak
                continue
            for c in ds.contrast.values:
                x = da.sel(contrast=c)
                if "neuron" in x.dims:
                    types = ds.neuron_type.sel(neuron=x.neuron).values
                    for ty in ("expansion",):
                        sel = x.isel(neuron=np.nonzero(types == ty)[0])
                        lines.append(f"{base}: peak temporal frequency (Hz) of the {int(np.isfinite(sel).sum())} "
                                     f"recorded {ty} units at contrast {c:g}: median {_med(sel)}")
                    lines.append(f"{base}: peak temporal frequency (Hz) of all {int(np.isfinite(x).sum())} recorded "
                                 f"units at contrast {c:g}: median {_med(x)}")
                else:
                    lines.append(f"{base}: peak temporal frequency (Hz) of the {int(np.isfinite(x).sum())} recorded "
                                 f"{x.dims[-1]}s at contrast {c:g}: median {_med(x)}")
    elif p == "rf-map":
        err = np.hypot(ds.rf_centre_azimuth_deg - ds.field_azimuth_deg,
                       ds.rf_centre_elevation_deg - ds.field_elevation_deg)
        lines.append(f"{ds.sizes['field']} mapped field(s) {ds.field.values.tolist()}: centre error (degree) median "
                     f"{_med(err)}; size (degree) median {_med(ds.rf_size_deg)} vs designed "
                     f"{_med(ds.field_size_deg)}")
    elif p == "looming":
        for v in ds.data_vars:
            if v.endswith("_peak") and "neuron" in ds[v].dims:
                ex = ds[v].isel(neuron=np.nonzero(ds.neuron_type.sel(neuron=ds[v].neuron).values == "expansion")[0])
                for lv in ds.l_over_v_s.values:
                    a = ex.sel(l_over_v_s=lv, motion="approach")
                    r = ex.sel(l_over_v_s=lv, motion="recede")
                    lines.append(f"{v} ({ds[v].attrs.get('units', '')}), {int(np.isfinite(a).sum())} expansion units, "
                                 f"l/|v| = {lv:g} s: approach median {_med(a)}; recede median {_med(r)}")
            if v.endswith("_time_of_peak_s") and "field" in ds[v].dims and "field_sees_disc" in ds.coords:
                reached = ds[v].isel(field=np.flatnonzero(ds.field_sees_disc.values))
                lines.append(f"{v} (s relative to collision), the {reached.sizes['field']} fields the disc reaches, "
                             "approach, per l/|v|: " + "; ".join(
                                 f"{lv:g} s: {_med(reached.sel(l_over_v_s=lv, motion='approach'))}"
                                 for lv in ds.l_over_v_s.values))
            if v.endswith("_time_of_peak_s") and "neuron" in ds[v].dims:
                ex = ds[v].isel(neuron=np.nonzero(ds.neuron_type.sel(neuron=ds[v].neuron).values == "expansion")[0])
                lines.append(f"{v} (s relative to collision), expansion units, approach, per l/|v|: " + "; ".join(
                    f"{lv:g} s: {_med(ex.sel(l_over_v_s=lv, motion='approach'))}" for lv in ds.l_over_v_s.values))
                from .published import looming_agreement
                mean = np.nanmean(ex.sel(motion="approach").transpose("l_over_v_s", ...).values.reshape(
                    ds.sizes["l_over_v_s"], -1), axis=1) if np.isfinite(ex.values).any() else ex.values[:0]
                a = looming_agreement(ds.l_over_v_s.values, mean) if mean.size else None
                if a is not None:
                    lines.append(f"{v}: slope of peak time vs l/|v| {a['model_slope']:.3g} (angular threshold "
                                 f"{a['model_theta_threshold_deg']:.3g} degree); locust LGMD (Gabbiani et al. 1999) "
                                 f"{a['published_slope']:.3g} ({a['published_theta_threshold_deg']:g} degree): "
                                 f"ratio {a['slope_ratio']:.3g}")
    elif p == "edges":
        from .edges import edges_summary
        from .published import edges_agreement
        lines.extend(edges_summary(ds))
        a = edges_agreement(ds)
        lines.append("published T4/T5 selectivity (Maisak et al. 2013; T4 ON, T5 OFF, every layer direction selective): "
                     + "; ".join(f"{c.upper()} polarity index {a[f'{c}_polarity_index']:+.3g} (+1: "
                                 f"{a[f'{c}_published_polarity'].upper()} only), DSI > 0 in "
                                 f"{a[f'{c}_selective_fraction']:.0%} of layers" for c in ("t4", "t5"))
                     + f"; polarity agrees: {'yes' if a['polarity_agrees'] else 'no'}")
    elif p == "current-injection":
        from .injection import injection_summary
        lines.extend(injection_summary(ds))
    elif p == "white-noise":
        from .white_noise import white_noise_summary
        lines.extend(white_noise_summary(ds))
    elif p in PLATE:
        from .adaptation import adaptation_summary
        from .contrast import contrast_summary
        from .flicker import flicker_summary
        lines.extend({"contrast": contrast_summary, "flicker": flicker_summary, "adaptation": adaptation_summary}[p](ds))
    elif p == "velocity-replay":
        from .replay_figures import replay_scores
        for k, val in replay_scores(ds).items():
            lines.append(f"{k}: {val:.4f}")
    return lines


def write_outputs(ds, outs, **nwb_metadata) -> list[Path]:
    """Write ``ds`` to each path of ``outs`` by its suffix (.nc, .nwb); nwb_metadata: experimenter,
    institution for the NWB file (see :func:`experiments.nwb.write_nwb`)."""
    from experiments.store import write_netcdf

    written = []
    for o in outs:
        if o.suffix.lower() == ".nc":
            written.append(write_netcdf(ds, o))
        else:
            from experiments.nwb import write_nwb
            written.append(write_nwb(ds, o, **nwb_metadata))
    return written


def main(args) -> int:
    """Handler of ``lobula ephys``: run the protocol, write its outputs and figure, print a summary."""
    opts = given(args)
    outs = check_outputs(args.out)
    plot = getattr(args, "plot", None)
    if plot and Path(plot).suffix.lower() not in (".png", ".pdf"):
        raise ValueError(f"--plot {plot}: use a .png or .pdf file name (both are written)")
    meta = {k: getattr(args, k) for k in ("experimenter", "institution") if hasattr(args, k)}
    if meta and not any(o.suffix.lower() == ".nwb" for o in outs):
        raise ValueError(f"{', '.join('--' + k for k in meta)} {'is' if len(meta) == 1 else 'are'} written into the "
                         f"NWB file only: add a .nwb to --out, or drop {'it' if len(meta) == 1 else 'them'}")
    blank = [k for k, v in meta.items() if not all(str(x).strip() for x in (v if isinstance(v, list) else [v]))]
    if blank:
        raise ValueError(f"--{blank[0]}: give a name, not an empty one")
    ds = run_protocol(args.protocol, opts, progress=not args.quiet)
    for path in write_outputs(ds, outs, **meta):
        print(f"wrote {path} ({args.protocol})")
    for line in summary(ds):
        print("  " + line)
    if plot:
        from .figures import plot_recording
        for path in plot_recording(ds, plot):
            print(f"wrote {path}")
    return 0


def parse_command(argv: list[str]):
    """Parse ``ephys …`` arguments with this module's parser (for tests and notebooks)."""
    parser = argparse.ArgumentParser(prog="lobula")
    add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


