"""The dense matcher's runtime: the freed heap goes back to the system at most every
``HEAP_RELEASE_EVERY_S`` (``heap_blocks``); every matching thread runs with the configured torch
thread count, whatever the other threads do (``cpu_threads``)."""

from __future__ import annotations

import threading

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


def test_every_matching_thread_runs_with_the_configured_thread_count() -> None:
    # a thread whose torch count was set before another matcher entered (the old refcounted
    # setting left it there: its ops ran with 2 threads or 1 depending on the timing)
    cpu = torch.device("cpu")
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    seen: dict[str, int] = {}
    b_ready, a_inside, b_done = threading.Event(), threading.Event(), threading.Event()

    def a() -> None:
        with runtime.cpu_threads(cpu, 1):
            a_inside.set()
            b_done.wait(10)

    def b() -> None:
        seen["b_before"] = torch.get_num_threads()  # starts from the count set last
        b_ready.set()
        a_inside.wait(10)
        with runtime.cpu_threads(cpu, 1):
            seen["b_inside"] = torch.get_num_threads()
        seen["b_after"] = torch.get_num_threads()
        b_done.set()

    try:
        tb = threading.Thread(target=b)
        tb.start()
        b_ready.wait(10)
        ta = threading.Thread(target=a)
        ta.start()
        tb.join(20)
        ta.join(20)
    finally:
        torch.set_num_threads(before)
    assert seen == {"b_before": 2, "b_inside": 1, "b_after": 2}
