"""Three-arm motion detectors: Hassenstein–Reichardt enhancement and Barlow–Levick suppression in one unit.

T4 (ON) and T5 (OFF) cells combine two mechanisms on three neighbouring columns (Haag, Arenz, Serbe,
Gabbiani & Borst 2016, eLife 5:e17421; Leong, Esch, Poole, Ganguli & Clandinin 2016, J Neurosci
36:8078): a delayed input on the preferred side *multiplies* the central input (HR enhancement of
preferred-direction motion), and a delayed input on the null side *shunts* it (Barlow–Levick
suppression of null-direction motion). Along a row of ommatidia A′, A, B, C (motion A → B the
preferred direction of the pair (A, B)) the half-detector for A → B, centred on B, is

    H_{A→B}^s = LP(A^s) · B^s / (1 + w · LP(C^s) / σ^s)

for each pathway s ∈ {ON, OFF}: x^ON = max(x, 0), x^OFF = max(−x, 0) of the photoreceptor signal x
(zero-mean in space after the LMCs' surround), LP the delay low-pass τ dy/dt = x − y (as
:mod:`lobula.emd`'s), w the suppression's weight and σ^s its half-saturation: fixed, or the pathway's
mean activity over all ommatidia, low-passed with ``tau_sigma_s`` (a contrast gain control, so that
the detector, like the HR correlator, scales as contrast²). The mirror half-detector H_{B→A} is centred
on A with B on its preferred side and A′ on its null side, and the pair's output is opponent, as the
HR correlator's:

    R = 2 · Σ_s (H_{A→B}^s − H_{B→A}^s).

With w = 0 it is the two-quadrant HR correlator (ON×ON + OFF×OFF, no mixed-sign products): for
jointly Gaussian inputs the two-quadrant correlation is half the full one to first order in the
inputs' correlation, so the factor 2 puts R on the HR correlator's scale. Where the lattice has no
ommatidium beyond B (or A′ beyond A), that half-detector has no null-side arm (no suppression).

The hypothesis it serves: an HR correlator's half-detector answers null-direction motion too, and the
opponent subtraction cancels that only on average; suppressing it at the source, as the fly's detectors
do (their direction selectivity is higher than a correlator's: Haag et al. 2016), could give the LC fields
a cleaner κ. Measured in the eye circuit (:class:`lobula.eye_circuit.EyeCircuitConfig` ``detector``),
decoded through the HR correlator's contrast pool, it reads worse than the correlator (docs/fly-eye.md,
"Could a fly do it?").

Discrete time
-------------
Inputs arrive every ``dt`` seconds. The low-passes are integrated exactly for the straight line
joining two samples (first-order hold, :func:`lobula.emd.emd_coefficients` with one sub-step; the
rectified input is treated the same way), σ's low-pass likewise, and the products are taken at the
sample instants, so a drifting grating's time-averaged output converges to the continuous-time
model's (``tests/test_three_arm.py`` checks it against a finely sampled integration).

Shapes: x (..., T, n) → R (..., T, P) for P pairs given as index arrays (A, B) and their null-side
neighbours (C beyond B, A′ beyond A; −1 where there is none: :func:`null_neighbours`). Leading dims
are trials; device and dtype follow the input; Python loops run over time only.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._optional import torch
from .emd import EMDConfig, emd_coefficients
from .photoreceptor import _check_dt

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["ThreeArmConfig", "ThreeArmState", "ThreeArmArray", "null_neighbours", "three_arm_run",
           "half_detector_run"]


@dataclass(frozen=True)
class ThreeArmConfig:
    """Three-arm detector settings (SI units).

    tau_s: the delay low-pass's time constant (s) on both outer arms; 35 ms, the HR correlator's.
    weight: w, the null-side arm's shunting weight (dimensionless); 1: a null-side input at its
        pathway's mean level halves the centre's drive; 0: the two-quadrant HR correlator.
    sigma: the suppression's half-saturation σ in the input's units, or None (default): each pathway's
        mean activity over all ommatidia, low-passed with ``tau_sigma_s``.
    tau_sigma_s: time constant (s) of that adaptive σ.
    """

    tau_s: float = 0.035
    weight: float = 1.0
    sigma: float | None = None
    tau_sigma_s: float = 1.0

    def __post_init__(self):
        if not (self.tau_s > 0 and math.isfinite(self.tau_s)):
            raise ValueError(f"three-arm tau_s must be a positive number of seconds, got {self.tau_s}")
        if not (self.weight >= 0 and math.isfinite(self.weight)):
            raise ValueError(f"three-arm weight must be a finite number >= 0, got {self.weight}")
        if self.sigma is not None and not (self.sigma > 0 and math.isfinite(self.sigma)):
            raise ValueError(f"three-arm sigma must be positive or None (adaptive), got {self.sigma}")
        if not (self.tau_sigma_s > 0 and math.isfinite(self.tau_sigma_s)):
            raise ValueError(f"three-arm tau_sigma_s must be a positive number of seconds, got {self.tau_sigma_s}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


class ThreeArmState(NamedTuple):
    """Streaming state: the arms' low-passes ``lp`` (..., 2, n) (ON, OFF), the last rectified input ``x``
    (..., 2, n), and the adaptive half-saturation's low-pass ``sigma`` (..., 2) and its last input ``s``
    (..., 2), all in the input's units."""

    lp: Tensor
    x: Tensor
    sigma: Tensor
    s: Tensor


