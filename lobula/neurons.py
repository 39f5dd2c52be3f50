"""Neuron dynamics: rate neurons, leaky integrate-and-fire neurons, Poisson spiking.

Every population is a batch of ``(trials, neurons)`` torch tensors (any shape works,
the update is elementwise); the device and float dtype follow the input. Nothing
loops over trials or neurons in Python; the whole-run helpers loop over time steps.

Units are SI throughout: seconds, volts, amperes, ohms, and rates in Hz (spikes/s).

Time convention (for all three models): the input of step ``k`` is held constant over
``[k·dt, (k+1)·dt)`` (zero-order hold, as a frame-by-frame pipeline delivers it), and
the state a step returns is the state at ``(k+1)·dt``. Within that assumption the rate
neuron and the subthreshold LIF membrane are integrated exactly (exponential
integration, not Euler), and LIF spike times are the exact threshold crossings inside
the step, so the step size sets the time resolution of the *input*, not the accuracy
of the integration.

Streaming API, the same for every model (``model`` = :class:`RateNeuron`,
:class:`LIFNeuron` or :class:`PoissonNeuron`)::

    state = model.init_state(trials, neurons, device=..., dtype=...)   # or None
    for frame in ...:
        state = model.step(state, input_k, dt, generator=g)            # new state
    rec = model.run(inputs, dt, seed=0)      # inputs (trials, time, neurons)
    rec["r"]  # (time, trials, neurons): time-major

Random numbers come only from an explicit ``torch.Generator`` (see
:func:`make_generator`), so the same seed gives identical arrays on the same device
(CPU and CUDA generators produce different streams).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple, Sequence

from ._optional import is_tensor, torch

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "RateNeuronConfig", "RateState", "RateNeuron", "naka_rushton", "rate_step",
    "LIFConfig", "LIFState", "LIFNeuron", "lif_step", "lif_fi_curve", "lif_rate", "lif_isi_cv",
    "lif_current_for_rate",
    "PoissonConfig", "PoissonState", "PoissonNeuron", "poisson_spikes",
    "make_generator",
]


# --------------------------------------------------------------------------- helpers

def make_generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    """A seeded ``torch.Generator`` on ``device`` (it must live where the tensors live)."""
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise TypeError(f"seed must be an int, got {seed!r}")
    g = torch.Generator(device=torch.device(device))
    g.manual_seed(seed)
    return g


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"time step dt must be a positive number of seconds, got {dt}")
    return dt


def _as_float(x, dtype: torch.dtype | None = None) -> Tensor:
    """Input as a floating tensor (integers become the default float dtype)."""
    x = torch.as_tensor(x)
    if dtype is not None:
        return x.to(dtype)
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())


def _check_input(x: Tensor, like: Tensor, what: str) -> None:
    # Broadcasting a (1, neurons) input over trials is fine; growing the state is not.
    # (The rule written out: torch.broadcast_shapes costs ~0.4 ms a call, and this runs every step.)
    xs, ls = tuple(x.shape), tuple(like.shape)
    ok = len(xs) <= len(ls) and all(a == b or a == 1 for a, b in zip(reversed(xs), reversed(ls)))
    if not ok:
        raise ValueError(f"{what} has shape {tuple(x.shape)} but the state is "
                         f"{tuple(like.shape)} (trials, neurons); pass one value per "
                         f"neuron, or init_state with the input's shape")


def _check_run_input(x, name: str) -> Tensor:
    x = _as_float(x)
    if x.dim() != 3:
        raise ValueError(f"{name} must be (trials, time, neurons), got shape {tuple(x.shape)}")
    if x.shape[1] == 0:
        raise ValueError(f"{name} has no time steps (shape {tuple(x.shape)})")
    return x


def _record(names: Sequence[str], allowed: Sequence[str], model: str) -> tuple[str, ...]:
    names = (names,) if isinstance(names, str) else tuple(names)
    bad = [n for n in names if n not in allowed]
    if bad:
        raise ValueError(f"{model} cannot record {bad}; it records {list(allowed)}")
    return names


def _run_loop(step, state, inputs: Tensor, dt: float, record: tuple[str, ...], generator):
    """Step over the time axis of ``inputs`` (trials, time, neurons), filling
    preallocated time-major records (one copy per step, no list+stack)."""
    n_t = inputs.shape[1]
    out: dict[str, Tensor] = {}
    for k in range(n_t):
        state = step(state, inputs[:, k], dt, generator=generator)
        if k == 0:
            for name in record:
                v = getattr(state, name)
                out[name] = torch.empty((n_t, *v.shape), dtype=v.dtype, device=v.device)
        for name in record:
            out[name][k] = getattr(state, name)
    return out, state


# --------------------------------------------------------------------------- rate neuron

@dataclass(frozen=True)
class RateNeuronConfig:
    """Leaky-integrator rate neuron with a Naka–Rushton output.

    ``tau_m * dx/dt = -x + u(t)``,  ``r = r_max * x^n / (x^n + c50^n)`` for x > 0, else 0.

    tau_m: integration time constant (s). 10 ms: the membrane/firing-rate time constant
        of the standard rate model (Dayan & Abbott 2001, Theoretical Neuroscience, §7.2).
    r_max: saturating rate (Hz). 100 Hz: an order-of-magnitude ceiling for sustained
        firing of visual projection neurons; set it per population.
    c50: drive giving half of r_max (same units as the input drive, which is
        dimensionless unless a stage says otherwise).
    n: Naka–Rushton exponent. 2, as in Heeger's (1992) normalisation model; Albrecht &
        Hamilton (1982) fit exponents of roughly 2–3 to contrast-response curves.
    """

    tau_m: float = 0.010
    r_max: float = 100.0
    c50: float = 1.0
    n: float = 2.0

    def __post_init__(self):
        for name in ("tau_m", "r_max", "c50", "n"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"RateNeuronConfig.{name} must be a positive number, got {v!r}")

    def to_dict(self) -> dict:
        return asdict(self)


class RateState(NamedTuple):
    """x: integrated drive (input units), r: output rate (Hz); each (trials, neurons)."""

    x: Tensor
    r: Tensor


def naka_rushton(x: Tensor, r_max: float, c50: float, n: float) -> Tensor:
    """Rectifying, saturating output ``r_max * x^n / (x^n + c50^n)`` for x > 0, else 0.

    x: drive, any shape; returns a rate in the units of ``r_max`` (Hz), same shape.
    Computed as ``r_max·q/(1+q)`` with ``q = (x/c50)^n`` (no cancellation for small
    drives); x/c50 is capped at 1e30^(1/n) so q cannot overflow even in float32 (there
    ``q/(1+q)`` is already 1 to machine precision), so huge or infinite drives give r_max.
    """
    y = (x * (1.0 / c50)).clamp(0.0, 1e30 ** (1.0 / n))
    q = y * y if n == 2 else y ** n            # the common exponent without pow
    return q / (1 + q) * r_max


def rate_step(state: RateState, drive: Tensor, dt: float, config: RateNeuronConfig) -> RateState:
    """One exact step of the leaky integrator for a drive held constant over ``dt`` (s).

    ``x(t+dt) = x + (1 - e^{-dt/τ})·(u - x)``; ``expm1`` keeps ``1 - e^{-dt/τ}``
    accurate when dt ≪ τ. drive: (trials, neurons), or broadcastable to the state.
    """
    gain = -math.expm1(-dt / config.tau_m)
    x = torch.lerp(state.x, drive.expand_as(state.x), gain)    # x + gain·(u − x), one kernel
    return RateState(x, naka_rushton(x, config.r_max, config.c50, config.n))


class RateNeuron:
    """A population of rate neurons (see :class:`RateNeuronConfig`)."""

    records = ("x", "r")

    def __init__(self, config: RateNeuronConfig | None = None):
        self.config = config or RateNeuronConfig()

    def init_state(self, trials: int, neurons: int, *, device=None,
                   dtype: torch.dtype | None = None, x0: float = 0.0) -> RateState:
        """Resting state (x = x0, default 0) of shape (trials, neurons)."""
        x = torch.full((trials, neurons), float(x0), device=device,
                       dtype=dtype or torch.get_default_dtype())
        c = self.config
        return RateState(x, naka_rushton(x, c.r_max, c.c50, c.n))

    def step(self, state: RateState | None, drive, dt: float, *, generator=None) -> RateState:
        """Advance by ``dt`` (s) with ``drive`` (trials, neurons) held constant.
        ``state=None`` starts from rest with the drive's shape, device and dtype.
        ``generator`` is accepted for a uniform interface and unused (no noise)."""
        dt = _check_dt(dt)
        if state is None:
            drive = _as_float(drive)
            state = RateState(torch.zeros_like(drive), torch.zeros_like(drive))  # rest: x = 0, r = 0
        else:
            drive = _as_float(drive, state.x.dtype)
            _check_input(drive, state.x, "drive")
        return rate_step(state, drive, dt, self.config)

    def run(self, drive, dt: float, *, state: RateState | None = None,
            record: Sequence[str] = ("x", "r"), seed: int | None = None,
            return_state: bool = False):
        """Whole run. drive: (trials, time, neurons). Returns ``{name: (time, trials,
        neurons)}`` for ``record`` ⊆ {"x", "r"}; entry k is the state at (k+1)·dt.
        ``seed`` is accepted for a uniform interface and unused. With
        ``return_state=True`` returns ``(records, final_state)`` to continue a stream."""
        dt = _check_dt(dt)
        drive = _check_run_input(drive, "drive")
        record = _record(record, self.records, "RateNeuron")
        if state is None:
            state = self.init_state(drive.shape[0], drive.shape[2], device=drive.device, dtype=drive.dtype)
        out, state = _run_loop(self.step, state, drive, dt, record, None)
        return (out, state) if return_state else out


# --------------------------------------------------------------------------- LIF neuron

_NOISE_KINDS = ("none", "white", "ou")


@dataclass(frozen=True)
class LIFConfig:
    """Leaky integrate-and-fire neuron driven by a current.

    ``tau_m dV/dt = -(V - V_rest) + R (I(t) + I_noise(t))``; a spike when V reaches
    V_threshold, then V is clamped at V_reset for t_ref.

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
        return self.noise != "none" and self.noise_std > 0

    @property
    def rheobase(self) -> float:
        """Smallest constant current (A) that makes the neuron fire."""
        return (self.V_threshold - self.V_rest) / self.R

    def to_dict(self) -> dict:
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


