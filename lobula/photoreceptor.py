"""Photoreceptors (and LMC-like first-order interneurons) of the ommatidial lattice.

The chain, per ommatidium, each stage optional except the first:

1. **Phototransduction low-pass**: first-order low-pass of time constant ``tau_s``.
2. **Luminance (Weber) adaptation**: divide by the mean luminance, itself a low-pass
   of the signal with ``tau_adapt_s``; the output becomes dimensionless (1 at steady
   state), so the chain codes contrast rather than luminance.
3. **LMC-like high-pass**: subtract a low-pass of time constant ``tau_hp_s``, which
   removes the mean (steady state 0), as large monopolar cells do.
4. **Contrast gain control**: divide by the running RMS of the signal (a low-pass of its
   square with ``tau_gain_s``), so the output's amplitude does not scale with contrast.

Across columns, :func:`lattice_filter` gives the LMCs' lateral inhibition (x − the neighbours'
mean), which removes the mean in space instead of in time (:mod:`lobula.eye_circuit`, "Lateral
inhibition"), and the columnar-pooling hypothesis.

Every low-pass is the exact discrete-time solution of ``τ dy/dt = x − y`` for an input
held constant over each step (zero-order hold, as a frame-by-frame pipeline delivers
it, and as :mod:`lobula.neurons` assumes): ``y += (1 − exp(−dt/τ))·(x − y)``. Units:
seconds; the signal keeps the frames' luminance units until stage 2.

State is kept between calls, so frames can be streamed one by one or in chunks; the
first frame initialises every stage to its steady state for that frame, so a stream
starts without a switch-on transient. Tensors are ``(..., n)`` per frame and
``(..., time, n)`` per sequence (trials × time × ommatidia); device and dtype follow
the input. Only the time loop is in Python; each step is vectorised over all trials
and ommatidia.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._optional import torch

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "PhotoreceptorConfig", "PhotoreceptorState", "Photoreceptors",
    "photoreceptor_init", "photoreceptor_step", "photoreceptor_run",
    "photoreceptor_frequency_response", "lowpass_scan", "lattice_filter", "spatial_filter", "MEAN_REMOVAL",
    "mean_removal",
]


@dataclass(frozen=True)
class PhotoreceptorConfig:
    """Time constants (seconds) of the photoreceptor chain; None switches a stage off.

    tau_s: phototransduction low-pass. 10 ms: light-adapted Drosophila R1–6, corner
        frequency ≈ 16 Hz (Juusola & Hardie 2001, J Gen Physiol 117:3); blowfly ~2–3 ms.
        0 passes frames through unfiltered.
    tau_hp_s: LMC-like high-pass removing the mean; None = off. Motion-vision models
        use ≈ 0.25 s (e.g. Eichner et al. 2011, Neuron 70:1155).
    tau_adapt_s: luminance (Weber) adaptation; None = off. ~1 s.
    tau_gain_s: contrast gain control (divide by running RMS); None = off. ~0.5 s.
    eps: floor of the adaptation and gain denominators, in their units (luminance
        for adaptation, output units for gain control), so darkness does not divide by 0.
    """

    tau_s: float = 0.010
    tau_hp_s: float | None = None
    tau_adapt_s: float | None = None
    tau_gain_s: float | None = None
    eps: float = 1e-3

    def __post_init__(self):
        if not (self.tau_s >= 0 and math.isfinite(self.tau_s)):
            raise ValueError(f"tau_s must be a non-negative number of seconds, got {self.tau_s}")
        for name in ("tau_hp_s", "tau_adapt_s", "tau_gain_s"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number of seconds or None, got {v}")
        if not self.eps > 0:
            raise ValueError(f"eps must be positive, got {self.eps}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


class PhotoreceptorState(NamedTuple):
    """Low-pass states (each (..., n)); None for stages that are off: lp and adapt in the input's
    luminance units, hp in the output's units, gain in the output's units squared."""

    lp: Tensor
    adapt: Tensor | None
    hp: Tensor | None
    gain: Tensor | None


def _decay(tau: float | None, dt: float) -> float:
    """Per-step retention exp(−dt/τ) of a first-order low-pass (0 for τ = 0)."""
    if tau is None:
        return 0.0
    return math.exp(-dt / tau) if tau > 0 else 0.0


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"frame interval dt must be a positive number of seconds, got {dt}")
    return dt


def _as_signal(x) -> Tensor:
    x = torch.as_tensor(x)
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())


def lowpass_scan(x: Tensor, a: float, y0: Tensor | None = None) -> Tensor:
    """First-order low-pass along dim −2 (time) of x (..., T, n), zero-order hold.

    ``y[t] = a·y[t−1] + (1 − a)·x[t]`` with ``a = exp(−dt/τ)`` (dimensionless) and ``y[−1] = y0``
    ((..., n); default: x[0], the steady state of the first input). Returns y (..., T, n) in x's units.
    """
    if a == 0.0:
        return x.clone()
    # Time-major and contiguous, so each step is one fused lerp on a contiguous slice.
    xt = x.movedim(-2, 0).contiguous()
    yt = torch.empty_like(xt)
    prev = xt[0] if y0 is None else y0.to(device=xt.device, dtype=xt.dtype).expand_as(xt[0])
    b = 1.0 - a
    for t in range(xt.shape[0]):  # the recursion is sequential in time only
        prev = torch.lerp(prev, xt[t], b, out=yt[t])
    return yt.movedim(0, -2)


def photoreceptor_init(config: PhotoreceptorConfig, x0) -> PhotoreceptorState:
    """Steady state of every stage of ``config`` for a constant input x0 (..., n) (luminance, any units)."""
    x0 = _as_signal(x0)
    lp = x0.clone()
    adapt = lp.clone() if config.tau_adapt_s is not None else None
    y = lp / (adapt + config.eps) if adapt is not None else lp
    hp = y.clone() if config.tau_hp_s is not None else None
    z = y - hp if hp is not None else y
    gain = (z * z) if config.tau_gain_s is not None else None
    return PhotoreceptorState(lp, adapt, hp, gain)


def photoreceptor_run(config: PhotoreceptorConfig, dt: float, x, state: PhotoreceptorState | None = None
                      ) -> tuple[Tensor, PhotoreceptorState]:
    """Photoreceptor output of the chain ``config`` for a sequence x (..., T, n) (luminance, any units)
    sampled every ``dt`` seconds.

    Returns (output (..., T, n), state after the last frame); the output is in x's units when
    neither adaptation nor gain control is on, else dimensionless contrast. ``state`` continues a
    stream (None: start at the steady state of x[..., 0, :]).
    """
    dt = _check_dt(dt)
    x = _as_signal(x)
    if x.dim() < 2:
        raise ValueError(f"photoreceptor input must be (..., time, n), got shape {tuple(x.shape)}")
    if state is None:
        state = photoreceptor_init(config, x[..., 0, :])
    lp = lowpass_scan(x, _decay(config.tau_s, dt), state.lp)
    y = lp
    adapt = hp = gain = None
    if config.tau_adapt_s is not None:
        m = lowpass_scan(lp, _decay(config.tau_adapt_s, dt), state.adapt)
        adapt = m[..., -1, :].clone()
        y = lp / (m + config.eps)
    if config.tau_hp_s is not None:
        mean = lowpass_scan(y, _decay(config.tau_hp_s, dt), state.hp)
        hp = mean[..., -1, :].clone()
        y = y - mean
    if config.tau_gain_s is not None:
        power = lowpass_scan(y * y, _decay(config.tau_gain_s, dt), state.gain)
        gain = power[..., -1, :].clone()
        y = y / torch.sqrt(power + config.eps * config.eps)
    return y, PhotoreceptorState(lp[..., -1, :].clone(), adapt, hp, gain)


def photoreceptor_step(config: PhotoreceptorConfig, dt: float, x, state: PhotoreceptorState | None = None
                       ) -> tuple[Tensor, PhotoreceptorState]:
    """One frame x (..., n) → (output (..., n), new state), the frame interval ``dt`` s; the streaming form of
    :func:`photoreceptor_run` (``config``, units as there)."""
    x = _as_signal(x)
    y, state = photoreceptor_run(config, dt, x.unsqueeze(-2), state)
    return y.squeeze(-2), state


def photoreceptor_frequency_response(config: PhotoreceptorConfig, dt: float, freq_hz) -> np.ndarray:
    """Complex gain (dimensionless, ``freq_hz``'s shape) of the linear stages (low-pass, high-pass) of
    ``config`` at ``freq_hz`` (Hz) for frames every ``dt`` s.

    Exact for this discrete-time implementation: each low-pass is
    ``(1 − a)/(1 − a·e^{−iωdt})`` and the high-pass is 1 minus its low-pass. The
    nonlinear stages (adaptation, gain control) are not included.
    """
    dt = _check_dt(dt)
    zinv = np.exp(-2j * np.pi * np.asarray(freq_hz, dtype=float) * dt)

    def lp(tau):
        a = _decay(tau, dt)
        return (1 - a) / (1 - a * zinv)

    h = lp(config.tau_s)
    if config.tau_hp_s is not None:
        h = h * (1 - lp(config.tau_hp_s))
    return h


class Photoreceptors:
    """Streaming photoreceptor array: ``out = pr.step(frame)`` keeps its own state.

    config: :class:`PhotoreceptorConfig`; dt: frame interval (s). ``run(seq)`` takes a
    (..., T, n) sequence and also continues the stored state; ``reset()`` forgets it.
    """

    def __init__(self, config: PhotoreceptorConfig | None = None, dt: float = 1.0 / 30.0):
        self.config = config or PhotoreceptorConfig()
        self.dt = _check_dt(dt)
        self.state: PhotoreceptorState | None = None

    def reset(self) -> None:
        """Forget the stored state."""
        self.state = None

    def step(self, x) -> Tensor:
        """Output (..., n) for one frame x (..., n) (:func:`photoreceptor_step`)."""
        y, self.state = photoreceptor_step(self.config, self.dt, x, self.state)
        return y

    def run(self, x) -> Tensor:
        """Output (..., T, n) for a sequence x (..., T, n) (:func:`photoreceptor_run`)."""
        y, self.state = photoreceptor_run(self.config, self.dt, x, self.state)
        return y


def lattice_filter(lattice, column_pool: float = 0.0, surround: float = 0.0):
    """Sparse (n, n) float32 matrix (dimensionless weights) of the columns' spatial filtering before the EMDs;
    None if neither is on.

    lattice: anything with ``n`` ommatidia and neighbour pairs ``pairs_a``, ``pairs_b`` (a
    :class:`lobula.compound_eye.CompoundEye`, a pinhole :class:`lobula.lattice.Lattice`).

    x' = (I − s·N)·((1 − α)·I + α·N)·x, N the mean over each ommatidium's lattice neighbours
    (six inside an eye, fewer at its rim): first columnar pooling of weight α (``column_pool``),
    then lateral inhibition of weight s (``surround``). An ommatidium with no neighbour passes unchanged.
    """
    if column_pool == 0.0 and surround == 0.0:
        return None
    import scipy.sparse as sp

    n = int(lattice.n)
    a = np.concatenate([lattice.pairs_a, lattice.pairs_b])
    b = np.concatenate([lattice.pairs_b, lattice.pairs_a])
    deg = np.bincount(a, minlength=n).astype(float)
    N = sp.csr_matrix((1.0 / deg[a], (a, b)), shape=(n, n))
    lone = sp.diags((deg == 0).astype(float))      # no neighbour: its pooled value is its own
    I = sp.identity(n, format="csr")
    M = ((I - surround * N) @ ((1.0 - column_pool) * I + column_pool * (N + lone))).tocoo()
    idx = torch.as_tensor(np.stack([M.row, M.col]).astype(np.int64))
    return torch.sparse_coo_tensor(idx, torch.as_tensor(M.data, dtype=torch.float32), (n, n),
                                   check_invariants=True).coalesce()


def spatial_filter(M, y: Tensor) -> Tensor:
    """:func:`lattice_filter`'s matrix M (n, n) applied to every frame of y (..., n), in y's units and dtype;
    y unchanged when M is None."""
    if M is None:
        return y
    flat = y.reshape(-1, y.shape[-1])
    return torch.sparse.mm(M, flat.t().float()).t().to(y.dtype).reshape(y.shape)


#: the two ways the columns may remove the mean luminance before the EMDs (``--mean-removal``):
#: name → (lateral-inhibition weight for :func:`lattice_filter`, the LMC high-pass ``tau_hp_s``).
#: "space": the surround, no temporal high-pass; "time": a 0.25 s high-pass, no surround.
MEAN_REMOVAL = {"space": (1.0, None), "time": (0.0, 0.25)}


def mean_removal(name: str, photoreceptor: PhotoreceptorConfig) -> tuple[float, PhotoreceptorConfig]:
    """(surround weight, photoreceptor configuration) of the :data:`MEAN_REMOVAL` ``name`` ("space" or "time"),
    the rest of
    ``photoreceptor`` kept: what ``--mean-removal`` sets on either EMD front end."""
    surround, tau_hp = MEAN_REMOVAL[name]
    return surround, replace(photoreceptor, tau_hp_s=tau_hp)