def null_neighbours(directions: np.ndarray, pairs_a, pairs_b, max_angle_deg: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """The null-side neighbours of every pair: (C, A′), each (P,) int, −1 where there is none.

    directions: (n, 3) unit axes of the ommatidia; pairs_a, pairs_b: (P,) neighbour pairs. C is the
    neighbour of B (a member of a pair with B) that continues the step A → B most nearly straight,
    A′ the neighbour of A that continues B → A; a continuation more than ``max_angle_deg`` (deg) off
    the pair's direction (at a lattice edge) counts as none. Vectorised over pairs.
    """
    d = np.asarray(directions, dtype=float)
    A = np.asarray(pairs_a, dtype=np.int64)
    B = np.asarray(pairs_b, dtype=np.int64)
    n = len(d)
    # Neighbour table (n, K), −1 padded.
    ends = np.concatenate([np.stack([A, B], 1), np.stack([B, A], 1)])
    ends = ends[np.argsort(ends[:, 0], kind="stable")]
    counts = np.bincount(ends[:, 0], minlength=n)
    K = max(1, int(counts.max()) if len(counts) else 1)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(ends)) - start[ends[:, 0]]
    table = np.full((n, K), -1, dtype=np.int64)
    table[ends[:, 0], slot] = ends[:, 1]
    cos_max = math.cos(math.radians(max_angle_deg))

    def beyond(frm, to):
        # The neighbour of `to` whose step from `to` is most nearly parallel to the step frm → to.
        step = d[to] - d[frm]
        cand = table[to]                                            # (P, K)
        nxt = d[np.where(cand >= 0, cand, 0)] - d[to][:, None, :]   # (P, K, 3)
        # Tangent-plane directions at `to`.
        u = to_tangent(step, d[to])
        v = to_tangent(nxt, d[to][:, None, :])
        cos = np.einsum("pk,pjk->pj", u, v)
        cos = np.where(cand >= 0, cos, -np.inf)
        j = np.argmax(cos, axis=1)
        best = cand[np.arange(len(to)), j]
        return np.where(cos[np.arange(len(to)), j] >= cos_max, best, -1)

    def to_tangent(v, at):
        v = v - np.sum(v * at, axis=-1, keepdims=True) * at
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)

    if len(A) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return beyond(A, B), beyond(B, A)


def _rectify(x: Tensor) -> Tensor:
    """(..., T, n) → (..., T, 2, n): the ON (max(x, 0)) and OFF (max(−x, 0)) pathways."""
    return torch.stack([x.clamp(min=0.0), (-x).clamp(min=0.0)], dim=-2)


