"""A bounded, ordered thread map for stages whose per-item work is mostly OpenCV/numpy (which
release the GIL): decoding frames ahead of the CNN, computing raster tiles ahead of the writer."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")
_END: Any = object()


def ordered_map(
    fn: Callable[[T], R], items: Iterable[T], workers: int, ahead: int | None = None
) -> Iterator[R]:
    """fn over items, results in the items' order. With workers > 1 they are computed by that
    many threads, at most ``ahead`` (default 2 × workers) items ahead of the consumer, so memory
    stays bounded. An exception is raised when its item's turn comes; the items not started yet
    are then cancelled. workers <= 1: plain ``map`` on the calling thread."""
    if workers <= 1:
        yield from map(fn, items)
        return
    limit = max(1, ahead if ahead is not None else 2 * workers)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        queue: deque[Future[R]] = deque()
        it = iter(items)
        try:
            while True:
                while len(queue) < limit and (item := next(it, _END)) is not _END:
                    queue.append(pool.submit(fn, item))
                if not queue:
                    return
                yield queue.popleft().result()
        finally:
            for f in queue:
                f.cancel()
