"""Torch runtime of the dense matching: the device, torch's CPU threads and malloc's heap while
pairs are matched (shared by concurrent matchers)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import torch

from roadsurf.core.errors import RoadsurfError


def torch_device(name: str) -> torch.device:
    """``auto`` -> CUDA when present, else CPU; any other name as torch reads it."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RoadsurfError(f"dense matching on {name!r}: no CUDA device here; use 'cpu'")
    return dev


_HEAP_LOCK = threading.Lock()
_heap_users = 0
# the freed heap is returned to the system at most this often (s): each return costs the next
# pair its page faults again (sample drive: 1.40 M faults, 4.8 s system time in the global map),
# while what stays resident meanwhile is one batch of pairs' temporaries, whatever the drive's
# length
HEAP_RELEASE_EVERY_S = 10.0
_heap_released_at = 0.0


@contextlib.contextmanager
def heap_blocks(dev: torch.device) -> Iterator[None]:
    """While pairs are matched on the CPU, malloc serves blocks up to 32 MB from its heap. After
    its reconstruction a run gives every block from 1 MB up its own memory map
    (``core.memory.fix_mmap_threshold``),
    and the matcher allocates and frees hundreds of image-sized temporaries per pair: each one
    then cost a map, page faults and an unmap (640 x 480: 0.125 -> 0.46 CPU s per pair, most of
    it system time). When the last concurrent matcher leaves, the run's threshold is set back
    and, at most every ``HEAP_RELEASE_EVERY_S``, the freed heap returned to the system
    (``release_free_memory``): what stays resident in between is the matchers' freed
    temporaries, reused by the next pairs. A threshold the user set (environment) is left
    alone."""
    global _heap_users, _heap_released_at
    from roadsurf.core.memory import fix_mmap_threshold, release_free_memory

    if dev.type != "cpu":
        yield
        return
    with _HEAP_LOCK:
        if _heap_users == 0:
            fix_mmap_threshold(32 * 2**20)
        _heap_users += 1
    try:
        yield
    finally:
        with _HEAP_LOCK:
            _heap_users -= 1
            now = time.monotonic()
            if _heap_users == 0 and fix_mmap_threshold():
                if now - _heap_released_at >= HEAP_RELEASE_EVERY_S:
                    release_free_memory()
                    _heap_released_at = now


@contextlib.contextmanager
def cpu_threads(dev: torch.device, n: int) -> Iterator[None]:
    """torch's CPU threads set to ``n`` for the calling thread inside (its own count restored
    on exit). Several pairs matched in parallel with one thread each beat one pair on all cores
    (the images are small), and on a busy machine torch's spinning threads cost 10x.

    The count is each thread's own (OpenMP's nthreads is per thread; a new thread starts from
    the last count set anywhere), so every thread that matches sets it: a process-wide count
    set only by the first of several concurrent users left the others at whatever they had
    started with, and the dense surface's bits changed with the threads' timing."""
    if dev.type != "cpu" or n <= 0:
        yield
        return
    own = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(own)
