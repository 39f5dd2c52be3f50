"""ON and OFF motion pathways into the lobula plate: lamina L1/L2 → T4/T5 half-correlators.

The fly splits each photoreceptor's signal into two channels before it computes motion
(Joesch et al. 2010, Nature 468:300; Eichner et al. 2011, Neuron 70:1155):

1. **Lamina** (:func:`lamina_on_off`): L1 and L2 high-pass the photoreceptor signal (first-order
   high-pass, x − LP_τhp(x)) and their targets keep one polarity each (half-wave rectification):

       ON  = max(HP_L1(x) − θ_on, 0)          brightening (L1 → Mi1/Tm3 → T4)
       OFF = max(−HP_L2(x) − θ_off, 0)        darkening   (L2 → Tm1/Tm2 → T5)

   θ (``offset_on`` / ``offset_off``) is a threshold in the signal's units: 0 is the plain half-wave
   rectifier, θ > 0 sharpens it, θ < 0 lets a tonic level −θ through at rest (the "DC
   component" of Eichner et al. 2011).
2. **Medulla/lobula** (:func:`t4_t5`): every column holds T4 cells (ON) and T5 cells (OFF) for four
   preferred directions, each a Hassenstein–Reichardt *half*-correlator of its own channel — the
   classical two-quadrant model (ON × ON for T4, OFF × OFF for T5; no ON × OFF terms):

       T_d[A] = LP_τ(c[A]) · c[B],    B = A's neighbour one step along the direction d,

   c the channel (ON for T4, OFF for T5) and LP_τ the first-order low-pass of the delay arm. A
   feature moving from A toward B reaches A first; the delayed arm holds it until it reaches B, so
   the product peaks for motion along d. Both arms are ≥ 0 (rectified), so every output is ≥ 0; the
   opponent subtraction happens downstream, in the lobula-plate tangential cells
   (:mod:`lobula.tangential_cells`).

Directions on the lattice
-------------------------
The four directions are named for the fly's body: front-to-back (progressive), back-to-front
(regressive), upward and downward. In the lattice plane of :class:`lobula.lattice.Lattice` (a
rightward, b downward, the camera's image axes) they are the unit vectors

    front-to-back = (+1, 0) for a right eye, (−1, 0) for a left one (azimuth grows away from the
    front on the right side of the head); back-to-front its opposite; downward (0, +1); upward (0, −1).

Each direction uses the lattice's axis directions (±ê_k, the neighbour steps) with the largest
cosine to it, every tied one averaged. On the hexagonal lattice (axes 0°, 60°, 120°, clockwise in
the image) front-to-back and back-to-front are exactly ±ê_0, and each vertical direction is served
by the two oblique axes 30° either side of it (downward: +ê_60° and +ê_120°, whose sum is vertical),
so T_down[A] is the mean of A's two half-correlators toward its lower-right and lower-left
neighbours. On the rectangular lattice all four are single axes. A column that lacks a neighbour
in a direction (the rim of the eye) outputs 0 there; one that has one of two oblique neighbours
uses that one. :func:`cardinal_neighbours` gives the tables.

Time
----
Every filter is the zero-order-hold first-order low-pass of :func:`lobula.photoreceptor.lowpass_scan`
(``y += (1 − exp(−dt/τ))·(x − y)``), started at the steady state of the first frame (the high-pass
starts at 0, so a sequence starts without a switch-on transient). The product is taken at the frame
instants only (no sub-steps, unlike :mod:`lobula.emd`), so the stimulus' temporal frequencies must
stay well below the frame rate's Nyquist limit (the product's 2·TF component aliases above
fps/4). The tuning holds at camera rates: on a 41-point TF grid (λ = 4Δφ, τ = 35 ms) the mean T4
response peaks at 4.0 Hz from 60 to 1000 frames/s and at 4.4 Hz at 30 frames/s (1/(2πτ) = 4.5 Hz).

Shapes: signals (..., T, n) — leading dims are trials, T frames, n ommatidia — in the photoreceptor
signal's units u; channels (..., T, n) in u; T4/T5 (..., T, n, 4) in u², the last dim ordered as
:data:`DIRECTIONS`. torch tensors; device and dtype follow the input. Only the recursive filters
loop over time in Python; every step is vectorised over trials and ommatidia.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._optional import torch
from .photoreceptor import _check_dt, lowpass_scan

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["DIRECTIONS", "OnOffConfig", "OnOff", "T4T5", "lamina_on_off", "contrast_gain", "cardinal_neighbours",
           "t4_t5", "direction_index"]

#: the four preferred directions of T4/T5, in the order of their output's last dim
DIRECTIONS = ("front_to_back", "back_to_front", "upward", "downward")


@dataclass(frozen=True)
class OnOffConfig:
    """Parameters of the lamina ON/OFF split and of the T4/T5 correlators (seconds; signal units u).

    tau_hp_on_s, tau_hp_off_s: high-pass time constants of L1 (ON) and L2 (OFF). 0.25 s, as in the
        two-quadrant model of Eichner et al. 2011 (Neuron 70:1155).
    offset_on, offset_off: rectification thresholds θ (units u of the photoreceptor signal):
        ON = max(HP − θ_on, 0), OFF = max(−HP − θ_off, 0). 0 is the plain half-wave rectifier.
    tau_delay_t4_s, tau_delay_t5_s: delay low-pass τ of the T4 (ON) and T5 (OFF) correlators. 35 ms puts
        the temporal-frequency optimum 1/(2πτ) at 4.5 Hz, as :class:`lobula.emd.EMDConfig`.
    eye: "right" or "left": which side of the head the lattice looks from; it sets which image
        direction is front-to-back (rightward for a right eye).
    contrast_c50: semi-saturation contrast c₅₀ (Michelson, dimensionless) of the lamina's divisive
        contrast gain; None (default) switches the stage off. On, each channel carries the lamina's
        Weber contrast k = HP(x)/LP(x) (x a luminance > 0, LP the high-pass's own running mean)
        divided by √(σ² + c₅₀²), σ² = 2·LP_τc(k²) the running contrast energy (Michelson-calibrated:
        σ = C for a sinusoid of contrast C). A sinusoid of contrast C then leaves the lamina with
        amplitude C/√(C² + c₅₀²), and each T4/T5 half-correlator (a product of two such channels) answers
        ∝ C²/(C² + c₅₀²): a Naka–Rushton function with exponent 2 and semi-saturation c₅₀, C the
        contrast reaching the lamina. The channels are then in normalised contrast units (≤ 1 at
        steady state) and θ with them.
    contrast_tau_s: time constant τc (s) of the running contrast energy σ² (used only with
        contrast_c50). 0.2 s: slow beside the correlators' 35 ms delay, so σ² ripples little at
        the TF optimum, and within the ~0.1–0.5 s of contrast adaptation in fly LMCs.
    """

    tau_hp_on_s: float = 0.25
    tau_hp_off_s: float = 0.25
    offset_on: float = 0.0
    offset_off: float = 0.0
    tau_delay_t4_s: float = 0.035
    tau_delay_t5_s: float = 0.035
    eye: str = "right"
    contrast_c50: float | None = None
    contrast_tau_s: float = 0.2

    def __post_init__(self):
        for name in ("tau_hp_on_s", "tau_hp_off_s", "tau_delay_t4_s", "tau_delay_t5_s"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number of seconds, got {v}")
        for name in ("offset_on", "offset_off"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number, got {getattr(self, name)}")
        if self.eye not in ("right", "left"):
            raise ValueError(f"eye must be 'right' or 'left', got {self.eye!r}")
        if self.contrast_c50 is not None and not (self.contrast_c50 > 0 and math.isfinite(self.contrast_c50)):
            raise ValueError(f"contrast_c50 must be a positive contrast or None (off), got {self.contrast_c50}")
        if not (self.contrast_tau_s > 0 and math.isfinite(self.contrast_tau_s)):
            raise ValueError(f"contrast_tau_s must be a positive number of seconds, got {self.contrast_tau_s}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


class OnOff(NamedTuple):
    """The lamina's two channels, each (..., T, n) ≥ 0 in the photoreceptor signal's units."""

    on: Tensor
    off: Tensor


class T4T5(NamedTuple):
    """Half-correlator outputs (..., T, n, 4) ≥ 0 in the channels' units squared; last dim as :data:`DIRECTIONS`."""

    t4: Tensor
    t5: Tensor


def _as_signal(x, name: str) -> Tensor:
    x = torch.as_tensor(x)
    x = x if x.is_floating_point() else x.to(torch.get_default_dtype())
    if x.dim() < 2:
        raise ValueError(f"{name} must be (..., time, n), got shape {tuple(x.shape)}")
    return x


def direction_index(name: str) -> int:
    """Position of the direction ``name`` (one of :data:`DIRECTIONS`) in the T4/T5 output's last dim."""
    try:
        return DIRECTIONS.index(name)
    except ValueError:
        raise ValueError(f"unknown direction {name!r}; use one of {DIRECTIONS}") from None


def lamina_on_off(photoreceptor_signal, dt: float, config: OnOffConfig | None = None) -> OnOff:
    """ON (L1) and OFF (L2) channels of a photoreceptor sequence.

    Parameters
    ----------
    photoreceptor_signal : Tensor or array, (..., T, n)
        Photoreceptor output (e.g. :func:`lobula.photoreceptor.photoreceptor_run`), any units u,
        sampled every ``dt``.
    dt : float
        Frame interval (s).
    config : OnOffConfig, optional
        High-pass time constants and rectification thresholds (default :class:`OnOffConfig`).

    Returns
    -------
    OnOff
        ``on = max(x − LP_τon(x) − θ_on, 0)`` and ``off = max(LP_τoff(x) − x − θ_off, 0)``, each
        (..., T, n) in u, ≥ 0. The low-passes start at x[..., 0, :] (no switch-on transient).
        With ``config.contrast_c50`` set, the high-passed signal first passes :func:`contrast_gain`
        (x must then be a luminance > 0) and the channels are in normalised contrast units.
    """
    cfg = config or OnOffConfig()
    dt = _check_dt(dt)
    x = _as_signal(photoreceptor_signal, "photoreceptor_signal")
    mean_on = lowpass_scan(x, math.exp(-dt / cfg.tau_hp_on_s))
    hp_on = x - mean_on
    if cfg.tau_hp_off_s == cfg.tau_hp_on_s:
        hp_off = hp_on
        if cfg.contrast_c50 is not None:
            hp_on = hp_off = contrast_gain(hp_on, mean_on, dt, cfg)
    else:
        mean_off = lowpass_scan(x, math.exp(-dt / cfg.tau_hp_off_s))
        hp_off = x - mean_off
        if cfg.contrast_c50 is not None:
            hp_on, hp_off = contrast_gain(hp_on, mean_on, dt, cfg), contrast_gain(hp_off, mean_off, dt, cfg)
    on = torch.clamp(hp_on - cfg.offset_on, min=0.0)
    off = torch.clamp(-hp_off - cfg.offset_off, min=0.0)
    return OnOff(on, off)


def contrast_gain(hp: Tensor, mean: Tensor, dt: float, config: OnOffConfig) -> Tensor:
    """The lamina's divisive contrast gain: Weber contrast over the running contrast energy plus c₅₀².

    Parameters
    ----------
    hp : Tensor, (..., T, n)
        The high-passed signal x − LP_τhp(x), in the luminance units u of x.
    mean : Tensor, (..., T, n)
        LP_τhp(x), the running mean luminance (u, > 0).
    dt : float
        Frame interval (s).
    config : OnOffConfig
        ``contrast_c50`` (c₅₀, not None) and ``contrast_tau_s`` (τc).

    Returns
    -------
    Tensor, (..., T, n)
        ``k / √(σ² + c₅₀²)``, dimensionless, with k = hp/mean the Weber contrast and
        σ²[t] = LP_τc(2k²) (the low-pass starts at 2k[0]², 0 for a first frame at steady state). For a
        sinusoid of amplitude C in k, σ² → C², so the output's amplitude is C/√(C² + c₅₀²).

    Raises
    ------
    ValueError
        If the mean luminance is not positive anywhere: the stage needs x in luminance units.
    """
    if not bool((mean > 0).all()):
        raise ValueError("the lamina's contrast gain (contrast_c50) divides by the mean luminance, so it needs the "
                         "photoreceptor signal in luminance units (> 0); the rig's circuit output has its adapted "
                         "level removed: record it with `lobula ephys contrast`, `flicker` or `adaptation` "
                         "(experiments.ephys.contrast), which feed the lamina the photoreceptor's low-pass stage, "
                         "or set contrast_c50 None")
    k = hp / mean
    energy = lowpass_scan(2.0 * k * k, math.exp(-dt / config.contrast_tau_s))
    return k * torch.rsqrt(energy + config.contrast_c50 ** 2)


def _direction_vectors(eye: str) -> np.ndarray:
    """Unit vectors (4, 2) of :data:`DIRECTIONS` in the lattice plane (a right, b down)."""
    ftb = 1.0 if eye == "right" else -1.0
    return np.array([[ftb, 0.0], [-ftb, 0.0], [0.0, -1.0], [0.0, 1.0]])


def cardinal_neighbours(lattice, eye: str = "right") -> np.ndarray:
    """Neighbour table of the four T4/T5 directions: (4, n, m) int64, −1 where there is none.

    Parameters
    ----------
    lattice : lobula.lattice.Lattice
        Its ``axis_vectors`` (K, 2) and ``axis_pairs`` (K tuples (A, B): B = A + Δφ·ê_k) are used.
    eye : {"right", "left"}
        Which side of the head the lattice looks from (sets front-to-back; module docstring).

    Returns
    -------
    numpy.ndarray
        ``nbr[d, A, j]``: the j-th neighbour of ommatidium A one step along direction d
        (:data:`DIRECTIONS` order). m is the largest number of lattice steps tied nearest to a
        direction: 2 on a hexagonal lattice (the vertical directions use both oblique axes), 1 on a
        rectangular one.
    """
    if eye not in ("right", "left"):
        raise ValueError(f"eye must be 'right' or 'left', got {eye!r}")
    axes = np.asarray(lattice.axis_vectors, dtype=float)                       # (K, 2)
    steps = np.concatenate([axes, -axes])                                      # (2K, 2): +ê_k then −ê_k
    cos = _direction_vectors(eye) @ steps.T                                    # (4, 2K)
    # Lattice steps within 1e-6 of the best cosine count as tied (exact ties: 30° either side of vertical).
    chosen = cos >= cos.max(axis=1, keepdims=True) - 1e-6
    m = int(chosen.sum(axis=1).max())
    n = int(lattice.n)
    K = len(axes)
    nbr = np.full((4, n, m), -1, dtype=np.int64)
    for d in range(4):  # four directions × at most two steps: the table, not the ommatidia
        for j, s in enumerate(np.flatnonzero(chosen[d])):
            a, b = lattice.axis_pairs[s % K]
            if s < K:
                nbr[d, a, j] = b            # +ê_k: A's neighbour is B
            else:
                nbr[d, b, j] = a            # −ê_k: B's neighbour is A
    return nbr


def _half_correlators(c: Tensor, tau: float, dt: float, nbr: Tensor, count: Tensor) -> Tensor:
    """``LP_τ(c[A]) · mean_j c[nbr[d, A, j]]`` for every direction d: c (..., T, n) → (..., T, n, 4)."""
    delayed = lowpass_scan(c, math.exp(-dt / tau))
    # A zero column at index n stands in for a missing neighbour (−1), so the gather needs no mask.
    padded = torch.cat([c, c.new_zeros(c.shape[:-1] + (1,))], dim=-1)
    n = c.shape[-1]
    idx = torch.where(nbr < 0, torch.full_like(nbr, n), nbr)                  # (4, n, m)
    undelayed = padded.index_select(-1, idx.reshape(-1)).reshape(c.shape[:-1] + tuple(idx.shape))
    undelayed = undelayed.sum(-1).movedim(-2, -1) / count                       # (..., T, n, 4)
    return delayed.unsqueeze(-1) * undelayed


def t4_t5(on, off, lattice, config: OnOffConfig | None = None, dt: float | None = None) -> T4T5:
    """T4 (ON × ON) and T5 (OFF × OFF) half-correlators for the four cardinal directions.

    Parameters
    ----------
    on, off : Tensor or array, (..., T, n)
        The ON and OFF channels (:func:`lamina_on_off`), ≥ 0, units u.
    lattice : lobula.lattice.Lattice
        The ommatidial lattice the channels are sampled on (its n and neighbour pairs).
    config : OnOffConfig, optional
        Delay time constants of T4 and T5 and the eye's side (default :class:`OnOffConfig`).
    dt : float, optional
        Frame interval (s); default the lattice camera's (``lattice.camera.frame_interval_s``).

    Returns
    -------
    T4T5
        ``t4[..., t, A, d] = LP_τT4(on)[..., t, A] · on[..., t, B_d(A)]`` and ``t5`` likewise with the
        OFF channel and τ_T5, each (..., T, n, 4) ≥ 0 in u², d in :data:`DIRECTIONS` order, B_d(A)
        A's neighbour along d (the mean of the two oblique neighbours for the vertical directions
        of a hexagonal lattice; 0 at the rim where there is none: :func:`cardinal_neighbours`). The
        delay low-pass starts at the first frame's value.
    """
    cfg = config or OnOffConfig()
    dt = _check_dt(lattice.camera.frame_interval_s if dt is None else dt)
    on = _as_signal(on, "on")
    off = _as_signal(off, "off")
    if on.shape != off.shape:
        raise ValueError(f"on and off must have the same shape, got {tuple(on.shape)} and {tuple(off.shape)}")
    if on.shape[-1] != lattice.n:
        raise ValueError(f"the channels have {on.shape[-1]} ommatidia, the lattice {lattice.n}")
    table = cardinal_neighbours(lattice, cfg.eye)
    nbr = torch.as_tensor(table, device=on.device)
    # Neighbours present per (ommatidium, direction); 1 where none, so the mean of nothing is 0.
    count = torch.as_tensor(np.maximum((table >= 0).sum(-1), 1).T, dtype=on.dtype, device=on.device)  # (n, 4)
    t4 = _half_correlators(on, cfg.tau_delay_t4_s, dt, nbr, count)
    t5 = _half_correlators(off.to(on.dtype), cfg.tau_delay_t5_s, dt, nbr, count)
    return T4T5(t4, t5)
