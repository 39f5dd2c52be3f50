"""What a front end is given and what it yields, shared by the front-end modules (which import this
module, never :mod:`lobula.front_ends` itself).

A front end turns footage into one of two kinds of sample, which :func:`lobula.velocity.field_rates`
consumes: :class:`lobula.flow.FlowSample` (a pair's dense flow, (2, H, W) 1/s, that the pipeline
derotates and pools into the receptive fields) or :class:`FieldSample` (the fields' rates at one
frame, pooled by the front end itself).
"""
from __future__ import annotations

import time as _time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from lobula.readers.flo import FloUnits
    from lobula.receptive_field import ReceptiveFields


@dataclass
class FieldSample:
    """The fields' rates at one frame: t s; r (F,) 1/s, the expansion rate; r2 (F,) 1/s², its pooled square."""

    t: float
    r: np.ndarray
    r2: np.ndarray


def _no_thread(items: Iterable, name: str = "stage") -> Iterator:
    return iter(items)


@dataclass
class FrontEndInput:
    """What :attr:`lobula.front_ends.FrontEnd.open` is given.

    footage: a :class:`lobula.readers.core.Footage` (camera, times (N,) s, ``frames()`` yielding
    (index, time s, image), its path, kind, files and truth). config: the run's VelocityConfig.
    fields: the receptive fields (:func:`lobula.receptive_field.tile_fields` on the footage's camera).
    timings: seconds per stage (``read``, ``flow``, ``fields`` to start with), which the front end adds
    to as its samples are drawn. attitude: the gyro's integrated attitude, t (k,) s -> camera → reference
    rotations (k, 3, 3), or None (no gyro, or ``config.derotate`` off). flo_files, flo_units: the
    precomputed flow of the ``flo`` front end (:mod:`lobula.readers.flo`). ahead: runs an iterable a few
    items ahead in a thread of its own, ``ahead(items, name) -> iterator`` (the command line's
    :func:`lobula.threads.threaded`); by default no thread.
    """

    footage: Any
    config: Any   # lobula.config.VelocityConfig, which imports this package (so not imported here)
    fields: "ReceptiveFields"
    timings: dict = field(default_factory=lambda: dict(read=0.0, flow=0.0, fields=0.0))
    attitude: Callable[[np.ndarray], np.ndarray] | None = None
    flo_files: list[Path] | None = None
    flo_units: "FloUnits | None" = None
    ahead: Callable[..., Iterator] = _no_thread


@dataclass
class FrontEndStream:
    """An opened front end: ``samples`` yields FlowSample or FieldSample (the entry's ``yields`` says which),
    lazily; ``total``: how many it will yield at most, for a progress bar."""

    samples: Iterator
    total: int


def timed(items: Iterable, timings: dict, key: str, minus: tuple[dict, str] | None = None) -> Iterator:
    """Pass items through, adding the time spent producing each to ``timings[key]`` (s).

    minus=(other, k): leave out what other[k] grew by meanwhile — the time this stage spent
    waiting for the stage before it, timed by a ``timed`` on its input in the same thread.
    """
    it = iter(items)
    while True:
        before, t0 = minus[0][minus[1]] if minus else 0.0, _time.perf_counter()
        try:
            item = next(it)
        except StopIteration:
            return
        timings[key] += _time.perf_counter() - t0 - ((minus[0][minus[1]] - before) if minus else 0.0)
        yield item