def lif_fi_curve(current, config: LIFConfig | None = None):
    """Analytic firing rate (Hz) of a noise-free LIF neuron under constant current (A).

    ``f = 1 / (t_ref + tau_m · ln((R I + V_rest - V_reset) / (R I - (V_th - V_rest))))``
    for ``R I > V_th - V_rest``, else 0. With V_reset = V_rest (the default) this is
    ``1 / (t_ref + tau_m · ln(R I / (R I - (V_th - V_rest))))``.
    Works on floats, numpy arrays and tensors (returns the same kind).
    """
    c = config or LIFConfig()
    if is_tensor(current):
        lib, I = torch, current
    else:
        import numpy as np
        lib, I = np, np.asarray(current, dtype=float)
    drive = c.R * I                                     # V_inf - V_rest (V)
    gap = drive - (c.V_threshold - c.V_rest)            # V_inf - V_th (V)
    fires = gap > 0
    # keep log's argument valid off the firing branch (where() evaluates both sides)
    num = lib.where(fires, drive + c.V_rest - c.V_reset, 2.0)
    isi = c.t_ref + c.tau_m * lib.log(num / lib.where(fires, gap, 1.0))
    f = lib.where(fires, 1.0 / isi, 0.0)
    return float(f) if f.ndim == 0 and not is_tensor(current) else f


