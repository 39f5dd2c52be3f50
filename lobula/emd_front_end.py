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
from scipy import sparse

from ._optional import torch
from .camera import PinholeCamera, angles_to_normalised, normalised_to_angles
from .emd import EMDArray, EMDConfig
from .lattice import Lattice, LatticeConfig
from .lc_geometry import expansion_templates
from .photoreceptor import PhotoreceptorConfig, Photoreceptors, lattice_filter, spatial_filter
from .receptive_field import ReceptiveFields


@dataclass
class EMDFrontEndConfig:
    """The EMD front end for velocity estimation.

    Parameters
    ----------
    lattice : LatticeConfig
        The ommatidia. Default Δφ = 0.75°, Δρ = Δφ: a ~5,000-ommatidia eye on the D435i's field
        of view, enough for 5° fields (the fly's 4.6° needs ≥ 20° fields).
    photoreceptor : PhotoreceptorConfig
        A 10 ms low-pass and no temporal high-pass: the surround removes the mean luminance.
    emd : EMDConfig
        The correlators' delay τ (s); 10 ms keeps the replay's image motion in the EMD's
        near-linear range.
    surround : float
        Weight s in [0, 1] of the LMCs' lateral inhibition, x − s·(the lattice neighbours' mean),
        after the photoreceptors (:func:`lobula.photoreceptor.lattice_filter`). 1 (default)
        removes the mean luminance in space, with no memory, as the compound eye's circuit does;
        0 with the photoreceptor's ``tau_hp_s=0.25`` removes it in time instead, whose high-pass
        drifts the decoded gain after every change of speed (its memory is a trailing copy of the
        pattern moving at the past speed). On development suite worlds (10 s, 320×240, realistic
        IMU, causal; seeds 100, 101) the surround reads panels 0.044 / 0.035 and corridor
        0.011 / 0.014 m/s, the high-pass 0.081 / 0.070 and 0.090 / 0.084.
    decoding : {"gradient-ratio"}
        How r̄ is decoded from the EMD pairs (see the module docstring).
    calibration : float or list of float
        Gain on r̄, one number or one per field (1 = none); fitted on another scene by
        :func:`fit_calibration`, then held fixed.
    latency_s : float or None
        s: how far the decoded r̄ trails the image motion; outputs are stamped that much earlier.
        None: the low-frequency group delay of the photoreceptor and EMD low-passes plus half a
        frame (the correlator averages over the frame interval).
    chunk : int
        Frames processed per batch.
    gaze : {"fixate", "none"}
        "fixate" (default): with a gyro, each frame is warped into a gaze held fixed in the world
        (:func:`lobula.gaze.fixation_reference`) before the lattice samples it, and the gaze jumps
        back to the camera (a saccade: photoreceptors and EMDs restart, and their output is NaN while
        they settle, as at the start) once the camera has turned ``saccade_limit_deg`` away from it; the
        fields' expansion templates follow the focus of expansion (the optical axis) into the gaze's frame each
        frame. At 30 frames/s a turning camera's image moves up to 1.6° per frame under the
        suite's turns, two ommatidial spacings at Δφ = 0.75°, so the correlators alias;
        subtracting the gyro's predicted response after them does not help (development rotation
        worlds 100 / 101, causal: 0.418 / 0.346 m/s, against 0.435 / 0.399 without it and
        0.107 / 0.049 on a stabilised image). "none": the camera's own image.
    saccade_limit_deg : float
        deg, in (0, 90]: how far the camera may turn from the fixated gaze before a saccade
        returns the gaze to it.
    heading_tau_s : float
        s: with a fixating gaze, the time constant with which the heading the templates follow
        (the camera's epipole, in the world-fixed frame) trails the camera's (0: no lag).
    """

    lattice: LatticeConfig = field(default_factory=lambda: LatticeConfig(dphi_deg=0.75))
    photoreceptor: PhotoreceptorConfig = field(default_factory=lambda: PhotoreceptorConfig(tau_s=0.010))
    emd: EMDConfig = field(default_factory=lambda: EMDConfig(tau_s=0.010))
    surround: float = 1.0
    decoding: str = "gradient-ratio"
    calibration: float | list = 1.0
    latency_s: float | None = None
    chunk: int = 16
    gaze: str = "fixate"
    saccade_limit_deg: float = 12.0
    heading_tau_s: float = 1.0

    def __post_init__(self):
        if self.gaze not in ("fixate", "none"):
            raise ValueError(f"EMD gaze must be 'fixate' or 'none', got {self.gaze!r}")
        if not (self.heading_tau_s >= 0 and np.isfinite(self.heading_tau_s)):
            raise ValueError(f"heading_tau_s must be a finite number of seconds >= 0, got {self.heading_tau_s}")
        if not 0.0 < self.saccade_limit_deg <= 90.0:
            raise ValueError(f"saccade_limit_deg must lie in (0, 90] degrees, got {self.saccade_limit_deg}")
        if not 0.0 <= self.surround <= 1.0:
            raise ValueError(f"surround must lie in [0, 1], got {self.surround}")
        if self.decoding != "gradient-ratio":
            raise ValueError(f"unknown EMD decoding {self.decoding!r}; available: 'gradient-ratio'")

    def to_dict(self) -> dict:
        """Every field as a dict, nested configurations as dicts."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "EMDFrontEndConfig":
        """The configuration :meth:`to_dict` wrote as ``d``."""
        d = dict(d)
        # A stored configuration without these fields describes a front end without them: no
        # surround (the mean removed in time) and the camera's own image.
        d.setdefault("surround", 0.0)
        d.setdefault("gaze", "none")
        return cls(lattice=LatticeConfig(**d.pop("lattice", {})),
                   photoreceptor=PhotoreceptorConfig(**d.pop("photoreceptor", {})),
                   emd=EMDConfig(**d.pop("emd", {})), **d)


def field_membership(lattice: Lattice, fields: ReceptiveFields) -> np.ndarray:
    """(F, P) bool: pair p of ``lattice`` belongs to field f of ``fields`` when its midpoint's azimuth and
    elevation lie in the field's box."""
    mid = lattice.pair_midpoint
    az, el = (np.degrees(a) for a in normalised_to_angles(mid[:, 0], mid[:, 1]))
    half = fields.size_deg / 2
    cen = fields.centres_deg
    return (np.abs(az[None, :] - cen[:, :1]) <= half) & (np.abs(el[None, :] - cen[:, 1:]) <= half)


