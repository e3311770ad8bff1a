"""A bounded, ordered thread map for stages whose per-item work is mostly OpenCV/numpy (which
release the GIL): decoding frames ahead of the CNN, computing raster tiles ahead of the writer.
``SharedCache``: the few decoded frames such threads share. ``one_blas_thread``: a function
whose dense algebra is too small for BLAS's own threads."""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K")
_END: Any = object()


def one_blas_thread(fn: Callable[..., R]) -> Callable[..., R]:
    """``fn`` run with BLAS on one thread (threadpoolctl), for work whose matrices are small
    (a few hundred unknowns): on 2 cores OpenBLAS's threads cost more than they give. Without
    threadpoolctl, BLAS keeps its own thread count."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> R:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover - a declared dependency
            return fn(*args, **kwargs)
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


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


class SharedCache(Generic[K, R]):
    """The ``size`` most recently used values, shared by threads. ``get`` loads a missing value
    outside the lock, so one slow decode does not block the other threads; two threads may load
    the same key once each, never a wrong value."""

    def __init__(self, size: int) -> None:
        self.size = max(1, int(size))
        self._d: OrderedDict[K, R] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: K, load: Callable[[], R]) -> R:
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
        value = load()
        with self._lock:
            self._d[key] = value
            self._d.move_to_end(key)
            while len(self._d) > self.size:
                self._d.popitem(last=False)
        return value
