"""Bounded read-ahead: results of a per-index function, computed by background threads ahead of
the consumer (the session reader's frames, the debugger's images)."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")


def prefetched(load: Callable[[int], T], indices: Iterable[int], ahead: int, *, workers: int = 1,
               thread_name: str = "contact-viz-prefetch") -> Iterator[T]:
    """``load(i)`` for each index in order, computed by ``workers`` background threads at most
    ``ahead`` indices ahead of the consumer, so memory stays bounded. Closing the generator
    early (break) cancels what is pending and joins the threads; an exception raised by
    ``load`` is raised here, at its index."""
    executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=thread_name)
    pending: deque[Future] = deque()
    todo = iter(indices)
    try:
        for index in todo:
            pending.append(executor.submit(load, index))
            if len(pending) >= ahead:
                break
        while pending:
            result = pending.popleft().result()
            index = next(todo, None)
            if index is not None:
                pending.append(executor.submit(load, index))
            yield result
    finally:
        for future in pending:
            future.cancel()
        executor.shutdown(wait=True, cancel_futures=True)