def _white_sigma(c: LIFConfig) -> float:
    """σ (V) of Brunel's (2000) τ dV/dt = −V + μ + σ√τ ξ for this config's white noise (0 without)."""
    return c.R * c.noise_std if (c.noisy and c.noise == "white") else 0.0


def _siegert_nodes(current, c: LIFConfig, nodes: int):
    """Integration nodes u from y_r = (V_reset − μ)/σ to y_θ = (V_θ − μ)/σ, (m, nodes), for
    the flattened ``current``; and which entries can fire at all (y_θ < 26: beyond, ν < 1e-290)."""
    import numpy as np
    sigma = _white_sigma(c)
    mu = c.V_rest + c.R * np.ravel(np.asarray(current, dtype=float))
    y_r, y_th = (c.V_reset - mu) / sigma, (c.V_threshold - mu) / sigma
    # Dense near threshold, where the integrands vary on a scale of 1/(1 + 2|y_θ|) (they grow like
    # e^{u²}; far below it they decay like 1/|u| and 1/|u|³), sparse toward reset: half the nodes
    # evenly over the last 4 such scales, half cubically spaced over the rest.
    near = np.minimum(4.0 / (1.0 + 2.0 * np.abs(y_th)), y_th - y_r)
    s = np.linspace(0.0, 1.0, nodes // 2)
    far = (y_th - near)[:, None] - (y_th - near - y_r)[:, None] * (s ** 3)[::-1]
    x = np.concatenate([far[:, :-1], (y_th - near)[:, None] + near[:, None] * s], axis=1)
    ok = y_th < 26.0
    return np.where(ok[:, None], x, 0.0), ok


def _check_white(c: LIFConfig, what: str) -> None:
    if c.noisy and c.noise != "white":
        raise ValueError(f"{what} is the white-noise diffusion approximation; this LIFConfig has noise={c.noise!r}")


def lif_rate(current, config: LIFConfig | None = None, nodes: int = 600):
    """Stationary firing rate (Hz) of an LIF neuron under a constant ``current`` (A, float or
    array) plus its white noise — Siegert's first-passage formula (the diffusion approximation;
    Brunel 2000, J. Comput. Neurosci. 8:183, eq. 21):
    ``1/ν = t_ref + τ√π ∫_{y_r}^{y_θ} e^{u²}(1 + erf u) du`` with y = (V − μ)/σ, μ = V_rest + R·I
    and σ = R·noise_std (:class:`LIFConfig`'s white-noise convention). Without noise it is
    :func:`lif_fi_curve`; "ou" noise is not white and is refused. ``nodes``: trapezoid points.
    """
    import numpy as np
    from scipy.special import erfcx
    c = config or LIFConfig()
    _check_white(c, "lif_rate")
    I = np.asarray(current, dtype=float)
    if _white_sigma(c) == 0:
        return lif_fi_curve(I, c)
    x, ok = _siegert_nodes(I, c, nodes)
    # e^{u²}(1 + erf u) = erfcx(−u): stable for u < 0, where it decays like 1/(√π |u|).
    mass = np.trapezoid(erfcx(-x), x, axis=1)
    return np.where(ok, 1.0 / (c.t_ref + c.tau_m * np.sqrt(np.pi) * mass), 0.0).reshape(I.shape)


def lif_isi_cv(current, config: LIFConfig | None = None, nodes: int = 600):
    """Coefficient of variation of the interspike interval of an LIF neuron under a constant
    ``current`` (A, float or array) plus its white noise (Brunel 2000, Appendix A):
    ``CV² = 2π(ντ)² ∫_{y_r}^{y_θ} e^{x²} ∫_{−∞}^{x} e^{y²}(1 + erf y)² dy dx``, ν = :func:`lif_rate`.
    A renewal train's spike count over a long window has Fano factor CV². 0 without noise;
    1 where the neuron cannot fire. ``nodes``: trapezoid points of the outer integral.
    """
    import numpy as np
    from scipy.special import erfcx
    c = config or LIFConfig()
    _check_white(c, "lif_isi_cv")
    I = np.asarray(current, dtype=float)
    if _white_sigma(c) == 0:
        return np.where(lif_fi_curve(I, c) > 0, 0.0, 1.0)
    if I.size > 16:   # the inner integral holds (entries, nodes, 200) values: bound its memory
        flat = I.ravel()
        return np.concatenate([lif_isi_cv(flat[i:i + 16], c, nodes) for i in range(0, flat.size, 16)]).reshape(I.shape)
    x, ok = _siegert_nodes(I, c, nodes)
    # Everything is scaled by e^{−Y}, Y = max(y_θ, 0)² (the integrands grow like e^{u²} up to y_θ),
    # and e^{x²} is taken inside the inner integral, so nothing over- or underflows:
    # CV² = 2π·outer_s / (t_ref/τ·e^{−Y} + √π·mass_s)².
    Y = np.maximum(x[:, -1:], 0.0) ** 2
    mass_s = np.trapezoid(erfcx(-x) * np.exp(-Y), x, axis=1)
    # Inner integral ∫_{−∞}^{x} erfcx(−y)² e^{x²−y²} dy: for x < 0 it decays within ~1/(2|x|) below
    # x, for x > 0 like e^{−y²} below 0; start where the integrand is < 1e-20 of its peak.
    lo = np.where(x < 0, x - 24.0 / (1.0 + 2.0 * np.abs(x)), -7.0)
    yy = x[:, :, None] - (x - lo)[:, :, None] * (np.linspace(0.0, 1.0, 200) ** 3)[::-1]
    h = (erfcx(-yy) * np.exp(-Y[:, :, None])) ** 2 * np.exp(x[:, :, None] ** 2 - yy ** 2)
    outer_s = np.trapezoid(np.trapezoid(h, yy, axis=2), x, axis=1)
    den = c.t_ref / c.tau_m * np.exp(-Y[:, 0]) + np.sqrt(np.pi) * mass_s
    cv = np.sqrt(np.maximum(2 * np.pi * outer_s / den ** 2, 0.0))
    return np.where(ok, cv, 1.0).reshape(I.shape)


def lif_current_for_rate(rate, config: LIFConfig | None = None, points: int = 800):
    """The constant current (A) at which this LIF fires at ``rate`` (Hz, array) on average —
    the inverse of :func:`lif_rate` (noise included), by interpolation on its curve.

    Rates must lie in [ν(I = 0), 1/t_ref); ValueError otherwise. Without noise ν(0) = 0 and
    rate 0 maps to the rheobase (the edge of firing).
    """
    import numpy as np
    c = config or LIFConfig()
    r = np.asarray(rate, dtype=float)
    gap = c.V_threshold - c.V_rest
    # Drives from rest to far above threshold, denser near it where the curve bends.
    drive = np.concatenate([np.linspace(0.0, gap, points // 4),
                            gap * (1 + np.geomspace(1e-4, 200.0, points - points // 4))])
    nu = lif_rate(drive / c.R, c)
    nu = np.maximum.accumulate(nu)
    top = 1.0 / c.t_ref if c.t_ref > 0 else np.inf
    if np.any(~np.isfinite(r)) or np.any(r < nu[0] - 1e-9) or np.any(r >= min(top, nu[-1])):
        raise ValueError(f"rates must lie in [{nu[0]:.3g}, {min(top, nu[-1]):.3g}) Hz for this LIFConfig, "
                         f"got {np.nanmin(r):.3g}–{np.nanmax(r):.3g}")
    # The last drive of every flat stretch: rate 0 without noise maps to the rheobase.
    keep = np.append(np.diff(nu) > 0, True)
    return np.interp(r, nu[keep], drive[keep]) / c.R


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
    """One step of ``dt`` (s) of an LIF population with ``current`` (A) held constant.

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
    """A population of leaky integrate-and-fire neurons (see :class:`LIFConfig`)."""

    records = ("v", "refractory", "noise", "spikes", "spike_offset")

    def __init__(self, config: LIFConfig | None = None):
        self.config = config or LIFConfig()

    def init_state(self, trials: int, neurons: int, *, device=None,
                   dtype: torch.dtype | None = None, generator: torch.Generator | None = None,
                   v0: float | None = None) -> LIFState:
        """Resting state (V = V_rest unless ``v0``), not refractory. With OU noise and
        a generator, the noise current starts from its stationary distribution so a
        run has no noise transient."""
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
        ``state=None`` starts from rest with the current's shape, device and dtype."""
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


# --------------------------------------------------------------------------- Poisson

_POISSON_MODES = ("count", "bernoulli")


@dataclass(frozen=True)
class PoissonConfig:
    """Poisson spiking from a rate (Hz).

    mode "count": the number of spikes in a step is Poisson(rate·dt), exact for any dt
    (counts in any window are Poisson, Fano factor 1). mode "bernoulli": at most one
    spike per step, with the exact probability 1 - e^{-rate·dt} of at least one event
    (a binary raster; its Fano factor is e^{-rate·dt}, ≈ 1 when rate·dt ≪ 1).
    """

    mode: str = "count"

    def __post_init__(self):
        if self.mode not in _POISSON_MODES:
            raise ValueError(f"PoissonConfig.mode must be one of {_POISSON_MODES}, got {self.mode!r}")

    def to_dict(self) -> dict:
        return asdict(self)


class PoissonState(NamedTuple):
    """spikes: spikes in the last step (trials, neurons)."""

    spikes: Tensor


def poisson_spikes(rate: Tensor, dt: float, generator: torch.Generator, *, mode: str = "count") -> Tensor:
    """Spikes in one step of ``dt`` (s) from ``rate`` (Hz, any shape; negative rates are
    rectified to 0, as a firing rate cannot be negative). Returns the spike counts as a
    float tensor of the rate's shape, dtype and device; see :class:`PoissonConfig`."""
    if generator is None:
        raise ValueError("poisson_spikes needs generator=make_generator(seed, device)")
    lam = rate.clamp_min(0) * dt
    if mode == "count":
        return torch.poisson(lam, generator=generator)
    if mode == "bernoulli":
        p = -torch.expm1(-lam)
        return (torch.rand(lam.shape, generator=generator, device=lam.device, dtype=lam.dtype) < p).to(lam.dtype)
    raise ValueError(f"mode must be one of {_POISSON_MODES}, got {mode!r}")


class PoissonNeuron:
    """Poisson spike generators driven by a rate (Hz), e.g. a :class:`RateNeuron`'s r."""

    records = ("spikes",)

    def __init__(self, config: PoissonConfig | None = None):
        self.config = config or PoissonConfig()

    def init_state(self, trials: int, neurons: int, *, device=None,
                   dtype: torch.dtype | None = None) -> PoissonState:
        return PoissonState(torch.zeros((trials, neurons), device=device,
                                        dtype=dtype or torch.get_default_dtype()))

    def step(self, state: PoissonState | None, rate, dt: float, *,
             generator: torch.Generator | None = None) -> PoissonState:
        """Spikes for one step; the state carries no memory (Poisson), only the output."""
        dt = _check_dt(dt)
        rate = _as_float(rate) if state is None else _as_float(rate, state.spikes.dtype)
        if state is not None:
            _check_input(rate, state.spikes, "rate")
            rate = rate.expand_as(state.spikes)
        return PoissonState(poisson_spikes(rate, dt, generator, mode=self.config.mode))

    def run(self, rate, dt: float, *, seed: int = 0, state: PoissonState | None = None,
            record: Sequence[str] = ("spikes",), return_state: bool = False):
        """Whole run. rate: (trials, time, neurons) in Hz. Returns ``{"spikes": (time,
        trials, neurons)}``. Steps over time like the streaming API, so a run and the
        same steps with the same seed give identical spikes."""
        dt = _check_dt(dt)
        rate = _check_run_input(rate, "rate")
        record = _record(record, self.records, "PoissonNeuron")
        g = make_generator(seed, rate.device)
        if state is None:
            state = self.init_state(rate.shape[0], rate.shape[2], device=rate.device, dtype=rate.dtype)
        out, state = _run_loop(self.step, state, rate, dt, record, g)
        return (out, state) if return_state else out
