"""Streaming stages that overlap: each stage of a frame pipeline runs in its own thread.

Decoding a PNG, computing DIS flow and pooling fields each take milliseconds and OpenCV and
NumPy release the GIL while they work, so on a two-core machine the stages overlap when each
runs one frame ahead of the next. :func:`threaded` turns any iterator into one whose items are
produced in a background thread, at most ``maxsize`` items ahead; memory stays bounded.
"""
from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator

_END = object()


def threaded(items: Iterable, maxsize: int = 4, name: str = "stage") -> Iterator:
    """Iterate over ``items`` produced in a background thread (named ``lobula-<name>``), at most ``maxsize`` ahead.

    Order is kept. An exception raised while producing is re-raised here, at the item where it
    happened. If the consumer stops early (break, exception, garbage collection), the producer
    stops within 0.1 s and the source iterator is closed in the thread that ran it.
    """
    if maxsize < 1:
        raise ValueError(f"maxsize must be at least 1, got {maxsize}")
    q: queue.Queue = queue.Queue(maxsize)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce():
        it = iter(items)
        try:
            for x in it:
                if not put((None, x)):
                    break
            else:
                put((None, _END))
        except BaseException as exc:  # handed to the consumer, which re-raises it
            put((exc, None))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    worker = threading.Thread(target=produce, name=f"lobula-{name}", daemon=True)
    worker.start()

    def consume():
        try:
            while True:
                exc, x = q.get()
                if exc is not None:
                    raise exc
                if x is _END:
                    return
                yield x
        finally:
            stop.set()
            worker.join(timeout=5)

    return consume()