def three_arm_init(x0) -> ThreeArmState:
    """State at rest for a constant input x0 (..., n) (any units): every low-pass settled on it."""
    x0 = torch.as_tensor(x0)
    x0 = x0 if x0.is_floating_point() else x0.to(torch.get_default_dtype())
    r = _rectify(x0.unsqueeze(-2)).squeeze(-3)        # (..., 2, n)
    s = r.mean(-1)
    return ThreeArmState(r.clone(), r.clone(), s.clone(), s.clone())


def _foh_scan(x: Tensor, y0: Tensor, x_prev: Tensor, c) -> Tensor:
    """First-order-hold low-pass along dim 0 (time) of x (T, ...): y_t = decay·y_{t−1} + beta·x_{t−1} + gamma·x_t,
    with y_{−1} = y0 and x_{−1} = x_prev (both (...)); returns (T, ...) in x's units."""
    drive = torch.empty_like(x)
    drive[0] = x_prev * c.beta + x[0] * c.gamma
    if x.shape[0] > 1:
        torch.add(x[:-1] * c.beta, x[1:], alpha=c.gamma, out=drive[1:])
    y = torch.empty_like(x)
    prev = y0
    for t in range(x.shape[0]):  # the recursion is sequential in time only
        prev = torch.add(drive[t], prev, alpha=c.decay, out=y[t])
    return y


def _scan(config: ThreeArmConfig, dt: float, x: Tensor, state: ThreeArmState | None):
    """Rectified inputs (T, M, 2, n), their delay low-passes (same), σ (T, M, 2, 1) and the new state, from
    x (M, T, n)."""
    r = _rectify(x).movedim(1, 0)                               # (T, M, 2, n)
    if state is None:
        state = three_arm_init(x[:, 0])
    c = emd_coefficients(EMDConfig(tau_s=config.tau_s, substeps=1), dt)
    lp = _foh_scan(r, state.lp.to(r), state.x.to(r), c)
    s_in = r.mean(-1)                                           # (T, M, 2)
    if config.sigma is None:
        cs = emd_coefficients(EMDConfig(tau_s=config.tau_sigma_s, substeps=1), dt)
        sig = _foh_scan(s_in, state.sigma.to(r), state.s.to(r), cs)
    else:
        sig = torch.full_like(s_in, float(config.sigma))
    new = ThreeArmState(lp[-1].clone(), r[-1].clone(),
                        sig[-1].clone() if config.sigma is None else state.sigma.to(r),
                        s_in[-1].clone())
    return r, lp, sig.unsqueeze(-1), new


def _pad_index(idx, n: int, device) -> Tensor:
    """Indices (P,) with −1 (no such ommatidium) sent to n, the zero column appended to every signal."""
    i = torch.as_tensor(np.asarray(idx, dtype=np.int64))
    return torch.where(i < 0, torch.full_like(i, n), i).to(device)


def three_arm_run(config: ThreeArmConfig, dt: float, x, pairs_a, pairs_b, null_b, null_a,
                  state: ThreeArmState | None = None) -> tuple[Tensor, ThreeArmState]:
    """Opponent three-arm outputs for a whole sequence.

    x: (..., T, n) photoreceptor signals (any units u, zero-mean in space) sampled every ``dt`` s;
    pairs_a, pairs_b: (P,) indices into n; null_b: (P,) C, the neighbour beyond B (−1: none); null_a:
    (P,) A′, the neighbour beyond A (−1: none) (:func:`null_neighbours`). Returns (R (..., T, P) in u²,
    the state after the last sample); ``state`` continues a stream, None starts at rest on x[..., 0, :].
    """
    return _run(config, dt, x, pairs_a, pairs_b, null_b, null_a, state, opponent=True)


def half_detector_run(config: ThreeArmConfig, dt: float, x, pairs_a, pairs_b, null_b,
                      state: ThreeArmState | None = None) -> tuple[Tensor, ThreeArmState]:
    """The half-detector H_{A→B} = Σ_s LP(A^s)·B^s/(1 + w·LP(C^s)/σ^s) alone (one T4 and one T5 cell
    preferring A → B), (..., T, P) in u² (no factor 2); arguments as :func:`three_arm_run`."""
    return _run(config, dt, x, pairs_a, pairs_b, null_b, None, state, opponent=False)


