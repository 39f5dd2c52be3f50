"""Middlebury ``.flo`` optical-flow files: reading them and turning their numbers into normalised flow.

A ``.flo`` file's units depend on who wrote it (:class:`FloUnits`): the FLIVVER files hold
rad/s on a resized grid, FlowNet2's raw output pixels per frame pair.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lobula.camera import PinholeCamera

from .core import FootageError

FLO_TAG = 202021.25


def read_flo(path: str | Path) -> np.ndarray:
    """Read the Middlebury .flo file at ``path``: returns (2, H, W) float32 (u, v) in the file's own units."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(12)
        if len(head) < 12:
            raise FootageError(f"{path}: too short to be a .flo file")
        tag = np.frombuffer(head[:4], "<f4")[0]
        w, h = np.frombuffer(head[4:], "<i4")
        if tag != FLO_TAG or w <= 0 or h <= 0 or w * h > 1 << 28:
            raise FootageError(f"{path}: not a Middlebury .flo file (tag {tag}, size {w}x{h})")
        data = np.frombuffer(fh.read(), "<f4")
    if data.size != 2 * w * h:
        raise FootageError(f"{path}: truncated .flo file ({data.size} of {2 * w * h} values)")
    return data.reshape(h, w, 2).transpose(2, 0, 1).copy()


@dataclass(frozen=True)
class FloUnits:
    """What a .flo file's numbers mean.

    units: "rad/s" (pixel displacement / (fx_ref·gap_s): the FLIVVER files) or
    "px" (pixel displacement over the frame pair: FlowNet2's raw output).
    gap_s: time between the two frames (s). ref_width/ref_height: image size the flow
    was computed at (the FLIVVER files: 640×448, resized from 480 rows). In "rad/s" the
    FLIVVER convention divides both components by the *original* fx, so pixels of the
    resized image are value·gap·fx on both axes.
    """

    units: str = "rad/s"
    gap_s: float = 0.2
    ref_width: int = 640
    ref_height: int = 448


def flo_to_normalised(flow: np.ndarray, camera: PinholeCamera, units: FloUnits) -> np.ndarray:
    """Convert a .flo field to normalised flow (1/s) on the camera's full-size pixel grid, (2, H, W).

    flow (2, h, w): the file's numbers (:func:`read_flo`), in ``units`` (:class:`FloUnits`).
    The flow is resized to the camera image, its vectors rescaled by the change of pixel
    size, and divided by the focal lengths and the frame gap.
    """
    _, h, w = flow.shape
    if (w, h) != (units.ref_width, units.ref_height):
        raise FootageError(f".flo field is {w}x{h} but its units say {units.ref_width}x{units.ref_height}")
    sx, sy = camera.width / w, camera.height / h
    if units.units == "rad/s":
        # The FLIVVER convention: pixel displacement of the resized image = value·gap·fx.
        du = flow[0] * units.gap_s * camera.fx
        dv = flow[1] * units.gap_s * camera.fx
    elif units.units == "px":
        du, dv = flow[0], flow[1]
    else:
        raise ValueError(f"unknown .flo units {units.units!r}; use 'rad/s' or 'px'")
    du = cv2.resize(du.astype(np.float32), (camera.width, camera.height), interpolation=cv2.INTER_LINEAR) * sx
    dv = cv2.resize(dv.astype(np.float32), (camera.width, camera.height), interpolation=cv2.INTER_LINEAR) * sy
    return np.stack(camera.flow_px_to_normalised(du, dv, units.gap_s)).astype(np.float32)
