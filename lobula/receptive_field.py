"""Receptive fields of lobula-columnar units: matched filters for forward-motion (radial) flow.

Each field f is a weight map w_f over pixels (a box or Gaussian in visual angle). Its
matched filter projects the flow onto the radial template p − e (e: epipole) and pools
by weighted least squares, r̄_f = Σ w⟨ṗ, p−e⟩ / Σ w|p−e|², the best single expansion
rate for the field; this weights pixels near the epipole, where the per-pixel ratio
is 0/0, down to nothing. r²̄_f is the same-weighted mean of the per-pixel r², which
differs from r̄_f² when a field spans several depths (the paper's point). All fields
are pooled at once by one sparse matrix product.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import sparse

from .camera import PinholeCamera, angles_to_normalised, normalised_to_angles


@dataclass
class FieldConfig:
    """Receptive-field tiling (degrees at this user-facing edge).

    size_deg: side of each square field. spacing_deg: centre spacing (None = size, a
    tiling). margin_deg: keep fields this far inside the image. shape: "box" (the
    paper) or "gaussian" (σ = size/4, truncated at the box). gap_correction: replace
    the pair rate (d0/d1 − 1)/Δt by the exact mean rate ln(d0/d1)/Δt. pooling:
    "least-squares" (|p−e|²-weighted, robust at the epipole) or "pixel-mean" (the
    paper: the plain mean of per-pixel ratios ⟨ṗ,p−e⟩/|p−e|², which blows up there).
    """

    size_deg: float = 5.0
    spacing_deg: float | None = None
    margin_deg: float = 0.0
    shape: str = "box"
    pooling: str = "least-squares"
    gap_correction: bool = True

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ReceptiveFields:
    """A tiling of fields over a camera image.

    centres_deg: (F, 2) azimuth, elevation (degrees, elevation positive down);
    size_deg: field side; weights: scipy sparse CSR (F, H·W); x, y: normalised pixel coordinates (H, W).
    """

    camera: PinholeCamera
    centres_deg: np.ndarray
    size_deg: float
    weights: sparse.csr_matrix
    x: np.ndarray
    y: np.ndarray

    @property
    def n_fields(self) -> int:
        return len(self.centres_deg)


def tile_fields(camera: PinholeCamera, config: FieldConfig | None = None) -> ReceptiveFields:
    """Tile the camera's field of view with square fields in (azimuth, elevation)."""
    cfg = config or FieldConfig()
    x, y = camera.normalised_grid()
    az, el = (np.degrees(a) for a in normalised_to_angles(x, y))
    spacing = cfg.spacing_deg or cfg.size_deg
    half = cfg.size_deg / 2 + cfg.margin_deg

    def centres(lo, hi):
        n = int(np.floor((hi - lo - 2 * half) / spacing + 1e-9)) + 1
        if n < 1:
            raise ValueError(f"fields of {cfg.size_deg}° do not fit in a {hi - lo:.1f}° field of view")
        return (lo + hi) / 2 + (np.arange(n) - (n - 1) / 2) * spacing

    # The usable extent is the rectangle inscribed in the image in angle space.
    az_c = centres(max(az[:, 0].max(), -90), min(az[:, -1].min(), 90))
    el_c = centres(el[0, :].max(), el[-1, :].min())
    cen = np.array([(a, e) for e in el_c for a in az_c])
    if cfg.shape not in ("box", "gaussian"):
        raise ValueError(f"unknown field shape {cfg.shape!r}; use 'box' or 'gaussian'")
    # Built once per run: a loop over fields (not pixels) that visits only the columns
    # whose azimuth (a function of x alone) can fall inside each field.
    half_size = cfg.size_deg / 2
    az_col = az[0]
    rows, cols, vals = [], [], []
    for k, (ca, ce) in enumerate(cen):
        c0 = np.searchsorted(az_col, ca - half_size, side="left")
        c1 = np.searchsorted(az_col, ca + half_size, side="right")
        sub_az, sub_el = az[:, c0:c1], el[:, c0:c1]
        inside = (np.abs(sub_az - ca) <= half_size) & (np.abs(sub_el - ce) <= half_size)
        iy, ix = np.nonzero(inside)
        if cfg.shape == "box":
            w = np.ones(iy.size, np.float32)
        else:
            s = cfg.size_deg / 4
            w = np.exp(-0.5 * ((sub_az[iy, ix] - ca) ** 2 + (sub_el[iy, ix] - ce) ** 2) / s ** 2)
        rows.append(np.full(iy.size, k))
        cols.append(iy * camera.width + ix + c0)
        vals.append(w.astype(np.float32))
    weights = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(len(cen), camera.width * camera.height))
    return ReceptiveFields(camera, cen, cfg.size_deg, weights, x.astype(np.float32), y.astype(np.float32))


def pool_fields(flow: np.ndarray, fields: ReceptiveFields, epipole=(0.0, 0.0),
                valid: np.ndarray | None = None, pooling: str = "least-squares") -> tuple[np.ndarray, np.ndarray]:
    """Matched-filter pooling of one flow field (2, H, W) in 1/s about the epipole.

    Returns r̄ (F,) and r²̄ (F,) in 1/s and 1/s². ``valid`` (H, W) bool excludes pixels
    (e.g. where flow is unknown); non-finite flow is excluded automatically. All fields
    are pooled by one sparse product of the (F, H·W) weights with three per-pixel maps.
    """
    flow = np.asarray(flow, dtype=np.float32)
    dx = fields.x - np.float32(epipole[0])
    dy = fields.y - np.float32(epipole[1])
    num = flow[0] * dx + flow[1] * dy
    den = dx * dx + dy * dy
    ok = np.isfinite(num)
    if valid is not None:
        ok &= valid
    num = np.where(ok, num, 0.0)
    den = np.where(ok, den, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        if pooling == "least-squares":
            sq = np.where(den > 0, num * num / den, 0.0)
        elif pooling == "pixel-mean":
            # Per-pixel ratio r = num/den, averaged with unit weight: num -> r, den -> 1.
            r_pix = np.where(den > 0, num / den, 0.0)
            num, den, sq = r_pix, ok.astype(np.float32), r_pix * r_pix
        else:
            raise ValueError(f"unknown pooling {pooling!r}; use 'least-squares' or 'pixel-mean'")
        pooled = fields.weights @ np.stack([num.ravel(), den.ravel(), sq.ravel()], axis=1).astype(np.float64)
        r = pooled[:, 0] / pooled[:, 1]
        r2 = pooled[:, 2] / pooled[:, 1]
    return r, r2


def gap_correction(r_pair: np.ndarray, r2_pair: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Turn rates measured from a frame pair into exact mean rates over its interval.

    A point at depth d0 seen again at d1 moves radially by the factor d0/d1, so the pair
    gives r_pair = (d0/d1 − 1)/Δt, whereas the mean of r = v/d over the interval is
    ln(d0/d1)/Δt. r²̄ is rescaled by the same factor squared. Entries where the
    factor is not positive stay NaN.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        arg = 1.0 + r_pair * dt_s
        r = np.where(arg > 0, np.log(np.where(arg > 0, arg, 1.0)) / dt_s, np.nan)
        scale = np.where(np.abs(r_pair) > 1e-12, r / r_pair, 1.0)
    return r, r2_pair * scale ** 2
