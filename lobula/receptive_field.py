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

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scipy import sparse

from ._fields import check_field_types
from .camera import PinholeCamera, normalised_to_angles
from .epipole import derotate, derotate_finite, turn


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

    def __post_init__(self):
        check_field_types(self)
        for name, value, low in (("size_deg", self.size_deg, 0.0), ("spacing_deg", self.spacing_deg, 0.0)):
            if value is not None and not (math.isfinite(value) and value > low):
                raise ValueError(f"FieldConfig.{name} must be a finite number of degrees > 0, got {value}")
        if not (math.isfinite(self.margin_deg) and self.margin_deg >= 0):
            raise ValueError(f"FieldConfig.margin_deg must be a finite number of degrees ≥ 0, got {self.margin_deg}")
        for name, value, allowed in (("shape", self.shape, ("box", "gaussian")),
                                     ("pooling", self.pooling, ("least-squares", "pixel-mean"))):
            if value not in allowed:
                raise ValueError(f"FieldConfig.{name} must be one of {', '.join(allowed)}, got {value!r}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


@dataclass
class ReceptiveFields:
    """A tiling of fields over a camera image.

    camera: the camera tiled (H, W px); centres_deg: (F, 2) azimuth, elevation (degrees, elevation positive down);
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
        """The number of fields, F."""
        return len(self.centres_deg)


def tile_fields(camera: PinholeCamera, config: FieldConfig | None = None) -> ReceptiveFields:
    """Tile the camera's field of view with square fields in (azimuth, elevation), as ``config`` (default
    :class:`FieldConfig`) says."""
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
                valid: np.ndarray | None = None, pooling: str = "least-squares",
                rotation=None, turns=None) -> tuple[np.ndarray, np.ndarray]:
    """Matched-filter pooling of one flow field (2, H, W) in 1/s about the epipole.

    Returns r̄ (F,) and r²̄ (F,) in 1/s and 1/s². ``valid`` (H, W) bool excludes pixels
    (e.g. where flow is unknown); non-finite flow is excluded automatically. All fields
    are pooled by one sparse product of the (F, H·W) weights with three per-pixel maps.
    rotation: the camera's angular velocity ω (3,) rad/s, whose rotational flow is
    subtracted first (:func:`lobula.epipole.derotate`), only on the pixels pooled; the
    result equals pooling ``derotate(flow, ω, fields.x, fields.y)``.
    turns: (r_m0, r_m1, dt_s) instead: the pair's finite rotation is removed exactly
    (:func:`_turn_pair`, as :func:`lobula.epipole.derotate_finite` does for the epipole),
    in the orientation at the pair's middle, where the epipole is.

    Fields pool the pixels on every :func:`pool_stride`-th row and column (1 up to ~80,000
    pixels: all of a 320×240 image; 2 at 640×480). This runs on every frame pair, so the
    per-pixel maps are made only inside the rectangle that holds every field's pixels
    (:func:`_pool_support`, ~80% of a 640×480 image) with few whole-map temporaries; pixels
    outside it have no weight, and the float32 maps and float64 sums are those of
    :func:`pool_fields_reference`, bit for bit.
    """
    if pooling not in ("least-squares", "pixel-mean"):
        raise ValueError(f"unknown pooling {pooling!r}; use 'least-squares' or 'pixel-mean'")
    flow = np.asarray(flow, dtype=np.float32)
    rows, cols, weights, x, y, squares = _pool_support(fields)
    flow = flow[:, rows, cols]
    if turns is not None:
        x, y, flow = _turn_pair(x, y, flow, *turns)
    elif rotation is not None:
        flow = derotate(flow, rotation, x, y, squares)
    dx = x - np.float32(epipole[0])
    dy = y - np.float32(epipole[1])
    num = flow[0] * dx
    t = flow[1] * dy
    num += t
    den = np.multiply(dx, dx, out=dx)
    den += np.multiply(dy, dy, out=dy)
    bad = ~np.isfinite(num)
    if valid is not None:
        bad |= ~np.asarray(valid, bool)[rows, cols]
    num[bad] = 0.0
    den[bad] = 0.0
    pos = den > 0
    maps = np.empty((num.size, 3), np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        if pooling == "least-squares":
            sq = np.multiply(num, num, out=t)
            sq /= den
            sq[~pos] = 0.0
        else:
            # Per-pixel ratio r = num/den, averaged with unit weight: num -> r, den -> 1.
            r_pix = np.divide(num, den, out=t)
            r_pix[~pos] = 0.0
            num, den, sq = r_pix, (~bad).astype(np.float32), r_pix * r_pix
        maps[:, 0] = num.ravel()
        maps[:, 1] = den.ravel()
        maps[:, 2] = sq.ravel()
        pooled = weights @ maps
        r = pooled[:, 0] / pooled[:, 1]
        r2 = pooled[:, 2] / pooled[:, 1]
    return r, r2


#: about how many pixels the fixed-pixel pooling reads at most (a 320×240 image has 76,800): DIS's
#: flow is smooth over its patches (8 px), so a larger image's neighbouring pixels repeat each
#: other's flow, and reading them all cost a 640×480 pair ~6.7 of its ~34 ms CPU (the readout's r̄,
#: r²̄ and ṙ̄ come from the material fields, which work on ~20,000 pixel blocks whatever the image).
POOL_PIXELS = 80_000


def pool_stride(height: int, width: int) -> int:
    """Every how many rows and columns :func:`pool_fields` reads in an image ``height`` × ``width`` px:
    1 up to ~:data:`POOL_PIXELS` pixels
    (320×240 and smaller read every pixel), 2 at 640×480 and 752×480, 3 at 1280×720."""
    return max(1, int(round(np.sqrt(height * width / POOL_PIXELS))))


def _pool_support(fields: ReceptiveFields):
    """(row slice, column slice, weights (F, pixels in the rectangle) float64 CSR, x, y,
    (1 + x², 1 + y²) for the derotation) for :func:`pool_fields`: the bounding rectangle of the fields'
    pixels on the pooling grid (every :func:`pool_stride`-th row and column) and the weights restricted
    to it (each row's entries in the same order, so its sums add the same terms in the same order).
    Kept on the fields object, rebuilt whenever its weights, grid or camera are replaced (a new
    tiling for a new camera is a new object anyway).
    """
    key = (id(fields.weights), id(fields.x), id(fields.y), id(fields.camera))
    cached = getattr(fields, "_pool_cache", None)
    if cached is not None and cached[0] == key and cached[1][0] is fields.weights:
        return cached[2]
    w = fields.weights.tocsr()
    h, wd = fields.x.shape
    s = pool_stride(h, wd)
    prow, pcol = w.indices // wd, w.indices % wd
    on = (prow % s == 0) & (pcol % s == 0)  # the pixels pooled (all where s = 1)
    if np.any(on):
        r0, r1 = int(prow[on].min()), int(prow[on].max()) + 1
        c0, c1 = int(pcol[on].min()), int(pcol[on].max()) + 1
    else:
        r0, r1, c0, c1 = 0, 1, 0, 1
    nr, nc = len(range(r0, r1, s)), len(range(c0, c1, s))
    cols = (prow[on] - r0) // s * nc + (pcol[on] - c0) // s
    field = np.repeat(np.arange(w.shape[0]), np.diff(w.indptr))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(field[on], minlength=w.shape[0]))])
    sub = sparse.csr_matrix((w.data[on].astype(np.float64), cols, indptr), shape=(w.shape[0], nr * nc))
    rows, cs = slice(r0, r1, s), slice(c0, c1, s)
    x = np.ascontiguousarray(fields.x[rows, cs], np.float32)
    y = np.ascontiguousarray(fields.y[rows, cs], np.float32)
    support = (rows, cs, sub, x, y, (1 + x * x, 1 + y * y))
    # Holding the weights themselves keeps their id from being reused while cached.
    fields._pool_cache = (key, (fields.weights, fields.x, fields.y, fields.camera), support)
    return support


def _turn_pair(x: np.ndarray, y: np.ndarray, flow: np.ndarray, r_m0: np.ndarray, r_m1: np.ndarray, dt_s: float):
    """Exact derotation of fixed pixels' flow: (X, Y, translational flow), float32 like the grid.

    :func:`lobula.epipole.derotate_finite` with float32 rotations (so the arithmetic stays float32):
    pixel (x, y) of the first frame and its match x + flow·dt are turned into the orientation at the
    pair's middle, and the flow left is at the turned pixel (X, Y). The first-order
    :func:`lobula.epipole.derotate` leaves the rotation's second-order term ≈ ω²·dt·x(1 + x²), radial
    and positive whichever way the camera turns: an expansion of ~ω²·dt (a still camera turning at
    45°/s over a 0.2 s pair read r̄ ≈ +0.1 1/s, the image of 0.3 m/s at 3 m).
    """
    f32 = lambda r: np.asarray(r, np.float32)  # noqa: E731
    return derotate_finite(x, y, flow, float(np.float32(dt_s)), f32(r_m0), f32(r_m1))


def pool_fields_reference(flow: np.ndarray, fields: ReceptiveFields, epipole=(0.0, 0.0),
                          valid: np.ndarray | None = None, pooling: str = "least-squares", rotation=None,
                          turns=None):
    """:func:`pool_fields` written plainly on the whole image (the definition it is tested against); the
    parameters and the returned r̄ (F,) 1/s and r²̄ (F,) 1/s² are :func:`pool_fields`'."""
    flow = np.asarray(flow, dtype=np.float32)
    x, y = fields.x, fields.y
    if turns is not None:
        x, y, flow = _turn_pair(x, y, flow, *turns)
    elif rotation is not None:
        from .epipole import rotational_flow

        flow = flow - rotational_flow(rotation, fields.x, fields.y).astype(np.float32)
    dx = x - np.float32(epipole[0])
    dy = y - np.float32(epipole[1])
    num = flow[0] * dx + flow[1] * dy
    den = dx * dx + dy * dy
    ok = np.isfinite(num)
    if valid is not None:
        ok &= valid
    stride = pool_stride(*x.shape)
    if stride > 1:  # only the pixels on the pooling grid
        grid = np.zeros(x.shape, bool)
        grid[::stride, ::stride] = True
        ok &= grid
    num = np.where(ok, num, 0.0)
    den = np.where(ok, den, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        if pooling == "least-squares":
            sq = np.where(den > 0, num * num / den, 0.0)
        elif pooling == "pixel-mean":
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
    factor is not positive stay NaN. r_pair (F,) 1/s and r2_pair (F,) 1/s², over a pair
    dt_s s long; returns (r (F,) 1/s, r² (F,) 1/s²).
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
    walls, slanted surfaces). Here each field's points in pair k − s are carried by the
    flow to where they are in pair k, r is pooled at both ends over the *same* points
    (least squares, the fields' weights), and ``ṙ̄ = (r̄_end − r̄_start)/δ``, with ``r̄``,
    ``r²̄`` the means of both ends, so all three terms see one set of depths and
    v_f = a·r̄/(ṙ̄ − r²̄) holds per field.

    Rotation: in a turning camera frame a point's forward depth also changes by the
    rotation (ḋ = −v − d(ωx y − ωy x)), adding r·(ωx(y − ey) − ωy(x − ex)) to Dr/Dt. Both
    ends are therefore expressed in ONE orientation, the camera's at the difference's
    centre (pair k − s/2), by exact finite derotation of each pair
    (:func:`lobula.epipole.derotate_finite`); in a fixed orientation the geometry has no
    rotation term, and at the centre a and v are the camera's own.

    A moving heading: read about one epipole e₀ (the centre's), a heading e that moves by ė over the
    difference adds −r·⟨ė, p − e₀⟩/|p − e₀|² to Dr/Dt. In the fixed orientation ė = (A_xy − e·A_z)/V_z,
    so r·ė = (A_xy − e·A_z)/d and each field's ratio becomes (ṙ̄ − r²̄)/r̄ = ⟨A, ñ⟩/V_z with
    ñ = (−m_x, −m_y, 1 + ⟨e, m⟩), m the field's ``moment`` Σw(p − e₀)/Σw|p − e₀|² (both ends' points):
    the acceleration along ñ, not the forward acceleration, and it does not cancel where the fields lie on
    one side of the heading (a pitched camera's ground). So each end is read about its own heading (the
    epipole its pair was given, turned into the centre's orientation; ``own_heading``), and then
    (ṙ̄ − r²̄)/r̄ = A_z/V_z. Where either end's heading is not ``settled`` (a fit still finding it, whose
    moves are its learning and not the platform's), both ends are read about the centre's. With
    ``own_heading`` False both ends are always read about the centre's, for a readout that takes the
    acceleration along ñ from the 3-D accelerometer (:func:`lobula.readout.field_axes`).

    Work is done on b×b pixel blocks (b chosen so ~20,000 blocks cover the image): the
    maps are smooth at that scale and the cost does not grow with the image.

    fields: the tiling; stagger: pairs between the difference's two ends s (even, ≥ 2);
    block: b (px; None: chosen as above); gap_correction: as :attr:`FieldConfig.gap_correction`;
    own_heading: as above.
    """

    def __init__(self, fields: ReceptiveFields, stagger: int, block: int | None = None, gap_correction: bool = True,
                 own_heading: bool = True):
        cam = fields.camera
        if stagger < 2 or stagger % 2:
            raise ValueError(f"the material difference needs an even stagger ≥ 2, got {stagger}")
        self.fields, self.stagger, self.gap_correction = fields, int(stagger), gap_correction
        self.own_heading = own_heading
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

    def update(self, t0: float, dt_pair: float, flow_full: np.ndarray, epipole,
               q0: np.ndarray | None = None, q1: np.ndarray | None = None, qm: np.ndarray | None = None,
               settled: bool = True):
        """Add frame pair k (first frame at t0 s, gap dt_pair s) and return the rates of pair k − s/2.

        flow_full: the image flow (2, H, W) 1/s, rotation included (how content moves);
        q0, q1, qm: the camera's orientation (camera → a fixed reference, from the integrated
        gyro) at the pair's first frame, second frame and middle (None: not turning);
        epipole (2,): the heading seen in the middle orientation; settled: whether that heading is
        known well enough for its motion to be read (see the class).
        Returns None until s pairs are buffered, else (r̄ 1/s, r²̄ 1/s², ṙ̄ 1/s², each (F,); moment m (F, 2),
        normalised coordinates⁻¹), for pair k − s/2.
        """
        eye = np.eye(3)
        item = dict(t0=t0, T=dt_pair, uf=self._blocks(flow_full[0]), vf=self._blocks(flow_full[1]),
                    e=np.asarray(epipole, float), settled=bool(settled), q0=eye if q0 is None else np.asarray(q0, float),
                    q1=eye if q1 is None else np.asarray(q1, float), qm=eye if qm is None else np.asarray(qm, float))
        self._buf.append(item)
        if len(self._buf) <= self.stagger:
            return None
        s0, sc = self._buf.pop(0), self._buf[self.stagger // 2 - 1]
        return self._difference(s0, sc, item)

    def _rates(self, item, qc, e, x, y, uf, vf):
        """Pair rates in the orientation qc at points (x, y) with flow (uf, vf): num, den maps."""
        from .epipole import derotate_finite

        X, Y, d = derotate_finite(x, y, (uf, vf), item["T"], qc.T @ item["q0"], qc.T @ item["q1"])
        dx, dy = X - e[0], Y - e[1]
        return d[0] * dx + d[1] * dy, dx * dx + dy * dy, d, X, Y, dx, dy

    def _difference(self, s0: dict, sc: dict, s1: dict):
        delta = s1["t0"] - s0["t0"]
        T = s0["T"]
        qc = sc["qm"]
        e0 = e1 = sc["e"]
        if self.own_heading and s0["settled"] and s1["settled"]:
            # each pair's heading, seen in its middle orientation, as the centre's orientation sees it
            e0, e1 = (np.array(turn(qc.T @ it["qm"], *it["e"])) for it in (s0, s1))
        num0, den0, d0, X0, Y0, dx0, dy0 = self._rates(s0, qc, e0, self.x, self.y, s0["uf"], s0["vf"])
        # Where the start's points are at the end. In the fixed orientation only translation
        # moves them, exactly for constant r along the pair (x − e scales by 1/(1 − ρδ),
        # ρ = v/d0), not linearly in δ; the gyro's rotation then says where pair k's first
        # camera sees them.
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = 1.0 + np.where(den0 > 0, num0 / den0, 0.0) * T  # d0/d1 over the pair
            rho = (1.0 - 1.0 / np.maximum(lam, 0.2)) / T
            grow = np.where(np.abs(rho) * T > 1e-6,
                            (1.0 / np.maximum(1.0 - rho * delta, 0.2) - 1.0) / np.where(np.abs(lam - 1) > 1e-9, lam - 1, 1.0),
                            delta / T)
        xe, ye = turn(s1["q0"].T @ qc, X0 + grow * T * d0[0], Y0 + grow * T * d0[1])
        b = self.block
        mx = ((xe * self.fx + self.cx) - (b - 1) / 2) / b
        my = ((ye * self.fy + self.cy) - (b - 1) / 2) / b
        inside = (mx >= 0) & (mx <= self.ws - 1) & (my >= 0) & (my <= self.hs - 1)
        mx, my = np.nan_to_num(mx).astype(np.float32), np.nan_to_num(my).astype(np.float32)
        remap = lambda m: cv2.remap(m, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        num1, den1, _, _, _, dx1, dy1 = self._rates(s1, qc, e1, xe, ye, remap(s1["uf"]), remap(s1["vf"]))
        ok = inside & np.isfinite(num0) & np.isfinite(num1)
        cols = []
        for num, den in ((num0, den0), (num1, den1)):
            num = np.where(ok, num, 0.0)
            den = np.where(ok, den, 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                sq = np.where(den > 0, num * num / den, 0.0)
            cols += [num.ravel(), den.ravel(), sq.ravel()]
        # The moment's numerator, Σw(p − e) over both ends' points (its denominator is r̄'s, Σw|p − e|²).
        cols += [np.where(ok, 0.5 * (dx0 + dx1), 0.0).ravel(), np.where(ok, 0.5 * (dy0 + dy1), 0.0).ravel()]
        pooled = self.weights @ np.stack(cols, axis=1).astype(np.float64)
        out = []
        for c in (0, 3):
            with np.errstate(divide="ignore", invalid="ignore"):
                r = pooled[:, c] / pooled[:, c + 1]
                r2 = pooled[:, c + 2] / pooled[:, c + 1]
            out.append(gap_correction(r, r2, T) if self.gap_correction else (r, r2))
        (ra, r2a), (rb, r2b) = out
        with np.errstate(divide="ignore", invalid="ignore"):
            moment = pooled[:, 6:8] / (0.5 * (pooled[:, 1] + pooled[:, 4]))[:, None]
        return 0.5 * (ra + rb), 0.5 * (r2a + r2b), (rb - ra) / delta, moment
