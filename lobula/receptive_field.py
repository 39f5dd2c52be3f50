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

import cv2
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
    material: take ṙ̄ along the image content (:class:`MaterialFields`, the material
    derivative Dr/Dt the geometry needs) instead of at fixed pixels (the paper).
    """

    size_deg: float = 5.0
    spacing_deg: float | None = None
    margin_deg: float = 0.0
    shape: str = "box"
    pooling: str = "least-squares"
    gap_correction: bool = True
    material: bool = True

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


class MaterialFields:
    """Receptive fields that follow the image content: ṙ̄ as the material derivative Dr/Dt.

    ṙ = a/d + r² holds along a scene point. At a fixed pixel other points flow through
    (∂r/∂t = Dr/Dt − u·∇r), which is wrong wherever r varies across the image (floors,
    walls, slanted surfaces). Here each field's points at the flow of frame k − s are
    carried by that flow to where they are at frame k, r is pooled at both ends over the
    *same* points (least squares, the fields' weights), and
    ``ṙ̄ = (r̄_end − r̄_start)/δ``, ``r̄``, ``r²̄`` the means of both ends (so all three
    terms see one set of depths and v_f = a·r̄/(ṙ̄ − r²̄ − r·g) is exact per field).

    Rotation: for a camera turning at ω, a point's forward depth changes as
    ḋ = −v − d(ωx y − ωy x) and the camera-frame velocity as v̇ = a − v(ωx ey − ωy ex), so
    Dr/Dt = a/d + r² + r·g with g = ωx(y − ey) − ωy(x − ex); the pooled r·g is returned
    (``r_omega``) for the readout to subtract.

    Work is done on b×b pixel blocks (b chosen so ~20,000 blocks cover the image): the
    maps are smooth at that scale and the cost does not grow with the image.
    """

    def __init__(self, fields: ReceptiveFields, stagger: int, block: int | None = None, gap_correction: bool = True):
        cam = fields.camera
        self.fields, self.stagger, self.gap_correction = fields, int(stagger), gap_correction
        b = self.block = block or max(1, int(round(np.sqrt(cam.width * cam.height / 20000))))
        self.hs, self.ws = cam.height // b, cam.width // b
        rows = np.arange(cam.height)[:, None] // b
        cols = np.arange(cam.width)[None, :] // b
        inside = (rows < self.hs) & (cols < self.ws)
        blk = np.where(inside, rows * self.ws + cols, 0).ravel()
        agg = sparse.csr_matrix((inside.ravel().astype(np.float64), (np.arange(blk.size), blk)),
                                shape=(blk.size, self.hs * self.ws))
        self.weights = (fields.weights.astype(np.float64) @ agg).tocsr()  # (F, blocks): Σ_pixels w
        self.x = self._blocks(fields.x)
        self.y = self._blocks(fields.y)
        self.fx, self.fy, self.cx, self.cy = cam.fx, cam.fy, cam.cx, cam.cy
        self._buf: list = []

    def _blocks(self, m: np.ndarray) -> np.ndarray:
        """Block means (hs, ws) of a full-resolution map; NaN stays NaN."""
        b = self.block
        m = np.asarray(m, np.float32)[: self.hs * b, : self.ws * b]
        if b == 1:
            return m.copy()
        return cv2.resize(m, (self.ws, self.hs), interpolation=cv2.INTER_AREA)

    @staticmethod
    def _g(omega, e, x, y):
        return np.float32(omega[0]) * (y - np.float32(e[1])) - np.float32(omega[1]) * (x - np.float32(e[0]))

    def update(self, t0: float, dt_pair: float, flow: np.ndarray, flow_full: np.ndarray, epipole, omega):
        """Add frame pair k (first frame at t0 s, gap dt_pair s) and return the rates of k − s/2.

        flow: derotated flow (2, H, W) 1/s, expressed in the first frame's orientation;
        flow_full: the image flow before derotation (how content moves); epipole (2,);
        omega: mean angular velocity over the pair (rad/s, camera frame).
        Returns None until s pairs are buffered, else (r̄, r²̄, ṙ̄, r_omega), each (F,).
        """
        dx = self.x - np.float32(epipole[0])
        dy = self.y - np.float32(epipole[1])
        u, v = self._blocks(flow[0]), self._blocks(flow[1])
        num = u * dx + v * dy
        den = dx * dx + dy * dy
        item = dict(t0=t0, T=dt_pair, num=num, den=den, e=np.asarray(epipole, float), omega=np.asarray(omega, float),
                    u=u, v=v, uf=self._blocks(flow_full[0]) - u, vf=self._blocks(flow_full[1]) - v)
        self._buf.append(item)
        if len(self._buf) <= self.stagger:
            return None
        s0 = self._buf.pop(0)
        return self._difference(s0, item)

    def _difference(self, s0: dict, s1: dict):
        delta = s1["t0"] - s0["t0"]
        T = s0["T"]
        # Where the start's points are at the end: the translational displacement over δ
        # is exact for a constant r along the pair (x − e scales by 1/(1 − ρδ), ρ = v/d0),
        # the rotational one is the rotation's flow times δ.
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = 1.0 + np.where(s0["den"] > 0, s0["num"] / s0["den"], 0.0) * T  # d0/d1 over the pair
            rho = (1.0 - 1.0 / np.maximum(lam, 0.2)) / T
            grow = np.where(np.abs(rho) * T > 1e-6,
                            (1.0 / np.maximum(1.0 - rho * delta, 0.2) - 1.0) / np.where(np.abs(lam - 1) > 1e-9, lam - 1, 1.0),
                            delta / T)
        xe = self.x + grow * s0["u"] * T + s0["uf"] * delta
        ye = self.y + grow * s0["v"] * T + s0["vf"] * delta
        b = self.block
        mx = ((xe * self.fx + self.cx) - (b - 1) / 2) / b
        my = ((ye * self.fy + self.cy) - (b - 1) / 2) / b
        inside = (mx >= 0) & (mx <= self.ws - 1) & (my >= 0) & (my <= self.hs - 1)
        mx, my = np.nan_to_num(mx).astype(np.float32), np.nan_to_num(my).astype(np.float32)
        dx1, dy1 = xe - np.float32(s1["e"][0]), ye - np.float32(s1["e"][1])
        den1 = dx1 * dx1 + dy1 * dy1  # |p − e|² at the points' new place (exact, not interpolated)
        num1 = cv2.remap(s1["num"] / np.where(s1["den"] > 0, s1["den"], np.inf), mx, my, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE) * den1  # r there, interpolated, times the new weight
        num0, den0 = s0["num"], s0["den"]
        ok = inside & np.isfinite(num0) & np.isfinite(num1)
        g0 = self._g(s0["omega"], s0["e"], self.x, self.y)
        g1 = self._g(s1["omega"], s1["e"], xe, ye)
        cols = []
        for num, den, g in ((num0, den0, g0), (num1, den1, g1)):
            num = np.where(ok, num, 0.0)
            den = np.where(ok, den, 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                sq = np.where(den > 0, num * num / den, 0.0)
            cols += [num.ravel(), den.ravel(), sq.ravel(), (num * g).ravel()]
        pooled = self.weights @ np.stack(cols, axis=1).astype(np.float64)
        out = []
        for c in (0, 4):
            with np.errstate(divide="ignore", invalid="ignore"):
                r = pooled[:, c] / pooled[:, c + 1]
                r2 = pooled[:, c + 2] / pooled[:, c + 1]
                rg = pooled[:, c + 3] / pooled[:, c + 1]
            if self.gap_correction:
                rc, r2 = gap_correction(r, r2, T)
                with np.errstate(divide="ignore", invalid="ignore"):
                    rg = rg * np.where(np.abs(r) > 1e-12, rc / r, 1.0)
                r = rc
            out.append((r, r2, rg))
        (ra, r2a, rga), (rb, r2b, rgb) = out
        return 0.5 * (ra + rb), 0.5 * (r2a + r2b), (rb - ra) / delta, 0.5 * (rga + rgb)
