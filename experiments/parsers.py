"""The options of the ``lobula`` subcommands whose code needs torch, OpenCV or xarray, and the
argparse ``type=`` checks every subcommand's numeric options use.

This module imports only the standard library at import, so building a parser, printing ``--help`` and
refusing a mistyped option or a bad value take a fraction of a second: the code that runs a
command is imported only when it runs (:class:`LazyCommand`). Each command's module keeps an
``add_parser`` that builds its parser from here. A few defaults and choices are written here
as the literal values of the constants they mirror (the depth run's settings, the lock-on
tolerance, the mean-removal and spike-model names, the figure names); tests/test_cli.py checks
each against its source.

Help-text rule (experiments.cli's formatter shows it): every option's help ends in one
``(default: …)``. The formatter writes it from the option's default; where the default is
decided later (None: the configuration's own value, or one chosen from the data; argparse's
SUPPRESS: an option the command must know was given), the help text writes it and says what
is chosen.
"""
from __future__ import annotations

import argparse
import importlib
import math


# ----------------------------------------------------------------------------- value checks
class Number:
    """An argparse ``type=``: a number in a range, refused at parse time with the range named.

    low, high: the bounds (None: unbounded); above, below: exclude the bound itself;
    integer: whole numbers only; inf: +inf is allowed as well (a bound that disables a
    check); note: where the value goes, added to the message (e.g. the configuration field
    whose own check it mirrors). NaN is always refused, and ±inf unless ``inf``.
    """

    def __init__(self, low: float | None = None, high: float | None = None, *, above: bool = False,
                 below: bool = False, integer: bool = False, inf: bool = False, note: str = ""):
        self.low, self.high, self.above, self.below = low, high, above, below
        self.integer, self.inf, self.note = integer, inf, note

    def __str__(self) -> str:
        kind = "a whole number" if self.integer else "a number"
        lo, hi = self.low, self.high
        if lo is not None and hi is not None:
            text = f"{kind} in {'(' if self.above else '['}{lo:g}, {hi:g}{')' if self.below else ']'}"
        elif lo is not None:
            text = f"{kind} {'>' if self.above else '≥'} {lo:g}"
        elif hi is not None:
            text = f"{kind} {'<' if self.below else '≤'} {hi:g}"
        else:
            text = f"a finite {kind[2:]}"
        return text + (" or inf" if self.inf else "") + (f" ({self.note})" if self.note else "")

    def __repr__(self) -> str:  # argparse names a type by its repr in some of its own messages
        return str(self)

    def __call__(self, text: str) -> float | int:
        try:
            x = int(text) if self.integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {self}, got {text!r}") from None
        finite = self.integer or math.isfinite(x)
        ok = (finite or (self.inf and x == math.inf)) and not math.isnan(x)
        if ok and self.low is not None:
            ok = x > self.low if self.above else x >= self.low
        if ok and self.high is not None and finite:
            ok = x < self.high if self.below else x <= self.high
        if not ok:
            raise argparse.ArgumentTypeError(f"must be {self}, got {text!r}")
        return x


POSITIVE = Number(0, above=True)
NONNEGATIVE = Number(0)
#: a rendered camera's scale of the D435i's 640×480: 4 gives 2560×1920, whose supersampled render needs GBs
CAMERA_SCALE = Number(0, 4, above=True, note="times the D435i's 640×480")


def positive_or_none(text: str) -> float | None:
    """An argparse ``type=``: a number > 0, or ``none`` (the check it sets is off)."""
    if text.strip().lower() == "none":
        return None
    try:
        return POSITIVE(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be a number > 0 or none, got {text!r}") from None


FINITE = Number()
COUNT = Number(1, integer=True)          # how many of something: ≥ 1
INDEX = Number(0, integer=True)          # a seed, an index, a count that may be zero
FRACTION = Number(0, 1)
#: interommatidial and acceptance angles of the camera's EMD lattice (lobula.lattice.LatticeConfig's range, degrees)
LATTICE_ANGLE = Number(0, 60, above=True, below=True)
#: an image size in pixels
PIXELS = Number(1, integer=True)
#: an EMD's delay time constant (s): flies' are 10 to 100 ms (lobula.emd.EMDConfig.tau_s); 1 ms to 1 s leaves room
#: either side, and a longer delay puts the correlator's optimum below 0.16 Hz and its settling beyond most runs
EMD_TAU = Number(0.001, 1.0, note="s, lobula.emd.EMDConfig.tau_s; flies': 0.01 to 0.1")
#: --tau's help after what the delay is
EMD_TAU_RANGE = "0.001 to 1 (flies': 0.01 to 0.1)"


def haltere_gain(text: str) -> str:
    """``--haltere-gain``: "natural" or a number in (0, 1.5]; the text is kept as given (the eye's options parse it)."""
    try:
        ok = text == "natural" or 0.0 < float(text) <= 1.5  # also refuses NaN
    except ValueError:
        ok = False
    if not ok:
        raise argparse.ArgumentTypeError(f"must be 'natural' or a number in (0, 1.5] (1: the unit gain), got {text!r}")
    return text


def seeds(text: str) -> str:
    """``--seeds``: a count N (seeds 0..N-1) or a comma-separated list, as experiments.suite.parse_seeds reads
    it; the text is kept as given."""
    from .families import parse_seeds

    try:
        parse_seeds(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive count N (seeds 0..N-1) or a comma-separated list of "
                                         f"seeds ('7,' for seed 7 alone), got {text!r}") from None
    return text


class LazyCommand:
    """A subcommand's ``func``: ``"module:function"``, imported when the command runs, not when it is parsed.

    A plain object, so that the parsed arguments still pickle (depth-suite hands them to worker processes).
    """

    def __init__(self, target: str):
        self.target = target

    def __call__(self, args) -> int:
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)(args)

    def __repr__(self) -> str:
        return f"LazyCommand({self.target!r})"

    def __eq__(self, other) -> bool:
        return isinstance(other, LazyCommand) and other.target == self.target

    def __hash__(self) -> int:
        return hash(self.target)


