"""The frame loop the two bag readers share (ROS1 ``.bag`` and rosbag2 ``.db3``).

Both formats are read through rosbags' ``Reader``: messages come in record-time order, and a
read can start at a record time. :func:`bag_frames` streams frames start..stop-1 of one image
topic one message at a time and turns what the bag library or a decoder raises on damaged input
into a FootageError naming the bag, the frame and the topic; how a message becomes a grey image
is the reader's own (``decode``).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Iterator

import numpy as np

from .core import Footage, FootageError


def bag_frames(footage: Footage, topic: str, record_ns: np.ndarray, start: int, stop: int | None, *,
               open_bag: Callable[[], tuple], select: Callable, decode: Callable, corrupt: tuple,
               fix: str) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield (index, time_s, grey float32 (H, W)) for frames start..stop-1 of ``topic``, one message at a time.

    footage: the bag's footage (its path, times and length). record_ns: (n,) int64, each frame's
    record time (ns) when the bag was opened. open_bag: ``() -> (Reader, ReaderError, context)``,
    the bag library's reader class, its error and what ``decode`` needs. select: ``connection ->
    bool``, the connections to read. decode: ``(i, raw, record_ns, context) -> grey | None``;
    None leaves frame i out (a bad frame with skip_bad_frames set). corrupt: the further exception
    types that mean damaged input. fix: what to do about a damaged bag, ending the message.
    """
    n = len(footage)
    start, stop = max(0, int(start)), (n if stop is None else min(int(stop), n))
    if start >= stop:
        return
    Reader, ReaderError, context = open_bag()
    first_ns = int(record_ns[start])
    # The reader starts at the first message with this record time, which may be a few frames
    # before ``start`` when record times repeat.
    i = int(np.searchsorted(record_ns, first_ns, side="left"))
    try:
        with Reader(footage.path) as reader:
            conns = [c for c in reader.connections if select(c)]
            for _, rec_ns, raw in reader.messages(connections=conns, start=first_ns):
                if i < start:
                    i += 1
                    continue
                grey = decode(i, raw, rec_ns, context)
                if grey is not None:
                    yield i, float(footage.times[i]), grey
                i += 1
                if i >= stop:
                    break
    except FootageError:
        raise
    except (ReaderError, *corrupt) as exc:
        raise FootageError(f"{footage.path}: cannot read frame {i} on {topic} ({type(exc).__name__}: {exc}); "
                           f"{fix}") from exc
    if i < stop:
        raise FootageError(f"{footage.path}: {topic} ended after frame {i - 1}, {n} frames when opened; "
                           f"the bag changed, open it again")
