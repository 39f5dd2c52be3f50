"""The ``emd`` front end: Hassenstein–Reichardt motion detectors on the camera's image
(:class:`lobula.emd_front_end.EMDFrontEnd`: lattice sampling, photoreceptors, EMDs, gradient-ratio fields).

It needs torch (the ``bio`` extra), imported when it opens, so the camera pipeline never loads it.
"""
from __future__ import annotations

from lobula.readers.core import FootageError

from .base import FieldSample, FrontEndInput, FrontEndStream, timed


def open_emd(inp: FrontEndInput) -> FrontEndStream:
    """The fields' rates at every frame (:class:`~lobula.front_ends.base.FieldSample`).

    With a gyro (``inp.attitude``) the gaze is stabilised by its attitude at the frames before the lattice
    (``config.emd.gaze``). Once drawn to the end, ``inp.timings`` holds the EMD's own stages (in place of
    flow and fields), ``n_ommatidia`` and ``n_saccades``; fewer than two frames raise FootageError.
    """
    from lobula._optional import require_torch
    from lobula.emd_front_end import EMDFrontEnd

    require_torch("the EMD front end")
    footage, timings = inp.footage, inp.timings
    front = EMDFrontEnd(footage.camera, inp.fields, inp.config.emd)
    orientation = None if inp.attitude is None else inp.attitude(footage.times)

    def samples():
        n = 0
        for t, r, r2 in front.run(timed(footage.frames(), timings, "read"), orientation):
            n += 1
            yield FieldSample(t, r, r2)
        timings.pop("flow", None)
        timings.pop("fields", None)
        timings.update(front.timings)
        timings["n_ommatidia"] = front.lattice.n
        timings["n_saccades"] = front.saccades
        if n < 2:
            raise FootageError(f"{footage.path}: too few frames for the EMD front end ({n})")

    return FrontEndStream(samples(), len(footage))
