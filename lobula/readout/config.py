"""The readout's parameters (:class:`ReadoutConfig`) and what it returns (:class:`ReadoutResult`), SI units."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from lobula._fields import check_field_types


@dataclass
class ReadoutConfig:
    """Readout parameters (SI units).

    Parameters
    ----------
    method : {"kalman", "median"}
        "kalman" (the project's default) or "median" (the paper's text).
    filter : {"zero-phase", "causal"}
        "zero-phase" (offline, the paper's) or "causal" (online).
    paper_wn : float
        The paper's Butterworth cutoff, as a fraction of Nyquist.
    paper_order : int
        The paper's Butterworth order.
    stagger : int
        Frames between the two samples of the staggered difference for ṙ̄.
    cutoff_hz : float
        Hz: cutoff of the kalman readout's common low-pass of r̄, r²̄ and a.
    online_window_sigma : float
        Online, that low-pass is a symmetric Gaussian FIR (gain ½ at ``cutoff_hz``) cut at this
        many of its σ either side, so every term reaches the filter this many σ late (plus half
        the stagger): the measurement latency the forward filter bridges with ∫a and its
        uncertain offset. 1.5 (0.30 s at 30 frames/s) lies in a broad optimum on the suite's
        development scenes (causal RMSE 0.0104 m/s; 1.0 / 2.5 read 0.0109 / 0.0119): the
        bridge's error grows with the latency, the cut kernel's leakage of noise as it shortens.
        Unused offline.
    order : int
        Order of the offline (zero-phase Butterworth) common low-pass.
    accel_min_m_s2 : float
        m/s²: |a| below this carries no depth information (the noise floor of a filtered
        accelerometer).
    depth_min_m, depth_max_m : float
        m: the range of depths a field may imply, a physical one (d > 0) up to a backdrop 2 km away: the
        readout assumes no indoor scale (a known-answer test reads the same flight from 0.3 to 200 m).
        A far field's κ is a ratio over a small r̄ and errs more; its scatter widens the band
        rather than biasing v̂.
    min_valid_fraction : float
        Fraction of the fields that must agree on a physical depth.
    rest_depth_max_m : float or None
        m: the farthest the fields' median depth may be when judging that no flow means no motion
        (:func:`~lobula.readout.measurements.rest_measurement`). None (the default): the footage's own,
        learned where vision has fixed the speed (:func:`~lobula.readout.measurements.scene_depth`)
        — no bound before any is learned, and none in a scene mostly beyond what the acceleration
        reveals. A number is the user's knowledge of the scene (a room: about 5).
    rest_depth_margin : float
        The learned depth is widened by this factor: a camera may stop where the scene is deeper than
        anything it showed while accelerating (backing away from a wall).
    rest_accel_change_m_s2 : float
        m/s²: that judgement is made only where the accelerometer's forward reading (smoothed over
        5 frames) stays within this of a line (an offset and its ramp) over the last second
        (offline: the second around the frame; :func:`accelerometer_steady`) and, online, where
        that reading less the learned offset lies within this (plus 2σ of the offset) of zero
        (:func:`kalman_velocity`'s ``rest_accel``): a camera that starts, stops or keeps
        accelerating is not at rest, whatever the image shows. 0.05 is ~8× the smoothed reading's
        white noise at the synthetic IMU's 150 µg/√Hz and under the 0.1 m/s² a gentle start
        reaches in a fraction of a second; not fitted (0.03 and 0.1 read the same).
    accel_noise : float
        m/s²/√Hz: white acceleration noise driving v. 0.01 is measured, not fitted: on the suite's
        development scenes the accelerometer-derived a less the truth's derivative, its offset and
        ramp removed, averages over 1 s to 0.001–0.009 m/s² on the families that do not turn;
        0.05 makes the posterior 2–3× wider than the errors and the estimate worse.
    accel_turn_noise : float
        m/s²/√Hz per rad/s of |ω|: more acceleration noise while the camera turns. 0.1: on the
        rotation family's development scenes that 1 s average is 0.08–0.12 × the rms |ω|. Used
        where :func:`readout` is given ``turn_rate``.
    accel_turn_rate_max : float or None
        rad/s: |ω| counts up to this in that noise. The 0.1 per rad/s is measured on turns up to
        ~1 rad/s, and a brief fast turn errs far less than its rate would say: across the body
        saccades of the development fly flights (the saccadic family, seeds 100–105; 20–90° at 5–30
        rad/s) the offline accelerometer's velocity error is at most 0.024 m/s a saccade, where the
        uncapped noise grants 0.6 m/s (1σ) and the capped one 0.03. None: no cap.
    bias_walk : float
        m/s²/√s: random walk of the accelerometer offset.
    bias_prior_m_s2 : float
        m/s²: prior std of the accelerometer offset.
    v_prior_m_s : float
        m/s: prior std of v, wide enough for cars and drones (±2σ: 30 m/s). A walking-pace prior (1 m/s)
        holds a road vehicle's v̂ near 1 m/s until vision overrules it (the suite's road family: 0.59 and
        12.6 m/s offline RMSE where 15 m/s gives 0.11 and 0.02); on the indoor families the two read alike.
    meas_floor_m_s : float
        m/s: the smallest standard deviation granted to one frame's measurement.
    kappa_rel_error : float
        Error of vision's κ = a/v that all fields share (flow error, residual rotation), as a
        fraction of |κ|, added in quadrature to the fields' standard error. 0.25 is fitted on one
        world only — the suite's "moving" family, development seed 100, where it brings the online
        filter's ±2σ coverage to ~95 % (0.1: 71 %) — and tested on the other families and seeds.
        The finer flow grid (:attr:`lobula.flow.FlowConfig.dis_grid_px`) would allow 0.125 there,
        but 0.125 fails three known-answer tests (the band widening while turning, a shared error
        covered offline, fields drowned in noise).
    adapt_s : float
        s: time constant of the offline filter's covariance matching, which scales the κ
        measurement's noise up by the running mean of its normalised squared innovations where
        they show it worse than claimed (0: off, the default). 2 s helps offline on the panels,
        fast and corridor families, but widens the corridor's band past 99.5 % coverage on the
        6 s scene of tests/test_families.py and doubles the ground family's seed-1 error.
    accel_scale_error : float
        Fraction (1σ): the accelerometer's scale-factor error. Vision measures only κ = a/v, so
        v̂ = a/κ takes the accelerometer's scale whole and nothing the camera sees corrects it; it
        adds ``accel_scale_error``·|v̂| to the posterior std. 0.01 is the sensitivity tolerance of a
        consumer MEMS accelerometer such as the D435i's BMI055, and what the realistic synthetic
        IMU draws per axis (stimuli.imu.IMUConfig.realistic); set it from a calibration where one
        exists.
    max_std_m_s, max_rel_std : float
        v̂ is reported (else unobservable, NaN) where its posterior std is at most ``max_std_m_s`` (m/s)
        or ``max_rel_std`` of |v̂|, whichever is larger: a camera at 8 m/s known to ±0.3 m/s is known
        (the accelerometer's 1 % scale error alone is 0.08 m/s there), one at 0.2 m/s is not.
    coupling_z, coupling_window_s, coupling_refute_z, coupling_power_m_s2 : float
        Vision fixes the speed only once the fields' ṙ̄ − r²̄ has followed the accelerometer
        (:mod:`lobula.readout.coupling`): Fisher's z of their correlation over ``coupling_window_s``
        (s) must reach ``coupling_z`` (one-sided; 3 is a 0.13 % chance of a coupling in noise), or the
        rest bound must hold v at 0. From then on the filter carries v̂ with the accelerometer, reported
        while its σ allows, until a whole window over which the low-passed acceleration varied by at
        least ``coupling_power_m_s2`` (m/s², std) shows z below ``coupling_refute_z``: vision is then
        refuted, takes no part in the filter, and v̂ is reported unobservable, with the reason.
        ``coupling_z`` 0: off.
    shared_error_frac, shared_error_s : float
        Vision's a_m = κ·v + b also carries an error all fields share that persists for seconds
        (fast family: +0.07–0.11 m/s² for seconds on end), which per-frame white noise cannot
        describe. Online it is a Schmidt–Kalman "consider" state: a Gauss–Markov error of time
        constant ``shared_error_s`` (s) whose std is ``shared_error_frac`` × the running RMS (same
        time constant) of the κ measurement's innovations — accounted for in the gain and the
        covariance, never estimated, so the forward filter can neither average it into a
        confident, wrong offset b nor let it run away. The RMS also takes in the start's large
        innovations (v still unknown), which keeps the offset from locking in during the first
        seconds. Offline the same error is an estimated state of the smoother, which has the whole
        record. 0.5 balances the fast family (whose error falls as the fraction grows) against
        the dim one (whose error rises) on the development scenes; 0: off.
    r2_term : {"field", "mean_squared"}
        "field": the field's mean of r² (the geometry); "mean_squared": r̄² (the ablation).
    fusion : {"kalman", "vision-only"}
        "kalman": vision's measurements fused with integrated acceleration; "vision-only": the
        per-frame robust median of v_f through the same low-pass, no acceleration integrated.
    reversal : bool
        Use the moments the image's expansion changes sign (:func:`reversal_measurement`): every
        field's r̄ = v/d has the sign of v whatever its depth, so where the fields' median r̄ goes
        from clearly negative to clearly positive (or back), v passed through 0 in between — a
        measurement v(t*) = 0 that needs neither depth nor κ, exactly where κ = a/v is
        ill-conditioned and a reversing camera loses its lock. On by default: on the development
        scenes it lowers the causal RMSE on all twelve fast-family seeds (0.0169 m/s against
        0.0174) and leaves the other families' errors, ±2σ coverage and observable fraction as
        they are.
    sign : bool
        Use the sign of the image's expansion (:func:`expansion_sign`): where the fields' signed
        median r̄ has been clearly of one sign (beyond NO_EXPANSION_SE standard errors) for
        SIGN_PERSIST_S, v has that sign whatever the depths, and a reported posterior (std ≤
        ``max_std_m_s``) of the other sign is moved to it, widened first where it is sure
        (:func:`_sign_update`). It needs no κ, so it guards against a κ that errs for seconds (an
        EMD front end whose gains drift as texture flows) and carries v̂ through zero against what
        every field sees. Off by default: on the camera's DIS readout (22 development scenes,
        causal) it changes nothing on 21 and costs one (mixed 101: 0.0155 m/s against 0.0138),
        as DIS's κ does not drift so.
    stop : bool
        Use where the fields' expansion falls to a few percent of what it was moments before
        (:func:`stop_measurement`): v fell alike, v(t) = ρ·v(t − Δ), whatever the depths — what
        tells a vehicle braking to a stop from an accelerometer offset, which a constant braking's
        κ cannot. On by default.
    stamp_error_s : float
        s (1σ): how far the fields' rates may be off the times they are stamped with, added to
        each reversal's timing (a front end whose latency is taken out only roughly, as the EMD's,
        moves the crossing it shows). One frame at 30 frames/s: with none the development scenes
        gain a little more, but rates stamped 2 frames late push the offline band below 90 %
        (tests/test_readout.py).
    lag_s : float
        s: with filter "causal", a fixed-lag smoother (0: the forward filter, the default). Every
        input stays online (causal low-passes, the online gravity reference); each frame's v̂ also
        takes the measurements up to ``lag_s`` after it, so it is known ``lag_s`` (plus the
        measurement latency) after the moment it describes — a declared delay, as in fixed-lag
        smoothing for odometry. The forward filter averages vision's errors over the past only,
        and its causal estimate stays ~2× the smoother's on the development scenes; 0.5–1 s of
        look-ahead recovers most of that.
    """

    method: str = "kalman"
    filter: str = "zero-phase"
    paper_wn: float = 0.04
    paper_order: int = 1
    stagger: int = 4
    cutoff_hz: float = 1.0
    online_window_sigma: float = 1.5
    order: int = 2
    accel_min_m_s2: float = 0.03
    depth_min_m: float = 0.1
    depth_max_m: float = 2000.0
    min_valid_fraction: float = 0.25
    rest_depth_max_m: float | None = None
    rest_depth_margin: float = 2.0
    rest_accel_change_m_s2: float = 0.05
    accel_noise: float = 0.01
    accel_turn_noise: float = 0.1
    accel_turn_rate_max: float | None = 1.0
    bias_walk: float = 0.002
    bias_prior_m_s2: float = 0.1
    v_prior_m_s: float = 15.0
    meas_floor_m_s: float = 0.02
    kappa_rel_error: float = 0.25
    adapt_s: float = 0.0
    accel_scale_error: float = 0.01
    max_std_m_s: float = 0.1
    max_rel_std: float = 0.05
    coupling_z: float = 3.0
    coupling_window_s: float = 4.0
    coupling_refute_z: float = 0.0
    coupling_power_m_s2: float = 0.05
    shared_error_frac: float = 0.5
    shared_error_s: float = 3.0
    r2_term: str = "field"
    fusion: str = "kalman"
    reversal: bool = True
    sign: bool = False
    stop: bool = True
    stamp_error_s: float = 0.033
    lag_s: float = 0.0

    @property
    def difference_frames(self) -> int:
        """Frames between the two ends of ṙ̄'s difference: ``stagger`` made even and at least 2."""
        return max(2, self.stagger + self.stagger % 2)

    def __post_init__(self):
        check_field_types(self)
        if self.accel_turn_rate_max is not None and not (np.isfinite(self.accel_turn_rate_max)
                                                         and self.accel_turn_rate_max > 0):
            raise ValueError(f"accel_turn_rate_max must be a finite rate > 0 (rad/s) or None, got {self.accel_turn_rate_max}")
        if not (np.isfinite(self.lag_s) and self.lag_s >= 0):
            raise ValueError(f"lag_s must be a finite number of seconds >= 0, got {self.lag_s}")
        if self.lag_s > 0 and (self.filter != "causal" or self.method != "kalman" or self.fusion != "kalman"):
            raise ValueError(f"lag_s (a fixed-lag smoother, {self.lag_s:g} s) needs the kalman readout's causal "
                             f"filter with kalman fusion, got method {self.method!r}, filter {self.filter!r}, "
                             f"fusion {self.fusion!r}; the zero-phase filter already sees the whole record")
        if self.r2_term not in ("field", "mean_squared"):
            raise ValueError(f"unknown r2_term {self.r2_term!r}; use 'field' or 'mean_squared'")
        if self.fusion not in ("kalman", "vision-only"):
            raise ValueError(f"unknown fusion {self.fusion!r}; use 'kalman' or 'vision-only'")
        if self.method not in ("kalman", "median"):
            raise ValueError(f"unknown readout method {self.method!r}; use 'kalman' or 'median'")
        if self.filter not in ("zero-phase", "causal"):
            raise ValueError(f"unknown filter kind {self.filter!r}; use 'zero-phase' or 'causal'")
        if not (np.isfinite(self.online_window_sigma) and self.online_window_sigma > 0):
            raise ValueError(f"online_window_sigma must be a positive number of σ, got {self.online_window_sigma}")
        if not (np.isfinite(self.stamp_error_s) and self.stamp_error_s >= 0):
            raise ValueError(f"stamp_error_s must be a finite number of seconds >= 0, got {self.stamp_error_s}")
        if self.rest_depth_max_m is not None and not self.rest_depth_max_m > 0:
            raise ValueError(f"rest_depth_max_m must be a depth in metres > 0 or None (learned), got {self.rest_depth_max_m}")
        if not (np.isfinite(self.rest_depth_margin) and self.rest_depth_margin >= 1.0):
            raise ValueError(f"rest_depth_margin must be a finite factor >= 1, got {self.rest_depth_margin}")
        if not 0.0 <= self.accel_scale_error < 1.0:
            raise ValueError(f"accel_scale_error is a fraction in [0, 1), got {self.accel_scale_error}")
        positive = ("cutoff_hz", "v_prior_m_s", "meas_floor_m_s", "max_std_m_s", "accel_min_m_s2",
                    "accel_noise", "bias_prior_m_s2", "depth_min_m", "depth_max_m", "coupling_window_s",
                    "shared_error_s")
        for name in positive:  # stds, rates, bounds and windows the filter divides by or widens with
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"ReadoutConfig.{name} must be a finite number > 0, got {value!r}")
        # stds, walks, thresholds and windows where 0 turns the term off and a negative one means nothing
        for name in ("accel_turn_noise", "bias_walk", "kappa_rel_error", "adapt_s", "coupling_z",
                     "coupling_power_m_s2", "rest_accel_change_m_s2"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"ReadoutConfig.{name} must be a finite number >= 0, got {value!r}")
        for name, low_open in (("min_valid_fraction", True), ("shared_error_frac", False)):
            value = getattr(self, name)
            if not (0 < value <= 1 if low_open else 0 <= value <= 1):
                raise ValueError(f"ReadoutConfig.{name} must be a fraction in {'(0' if low_open else '[0'}, 1], "
                                 f"got {value!r}")
        if not self.depth_min_m < self.depth_max_m:
            raise ValueError(f"ReadoutConfig.depth_min_m must be below depth_max_m ({self.depth_max_m} m), got "
                             f"{self.depth_min_m}")
        if not 0 < self.paper_wn < 1:
            raise ValueError(f"ReadoutConfig.paper_wn must be a normalised frequency in (0, 1) (1: Nyquist), got "
                             f"{self.paper_wn!r}")
        if not (isinstance(self.max_rel_std, (int, float)) and self.max_rel_std >= 0):  # 0: the absolute bound alone
            raise ValueError(f"ReadoutConfig.max_rel_std must be a number >= 0, got {self.max_rel_std!r}")
        for name in ("order", "stagger", "paper_order"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"ReadoutConfig.{name} must be a whole number >= 1, got {value!r}")

    @classmethod
    def paper(cls, filter: str = "zero-phase") -> "ReadoutConfig":
        """The paper's readout as its text states it.

        Parameters
        ----------
        filter : {"zero-phase", "causal"}
            The Butterworth's kind: offline (the paper's) or online.

        Returns
        -------
        ReadoutConfig
            method "median", a 5-frame stagger, the paper's Butterworth.
        """
        return cls(method="median", filter=filter, stagger=5)

    #: κ's shared error (kappa_rel_error, shared_error_frac) for EMD fields, in place of DIS flow's 0.25 / 0.5
    EMD_KAPPA_ERRORS = (0.5, 0.8)

    @classmethod
    def emd(cls, **kw) -> "ReadoutConfig":
        """The readout for EMD fields: κ's shared error as the compound eye's readout carries it
        (:data:`EMD_KAPPA_ERRORS`; experiments.eye_velocity.EyeVelocityConfig says why: each field's EMD
        gain drifts as texture flows through it, an error the fields share and that lasts). On the camera's
        EMD front end (development suite worlds, seeds 100 / 101, causal, fixating gaze), DIS's 0.25 / 0.5 →
        these: ±2σ rotation 53 / 100 → 89 / 100 %, dim 67 → 100 %, offaxis 79 → 97 %, mixed 58 → 70 %,
        panels 90 / 96 → 96 / 100 %; RMSE rotation 0.110 / 0.036 → 0.120 / 0.027 m/s, panels 0.045 / 0.032 →
        0.054 / 0.032, dim 0.044 → 0.036, moving 0.057 → 0.047, offaxis 0.074 → 0.067, the rest within
        0.004; observable under rotation 75 / 84 → 58 / 65 % (the wider band says so).

        Parameters
        ----------
        **kw
            Further fields of ReadoutConfig; a ``kappa_rel_error`` or ``shared_error_frac`` given here wins.

        Returns
        -------
        ReadoutConfig
        """
        k, s = cls.EMD_KAPPA_ERRORS
        return cls(**{"kappa_rel_error": k, "shared_error_frac": s, **kw})

    def to_dict(self) -> dict:
        """The fields as a plain dict (name: value)."""
        return asdict(self)


