"""The velocity pipeline's front ends: what turns footage into the receptive fields' expansion rates.

:data:`FRONT_ENDS` maps each name to a :class:`FrontEnd` entry: its one-line description, whether
it needs torch, what it yields, its epipole policy, its readout defaults, how the gyro derotates
it, and ``open``, the factory that, given the footage, the :class:`~lobula.config.VelocityConfig`
and the rest of a :class:`~lobula.front_ends.base.FrontEndInput`, yields the samples
:func:`lobula.velocity.field_rates` consumes:

* ``dis``, ``farneback``: dense optical flow on the camera's frames (:mod:`lobula.front_ends.optic_flow`);
* ``flo``: precomputed flow from ``.flo`` files (:mod:`lobula.front_ends.flo`);
* ``emd``: Hassenstein–Reichardt motion detectors on the camera's image (:mod:`lobula.front_ends.emd`, torch).

Adding a front end is one module and one entry (:func:`register_front_end`). The entries' attributes
cost no import: each front end's module loads when it opens. The command line's parsers, which import
only the standard library, hold the names as a literal (``experiments.parsers.FRONT_END_NAMES``, checked
against this registry by tests/test_front_ends.py).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from lobula.readout.config import ReadoutConfig

from .base import FieldSample, FrontEndInput, FrontEndStream

__all__ = ["FRONT_ENDS", "FieldSample", "FrontEnd", "FrontEndInput", "FrontEndStream",
           "get_front_end", "register_front_end"]

#: κ's errors (ReadoutConfig kappa_rel_error, shared_error_frac) a front end gets when it names none:
#: ReadoutConfig's defaults, set for dense optical flow
FLOW_KAPPA_ERRORS = (ReadoutConfig.kappa_rel_error, ReadoutConfig.shared_error_frac)


@dataclass(frozen=True)
class FrontEnd:
    """One front end of the velocity pipeline.

    name: what ``VelocityConfig.front_end`` and ``--front-end`` call it. description: what measures the
    image motion, in a few words (figure captions). open: ``open(FrontEndInput) -> FrontEndStream``, the
    factory. needs_torch: it runs on torch (the ``bio`` extra). yields: "flow" (a
    :class:`lobula.flow.FlowSample` per frame pair, which the pipeline derotates and pools into the
    fields) or "fields" (a :class:`~lobula.front_ends.base.FieldSample` per frame: the front end pools
    itself). epipoles: the epipole policies it runs with ("estimate": fitted to the flow; "principal":
    the principal point); the first is its default. kappa_errors: its readout's κ errors
    (kappa_rel_error, shared_error_frac) by default (:data:`FLOW_KAPPA_ERRORS`, or
    ``ReadoutConfig.EMD_KAPPA_ERRORS`` for the EMD's fields). derotation: what the gyro turns, "flow"
    (each pair's flow derotated exactly by the integrated gyro) or "gaze" (the frames' gaze stabilised
    before the front end, ``VelocityConfig.emd.gaze``). live: it takes each pair from the footage's frames
    as they stream in, so the pipeline knows when each row's frames are in, fits the gyro's bias and
    scale with the heading pair by pair and measures the material rates. sections: the
    VelocityConfig sections it reads beyond the shared ones ("flow": FlowConfig, whose ``method``
    the front end sets; "emd": EMDFrontEndConfig).
    """

    name: str
    description: str
    open: Callable[[FrontEndInput], FrontEndStream]
    needs_torch: bool = False
    yields: str = "flow"
    epipoles: tuple[str, ...] = ("estimate", "principal")
    kappa_errors: tuple[float, float] = FLOW_KAPPA_ERRORS
    derotation: str = "flow"
    live: bool = False
    sections: tuple[str, ...] = ("flow",)

    def __post_init__(self):
        if self.yields not in ("flow", "fields"):
            raise ValueError(f"front end {self.name!r}: yields must be 'flow' or 'fields', got {self.yields!r}")
        if self.derotation not in ("flow", "gaze"):
            raise ValueError(f"front end {self.name!r}: derotation must be 'flow' or 'gaze', got {self.derotation!r}")
        if not self.epipoles or set(self.epipoles) - {"estimate", "principal"}:
            raise ValueError(f"front end {self.name!r}: epipoles must be among 'estimate', 'principal', "
                             f"got {self.epipoles!r}")

    def default_readout(self) -> ReadoutConfig:
        """A new ReadoutConfig with this front end's κ errors (ReadoutConfig's other defaults)."""
        k, s = self.kappa_errors
        return ReadoutConfig(kappa_rel_error=k, shared_error_frac=s)

    @property
    def estimates_epipole(self) -> bool:
        """Whether it can run with the epipole fitted to its flow (else the principal point only)."""
        return "estimate" in self.epipoles


def _open_dis(inp):
    from .dis import open_dis
    return open_dis(inp)


def _open_farneback(inp):
    from .farneback import open_farneback
    return open_farneback(inp)


def _open_flo(inp):
    from .flo import open_flo
    return open_flo(inp)


def _open_emd(inp):
    from .emd import open_emd
    return open_emd(inp)


#: every front end by name, in the order the command line lists them
FRONT_ENDS: dict[str, FrontEnd] = {fe.name: fe for fe in (
    FrontEnd("dis", "dense optical flow (OpenCV DIS)", _open_dis, live=True),
    FrontEnd("farneback", "dense optical flow (Farnebäck)", _open_farneback, live=True),
    FrontEnd("flo", "precomputed optical flow (.flo files)", _open_flo),
    # The EMD's fields expand about the principal point (it has no epipole estimate), and each
    # field's EMD gain drifts as texture flows through it: κ's larger shared error (ReadoutConfig.emd).
    FrontEnd("emd", "Hassenstein–Reichardt motion detectors (EMD array)", _open_emd, needs_torch=True,
             yields="fields", epipoles=("principal",), kappa_errors=ReadoutConfig.EMD_KAPPA_ERRORS, derotation="gaze",
             sections=("emd",)),
)}


def register_front_end(front_end: FrontEnd) -> FrontEnd:
    """Add ``front_end`` to :data:`FRONT_ENDS` (one of the same name is replaced); returns it.

    The command line's ``--front-end`` offers the names registered here (``experiments.parsers.FRONT_END_NAMES``);
    a front end registered at run time serves the library (``VelocityConfig(front_end=...)``).
    """
    FRONT_ENDS[front_end.name] = front_end
    return front_end


def get_front_end(name: str) -> FrontEnd:
    """The entry of front end ``name``; ValueError naming the known front ends when there is none."""
    try:
        return FRONT_ENDS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown front end {name!r}; the front ends known: {', '.join(FRONT_ENDS)}") from None
