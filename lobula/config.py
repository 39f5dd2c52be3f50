"""The velocity pipeline's configuration: one dataclass per stage, gathered in one object.

Every output carries ``VelocityConfig.to_json()`` and the package version, so a file
says exactly how it was made; :meth:`VelocityConfig.from_json` rebuilds the run.
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict, dataclass, field, fields

from ._fields import check_field_types
from .emd_front_end import EMDFrontEndConfig
from .flow import FlowConfig
from .front_ends import FRONT_ENDS, get_front_end
from .readout import ReadoutConfig
from .receptive_field import FieldConfig


@dataclass
class VelocityConfig:
    """Velocity estimation from footage.

    front_end: a name of :data:`lobula.front_ends.FRONT_ENDS` ("dis" | "farneback" | "flo" | "emd"). epipole: "estimate" (from the
    derotated flow) or "principal" (assume the principal point, as the paper does).
    flow, fields: the flow stage's and the receptive fields' configurations (:class:`lobula.flow.FlowConfig`,
    :class:`lobula.receptive_field.FieldConfig`).
    derotate: subtract gyro-predicted rotational flow when a gyroscope is present.
    gyro_bias_from_vision: with a gyroscope, estimate its bias from the rotation the
    derotated flow still shows (lobula.imu.vision_gyro_bias) for the attitude that
    removes gravity and for the readout's gravity-drift std; else (the default) the heading and
    bias fit's estimate (lobula.epipole.HeadingBiasEstimator, its std scaled by
    lobula.imu.HEADING_BIAS_STD_SCALE) fused with the still-camera one
    (lobula.imu.fused_gyro_bias). Off by default: on frontal scenes a pitch/yaw bias is nearly
    confounded with an epipole shift, and on 2 of 7 development scenes one axis's estimate
    stays near 0 with a std that claims otherwise.
    gyro_scale_prior: prior std (dimensionless) of the gyro's scale-factor and axis-misalignment error E (a 3×3
    matrix, the rate read is (I + E)·ω + b), fitted with the heading and the bias from the flow
    (lobula.epipole.HeadingBiasEstimator) and applied to the fields' attitude
    (lobula.imu.GyroAttitude); 0: not fitted. A residual rotation E·ω grows with the turn
    rate: a MEMS gyro's 1 % scale error at 2 rad/s leaves 0.02 rad/s, ten times its bias.
    gyro_bias_prior_deg_s: prior std (°/s) of the gyro's zero-rate offset before the record measures
    it (still samples, the heading fit): a consumer data sheet's ±1°/s by default
    (lobula.imu.GYRO_BIAS_PRIOR); a gyro calibrated on the platform may say less. It bounds how
    fast gravity may leak into the forward axis through the integrated attitude, so a prior narrower
    than the gyro's real offset makes the readout confidently wrong.
    saccade_gate_deg_s: a pair of frames between two consecutive frames of which the gyro turned faster
    than this (°/s) is not read: its flow is left out of the fields (NaN rates, and every material difference
    spanning it) and of the heading fit, and the heading is re-learned after it, since a vehicle's
    velocity turns with its body (:meth:`lobula.epipole.EpipoleEstimator.forget_heading`). 150 °/s is
    15° in 0.1 s: faster, the heading would be reset (``heading_reset_deg``) every three frames at 30
    frames/s, sooner than the fit learns it again (~10 pairs), and the fields would read the turn about a
    heading it has not found. It lies above a fly's intersaccadic wobble and a hand-held camera's or a
    drone's turns (the suite's families turn at most 43 °/s) and below a body saccade's 800-1800 °/s.
    Chosen on development flights (the saccadic family's worlds, seeds 100-103): turns spread over
    0.4-0.8 s read 0.009-0.072 m/s offline, ±2σ 95-100 %, where 300 °/s read them 0.14-0.29 off with ±2σ
    34-47 %; the saccadic flights read alike at both. None: every pair is read.
    heading_reset_deg: the heading is also fitted afresh once the camera has turned this far (°) from
    the orientation it was last fitted afresh in: between such resets it is held fixed in the world,
    which a vehicle's bend breaks (a fly's 20-90° turns over 0.4-0.8 s, at 100-225 °/s: held through
    them the epipole errs by 14-20° on the median frame, reset every 15° by 1.4-3.8°; exact flow). 15°:
    beyond a hand-held or gimbal camera's wobble, so a camera that only wobbles is never reset (the
    suite's turning families stay within 14° of their start). None: never.
    heading_walk: how fast the heading may move between the camera's turns (normalised coordinates/√s, a random
    walk in the joint heading-and-bias fit that runs with a gyro, :meth:`lobula.epipole.HeadingBiasEstimator.walk_heading`),
    for a platform whose velocity turns while its camera holds still (a drone drifting sideways as it gathers
    speed, a car changing lanes, a walker's bounce). With it the fit follows such a turn within a few degrees,
    and each end of a material difference is read about its own heading
    (:class:`lobula.receptive_field.MaterialFields`). 0 (the default): the heading is held in the world
    between turns and both ends are read about one heading. At 0.15 (8.5° over a second at the centre) the
    development drones, road vehicles and walks (seeds 100-105, offline) read better — drones 0.73 and
    1.02 m/s off (±2σ 99 %, 0 %) read 0.18 and 0.27 (±2σ 100 %, 94 %), a car braking at once 0.72 → 0.18, a
    walk 0.61 (±2σ 0 %) → 0.05 — but the reported seeds 0-2 read worse: drones 0.44 (±2σ 31 %) → 0.72 and
    0.40 (±2σ 100 %) → 1.17, both ±2σ 0 %, a road vehicle 0.11 → 0.20 (±2σ 44 %), and the turning held-out
    mixed family 0.010 → 0.017 online; so it is off by default (docs/results.md). It needs that fit (a gyro,
    the estimated epipole, the dis or farneback front end) and is refused where it does not run.
    heading_motion: each material field's κ measures the acceleration along its own axis
    (:func:`lobula.readout.field_axes`), from the IMU's 3-D gravity-free acceleration, rather than the
    forward acceleration: a heading that moves (a drone's drift, a walker's bounce) enters ṙ̄ as the
    acceleration across the heading over the speed, which the forward acceleration does not hold. The
    relation is exact about the velocity's true heading (tests/test_geometry.py), for which the
    acceleration's own direction stands in (:func:`lobula.readout.acceleration_heading`). On the
    development drones the option makes some confidently wrong answers honest and one right answer wrong,
    and it costs the turning indoor families online, with an ideal IMU and the true heading too
    (docs/results.md), so it is off by default. With it both ends of a material difference are read about
    one heading, as its relation needs. Needs the material fields and an accelerometer; ignored without them.
    timestamps: "mid" (a pair's flow belongs to the middle of its interval) or
    "start" (the paper: to its first frame). accel_from_truth: take forward
    acceleration from truth.csv instead of the IMU (labelled in the output).
    readout: None (the default) gives a ReadoutConfig with the front end's κ errors
    (:attr:`lobula.front_ends.FrontEnd.kappa_errors`: ReadoutConfig's own for the flow front ends,
    ``ReadoutConfig.EMD_KAPPA_ERRORS``, κ's larger shared error, for "emd").
    emd: the EMD front end (lattice, photoreceptors, EMD, decoding) when front_end is "emd".
    Its epipole is the principal point (the EMD path has no estimate: a configuration made for it
    with the default "estimate" records "principal", what runs, and asking for "estimate" with it
    fails in :func:`lobula.velocity.estimate_velocity`). There ``derotate`` stabilises the
    frames' gaze by the integrated gyro before the lattice (``emd.gaze``: fixations and saccades,
    :func:`lobula.gaze.fixation_reference`) rather than derotating flow, and gives the gyro to the
    accelerometer's attitude as for the flow front ends (the output's ``derotation`` attribute says which).
    """

    front_end: str = "dis"
    flow: FlowConfig = field(default_factory=FlowConfig)
    fields: FieldConfig = field(default_factory=FieldConfig)
    readout: ReadoutConfig | None = None
    epipole: str = "estimate"
    derotate: bool = True
    gyro_bias_from_vision: bool = False
    gyro_scale_prior: float = 0.02
    gyro_bias_prior_deg_s: float = 1.0
    saccade_gate_deg_s: float | None = 150.0
    heading_reset_deg: float | None = 15.0
    heading_walk: float = 0.0
    heading_motion: bool = False
    timestamps: str = "mid"
    accel_from_truth: bool = False
    emd: EMDFrontEndConfig = field(default_factory=EMDFrontEndConfig)

    def __post_init__(self):
        fe = get_front_end(self.front_end)
        if self.readout is None:   # EMD fields' κ errs more than flow's: the front end's own κ errors
            self.readout = fe.default_readout()
        if self.epipole == "estimate" and not fe.estimates_epipole:
            self.epipole = fe.epipoles[0]   # what the front end runs with (the EMD: the principal point)
        self._check()

    def _check(self) -> None:
        """The checks of every field, which change nothing (:meth:`validate` runs them again)."""
        check_field_types(self)
        get_front_end(self.front_end)
        for name, kind in (("flow", FlowConfig), ("fields", FieldConfig), ("readout", ReadoutConfig),
                           ("emd", EMDFrontEndConfig)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"VelocityConfig.{name} must be a {kind.__name__}, got "
                                f"{type(getattr(self, name)).__name__} (VelocityConfig.from_dict reads dicts)")
        if self.epipole not in ("estimate", "principal"):
            raise ValueError(f"epipole must be 'estimate' or 'principal', got {self.epipole!r}")
        if self.timestamps not in ("mid", "start"):
            raise ValueError(f"timestamps must be 'mid' or 'start', got {self.timestamps!r}")
        if not (self.gyro_scale_prior >= 0 and math.isfinite(self.gyro_scale_prior)):
            raise ValueError(f"gyro_scale_prior must be a finite std >= 0, got {self.gyro_scale_prior}")
        if not (self.gyro_bias_prior_deg_s > 0 and math.isfinite(self.gyro_bias_prior_deg_s)):
            raise ValueError(f"gyro_bias_prior_deg_s must be a finite std > 0, got {self.gyro_bias_prior_deg_s}")
        if self.heading_reset_deg is not None and not (self.heading_reset_deg > 0 and math.isfinite(self.heading_reset_deg)):
            raise ValueError(f"heading_reset_deg must be a finite angle > 0 (°) or None, got {self.heading_reset_deg}")
        if not (self.heading_walk >= 0 and math.isfinite(self.heading_walk)):
            raise ValueError(f"heading_walk must be a finite rate >= 0 (normalised/√s), got {self.heading_walk}")
        if self.saccade_gate_deg_s is not None and not (self.saccade_gate_deg_s > 0 and math.isfinite(self.saccade_gate_deg_s)):
            raise ValueError(f"saccade_gate_deg_s must be a finite rate > 0 (°/s) or None, got {self.saccade_gate_deg_s}")

    def validate(self) -> "VelocityConfig":
        """Check the configuration as it is now, its parts included (a ValueError or TypeError naming the field);
        returns it. A field set after construction (``cfg.readout.filter = "causal"``) is checked here, as
        :func:`lobula.velocity.estimate_velocity` and :class:`lobula.velocity.VelocityEstimator` do before a run."""
        self._check()
        for name in ("flow", "fields", "readout", "emd"):
            part = getattr(self, name)
            if hasattr(part, "__post_init__"):  # the parts' own checks, which change nothing
                part.__post_init__()
        return self

    @classmethod
    def paper(cls, front_end: str = "dis", filter: str = "zero-phase") -> "VelocityConfig":
        """The FLIVVER paper's text: 6-frame pairs stamped at their first frame, epipole at the
        principal point, per-pixel v/d averaged in 5° fields, the paper's median readout; each pair's
        flow in one step (no gyro pre-warp, no chaining through the frames between). front_end: as
        the field; filter: the readout's (:meth:`lobula.readout.ReadoutConfig.paper`)."""
        return cls(front_end=front_end, flow=FlowConfig(gap=6, prewarp=False, chain_fraction=0.0),
                   fields=FieldConfig(size_deg=5.0, pooling="pixel-mean", gap_correction=False, material=False),
                   readout=ReadoutConfig.paper(filter), epipole="principal", timestamps="start")

    def for_front_end(self, front_end: str) -> "VelocityConfig":
        """A deep copy that runs ``front_end``, with its epipole and κ-error defaults where this one had the
        other front end's (values set otherwise are kept)."""
        d = copy.deepcopy(self)
        d.front_end = front_end
        d.__post_init__()          # the front end's epipole, as a new configuration's, and validation
        now = (d.readout.kappa_rel_error, d.readout.shared_error_frac)
        # Another front end's default κ errors become this one's; κ errors set otherwise stay.
        if now in {tuple(f.kappa_errors) for f in FRONT_ENDS.values()}:
            d.readout.kappa_rel_error, d.readout.shared_error_frac = get_front_end(front_end).kappa_errors
        return d

    def to_dict(self) -> dict:
        """Every field, nested configurations as dicts."""
        return asdict(self)

    def to_json(self) -> str:
        """:meth:`to_dict` as one JSON string (keys sorted), as every output carries it."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "VelocityConfig":
        """The configuration :meth:`to_dict` wrote as ``d`` (keys it does not know are ignored)."""
        kinds = {f.name: f.type for f in fields(cls)}
        sub = dict(flow=FlowConfig, fields=FieldConfig, readout=ReadoutConfig, emd=EMDFrontEndConfig.from_dict)
        return cls(**{k: (sub[k](**v) if k in sub and k != "emd" else sub[k](v) if k == "emd" else v)
                      for k, v in d.items() if k in kinds})

    @classmethod
    def from_json(cls, text: str) -> "VelocityConfig":
        """The configuration :meth:`to_json` wrote as ``text``."""
        return cls.from_dict(json.loads(text))