def std_allowed(v, cfg: "ReadoutConfig"):
    """m/s: the largest posterior std at which v̂ (m/s, any shape) is reported: max(max_std_m_s, max_rel_std·|v̂|)."""
    return np.maximum(cfg.max_std_m_s, cfg.max_rel_std * np.abs(v))


@dataclass
class ReadoutResult:
    """Per-frame outputs of the readout, time-major (n frames, F fields).

    Parameters
    ----------
    v_hat : ndarray, (n,)
        m/s: the estimated forward velocity: where observable, the filter's posterior; beyond, carried by the
        accelerometer (:mod:`lobula.readout.carry`); NaN where vision has not fixed the speed (online: yet).
    observable : ndarray of bool, (n,)
        Where vision fixes v_hat.
    v_std : ndarray, (n,)
        m/s: its standard deviation (NaN where v_hat is, and throughout for the paper's readout).
    v_field : ndarray, (n, F)
        m/s: each field's velocity a·r̄/(ṙ̄ − r²̄), NaN for rejected fields.
    r_dot : ndarray, (n, F)
        1/s²: each field's ṙ̄.
    measurement : ndarray, (n,)
        m/s: vision's per-frame velocity measurement (the paper's: the median of v_field).
    measurement_std : ndarray, (n,)
        m/s: its standard deviation.
    accel : ndarray, (n,)
        m/s²: the forward acceleration used.
    info : dict
        The kalman readout's ``measurement_delay_s`` (s) and, with kalman fusion, ``lag_s`` (s), the verdicts on
        vision (``vision_*``, ``scene_depth``) and the filter's ``posterior_mean`` and ``posterior_std`` (m/s, (n,),
        on every frame); empty for the paper's.
    """

    v_hat: np.ndarray
    observable: np.ndarray
    v_std: np.ndarray
    v_field: np.ndarray
    r_dot: np.ndarray
    measurement: np.ndarray
    measurement_std: np.ndarray
    accel: np.ndarray
    info: dict = field(default_factory=dict)

