"""The ``dis`` front end: OpenCV's DIS dense optical flow (:mod:`lobula.flow`, ``FlowConfig.dis_preset``)."""
from __future__ import annotations

from .base import FrontEndInput, FrontEndStream
from .optic_flow import dense_flow


def open_dis(inp: FrontEndInput) -> FrontEndStream:
    """DIS flow pairs (1/s) on the frames of ``inp`` (a FrontEndInput;
    :func:`lobula.front_ends.optic_flow.dense_flow`)."""
    return dense_flow(inp, "dis")
