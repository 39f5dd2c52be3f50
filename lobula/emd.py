"""Hassenstein–Reichardt elementary motion detectors (EMDs) between lattice neighbours.

For a pair of ommatidia (A, B), B the neighbour of A along a lattice axis, the
opponent (full) correlator is

    R = LP_τ(A)·B − A·LP_τ(B),

with LP_τ the first-order low-pass ``τ dy/dt = x − y`` acting as the delay. Motion
from A toward B gives R > 0. For sine inputs of amplitude α_A, α_B at angular
frequency ω = 2π·TF, B lagging A by the phase Δϕ (a grating of wavelength λ drifting
from A to B over their separation Δφ: Δϕ = 2πΔφ/λ), the steady-state mean is

    R̄ = α_A·α_B · sin Δϕ · ωτ / (1 + (ωτ)²)          (continuous time)

— zero at ω = 0, peak α_Aα_B·sinΔϕ/2 at ωτ = 1, sign flipping with direction, not
proportional to speed (DESIGN.md). Mean luminance cancels in the opponent
subtraction; an acceptance function multiplies each amplitude by its contrast
transfer (:func:`lobula.lattice.acceptance_attenuation`), so R̄ carries it squared.

Discrete time
-------------
Frames arrive every ``dt`` seconds. Between two frames the input is taken as the
straight line joining them, and the low-pass is integrated *exactly* for that
piecewise-linear input (first-order-hold exponential integration,
``y_j = a·y_{j−1} + (1−a)·x_{j−1} + (1 − τ(1−a)/h)·(x_j − x_{j−1})`` over a sub-step h,
a = exp(−h/τ)). The correlator is evaluated at ``S`` sub-steps inside each frame
interval (ending at the frame) and the frame's output is their mean, so with a τ short
against dt the fast delay is still resolved and the product is not aliased. Because
every sub-step quantity is a fixed linear combination of (low-pass state at the start
of the interval, previous frame, current frame), the S-sub-step mean of the products
collapses exactly to three antisymmetric cross terms with precomputed coefficients
(:func:`emd_coefficients`): the cost per frame does not grow with S. S = 1 gives the
correlator at the frame instant; large S its mean over the frame interval.
:func:`emd_sine_response_discrete` is the exact steady-state prediction of this
discrete scheme, :func:`emd_sine_response` the continuous-time formula above.

Shapes: per frame (..., n) → (..., P); per sequence (..., T, n) → (..., T, P), with
P pairs given as index arrays (A, B) into the n ommatidia (see
:class:`lobula.lattice.Lattice`: ``pairs_a``, ``pairs_b``). Leading dims are trials;
device and dtype follow the input. Pairs are computed pair-major, ommatidium rows against
ommatidium rows: where a lattice numbered row by row gives runs of consecutive pairs
(:func:`pair_runs`) each run is two slices (no gather); Python loops run over time steps
and over those runs (one per lattice row and axis), never over pairs.
"""
from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._optional import torch
from .photoreceptor import _check_dt

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "EMDConfig", "EMDCoefficients", "EMDState", "EMDArray", "emd_coefficients",
    "emd_init", "emd_step", "emd_run", "pair_runs", "pair_difference", "emd_sine_response", "emd_sine_response_discrete",
]


@dataclass(frozen=True)
class EMDConfig:
    """Hassenstein–Reichardt correlator settings.

    tau_s: delay low-pass time constant (s). 35 ms puts the temporal-frequency optimum
        1/(2πτ) at 4.5 Hz, as in blowfly HS cells (Hausen 1982; Borst & Egelhaaf 1989,
        TINS 12:297); Drosophila models use 35–50 ms.
    substeps: correlator evaluations per frame interval, averaged into the frame's
        output; None picks min(256, max(4, ⌈16·dt/τ⌉)), i.e. ≥ 16 per τ.
    """

    tau_s: float = 0.035
    substeps: int | None = None

    def __post_init__(self):
        if not (self.tau_s > 0 and math.isfinite(self.tau_s)):
            raise ValueError(f"EMD tau_s must be a positive number of seconds, got {self.tau_s}")
        if self.substeps is not None and (not isinstance(self.substeps, (int, np.integer)) or self.substeps < 1):
            raise ValueError(f"EMD substeps must be a positive integer or None, got {self.substeps!r}")

    def substeps_for(self, dt: float) -> int:
        """Number of sub-steps used at frame interval ``dt`` (s)."""
        if self.substeps is not None:
            return int(self.substeps)
        return int(min(256, max(4, math.ceil(16.0 * dt / self.tau_s))))

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


