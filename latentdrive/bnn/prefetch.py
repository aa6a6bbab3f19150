"""Read ahead: produce an iterator's next items on a background thread.

Training reads its batches from compressed shards; decompressing and dequantizing them
costs about a third of a small model's CPU step. Both release the GIL, so a thread can
prepare the next batches while the optimizer step runs. Order and content are those of
the wrapped iterator, so results do not change. Where torch already keeps every CPU core
busy the gain is expected to be small; it is meant for setups where the model leaves CPU
cores idle (training on a GPU). To see what it does on a machine, train the same BNN with
``latentdrive train-bnn DATASET RUN --set prefetch=0`` and with the default read-ahead:
each prints its samples/s on its last line.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Generator, Iterable
from typing import TypeVar

__all__ = ["prefetch"]

T = TypeVar("T")

_DONE = object()


class _Failed:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def prefetch(items: Iterable[T], depth: int = 2) -> Generator[T, None, None]:
    """Yield the items of ``items`` in order, produced ahead on a thread.

    Up to ``depth`` items wait in a queue, plus one the producer holds while the queue is
    full. ``depth = 0`` iterates in the calling thread. An exception raised by ``items`` is
    re-raised here at the point it occurred in the sequence. Closing the generator
    (``close()``, or the garbage collection of an abandoned one, as after a ``break`` or an
    exception in a ``for`` loop) stops the producer after at most one more item.
    """
    if depth < 0:
        raise ValueError(f"depth must be >= 0, got {depth}")
    if depth == 0:
        yield from items
        return
    q: queue.Queue[object] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(_DONE)
        except BaseException as exc:  # handed to the consumer, which re-raises it
            q.put(_Failed(exc))

    thread = threading.Thread(target=produce, name="latentdrive-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, _Failed):
                raise item.exc
            yield item  # type: ignore[misc]
    finally:
        stop.set()
        # Unblock a producer waiting on a full queue, then let it finish its current item.
        while thread.is_alive():
            try:
                q.get_nowait()
            except queue.Empty:
                thread.join(timeout=0.05)
