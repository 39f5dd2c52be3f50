"""Lobula-plate tangential cells: HS and VS cells integrating T4/T5 with dendritic gain control.

HS cells (horizontal system) collect, on their dendrites in lobula-plate layer 1, the T4 and T5
cells tuned to front-to-back motion (excitatory, cholinergic) and, through inhibitory lobula-plate
interneurons from layer 2, those tuned to back-to-front motion (Mauss et al. 2015, Cell 162:351).
VS cells (vertical system) do the same with downward (layer 4, excitatory) and upward (layer 3,
inhibitory) motion. Each cell here pools over a receptive field on the lattice:

- HS: ``n_hs`` elevation bands of equal height spanning the lattice, dorsal to ventral (three:
  HSN, HSE, HSS);
- VS: ``n_vs`` azimuth stripes of equal width, in order of increasing azimuth (left to right in the
  image).

Membrane (one compartment, potentials in mV relative to rest, conductances in units of the leak
conductance g_leak):

    g_e(t) = g_exc · Σ_A w_A (T4 + T5)_pref[t, A] / Σ_A w_A
    g_i(t) = g_inh · Σ_A w_A (T4 + T5)_null[t, A] / Σ_A w_A
    τ_m dV/dt = −V − g_e (V − E_exc) − g_i (V − E_inh)

w the receptive field (1 inside, 0 outside), so each conductance grows with the number of columns
a pattern covers and equals g_exc (g_inh) times the drive when the whole field carries the same drive.
The steady state is the shunting (divisive) form

    V∞ = (E_exc·g_e + E_inh·g_i) / (1 + g_e + g_i),

which saturates as a pattern grows — at a level between the reversal potentials set by the ratio
g_e/g_i, so the sign still follows the direction of motion. This is the dendritic gain control of
Borst, Egelhaaf & Haag 1995 (J Comput Neurosci 2:5): it needs only the imperfect direction
selectivity of the inputs (the null direction still drives some excitation). The same imperfection
makes motion orthogonal to a cell's axis drive its excitatory and inhibitory layers alike (the
rectified channels' mean), which depolarises it since E_exc > −E_inh: with the defaults a vertical
grating that gives HS +27 mV front-to-back and −12 mV back-to-front gives it about +9 mV. Between frames the
conductances are held constant and V relaxes exactly: ``V ← V∞ + (V − V∞)·exp(−dt·(1 + g_e + g_i)/τ_m)``
(the effective time constant shortens as the conductances open).

Shapes: T4/T5 (..., T, n, 4) as :func:`lobula.motion_pathways.t4_t5` returns them; HS (..., T, n_hs),
VS (..., T, n_vs), mV. torch tensors, device and dtype of the input; the time loop is the only
Python loop, each step vectorised over trials and cells.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._optional import torch
from .motion_pathways import direction_index
from .photoreceptor import _check_dt, lowpass_scan

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["TangentialConfig", "HSVS", "Conductances", "tangential_fields", "conductances", "hs_vs",
           "shunting_potential"]


@dataclass(frozen=True)
class TangentialConfig:
    """Receptive fields and membrane of the HS and VS cells (mV relative to rest; seconds).

    n_hs: number of HS cells, elevation bands dorsal to ventral (3: HSN, HSE, HSS).
    n_vs: number of VS cells, azimuth stripes in order of increasing azimuth.
    tau_m_s: membrane time constant τ_m = C/g_leak. 4 ms: HS and VS cells' passive cut-off of
        40–80 Hz (Borst & Haag 1996, J Comput Neurosci 3:313).
    e_exc_mv, e_inh_mv: reversal potentials of the excitatory (T4/T5, cholinergic: a cation
        conductance near 0 mV) and inhibitory (lobula-plate interneurons, glutamate-gated chloride
        near −80 mV) synapses, relative to a rest near −50 mV: model values +50 and −30 mV.
    g_exc, g_inh: excitatory and inhibitory conductance, in units of g_leak, per unit of T4 + T5
        output (the photoreceptor signal's units u to the power −2) carried by the whole receptive
        field. 100 makes a contrast-0.5 grating at the correlators' optimum on a mean luminance of 1
        (or in contrast units) open g_e ≈ 2–3 across the whole field: well into saturation.
    channel_noise_mv: channel noise, a white Gaussian current on each membrane, stated as the standard
        deviation (mV) of the potential it gives at rest (g_e = g_i = 0); open conductances shunt it
        to σ/√(1 + g_e + g_i). 0 (default): no noise.
    adapt_tau_s: motion adaptation, a slow divisive gain on each cell's excitatory and inhibitory
        conductance driven by that conductance itself: ``g' = G·g``, ``G = LP_τa(1/(1 + g/g½))``
        (G = 1 unadapted, 1/2 after long drive at g = g½). Once the drive stops, 1 − G decays as
        exp(−t/τa) exactly (per frame, exp(−dt/τa)). None (default): off. 1–3 s: the recovery of
        blowfly HS/VS cells after prolonged motion (Harris et al. 2000, Nature 405:1073; Kurtz et al.
        2000, J Neurosci 20:5945).
    adapt_half_g: g½, the conductance (units of g_leak) that halves the gain at steady state.
    """

    n_hs: int = 3
    n_vs: int = 6
    tau_m_s: float = 0.004
    e_exc_mv: float = 50.0
    e_inh_mv: float = -30.0
    g_exc: float = 100.0
    g_inh: float = 100.0
    channel_noise_mv: float = 0.0
    adapt_tau_s: float | None = None
    adapt_half_g: float = 1.0

    def __post_init__(self):
        for name in ("n_hs", "n_vs"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not (self.tau_m_s > 0 and math.isfinite(self.tau_m_s)):
            raise ValueError(f"tau_m_s must be a positive number of seconds, got {self.tau_m_s}")
        if not (self.e_exc_mv > 0 > self.e_inh_mv):
            raise ValueError(f"need e_exc_mv > 0 > e_inh_mv (relative to rest), got {self.e_exc_mv}, {self.e_inh_mv}")
        for name in ("g_exc", "g_inh"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a non-negative number, got {v}")
        if not (self.channel_noise_mv >= 0 and math.isfinite(self.channel_noise_mv)):
            raise ValueError(f"channel_noise_mv must be a non-negative number of mV, got {self.channel_noise_mv}")
        if self.adapt_tau_s is not None and not (self.adapt_tau_s > 0 and math.isfinite(self.adapt_tau_s)):
            raise ValueError(f"adapt_tau_s must be a positive number of seconds or None (off), got {self.adapt_tau_s}")
        if not (self.adapt_half_g > 0 and math.isfinite(self.adapt_half_g)):
            raise ValueError(f"adapt_half_g must be a positive conductance (units of g_leak), got {self.adapt_half_g}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


class HSVS(NamedTuple):
    """Membrane potentials (mV relative to rest): hs (..., T, n_hs), vs (..., T, n_vs)."""

    hs: Tensor
    vs: Tensor


def _bands(values: np.ndarray, k: int) -> np.ndarray:
    """Membership (k, n) float64 of n values in k equal-width bands spanning their range."""
    lo, hi = float(values.min()), float(values.max())
    edges = np.linspace(lo, hi, k + 1)
    band = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, k - 1)  # the maximum joins the last band
    return (band[None, :] == np.arange(k)[:, None]).astype(float)


def tangential_fields(lattice, config: TangentialConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Receptive-field weights of the HS and VS cells on ``lattice``.

    Parameters
    ----------
    lattice : lobula.lattice.Lattice
        Its ``elevation`` and ``azimuth`` (n,), radians (elevation positive down).
    config : TangentialConfig, optional
        Numbers of cells (default :class:`TangentialConfig`).

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        HS weights (n_hs, n): equal elevation bands, row 0 the most dorsal (most negative
        elevation); VS weights (n_vs, n): equal azimuth stripes, row 0 the smallest azimuth. 1 inside
        a field, 0 outside; each ommatidium belongs to exactly one HS and one VS field.
    """
    cfg = config or TangentialConfig()
    return _bands(np.asarray(lattice.elevation, float), cfg.n_hs), _bands(np.asarray(lattice.azimuth, float), cfg.n_vs)


def shunting_potential(g_e, g_i, e_exc_mv: float, e_inh_mv: float):
    """Steady-state potential ``(E_exc·g_e + E_inh·g_i)/(1 + g_e + g_i)`` (mV relative to rest).

    g_e, g_i: excitatory and inhibitory conductances in units of g_leak (arrays or tensors, broadcast);
    e_exc_mv, e_inh_mv: reversal potentials (mV relative to rest).
    """
    return (e_exc_mv * g_e + e_inh_mv * g_i) / (1.0 + g_e + g_i)


def _integrate(g_e: Tensor, g_i: Tensor, cfg: TangentialConfig, dt: float, current_mv=None, noise=None) -> Tensor:
    """Exact relaxation of the one-compartment membrane under conductances held over each frame:
    g_e, g_i (..., T, c) → V (..., T, c) mV, starting at the first frame's steady state. current_mv:
    an injected current over the leak conductance, I/g_leak (mV, broadcast to (..., T, c); None: none).
    noise: standard normal draws (..., T, c) for the channel noise of ``cfg.channel_noise_mv`` (None or σ = 0:
    none). With noise the relaxation is the exact Ornstein–Uhlenbeck step under the held conductances,
    ``V ← V∞ + (V − V∞)·k + σ·√((1 − k²)/g_tot)·ξ`` with k = exp(−dt·g_tot/τ_m), g_tot = 1 + g_e + g_i,
    and the first frame draws from its stationary spread σ/√g_tot."""
    g_tot = 1.0 + g_e + g_i
    v_inf = (cfg.e_exc_mv * g_e + cfg.e_inh_mv * g_i) / g_tot
    if current_mv is not None:
        # τ_m dV/dt = −V − g_e(V − E_exc) − g_i(V − E_inh) + I/g_leak: the current adds I/g_leak to the
        # numerator of V∞, so at rest (g_e = g_i = 0) V∞ = I/g_leak.
        v_inf = v_inf + torch.as_tensor(current_mv, dtype=v_inf.dtype, device=v_inf.device) / g_tot
    keep = torch.exp(-dt * g_tot / cfg.tau_m_s)
    v_inf_t, keep_t = v_inf.movedim(-2, 0).contiguous(), keep.movedim(-2, 0).contiguous()
    v = torch.empty_like(v_inf_t)
    if noise is not None and cfg.channel_noise_mv > 0:
        xi = torch.as_tensor(noise, dtype=v_inf.dtype, device=v_inf.device).expand_as(v_inf)
        g_t = g_tot.expand_as(v_inf).movedim(-2, 0)
        kick = (cfg.channel_noise_mv * torch.sqrt((1.0 - keep_t * keep_t) / g_t) * xi.movedim(-2, 0)).contiguous()
        prev = v_inf_t[0] + cfg.channel_noise_mv * torch.rsqrt(g_t[0]) * xi.movedim(-2, 0)[0]
        v[0] = prev
        for t in range(1, v.shape[0]):  # the recursion is sequential in time only
            prev = torch.lerp(v_inf_t[t], prev, keep_t[t], out=v[t]).add_(kick[t])
        return v.movedim(0, -2)
    prev = v_inf_t[0]
    for t in range(v.shape[0]):  # the recursion is sequential in time only
        prev = torch.lerp(v_inf_t[t], prev, keep_t[t], out=v[t])
    return v.movedim(0, -2)


class Conductances(NamedTuple):
    """Synaptic conductances (units of g_leak), after motion adaptation: HS (..., T, n_hs), VS (..., T, n_vs)."""

    hs_exc: Tensor
    hs_inh: Tensor
    vs_exc: Tensor
    vs_inh: Tensor


def _adapt(g: Tensor, cfg: TangentialConfig, dt: float) -> Tensor:
    """Motion adaptation of a conductance g (..., T, c): ``g·LP_τa(1/(1 + g/g½))`` (:class:`TangentialConfig`'s
    adapt_tau_s), the gain starting at the first frame's steady state; g unchanged when off."""
    if cfg.adapt_tau_s is None:
        return g
    gain = lowpass_scan(1.0 / (1.0 + g / cfg.adapt_half_g), math.exp(-dt / cfg.adapt_tau_s))
    return g * gain


def conductances(t4, t5, lattice, config: TangentialConfig | None = None, dt: float | None = None) -> Conductances:
    """The excitatory and inhibitory conductances of every HS and VS cell from the T4 and T5 layers.

    Parameters
    ----------
    t4, t5 : Tensor, (..., T, n, 4)
        Half-correlator outputs (:func:`lobula.motion_pathways.t4_t5`), units u².
    lattice : lobula.lattice.Lattice
        The lattice they were computed on (its receptive fields).
    config : TangentialConfig, optional
        Fields, synaptic gains and motion adaptation (default :class:`TangentialConfig`).
    dt : float, optional
        Frame interval (s); default the lattice camera's.

    Returns
    -------
    Conductances
        ``g_exc·`` (``g_inh·``) the mean over each field of the preferred (null) layers' T4 + T5
        (HS: front-to-back (back-to-front); VS: downward (upward)), each (..., T, cells) in units of
        g_leak, times the adaptation gain when ``config.adapt_tau_s`` is set.
    """
    cfg = config or TangentialConfig()
    dt = _check_dt(lattice.camera.frame_interval_s if dt is None else dt)
    t4 = torch.as_tensor(t4)
    t5 = torch.as_tensor(t5).to(t4.dtype)
    if t4.shape != t5.shape or t4.dim() < 3 or t4.shape[-1] != 4:
        raise ValueError(f"t4 and t5 must both be (..., T, n, 4), got {tuple(t4.shape)} and {tuple(t5.shape)}")
    if t4.shape[-2] != lattice.n:
        raise ValueError(f"the T4/T5 layers have {t4.shape[-2]} ommatidia, the lattice {lattice.n}")
    drive = t4 + t5                                                            # (..., T, n, 4)
    w_hs, w_vs = tangential_fields(lattice, cfg)
    # Each field's mean over all of its columns (unstimulated ones count as 0): g grows with pattern size.
    m_hs = torch.as_tensor(w_hs / w_hs.sum(1, keepdims=True), dtype=drive.dtype, device=drive.device)
    m_vs = torch.as_tensor(w_vs / w_vs.sum(1, keepdims=True), dtype=drive.dtype, device=drive.device)

    def pooled(name: str, m: Tensor) -> Tensor:
        return drive[..., direction_index(name)] @ m.t()                       # (..., T, cells)

    return Conductances(*(_adapt(g, cfg, dt) for g in (
        cfg.g_exc * pooled("front_to_back", m_hs), cfg.g_inh * pooled("back_to_front", m_hs),
        cfg.g_exc * pooled("downward", m_vs), cfg.g_inh * pooled("upward", m_vs))))


def hs_vs(t4, t5, lattice, config: TangentialConfig | None = None, dt: float | None = None, *,
          hs_current_mv=None, vs_current_mv=None, noise=None) -> HSVS:
    """HS and VS membrane potentials from the T4 and T5 layers.

    Parameters
    ----------
    t4, t5 : Tensor, (..., T, n, 4)
        Half-correlator outputs of :func:`lobula.motion_pathways.t4_t5` (last dim in
        :data:`lobula.motion_pathways.DIRECTIONS` order), ≥ 0, units u².
    lattice : lobula.lattice.Lattice
        The lattice they were computed on (its azimuth and elevation set the receptive fields).
    config : TangentialConfig, optional
        Receptive fields and membrane (default :class:`TangentialConfig`).
    dt : float, optional
        Frame interval (s); default the lattice camera's.
    hs_current_mv, vs_current_mv : Tensor or array, optional
        Current injected into each HS (VS) cell divided by its leak conductance, I/g_leak (mV; the
        potential it holds at rest), broadcast to (..., T, n_hs) ((..., T, n_vs)); held over each frame.
        The steady state becomes ``V∞ = (E_exc·g_e + E_inh·g_i + I/g_leak)/(1 + g_e + g_i)``. None: no
        current (the cells' own membrane).
    noise : (Tensor, Tensor), optional
        Standard normal draws (..., T, n_hs) and (..., T, n_vs) for the channel noise of
        ``config.channel_noise_mv`` (the caller seeds them, e.g. per trial); None: no noise.

    Returns
    -------
    HSVS
        ``hs`` (..., T, n_hs): excited by front-to-back, inhibited by back-to-front T4 + T5 over each
        elevation band; ``vs`` (..., T, n_vs): excited by downward, inhibited by upward over each
        azimuth stripe. mV relative to rest, positive = depolarised; the first frame starts at its
        own steady state.
    """
    cfg = config or TangentialConfig()
    dt = _check_dt(lattice.camera.frame_interval_s if dt is None else dt)
    g = conductances(t4, t5, lattice, cfg, dt)
    xi_hs, xi_vs = (None, None) if noise is None else noise
    hs = _integrate(g.hs_exc, g.hs_inh, cfg, dt, hs_current_mv, xi_hs)
    vs = _integrate(g.vs_exc, g.vs_inh, cfg, dt, vs_current_mv, xi_vs)
    return HSVS(hs, vs)
