"""Geometry of the LC stage on an ommatidial lattice: expansion templates, field centres and weights,
and the dendritic subunits pairs are pooled into.

One implementation of the matched-filter template serves both the LC population
(:mod:`lobula.population`) and the EMD front end's decoding weights
(:func:`lobula.emd_front_end.pair_pooling_weights`).

For a neighbour pair p (midpoint m_p, step Δp from A to B, unit direction u_p, all in
normalised image coordinates) and an epipole e, forward translation at expansion rate r
moves the image as ``ṗ = r·(p − e)``; along the pair that is ``r·t_p`` inter-ommatidial
steps per second with the **template** ``t_p = ⟨m_p − e, Δp⟩/|Δp|²`` (s per s⁻¹).
"""
from __future__ import annotations

import math

import numpy as np

from .camera import angles_to_normalised

__all__ = ["expansion_templates", "pair_templates", "field_centres", "field_weights", "pair_blocks"]


def expansion_templates(lattice, epipole_xy=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair expansion template t_p (P,) and radial alignment μ_p (P,) of the pairs of ``lattice`` (a
    :class:`lobula.lattice.Lattice` or a compound eye) for an epipole in normalised image coordinates
    ``epipole_xy`` (2,).

    t_p = ⟨m_p − e, Δp⟩/|Δp|² (steps per second per unit expansion rate);
    μ_p = ⟨u_p, (m_p − e)/|m_p − e|⟩ ∈ [−1, 1] (0 at the epipole itself).
    """
    e = np.asarray(epipole_xy, dtype=float).reshape(2)
    step = lattice.normalised[lattice.pairs_b] - lattice.normalised[lattice.pairs_a]
    rel = lattice.pair_midpoint - e[None, :]
    t = np.einsum("pk,pk->p", rel, step) / np.einsum("pk,pk->p", step, step)
    dist = np.linalg.norm(rel, axis=1)
    mu = np.where(dist > 1e-12, np.einsum("pk,pk->p", lattice.pair_direction, rel) / np.maximum(dist, 1e-12), 0.0)
    return t, mu


def pair_templates(lattice, epipole_deg=(0.0, 0.0), template: str = "direction") -> tuple[np.ndarray, np.ndarray]:
    """Per-pair matched-filter weight μ_p and expansion template t_p, both (P,), of the pairs of ``lattice``,
    the epipole ``epipole_deg`` in degrees (az, el).

    μ_p: the radial alignment ("direction": the local preferred direction of an
    expansion-tuned LPTC/LC dendrite, Krapp & Hengstenberg 1996) or t_p itself ("flow":
    the least-squares matched filter, Franz & Krapp 2000). μ_p·t_p ≥ 0 for both, so
    pooled gains are positive.
    """
    if template not in ("direction", "flow"):
        raise ValueError(f"template must be 'direction' or 'flow', got {template!r}")
    e = np.array(angles_to_normalised(*np.radians(np.asarray(epipole_deg, float))), dtype=float)
    t, mu = expansion_templates(lattice, e)
    return (t.copy(), t) if template == "flow" else (mu, t)


def field_centres(lattice, config) -> np.ndarray:
    """Field centres (F, 2) in degrees (az, el): ``config.centres_deg``, or a grid tiling the lattice's extent.

    config: a :class:`lobula.population.ReceptiveFieldConfig` (centres_deg, spacing_deg, size_deg, margin_deg).
    """
    if config.centres_deg is not None:
        return np.asarray(config.centres_deg, dtype=float)
    spacing = config.spacing_deg or config.size_deg
    half = config.size_deg / 2.0 + config.margin_deg

    def axis(lo, hi):
        k = int(np.floor((hi - lo - 2.0 * half) / spacing + 1e-9)) + 1
        if k < 1:
            raise ValueError(f"LC fields of {config.size_deg}° (margin {config.margin_deg}°) do not fit the eye's "
                             f"{hi - lo:.1f}° extent; use a smaller size_deg or give centres_deg")
        return (lo + hi) / 2.0 + (np.arange(k) - (k - 1) / 2.0) * spacing

    az, el = lattice.azimuth_deg, lattice.elevation_deg
    ga, ge = np.meshgrid(axis(az.min(), az.max()), axis(el.min(), el.max()), indexing="xy")
    return np.stack([ga.ravel(), ge.ravel()], axis=1)


def field_weights(az_deg: np.ndarray, el_deg: np.ndarray, centres_deg: np.ndarray, size_deg: float,
                  shape: str) -> np.ndarray:
    """Receptive-field weight (F, m) (dimensionless, peak 1) of each field, centres ``centres_deg`` (F, 2)
    (az, el) in degrees, at points ``az_deg``, ``el_deg`` (m,), degrees.

    shape "gaussian": FWHM ``size_deg``, cut at 1.5 FWHM; "box": a square of side ``size_deg``.
    """
    da = az_deg[None, :] - centres_deg[:, :1]
    de = el_deg[None, :] - centres_deg[:, 1:]
    if shape == "box":
        return ((np.abs(da) <= size_deg / 2.0) & (np.abs(de) <= size_deg / 2.0)).astype(float)
    if shape == "gaussian":
        q = (da * da + de * de) / (size_deg * size_deg)
        return np.where(q <= 1.5 ** 2, np.exp(-4.0 * math.log(2.0) * q), 0.0)
    raise ValueError(f"shape must be 'gaussian' or 'box', got {shape!r}")


def pair_blocks(lattice, block: int) -> np.ndarray:
    """Block id (P,) of each pair's A ommatidium on the lattice's integer grid cut into block×block squares:
    the dendritic subunit the pair's T4/T5 terminal converges on."""
    idx = lattice.index
    ij = idx - idx.min(axis=0)
    n_i = int(ij[:, 0].max()) + 1
    ib = -(-n_i // int(block))
    ia, ja = ij[lattice.pairs_a, 0], ij[lattice.pairs_a, 1]
    return (ja // block) * ib + (ia // block)