def pair_pooling_weights(lattice: Lattice, fields: ReceptiveFields, epipole=(0.0, 0.0),
                         tau_s: float = 0.01) -> tuple[sparse.csr_matrix, sparse.csr_matrix]:
    """Sparse (F, P) weights for the numerator Σ c·R·m and the denominator Σ c²·G·m².

    A pair belongs to a field when its midpoint's azimuth and elevation fall inside the
    field's box. m_j = ⟨p_j − e, u_j⟩ is the matched filter (normalised units),
    c_j = 2τ/s_j with s_j the pair's separation in normalised image units, so
    c_j·m_j = 2τ·t_j with t_j the expansion template of :func:`lobula.lc_geometry.expansion_templates`.
    lattice: its pairs; fields: the fields; epipole (2,): normalised; tau_s: the EMD's τ (s). The
    numerator's weights are in s, the denominator's in s².
    """
    inside = field_membership(lattice, fields)
    t, _ = expansion_templates(lattice, epipole)
    cm = 2.0 * tau_s * t
    num = sparse.csr_matrix(inside * cm[None, :])
    den = sparse.csr_matrix(inside * (cm * cm)[None, :])
    return num, den


def epipole_pooling_weights(lattice: Lattice, fields: ReceptiveFields,
                            tau_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Dense (P, 3F) and (P, 6F) weights whose pooled sums give :func:`pair_pooling_weights`' numerator
    and denominator for any epipole e = (e_x, e_y) (normalised units), by :func:`pooled_at_epipole`.

    The expansion template is linear in the epipole, t_p(e) = α_p − e·β_p with α_p = ⟨m_p, Δp⟩/|Δp|²
    and β_p = Δp/|Δp|², so Σ c·R·t is three sums (α, β_x, β_y) and Σ c²·G·t² six (αα, αβ_x, αβ_y,
    β_xβ_x, β_xβ_y, β_yβ_y): an epipole that moves every frame costs no new weights.
    Columns are grouped by term, F fields each. lattice, fields, tau_s (s): as for :func:`pair_pooling_weights`.
    """
    inside = field_membership(lattice, fields)                                 # (F, P)
    step = lattice.normalised[lattice.pairs_b] - lattice.normalised[lattice.pairs_a]
    beta = step / np.einsum("pk,pk->p", step, step)[:, None]                  # (P, 2)
    alpha = np.einsum("pk,pk->p", lattice.pair_midpoint, beta)                # (P,)
    c = 2.0 * tau_s
    terms_n = [alpha, beta[:, 0], beta[:, 1]]
    terms_d = [alpha * alpha, alpha * beta[:, 0], alpha * beta[:, 1],
               beta[:, 0] * beta[:, 0], beta[:, 0] * beta[:, 1], beta[:, 1] * beta[:, 1]]
    num = np.concatenate([(inside * (c * x)[None, :]).T for x in terms_n], 1)
    den = np.concatenate([(inside * (c * c * x)[None, :]).T for x in terms_d], 1)
    return num, den


def pooled_at_epipole(num_terms: np.ndarray, den_terms: np.ndarray, epipole: np.ndarray):
    """Numerator and denominator (T, F) at per-frame epipoles ``epipole`` (T, 2) (normalised) from the sums
    ``num_terms`` (T, 3F) and ``den_terms`` (T, 6F) of :func:`epipole_pooling_weights`' weights."""
    F = num_terms.shape[-1] // 3
    n = [num_terms[..., i * F:(i + 1) * F] for i in range(3)]
    d = [den_terms[..., i * F:(i + 1) * F] for i in range(6)]
    ex, ey = epipole[..., :1], epipole[..., 1:2]
    num = n[0] - ex * n[1] - ey * n[2]
    den = d[0] - 2 * ex * d[1] - 2 * ey * d[2] + ex * ex * d[3] + 2 * ex * ey * d[4] + ey * ey * d[5]
    return num, den


class EMDFrontEnd:
    """Frames → photoreceptors → EMDs → per-field r̄ (1/s) by gradient-ratio decoding.

    ``run(frames, orientation=None)`` streams (index, time_s, image (H, W)) and yields
    (time_s − latency, r̄ (F,), r²̄ (F,)) per frame; with the camera's attitude per frame it
    stabilises the gaze first (``EMDFrontEndConfig.gaze``; ``saccades`` counts the jumps).
    ``timings`` accumulates seconds per stage (sampling, which includes the gaze's warp,
    photoreceptor, emd, fields).

    camera: the frames' camera; fields: the receptive fields; config: :class:`EMDFrontEndConfig`
    (None: the default); epipole (2,): the expansion's centre, normalised; device: where torch runs.
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
        self._fields = fields
        self._epipole = np.asarray(epipole, dtype=float).reshape(2)
        self._num_e = self._den_e = None     # the moving-epipole weights, built when a gaze first needs them
        self.saccades = 0
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
        # The columns start at rest (the photoreceptors' and delay lines' state set to the first frame, as if
        # nothing had moved): their first frame reads no motion and the next ones climb to the moving level, a
        # ṙ that is the circuit's, not the world's (the fast family's camera braking at 4 m/s²: r̄ 0, then 70 %,
        # then its level; low-passed, κ read +2.4 /s against a true −2.4, and the online readout took the
        # accelerometer's offset from it for the whole run). Those frames are left out: the first, and those
        # within twice the photoreceptor and EMD time constants of the (re)start.
        self.settle_s = 2.0 * (cfg.photoreceptor.tau_s + cfg.emd.tau_s + (cfg.photoreceptor.tau_hp_s or 0.0))
        self._age = 0   # frames the columns have run since they started, or restarted after a saccade
        self.timings = dict(sampling=0.0, photoreceptor=0.0, emd=0.0, fields=0.0)

    def _batch(self, frames: np.ndarray, gaze: dict | None = None, index: np.ndarray | None = None):
        tm = self.timings
        t0 = _time.perf_counter()
        restart = None
        if gaze is not None:
            import cv2

            h, w = frames.shape[1:]
            frames = np.stack([cv2.warpPerspective(f, gaze["homography"][i], (w, h),
                                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                                   borderMode=cv2.BORDER_REPLICATE)
                               for f, i in zip(frames, index)])
            restart = gaze["saccade"][index[0]]
            if restart:   # the gaze jumped: the columns start again from this frame, as at the start
                self.photoreceptors.reset()
                self.emds.reset()
        x = self.lattice.sample(torch.as_tensor(frames, device=self.device) / 255.0)  # (T, n)
        t1 = _time.perf_counter()
        y = self.photoreceptors.run(x)
        y = spatial_filter(self._surround, y)
        t2 = _time.perf_counter()
        R = self.emds.run(y)  # (T, P)
        t3 = _time.perf_counter()
        G = (y[:, self._b] - y[:, self._a]) ** 2
        if gaze is None:
            num, den = R @ self._num, G @ self._den
        else:   # the terms combined in float64: they cancel each other in part
            e = torch.as_tensor(gaze["epipole"][index], dtype=torch.float64, device=self.device)
            num, den = pooled_at_epipole((R @ self._num_e).double(), (G @ self._den_e).double(), e)
        r = (self._gain * num / den.clamp_min(1e-20)).double().cpu().numpy()
        r[den.cpu().numpy() <= 0] = np.nan
        if restart:
            self._age = 0
        age = self._age + np.arange(len(r))
        r[age * self.camera.frame_interval_s < self.settle_s] = np.nan   # the columns settling (see __init__)
        self._age += len(r)
        if gaze is not None:
            r[~gaze["seen"][index]] = np.nan   # fields turned out of the camera's view
        tm["sampling"] += t1 - t0
        tm["photoreceptor"] += t2 - t1
        tm["emd"] += t3 - t2
        tm["fields"] += _time.perf_counter() - t3
        return r, r * r

    def gaze(self, orientation: np.ndarray) -> dict | None:
        """The stabilised gaze for frames of attitudes ``orientation`` (N, 3, 3) (camera → a fixed frame):
        per frame the homography (N, 3, 3) taking a gaze pixel to the camera's, the focus of expansion
        in the gaze's normalised coordinates (N, 2) and the saccades (N,) bool; None with gaze "none"."""
        from .gaze import fixation_reference

        if self.config.gaze == "none":
            return None
        q = np.asarray(orientation, dtype=float)
        ref, saccade = fixation_reference(q, self.config.saccade_limit_deg)
        rel = np.swapaxes(q, 1, 2) @ ref                              # gaze → camera directions
        hom = np.stack([self.camera.rotation_homography(r) for r in rel])
        # The heading: the camera's (its epipole) followed with a lag, in the fixed frame (see heading_tau_s).
        h_cam = np.append(self._epipole, 1.0) / np.linalg.norm(np.append(self._epipole, 1.0))
        ahead = q @ h_cam                                             # (N, 3), fixed frame
        beta = 1.0 - np.exp(-self.camera.frame_interval_s / self.config.heading_tau_s) \
            if self.config.heading_tau_s > 0 else 1.0
        h = np.empty_like(ahead)
        h[0] = ahead[0]
        for k in range(1, len(h)):  # a 3-vector recursion per frame
            x = h[k - 1] + beta * (ahead[k] - h[k - 1])
            h[k] = x / np.linalg.norm(x)
        d = np.einsum("nji,nj->ni", ref, h)                           # the heading, in the gaze
        return dict(homography=hom, epipole=d[:, :2] / d[:, 2:3], saccade=saccade, seen=self._seen(rel))

    def _seen(self, rel: np.ndarray) -> np.ndarray:
        """(N, F) bool: the field's box (its four corners) lies inside the camera's image when the gaze
        is turned by ``rel`` (N, 3, 3), gaze → camera. Elsewhere the warped image is the replicated border."""
        half = self._fields.size_deg / 2
        cen = np.radians(self._fields.centres_deg)
        corners = np.stack([cen + np.radians([sx * half, sy * half]) for sx in (-1, 1) for sy in (-1, 1)], 1)
        x, y = angles_to_normalised(corners[..., 0], corners[..., 1])                   # (F, 4)
        ray = np.stack([x, y, np.ones_like(x)], -1)                                      # (F, 4, 3)
        cam = np.einsum("nij,fcj->nfci", rel, ray)                                       # (N, F, 4, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = self.camera.normalised_to_pixel(cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2])
        c = self.camera
        inside = (cam[..., 2] > 0) & (u >= 0) & (u <= c.width - 1) & (v >= 0) & (v <= c.height - 1)
        return inside.all(-1)

    def run(self, frames: Iterable[tuple[int, float, np.ndarray]],
            orientation: np.ndarray | None = None) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
        """Stream frames (index, time s, grey image (H, W) in grey levels 0..255), yielding (time s, r̄ (F,)
        1/s, r²̄ (F,) 1/s²) per frame; ``orientation`` (N, 3, 3), the camera's attitude at every footage
        frame index (camera → a fixed frame, from the integrated gyro), stabilises the gaze (``config.gaze``)."""
        g = None if orientation is None else self.gaze(orientation)
        if g is not None and self._num_e is None:
            num, den = epipole_pooling_weights(self.lattice, self._fields, self.config.emd.tau_s)
            self._num_e = torch.from_numpy(num.astype(np.float32)).to(self.device)   # (P, 3F)
            self._den_e = torch.from_numpy(den.astype(np.float32)).to(self.device)   # (P, 6F)
        self.saccades = 0 if g is None else int(g["saccade"].sum())
        buf_i, buf_t, buf_f = [], [], []
        for i, t, img in frames:
            if g is not None and g["saccade"][i] and buf_f:   # a saccade starts a new batch
                yield from self._flush(buf_i, buf_t, buf_f, g)
            buf_i.append(i)
            buf_t.append(t)
            buf_f.append(img)
            if len(buf_f) == self.config.chunk:
                yield from self._flush(buf_i, buf_t, buf_f, g)
        if buf_f:
            yield from self._flush(buf_i, buf_t, buf_f, g)

    def _flush(self, buf_i, buf_t, buf_f, gaze=None):
        r, r2 = self._batch(np.stack(buf_f), gaze, np.asarray(buf_i))
        out = list(zip([t - self.latency_s for t in buf_t], r, r2))
        buf_i.clear()
        buf_t.clear()
        buf_f.clear()
        return out


def fit_calibration(r_emd: np.ndarray, r_true: np.ndarray, per_field: bool = True):
    """Least-squares gains g (dimensionless) with r_true ≈ g·r_emd; r_emd, r_true (n, F) 1/s.

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
