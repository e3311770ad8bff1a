"""roadsurf.core.memory: freed heap pages go back to the system, threads share capped arenas.

Each check runs in a fresh Python process: malloc's arenas and limit are process-wide."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from roadsurf.core.memory import _glibc, fix_mmap_threshold, limit_malloc_arenas

needs_glibc = pytest.mark.skipif(_glibc() is None, reason="glibc malloc only (Linux)")

_HELPERS = """
import ctypes, json, threading
from roadsurf.core import memory

def rss_mb():
    with open("/proc/self/status") as f:
        return next(int(x.split()[1]) for x in f if x.startswith("VmRSS")) / 1024

def heaps():
    # malloc_info's XML lists one <heap> per arena
    libc = memory._glibc()
    libc.fopen.restype = ctypes.c_void_p
    libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
    libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
    libc.fclose.argtypes = [ctypes.c_void_p]
    fp = libc.fopen(PATH.encode(), b"w")
    libc.malloc_info(0, fp)
    libc.fclose(fp)
    return open(PATH).read().count("<heap nr=")
"""


def _run(body: str, tmp_path, env: dict[str, str] | None = None) -> dict:
    code = f"PATH = {str(tmp_path / 'info.xml')!r}\n" + _HELPERS + textwrap.dedent(body)
    user = ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "GLIBC_TUNABLES")
    e = {k: v for k, v in os.environ.items() if k not in user}
    p = subprocess.run(
        [sys.executable, "-c", code], env=e | (env or {}), capture_output=True, text=True
    )
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout.strip().splitlines()[-1])


@needs_glibc
def test_release_free_memory_returns_pages_freed_by_a_thread(tmp_path) -> None:
    """A worker thread fills its arena with 4 KB blocks, keeps one in 64 (the arena cannot
    shrink from its top) and frees the rest: the pages stay resident until released."""
    res = _run(
        """
        kept = []
        def work():
            blocks = [bytearray(4000) for _ in range(40000)]  # about 160 MB
            kept.extend(blocks[::64])
        t = threading.Thread(target=work)
        t.start(); t.join()
        before = rss_mb()
        released = memory.release_free_memory()
        print(json.dumps({"before": before, "after": rss_mb(), "released": released}))
        """,
        tmp_path,
    )
    assert res["released"] is True
    assert res["before"] > 140, res  # glibc kept the freed pages
    assert res["before"] - res["after"] > 100, res  # ... and gave them back when asked


@needs_glibc
@pytest.mark.parametrize("limit", [None, 2])
def test_limit_malloc_arenas_caps_the_arenas_of_new_threads(tmp_path, limit) -> None:
    res = _run(
        f"""
        limited = memory.limit_malloc_arenas({limit}) if {limit} else None
        barrier = threading.Barrier(6)
        def work():
            block = bytearray(1 << 16)  # the thread's first allocation picks its arena
            barrier.wait()  # all alive at once: none inherits another's freed arena
        ts = [threading.Thread(target=work) for _ in range(6)]
        [t.start() for t in ts]
        [t.join() for t in ts]
        print(json.dumps({{"heaps": heaps(), "limited": limited}}))
        """,
        tmp_path,
    )
    if limit is None:
        assert res["heaps"] > 3, res  # glibc's default: an arena per thread (up to 8 per core)
    else:
        assert res["limited"] is True
        assert res["heaps"] <= limit, res


@needs_glibc
def test_a_limit_set_by_the_user_wins(tmp_path) -> None:
    res = _run(
        'print(json.dumps({"limited": memory.limit_malloc_arenas(2)}))',
        tmp_path,
        env={"MALLOC_ARENA_MAX": "4"},
    )
    assert res["limited"] is False


def test_limit_malloc_arenas_refuses_zero() -> None:
    with pytest.raises(ValueError, match="n must be >= 1"):
        limit_malloc_arenas(0)


@needs_glibc
@pytest.mark.parametrize("fixed", [False, True])
def test_fix_mmap_threshold_returns_freed_arrays_at_once(tmp_path, fixed) -> None:
    """Once a 16 MB block was freed, glibc serves 4 MB blocks from its heap; freed between
    long-lived small blocks they stay resident (no trim reaches them). With the threshold fixed
    each is its own memory map, unmapped by free: the freed 160 MB leave at once."""
    res = _run(
        f"""
        done = memory.fix_mmap_threshold() if {fixed} else None
        big = bytearray(16 << 20); del big  # raises glibc's dynamic threshold to 16 MB
        base = rss_mb()
        blocks, kept = [], []
        for _ in range(40):
            blocks.append(b"\\1" * (4 << 20))  # written: resident
            kept.append(bytearray(1000))  # long-lived, above each block
        full = rss_mb()
        del blocks
        print(json.dumps({{"done": done, "grown": full - base, "left": rss_mb() - base}}))
        """,
        tmp_path,
    )
    assert res["grown"] > 150, res
    if fixed:
        assert res["done"] is True
        assert res["left"] < 20, res
    else:
        assert res["left"] > 140, res  # the case the fix is for: still resident


@needs_glibc
def test_an_mmap_threshold_set_by_the_user_wins(tmp_path) -> None:
    res = _run(
        'print(json.dumps({"done": memory.fix_mmap_threshold()}))',
        tmp_path,
        env={"MALLOC_MMAP_THRESHOLD_": "1048576"},
    )
    assert res["done"] is False


def test_fix_mmap_threshold_refuses_nonsense() -> None:
    with pytest.raises(ValueError, match="n_bytes must be in"):
        fix_mmap_threshold(0)
    with pytest.raises(ValueError, match="n_bytes must be in"):
        fix_mmap_threshold(64 * 2**20)
