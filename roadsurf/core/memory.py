"""Keep the C heap from holding freed memory, so a run's peak RSS stays flat in the drive's length.

glibc's malloc gives each thread that allocates its own arena (up to 8 per core) and returns
freed memory to the system only from the top of a heap. The stages allocate and free many
image-sized NumPy arrays on worker threads (reconstruction's feature threads, mapping's raster
tiles, detection's pairs), so freed pages stayed resident, arena by arena, and the peak RSS of
`roadsurf run` depended on how the threads happened to interleave as much as on what the run
held (measurements: docs/benchmarks.md, "memory").

``limit_malloc_arenas`` caps the arenas (``mallopt(M_ARENA_MAX)``) and ``release_free_memory``
returns every arena's free pages (``malloc_trim(0)``). ``fix_mmap_threshold`` keeps large blocks
(image-sized arrays, raster tiles) in their own memory maps, unmapped when freed: glibc raises its
mmap threshold to the size of every mapped block freed (up to 32 MB), after which such arrays come
from the arenas and their freed space stays resident, fragmented between long-lived small blocks
(measured: 95 MB more resident after the global map of a 300-frame drive). All are no-ops
returning False where the C library is not glibc (macOS, Windows, musl).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import os
import sys
from typing import Any

log = logging.getLogger(__name__)

M_ARENA_MAX = -8  # mallopt parameter numbers (glibc malloc.h)
M_MMAP_THRESHOLD = -3
DEFAULT_ARENAS = 2  # arenas for a run: its threads are few (2 per stage by default)
# blocks from this size up get their own memory map (bytes): a raster tile's arrays (1024 x 1024
# px: 1-8 MB) but not most image-sized temporaries (640 x 480 gray 0.3 MB, float32 1.2 MB),
# which a stage allocates and frees by the hundred per frame: as maps they cost page faults
# (reconstruction of 20 frames at 640 px, CPU s user/system: dynamic 5.4/0.14, fixed 256 KB
# 5.7/1.45, 4 MB 5.6/0.9). glibc's initial (dynamic) threshold is 128 KB.
DEFAULT_MMAP_THRESHOLD = 1024 * 1024


@functools.cache
def _glibc() -> Any | None:
    """The process's C library when it is glibc, else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 - only glibc has it (musl does not)
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    except (OSError, AttributeError):
        return None
    return libc


def limit_malloc_arenas(n: int = DEFAULT_ARENAS) -> bool:
    """Let all threads of this process share at most ``n`` malloc arenas from now on.

    glibc fixes its arena limit when it first needs a ninth arena, so call this early (before
    many threads have allocated); arenas that exist already are kept, new threads reuse them.
    A limit set by the user (``MALLOC_ARENA_MAX`` or ``GLIBC_TUNABLES=glibc.malloc.arena_max``)
    wins. True when the limit was set.
    """
    if n < 1:
        raise ValueError(f"limit_malloc_arenas: n must be >= 1 (got {n})")
    libc = _glibc()
    if libc is None:
        return False
    if "MALLOC_ARENA_MAX" in os.environ or "arena_max" in os.environ.get("GLIBC_TUNABLES", ""):
        log.debug("malloc arena limit left to the environment")
        return False
    return bool(libc.mallopt(M_ARENA_MAX, int(n)))


def fix_mmap_threshold(n_bytes: int = DEFAULT_MMAP_THRESHOLD) -> bool:
    """Serve every block of ``n_bytes`` or more by its own memory map from now on, returned to
    the system when freed, and stop glibc from raising that threshold (its dynamic threshold
    grows to the largest mapped block freed, up to 32 MB, and larger arrays then stay resident
    in the arenas after they are freed). Setting it also fixes the heap's trim threshold at its
    default (128 KB). A threshold set by the user (``MALLOC_MMAP_THRESHOLD_`` or
    ``GLIBC_TUNABLES=glibc.malloc.mmap_threshold``) wins. True when the threshold was set."""
    if not 0 < n_bytes <= 32 * 2**20:
        raise ValueError(f"fix_mmap_threshold: n_bytes must be in (0, 32 MiB] (got {n_bytes})")
    libc = _glibc()
    if libc is None:
        return False
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "mmap_threshold" in os.environ.get(
        "GLIBC_TUNABLES", ""
    ):
        log.debug("malloc mmap threshold left to the environment")
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, int(n_bytes)))


def release_free_memory() -> bool:
    """Return the free pages of every malloc arena to the operating system (``malloc_trim(0)``;
    a few milliseconds). Live memory is untouched. True when glibc released something."""
    libc = _glibc()
    if libc is None:
        return False
    return bool(libc.malloc_trim(0))
