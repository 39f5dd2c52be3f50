"""Poisson spiking from a rate: spike counts, or a binary raster, per step.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple, Sequence

from .._optional import torch
from .streaming import _as_float, _check_dt, _check_input, _check_run_input, _record, _run_loop, make_generator

if TYPE_CHECKING:
    from torch import Tensor


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
        """Every field as a dict."""
        return asdict(self)


class PoissonState(NamedTuple):
    """spikes: spikes in the last step (trials, neurons)."""

    spikes: Tensor


def poisson_spikes(rate: Tensor, dt: float, generator: torch.Generator, *, mode: str = "count") -> Tensor:
    """Spikes in one step of ``dt`` (s) from ``rate`` (Hz, any shape; negative rates are
    rectified to 0, as a firing rate cannot be negative). Returns the spike counts as a
    float tensor of the rate's shape, dtype and device; ``generator``: the torch generator drawn from;
    ``mode``: "count" or "bernoulli", see :class:`PoissonConfig`."""
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
    """Poisson spike generators driven by a rate (Hz), e.g. a :class:`RateNeuron`'s r; ``config``: the
    :class:`PoissonConfig` (None: the default)."""

    records = ("spikes",)

    def __init__(self, config: PoissonConfig | None = None):
        self.config = config or PoissonConfig()

    def init_state(self, trials: int, neurons: int, *, device=None,
                   dtype: torch.dtype | None = None) -> PoissonState:
        """No spikes, shape (trials, neurons), on ``device`` in ``dtype`` (None: torch's default)."""
        return PoissonState(torch.zeros((trials, neurons), device=device,
                                        dtype=dtype or torch.get_default_dtype()))

    def step(self, state: PoissonState | None, rate, dt: float, *,
             generator: torch.Generator | None = None) -> PoissonState:
        """Spikes (trials, neurons) for one step of ``dt`` (s) at ``rate`` (Hz, (trials, neurons) or
        broadcastable to the state), drawn with ``generator``; the state carries no memory (Poisson), only
        the output."""
        dt = _check_dt(dt)
        rate = _as_float(rate) if state is None else _as_float(rate, state.spikes.dtype)
        if state is not None:
            _check_input(rate, state.spikes, "rate")
            rate = rate.expand_as(state.spikes)
        return PoissonState(poisson_spikes(rate, dt, generator, mode=self.config.mode))

    def run(self, rate, dt: float, *, seed: int = 0, state: PoissonState | None = None,
            record: Sequence[str] = ("spikes",), return_state: bool = False):
        """Whole run. rate: (trials, time, neurons) in Hz, steps of ``dt`` (s). Returns ``{"spikes": (time,
        trials, neurons)}`` (``record``: only "spikes"). Steps over time like the streaming API, so a run and
        the same steps with the same seed give identical spikes. ``state`` continues a stream; with
        ``return_state=True`` returns ``(records, final_state)``."""
        dt = _check_dt(dt)
        rate = _check_run_input(rate, "rate")
        record = _record(record, self.records, "PoissonNeuron")
        g = make_generator(seed, rate.device)
        if state is None:
            state = self.init_state(rate.shape[0], rate.shape[2], device=rate.device, dtype=rate.dtype)
        out, state = _run_loop(self.step, state, rate, dt, record, g)
        return (out, state) if return_state else out
