"""The ``flo`` front end: precomputed optical flow, one Middlebury ``.flo`` file per frame pair
(:mod:`lobula.readers.flo` reads them)."""
from __future__ import annotations

import re
from pathlib import Path

from lobula.flow import FlowSample
from lobula.readers.core import FootageError
from lobula.readers.flo import FloUnits, flo_to_normalised, read_flo

from .base import FrontEndInput, FrontEndStream, timed


def flo_samples(footage, flo_files: list[Path], units: FloUnits):
    """FlowSamples (normalised flow (2, H, W), 1/s) from ``flo_files``, .flo files named ``*_<i0>_to_<i1>.flo``
    (raw frame numbers or indices), in ``units`` (:class:`lobula.readers.flo.FloUnits`), on ``footage`` (a
    :class:`lobula.readers.core.Footage`)."""
    by_name = {int(f.stem): i for i, f in enumerate(footage.files) if f.stem.isdigit()}
    for path in flo_files:
        m = re.search(r"(\d+)_to_(\d+)\.flo$", path.name)
        if not m:
            raise FootageError(f"{path}: .flo files must be named *_<first>_to_<second>.flo")
        a, b = int(m.group(1)), int(m.group(2))
        t0, t1 = _frame_time(footage, a, by_name), _frame_time(footage, b, by_name)
        flow = flo_to_normalised(read_flo(path), footage.camera, units)
        yield FlowSample(a, t0, t1, flow)


def _frame_time(footage, frame: int, by_name: dict) -> float:
    if frame in by_name:
        return float(footage.times[by_name[frame]])
    if footage.kind == "d435i-sample":
        vel = footage.truth
        # raw_frame = sample + 3; time_s is the sample's time.
        k = frame - 3
        if 0 <= k < len(vel["time_s"]):
            return float(vel["time_s"][k])
    raise FootageError(f"no time known for frame {frame} in {footage.path}")


def open_flo(inp: FrontEndInput) -> FrontEndStream:
    """The pairs of ``inp.flo_files`` in their order (units ``inp.flo_units``, default FloUnits());
    FootageError without files."""
    if not inp.flo_files:
        raise FootageError("--front-end flo needs --flo FILE_OR_DIR with *_<first>_to_<second>.flo files")
    samples = timed(flo_samples(inp.footage, inp.flo_files, inp.flo_units or FloUnits()), inp.timings, "flow")
    return FrontEndStream(samples, len(inp.flo_files))
