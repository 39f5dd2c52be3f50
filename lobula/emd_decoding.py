"""The biological front end: photoreceptor lattice → EMD array → receptive-field expansion rates.

The EMD's output is not proportional to image speed (DESIGN.md): for a pair (A, B)
a distance s apart (normalised image units) seeing a pattern move at speed w along
A→B, the mean opponent response is, for a sine of wavelength λ (phase step
Δϕ = 2πs/λ) at temporal frequency ω = 2πw/λ,

    R̄ = C²·sinΔϕ·ωτ/(1 + (ωτ)²),       while  Ḡ = mean (B − A)² = C²·(1 − cosΔϕ).

Their ratio R̄/Ḡ = ωτ·cot(Δϕ/2)/(1 + (ωτ)²) → 2τ·w/s when ωτ ≪ 1 and Δϕ ≪ 1: the
contrast C² and the pattern cancel. This is the **gradient-ratio** decoding: a
divisive (contrast-normalising) pool G = (B − A)², the squared local contrast
difference that every EMD pair already has at its inputs. Pooled over a receptive
field with the matched filter m_j = ⟨p_j − e, u_j⟩ (the radial template at pair j
projected on the pair's direction u_j), weighted least squares of
R_j ≈ (2τ/s_j)·G_j·r·m_j (noise variance ∝ G_j) gives

    r̄_f = Σ_j c_j R_j m_j / Σ_j c_j² G_j m_j²,   c_j = 2τ/s_j,

i.e. an LC unit summing motion signals along its expansion template, divided by a
pooled contrast signal. What it assumes and where it fails:

* **ωτ ≪ 1.** Faster image motion is underestimated by 1/(1 + (ωτ)²) (the EMD's
  temporal-frequency tuning); the bias grows with image speed, short wavelengths and τ.
  A short τ widens the linear range; a ``calibration`` gain fitted on one synthetic
  scene with known r (:func:`fit_calibration`) corrects the mean bias for similar
  spectra and is held fixed afterwards.
* **Δϕ ≪ 1**, i.e. the lattice resolves the texture; aliasing (λ < 2s) reverses sign.
* Brightness constancy and rigid motion; r²̄_f is taken as r̄_f² (one depth per field),
  because single pairs are too noisy to square.
* The epipole is the principal point unless given.
"""
from __future__ import annotations

import time as _time
from dataclasses import asdict, dataclass, field
from typing import Iterable, Iterator

import numpy as np
import torch
from scipy import sparse

from .camera import PinholeCamera, normalised_to_angles
from .emd import EMDArray, EMDConfig
from .lattice import Lattice, LatticeConfig
from .lc_geometry import expansion_templates
from .photoreceptor import PhotoreceptorConfig, Photoreceptors, lattice_filter, spatial_filter
from .receptive_field import ReceptiveFields


