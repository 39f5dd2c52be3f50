"""What the neuron models' streaming API shares: seeded generators, the checks of time steps and
inputs, and the loop over time steps that fills time-major records.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

from .._optional import torch

if TYPE_CHECKING:
    from torch import Tensor


def make_generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    """A ``torch.Generator`` seeded with the integer ``seed`` on ``device`` (it must live where the tensors live)."""
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
