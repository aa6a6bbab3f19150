"""Read-ahead keeps order, surfaces errors where they happened, and stops when abandoned."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from latentdrive.bnn.prefetch import prefetch


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_items_arrive_in_order(depth: int) -> None:
    assert list(prefetch(iter(range(50)), depth)) == list(range(50))


def test_an_error_arrives_after_the_items_before_it() -> None:
    def items() -> Iterator[int]:
        yield 1
        yield 2
        raise OSError("shard unreadable")

    got = []
    with pytest.raises(OSError, match="shard unreadable"):
        for x in prefetch(items(), 2):
            got.append(x)
    assert got == [1, 2]


def test_abandoning_the_iterator_stops_the_producer() -> None:
    produced = []

    def items() -> Iterator[int]:
        for i in range(10_000):
            produced.append(i)
            yield i

    it = prefetch(items(), 2)
    assert next(it) == 0
    it.close()
    time.sleep(0.2)
    assert len(produced) <= 5
    assert not any(t.name == "latentdrive-prefetch" for t in threading.enumerate())


def test_the_producer_runs_ahead() -> None:
    started = threading.Event()

    def items() -> Iterator[int]:
        yield 0
        started.set()
        yield 1

    it = prefetch(items(), 2)
    assert next(it) == 0
    # The second item is produced without being asked for.
    assert started.wait(timeout=5.0)
    assert list(it) == [1]


def test_negative_depth_is_refused() -> None:
    with pytest.raises(ValueError, match="depth"):
        list(prefetch(iter([]), -1))
