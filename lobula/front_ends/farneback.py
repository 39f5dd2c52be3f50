"""The ``farneback`` front end: OpenCV's Farnebäck dense optical flow (:mod:`lobula.flow`)."""
from __future__ import annotations

from .base import FrontEndInput, FrontEndStream
from .optic_flow import dense_flow


def open_farneback(inp: FrontEndInput) -> FrontEndStream:
    """Farnebäck flow pairs (1/s) on the frames of ``inp`` (a FrontEndInput;
    :func:`lobula.front_ends.optic_flow.dense_flow`)."""
    return dense_flow(inp, "farneback")
