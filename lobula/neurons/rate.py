"""The rate neuron: a leaky integrator with a Naka–Rushton output, integrated exactly over each step.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple, Sequence

from .._optional import torch
from .streaming import _as_float, _check_dt, _check_input, _check_run_input, _record, _run_loop

if TYPE_CHECKING:
    from torch import Tensor


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
        """Every field as a dict."""
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
    accurate when dt ≪ τ. drive: (trials, neurons) (dimensionless), or broadcastable to the state;
    config: the neuron. Returns the new state.
    """
    gain = -math.expm1(-dt / config.tau_m)
    x = torch.lerp(state.x, drive.expand_as(state.x), gain)    # x + gain·(u − x), one kernel
    return RateState(x, naka_rushton(x, config.r_max, config.c50, config.n))


class RateNeuron:
    """A population of rate neurons of ``config`` (see :class:`RateNeuronConfig`; None: the default)."""

    records = ("x", "r")

    def __init__(self, config: RateNeuronConfig | None = None):
        self.config = config or RateNeuronConfig()

    def init_state(self, trials: int, neurons: int, *, device=None,
                   dtype: torch.dtype | None = None, x0: float = 0.0) -> RateState:
        """Resting state (x = x0, default 0) of shape (trials, neurons), on ``device`` in ``dtype`` (None:
        torch's default)."""
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
        """Whole run. drive: (trials, time, neurons), dimensionless, steps of ``dt`` (s).
        Returns ``{name: (time, trials, neurons)}`` for ``record`` ⊆ {"x", "r"}; entry k is the state at (k+1)·dt.
        ``seed`` is accepted for a uniform interface and unused. With
        ``return_state=True`` returns ``(records, final_state)`` to continue a stream."""
        dt = _check_dt(dt)
        drive = _check_run_input(drive, "drive")
        record = _record(record, self.records, "RateNeuron")
        if state is None:
            state = self.init_state(drive.shape[0], drive.shape[2], device=drive.device, dtype=drive.dtype)
        out, state = _run_loop(self.step, state, drive, dt, record, None)
        return (out, state) if return_state else out