# ----------------------------------------------------------------------------- shared help texts
#: the mean-removal names (sorted keys of lobula.photoreceptor.MEAN_REMOVAL)
MEAN_REMOVAL = ("space", "time")
#: the output neurons' spike models (sorted keys of lobula.readout_neuron.SPIKE_MODELS)
SPIKE_MODELS = ("lif", "poisson")
#: the velocity front ends (the keys of lobula.front_ends.FRONT_ENDS, in its order)
FRONT_END_NAMES = ("dis", "farneback", "flo", "emd")
#: `lobula compare`'s default: every front end, the EMD array first (experiments.compare.DEFAULT_FRONT_ENDS)
COMPARE_FRONT_ENDS = ("emd", "dis", "farneback", "flo")
#: lock-on tolerance (m/s) and hold time (s) of the scores (experiments.compare.LOCK_TOL_M_S, LOCK_HOLD_S)
LOCK_TOL_M_S, LOCK_HOLD_S = 0.1, 1.0

HALTERE_GAIN_HELP = ("with --rotation haltere or both: the prior of the gain each LC field subtracts the haltere's "
                     "predicted turn at, before it has learned its own (lobula.eye_circuit.EyeCircuitConfig."
                     "rotation_gain_prior): natural = the gain the EMDs read natural scenes at (natural_scene_gain, "
                     "0.48 at Δφ = Δρ = 5° with the surround), or a number in (0, 1.5], e.g. 1 for the unit gain")


#: the .flo files' options and their defaults (argparse dests)
FLO_OPTION_DEFAULTS = {"flo_units": "rad/s", "flo_gap": 0.2, "flo_size": [640, 448]}


def _flo_options(p, what: str = "front end flo") -> None:
    d = FLO_OPTION_DEFAULTS
    p.add_argument("--flo-units", default=d["flo_units"], choices=["rad/s", "px"], help="units of the .flo values")
    p.add_argument("--flo-gap", type=POSITIVE, default=d["flo_gap"], help="time between the .flo frame pair (s)")
    p.add_argument("--flo-size", type=PIXELS, nargs=2, default=d["flo_size"], metavar=("W", "H"),
                   help=f"image size (pixels) the .flo refers to ({what})")


def add_footage_options(p) -> None:
    """The reader options every footage-reading command shares (experiments.info.open_footage_from_args reads them)."""
    p.add_argument("--stream", default=None,
                   help="RealSense .bag/.db3: image stream to read, e.g. Color_0 or Infrared_1 (default: colour, "
                        "else infrared)")
    p.add_argument("--clock", default="device", choices=["device", "header", "record"],
                   help="RealSense .bag/.db3: frame and IMU times from the device's time stamps, the message "
                        "header stamps, or the bag's record times")
    p.add_argument("--skip-bad-frames", action="store_true",
                   help="leave out frames that cannot be decoded (counted in the output's attrs) instead of stopping")
    p.add_argument("--clock-offset", default=None, metavar="S|auto",
                   help="seconds added to the IMU's times to put them on the camera's clock, or 'auto' to "
                        "estimate it by cross-correlating the gyro with the image rotation (default: none, the "
                        "times as recorded)")
    p.add_argument("--rolling-shutter", type=Number(0, note="lobula.camera.PinholeCamera.rolling_shutter_s"),
                   default=None, metavar="SECONDS",
                   help="the sensor's readout, its first row's exposure to its last's (s): each row's flow is put "
                        "back on the frames' times for the rotation (lobula.rolling_shutter) (default: the "
                        "camera.json's rolling_shutter_s, else 0, a global shutter)")
    p.add_argument("--undistort", default="same-k", choices=["same-k", "optimal"],
                   help="a distorted lens (EuRoC's sensor.yaml, or a camera.json \"distortion\": kannala-brandt or "
                        "radtan): resample each frame onto a pinhole camera with the same K (same-k), or with a focal "
                        "length that keeps the whole view (optimal: OpenCV's new K for EuRoC; the whole width up to "
                        "150° for a camera.json lens)")
    p.add_argument("--camera", metavar="FILE",
                   help="the intrinsics to use instead of the recording's: a camera.json (width, height, fx, fy, cx, "
                        "cy in pixels, frame_rate_hz; optionally a lens \"distortion\": {\"model\": "
                        "\"kannala-brandt\"|\"radtan\", \"coeffs\": [...]}), an OpenCV calibration (FileStorage "
                        "YAML/XML/JSON), a ROS camera_info YAML, a Kalibr camchain (cam0; its T_cam_imu and "
                        "timeshift_cam_imu too) or a Gyroflow lens profile (scaled to the footage's resolution); for "
                        "a bag without usable CameraInfo, or to correct them; for a footage folder or video it "
                        "stands for their camera.json (imu_to_camera too) (default: the recording's own)")