class EMDCoefficients(NamedTuple):
    """Per-frame coefficients of the discrete correlator (all dimensionless).

    Low-pass state at the end of a frame: ``l' = decay·l + beta·x_prev + gamma·x``.
    Frame output: ``R = l_A·w_B − w_A·l_B + n_pc·(xp_A·x_B − x_A·xp_B)`` with
    ``w = n_lp·x_prev + n_lc·x`` and l the state at the start of the frame.
    """

    substeps: int
    decay: float
    beta: float
    gamma: float
    n_lp: float
    n_lc: float
    n_pc: float


class EMDState(NamedTuple):
    """Streaming state: low-pass outputs ``lp`` and last input frame ``x``, both (..., n) in the input's units."""

    lp: Tensor
    x: Tensor


@functools.lru_cache(maxsize=256)
def emd_coefficients(config: EMDConfig, dt: float) -> EMDCoefficients:
    """Exact per-frame coefficients of the sub-stepped correlator of ``config`` at frame interval ``dt`` (s).

    Tracks, over the S sub-steps, each low-pass value and interpolated input as a
    linear combination of s = (l, x_prev, x); the mean product lp_j[A]·x_j[B] is then
    s_Aᵀ M s_B and the opponent correlator s_Aᵀ (M − Mᵀ) s_B.
    """
    dt = _check_dt(dt)  # (cached: a stream asks for the same coefficients every frame)
    S = config.substeps_for(dt)
    h = dt / S
    a = math.exp(-h / config.tau_s)
    one_minus_a = -math.expm1(-h / config.tau_s)
    b1 = 1.0 - config.tau_s * one_minus_a / h  # weight of the input's slope (first-order hold)
    lp = np.array([1.0, 0.0, 0.0])
    M = np.zeros((3, 3))
    for j in range(1, S + 1):  # S scalar updates, once per configuration
        x_prev = np.array([0.0, 1.0 - (j - 1) / S, (j - 1) / S])
        x_j = np.array([0.0, 1.0 - j / S, j / S])
        lp = a * lp + one_minus_a * x_prev + b1 * (x_j - x_prev)
        M += np.outer(lp, x_j)
    N = (M - M.T) / S
    return EMDCoefficients(S, float(lp[0]), float(lp[1]), float(lp[2]),
                           float(N[0, 1]), float(N[0, 2]), float(N[1, 2]))


def _pair_index(pairs_a, pairs_b, n: int, device) -> Tensor:
    """Pair indices A then B concatenated, (2P,) long on ``device``, checked against n ommatidia."""
    A = torch.as_tensor(pairs_a, dtype=torch.long)
    B = torch.as_tensor(pairs_b, dtype=torch.long)
    if A.dim() != 1 or A.shape != B.shape:
        raise ValueError(f"pairs_a and pairs_b must be 1-D of equal length, got {tuple(A.shape)} and {tuple(B.shape)}")
    if len(A) and (int(torch.minimum(A.min(), B.min())) < 0 or int(torch.maximum(A.max(), B.max())) >= n):
        raise ValueError(f"pair indices must lie in [0, {n}) for {n} ommatidia")
    return torch.cat([A, B]).to(device)


# A run of pairs whose A and B ends are both consecutive ommatidia is read as two slices of
# the signal (views, no copy); a lattice's rows give long runs. Below this mean run length
# the per-run Python overhead outweighs the gather it saves and the pairs are gathered.
_MIN_MEAN_RUN = 8


def pair_runs(pairs_a, pairs_b) -> np.ndarray | None:
    """Runs of pairs (p0, a0, b0, L): pairs p0..p0+L−1 join ommatidia a0+i and b0+i, (K, 4) int, of the
    pairs ``pairs_a``, ``pairs_b`` ((P,) ommatidium indices).

    None when the mean run is shorter than 8 pairs (an irregular lattice: gather instead).
    A regular lattice numbered row by row has one run per row and axis.
    """
    A = np.asarray(pairs_a, dtype=np.int64).ravel()
    B = np.asarray(pairs_b, dtype=np.int64).ravel()
    if len(A) == 0:
        return None
    start = np.flatnonzero(np.r_[True, (np.diff(A) != 1) | (np.diff(B) != 1)])
    if len(A) < _MIN_MEAN_RUN * len(start):
        return None
    length = np.diff(np.r_[start, len(A)])
    return np.stack([start, A[start], B[start], length], axis=1)


def _runs_of(AB: Tensor) -> np.ndarray | None:
    P = AB.shape[0] // 2
    ab = AB.detach().cpu().numpy()
    return pair_runs(ab[:P], ab[P:])


