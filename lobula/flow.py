"""Dense optic-flow front ends: angular flow (normalised coordinates per second, 1/s) at each pixel.

OpenCV DIS (with its presets) and Farneback compute flow between frames ``gap``
frames apart, staggered so that every frame starts a pair (the paper: 6 frames,
0.2 s, at 30 frames/s). A pair's flow is the *average* image velocity over its
interval, so it belongs to the middle of the interval: :class:`StaggeredFlow`
stamps each flow with that mid time. Precomputed flow (``.flo``) enters through
:func:`lobula.readers.flo.flo_to_normalised`.
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass
from typing import Iterable, Iterator

import cv2
import numpy as np

from ._fields import check_field_types
from .camera import PinholeCamera

DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
               "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


@dataclass
class FlowConfig:
    """Dense-flow front-end parameters.

    method: "dis" or "farneback". gap: frames between the two images of a pair.
    dis_preset: "ultrafast" | "fast" | "medium". threads: OpenCV threads (0 = OpenCV's default).
    prewarp: where the camera's rotation over a pair is known (the integrated gyro), warp the
    pair's second image into the first image's orientation before the flow, so the flow
    method sees only the translation's (and the gyro error's) small displacements, then
    compose the warp back: the flow returned is still the raw image flow (:func:`prewarp_flow`).
    dis_grid_px: DIS refines its flow down to a finest pyramid level that its preset fixes as a
    power of two below the image (``fast``: 1/4, so 160×120 at 640×480 but 80×60 at 320×240).
    The level is taken finer while it would be narrower than this many pixels, so the flow's
    angular resolution does not fall with the image size (0: the preset's level at every size).
    On the 80×60 grid the growth of r as a surface nears is smoothed away: vision's a/v errs by
    −0.3·r̄·v per frame (r̄·v ≈ v²/d; development corridor and fast scenes, seed 102, 320×240),
    on a 160-px grid by −0.1·r̄·v, as the same scenes give at 640×480 with the preset unchanged
    (exact flow: 0.0). Over the 36 development scenes (9 families × seeds 100–103) the 160-px
    grid reads zero-phase RMSE 0.0073 m/s against 0.0091 on the preset's, causal 0.0149 against
    0.0203.
    Cost: unchanged at 640×480 (160 px is the preset's own grid there); at 320×240 DIS ``fast``
    takes 4.5 against 1.3 ms a pair (one thread).
    chain_fraction: a pair whose image moves far is computed through the frames between its two
    images and the steps composed (:func:`chained_flow`): when the previous pair's displacement
    (:func:`far_displacement`, its 98th percentile) exceeds this fraction of the image width, in as
    many steps as it holds of that (up to ``gap``); and the first pair and every ``chain_check``-th
    are computed in two steps as a check, kept if they move that far, because a failed flow hides
    its own failure. Why: DIS cannot follow a fast approach. On the development fast scene
    (corridor, 2 m/s, seed 103, 320×240) the single 6-frame pair's flow keeps 0.97 of the exact
    displacement while its 90th percentile stays under ~30 px, then collapses to −0.1…0.3 of it
    (errors 13–22 px) as the approach reaches 35–43 px — while reading only 11–15 px itself;
    through the frames between, in 2 or 3 steps, it keeps 1.00 (errors 0.2–0.3 px). 0.05 (16 px at
    320 wide): below where the single pair starts to fail, so a speed that grows is caught before;
    a pair that already failed reads less, which the periodic check catches. The displacement is
    what the flow method saw, less the pre-warped rotation (steps add their flows' noise: a slow
    translation seen through a fast turn is better in one step). 0: off. The cost is that of the
    steps, only where the image moves that far, and two extra flows every ``chain_check`` pairs
    (the check; a slow flow is then the single step's, as without chaining).
    """

    method: str = "dis"
    gap: int = 6
    dis_preset: str = "fast"
    threads: int = 0
    prewarp: bool = True
    dis_grid_px: int = 160
    chain_fraction: float = 0.05
    chain_check: int = 30

    def __post_init__(self):
        check_field_types(self)
        if self.dis_preset not in DIS_PRESETS:
            raise ValueError(f"FlowConfig.dis_preset must be one of {sorted(DIS_PRESETS)}, got {self.dis_preset!r}")
        for name, low in (("gap", 1), ("threads", 0), ("dis_grid_px", 0)):
            if getattr(self, name) < low:
                raise ValueError(f"FlowConfig.{name} must be a whole number >= {low}, got {getattr(self, name)!r}")
        if not (self.chain_fraction >= 0 and self.chain_check >= 1):
            raise ValueError(f"chain_fraction must be >= 0 (0: off) and chain_check >= 1 pair, got "
                             f"{self.chain_fraction}, {self.chain_check}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


def make_flow_fn(config: FlowConfig):
    """A function (frame0, frame1) -> pixel displacement (2, H, W) float32 px for uint8/float grey frames
    (H, W), the method, preset and threads of ``config``."""
    if config.threads:
        cv2.setNumThreads(config.threads)
    if config.method == "dis":
        if config.dis_preset not in DIS_PRESETS:
            raise ValueError(f"unknown DIS preset {config.dis_preset!r}; choose from {sorted(DIS_PRESETS)}")
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[config.dis_preset])
        preset_finest = dis.getFinestScale()

        def fn(a, b):
            dis.setFinestScale(dis_finest_scale(preset_finest, a.shape[1], config.dis_grid_px))
            f = dis.calc(_u8(a), _u8(b), None)
            return f.transpose(2, 0, 1)
    elif config.method == "farneback":
        def fn(a, b):
            f = cv2.calcOpticalFlowFarneback(_u8(a), _u8(b), None, pyr_scale=0.5, levels=4, winsize=21,
                                             iterations=5, poly_n=7, poly_sigma=1.5, flags=0)
            return f.transpose(2, 0, 1)
    else:
        raise ValueError(f"unknown flow method {config.method!r}; use 'dis' or 'farneback'")
    return fn


def dis_finest_scale(preset_finest: int, width_px: int, grid_px: int) -> int:
    """DIS's finest pyramid level (0: full resolution) for an image width_px wide: the preset's
    (``preset_finest``), or finer while the level would be narrower than grid_px pixels (grid_px ≤ 0:
    the preset's)."""
    s = int(preset_finest)
    while grid_px > 0 and s > 0 and (width_px >> s) < grid_px:
        s -= 1
    return s


def _u8(img: np.ndarray) -> np.ndarray:
    return img if img.dtype == np.uint8 else np.clip(np.round(img), 0, 255).astype(np.uint8)


def pixel_to_angular(flow_px: np.ndarray, camera: PinholeCamera, dt_s: float) -> np.ndarray:
    """Pixel displacement ``flow_px`` over dt_s seconds (2, H, W) px -> normalised flow in 1/s (2, H, W)
    float32, through ``camera``'s focal lengths.

    Divides into one float32 output (as :meth:`PinholeCamera.flow_px_to_normalised` does, the
    same operation and rounding) instead of stacking two temporaries and copying them again.
    """
    flow_px = np.asarray(flow_px)
    if flow_px.dtype != np.float32:
        return np.stack(camera.flow_px_to_normalised(flow_px[0], flow_px[1], dt_s)).astype(np.float32)
    out = np.empty(flow_px.shape, np.float32)
    np.divide(flow_px[0], camera.fx * dt_s, out=out[0])
    np.divide(flow_px[1], camera.fy * dt_s, out=out[1])
    return out


#: px: below this predicted rotational displacement anywhere in the image a pair is not warped
#: (interpolating the image would cost more than the rotation's displacement).
PREWARP_MIN_PX = 0.5


def rotation_warp(camera: PinholeCamera, r01: np.ndarray):
    """The homography of a pure rotation as a function (u, v) px -> (u1, v1) px.

    r01 (3, 3) takes camera vectors at the pair's second frame into the first frame's camera
    frame (Q(t0)ᵀ·Q(t1) from the integrated gyro). A pixel (u, v) of the first frame looks
    along the ray d0; the second frame sees that ray at r01ᵀ·d0, i.e. at the returned pixel.
    """
    h = camera.rotation_homography(np.asarray(r01, float).T)
    h = h / h[2, 2]

    def warp(u, v):
        w = h[2, 0] * u + h[2, 1] * v + h[2, 2]
        return (h[0, 0] * u + h[0, 1] * v + h[0, 2]) / w, (h[1, 0] * u + h[1, 1] * v + h[1, 2]) / w
    return warp


def prewarp_flow(fn, a: np.ndarray, b: np.ndarray, camera: PinholeCamera, r01: np.ndarray) -> np.ndarray:
    """Pixel displacement (2, H, W) px from image a to image b, with b first turned into a's orientation.

    fn: the flow function, (a, b) -> (2, H, W) px (:func:`make_flow_fn`); a, b (H, W): grey images of
    ``camera``; r01 (3, 3): as for :func:`rotation_warp`.
    Under a fast turn (0.8 rad/s over a 0.2 s pair moves the image ~30 px at 320×240) a
    coarse-to-fine flow such as DIS loses the small translational flow in the rotation's
    large one. The rotation r01 (see :func:`rotation_warp`) is known from the gyro, so b is
    resampled at W(p) (the pixel where b sees a's ray p): b_w(p) = b(W(p)). The flow δ
    from a to b_w holds only translation and what the gyro got wrong, and the raw
    displacement is W(p + δ) − p, exact for any rotation angle (a homography, no small-
    angle step). Pixels whose match falls outside b (their scene point left the view) are
    NaN: b_w holds b's replicated edge there, so the method's flow would be the rotation
    alone, a translational flow of zero (downstream every stage skips non-finite flow).
    """
    import cv2

    h, w = a.shape[:2]
    hom = camera.rotation_homography(np.asarray(r01, float).T)  # a's pixel -> b's pixel (homogeneous)
    warp = rotation_warp(camera, r01)
    # A rotation's homography displaces the image most at its border: test corners and edge middles.
    bu = np.array([0, w / 2, w - 1, 0, w - 1, 0, w / 2, w - 1], float)
    bv = np.array([0, 0, 0, h / 2, h / 2, h - 1, h - 1, h - 1], float)
    cu, cv_ = warp(bu, bv)
    if max(np.abs(cu - bu).max(), np.abs(cv_ - bv).max()) < PREWARP_MIN_PX:
        return fn(a, b)
    bw = cv2.warpPerspective(_u8(b), hom, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
    return compose_homography(fn(a, bw), hom)


def compose_homography(flow_px: np.ndarray, hom: np.ndarray) -> np.ndarray:
    """The raw displacement W(p + δ) − p (2, H, W) float32 of a flow δ (2, H, W) px taken on
    the warped image, W the homography ``hom`` (3, 3) of a's pixel to b's; NaN where W(p + δ)
    falls outside the image (the point left the view). Returned as a view of (H, W, 2), like
    the flow functions' own.

    Each step is one OpenCV pass (the transform, the in-image test and a masked subtraction
    into a NaN-filled output): boolean indexing of the interleaved points costs 3× the rest.
    """
    h, w = flow_px.shape[1:]
    grid = _pixel_grid(h, w)
    pts = cv2.add(flow_px.transpose(1, 2, 0), grid)               # where a's pixels went in b_w (px)
    moved = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), hom).reshape(h, w, 2)
    # A point whose match lies outside b left the view: b_w there is b's replicated edge, and
    # the "flow" the method found is the rotation alone. Unknown, not zero: NaN. (The flow
    # methods here give no NaN; cv2.perspectiveTransform would map one to the pixel (0, 0).)
    inside = cv2.inRange(moved, (0.0, 0.0), (float(w - 1), float(h - 1)))
    out = np.full((h, w, 2), np.nan, np.float32)
    cv2.subtract(moved, grid, dst=out, mask=inside)
    return out.transpose(2, 0, 1)


_GRIDS: dict = {}


def _pixel_grid(h: int, w: int) -> np.ndarray:
    """Pixel coordinates (h, w, 2) float32 (u, v), cached per image size."""
    if (h, w) not in _GRIDS:
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        _GRIDS[(h, w)] = np.stack([u, v], -1)
    return _GRIDS[(h, w)]


def compose_flows(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Displacement (2, H, W) px of ``first`` followed by ``second`` (each (2, H, W) px, the second
    defined on the intermediate image): p + first(p) + second(p + first(p)), the second sampled
    bilinearly. NaN where either is NaN or the intermediate point lies outside the image."""
    h, w = first.shape[1:]
    pos = cv2.add(np.ascontiguousarray(first.transpose(1, 2, 0), np.float32), _pixel_grid(h, w))
    pos[~np.isfinite(pos)] = -2.0
    out = np.empty((2, h, w), np.float32)
    for j in range(2):
        # Replicated border: a point on the last row or column still reads its own value (a constant
        # NaN border would enter there with weight 0 and make it NaN); points outside are set below.
        out[j] = cv2.remap(np.ascontiguousarray(second[j], np.float32), pos[..., 0], pos[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    outside = cv2.inRange(pos, (0.0, 0.0), (float(w - 1), float(h - 1))) == 0
    out[:, outside | np.isnan(out).any(0)] = np.nan
    return first + out


def chained_flow(flow_fn, frames: list, steps: int) -> np.ndarray:
    """Displacement (2, H, W) px from the first to the last of ``frames`` (a list of (time_s, image)),
    computed in ``steps`` (≤ len(frames) − 1) flows between frames spread evenly over the list and
    composed (:func:`compose_flows`). flow_fn(t0, a, t1, b) -> (2, H, W) px for one step."""
    n = len(frames) - 1
    cuts = sorted({int(round(j * n / steps)) for j in range(steps + 1)})
    total = None
    for i, j in zip(cuts[:-1], cuts[1:]):
        (t0, a), (t1, b) = frames[i], frames[j]
        step = np.asarray(flow_fn(t0, a, t1, b), np.float32)
        total = step if total is None else compose_flows(total, step)
    return total


def far_displacement(px: np.ndarray, warp=None) -> float:
    """98th percentile of the displacement magnitude (px) of ``px`` (2, H, W) px over finite pixels, on every
    4th row and column
    (not a median or a 90th: where sky or a far backdrop fills most of the image, the near floor that
    moves far is a few per cent of it; chaining on the 90th instead, eight unseen scenes: zero-phase
    0.0098 against 0.0092 m/s, causal 0.0315 against 0.0307; development seeds 0.0060 / 0.0135
    against 0.0059 / 0.0134);
    with ``warp`` (:func:`rotation_warp`), of what is left after the rotation's own displacement: what
    the flow method saw of a prewarped pair."""
    du, dv = px[0, ::4, ::4], px[1, ::4, ::4]
    if warp is not None:
        v, u = np.mgrid[0:px.shape[1]:4, 0:px.shape[2]:4].astype(float)
        wu, wv = warp(u, v)
        du, dv = du - (wu - u), dv - (wv - v)
    m = np.hypot(du, dv)
    m = m[np.isfinite(m)]
    return float(np.quantile(m, 0.98)) if m.size else 0.0


@dataclass
class FlowSample:
    """One staggered flow: pair (index, index + gap) of frame indices, times t0 < t1 (s), normalised flow
    (2, H, W) 1/s."""

    index: int
    t0: float
    t1: float
    flow: np.ndarray

    @property
    def t_mid(self) -> float:
        """The pair's middle time (s)."""
        return 0.5 * (self.t0 + self.t1)

    @property
    def dt(self) -> float:
        """The pair's gap (s)."""
        return self.t1 - self.t0


class StaggeredFlow:
    """Flow between frame k and frame k + gap for every k, from a stream of frames.

    Holds only ``gap + 1`` frames, so memory is independent of the footage length.
    Usage: ``for sample in StaggeredFlow(camera, config).run(frames): ...`` where frames
    yields (index, time_s, image).
    """

    def __init__(self, camera: PinholeCamera, config: FlowConfig | None = None, rotation=None):
        """rotation: optional function (t0, t1) -> r01 (3, 3), the camera's rotation over a pair
        (second frame's vectors into the first's, from the integrated gyro); with it and
        ``config.prewarp`` each pair's flow is computed on the derotated image (:func:`prewarp_flow`)."""
        self.camera = camera
        self.config = config or FlowConfig()
        self.rotation = rotation if self.config.prewarp else None
        if self.config.gap < 1:
            raise ValueError("flow gap must be at least one frame")
        self._fn = make_flow_fn(self.config)
        self._buf: deque | None = None  # the last gap + 1 frames
        self._last_far, self._count = 0.0, 0

    def _pair(self, t0, a, t1, b) -> np.ndarray:
        """Pixel displacement (2, H, W) from image a at t0 to image b at t1 (prewarped where the rotation is known)."""
        if self.rotation is not None:
            return prewarp_flow(self._fn, a, b, self.camera, self.rotation(t0, t1))
        return self._fn(a, b)

    def run(self, frames: Iterable[tuple[int, float, np.ndarray]]) -> Iterator[FlowSample]:
        """FlowSample of every pair, from frames (index, time s, grey image (H, W)) in order."""
        for item in frames:
            sample = self.push(item)
            if sample is not None:
                yield sample

    def push(self, item: tuple[int, float, np.ndarray]) -> FlowSample | None:
        """Take in the next frame, ``item`` = (index, time s, grey image (H, W)); returns the pair it completes
        (from ``gap`` frames
        before to it), or None while fewer than ``gap + 1`` frames have come."""
        cfg = self.config
        if self._buf is None:
            self._buf = deque(maxlen=cfg.gap + 1)
        buf = self._buf
        buf.append(item)
        if len(buf) < buf.maxlen:
            return None
        (i0, t0, a), (_, t1, b) = buf[0], buf[-1]
        reach = cfg.chain_fraction * a.shape[1]  # px a single step may move
        steps = min(cfg.gap, int(np.ceil(self._last_far / reach))) if reach > 0 else 1
        check = reach > 0 and cfg.gap > 1 and steps < 2 and self._count % cfg.chain_check == 0
        r01 = None if self.rotation is None else self.rotation(t0, t1)  # once per pair
        turn = None if r01 is None or reach <= 0 else rotation_warp(self.camera, r01)
        px = None
        if steps > 1 or check:
            px = chained_flow(self._pair, [(t, im) for _, t, im in buf], max(steps, 2))
            if check and far_displacement(px, turn) <= reach:
                px = None  # a check that found the image slow: one step is the better flow there
        if px is None:
            px = self._fn(a, b) if r01 is None else prewarp_flow(self._fn, a, b, self.camera, r01)
        if reach > 0:
            self._last_far = far_displacement(px, turn)
        self._count += 1
        return FlowSample(i0, t0, t1, pixel_to_angular(px, self.camera, t1 - t0))
