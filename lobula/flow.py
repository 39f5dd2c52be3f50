"""Dense optic-flow front ends: angular flow (normalised coordinates per second, 1/s) at each pixel.

OpenCV DIS (with its presets) and Farneback compute flow between frames ``gap``
frames apart, staggered so that every frame starts a pair (the paper: 6 frames,
0.2 s, at 30 frames/s). A pair's flow is the *average* image velocity over its
interval, so it belongs to the middle of the interval: :class:`StaggeredFlow`
stamps each flow with that mid time. Precomputed flow (``.flo``) enters through
:func:`stimuli.footage.flo_to_normalised`.
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass
from typing import Iterable, Iterator

import cv2
import numpy as np

from .camera import PinholeCamera

DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
               "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


@dataclass
class FlowConfig:
    """Dense-flow front-end parameters.

    method: "dis" or "farneback". gap: frames between the two images of a pair.
    dis_preset: "ultrafast" | "fast" | "medium". threads: OpenCV threads (0 = OpenCV's default).
    """

    method: str = "dis"
    gap: int = 6
    dis_preset: str = "fast"
    threads: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def make_flow_fn(config: FlowConfig):
    """A function (frame0, frame1) -> pixel displacement (2, H, W) float32 for uint8/float grey frames."""
    if config.threads:
        cv2.setNumThreads(config.threads)
    if config.method == "dis":
        if config.dis_preset not in DIS_PRESETS:
            raise ValueError(f"unknown DIS preset {config.dis_preset!r}; choose from {sorted(DIS_PRESETS)}")
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[config.dis_preset])

        def fn(a, b):
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


def _u8(img: np.ndarray) -> np.ndarray:
    return img if img.dtype == np.uint8 else np.clip(np.round(img), 0, 255).astype(np.uint8)


def pixel_to_angular(flow_px: np.ndarray, camera: PinholeCamera, dt_s: float) -> np.ndarray:
    """Pixel displacement over dt_s seconds (2, H, W) -> normalised flow in 1/s (2, H, W)."""
    return np.stack(camera.flow_px_to_normalised(flow_px[0], flow_px[1], dt_s)).astype(np.float32)


@dataclass
class FlowSample:
    """One staggered flow: pair (i0, i0 + gap), times t0 < t1, mid time, normalised flow (2, H, W) 1/s."""

    index: int
    t0: float
    t1: float
    flow: np.ndarray

    @property
    def t_mid(self) -> float:
        return 0.5 * (self.t0 + self.t1)

    @property
    def dt(self) -> float:
        return self.t1 - self.t0


class StaggeredFlow:
    """Flow between frame k and frame k + gap for every k, from a stream of frames.

    Holds only ``gap + 1`` frames, so memory is independent of the footage length.
    Usage: ``for sample in StaggeredFlow(camera, config).run(frames): ...`` where frames
    yields (index, time_s, image).
    """

    def __init__(self, camera: PinholeCamera, config: FlowConfig | None = None):
        self.camera = camera
        self.config = config or FlowConfig()
        if self.config.gap < 1:
            raise ValueError("flow gap must be at least one frame")
        self._fn = make_flow_fn(self.config)

    def run(self, frames: Iterable[tuple[int, float, np.ndarray]]) -> Iterator[FlowSample]:
        buf: deque = deque(maxlen=self.config.gap + 1)
        for item in frames:
            buf.append(item)
            if len(buf) == buf.maxlen:
                (i0, t0, a), (_, t1, b) = buf[0], buf[-1]
                flow = pixel_to_angular(self._fn(a, b), self.camera, t1 - t0)
                yield FlowSample(i0, t0, t1, flow)