# ----------------------------------------------------------------------------- lobula velocity (camera)
def add_velocity_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula velocity`'s camera options (experiments.velocity_command adds the compound eye's)."""
    v = subparsers.add_parser("velocity", help="estimate forward velocity from footage")
    v.add_argument("footage", help="footage folder, D435i sample, RealSense .bag/.db3, EuRoC folder or video file")
    v.add_argument("--front-end", default="dis", choices=FRONT_END_NAMES,
                   help="what measures the image motion: dis or farneback (OpenCV dense optical flow), flo "
                        "(precomputed .flo files, with --flo) or emd (an EMD array on the camera image)")
    v.add_argument("--out", required=True, help="output NetCDF (written atomically)")
    v.add_argument("--plot", help="PNG of v̂ against truth (default: no figure)")
    v.add_argument("--tum", metavar="FILE",
                   help="the camera's trajectory in the TUM format (timestamp tx ty tz qx qy qz qw; evo reads it): "
                        "v̂ along the heading, turned by the gyro's attitude and integrated from the first "
                        "observable estimate; needs a gyro (default: none)")
    v.add_argument("--paper", action="store_true", help="the paper's configuration, as its text states it")
    v.add_argument("--filter", default="zero-phase", choices=["zero-phase", "causal"],
                   help="readout filter: zero-phase (offline smoother, the whole record) or causal (online)")
    v.add_argument("--lag", type=Number(0, note="lobula.readout.ReadoutConfig.lag_s"), metavar="SECONDS",
                   help="with --filter causal: a fixed-lag smoother; each v_hat also uses the next SECONDS of "
                        "footage and is known that much later (lobula.readout.ReadoutConfig.lag_s) "
                        "(default: 0, the forward filter)")
    v.add_argument("--gap", type=COUNT, help="frames between the two images of a flow pair (default: 6)")
    v.add_argument("--field-size", type=POSITIVE,
                   help="receptive-field size (deg) (default: 5 on camera footage; the eye's LC field FWHM, 30, "
                        "on compound-eye footage)")
    v.add_argument("--dis-preset", choices=["ultrafast", "fast", "medium"],
                   help="OpenCV DIS preset of --front-end dis (default: fast)")
    v.add_argument("--dis-grid-px", type=INDEX,
                   help="DIS refines its flow on a grid at least this many pixels wide (its preset's finest "
                        "level, made finer on small images; lobula.flow.FlowConfig.dis_grid_px; 0: the preset's "
                        "level at every image size) (default: 160)")
    v.add_argument("--epipole", choices=["estimate", "principal"],
                   help="heading: estimated from the flow, or the principal point (default: estimate; principal "
                        "with --paper or --front-end emd)")
    v.add_argument("--accel-from-truth", action="store_true",
                   help="forward acceleration from truth.csv instead of imu.csv")
    v.add_argument("--gyro-bias-from-vision", action="store_true",
                   help="estimate the gyro bias from the flow's residual rotation (lobula.imu.vision_gyro_bias) "
                        "for gravity removal and the drift std; writes gyro_bias, gyro_bias_std")
    v.add_argument("--heading-motion", action="store_true",
                   help="each field's κ measures the acceleration along its own axis, from the IMU's 3-D "
                        "acceleration, which holds a heading that moves (a drone's drift, a walker's bounce) "
                        "(VelocityConfig.heading_motion; docs/results.md says where it helps and where it costs)")
    v.add_argument("--accel-scale-error", type=Number(0, 1, below=True, note="ReadoutConfig.accel_scale_error"),
                   metavar="FRACTION",
                   help="the accelerometer's scale-factor error (1σ fraction), added to v_std as FRACTION·|v̂| "
                        "(vision cannot see it; lobula.readout.ReadoutConfig.accel_scale_error; set it from your "
                        "IMU's calibration) (default: 0.01, a consumer MEMS sensitivity tolerance)")
    v.add_argument("--speed-prior", type=POSITIVE, metavar="M_S",
                   help="prior std (1σ, m/s) of the forward speed before vision fixes it "
                        "(lobula.readout.ReadoutConfig.v_prior_m_s): your platform's — about 1 for a walker or a "
                        "hand-held camera, 15 for a car or a drone; a narrower prior answers sooner on short clips "
                        "(default: 15)")
    v.add_argument("--coupling", type=NONNEGATIVE, metavar="Z",
                   help="Fisher z the image's expansion must reach against the accelerometer over 4 s before vision "
                        "fixes the speed (lobula.readout.coupling, ReadoutConfig.coupling_z); 0 turns the test off and "
                        "the posterior's std decides alone — a clip of 2-3 s rarely shows enough to reach 3, and a "
                        "stabilised or moving image shows a κ that is noise (default: 3)")
    v.add_argument("--rest-depth", type=POSITIVE, metavar="M",
                   help="the farthest the scene's typical (median) surface lies, in metres, when no expansion is "
                        "taken to mean the camera is still (ReadoutConfig.rest_depth_max_m): about 5 in a room. "
                        "Without it the depth is learned from the footage while vision measures it, and no flow in a "
                        "scene not yet measured (a still start, a distant view) bounds nothing (default: learned)")
    v.add_argument("--saccade-gate", type=positive_or_none, default=argparse.SUPPRESS, metavar="DEG_S|none",
                   help="a flow pair between two consecutive frames of which the gyro turned faster than this (°/s) is "
                        "not read, and the heading is fitted afresh after it: a saccade or a whip pan, whose image "
                        "moves past what the flow resolves (VelocityConfig.saccade_gate_deg_s); none: every pair is "
                        "read (default: 150)")
    v.add_argument("--heading-reset", type=positive_or_none, default=argparse.SUPPRESS, metavar="DEG|none",
                   help="the heading is fitted afresh each time the camera has turned this far (°), since a vehicle's "
                        "velocity turns with it through a bend (VelocityConfig.heading_reset_deg); none: held in the "
                        "world throughout, as for a hand-held camera that only pans (default: 15)")
    v.add_argument("--heading-walk", type=NONNEGATIVE, default=argparse.SUPPRESS, metavar="RATE",
                   help="how fast the heading may move between the camera's turns, in normalised image coordinates "
                        "per √s: a drone's sideways drift, a car's lane change, a walker's bounce "
                        "(VelocityConfig.heading_walk): each end of a material difference is then read about its own heading; "
                        "needs a gyro and the estimated epipole. "
                        "Measured, not adopted: it helps development drones and hurts the reported ones (docs/results.md); "
                        "0: held in the world between turns (default: 0)")
    v.add_argument("--flo", help=".flo file or folder of *_<first>_to_<second>.flo files (front end flo) "
                                 "(default: none)")
    _flo_options(v)
    v.add_argument("--dphi", type=LATTICE_ANGLE, help="EMD front end: interommatidial angle Δφ (deg) (default: 0.75)")
    v.add_argument("--drho", type=LATTICE_ANGLE, help="EMD front end: acceptance angle Δρ (deg) (default: Δφ)")
    v.add_argument("--tau", type=EMD_TAU, help=f"EMD front end: delay time constant (s), {EMD_TAU_RANGE} "
                                               "(default: 0.010 on camera footage, 0.035 on compound-eye footage)")
    v.add_argument("--mean-removal", choices=MEAN_REMOVAL,
                   help="EMD front end: how the columns remove the mean luminance before the EMDs — space: the "
                        "LMCs' lateral inhibition (x − the lattice neighbours' mean), no temporal high-pass; time: "
                        "an LMC-like 0.25 s temporal high-pass, no surround (lobula.photoreceptor.MEAN_REMOVAL) "
                        "(default: space)")
    v.add_argument("--emd-gaze", choices=["fixate", "none"],
                   help="EMD front end on camera footage with a gyro: fixate — warp each frame into a gaze held "
                        "fixed by the integrated gyro, with a saccade back to the camera once it has turned 12° away "
                        "(lobula.gaze.fixation_reference); none — the camera's own image (default: fixate)")
    v.add_argument("--emd-calibration", help="EMD front end: gains JSON from `lobula calibrate-emd` on another scene "
                                             "(default: none, unit gains)")
    v.add_argument("--skip", type=NONNEGATIVE, default=2.0,
                   help="seconds ignored at the start when scoring (at most a quarter of the footage)")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    add_footage_options(v)
    v.set_defaults(func=LazyCommand("experiments.velocity:run_velocity"))
    return v


# ----------------------------------------------------------------------------- lobula eye-velocity
def add_eye_velocity_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula eye-velocity` (experiments.eye_velocity)."""
    v = subparsers.add_parser("eye-velocity", help="estimate forward velocity from compound-eye footage "
                                                   "(photoreceptors, EMDs, LC fields, readout; causal)")
    v.add_argument("footage", help="eye-footage folder from `lobula scene OUT --eye fly`")
    v.add_argument("--out", required=True, help="output NetCDF (written atomically)")
    v.add_argument("--plot", help="PNG of v̂ against truth (default: no figure)")
    v.add_argument("--rotation", default="haltere", choices=["none", "haltere", "wide-field", "both"],
                   help="rotation handling: gyro-driven (haltere) subtraction, left+right wide-field sums, both, none")
    v.add_argument("--haltere-gain", type=haltere_gain, metavar="natural|G",
                   help=HALTERE_GAIN_HELP + " (default: natural)")
    v.add_argument("--mean-removal", default="space", choices=MEAN_REMOVAL,
                   help="how the columns remove the mean luminance before the EMDs: space = the LMCs' lateral "
                        "inhibition, x − the six neighbours' mean (EyeCircuitConfig.surround 1, no temporal "
                        "high-pass); time = an LMC-like 0.25 s temporal high-pass, no surround (its memory "
                        "drifts the fields' gains after each change of speed)")
    v.add_argument("--field-size", type=Number(2.0, 120.0, note="EyeCircuitConfig.fields.size_deg"), default=30.0,
                   help="LC field FWHM (deg), 2 to 120")
    v.add_argument("--tau", type=EMD_TAU, default=0.035, help=f"EMD delay time constant (s), {EMD_TAU_RANGE}")
    v.add_argument("--filter", default="causal", choices=["causal", "zero-phase"], help="readout filter kind")
    v.add_argument("--accel-from-truth", action="store_true",
                   help="forward acceleration from truth.csv instead of the accelerometer")
    v.add_argument("--accel-scale-error", type=Number(0, 1, below=True, note="ReadoutConfig.accel_scale_error"),
                   metavar="FRACTION",
                   help="the accelerometer's scale-factor error (1σ fraction) the kalman/spikes readouts add to "
                        "v_std as FRACTION·|v̂| (lobula.readout.ReadoutConfig.accel_scale_error) (default: 0.01)")
    v.add_argument("--readout", default="kalman", choices=["kalman", "spikes", "neuron", "neuron-rate"],
                   help="kalman: the arithmetic readout (lobula.readout, rates); spikes: its v̂ carried by 10 "
                        "push-pull spiking output neuron pairs, decoded causally; neuron: the shunting readout "
                        "neuron (lobula.readout_neuron) with spikes; neuron-rate: its rates")
    v.add_argument("--seed", type=INDEX, help="seed of the readout neuron's spikes (default: 0)")
    v.add_argument("--spike-model", choices=SPIKE_MODELS,
                   help="how the output neurons spike with --readout spikes or neuron: lif (leaky "
                        "integrate-and-fire with membrane noise) or poisson (Poisson trains) (default: lif)")
    v.add_argument("--membrane-noise", type=NONNEGATIVE, metavar="MV",
                   help="the LIF output neurons' free-membrane noise SD in mV (default: 1.0)")
    v.add_argument("--uncertainty", default="halves", choices=["halves", "posterior"],
                   help="v_std of the kalman/spikes readouts: halves = the posterior std with the field halves' "
                        "disagreement and the EMD gain error added; posterior = the readout's posterior std alone")
    v.add_argument("--skip", type=NONNEGATIVE, default=2.0,
                   help="seconds ignored at the start when scoring (at most a quarter of the footage)")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.set_defaults(func=LazyCommand("experiments.eye_velocity:run_eye_velocity"))
    return v


# ----------------------------------------------------------------------------- lobula compare
def add_compare_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula compare` (experiments.compare)."""
    c = subparsers.add_parser(
        "compare", help="every front end on the same footage and readout, scored side by side",
        description="Front ends side by side: every front end on the same footage and the same readout "
                    "(fields, readout, filter and acceleration shared), each scored against the truth.")
    c.add_argument("footage",
                   help="footage folder (synthetic: r̄ is also scored against depth maps) or the D435i sample")
    c.add_argument("--front-ends", default=",".join(COMPARE_FRONT_ENDS),
                   help=f"comma-separated, from {', '.join(COMPARE_FRONT_ENDS)} (flo is skipped without --flo)")
    c.add_argument("--out", required=True, help="comparison NetCDF (written atomically)")
    c.add_argument("--csv", help="the table as CSV (default: none)")
    c.add_argument("--plot",
                   help="PNG: v̂ of each front end against truth, RMSE/lock-on/time bars (default: no figure)")
    c.add_argument("--config", help="VelocityConfig JSON to share between front ends (e.g. a run's attrs['config']) "
                                    "(default: VelocityConfig(), or the paper's with --paper)")
    c.add_argument("--paper", action="store_true", help="the paper's configuration for every front end")
    shared = "the shared configuration's"
    c.add_argument("--filter", choices=["zero-phase", "causal"],
                   help=f"readout filter (default: {shared}, zero-phase unless --config says otherwise)")
    c.add_argument("--gap", type=COUNT, help=f"frames between the two images of a flow pair (default: {shared}, 6)")
    c.add_argument("--field-size", type=POSITIVE, help=f"receptive-field size (deg) (default: {shared}, 5)")
    c.add_argument("--accel-from-truth", action="store_true", help="forward acceleration from truth.csv")
    c.add_argument("--dphi", type=LATTICE_ANGLE,
                   help=f"EMD: interommatidial angle Δφ (deg) (default: {shared}, 0.75)")
    c.add_argument("--drho", type=LATTICE_ANGLE, help=f"EMD: acceptance angle Δρ (deg) (default: {shared}, Δφ)")
    c.add_argument("--tau", type=EMD_TAU,
                   help=f"EMD: delay time constant (s), {EMD_TAU_RANGE} (default: {shared}, 0.010)")
    c.add_argument("--emd-calibration", help="EMD: gains JSON from `lobula calibrate-emd` on another scene "
                                             "(default: none, unit gains)")
    c.add_argument("--emd-gaze", choices=["fixate", "none"],
                   help="EMD: with a gyro, a gaze fixated by the integrated gyro (saccades beyond 12°) or the "
                        f"camera's own image (default: {shared}, fixate)")
    c.add_argument("--flo", help=".flo file or folder of *_<first>_to_<second>.flo files (front end flo) "
                                 "(default: none)")
    _flo_options(c)
    c.add_argument("--skip", type=NONNEGATIVE,
                   help="seconds ignored when scoring (default: 2, at most a quarter of the footage)")
    c.add_argument("--tol", type=POSITIVE, default=LOCK_TOL_M_S, help="lock-on tolerance (m/s)")
    c.add_argument("--hold", type=NONNEGATIVE, default=LOCK_HOLD_S, help="lock-on hold time (s)")
    c.add_argument("--quiet", action="store_true", help="no progress lines")
    add_footage_options(c)
    c.set_defaults(func=LazyCommand("experiments.compare:_compare"))
    return c


