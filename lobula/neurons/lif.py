"""The leaky integrate-and-fire neuron: exact subthreshold integration, exact threshold crossings
inside a step, a refractory period, and white or Ornstein–Uhlenbeck current noise.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple, Sequence

from .._optional import torch
from .streaming import _as_float, _check_dt, _check_input, _check_run_input, _record, _run_loop, make_generator

if TYPE_CHECKING:
    from torch import Tensor


_NOISE_KINDS = ("none", "white", "ou")


@dataclass(frozen=True)
class LIFConfig:
    """Leaky integrate-and-fire neuron driven by a current.

    ``tau_m dV/dt = -(V - V_rest) + R (I(t) + I_noise(t))``; a spike when V reaches
    V_threshold, then V is clamped at V_reset for t_ref. SI units: V_rest, V_threshold,
    V_reset in V; t_ref, tau_m, noise_tau in s; R in Ω; noise_std in A.

    Defaults are the integrate-and-fire example of Dayan & Abbott (2001, §5.4):
    V_rest = V_reset = -65 mV, V_threshold = -50 mV, tau_m = 10 ms, R = 10 MΩ
    (rheobase 1.5 nA). t_ref = 2 ms is a typical absolute refractory period (Gerstner
    et al. 2014, Neuronal Dynamics, ch. 1).

    Noise (``noise``):
      - ``"none"``;
      - ``"ou"``: an Ornstein–Uhlenbeck current with stationary standard deviation
        ``noise_std`` (A) and correlation time ``noise_tau`` (s), updated by its exact
        discretisation; the membrane holds it constant within a step (its error is
        O(dt/noise_tau)). 5 ms lies between the excitatory (2.7 ms) and inhibitory
        (10.5 ms) synaptic-noise time constants of Destexhe et al. (2001);
      - ``"white"``: ``I_noise = noise_std·sqrt(tau_m)·ξ(t)`` (ξ unit Gaussian white
        noise, the convention of Brunel 2000), so the free membrane's stationary SD is
        ``R·noise_std/√2``; the membrane update with it is exact (an OU process in V).
    """

    V_rest: float = -0.065
    V_threshold: float = -0.050
    V_reset: float = -0.065
    t_ref: float = 0.002
    tau_m: float = 0.010
    R: float = 10e6
    noise: str = "none"
    noise_std: float = 0.0
    noise_tau: float = 0.005

    def __post_init__(self):
        for name in ("V_rest", "V_threshold", "V_reset", "t_ref", "tau_m", "R", "noise_std", "noise_tau"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"LIFConfig.{name} must be a finite number, got {v!r}")
        if self.tau_m <= 0 or self.R <= 0 or self.noise_tau <= 0:
            raise ValueError(f"LIFConfig tau_m, R and noise_tau must be positive, got "
                             f"tau_m={self.tau_m}, R={self.R}, noise_tau={self.noise_tau}")
        if self.t_ref < 0 or self.noise_std < 0:
            raise ValueError(f"LIFConfig t_ref and noise_std must be >= 0, got "
                             f"t_ref={self.t_ref}, noise_std={self.noise_std}")
        if not self.V_reset < self.V_threshold:
            raise ValueError(f"LIFConfig needs V_reset < V_threshold, got V_reset={self.V_reset} "
                             f"V, V_threshold={self.V_threshold} V (volts, not mV)")
        if self.noise not in _NOISE_KINDS:
            raise ValueError(f"LIFConfig.noise must be one of {_NOISE_KINDS}, got {self.noise!r}")

    @property
    def noisy(self) -> bool:
        """Whether the neuron has noise (a noise kind other than "none" and noise_std > 0)."""
        return self.noise != "none" and self.noise_std > 0

    @property
    def rheobase(self) -> float:
        """Smallest constant current (A) that makes the neuron fire."""
        return (self.V_threshold - self.V_rest) / self.R

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


class LIFState(NamedTuple):
    """State of an LIF population; every field (trials, neurons).

    v: membrane potential (V) at the end of the last step; refractory: refractory time
    still to serve (s); noise: OU noise current (A, zeros unless noise="ou");
    spikes: number of spikes in the last step; spike_offset: time of the first of them
    after the start of the step (s), NaN where there was none.
    """

    v: Tensor
    refractory: Tensor
    noise: Tensor
    spikes: Tensor
    spike_offset: Tensor


def _lif_segment(v0: Tensor, v_inf: Tensor, h: Tensor, c: LIFConfig, sd_inf: float,
                 generator: torch.Generator | None):
    """Free relaxation of V from ``v0`` toward ``v_inf`` for ``h`` seconds.

    Returns (v_end, crossed, t_cross): V at the end, whether V reached threshold
    within h, and when (s after the segment's start; meaningful only where crossed).
    Without white noise V is monotone toward v_inf, so it crossed iff it ends at or
    above threshold, and the crossing time is exact: τ·ln((V_inf − V0)/(V_inf − V_th)).
    With white noise (sd_inf > 0) the end value carries the exact OU increment and the
    crossing time is that of the exponential path from v0 to v_end. A path that starts and
    ends below threshold may still have touched it in between: it did with the Brownian
    bridge's probability exp(−2(V_th − V0)(V_th − V_end)/s²), s² the increment's variance
    (the standard correction of discretely monitored barriers; it makes the spike count at
    dt = 1 ms match Siegert's rate where dt ≪ tau_m), and such a spike is put mid-segment.
    """
    v_th = c.V_threshold
    decay = torch.exp(h * (-1.0 / c.tau_m))
    v_end = v_inf + (v0 - v_inf) * decay
    target = v_inf
    if sd_inf > 0:
        xi = torch.randn(v0.shape, generator=generator, device=v0.device, dtype=v0.dtype)
        v_end = v_end + sd_inf * torch.sqrt(-torch.expm1(h * (-2.0 / c.tau_m))) * xi
        # The noise over the step acts like an extra constant current: relax toward the
        # target that ends at v_end, and take that path's crossing time (exact as σ → 0,
        # unlike a linear interpolation, which is badly off when dt is not ≪ tau_m).
        target = (v_end - v0 * decay) / -torch.expm1(h * (-1.0 / c.tau_m))
    # NaN or inf where there is no crossing: those entries are never selected.
    t_cross = torch.minimum(c.tau_m * torch.log((target - v0) / (target - v_th)), h)
    at_start = v0 >= v_th                       # started at/above threshold: fires at once
    crossed = (v_end >= v_th) | at_start
    t_cross = torch.where(at_start, 0.0, t_cross)
    if sd_inf > 0:
        var = sd_inf ** 2 * -torch.expm1(h * (-2.0 / c.tau_m))
        touched = torch.exp(-2.0 * (v_th - v0).clamp_min(0) * (v_th - v_end).clamp_min(0) / var)
        u = torch.rand(v0.shape, generator=generator, device=v0.device, dtype=v0.dtype)
        bridged = ~crossed & (u < touched)      # NaN where h = 0: never
        crossed = crossed | bridged
        t_cross = torch.where(bridged, 0.5 * h, t_cross)
    return v_end, crossed, t_cross


def lif_step(state: LIFState, current: Tensor, dt: float, config: LIFConfig,
             generator: torch.Generator | None = None) -> LIFState:
    """One step of ``dt`` (s) of an LIF population in ``state`` (:class:`LIFState`, (trials, neurons)) with
    ``current`` (A, (trials, neurons)) held constant, the neuron of ``config``; ``generator``: the torch
    generator of the noise (required where ``config`` has noise). Returns the new state.

    Between events the membrane relaxes exactly toward ``V_inf = V_rest + R·I``; a
    threshold crossing inside the step is found in closed form,
    ``t* = tau_m · ln((V_inf - V0)/(V_inf - V_th))`` (with white noise, the same formula
    for the exponential path that ends at the noisy V, and crossings that return below
    threshold within the step drawn with the Brownian bridge's probability: keep dt ≪ tau_m).
    After a spike V sits at V_reset for t_ref, and the step reports the spike count and
    the exact time of the first spike. If t_ref < dt the refractory period can end
    inside the step; the neuron then
    integrates again from that moment, so several spikes per step are counted exactly
    (a loop over such events runs on the whole batch with masks and stops when none
    is left; with t_ref ≥ dt it never runs).
    """
    c = config
    v, ref = state.v, state.refractory
    if c.noisy and generator is None:
        raise ValueError("this LIFConfig has noise: pass generator=make_generator(seed, device)")
    # Exact SD of the white-noise membrane increment over h: (R σ/√2)·sqrt(1 - e^{-2h/τ}).
    sd_inf = c.R * c.noise_std / math.sqrt(2.0) if (c.noisy and c.noise == "white") else 0.0
    i_total = current + state.noise if c.noise == "ou" else current
    v_inf = c.V_rest + c.R * i_total

    # First segment: from the end of any refractory period to the end of the step.
    t0 = ref.clamp(max=dt)                      # s after the step's start
    v0 = torch.where(ref > 0, c.V_reset, v)     # clamped at V_reset while refractory
    v_end, crossed, t_cross = _lif_segment(v0, v_inf, dt - t0, c, sd_inf, generator)
    t_spike = t0 + t_cross
    spikes = crossed.to(v.dtype)
    offset = torch.where(crossed, t_spike, float("nan"))
    v_out = torch.where(crossed, c.V_reset, v_end)
    free_at = torch.where(crossed, t_spike + c.t_ref, ref)   # when each neuron is free again
    if c.t_ref < dt:
        active = crossed & (free_at < dt)
        events = 1
        while bool(active.any()):
            events += 1
            if events > 10_000:   # only with t_ref = 0 and a drive far above threshold
                raise RuntimeError(f"over 10000 spikes in one step of {dt} s: use a smaller dt "
                                   f"or a refractory period t_ref > 0")
            h = (dt - free_at).clamp_min(0)
            v_end, crossed, t_cross = _lif_segment(torch.full_like(v, c.V_reset), v_inf, h, c,
                                                   sd_inf, generator)
            crossed = crossed & active
            spikes = spikes + crossed.to(v.dtype)
            v_out = torch.where(active, torch.where(crossed, c.V_reset, v_end), v_out)
            free_at = torch.where(crossed, free_at + t_cross + c.t_ref, free_at)
            active = crossed & (free_at < dt)
    refractory = (free_at - dt).clamp_min(0)

    noise = state.noise
    if c.noise == "ou" and c.noisy:
        # Exact OU discretisation: x' = x e^{-dt/τn} + σ sqrt(1 - e^{-2dt/τn}) ξ.
        xi = torch.randn(v.shape, generator=generator, device=v.device, dtype=v.dtype)
        noise = noise * math.exp(-dt / c.noise_tau) + \
            c.noise_std * math.sqrt(-math.expm1(-2 * dt / c.noise_tau)) * xi
    return LIFState(v_out, refractory, noise, spikes, offset)


class LIFNeuron:
    """A population of leaky integrate-and-fire neurons of ``config`` (see :class:`LIFConfig`; None: the default)."""

    records = ("v", "refractory", "noise", "spikes", "spike_offset")

    def __init__(self, config: LIFConfig | None = None):
        self.config = config or LIFConfig()

    def init_state(self, trials: int, neurons: int, *, device=None,
                   dtype: torch.dtype | None = None, generator: torch.Generator | None = None,
                   v0: float | None = None) -> LIFState:
        """Resting state (trials, neurons) (V = V_rest unless ``v0``, V), not refractory, tensors on ``device``
        in ``dtype`` (None: torch's default). With OU noise and a ``generator``, the noise current starts
        from its stationary distribution so a run has no noise transient."""
        shape = (trials, neurons)
        dtype = dtype or torch.get_default_dtype()
        c = self.config
        v = torch.full(shape, c.V_rest if v0 is None else float(v0), device=device, dtype=dtype)
        noise = torch.zeros_like(v)
        if c.noise == "ou" and c.noisy and generator is not None:
            noise = c.noise_std * torch.randn(shape, generator=generator, device=v.device, dtype=dtype)
        return LIFState(v, torch.zeros_like(v), noise, torch.zeros_like(v),
                        torch.full_like(v, float("nan")))

    def step(self, state: LIFState | None, current, dt: float, *,
             generator: torch.Generator | None = None) -> LIFState:
        """Advance by ``dt`` (s) with ``current`` (A, trials × neurons) held constant.
        ``state=None`` starts from rest with the current's shape, device and dtype. ``generator``: the torch
        generator of the noise (required where the neuron has noise)."""
        dt = _check_dt(dt)
        if state is None:
            current = _as_float(current)
            if current.dim() != 2:
                raise ValueError(f"current must be (trials, neurons), got shape {tuple(current.shape)}")
            state = self.init_state(*current.shape, device=current.device, dtype=current.dtype,
                                    generator=generator)
        else:
            current = _as_float(current, state.v.dtype)
            _check_input(current, state.v, "current")
        return lif_step(state, current, dt, self.config, generator)

    def run(self, current, dt: float, *, seed: int | None = 0, state: LIFState | None = None,
            record: Sequence[str] = ("v", "spikes"), return_state: bool = False):
        """Whole run. current: (trials, time, neurons) in A. Returns ``{name: (time,
        trials, neurons)}`` for ``record`` ⊆ {"v", "refractory", "noise", "spikes",
        "spike_offset"}; entry k is the state at (k+1)·dt, and the exact time of the
        first spike in step k is ``k·dt + spike_offset[k]``. ``seed`` seeds a generator
        on the current's device (used only with noise). With ``return_state=True``
        returns ``(records, final_state)``."""
        dt = _check_dt(dt)
        current = _check_run_input(current, "current")
        record = _record(record, self.records, "LIFNeuron")
        g = make_generator(seed, current.device) if (self.config.noisy and seed is not None) else None
        if self.config.noisy and g is None:
            raise ValueError("this LIFConfig has noise: give run() an integer seed")
        if state is None:
            state = self.init_state(current.shape[0], current.shape[2], device=current.device,
                                    dtype=current.dtype, generator=g)
        out, state = _run_loop(self.step, state, current, dt, record, g)
        return (out, state) if return_state else out
