"""Dense optical flow on the camera's frames (OpenCV DIS or Farnebäck, :mod:`lobula.flow`): the shared
body of the ``dis`` and ``farneback`` front ends."""
from __future__ import annotations

import numpy as np

from lobula.flow import StaggeredFlow

from .base import FrontEndInput, FrontEndStream, timed


def dense_flow(inp: FrontEndInput, method: str) -> FrontEndStream:
    """Staggered flow pairs (:class:`lobula.flow.FlowSample`, 1/s) by ``method`` ("dis" | "farneback"),
    which it sets as ``inp.config.flow.method``.

    Decoding, flow and pooling overlap: decoding and flow each run in a thread of their own
    (``inp.ahead``), a few frames ahead. With a gyro (``inp.attitude``) each pair's flow is taken on the
    image turned by the gyro's rotation (lobula.flow.prewarp_flow): the flow method then sees only small
    displacements. The stream's times go to ``inp.timings``: read, flow (less the flow's wait for frames).
    """
    config, timings = inp.config, inp.timings
    config.flow.method = method
    frames = inp.ahead(timed(inp.footage.frames(), timings, "read"), name="decode")
    waited = dict(decode=0.0)
    turn = None
    if inp.attitude is not None:
        def turn(t0, t1, plain=inp.attitude):
            q = plain(np.array([t0, t1]))
            return q[0].T @ q[1]
    flows = StaggeredFlow(inp.footage.camera, config.flow, rotation=turn).run(timed(frames, waited, "decode"))
    samples = inp.ahead(timed(flows, timings, "flow", minus=(waited, "decode")), name="flow")
    return FrontEndStream(samples, max(len(inp.footage) - config.flow.gap, 0))