# ----------------------------------------------------------------------------- lobula sweep
def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula sweep` (experiments.sweep)."""
    s = subparsers.add_parser("sweep", help="a grid over configuration parameters, each point a scored synthetic run "
                                            "(Dask, Zarr, resumable)",
                              description="A grid over velocity and synthetic-run parameters; each point renders "
                                          "(or reuses) a synthetic run, estimates velocity and scores it against "
                                          "truth. Finished points are recorded beside the store, so an interrupted "
                                          "sweep resumes where it stopped.")
    s.add_argument("--param", action="append", metavar="PATH=V1,V2,...",
                   help="a swept parameter: a dotted path into the velocity configuration (fields.size_deg, "
                        "readout.cutoff_hz, front_end, emd.emd.tau_s, emd.lattice.dphi_deg, ...) or the synthetic "
                        "run (scene.seed, scene.noise_grey, imu.accel_noise_density, duration_s, ...), or 'seed'; "
                        "values comma-separated, a JSON list, or lin:A:B:N / log:A:B:N. Repeat for more dims "
                        "(default: none; at least one is needed unless --list-params)")
    s.add_argument("--out", help="output Zarr store (written atomically); records go to OUT's stem + .points/ "
                                 "(default: none; needed unless --list-params)")
    s.add_argument("--base-duration", type=POSITIVE, default=30.0, help="duration of each synthetic run (s)")
    s.add_argument("--start", type=NONNEGATIVE, default=0.0, help="window start in the velocity profile (s)")
    s.add_argument("--scale", type=CAMERA_SCALE, default=0.5, help="image scale of the D435i camera (0.5 = 320×240)")
    s.add_argument("--profile", help="velocity CSV (default: the real FLIVVER run when ../shared is present, else "
                                     "the built-in profile)")
    s.add_argument("--builtin-profile", action="store_true", help="use the built-in velocity profile")
    s.add_argument("--base-velocity", help="VelocityConfig JSON (or a velocity NetCDF's attrs['config'] saved as JSON) "
                                           "(default: VelocityConfig(), or the paper's with --paper)")
    s.add_argument("--base-run", help="TrackRunConfig JSON (or a rendered footage's scene.json) (default: a run of "
                                      "--base-duration, --start, --scale and --profile)")
    s.add_argument("--paper", action="store_true", help="start from the paper's velocity configuration")
    s.add_argument("--skip", type=NONNEGATIVE, default=2.0, help="seconds ignored at the start when scoring")
    s.add_argument("--tol", type=POSITIVE, default=LOCK_TOL_M_S, help="lock-on tolerance (m/s)")
    s.add_argument("--hold", type=NONNEGATIVE, default=LOCK_HOLD_S, help="lock-on hold time (s)")
    s.add_argument("--scheduler", default="processes",
                   help="processes (a local dask.distributed cluster), threads, synchronous, or the ADDRESS of a "
                        "dask.distributed scheduler (e.g. tcp://10.0.0.5:8786)")
    s.add_argument("--workers", type=COUNT, default=2, help="local workers")
    s.add_argument("--keep-renders", action="store_true", help="keep the rendered footage beside the store")
    s.add_argument("--no-series", action="store_true", help="metrics only; no per-frame v_hat etc. in the store")
    s.add_argument("--dry-run", action="store_true", help="print the grid and what is already recorded, run nothing")
    s.add_argument("--list-params", action="store_true",
                   help="print every sweepable path with its value in the base configurations, and the aliases")
    s.add_argument("--quiet", action="store_true", help="no progress lines")
    s.set_defaults(func=LazyCommand("experiments.sweep:_sweep"))
    return s


# ----------------------------------------------------------------------------- lobula depth
#: DepthRunConfig's defaults that `lobula depth` and `lobula depth-suite` show (experiments.depth_stream)
DEPTH_METHODS = ("ratio", "tv", "parallax")
FOOTAGE_GAMMA = 1e-6
DEPTH_RUN_DEFAULTS = dict(snr_min=3.0, max_range_m=20.0, max_scale_rel_std=0.2, min_speed_m_s=0.03)
#: options of the two-pass footage route that the single ``--flo`` pair has no use for
FOOTAGE_ROUTE_ONLY = ("every", "velocity", "velocity_run", "dis_preset", "accel_from_truth", "unweighted",
                      "snr_min", "tv_start", "min_speed", "max_scale_rel_std", "average_frames", "plot_time",
                      "front_end")
#: a relative std bound, where inf keeps every map
_REL_STD = Number(0, above=True, inf=True)


def add_depth_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula depth` (experiments.depth)."""
    d = subparsers.add_parser(
        "depth", help="dense depth maps from footage (ratio, TV, plane+parallax), scored against exact depth",
        description="Estimate v̂ with the velocity pipeline, then dense forward depth at the first frame of "
                    "every N-th flow pair (exact finite derotation from the gyro, the gyro-stabilised heading as "
                    "epipole); scores against depth/NNNNNN.npy when the footage has it. For scene families x "
                    "seeds beside baselines: lobula depth-suite --help.")
    d.add_argument("footage", help="footage folder, D435i sample, RealSense .bag/.db3, EuRoC folder or video file")
    d.add_argument("--method", default="tv", choices=list(DEPTH_METHODS),
                   help="ratio map v/r, TV-regularised fit, or plane+parallax (the same finite derotation "
                        "through the plane-at-infinity homography)")
    d.add_argument("--every", type=COUNT, default=1,
                   help="solve every N-th flow pair (10 matches the synthetic runs' depth/ maps)")
    d.add_argument("--out", required=True, help="output .nc (NetCDF, written atomically) or .zarr (streamed)")
    d.add_argument("--plot", help="PNG panel: frame, true depth, each method's depth (default: no figure)")
    d.add_argument("--plot-time", type=FINITE, help="time (s) of the panel's pair (default: the fastest scored pair)")
    d.add_argument("--front-end", default="dis", choices=["dis", "farneback"],
                   help="dense flow of both passes (with --velocity-run, that run's flow is reused)")
    d.add_argument("--velocity", default="estimate", choices=["estimate", "truth"],
                   help="speed for d = v/z: v̂ of the velocity pipeline, or the exact mean velocity over each pair "
                        "from truth.csv (footage with ground truth only; the output's velocity_source says which)")
    d.add_argument("--velocity-run", help="a velocity NetCDF of this footage (from `lobula velocity`) to reuse "
                                          "(default: none, the velocity pass runs)")
    d.add_argument("--epipole", default="final", choices=["final", "running", "principal"],
                   help="heading: the velocity pass's final or running gyro-stabilised estimate, or the principal "
                        "point")
    d.add_argument("--dis-preset", choices=["ultrafast", "fast", "medium"],
                   help="velocity pass: DIS preset (default: the velocity pipeline's own, fast)")
    d.add_argument("--accel-from-truth", action="store_true",
                   help="velocity pass: forward acceleration from truth.csv instead of imu.csv")
    d.add_argument("--average-frames", type=INDEX, metavar="K",
                   help="depth flow: each image the mean of frames i-K..i+K turned into frame i's orientation by "
                        "the gyro; 0: single frames (default: 2 with a gyroscope, 0 without)")
    d.add_argument("--gamma", type=NONNEGATIVE, default=FOOTAGE_GAMMA, help="TV weight (1/s x normalised length)")
    d.add_argument("--unweighted", action="store_true",
                   help="TV: uniform data term (the paper's) instead of weighting by the flow's precision 1/sigma^2")
    d.add_argument("--snr-min", type=NONNEGATIVE, default=DEPTH_RUN_DEFAULTS["snr_min"],
                   help="ratio/parallax: no depth where the predicted translational flow is below this many "
                        "flow-noise sigma (near the epipole)")
    d.add_argument("--max-range", type=POSITIVE, default=DEPTH_RUN_DEFAULTS["max_range_m"],
                   help="scores count pixels whose exact depth is within this range (m); sky and farther pixels "
                        "are counted, not scored")
    d.add_argument("--max-scale-rel-std", type=_REL_STD, default=DEPTH_RUN_DEFAULTS["max_scale_rel_std"],
                   help="a map whose speed is known only to a relative std v_std/|v| above this has no known "
                        "metric scale and is reported as unobservable (all NaN, metric=False); inf keeps every map")
    d.add_argument("--tv-start", default="cold", choices=["cold", "warm"],
                   help="TV: coarse-to-fine per map (faster) or warm start from the previous map")
    d.add_argument("--min-speed", type=NONNEGATIVE, default=DEPTH_RUN_DEFAULTS["min_speed_m_s"],
                   help="pairs slower than this (m/s) are not ranged (all invalid)")
    d.add_argument("--device", default="cpu", help="torch device for TV (cpu, cuda); on cpu it uses one thread")
    d.add_argument("--flo", help="instead: depth from one precomputed .flo pair (*_<first>_to_<second>.flo), "
                                 "v from the ground truth (default: none, depth along the footage)")
    _flo_options(d, "with --flo")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    add_footage_options(d)
    d.set_defaults(func=LazyCommand("experiments.depth:run_depth"),
                   flo_ignores={k: d.get_default(k) for k in FOOTAGE_ROUTE_ONLY})
    return d


# ----------------------------------------------------------------------------- lobula depth-suite
def add_depth_suite_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula depth-suite` (experiments.depth_suite)."""
    from .families import FAMILIES

    p = subparsers.add_parser(
        "depth-suite", help="depth on the suite's families x seeds, beside baselines",
        description="Depth on the accuracy suite's scene families × seeds, beside baselines. What is scored: "
                    "the module documentation of experiments.depth_suite.")
    p.add_argument("--out", required=True, help="output folder (scenes are kept there and reused)")
    p.add_argument("--families", default="all", help=f"comma-separated, or 'all': {', '.join(FAMILIES)}")
    p.add_argument("--seeds", type=seeds, default="3",
                   help="seeds per family: a count N (seeds 0..N-1, the reported ones) or a comma-separated list "
                        "(e.g. 100,101: development seeds; 7, for seed 7 alone)")
    p.add_argument("--duration", type=POSITIVE, default=6.0,
                   help="seconds per scene (the velocity suite renders 10 s at --scale 0.5)")
    p.add_argument("--skip", type=NONNEGATIVE, default=2.0,
                   help="pairs starting in the first SKIP seconds are not scored (the velocity readout locks on "
                        "then; the velocity suite skips the same)")
    p.add_argument("--scale", type=CAMERA_SCALE, default=0.25,
                   help="camera scale of the D435i's 640x480 (0.25: 160x120; 0.5: 320x240, the velocity suite's)")
    p.add_argument("--every", type=COUNT, default=5, help="exact depth (and a scored map) every N frames")
    p.add_argument("--max-range", type=POSITIVE, default=DEPTH_RUN_DEFAULTS["max_range_m"],
                   help="score pixels whose exact depth is within this range (m)")
    p.add_argument("--max-scale-rel-std", type=_REL_STD, default=DEPTH_RUN_DEFAULTS["max_scale_rel_std"],
                   help="maps whose speed has v_std/|v| above this have no known metric scale: unobservable, as "
                        "`lobula depth` reports them (the table also gives every map unmasked and scale-invariant)")
    p.add_argument("--filter", default="zero-phase", choices=["zero-phase", "causal"], help="velocity readout filter")
    p.add_argument("--average-frames", type=INDEX, metavar="K",
                   help="depth flow: each image the mean of frames i-K..i+K turned into frame i's orientation by "
                        "the gyro (default: 2 with a gyroscope, 0 without)")
    p.add_argument("--workers", type=COUNT, default=1, help="scenes run in parallel (processes, one torch thread each)")
    p.add_argument("--device", default="cpu", help="torch device of the TV solver (cpu, cuda)")
    p.add_argument("--imu", default="realistic", choices=["ideal", "realistic"], help="synthetic IMU model")
    p.add_argument("--imu-mount", default="rotated", choices=["camera", "rotated"], help="IMU mounting")
    p.add_argument("--sample-map", type=INDEX, default=6,
                   help="which scored pair of each family's first seed the maps figure shows")
    p.set_defaults(func=LazyCommand("experiments.depth_suite:run_depth_suite"))
    return p


