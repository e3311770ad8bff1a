"""The dense matcher's heap: the freed heap goes back to the system at most every
``HEAP_RELEASE_EVERY_S`` (``reconstruction.dense.runtime.heap_blocks``)."""

from __future__ import annotations

import torch

from roadsurf.core import memory
from roadsurf.reconstruction.dense import runtime


def test_the_heap_is_released_at_most_every_interval(monkeypatch) -> None:
    calls: list[int] = []
    monkeypatch.setattr(memory, "release_free_memory", lambda: calls.append(1) or True)
    monkeypatch.setattr(memory, "fix_mmap_threshold", lambda *a: True)
    monkeypatch.setattr(runtime, "_heap_released_at", 0.0)
    clock = [1000.0]
    monkeypatch.setattr(runtime.time, "monotonic", lambda: clock[0])
    cpu = torch.device("cpu")
    for _ in range(5):  # five pairs one after the other, 1 s apart
        with runtime.heap_blocks(cpu):
            pass
        clock[0] += 1.0
    assert len(calls) == 1  # the first gap only
    clock[0] += runtime.HEAP_RELEASE_EVERY_S
    with runtime.heap_blocks(cpu):
        with runtime.heap_blocks(cpu):  # a concurrent matcher: no release while one works
            pass
        assert len(calls) == 1
    assert len(calls) == 2
