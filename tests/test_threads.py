"""Overlapped stages keep order, propagate errors, stop early without leaking threads, and overlap."""
import threading
import time

import pytest

from lobula.threads import threaded


def test_order_and_completeness():
    assert list(threaded(range(1000), maxsize=3)) == list(range(1000))


def test_errors_reach_the_consumer_at_their_item():
    def gen():
        yield 1
        yield 2
        raise OSError("frame 3 is corrupt")

    got = []
    with pytest.raises(OSError, match="frame 3"):
        for x in threaded(gen()):
            got.append(x)
    assert got == [1, 2]


def test_early_stop_closes_the_source_in_its_thread():
    closed = threading.Event()

    def gen():
        try:
            for i in range(10 ** 9):
                yield i
        finally:
            closed.set()

    it = threaded(gen(), maxsize=2)
    assert [next(it) for _ in range(5)] == list(range(5))
    it.close()
    assert closed.wait(2)
    assert not any(t.name.startswith("lobula-") and t.is_alive() for t in threading.enumerate())


def test_stages_overlap():
    """Two stages that each sleep 10 ms per item take about 10 ms per item together, not 20."""
    def slow(items):
        for x in items:
            time.sleep(0.01)
            yield x

    t0 = time.perf_counter()
    n = sum(1 for _ in slow(threaded(slow(range(40)))))
    wall = time.perf_counter() - t0
    assert n == 40 and wall < 0.9 * 40 * 0.02  # serial would take 40 × 20 ms


def test_rejects_a_zero_buffer():
    with pytest.raises(ValueError, match="maxsize"):
        threaded([1], maxsize=0)