# ----------------------------------------------------------------------------- lobula calibrate-camera
def add_calibrate_camera_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula calibrate-camera` (experiments.camera_calibration)."""
    c = subparsers.add_parser("calibrate-camera",
                              help="measure a footage's focal length and IMU axes from its gyro against the image's "
                                   "rotation")
    c.add_argument("footage", help="footage with a gyroscope that pans and tilts (any layout the readers open)")
    c.add_argument("--out", required=True, help="camera.json with the focal length found (the lens's distortion, the "
                                                "size, the principal point and the rate kept from the first guess) "
                                                "and the IMU's rotation into the camera (imu_to_camera): the first "
                                                "guess's, turned where the image's rotation clearly disagrees with it")
    c.add_argument("--iterations", type=COUNT, default=4, help="rescalings at most")
    c.add_argument("--min-correlation", type=Number(0, 1), default=0.7,
                   help="the least correlation of the image's pan/tilt rates with the gyro's")
    add_footage_options(c)
    c.set_defaults(func=LazyCommand("experiments.camera_calibration:run_calibrate_camera"))
    return c


# ----------------------------------------------------------------------------- lobula calibrate-emd
def add_calibrate_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula calibrate-emd` (experiments.calibrate)."""
    c = subparsers.add_parser("calibrate-emd", help="fit the EMD front end's per-field gains on a synthetic run")
    c.add_argument("footage", help="a synthetic footage folder with depth/ and truth.csv (not a test scene)")
    c.add_argument("--out", required=True, help="gains JSON for `lobula velocity --emd-calibration`")
    c.add_argument("--single-gain", action="store_true", help="one gain for all fields")
    c.set_defaults(func=LazyCommand("experiments.calibrate:run_calibrate"))
    return c


# ----------------------------------------------------------------------------- lobula figures
#: experiments.figures.FIGURES and EXTRA_FIGURES (made only when named)
FIGURES = ("replay_emd_vs_dis", "rmse_vs_field_size", "rmse_vs_dphi", "rmse_vs_tau_contrast_noise",
           "error_vs_acceleration", "rate_vs_spiking", "replay_velocity")
EXTRA_FIGURES = ("eye_rmse", "eye_rate_vs_spiking", "eye_rmse_vs_dphi_fov", "emd_gaze", "fly_flight")


def add_figures_parser(subparsers) -> argparse.ArgumentParser:
    """`lobula figures` (experiments.figures)."""
    f = subparsers.add_parser("figures", help="make the hypothesis figures (PNG + JSON with command and config)")
    f.add_argument("--out", default="figures", help="output folder")
    f.add_argument("--only", nargs="+", choices=FIGURES + EXTRA_FIGURES, metavar="FIGURE",
                   help=f"make only these figures, from {', '.join(FIGURES + EXTRA_FIGURES)} (default: all but "
                        f"{', '.join(EXTRA_FIGURES)}, which render their own worlds and are made only when named)")
    f.add_argument("--start", type=NONNEGATIVE, default=5.0, help="replay window start in the real trajectory (s)")
    f.add_argument("--duration", type=POSITIVE, default=25.0, help="replay duration (s)")
    f.add_argument("--seed", type=INDEX, default=0, help="scene, IMU and spike seed")
    f.add_argument("--quick", action="store_true", help="coarse grids (for tests)")
    f.add_argument("--quiet", action="store_true", help="no progress lines")
    f.set_defaults(func=LazyCommand("experiments.figures:main"))
    return f