def _run(config, dt, x, pairs_a, pairs_b, null_b, null_a, state, opponent: bool):
    """(output (..., T, P), new state): the opponent detector (``opponent``) or the half-detector alone."""
    dt = _check_dt(dt)
    x = torch.as_tensor(x)
    x = x if x.is_floating_point() else x.to(torch.get_default_dtype())
    if x.dim() < 2:
        raise ValueError(f"three-arm input must be (..., time, n), got shape {tuple(x.shape)}")
    lead, T, n = x.shape[:-2], x.shape[-2], x.shape[-1]
    M = math.prod(lead)
    A = _pad_index(pairs_a, n, x.device)
    B = _pad_index(pairs_b, n, x.device)
    C = _pad_index(null_b, n, x.device)
    if not (A.shape == B.shape == C.shape) or (len(A) and int(torch.maximum(A.max(), B.max())) >= n):
        raise ValueError(f"pairs_a, pairs_b, null_b must be (P,) indices into {n} ommatidia")
    st = None if state is None else ThreeArmState(*(s.reshape((M,) + tuple(s.shape[len(lead):])) for s in state))
    r, lp, sig, new = _scan(config, dt, x.reshape(M, T, n), st)
    zero = r.new_zeros(r.shape[:-1] + (1,))
    r, lp = torch.cat([r, zero], -1), torch.cat([lp, zero], -1)   # index n: no ommatidium, silent
    w = float(config.weight)
    inv = w / (sig + 1e-30 * (sig == 0))                         # (T, M, 2, 1)

    def half(a, b, c):
        num = lp.index_select(-1, a) * r.index_select(-1, b)
        return num if w == 0.0 else num / (1.0 + lp.index_select(-1, c) * inv)

    H = half(A, B, C).sum(-2)                                   # (T, M, P): ON + OFF
    if opponent:
        Ap = _pad_index(null_a, n, x.device)
        H = 2.0 * (H - half(B, A, Ap).sum(-2))
    out = H.movedim(0, 1).reshape(lead + (T, H.shape[-1]))
    new = ThreeArmState(*(s.reshape(lead + tuple(s.shape[1:])) for s in new))
    return out, new


class ThreeArmArray:
    """Streaming three-arm detectors over fixed neighbour pairs: ``R = arms.run(seq)``.

    pairs_a, pairs_b: (P,) indices; null_b, null_a: (P,) their null-side neighbours C and A′ (−1: none;
    :func:`null_neighbours`); config: :class:`ThreeArmConfig`; dt: sample interval (s). ``run(x)`` takes
    (..., T, n) and continues the stored state; ``reset()`` forgets it.
    """

    def __init__(self, pairs_a, pairs_b, null_b, null_a, config: ThreeArmConfig | None = None, dt: float = 0.002):
        self.config = config or ThreeArmConfig()
        self.dt = _check_dt(dt)
        self.pairs_a, self.pairs_b = np.asarray(pairs_a), np.asarray(pairs_b)
        self.null_b, self.null_a = np.asarray(null_b), np.asarray(null_a)
        self.state: ThreeArmState | None = None

    @classmethod
    def from_eye(cls, eye, config: ThreeArmConfig | None = None, dt: float = 0.002) -> "ThreeArmArray":
        """All neighbour pairs of a :class:`lobula.compound_eye.CompoundEye`, at sample interval dt (s)."""
        nb, na = null_neighbours(eye.directions, eye.pairs_a, eye.pairs_b)
        return cls(eye.pairs_a, eye.pairs_b, nb, na, config, dt)

    def reset(self) -> None:
        """Forget the stored state."""
        self.state = None

    def run(self, x) -> Tensor:
        """A sequence x (..., T, n) (units u) → R (..., T, P) (u²), continuing the stored state."""
        R, self.state = three_arm_run(self.config, self.dt, x, self.pairs_a, self.pairs_b, self.null_b,
                                      self.null_a, self.state)
        return R