@dataclass
class EMDFrontEndConfig:
    """The EMD front end for velocity estimation.

    lattice: ommatidia (default Δφ = 0.75°, Δρ = Δφ: a ~5,000-ommatidia eye on the
    D435i's field of view, enough for 5° fields; the fly's 4.6° needs ≥ 20° fields).
    photoreceptor: low-pass 10 ms (no temporal high-pass: the surround removes the mean).
    surround: weight s of the LMCs' lateral inhibition, x − s·(the lattice neighbours' mean),
    after the photoreceptors (:func:`lobula.photoreceptor.lattice_filter`): 1 (default) removes
    the mean luminance in space, with no memory, as the compound eye's circuit does; 0 with
    ``tau_hp_s=0.25`` is the front end until the twenty-seventh session, whose temporal high-pass
    drifts the decoded gain after every change of speed (its memory is a trailing copy of the
    pattern moving at the past speed). Measured on development suite worlds (10 s, 320×240,
    realistic IMU, causal; seeds 100, 101), high-pass → surround: panels 0.081 / 0.070 → 0.044 /
    0.035, corridor 0.090 / 0.084 → 0.011 / 0.014 m/s.
    emd: delay τ (s); 10 ms keeps the replay's image motion in the EMD's near-linear range.
    decoding: "gradient-ratio". calibration: gain on r̄, one number or one per field
    (1 = none; fitted on another scene by :func:`fit_calibration`, then held fixed).
    latency_s: how far the decoded r̄ trails the image motion; outputs are stamped that
    much earlier. None: the low-frequency group delay of the photoreceptor and EMD
    low-passes plus half a frame (the correlator averages over the frame interval).
    chunk: frames processed per batch.
    """

    lattice: LatticeConfig = field(default_factory=lambda: LatticeConfig(dphi_deg=0.75))
    photoreceptor: PhotoreceptorConfig = field(default_factory=lambda: PhotoreceptorConfig(tau_s=0.010))
    emd: EMDConfig = field(default_factory=lambda: EMDConfig(tau_s=0.010))
    surround: float = 1.0
    decoding: str = "gradient-ratio"
    calibration: float | list = 1.0
    latency_s: float | None = None
    chunk: int = 16

    def __post_init__(self):
        if not 0.0 <= self.surround <= 1.0:
            raise ValueError(f"surround must lie in [0, 1], got {self.surround}")
        if self.decoding != "gradient-ratio":
            raise ValueError(f"unknown EMD decoding {self.decoding!r}; available: 'gradient-ratio'")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "EMDFrontEndConfig":
        d = dict(d)
        d.setdefault("surround", 0.0)   # configurations written before the surround existed had none
        return cls(lattice=LatticeConfig(**d.pop("lattice", {})),
                   photoreceptor=PhotoreceptorConfig(**d.pop("photoreceptor", {})),
                   emd=EMDConfig(**d.pop("emd", {})), **d)


def pair_pooling_weights(lattice: Lattice, fields: ReceptiveFields, epipole=(0.0, 0.0),
                         tau_s: float = 0.01) -> tuple[sparse.csr_matrix, sparse.csr_matrix]:
    """Sparse (F, P) weights for the numerator Σ c·R·m and the denominator Σ c²·G·m².

    A pair belongs to a field when its midpoint's azimuth and elevation fall inside the
    field's box. m_j = ⟨p_j − e, u_j⟩ is the matched filter (normalised units),
    c_j = 2τ/s_j with s_j the pair's separation in normalised image units, so
    c_j·m_j = 2τ·t_j with t_j the expansion template of :func:`lobula.lc_geometry.expansion_templates`.
    """
    mid = lattice.pair_midpoint
    az, el = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
    half = fields.size_deg / 2
    cen = fields.centres_deg
    inside = (np.abs(az[None, :] - cen[:, :1]) <= half) & (np.abs(el[None, :] - cen[:, 1:]) <= half)
    t, _ = expansion_templates(lattice, epipole)
    cm = 2.0 * tau_s * t
    num = sparse.csr_matrix(inside * cm[None, :])
    den = sparse.csr_matrix(inside * (cm * cm)[None, :])
    return num, den