def pair_difference(y: Tensor, AB: Tensor, runs: np.ndarray | None = None, out: Tensor | None = None) -> Tensor:
    """``y[B] − y[A]`` along dim 0 for every pair: y (n, ...) → (P, ...), ommatidium-major, in y's units.

    AB: the pair indices A then B concatenated, (2P,) long; out: a (P, ...) buffer to write into
    (None: a new one). runs: :func:`pair_runs` of the pairs (None: gather). Slices, not a gather, where the
    pairs run along the lattice's rows.
    """
    P = AB.shape[0] // 2
    if out is None:
        out = y.new_empty((P,) + tuple(y.shape[1:]))
    if runs is None:
        torch.sub(y.index_select(0, AB[P:]), y.index_select(0, AB[:P]), out=out)
        return out
    for p0, a0, b0, L in runs.tolist():  # one slice pair per lattice row and axis, not per pair
        torch.sub(y[b0:b0 + L], y[a0:a0 + L], out=out[p0:p0 + L])
    return out


def _as_signal(x) -> Tensor:
    x = torch.as_tensor(x)
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())


def emd_init(x0) -> EMDState:
    """State at rest for a constant input x0 (..., n) (any units): low-pass settled on x0."""
    x0 = _as_signal(x0)
    return EMDState(x0.clone(), x0.clone())


def _correlate(l0: Tensor, xp: Tensor, xc: Tensor, AB: Tensor, c: EMDCoefficients, runs: np.ndarray | None,
               out: Tensor) -> Tensor:
    """Frame outputs into ``out`` (P, ...) from start-of-frame low-pass l0, previous xp and
    current xc, each ommatidium-major (n, ...) (views allowed).

    AB: the pair indices A then B concatenated, (2P,); runs: their :func:`pair_runs` or None.
    Ommatidium-major so that both ends of a pair are whole rows: a slice of rows per run
    (no copy) or one row gather (several times faster than gathering along the last dim).
    """
    P = AB.shape[0] // 2
    w = xp * c.n_lp + xc * c.n_lc
    if runs is None:
        A, B = AB[:P], AB[P:]
        torch.mul(l0.index_select(0, A), w.index_select(0, B), out=out)
        out.addcmul_(w.index_select(0, A), l0.index_select(0, B), value=-1.0)
        if c.n_pc != 0.0:
            out.addcmul_(xp.index_select(0, A), xc.index_select(0, B), value=c.n_pc)
            out.addcmul_(xc.index_select(0, A), xp.index_select(0, B), value=-c.n_pc)
        return out
    for p0, a0, b0, L in runs.tolist():  # one run per lattice row and axis
        a, b, r = slice(a0, a0 + L), slice(b0, b0 + L), out[p0:p0 + L]
        torch.mul(l0[a], w[b], out=r)
        r.addcmul_(w[a], l0[b], value=-1.0)
        if c.n_pc != 0.0:
            r.addcmul_(xp[a], xc[b], value=c.n_pc)
            r.addcmul_(xc[a], xp[b], value=-c.n_pc)
    return out


