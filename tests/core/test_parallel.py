"""roadsurf.core.parallel.ordered_map: order, bounded look-ahead, errors in turn."""

from __future__ import annotations

import pytest

from roadsurf.core.parallel import ordered_map


def test_ordered_map_keeps_order_bounds_lookahead_and_raises_in_turn() -> None:
    import threading
    import time

    started: list[int] = []
    lock = threading.Lock()

    def slow_square(i: int) -> int:
        with lock:
            started.append(i)
        time.sleep(0.02 if i % 3 == 0 else 0.0)  # later items finish first
        return i * i

    got = []
    for v in ordered_map(slow_square, list(range(20)), 2):
        got.append(v)
        if len(got) == 1:
            time.sleep(0.1)
            assert len(started) <= 1 + 2 * 2  # at most 2 x workers ahead of the consumer
    assert got == [i * i for i in range(20)]
    assert list(ordered_map(slow_square, [3, 1], 1)) == [9, 1]

    def fails_at_5(i: int) -> int:
        if i == 5:
            raise ValueError("tile 5")
        return i

    out = []
    with pytest.raises(ValueError, match="tile 5"):
        for v in ordered_map(fails_at_5, list(range(10)), 2):
            out.append(v)
    assert out == [0, 1, 2, 3, 4]
    # an explicit look-ahead bounds the work in flight the same way
    started.clear()
    for i, v in enumerate(ordered_map(slow_square, list(range(12)), 2, ahead=3)):
        if i == 0:
            time.sleep(0.1)
            assert len(started) <= 1 + 3
        assert v == i * i


def test_shared_cache_keeps_the_most_recent_values_and_loads_each_once():
    from roadsurf.core.parallel import SharedCache

    loads: list[int] = []

    def loader(k: int):
        def load() -> int:
            loads.append(k)
            return k * k

        return load

    c: SharedCache[int, int] = SharedCache(2)
    assert [c.get(k, loader(k)) for k in (1, 2, 1, 3, 1, 2)] == [1, 4, 1, 9, 1, 4]
    # 1 stays (used again before 3 came), 2 was evicted by 3 and is loaded again
    assert loads == [1, 2, 3, 2]


def test_shared_cache_under_threads_gives_every_key_its_own_value():
    from concurrent.futures import ThreadPoolExecutor

    from roadsurf.core.parallel import SharedCache

    c: SharedCache[int, int] = SharedCache(3)
    keys = [k % 7 for k in range(500)]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda k: c.get(k, lambda: 10 * k), keys))
    assert got == [10 * k for k in keys]


def test_gray_frames_reads_once_and_gives_none_for_missing_or_unreadable_frames(
    tmp_path, caplog
) -> None:
    import logging

    import cv2
    import numpy as np

    from roadsurf.io.drive import Frame, GrayFrames

    img = np.arange(48, dtype=np.uint8).reshape(6, 8)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    (tmp_path / "b.png").write_bytes(b"not a png")
    frames = [
        Frame(0, "a.png", tmp_path / "a.png", 0.0),
        Frame(1, "b.png", tmp_path / "b.png", 0.1),
    ]
    gf = GrayFrames(frames, 2, "test: skipping")
    with caplog.at_level(logging.WARNING, logger="roadsurf.io.drive"):
        a = gf.get("a.png")
        assert np.array_equal(a, img) and gf.get("a.png") is a  # cached, not read again
        assert gf.get("b.png") is None and gf.get("nowhere.png") is None
    assert caplog.text.count("test: skipping") == 1 and "b.png" in caplog.text


def test_one_blas_thread_runs_the_function_with_blas_on_one_thread() -> None:
    from threadpoolctl import threadpool_info

    from roadsurf.core.parallel import one_blas_thread

    @one_blas_thread
    def inside(x: int, *, y: int) -> tuple[int, list[int]]:
        return x + y, [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    total, threads = inside(2, y=3)
    assert total == 5 and inside.__name__ == "inside"
    assert threads and all(n == 1 for n in threads)  # numpy's BLAS is found, on one thread