class EMDFrontEnd:
    """Frames → photoreceptors → EMDs → per-field r̄ (1/s) by gradient-ratio decoding.

    ``run(frames)`` streams (index, time_s, image (H, W)) and yields
    (time_s − latency, r̄ (F,), r²̄ (F,)) per frame; ``timings`` accumulates seconds per stage
    (sampling, photoreceptor, emd, fields).
    """

    def __init__(self, camera: PinholeCamera, fields: ReceptiveFields, config: EMDFrontEndConfig | None = None,
                 epipole=(0.0, 0.0), device: str | torch.device = "cpu"):
        self.config = cfg = config or EMDFrontEndConfig()
        self.camera = camera
        self.device = torch.device(device)
        t0 = _time.perf_counter()
        self.lattice = Lattice(camera, cfg.lattice)
        self.lattice.operator_on(self.device)  # built once here, so per-frame timings are steady-state
        self.build_s = _time.perf_counter() - t0
        dt = camera.frame_interval_s
        self.photoreceptors = Photoreceptors(cfg.photoreceptor, dt)
        self._surround = lattice_filter(self.lattice, 0.0, cfg.surround)
        if self._surround is not None:
            self._surround = self._surround.to(self.device)
        self.emds = EMDArray.from_lattice(self.lattice, cfg.emd, dt)
        num, den = pair_pooling_weights(self.lattice, fields, epipole, cfg.emd.tau_s)
        self._num = torch.from_numpy(num.toarray().T.astype(np.float32)).to(self.device)  # (P, F)
        self._den = torch.from_numpy(den.toarray().T.astype(np.float32)).to(self.device)
        a = torch.as_tensor(self.lattice.pairs_a, device=self.device)
        b = torch.as_tensor(self.lattice.pairs_b, device=self.device)
        self._a, self._b = a, b
        gain = np.asarray(cfg.calibration, dtype=np.float32)
        if gain.ndim and gain.shape != (fields.n_fields,):
            raise ValueError(f"EMD calibration has {gain.size} gains but there are {fields.n_fields} fields; "
                             f"fit it with the same field configuration")
        self._gain = torch.as_tensor(gain, device=self.device)
        self.latency_s = (cfg.latency_s if cfg.latency_s is not None
                          else cfg.photoreceptor.tau_s + cfg.emd.tau_s + 0.5 * dt)
        self.timings = dict(sampling=0.0, photoreceptor=0.0, emd=0.0, fields=0.0)

    def _batch(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tm = self.timings
        t0 = _time.perf_counter()
        x = self.lattice.sample(torch.as_tensor(frames, device=self.device) / 255.0)  # (T, n)
        t1 = _time.perf_counter()
        y = self.photoreceptors.run(x)
        y = spatial_filter(self._surround, y)
        t2 = _time.perf_counter()
        R = self.emds.run(y)  # (T, P)
        t3 = _time.perf_counter()
        G = (y[:, self._b] - y[:, self._a]) ** 2
        num = R @ self._num
        den = G @ self._den
        r = (self._gain * num / den.clamp_min(1e-20)).double().cpu().numpy()
        r[den.cpu().numpy() <= 0] = np.nan
        tm["sampling"] += t1 - t0
        tm["photoreceptor"] += t2 - t1
        tm["emd"] += t3 - t2
        tm["fields"] += _time.perf_counter() - t3
        return r, r * r

    def run(self, frames: Iterable[tuple[int, float, np.ndarray]]) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
        buf_t, buf_f = [], []
        for _, t, img in frames:
            buf_t.append(t)
            buf_f.append(img)
            if len(buf_f) == self.config.chunk:
                yield from self._flush(buf_t, buf_f)
        if buf_f:
            yield from self._flush(buf_t, buf_f)

    def _flush(self, buf_t, buf_f):
        r, r2 = self._batch(np.stack(buf_f))
        out = list(zip([t - self.latency_s for t in buf_t], r, r2))
        buf_t.clear()
        buf_f.clear()
        return out


def fit_calibration(r_emd: np.ndarray, r_true: np.ndarray, per_field: bool = True):
    """Least-squares gains g with r_true ≈ g·r_emd; r_emd, r_true (n, F).

    per_field: one gain per field (F,) (fields near the epipole see slow motion, the
    periphery fast motion, so their biases differ), else one number. Fit on one scene
    with known r (a synthetic run's depth maps) and hold fixed for others: it absorbs
    the mean temporal-frequency and spatial-sampling bias of the gradient ratio.
    """
    ok = np.isfinite(r_emd) & np.isfinite(r_true)
    x, y = np.where(ok, r_emd, 0.0), np.where(ok, r_true, 0.0)
    if not per_field:
        return float(np.sum(x * y) / np.sum(x * x))
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.sum(x * y, 0) / np.sum(x * x, 0)
    return np.where(np.isfinite(g), g, 1.0)