def emd_run(config: EMDConfig, dt: float, x, pairs_a, pairs_b, state: EMDState | None = None,
            max_chunk: int = 4_000_000, pair_index: Tensor | None = None,
            runs: np.ndarray | None | str = "auto", out: Tensor | None = None) -> tuple[Tensor, EMDState]:
    """Correlator outputs for a whole sequence, the correlator of ``config``.

    x: (..., T, n) photoreceptor signals (any units u) sampled every ``dt`` seconds;
    pairs_a, pairs_b: (P,) indices into n. Returns (R (..., T, P) in u², state after
    the last frame). ``state`` continues a stream; None starts at rest on x[..., 0, :]
    (so the first output is 0). ``max_chunk`` bounds the elements of the per-piece
    work buffers (memory only; results do not depend on it). ``pair_index``: the checked
    concatenation (A, B) on x's device, to skip rebuilding it (as :class:`EMDArray`
    does); ``runs``: its :func:`pair_runs` ("auto": work them out; None: gather).

    R is computed pair-major and returned as a (..., T, P) view of its (P, T, M)
    storage, M = the leading dims' size (not contiguous): matrix products and
    :meth:`lobula.population.LCPopulation.pool_pairs` read it without a transposing copy;
    call ``.contiguous()`` where a layout matters. ``out``: a contiguous (P, T, M) buffer
    of x's dtype to write that storage into (a caller stepping in chunks reuses it and
    spares the allocator a fresh large block each chunk).
    """
    dt = _check_dt(dt)
    x = _as_signal(x)
    if x.dim() < 2:
        raise ValueError(f"EMD input must be (..., time, n), got shape {tuple(x.shape)}")
    c = emd_coefficients(config, dt)
    n = x.shape[-1]
    AB = pair_index if pair_index is not None else _pair_index(pairs_a, pairs_b, n, x.device)
    if isinstance(runs, str):
        if runs != "auto":
            raise ValueError(f"runs must be 'auto', None or pair_runs(...), got {runs!r}")
        runs = _runs_of(AB)
    P = AB.shape[0] // 2
    if state is None:
        state = emd_init(x[..., 0, :])
    lead, T = x.shape[:-2], x.shape[-2]
    M = math.prod(lead)
    if out is None:
        out = x.new_empty((P, T, M))
    elif out.shape != (P, T, M) or not out.is_contiguous() or out.dtype != x.dtype or out.device != x.device:
        raise ValueError(f"out must be a contiguous {(P, T, M)} {x.dtype} tensor on {x.device}, "
                         f"got {tuple(out.shape)} {out.dtype} on {out.device}")
    xv = x.reshape(M, T, n)
    x_last = state.x.to(device=x.device, dtype=x.dtype).expand(lead + (n,)).reshape(M, n)
    lp_last = state.lp.to(device=x.device, dtype=x.dtype).expand(lead + (n,)).reshape(M, n)
    # Time pieces bound the work buffers (memory only); where pairs are gathered, the
    # gathered copies (P per piece and signal) too.
    per_frame = n * M if runs is not None else max(n, 4 * P) * M
    step = max(1, min(T, max_chunk // max(1, per_frame)))
    for i in range(0, T, step):
        j = min(T, i + step)
        # Ommatidium-major (n, frames + 1, M) with the previous frame in front: x_prev and x
        # are two overlapping views of it, and a pair's ends are whole rows (slices per run).
        X = x.new_empty((n, j - i + 1, M))
        X[:, 0] = x_last.t()
        X[:, 1:] = xv[:, i:j].permute(2, 1, 0)
        # Low-pass at the end of each frame: l_t = decay·l_{t−1} + beta·x_{t−1} + gamma·x_t.
        drive = X[:, :-1] * c.beta + X[:, 1:] * c.gamma
        Lp = torch.empty_like(X)
        Lp[:, 0] = lp_last.t()
        for t in range(j - i):  # the recursion is sequential in time only
            torch.add(drive[:, t], Lp[:, t], alpha=c.decay, out=Lp[:, t + 1])
        _correlate(Lp[:, :-1], X[:, :-1], X[:, 1:], AB, c, runs, out[:, i:j])
        x_last, lp_last = X[:, -1].t(), Lp[:, -1].t()
    R = out.permute(1, 2, 0).reshape((T,) + lead + (P,)).movedim(0, -2)
    new = EMDState(lp_last.clone(memory_format=torch.contiguous_format).reshape(lead + (n,)),
                   x_last.clone(memory_format=torch.contiguous_format).reshape(lead + (n,)))
    return R, new


def emd_step(config: EMDConfig, dt: float, x, pairs_a, pairs_b, state: EMDState | None = None,
             pair_index: Tensor | None = None, runs: np.ndarray | None | str = "auto") -> tuple[Tensor, EMDState]:
    """One frame x (..., n) → (R (..., P), new state); the streaming form of :func:`emd_run`, whose
    parameters (``config``, ``dt`` s, ``pairs_a``, ``pairs_b``, ``pair_index``, ``runs``) and units it takes."""
    x = _as_signal(x)
    R, new = emd_run(config, dt, x.unsqueeze(-2), pairs_a, pairs_b, state, pair_index=pair_index, runs=runs)
    return R.squeeze(-2), new


def emd_sine_response(tau_s: float, temporal_freq_hz, phase_diff_rad, amplitude_a=1.0, amplitude_b=None):
    """Continuous-time steady-state mean of R for sine inputs (the textbook formula).

    ``α_A·α_B·sin(Δϕ)·ωτ/(1+(ωτ)²)``, ω = 2π·TF; Δϕ > 0 when B lags A (motion A → B).
    tau_s: τ (s); temporal_freq_hz: TF (Hz); phase_diff_rad: Δϕ (rad); amplitude_a, amplitude_b:
    α_A, α_B (None: α_A). Arrays broadcast; amplitudes in the input's units, result in their square.
    """
    amplitude_b = amplitude_a if amplitude_b is None else amplitude_b
    wt = 2.0 * np.pi * np.asarray(temporal_freq_hz, dtype=float) * tau_s
    return np.asarray(amplitude_a) * np.asarray(amplitude_b) * np.sin(phase_diff_rad) * wt / (1.0 + wt * wt)


def emd_sine_response_discrete(config: EMDConfig, dt: float, temporal_freq_hz, phase_diff_rad,
                               amplitude_a=1.0, amplitude_b=None):
    """Exact steady-state mean of this implementation's R for sampled sine inputs.

    Inputs ``x_A[k] = α_A·cos(ω k dt + φ)``, ``x_B[k] = α_B·cos(ω k dt + φ − Δϕ)``
    (plus any constant, which cancels). Exact for the time average over whole periods
    when 2·TF·dt is not an integer (otherwise the product's 2ω term aliases onto the
    mean and the result depends on the phase φ). Arrays broadcast. config: the correlator; dt:
    frame interval (s); temporal_freq_hz: TF = ω/2π (Hz); phase_diff_rad: Δϕ (rad); amplitude_a,
    amplitude_b: α_A, α_B in the input's units (None: α_A); the result is in their product's units.
    """
    dt = _check_dt(dt)
    c = emd_coefficients(config, dt)
    amplitude_b = amplitude_a if amplitude_b is None else amplitude_b
    z = np.exp(-2j * np.pi * np.asarray(temporal_freq_hz, dtype=float) * dt)  # one frame's delay
    g = (c.beta * z + c.gamma) / (1.0 - c.decay * z)  # end-of-frame low-pass phasor
    # phasors: l0 = g·z, x_prev = z, x = 1; mean(u_A v_B − v_A u_B) = −α_Aα_B sinΔϕ Im(u v̄)
    gain = -(c.n_lp * np.imag(g) + c.n_lc * np.imag(g * z) + c.n_pc * np.imag(z))
    return np.asarray(amplitude_a) * np.asarray(amplitude_b) * np.sin(phase_diff_rad) * gain


class EMDArray:
    """Streaming EMD array over fixed neighbour pairs: ``R = emds.step(frame)``.

    config: :class:`EMDConfig`; dt: frame interval (s); pairs_a, pairs_b: (P,) indices
    (e.g. ``lattice.pairs_a``, ``lattice.pairs_b``). ``run(seq)`` takes (..., T, n) and
    continues the stored state; ``reset()`` forgets it.
    """

    def __init__(self, pairs_a, pairs_b, config: EMDConfig | None = None, dt: float = 1.0 / 30.0):
        self.config = config or EMDConfig()
        self.dt = _check_dt(dt)
        self.pairs_a = torch.as_tensor(pairs_a, dtype=torch.long)
        self.pairs_b = torch.as_tensor(pairs_b, dtype=torch.long)
        self.state: EMDState | None = None
        self._pairs_cache: dict = {}

    @classmethod
    def from_lattice(cls, lattice, config: EMDConfig | None = None, dt: float | None = None) -> "EMDArray":
        """All neighbour pairs of a :class:`lobula.lattice.Lattice`, correlators of ``config``; dt (s) defaults
        to its camera's frame interval."""
        return cls(lattice.pairs_a, lattice.pairs_b, config,
                   lattice.camera.frame_interval_s if dt is None else dt)

    @property
    def coefficients(self) -> EMDCoefficients:
        """The per-frame coefficients at this array's dt (:func:`emd_coefficients`)."""
        return emd_coefficients(self.config, self.dt)

    def _pairs(self, device, n: int) -> tuple[Tensor, np.ndarray | None]:
        key = (torch.device(device), n)
        if key not in self._pairs_cache:
            self._pairs_cache[key] = (_pair_index(self.pairs_a, self.pairs_b, n, key[0]),
                                      pair_runs(self.pairs_a, self.pairs_b))
        return self._pairs_cache[key]

    def reset(self) -> None:
        """Forget the stored state."""
        self.state = None

    def step(self, x) -> Tensor:
        """One frame x (..., n) (units u) → R (..., P) (u²), continuing the stored state."""
        x = _as_signal(x)
        AB, runs = self._pairs(x.device, x.shape[-1])
        r, self.state = emd_step(self.config, self.dt, x, None, None, self.state, pair_index=AB, runs=runs)
        return r

    def run(self, x) -> Tensor:
        """A sequence x (..., T, n) (units u) → R (..., T, P) (u²), continuing the stored state."""
        x = _as_signal(x)
        AB, runs = self._pairs(x.device, x.shape[-1])
        r, self.state = emd_run(self.config, self.dt, x, None, None, self.state, pair_index=AB, runs=runs)
        return r
